//! Direction encoding (SPEC §4.3): real spherical harmonics up to degree 4 (16 values), the
//! polynomials and constants of tiny-cuda-nn's `SphericalHarmonics` encoding (Condon–Shortley
//! signs; band 1 = −C₁·y, +C₁·z, −C₁·x).
//!
//! The encoding is applied to the direction exactly as given (no renormalisation inside): the
//! pipeline passes the pixel's unit view direction. tiny-cuda-nn maps `(d+1)/2` back with `2x−1`
//! in f32 first; that round trip can move `d` by an ulp, the polynomials are the same.
//!
//! Numerics: every value is evaluated in the model's scalar `R` with unfused multiplies and adds,
//! in the operand order written below (which follows the reference polynomials), constants given
//! as f64 literals and rounded to `R` (for f32 these round to tiny-cuda-nn's f32 literals).

use crate::model::Real;

/// Number of SH outputs (degree 4 → 4² = 16).
pub const SH_DIM: usize = 16;

// Constants of the real SH basis (tiny-cuda-nn's `sh_enc`, degree ≤ 4).
#[allow(clippy::excessive_precision)]
const C0: f64 = 0.28209479177387814; // 1/(2√π)
#[allow(clippy::excessive_precision)]
const C1: f64 = 0.48860251190291987; // √3/(2√π)
#[allow(clippy::excessive_precision)]
const C2: f64 = 1.0925484305920792; // √15/(2√π)
#[allow(clippy::excessive_precision)]
const C3: f64 = 0.94617469575755997; // 3√5/(4√π)
#[allow(clippy::excessive_precision)]
const C4: f64 = 0.31539156525251999; // √5/(4√π)
#[allow(clippy::excessive_precision)]
const C5: f64 = 0.54627421529603959; // √15/(4√π)
#[allow(clippy::excessive_precision)]
const C6: f64 = 0.59004358992664352; // √70/(8√π)
#[allow(clippy::excessive_precision)]
const C7: f64 = 2.8906114426405538; // √105/(2√π)
#[allow(clippy::excessive_precision)]
const C8: f64 = 0.45704579946446572; // √42/(8√π)
#[allow(clippy::excessive_precision)]
const C9: f64 = 0.3731763325901154; // √7/(4√π)
#[allow(clippy::excessive_precision)]
const C10: f64 = 1.4453057213202769; // √105/(4√π)

#[inline(always)]
fn c<R: Real>(v: f64) -> R {
    R::from_f64(v)
}

/// Encode one direction: `out[16]` (overwritten).
#[inline]
pub fn sh_forward_one<R: Real>(d: [R; 3], out: &mut [R]) {
    let (x, y, z) = (d[0], d[1], d[2]);
    let (xy, xz, yz) = (x * y, x * z, y * z);
    let (x2, y2, z2) = (x * x, y * y, z * z);
    out[0] = c(C0);
    out[1] = -c::<R>(C1) * y;
    out[2] = c::<R>(C1) * z;
    out[3] = -c::<R>(C1) * x;
    out[4] = c::<R>(C2) * xy;
    out[5] = -c::<R>(C2) * yz;
    out[6] = c::<R>(C3) * z2 - c::<R>(C4);
    out[7] = -c::<R>(C2) * xz;
    out[8] = c::<R>(C5) * x2 - c::<R>(C5) * y2;
    out[9] = c::<R>(C6) * y * (c::<R>(-3.0) * x2 + y2);
    out[10] = c::<R>(C7) * xy * z;
    out[11] = c::<R>(C8) * y * (R::ONE - c::<R>(5.0) * z2);
    out[12] = c::<R>(C9) * z * (c::<R>(5.0) * z2 - c::<R>(3.0));
    out[13] = c::<R>(C8) * x * (R::ONE - c::<R>(5.0) * z2);
    out[14] = c::<R>(C10) * z * (x2 - y2);
    out[15] = c::<R>(C6) * x * (-x2 + c::<R>(3.0) * y2);
}

/// Accumulate `d_dir[3] += ∂L/∂d` from `d_out[16]` (hand-derived from the polynomials above).
#[inline]
pub fn sh_backward_one<R: Real>(d: [R; 3], d_out: &[R], d_dir: &mut [R]) {
    let (x, y, z) = (d[0], d[1], d[2]);
    let (xy, xz, yz) = (x * y, x * z, y * z);
    let (x2, y2, z2) = (x * x, y * y, z * z);
    let g = d_out;
    let two = c::<R>(2.0);
    let (c1, c2, c3, c5, c6, c7, c8, c9, c10) = (
        c::<R>(C1),
        c::<R>(C2),
        c::<R>(C3),
        c::<R>(C5),
        c::<R>(C6),
        c::<R>(C7),
        c::<R>(C8),
        c::<R>(C9),
        c::<R>(C10),
    );
    let one_m_5z2 = R::ONE - c::<R>(5.0) * z2;
    // ∂/∂x
    let mut dx = -c1 * g[3];
    dx += c2 * y * g[4];
    dx += -c2 * z * g[7];
    dx += two * c5 * x * g[8];
    dx += c::<R>(-6.0) * c6 * xy * g[9];
    dx += c7 * yz * g[10];
    dx += c8 * one_m_5z2 * g[13];
    dx += two * c10 * xz * g[14];
    dx += c6 * c::<R>(3.0) * (y2 - x2) * g[15];
    // ∂/∂y
    let mut dy = -c1 * g[1];
    dy += c2 * x * g[4];
    dy += -c2 * z * g[5];
    dy += -two * c5 * y * g[8];
    dy += c6 * c::<R>(3.0) * (y2 - x2) * g[9];
    dy += c7 * xz * g[10];
    dy += c8 * one_m_5z2 * g[11];
    dy += -two * c10 * yz * g[14];
    dy += c::<R>(6.0) * c6 * xy * g[15];
    // ∂/∂z
    let mut dz = c1 * g[2];
    dz += -c2 * y * g[5];
    dz += two * c3 * z * g[6];
    dz += -c2 * x * g[7];
    dz += c7 * xy * g[10];
    dz += c::<R>(-10.0) * c8 * yz * g[11];
    dz += c9 * (c::<R>(15.0) * z2 - c::<R>(3.0)) * g[12];
    dz += c::<R>(-10.0) * c8 * xz * g[13];
    dz += c10 * (x2 - y2) * g[14];
    d_dir[0] += dx;
    d_dir[1] += dy;
    d_dir[2] += dz;
}

/// Encode N directions: `out[N, 16]` (overwritten).
pub fn sh_forward<R: Real>(dirs: &[[f32; 3]], out: &mut [R]) {
    for (d, o) in dirs.iter().zip(out.chunks_exact_mut(SH_DIM)) {
        sh_forward_one(dir_to::<R>(d), o);
    }
}

/// Accumulate `d_dirs[N, 3] += ∂L/∂dirs` from `d_out[N, 16]`.
pub fn sh_backward<R: Real>(dirs: &[[f32; 3]], d_out: &[R], d_dirs: &mut [R]) {
    for ((d, g), dd) in dirs
        .iter()
        .zip(d_out.chunks_exact(SH_DIM))
        .zip(d_dirs.chunks_exact_mut(3))
    {
        sh_backward_one(dir_to::<R>(d), g, dd);
    }
}

#[inline(always)]
pub fn dir_to<R: Real>(d: &[f32; 3]) -> [R; 3] {
    [R::from_f32(d[0]), R::from_f32(d[1]), R::from_f32(d[2])]
}

#[cfg(test)]
#[allow(clippy::needless_range_loop)] // the Gram matrix is indexed as in its formula
mod tests {
    use super::*;

    /// Orthonormality of the basis on the sphere (a property independent of the implementation):
    /// a Monte-Carlo estimate of ∫ Y_i Y_j dΩ must be ≈ δ_ij.
    #[test]
    fn orthonormal_on_sphere() {
        let n = 200_000u64;
        let mut gram = [[0.0f64; SH_DIM]; SH_DIM];
        let mut y = [0.0f64; SH_DIM];
        for k in 0..n {
            // Uniform on the sphere from two counter-based draws.
            let u = crate::rng::uniform_f64(1, crate::rng::Purpose::Test, 0, k) * 2.0 - 1.0;
            let phi =
                crate::rng::uniform_f64(1, crate::rng::Purpose::Test, 1, k) * std::f64::consts::TAU;
            let s = (1.0 - u * u).sqrt();
            sh_forward_one([s * phi.cos(), s * phi.sin(), u], &mut y);
            for i in 0..SH_DIM {
                for j in 0..SH_DIM {
                    gram[i][j] += y[i] * y[j];
                }
            }
        }
        let area = 4.0 * std::f64::consts::PI / n as f64;
        for i in 0..SH_DIM {
            for j in 0..SH_DIM {
                let g = gram[i][j] * area;
                let want = if i == j { 1.0 } else { 0.0 };
                // MC error ~ a few / sqrt(n) for these bounded polynomials.
                assert!((g - want).abs() < 0.03, "gram[{i}][{j}] = {g}");
            }
        }
    }

    /// Band-1 signs as in tiny-cuda-nn: Y1 = −C1·y, Y2 = +C1·z, Y3 = −C1·x.
    #[test]
    fn band1_signs() {
        let mut y = [0.0f64; SH_DIM];
        sh_forward_one([1.0, 0.0, 0.0], &mut y);
        assert!(y[3] < 0.0 && y[1] == 0.0 && y[2] == 0.0);
        sh_forward_one([0.0, 1.0, 0.0], &mut y);
        assert!(y[1] < 0.0);
        sh_forward_one([0.0, 0.0, 1.0], &mut y);
        assert!(y[2] > 0.0);
        assert_eq!(y[0], C0);
    }
}
