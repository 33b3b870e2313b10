//! Footprint-aware level weighting (SPEC §4.10; beyond the paper, in the spirit of Zip-NeRF's
//! feature down-weighting): a sub-sample's grid-H level l is scaled by a smooth function of how
//! many of that level's cells its pixel's footprint covers, so a far pixel neither reads nor
//! writes levels much finer than itself.
//!
//! ```text
//! r_l = footprint · scale_l           (the pixel's footprint in cells of level l; f64)
//! w(r) = 1                   r ≤ 1
//!        1 − t²(3 − 2t)      t = log2(r) / 2,   1 < r < 4
//!        0                   r ≥ 4
//! F_H,w(x_j)[l·F + f] = w(r_l) · F_H(x_j)[l·F + f]
//! ```
//! `footprint` is the pixel's (SPEC §1.1, normalised units, the batch's f32 value) and applies to
//! all its sub-samples. Each level's weight comes from its own scale alone (nothing assumes the
//! scales grow with l). A sub-sample evaluates its first `active` levels, `active` = 1 + the last
//! level whose f64 weight is > 0 (tested before rounding to the model's float); the rest are
//! neither gathered nor scattered. With b > 1 the weights fall with l, so those are exactly the
//! levels of positive weight; a level below `active` with weight 0 (b ≤ 1) is gathered and
//! multiplied by 0. `w` is evaluated as `1 − ((t·t)·(3 − 2·t))` in f64, unfused.
//! The weights are data (the footprint is not differentiated), so the backward pass scales the
//! gradient of each level by the same `w`. ξ's output (Eq. 5) is not weighted.

use super::real::Real;

/// Below this many cells per footprint a level has full weight.
pub const R_FULL: f64 = 1.0;
/// From this many cells per footprint a level has weight 0 (a smoothstep in log2 between).
pub const R_ZERO: f64 = 4.0;

/// `w(r)` of the module doc, in f64.
#[inline]
pub fn weight(r: f64) -> f64 {
    if r.is_nan() || r <= R_FULL {
        return 1.0;
    }
    if r >= R_ZERO {
        return 0.0;
    }
    let t = (r / R_FULL).log2() / (R_ZERO / R_FULL).log2();
    1.0 - t * t * (3.0 - 2.0 * t)
}

/// For each sample of each pixel: its level weights `w[v, L]` (model float) and its number of
/// active levels `active[v]`. `start[n+1]` is the pixels' sample ranges (local to `w`), `fp[n]`
/// their footprints, `scales[L]` grid H's per-level scales. Returns whether every weight is 1
/// (then [`apply_level_weights`] would change nothing: a close-up's pixels are finer than every
/// level).
pub fn level_weights<R: Real>(
    scales: &[f32],
    start: &[usize],
    fp: &[f32],
    w: &mut [R],
    active: &mut [u8],
) -> bool {
    let nl = scales.len();
    assert!(
        nl <= u8::MAX as usize,
        "level weighting: at most 255 levels"
    );
    let mut row = vec![R::ZERO; nl];
    let mut all_one = true;
    for (i, &f) in fp.iter().enumerate() {
        let mut act = 0u8;
        for (l, (&s, o)) in scales.iter().zip(row.iter_mut()).enumerate() {
            let x = weight(f as f64 * s as f64);
            *o = R::from_f64(x);
            all_one &= *o == R::ONE;
            if x > 0.0 {
                act = l as u8 + 1;
            }
        }
        for r in start[i]..start[i + 1] {
            w[r * nl..(r + 1) * nl].copy_from_slice(&row);
            active[r] = act;
        }
    }
    all_one
}

/// `x[v, L·F] *= w[v, L]` per level (forward: the weighted features; backward: the weighted
/// gradient of grid H's output). `nl` levels of `nf` features.
pub fn apply_level_weights<R: Real>(w: &[R], nl: usize, nf: usize, x: &mut [R]) {
    assert_eq!(
        x.len() / (nl * nf).max(1),
        w.len() / nl.max(1),
        "level weights: shapes"
    );
    // Every level is multiplied, those of full weight too (x · 1 is x, bit for bit): a loop
    // without a test per level, which the compiler vectorises.
    if nf == 2 {
        for (xr, wr) in x.chunks_exact_mut(nl * 2).zip(w.chunks_exact(nl)) {
            for (v, &wl) in xr.chunks_exact_mut(2).zip(wr) {
                v[0] *= wl;
                v[1] *= wl;
            }
        }
        return;
    }
    for (xr, wr) in x.chunks_exact_mut(nl * nf).zip(w.chunks_exact(nl)) {
        for (v, &wl) in xr.chunks_exact_mut(nf.max(1)).zip(wr) {
            for v in v {
                *v *= wl;
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn weight_is_smooth_and_bounded() {
        assert_eq!(weight(0.0), 1.0);
        assert_eq!(weight(1.0), 1.0);
        assert_eq!(weight(4.0), 0.0);
        assert_eq!(weight(100.0), 0.0);
        assert!((weight(2.0) - 0.5).abs() < 1e-15, "midpoint in log2");
        let mut prev = 1.0;
        for i in 0..=400 {
            let w = weight(1.0 + 3.0 * i as f64 / 400.0);
            assert!(w <= prev && (0.0..=1.0).contains(&w));
            prev = w;
        }
        // Continuous at both ends (smoothstep: zero slope there).
        assert!(1.0 - weight(1.0 + 1e-6) < 1e-10 && weight(4.0 - 1e-6) < 1e-10);
    }
}
