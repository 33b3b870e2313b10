//! Structural loss term D-SSIM on patch batches (SPEC §4.7; beyond the paper, as 3D Gaussian
//! Splatting trains: `L = (1−λ)·L1 + λ·(1 − SSIM)`).
//!
//! A patch batch (`train/sampler.rs` [`patch_pixels`]) holds P patches of k×k neighbouring pixels
//! of one training view: pixel (dx, dy) of patch j is batch row `j·k² + dy·k + dx`. Per patch and
//! colour channel, SSIM is evaluated at every position where a w×w window fits inside the patch
//! (no padding), w = min(11, k), with the Gaussian weights of `eval/metrics.rs` (σ = 1.5, the
//! 1-D weights `g(t) = exp(−(t − (w−1)/2)² / 2σ²)` normalised to sum 1, the 2-D window their
//! outer product). With x the prediction and y the photo in a window, moments
//! `μx = Σ w_i x_i`, `Sxx = Σ w_i x_i²`, `Sxy = Σ w_i x_i y_i` (and `μy`, `Syy`),
//! `σx² = Sxx − μx²`, `σxy = Sxy − μx μy`:
//!
//! `SSIM = (2μxμy + C1)(2σxy + C2) / ((μx² + μy² + C1)(σx² + σy² + C2))`, C1 = 0.01², C2 = 0.03².
//!
//! The term is `λ·(1 − Σ SSIM / M)` over the M counted (window, channel) pairs of the batch; a
//! window that covers a masked slot (`Batch::patch_mask` = 0: a filler for a pixel that does not
//! see the mesh, see the sampler) is not counted. M = 0 gives a term of 0.
//!
//! Backward, per window (S = SSIM, A1, A2, B1, B2 the four factors above):
//! `∂S/∂x_i = w_i·(∂S/∂μx + 2x_i·∂S/∂Sxx + y_i·∂S/∂Sxy)` with
//! `∂S/∂μx = S·(2μy/A1 − 2μy/A2 − 2μx/B1 + 2μx/B2)`, `∂S/∂Sxx = −S/B2`, `∂S/∂Sxy = 2S/A2`.
//!
//! Numerics: every moment, SSIM and gradient in f64 whatever the model's scalar `R` (inputs
//! widened from `R`/f32, the gradient rounded once to `R` when it is added); patches, windows,
//! channels and window elements in a fixed order (patch, channel, window row, window column,
//! element row-major), so the result does not depend on the thread count.

use crate::model::Real;

/// SSIM's stabilising constants for data range 1 (Wang et al. 2004).
pub const C1: f64 = 0.01 * 0.01;
pub const C2: f64 = 0.03 * 0.03;
/// Standard deviation of the Gaussian window (as `eval/metrics.rs`).
pub const SIGMA: f64 = 1.5;
/// Largest window side (3DGS's 11×11).
pub const MAX_WINDOW: usize = 11;

/// Window side for patches of side `k`.
pub fn window_side(k: usize) -> usize {
    k.min(MAX_WINDOW)
}

/// The normalised 1-D Gaussian weights of a window of side `w` (module docs).
pub fn window_weights(w: usize) -> Vec<f64> {
    let c = (w as f64 - 1.0) / 2.0;
    let g: Vec<f64> = (0..w)
        .map(|t| (-(t as f64 - c).powi(2) / (2.0 * SIGMA * SIGMA)).exp())
        .collect();
    let s: f64 = g.iter().sum();
    g.into_iter().map(|v| v / s).collect()
}

/// One window's moments of prediction x and photo y.
struct Moments {
    mx: f64,
    my: f64,
    sxx: f64,
    syy: f64,
    sxy: f64,
}

/// SSIM of one window and its partials (∂S/∂μx, ∂S/∂Sxx, ∂S/∂Sxy).
fn ssim_of(m: &Moments) -> (f64, [f64; 3]) {
    let vx = m.sxx - m.mx * m.mx;
    let vy = m.syy - m.my * m.my;
    let cxy = m.sxy - m.mx * m.my;
    let a1 = 2.0 * m.mx * m.my + C1;
    let a2 = 2.0 * cxy + C2;
    let b1 = m.mx * m.mx + m.my * m.my + C1;
    let b2 = vx + vy + C2;
    let s = a1 * a2 / (b1 * b2);
    let d_mx = s * (2.0 * m.my / a1 - 2.0 * m.my / a2 - 2.0 * m.mx / b1 + 2.0 * m.mx / b2);
    (s, [d_mx, -s / b2, 2.0 * s / a2])
}

/// Visit every counted (patch, channel, window) of a batch of `n` rows in patches of side `k`:
/// `f(rows of the window with their weights, channel)`.
fn for_each_window(k: usize, n: usize, mask: &[u8], mut f: impl FnMut(&[(usize, f64)], usize)) {
    let w = window_side(k);
    let g = window_weights(w);
    let k2 = k * k;
    let mut rows: Vec<(usize, f64)> = Vec::with_capacity(w * w);
    for p in 0..n / k2 {
        let base = p * k2;
        for oy in 0..=k - w {
            for ox in 0..=k - w {
                rows.clear();
                let mut masked = false;
                for (dy, &gy) in g.iter().enumerate() {
                    for (dx, &gx) in g.iter().enumerate() {
                        let r = base + (oy + dy) * k + ox + dx;
                        masked |= mask.get(r).is_some_and(|&m| m == 0);
                        rows.push((r, gy * gx));
                    }
                }
                if masked {
                    continue;
                }
                for c in 0..3 {
                    f(&rows, c);
                }
            }
        }
    }
}

fn moments<R: Real>(rows: &[(usize, f64)], c: usize, rgb: &[R], target: &[[f32; 3]]) -> Moments {
    let mut m = Moments {
        mx: 0.0,
        my: 0.0,
        sxx: 0.0,
        syy: 0.0,
        sxy: 0.0,
    };
    for &(r, wi) in rows {
        let x = rgb[r * 3 + c].to_f64();
        let y = target[r][c] as f64;
        m.mx += wi * x;
        m.my += wi * y;
        m.sxx += wi * x * x;
        m.syy += wi * y * y;
        m.sxy += wi * x * y;
    }
    m
}

/// SSIM forward over a patch batch: `(Σ SSIM, M)` over the counted (window, channel) pairs of
/// `rgb [n, 3]` against `target [n]` in patches of side `k` (`mask` `[n]` or empty = all counted).
pub fn ssim_forward<R: Real>(
    k: usize,
    rgb: &[R],
    target: &[[f32; 3]],
    mask: &[u8],
) -> (f64, usize) {
    let (mut sum, mut count) = (0.0f64, 0usize);
    for_each_window(k, target.len(), mask, |rows, c| {
        sum += ssim_of(&moments(rows, c, rgb, target)).0;
        count += 1;
    });
    (sum, count)
}

/// SSIM backward: `d_rgb [n, 3] += scale · ∂(Σ SSIM)/∂rgb` (the D-SSIM term passes
/// `scale = −λ/M`), accumulated in f64 and added to `d_rgb` once per element.
pub fn ssim_backward<R: Real>(
    k: usize,
    rgb: &[R],
    target: &[[f32; 3]],
    mask: &[u8],
    scale: f64,
    d_rgb: &mut [R],
) {
    let mut d = vec![0.0f64; rgb.len()];
    for_each_window(k, target.len(), mask, |rows, c| {
        let m = moments(rows, c, rgb, target);
        let (_, [d_mx, d_sxx, d_sxy]) = ssim_of(&m);
        for &(r, wi) in rows {
            let x = rgb[r * 3 + c].to_f64();
            let y = target[r][c] as f64;
            d[r * 3 + c] += wi * (d_mx + 2.0 * x * d_sxx + y * d_sxy);
        }
    });
    for (o, v) in d_rgb.iter_mut().zip(d) {
        *o += R::from_f64(v * scale);
    }
}

/// The loss of a batch whose L1 part (mean ρ over 3N) is `l1`: `(1−λ)·l1 + λ·(1 − Σ/M)`.
pub fn combine(lambda: f64, l1: f64, ssim_sum: f64, count: usize) -> f64 {
    let d = if count == 0 {
        0.0
    } else {
        1.0 - ssim_sum / count as f64
    };
    (1.0 - lambda) * l1 + lambda * d
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn identical_patches_score_one_and_weights_sum_to_one() {
        for w in [3, 8, 11] {
            let g = window_weights(w);
            assert!((g.iter().sum::<f64>() - 1.0).abs() < 1e-15);
            assert!((g[0] - g[w - 1]).abs() < 1e-15, "symmetric");
        }
        let k = 4;
        let target: Vec<[f32; 3]> = (0..32)
            .map(|i| [(i % 7) as f32 / 7.0, (i % 3) as f32 / 3.0, 0.5])
            .collect();
        let rgb: Vec<f64> = target.iter().flatten().map(|&v| v as f64).collect();
        let (s, m) = ssim_forward(k, &rgb, &target, &[]);
        assert_eq!(m, 2 * 3); // two patches, one window each, three channels
        assert!((s / m as f64 - 1.0).abs() < 1e-12, "{s}");
        // A flattened prediction (the patch mean everywhere) scores below 1.
        let flat: Vec<f64> = vec![0.4; 96];
        assert!(ssim_forward(k, &flat, &target, &[]).0 / (m as f64) < 0.9);
        // Masking one slot of patch 1 drops its window.
        let mut mask = vec![1u8; 32];
        mask[20] = 0;
        assert_eq!(ssim_forward(k, &rgb, &target, &mask).1, 3);
        assert_eq!(combine(0.2, 0.5, 3.0, 6), 0.8 * 0.5 + 0.2 * 0.5);
        assert_eq!(combine(0.2, 0.5, 0.0, 0), 0.4);
    }
}
