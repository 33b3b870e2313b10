//! Photometric loss (SPEC §4.7): mean over pixels and channels of L1 (default; derivative 0 at
//! r = 0), L2 (mean r², no ½) or smooth-L1 with δ (0.5r²/δ for |r| < δ, else |r| − 0.5δ), with
//! r = rgb − target.
//!
//! Numerics: per-element terms in the model's scalar `R`; the value is summed in f64 (it is only
//! reported, never differentiated) per fixed-size pixel chunk, chunks combined in order by the
//! caller, then divided by 3N. The gradient is `ρ'(r) / (3N)` in `R`.

use crate::model::config::LossKind;
use crate::model::Real;

/// Per-element loss ρ(r) and its derivative ρ'(r).
#[inline]
pub fn loss_elem<R: Real>(kind: LossKind, delta: R, r: R) -> (R, R) {
    match kind {
        LossKind::L1 => {
            let g = if r > R::ZERO {
                R::ONE
            } else if r < R::ZERO {
                -R::ONE
            } else {
                R::ZERO
            };
            (r.abs(), g)
        }
        LossKind::L2 => (r * r, R::from_f64(2.0) * r),
        LossKind::SmoothL1 => {
            let a = r.abs();
            if a < delta {
                (R::from_f64(0.5) * r * r / delta, r / delta)
            } else {
                let g = if r > R::ZERO { R::ONE } else { -R::ONE };
                (a - R::from_f64(0.5) * delta, g)
            }
        }
    }
}

/// Loss forward over a chunk of pixels: returns the f64 SUM of ρ over `rgb [n, 3]` vs
/// `target [n, 3]` (the caller divides by 3N after combining chunks in order).
pub fn loss_forward<R: Real>(kind: LossKind, delta: f64, rgb: &[R], target: &[[f32; 3]]) -> f64 {
    let d = R::from_f64(delta);
    let mut s = 0.0f64;
    for (p, t) in rgb.chunks_exact(3).zip(target) {
        for c in 0..3 {
            s += loss_elem(kind, d, p[c] - R::from_f32(t[c])).0.to_f64();
        }
    }
    s
}

/// Loss backward: `d_rgb [n, 3] += ρ'(rgb − target) · scale` with `scale = 1/(3N)` (N = pixels in
/// the whole batch, not the chunk).
pub fn loss_backward<R: Real>(
    kind: LossKind,
    delta: f64,
    rgb: &[R],
    target: &[[f32; 3]],
    scale: R,
    d_rgb: &mut [R],
) {
    let d = R::from_f64(delta);
    for ((p, t), g) in rgb
        .chunks_exact(3)
        .zip(target)
        .zip(d_rgb.chunks_exact_mut(3))
    {
        for c in 0..3 {
            g[c] += loss_elem(kind, d, p[c] - R::from_f32(t[c])).1 * scale;
        }
    }
}

/// Sigmoid forward `rgb = 1/(1+exp(−z))` (Eq. 3's output activation), in place semantics:
/// `out[i] = σ(z[i])`.
pub fn sigmoid_forward<R: Real>(z: &[R], out: &mut [R]) {
    for (o, &v) in out.iter_mut().zip(z) {
        *o = R::ONE / (R::ONE + (-v).exp());
    }
}

/// Sigmoid backward from its output `s`: `dz += ds · s(1−s)`.
pub fn sigmoid_backward<R: Real>(s: &[R], ds: &[R], dz: &mut [R]) {
    for ((d, &g), &v) in dz.iter_mut().zip(ds).zip(s) {
        *d += g * (v * (R::ONE - v));
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn values_at_known_points() {
        // Definitions of SPEC §4.7 evaluated by hand.
        assert_eq!(loss_elem(LossKind::L1, 0.01, -0.25f64), (0.25, -1.0));
        assert_eq!(loss_elem(LossKind::L1, 0.01, 0.0f64).1, 0.0);
        assert_eq!(loss_elem(LossKind::L2, 0.01, 0.5f64), (0.25, 1.0));
        let (v, g) = loss_elem(LossKind::SmoothL1, 0.5, 0.25f64);
        assert_eq!((v, g), (0.0625, 0.5));
        let (v, g) = loss_elem(LossKind::SmoothL1, 0.5, -1.0f64);
        assert_eq!((v, g), (0.75, -1.0));
        // continuity of smooth-L1 at |r| = δ
        let d = 0.01f64;
        let a = loss_elem(LossKind::SmoothL1, d, d * (1.0 - 1e-12)).0;
        let b = loss_elem(LossKind::SmoothL1, d, d).0;
        assert!((a - b).abs() < 1e-12);
    }
}
