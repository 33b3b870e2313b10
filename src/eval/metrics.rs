//! Image metrics (SPEC §7): PSNR on RGB in `[0,1]`; SSIM as Wang et al. 2004 with an 11×11
//! Gaussian window (σ = 1.5), K1 = 0.01, K2 = 0.03, data range 1, per channel then averaged.
//!
//! SSIM follows scikit-image's `structural_similarity(gaussian_weights=True, sigma=1.5,
//! use_sample_covariance=False, data_range=1, channel_axis=-1)`: local moments with a separable
//! Gaussian of radius `int(3.5·σ + 0.5) = 5` (11 taps, normalised to sum 1), the SSIM map
//! cropped by 5 pixels on each side (so the padding mode never matters), and its mean. Images
//! smaller than 11×11 have no valid window: SSIM is then NaN.
//!
//! Masked variants average only over pixels whose mask is set (pixels whose rays hit the mesh):
//! masked PSNR uses the MSE over masked pixels; masked SSIM is the mean of the cropped SSIM map
//! over masked pixels. Everything is computed in f64.

use crate::model::ssim::{window_weights, C1, C2};

/// Mean squared error over all pixels and channels (or masked pixels only).
fn mse(a: &[f32], b: &[f32], mask: Option<&[bool]>) -> f64 {
    assert_eq!(a.len(), b.len(), "images differ in size");
    let (mut s, mut n) = (0.0f64, 0usize);
    for (i, (pa, pb)) in a.chunks_exact(3).zip(b.chunks_exact(3)).enumerate() {
        if mask.is_some_and(|m| !m[i]) {
            continue;
        }
        for c in 0..3 {
            let d = pa[c] as f64 - pb[c] as f64;
            s += d * d;
        }
        n += 3;
    }
    if n == 0 {
        f64::NAN
    } else {
        s / n as f64
    }
}

/// PSNR in dB for values in `[0,1]`: `-10 log10(MSE)` (∞ for identical images).
pub fn psnr(a: &[f32], b: &[f32]) -> f64 {
    -10.0 * mse(a, b, None).log10()
}

/// PSNR over the pixels where `mask` is true (`mask.len()` = pixels).
pub fn psnr_masked(a: &[f32], b: &[f32], mask: &[bool]) -> f64 {
    -10.0 * mse(a, b, Some(mask)).log10()
}

const RADIUS: usize = 5;

/// The cropped SSIM map of one channel: `(h - 10) × (w - 10)` values.
fn ssim_map_channel(x: &[f64], y: &[f64], w: usize, h: usize) -> Vec<f64> {
    // σ = 1.5, 11 taps: the window the training's D-SSIM term uses too (`model/ssim.rs`).
    let taps = window_weights(2 * RADIUS + 1);
    let (ow, oh) = (w - 2 * RADIUS, h - 2 * RADIUS);
    // Separable filtering of the five moment images, valid region only.
    let filt = |img: &dyn Fn(usize) -> f64| -> Vec<f64> {
        let mut rows = vec![0.0; ow * h];
        for r in 0..h {
            for c in 0..ow {
                let mut s = 0.0;
                for (k, t) in taps.iter().enumerate() {
                    s += t * img(r * w + c + k);
                }
                rows[r * ow + c] = s;
            }
        }
        let mut out = vec![0.0; ow * oh];
        for r in 0..oh {
            for c in 0..ow {
                let mut s = 0.0;
                for (k, t) in taps.iter().enumerate() {
                    s += t * rows[(r + k) * ow + c];
                }
                out[r * ow + c] = s;
            }
        }
        out
    };
    let ux = filt(&|i| x[i]);
    let uy = filt(&|i| y[i]);
    let uxx = filt(&|i| x[i] * x[i]);
    let uyy = filt(&|i| y[i] * y[i]);
    let uxy = filt(&|i| x[i] * y[i]);
    let (c1, c2) = (C1, C2);
    (0..ow * oh)
        .map(|i| {
            let (mx, my) = (ux[i], uy[i]);
            let vx = uxx[i] - mx * mx;
            let vy = uyy[i] - my * my;
            let vxy = uxy[i] - mx * my;
            ((2.0 * mx * my + c1) * (2.0 * vxy + c2)) / ((mx * mx + my * my + c1) * (vx + vy + c2))
        })
        .collect()
}

fn ssim_impl(a: &[f32], b: &[f32], w: usize, h: usize, mask: Option<&[bool]>) -> f64 {
    assert_eq!(a.len(), w * h * 3, "image a is not {w}×{h}×3");
    assert_eq!(b.len(), w * h * 3, "image b is not {w}×{h}×3");
    if w <= 2 * RADIUS || h <= 2 * RADIUS {
        return f64::NAN;
    }
    let (ow, oh) = (w - 2 * RADIUS, h - 2 * RADIUS);
    let mut total = 0.0;
    for c in 0..3 {
        let x: Vec<f64> = a.iter().skip(c).step_by(3).map(|&v| v as f64).collect();
        let y: Vec<f64> = b.iter().skip(c).step_by(3).map(|&v| v as f64).collect();
        let map = ssim_map_channel(&x, &y, w, h);
        let (mut s, mut n) = (0.0, 0usize);
        for r in 0..oh {
            for col in 0..ow {
                if mask.is_some_and(|m| !m[(r + RADIUS) * w + col + RADIUS]) {
                    continue;
                }
                s += map[r * ow + col];
                n += 1;
            }
        }
        total += if n == 0 { f64::NAN } else { s / n as f64 };
    }
    total / 3.0
}

/// SSIM of two RGB images (`w × h × 3`, row-major), per channel then averaged.
pub fn ssim(a: &[f32], b: &[f32], w: usize, h: usize) -> f64 {
    ssim_impl(a, b, w, h, None)
}

/// SSIM averaged over the (cropped) SSIM map where `mask` is true.
pub fn ssim_masked(a: &[f32], b: &[f32], w: usize, h: usize, mask: &[bool]) -> f64 {
    ssim_impl(a, b, w, h, Some(mask))
}

/// Per-pixel ꟻLIP error (NVIDIA's LDR ꟻLIP, Andersson et al. 2020, via the `nv-flip` crate's
/// reference C++), `[h*w]` values in [0, 1], of `test` against `reference` (both RGB in [0, 1],
/// sRGB-encoded, quantised to 8 bits as `round(clamp(v, 0, 1)·255)` as ꟻLIP's LDR mode reads
/// images), at nv-flip's `DEFAULT_PIXELS_PER_DEGREE`, 67 (ꟻLIP's viewing conditions, a 0.7 m wide
/// monitor of 3840 pixels viewed from 0.7 m, give 67.02, NVIDIA's flip-evaluator's own default;
/// the mean error then differs by ~1e-5: `tests/eval_protocol.rs` holds xscale to flip-evaluator
/// at 67 within 1e-6).
pub fn flip_map(reference: &[f32], test: &[f32], w: usize, h: usize) -> Vec<f32> {
    assert_eq!(reference.len(), w * h * 3, "reference is not {w}×{h}×3");
    assert_eq!(test.len(), w * h * 3, "test is not {w}×{h}×3");
    let q = |d: &[f32]| -> Vec<u8> {
        d.iter()
            .map(|&v| (if v.is_nan() { 0.0 } else { v.clamp(0.0, 1.0) } * 255.0).round() as u8)
            .collect()
    };
    let (rq, tq) = (q(reference), q(test));
    let r = nv_flip::FlipImageRgb8::with_data(w as u32, h as u32, &rq);
    let t = nv_flip::FlipImageRgb8::with_data(w as u32, h as u32, &tq);
    nv_flip::flip(r, t, nv_flip::DEFAULT_PIXELS_PER_DEGREE).to_vec()
}

/// Mean of a per-pixel map over the pixels where `mask` is true (all pixels without a mask);
/// NaN when no pixel counts.
pub fn masked_mean(map: &[f32], mask: Option<&[bool]>) -> f64 {
    let (mut s, mut n) = (0.0f64, 0usize);
    for (i, &v) in map.iter().enumerate() {
        if mask.is_some_and(|m| !m[i]) {
            continue;
        }
        s += v as f64;
        n += 1;
    }
    if n == 0 {
        f64::NAN
    } else {
        s / n as f64
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::rng::{uniform_f32, Purpose};

    fn noise(w: usize, h: usize, seed: u64) -> Vec<f32> {
        (0..w * h * 3)
            .map(|i| uniform_f32(seed, Purpose::Test, 0, i as u64))
            .collect()
    }

    #[test]
    fn psnr_known() {
        let a = vec![0.5f32; 12];
        let mut b = a.clone();
        for v in b.iter_mut() {
            *v += 0.1;
        }
        // MSE = 0.01 (up to f32 rounding of 0.6) → 20 dB.
        assert!((psnr(&a, &b) - 20.0).abs() < 1e-5);
        assert!(psnr(&a, &a).is_infinite());
        let mask = [true, false, false, false];
        b[3..].iter_mut().for_each(|v| *v = 1.0);
        assert!((psnr_masked(&a, &b, &mask) - 20.0).abs() < 1e-5);
    }

    #[test]
    fn ssim_properties() {
        let (w, h) = (32, 24);
        let a = noise(w, h, 1);
        assert!((ssim(&a, &a, w, h) - 1.0).abs() < 1e-12);
        // Symmetric, below 1 for different images, and degrades with more noise.
        let b: Vec<f32> = a
            .iter()
            .zip(noise(w, h, 2))
            .map(|(x, n)| (x + 0.1 * (n - 0.5)).clamp(0.0, 1.0))
            .collect();
        let c: Vec<f32> = a
            .iter()
            .zip(noise(w, h, 2))
            .map(|(x, n)| (x + 0.4 * (n - 0.5)).clamp(0.0, 1.0))
            .collect();
        let (sab, sba, sac) = (ssim(&a, &b, w, h), ssim(&b, &a, w, h), ssim(&a, &c, w, h));
        assert!((sab - sba).abs() < 1e-12);
        assert!(sab < 0.999 && sac < sab, "{sab} {sac}");
        // A constant offset on a flat image: luminance term only.
        let f = vec![0.5f32; w * h * 3];
        let g = vec![0.6f32; w * h * 3];
        let (mx, my) = (0.5f32 as f64, 0.6f32 as f64);
        let expect = (2.0 * mx * my + 1e-4) / (mx * mx + my * my + 1e-4);
        assert!((ssim(&f, &g, w, h) - expect).abs() < 1e-9);
    }

    /// Against scikit-image 0.25 (`structural_similarity(a, b, gaussian_weights=True, sigma=1.5,
    /// use_sample_covariance=False, data_range=1.0, channel_axis=-1)` on float64 copies of these
    /// f32 images: an independent implementation, value computed once with Python).
    #[test]
    fn ssim_matches_scikit_image() {
        let (w, h) = (23usize, 17usize);
        let a: Vec<f32> = (0..w * h * 3)
            .map(|i| (0.5 + 0.4 * (i as f64 * 0.37).sin()) as f32)
            .collect();
        let b: Vec<f32> = a
            .iter()
            .enumerate()
            .map(|(i, &x)| (x as f64 + 0.15 * (i as f64 * 1.91).cos()).clamp(0.0, 1.0) as f32)
            .collect();
        let v = ssim(&a, &b, w, h);
        assert!((v - 0.9526834511575056).abs() < 1e-9, "{v}");
    }
}
