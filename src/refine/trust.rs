//! The trust region of the mesh refinement (`[model.refine] trust_batches`, `trust_holdout`;
//! docs/geometry.md §3, "Trust region"): the acceptance batches an update is measured on and the
//! paired error that decides it. The decision itself is in `refine/refiner.rs`.
//!
//! Acceptance batch j of the update after step k: slot i is kept pixel
//! `pool[below(seed, RefineTrust, k, j·size + i, |pool|)]` — a pure function of (seed, k, j, i),
//! the same pixels for the mesh before and after the update (a paired comparison: the noise of
//! which pixels are drawn cancels), different at every update. The pool is every kept pixel of the
//! training views, or (`trust_holdout` = n > 0) those of the validation views only: the views
//! whose appearance row r has `r % n == n − 1`, which give no offset gradient.
//!
//! The measure is the photometric MSE (what the held-out PSNR scores) of the rows that see the
//! mesh both before and after (a row none of whose rays hits a moved mesh is left out of both),
//! summed in row order in f64: deterministic and independent of the thread count.

use crate::model::batch::Batch;
use crate::model::hfm::Hfm;
use crate::rng::{below, Purpose};
use crate::train::sampler::Samples;
use anyhow::{bail, ensure, Result};

/// Whether appearance row `row` is a validation view under `trust_holdout = holdout`.
#[inline]
pub fn is_validation_row(row: i32, holdout: u32) -> bool {
    holdout > 0 && row >= 0 && row as u32 % holdout == holdout - 1
}

/// The kept pixels the acceptance batches are drawn from (module docs).
#[derive(Clone, Debug)]
pub struct TrustPool {
    /// `(first kept index, count)` of each view in the pool, in view order.
    ranges: Vec<(usize, usize)>,
    total: usize,
}

impl TrustPool {
    /// Every kept pixel (`holdout` = 0) or the validation views' (streamed samples only: the
    /// refinement needs them).
    pub fn new(samples: &Samples, holdout: u32) -> Result<TrustPool> {
        let Samples::Stream(s) = samples else {
            bail!("model.refine: the trust region needs streamed samples");
        };
        let n = s.len();
        let mut ranges = Vec::new();
        for (slot, v) in s.views.iter().enumerate() {
            let end = s.views.get(slot + 1).map_or(n, |w| w.start);
            if holdout == 0 || is_validation_row(v.view as i32, holdout) {
                ranges.push((v.start, end - v.start));
            }
        }
        ranges.retain(|r| r.1 > 0);
        let total = ranges.iter().map(|r| r.1).sum();
        ensure!(
            total > 0,
            "model.refine: trust_holdout = {holdout} leaves no kept pixel for the acceptance test ({} training views)",
            s.views.len()
        );
        Ok(TrustPool { ranges, total })
    }

    /// The kept-pixel indices of acceptance batch `j` of the update after step `k`.
    pub fn pixels(&self, seed: u64, k: u64, j: u64, size: usize) -> Vec<usize> {
        (0..size as u64)
            .map(|i| {
                let mut r = below(
                    seed,
                    Purpose::RefineTrust,
                    k,
                    j * size as u64 + i,
                    self.total as u64,
                ) as usize;
                for &(start, len) in &self.ranges {
                    if r < len {
                        return start + r;
                    }
                    r -= len;
                }
                unreachable!("r < total")
            })
            .collect()
    }
}

/// Each row's squared RGB error (summed over channels, f64) under `model` with `params`;
/// `None` for a row none of whose sub-samples is valid.
pub fn row_errors(model: &Hfm, params: &[f32], mut batch: Batch) -> Result<Vec<Option<f64>>> {
    let s = batch.samples_per_pixel();
    let n = batch.n_pixels();
    let rows: Vec<usize> = (0..n)
        .filter(|&i| batch.valid[i * s..(i + 1) * s].iter().any(|&v| v != 0))
        .collect();
    batch.drop_empty_pixels();
    let mut out = vec![None; n];
    if rows.is_empty() {
        return Ok(out);
    }
    let fwd = model.forward(params, &batch)?;
    for c in &fwd.chunks {
        for (k, p) in c.pixels.clone().enumerate() {
            let mut se = 0.0f64;
            for ch in 0..3 {
                let d = c.rgb[k * 3 + ch] as f64 - batch.target[p][ch] as f64;
                se += d * d;
            }
            out[rows[p]] = Some(se);
        }
    }
    Ok(out)
}

/// The MSE (per channel) of `a` and of `b` over the rows present in both (f64, row order).
pub fn paired_mse(a: &[Vec<Option<f64>>], b: &[Vec<Option<f64>>]) -> (f64, f64) {
    let (mut sa, mut sb, mut n) = (0.0f64, 0.0f64, 0usize);
    for (ra, rb) in a.iter().zip(b) {
        for (x, y) in ra.iter().zip(rb) {
            if let (Some(x), Some(y)) = (x, y) {
                sa += x;
                sb += y;
                n += 3;
            }
        }
    }
    let n = n.max(1) as f64;
    (sa / n, sb / n)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn validation_rows_and_paired_mse() {
        assert!(!is_validation_row(5, 0));
        assert!(is_validation_row(5, 6) && !is_validation_row(6, 6) && is_validation_row(11, 6));
        assert!(!is_validation_row(-1, 2));
        let a = vec![vec![Some(3.0), None, Some(6.0)]];
        let b = vec![vec![Some(0.0), Some(9.0), None]];
        // Only row 0 is in both: 3 / 3 channels and 0 / 3.
        assert_eq!(paired_mse(&a, &b), (1.0, 0.0));
    }
}
