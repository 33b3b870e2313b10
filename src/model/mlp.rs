//! ReLU MLPs (the shader of Eq. 3 and the deformation ξ of Eq. 5): linear layers `y = W x (+ b)`
//! with `W` `[out, in]` row-major and an optional bias, ReLU after every hidden layer, the last
//! layer linear (the shader's sigmoid lives in `hfm.rs`). Xavier-uniform initialisation from the
//! counter-based generator; optionally a zero last layer (ξ starts undeformed, SPEC §4.4).
//!
//! Numerics (part of the oracle's definition; a backend comparing against us should expect
//! ~1e-6 relative differences, not bit equality, because it will sum in another order):
//! - forward: `y[o] = (((b[o] or +0) + x[0]·W[o,0]) + x[1]·W[o,1]) + …` in input order, every
//!   product and sum rounded separately (no fused multiply-add: Rust never contracts, and the
//!   result does not depend on the CPU's FMA support).
//! - backward: `dx[m,i] += Σ_o dy[m,o]·W[o,i]` (o ascending), `dW[o,i] += Σ_m dy[m,o]·x[m,i]`
//!   (rows ascending), `db[o] += Σ_m dy[m,o]` (rows ascending), each sum starting from the
//!   buffer's current value.
//!   Callers hand in a fresh (zeroed) chunk buffer for `dW` per fixed-size chunk of rows and
//!   combine chunk buffers in chunk order (SPEC §5), so results never depend on the thread count.
//! - All three products go through one register-tiled kernel (`gemm`): for f32 on x86-64
//!   with AVX2 (detected at run time) an intrinsics kernel with 6×16 tiles and masked column
//!   edges, otherwise a portable one with 4×16 tiles the compiler keeps in registers. Both do
//!   the same IEEE operations in the same order, so they are bit-identical (tested below).

use crate::model::Real;
use crate::rng::{self, Purpose};

/// One linear layer inside an MLP's parameter slice.
#[derive(Clone, Debug, PartialEq)]
pub struct Linear {
    pub in_dim: usize,
    pub out_dim: usize,
    /// Offset of `W [out, in]` in the MLP's parameter slice.
    pub w_off: usize,
    /// Offset of `b [out]`, if the layer has a bias.
    pub b_off: Option<usize>,
}

/// A ReLU MLP whose parameters are one contiguous slice (`[W0, (b0), W1, (b1), …]`).
#[derive(Clone, Debug, PartialEq)]
pub struct Mlp {
    pub layers: Vec<Linear>,
    pub n_params: usize,
}

/// Forward activations of an MLP over `rows` rows: `hidden[k]` is layer k's output after ReLU
/// (`[rows, width_k]`), `out` the last layer's linear output `[rows, out]`.
#[derive(Clone, Debug, Default)]
pub struct MlpActs<R> {
    pub hidden: Vec<Vec<R>>,
    pub out: Vec<R>,
}

impl Mlp {
    /// `dims = [in, hidden…, out]`.
    pub fn new(dims: &[usize], bias: bool) -> Mlp {
        assert!(
            dims.len() >= 2,
            "an MLP needs at least an input and an output size"
        );
        let mut off = 0;
        let mut layers = Vec::new();
        for w in dims.windows(2) {
            let (i, o) = (w[0], w[1]);
            let w_off = off;
            off += i * o;
            let b_off = if bias {
                let b = off;
                off += o;
                Some(b)
            } else {
                None
            };
            layers.push(Linear {
                in_dim: i,
                out_dim: o,
                w_off,
                b_off,
            });
        }
        Mlp {
            layers,
            n_params: off,
        }
    }

    pub fn in_dim(&self) -> usize {
        self.layers[0].in_dim
    }
    pub fn out_dim(&self) -> usize {
        self.layers.last().unwrap().out_dim
    }

    /// Transposed weights `Wᵀ [in, out]` of every layer (the forward kernel's layout). Computed
    /// once per pipeline pass and shared by all chunks.
    pub fn transpose_weights<R: Real>(&self, p: &[R]) -> Vec<Vec<R>> {
        self.layers
            .iter()
            .map(|l| {
                let w = &p[l.w_off..l.w_off + l.in_dim * l.out_dim];
                let mut t = vec![R::ZERO; w.len()];
                for o in 0..l.out_dim {
                    for i in 0..l.in_dim {
                        t[i * l.out_dim + o] = w[o * l.in_dim + i];
                    }
                }
                t
            })
            .collect()
    }

    /// Forward over `rows` rows of `x [rows, in]`. `wt` from [`Mlp::transpose_weights`].
    pub fn forward<R: Real>(
        &self,
        p: &[R],
        wt: &[Vec<R>],
        x: &[R],
        rows: usize,
        acts: &mut MlpActs<R>,
    ) {
        let n = self.layers.len();
        acts.hidden.resize_with(n - 1, Vec::new);
        for (k, l) in self.layers.iter().enumerate() {
            let bias = l.b_off.map(|b| &p[b..b + l.out_dim]);
            let mut y = if k + 1 < n {
                std::mem::take(&mut acts.hidden[k])
            } else {
                std::mem::take(&mut acts.out)
            };
            // Every element is written by `linear_forward` (bias or zero, then the product), so
            // a reused buffer keeps its old values here rather than being zeroed twice.
            y.resize(rows * l.out_dim, R::ZERO);
            {
                let input: &[R] = if k == 0 { x } else { &acts.hidden[k - 1] };
                linear_forward(&wt[k], bias, input, rows, l.in_dim, l.out_dim, &mut y);
            }
            if k + 1 < n {
                relu_forward(&mut y);
                acts.hidden[k] = y;
            } else {
                acts.out = y;
            }
        }
    }

    /// Backward over the same rows. `d_out [rows, out]` is ∂L/∂(last linear output) and is
    /// consumed as scratch. Accumulates `dp += ∂L/∂params` (the MLP's own parameter layout) and,
    /// if given, `dx [rows, in] += ∂L/∂x`.
    // A hot kernel (inner loop of a step): its arguments are the buffers and sizes it works on,
    // llm.c style; kept as they are rather than re-measure its speed behind a struct.
    #[allow(clippy::too_many_arguments)]
    pub fn backward<R: Real>(
        &self,
        p: &[R],
        x: &[R],
        rows: usize,
        acts: &MlpActs<R>,
        d_out: Vec<R>,
        dp: &mut [R],
        dx: Option<&mut [R]>,
    ) {
        let mut dy = d_out;
        let mut dx = dx;
        for (k, l) in self.layers.iter().enumerate().rev() {
            let w = &p[l.w_off..l.w_off + l.in_dim * l.out_dim];
            let input: &[R] = if k == 0 { x } else { &acts.hidden[k - 1] };
            let (dw_part, rest) = dp[l.w_off..].split_at_mut(l.in_dim * l.out_dim);
            let db = l.b_off.map(|b| {
                debug_assert_eq!(b, l.w_off + l.in_dim * l.out_dim);
                &mut rest[..l.out_dim]
            });
            if k > 0 {
                let mut dprev = vec![R::ZERO; rows * l.in_dim];
                linear_backward(
                    w,
                    input,
                    &dy,
                    rows,
                    l.in_dim,
                    l.out_dim,
                    dw_part,
                    db,
                    Some(&mut dprev),
                );
                relu_backward(&acts.hidden[k - 1], &mut dprev);
                dy = dprev;
            } else {
                linear_backward(
                    w,
                    input,
                    &dy,
                    rows,
                    l.in_dim,
                    l.out_dim,
                    dw_part,
                    db,
                    dx.take(),
                );
            }
        }
    }

    /// Xavier-uniform weights `U(±sqrt(6/(fan_in+fan_out)))`, element e of layer k drawn as
    /// `uniform_f64(seed, InitWeights, tensor_ids[k], e)`; biases zero; the last layer all zero
    /// if `zero_last` (ξ, SPEC §4.4). Returns the MLP's parameter slice in f32.
    pub fn init(&self, seed: u64, tensor_ids: &[u64], zero_last: bool) -> Vec<f32> {
        let mut p = vec![0.0f32; self.n_params];
        for (k, l) in self.layers.iter().enumerate() {
            if zero_last && k + 1 == self.layers.len() {
                continue;
            }
            let limit = (6.0 / (l.in_dim + l.out_dim) as f64).sqrt();
            for e in 0..l.in_dim * l.out_dim {
                let u = rng::uniform_f64(seed, Purpose::InitWeights, tensor_ids[k], e as u64);
                p[l.w_off + e] = ((2.0 * u - 1.0) * limit) as f32;
            }
        }
        p
    }
}

/// `y [rows, out] = x [rows, in] · Wᵀ (+ b)` (overwritten), with `wt = Wᵀ [in, out]`.
pub fn linear_forward<R: Real>(
    wt: &[R],
    b: Option<&[R]>,
    x: &[R],
    rows: usize,
    in_dim: usize,
    out_dim: usize,
    y: &mut [R],
) {
    #[cfg(target_arch = "x86_64")]
    if std::is_x86_feature_detected!("avx2") {
        // SAFETY: the CPU supports AVX2 (checked just above).
        unsafe { linear_forward_avx2(wt, b, x, rows, in_dim, out_dim, y) };
        return;
    }
    linear_forward_body::<R, false>(wt, b, x, rows, in_dim, out_dim, y)
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
unsafe fn linear_forward_avx2<R: Real>(
    wt: &[R],
    b: Option<&[R]>,
    x: &[R],
    rows: usize,
    in_dim: usize,
    out_dim: usize,
    y: &mut [R],
) {
    linear_forward_body::<R, true>(wt, b, x, rows, in_dim, out_dim, y)
}

/// `AVX2`: the caller has checked that the CPU has AVX2 (see [`gemm`]).
#[inline(always)]
fn linear_forward_body<R: Real, const AVX2: bool>(
    wt: &[R],
    b: Option<&[R]>,
    x: &[R],
    rows: usize,
    in_dim: usize,
    out_dim: usize,
    y: &mut [R],
) {
    assert!(wt.len() == in_dim * out_dim && x.len() >= rows * in_dim && y.len() >= rows * out_dim);
    match b {
        Some(b) => {
            for yr in y[..rows * out_dim].chunks_exact_mut(out_dim.max(1)) {
                yr.copy_from_slice(b);
            }
            // y [rows, out] += x [rows, in] · Wᵀ [in, out]
            gemm::<R, AVX2>(
                rows, out_dim, in_dim, x, in_dim, 1, wt, out_dim, y, out_dim, false,
            );
        }
        // y [rows, out] = 0 + x [rows, in] · Wᵀ [in, out]
        None => gemm::<R, AVX2>(
            rows, out_dim, in_dim, x, in_dim, 1, wt, out_dim, y, out_dim, true,
        ),
    }
}

/// Register tile of [`gemm`]: MR rows × NR columns of C kept in registers.
const MR: usize = 4;
const NR: usize = 16;

/// `C [m, n] += A [m, k] · B [k, n]`, every element summed from its current value over k in
/// ascending order with separately rounded products and sums (the order the module doc
/// promises). A is addressed with strides (`a_rs` per row, `a_cs` per column) so the same kernel
/// serves `x·Wᵀ`, `dy·W` and `dyᵀ·x`; B and C are row-major with leading dimensions `ldb`, `ldc`.
/// Tiles of MR × NR are accumulated in registers; the ragged edges take a scalar loop with the
/// same order of operations, so the result does not depend on the tiling.
///
/// `AVX2 = true` is a promise that the CPU has AVX2: only the run-time dispatch of
/// [`linear_forward`] / [`linear_backward`] passes it, after `is_x86_feature_detected!`. With it,
/// f32 products take the intrinsics kernel (`avx2::gemm_acc_f32`).
///
/// With `zero_c`, C starts from zero instead: `C [m, n] = 0 + A [m, k] · B [k, n]`, the same
/// bits as zeroing C and accumulating, without the pass that zeroes it (the AVX2 kernel starts
/// its tiles at +0 instead of loading C; C's earlier contents are never read).
#[inline(always)]
// A hot kernel (inner loop of a step): its arguments are the buffers and sizes it works on,
// llm.c style; kept as they are rather than re-measure its speed behind a struct.
#[allow(clippy::too_many_arguments)]
fn gemm<R: Real, const AVX2: bool>(
    m: usize,
    n: usize,
    k: usize,
    a: &[R],
    a_rs: usize,
    a_cs: usize,
    b: &[R],
    ldb: usize,
    c: &mut [R],
    ldc: usize,
    zero_c: bool,
) {
    if m == 0 || n == 0 {
        return;
    }
    #[cfg(target_arch = "x86_64")]
    if AVX2 {
        debug_assert!(std::is_x86_feature_detected!("avx2"));
        if let (Some(a32), Some(b32), Some(c32)) = (as_f32(a), as_f32(b), as_f32_mut(c)) {
            let (la, lb, lc) = (a32.len(), b32.len(), c32.len());
            // The kernel reads A, B and writes C at exactly the places the loops below do.
            assert!(k == 0 || la > (m - 1) * a_rs + (k - 1) * a_cs);
            assert!(k == 0 || lb >= (k - 1) * ldb + n);
            assert!(lc >= (m - 1) * ldc + n);
            // SAFETY: AVX2 is present (the caller's promise, `AVX2`); every address the kernel
            // touches is in bounds (asserted above: rows < m, columns < n, k < k of each operand).
            unsafe {
                avx2::gemm_acc_f32(
                    m,
                    n,
                    k,
                    a32.as_ptr(),
                    a_rs,
                    a_cs,
                    b32.as_ptr(),
                    ldb,
                    c32.as_mut_ptr(),
                    ldc,
                    zero_c,
                )
            };
            return;
        }
    }
    if zero_c {
        for row in c[..(m - 1) * ldc + n].chunks_mut(ldc) {
            row[..n].fill(R::ZERO);
        }
    }
    gemm_acc_generic(m, n, k, a, a_rs, a_cs, b, ldb, c, ldc)
}

/// The portable [`gemm`] (any `R`; the f64 model and machines without AVX2).
#[inline(always)]
// A hot kernel (inner loop of a step): its arguments are the buffers and sizes it works on,
// llm.c style; kept as they are rather than re-measure its speed behind a struct.
#[allow(clippy::too_many_arguments)]
fn gemm_acc_generic<R: Real>(
    m: usize,
    n: usize,
    k: usize,
    a: &[R],
    a_rs: usize,
    a_cs: usize,
    b: &[R],
    ldb: usize,
    c: &mut [R],
    ldc: usize,
) {
    let m_full = m / MR * MR;
    let n_full = n / NR * NR;
    let scalar = |c: &mut [R], i: usize, j: usize| {
        let mut s = c[i * ldc + j];
        for kk in 0..k {
            s += a[i * a_rs + kk * a_cs] * b[kk * ldb + j];
        }
        c[i * ldc + j] = s;
    };
    for i0 in (0..m_full).step_by(MR) {
        for j0 in (0..n_full).step_by(NR) {
            let mut acc = [[R::ZERO; NR]; MR];
            for (r, row) in acc.iter_mut().enumerate() {
                row.copy_from_slice(&c[(i0 + r) * ldc + j0..(i0 + r) * ldc + j0 + NR]);
            }
            for kk in 0..k {
                let brow: &[R; NR] = b[kk * ldb + j0..kk * ldb + j0 + NR].try_into().unwrap();
                for (r, row) in acc.iter_mut().enumerate() {
                    let av = a[(i0 + r) * a_rs + kk * a_cs];
                    for (cv, &bv) in row.iter_mut().zip(brow) {
                        *cv += av * bv;
                    }
                }
            }
            for (r, row) in acc.iter().enumerate() {
                c[(i0 + r) * ldc + j0..(i0 + r) * ldc + j0 + NR].copy_from_slice(row);
            }
        }
        for i in i0..i0 + MR {
            for j in n_full..n {
                scalar(c, i, j);
            }
        }
    }
    // Ragged rows: 1 × NR tiles, then scalar.
    for i in m_full..m {
        for j0 in (0..n_full).step_by(NR) {
            let mut acc = [R::ZERO; NR];
            acc.copy_from_slice(&c[i * ldc + j0..i * ldc + j0 + NR]);
            for kk in 0..k {
                let brow: &[R; NR] = b[kk * ldb + j0..kk * ldb + j0 + NR].try_into().unwrap();
                let av = a[i * a_rs + kk * a_cs];
                for (cv, &bv) in acc.iter_mut().zip(brow) {
                    *cv += av * bv;
                }
            }
            c[i * ldc + j0..i * ldc + j0 + NR].copy_from_slice(&acc);
        }
        for j in n_full..n {
            scalar(c, i, j);
        }
    }
}

/// `Some` when `R` is `f32` (the same slice, typed).
fn as_f32<R: Real>(x: &[R]) -> Option<&[f32]> {
    (std::any::TypeId::of::<R>() == std::any::TypeId::of::<f32>())
        // SAFETY: R is f32 (same type, same layout).
        .then(|| unsafe { std::slice::from_raw_parts(x.as_ptr() as *const f32, x.len()) })
}

fn as_f32_mut<R: Real>(x: &mut [R]) -> Option<&mut [f32]> {
    (std::any::TypeId::of::<R>() == std::any::TypeId::of::<f32>())
        // SAFETY: R is f32 (same type, same layout).
        .then(|| unsafe { std::slice::from_raw_parts_mut(x.as_mut_ptr() as *mut f32, x.len()) })
}

/// The f32 [`gemm`] with AVX2 intrinsics: 6×16 register tiles (12 accumulators), then an
/// 8-wide and a masked column edge, every C element summed over k in ascending order with a separately
/// rounded product and sum, exactly as the generic kernel (tested bit for bit). The generic
/// kernel, compiled with AVX2, spends half its instructions on bounds checks and reloading row
/// pointers; this one keeps the tile's row offsets in registers.
#[cfg(target_arch = "x86_64")]
#[allow(clippy::needless_range_loop)] // index loops over register tiles read best as they are
mod avx2 {
    use std::arch::x86_64::*;

    /// # Safety
    /// AVX2 must be available; for i < m, kk < k, j < n: `a[i*a_rs + kk*a_cs]`,
    /// `b[kk*ldb + j]` and `c[i*ldc + j]` must be in bounds.
    #[target_feature(enable = "avx2")]
    // A hot kernel (inner loop of a step): its arguments are the buffers and sizes it works on,
    // llm.c style; kept as they are rather than re-measure its speed behind a struct.
    #[allow(clippy::too_many_arguments)]
    pub unsafe fn gemm_acc_f32(
        m: usize,
        n: usize,
        k: usize,
        a: *const f32,
        a_rs: usize,
        a_cs: usize,
        b: *const f32,
        ldb: usize,
        c: *mut f32,
        ldc: usize,
        zero_c: bool,
    ) {
        let g = Gemm {
            n,
            k,
            a,
            a_rs,
            a_cs,
            b,
            ldb,
            c,
            ldc,
            zero_c,
        };
        let mut i0 = 0;
        while i0 + 6 <= m {
            g.rows::<6>(i0);
            i0 += 6;
        }
        match m - i0 {
            5 => g.rows::<5>(i0),
            4 => g.rows::<4>(i0),
            3 => g.rows::<3>(i0),
            2 => g.rows::<2>(i0),
            1 => g.rows::<1>(i0),
            _ => {}
        }
    }

    #[derive(Clone, Copy)]
    struct Gemm {
        n: usize,
        k: usize,
        a: *const f32,
        a_rs: usize,
        a_cs: usize,
        b: *const f32,
        ldb: usize,
        c: *mut f32,
        ldc: usize,
        /// Start the tiles at +0 instead of loading C (`gemm` from zero): C is only written.
        zero_c: bool,
    }

    impl Gemm {
        /// Rows `i0..i0+MR` of C, every column.
        #[inline(always)]
        unsafe fn rows<const MR: usize>(self, i0: usize) {
            let mut j0 = 0;
            while j0 + 16 <= self.n {
                self.tile::<MR, 2>(i0, j0);
                j0 += 16;
            }
            if j0 + 8 <= self.n {
                self.tile::<MR, 1>(i0, j0);
                j0 += 8;
            }
            if j0 < self.n {
                self.tile_masked::<MR>(i0, j0, self.n - j0);
            }
        }

        /// The MR × `cols` (< 8) tile at (i0, j0): the 8-wide tile with masked loads and stores
        /// (lanes ≥ `cols` are neither read nor written).
        #[inline(always)]
        unsafe fn tile_masked<const MR: usize>(self, i0: usize, j0: usize, cols: usize) {
            let lanes = _mm256_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7);
            let mask = _mm256_cmpgt_epi32(_mm256_set1_epi32(cols as i32), lanes);
            let mut acc = [_mm256_setzero_ps(); MR];
            let mut off = [0usize; MR];
            for r in 0..MR {
                off[r] = (i0 + r) * self.a_rs;
                if !self.zero_c {
                    acc[r] = _mm256_maskload_ps(self.c.add((i0 + r) * self.ldc + j0), mask);
                }
            }
            let mut ap = self.a;
            let mut bp = self.b.add(j0);
            for _ in 0..self.k {
                let bv = _mm256_maskload_ps(bp, mask);
                for r in 0..MR {
                    let av = _mm256_broadcast_ss(&*ap.add(off[r]));
                    acc[r] = _mm256_add_ps(acc[r], _mm256_mul_ps(av, bv));
                }
                ap = ap.add(self.a_cs);
                bp = bp.add(self.ldb);
            }
            for r in 0..MR {
                _mm256_maskstore_ps(self.c.add((i0 + r) * self.ldc + j0), mask, acc[r]);
            }
        }

        /// The MR × 8·NV tile at (i0, j0), accumulated in registers.
        #[inline(always)]
        unsafe fn tile<const MR: usize, const NV: usize>(self, i0: usize, j0: usize) {
            let mut acc = [[_mm256_setzero_ps(); NV]; MR];
            let mut off = [0usize; MR];
            for r in 0..MR {
                off[r] = (i0 + r) * self.a_rs;
                if !self.zero_c {
                    for v in 0..NV {
                        acc[r][v] = _mm256_loadu_ps(self.c.add((i0 + r) * self.ldc + j0 + 8 * v));
                    }
                }
            }
            let mut ap = self.a;
            let mut bp = self.b.add(j0);
            for _ in 0..self.k {
                let mut bv = [_mm256_setzero_ps(); NV];
                for v in 0..NV {
                    bv[v] = _mm256_loadu_ps(bp.add(8 * v));
                }
                for r in 0..MR {
                    let av = _mm256_broadcast_ss(&*ap.add(off[r]));
                    for v in 0..NV {
                        acc[r][v] = _mm256_add_ps(acc[r][v], _mm256_mul_ps(av, bv[v]));
                    }
                }
                ap = ap.add(self.a_cs);
                bp = bp.add(self.ldb);
            }
            for r in 0..MR {
                for v in 0..NV {
                    _mm256_storeu_ps(self.c.add((i0 + r) * self.ldc + j0 + 8 * v), acc[r][v]);
                }
            }
        }
    }
}

/// ReLU in place: `max(0, y)` (NaN stays NaN).
pub fn relu_forward<R: Real>(y: &mut [R]) {
    for v in y.iter_mut() {
        // A select (not a conditional store) so the loop vectorises.
        *v = if *v < R::ZERO { R::ZERO } else { *v };
    }
}

/// `dy *= (y > 0)` where `y` is the ReLU output (derivative 0 at the kink).
pub fn relu_backward<R: Real>(y: &[R], dy: &mut [R]) {
    for (g, &v) in dy.iter_mut().zip(y) {
        *g = if v > R::ZERO { *g } else { R::ZERO };
    }
}

/// Accumulate the gradients of `y = x Wᵀ + b` over `rows` rows: `dw [out, in] += dyᵀ x`,
/// `db [out] += Σ dy`, `dx [rows, in] += dy W`.
// A hot kernel (inner loop of a step): its arguments are the buffers and sizes it works on,
// llm.c style; kept as they are rather than re-measure its speed behind a struct.
#[allow(clippy::too_many_arguments)]
pub fn linear_backward<R: Real>(
    w: &[R],
    x: &[R],
    dy: &[R],
    rows: usize,
    in_dim: usize,
    out_dim: usize,
    dw: &mut [R],
    db: Option<&mut [R]>,
    dx: Option<&mut [R]>,
) {
    #[cfg(target_arch = "x86_64")]
    if std::is_x86_feature_detected!("avx2") {
        // SAFETY: the CPU supports AVX2 (checked just above).
        unsafe { linear_backward_avx2(w, x, dy, rows, in_dim, out_dim, dw, db, dx) };
        return;
    }
    linear_backward_body::<R, false>(w, x, dy, rows, in_dim, out_dim, dw, db, dx)
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
// A hot kernel (inner loop of a step): its arguments are the buffers and sizes it works on,
// llm.c style; kept as they are rather than re-measure its speed behind a struct.
#[allow(clippy::too_many_arguments)]
unsafe fn linear_backward_avx2<R: Real>(
    w: &[R],
    x: &[R],
    dy: &[R],
    rows: usize,
    in_dim: usize,
    out_dim: usize,
    dw: &mut [R],
    db: Option<&mut [R]>,
    dx: Option<&mut [R]>,
) {
    linear_backward_body::<R, true>(w, x, dy, rows, in_dim, out_dim, dw, db, dx)
}

/// `AVX2`: the caller has checked that the CPU has AVX2 (see [`gemm`]).
#[inline(always)]
// A hot kernel (inner loop of a step): its arguments are the buffers and sizes it works on,
// llm.c style; kept as they are rather than re-measure its speed behind a struct.
#[allow(clippy::too_many_arguments)]
fn linear_backward_body<R: Real, const AVX2: bool>(
    w: &[R],
    x: &[R],
    dy: &[R],
    rows: usize,
    in_dim: usize,
    out_dim: usize,
    dw: &mut [R],
    db: Option<&mut [R]>,
    dx: Option<&mut [R]>,
) {
    assert!(w.len() == in_dim * out_dim && dw.len() == in_dim * out_dim);
    assert!(x.len() >= rows * in_dim && dy.len() >= rows * out_dim);
    if let Some(db) = db {
        for gr in dy[..rows * out_dim].chunks_exact(out_dim.max(1)) {
            for (d, &g) in db.iter_mut().zip(gr) {
                *d += g;
            }
        }
    }
    // dW [out, in] += dyᵀ [out, rows] · x [rows, in]   (rows ascending)
    gemm::<R, AVX2>(
        out_dim, in_dim, rows, dy, 1, out_dim, x, in_dim, dw, in_dim, false,
    );
    // dx [rows, in] += dy [rows, out] · W [out, in]     (o ascending)
    if let Some(dx) = dx {
        assert!(dx.len() >= rows * in_dim);
        gemm::<R, AVX2>(
            rows, in_dim, out_dim, dy, out_dim, 1, w, in_dim, dx, in_dim, false,
        );
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn rand_vec(n: usize, a: u64) -> Vec<f32> {
        (0..n)
            .map(|i| rng::uniform_f32(3, Purpose::Test, a, i as u64) * 2.0 - 1.0)
            .collect()
    }

    /// The run-time dispatched (AVX2) kernels and the baseline kernels are bit-identical.
    #[test]
    fn dispatch_paths_bit_identical() {
        let (rows, i, o) = (37, 52, 64);
        let wt = rand_vec(i * o, 1);
        let w = rand_vec(i * o, 2);
        let mut x = rand_vec(rows * i, 3);
        for v in x.iter_mut().step_by(3) {
            *v = 0.0;
        }
        let dy = rand_vec(rows * o, 4);
        let b = rand_vec(o, 5);
        let mut y1 = vec![0.0f32; rows * o];
        let mut y2 = y1.clone();
        linear_forward(&wt, Some(&b), &x, rows, i, o, &mut y1);
        linear_forward_body::<f32, false>(&wt, Some(&b), &x, rows, i, o, &mut y2);
        assert!(y1.iter().zip(&y2).all(|(a, b)| a.to_bits() == b.to_bits()));
        let (mut dw1, mut dx1, mut db1) =
            (vec![0.0f32; i * o], vec![0.0f32; rows * i], vec![0.0f32; o]);
        let (mut dw2, mut dx2, mut db2) = (dw1.clone(), dx1.clone(), db1.clone());
        linear_backward(
            &w,
            &x,
            &dy,
            rows,
            i,
            o,
            &mut dw1,
            Some(&mut db1),
            Some(&mut dx1),
        );
        linear_backward_body::<f32, false>(
            &w,
            &x,
            &dy,
            rows,
            i,
            o,
            &mut dw2,
            Some(&mut db2),
            Some(&mut dx2),
        );
        for (a, b) in [(&dw1, &dw2), (&dx1, &dx2), (&db1, &db2)] {
            assert!(a
                .iter()
                .zip(b.iter())
                .all(|(p, q)| p.to_bits() == q.to_bits()));
        }
    }

    /// The f32 AVX2 kernel and the portable kernel are bit-identical on every shape the MLPs
    /// use and on ragged ones (rows and columns not multiples of the tiles, k = 0 and 1), for
    /// the three operand layouts (x·Wᵀ, dyᵀ·x, dy·W).
    #[test]
    fn gemm_kernels_bit_identical() {
        let shapes = [
            (128, 64, 64),
            (512, 44, 32),
            (512, 32, 32),
            (128, 3, 64),
            (64, 64, 128),
            (44, 32, 512),
            (7, 23, 5),
            (13, 9, 1),
            (5, 17, 0),
            (1, 1, 3),
        ];
        for (si, &(m, n, k)) in shapes.iter().enumerate() {
            for (a_rs, a_cs) in [(k, 1), (1, m)] {
                let a = rand_vec((m * a_rs.max(1) + k * a_cs).max(1), 20 + si as u64);
                let b = rand_vec((k * n).max(1), 40 + si as u64);
                let c0 = rand_vec(m * n, 60 + si as u64);
                let (mut c1, mut c2) = (c0.clone(), c0.clone());
                if std::is_x86_feature_detected!("avx2") {
                    gemm::<f32, true>(m, n, k, &a, a_rs, a_cs, &b, n, &mut c1, n, false);
                } else {
                    gemm::<f32, false>(m, n, k, &a, a_rs, a_cs, &b, n, &mut c1, n, false);
                }
                gemm_acc_generic(m, n, k, &a, a_rs, a_cs, &b, n, &mut c2, n);
                assert!(
                    c1.iter().zip(&c2).all(|(x, y)| x.to_bits() == y.to_bits()),
                    "shape {m}x{n}x{k}, strides ({a_rs}, {a_cs})"
                );
                // From zero: C's old contents (NaN here) are never read, and the result is
                // zeroing C then accumulating, bit for bit, in both builds.
                let mut zeroed = vec![0.0f32; m * n];
                gemm_acc_generic(m, n, k, &a, a_rs, a_cs, &b, n, &mut zeroed, n);
                for avx2 in [true, false] {
                    let mut c3 = vec![f32::NAN; m * n];
                    if avx2 && std::is_x86_feature_detected!("avx2") {
                        gemm::<f32, true>(m, n, k, &a, a_rs, a_cs, &b, n, &mut c3, n, true);
                    } else {
                        gemm::<f32, false>(m, n, k, &a, a_rs, a_cs, &b, n, &mut c3, n, true);
                    }
                    assert!(
                        c3.iter()
                            .zip(&zeroed)
                            .all(|(x, y)| x.to_bits() == y.to_bits()),
                        "gemm from zero, shape {m}x{n}x{k}, strides ({a_rs}, {a_cs}), avx2 {avx2}"
                    );
                }
            }
        }
    }

    /// The tiled kernels give exactly the documented order of operations (checked bitwise in f32
    /// against plain sequential loops, including ragged tile edges).
    #[test]
    fn kernels_follow_documented_order() {
        let (rows, i, o) = (13, 37, 21);
        let w = rand_vec(i * o, 6);
        let x = rand_vec(rows * i, 7);
        let dy = rand_vec(rows * o, 8);
        let mut wt = vec![0.0f32; i * o];
        for a in 0..o {
            for c in 0..i {
                wt[c * o + a] = w[a * i + c];
            }
        }
        let mut y = vec![0.0f32; rows * o];
        linear_forward(&wt, None, &x, rows, i, o, &mut y);
        let (mut dw, mut dx) = (rand_vec(i * o, 9), rand_vec(rows * i, 10));
        let (dw0, dx0) = (dw.clone(), dx.clone());
        linear_backward(&w, &x, &dy, rows, i, o, &mut dw, None, Some(&mut dx));
        for m in 0..rows {
            for a in 0..o {
                let mut s = 0.0f32;
                for c in 0..i {
                    s += x[m * i + c] * w[a * i + c];
                }
                assert_eq!(s.to_bits(), y[m * o + a].to_bits());
            }
            for c in 0..i {
                let mut s = dx0[m * i + c];
                for a in 0..o {
                    s += dy[m * o + a] * w[a * i + c];
                }
                assert_eq!(s.to_bits(), dx[m * i + c].to_bits());
            }
        }
        for a in 0..o {
            for c in 0..i {
                let mut s = dw0[a * i + c];
                for m in 0..rows {
                    s += dy[m * o + a] * x[m * i + c];
                }
                assert_eq!(s.to_bits(), dw[a * i + c].to_bits());
            }
        }
    }

    /// Forward against a naive dot product in f64 (independent formulation).
    #[test]
    fn forward_matches_naive() {
        let mlp = Mlp::new(&[5, 7, 3], true);
        let p: Vec<f64> = rand_vec(mlp.n_params, 9)
            .iter()
            .map(|&v| v as f64)
            .collect();
        let x: Vec<f64> = rand_vec(4 * 5, 10).iter().map(|&v| v as f64).collect();
        let wt = mlp.transpose_weights(&p);
        let mut acts = MlpActs::default();
        mlp.forward(&p, &wt, &x, 4, &mut acts);
        for m in 0..4 {
            let mut h = [0.0f64; 7];
            let l0 = &mlp.layers[0];
            for (o, ho) in h.iter_mut().enumerate() {
                let mut s = p[l0.b_off.unwrap() + o];
                for i in 0..5 {
                    s += p[l0.w_off + o * 5 + i] * x[m * 5 + i];
                }
                *ho = s.max(0.0);
            }
            let l1 = &mlp.layers[1];
            for o in 0..3 {
                let mut s = p[l1.b_off.unwrap() + o];
                for (i, hi) in h.iter().enumerate() {
                    s += p[l1.w_off + o * 7 + i] * hi;
                }
                assert!((s - acts.out[m * 3 + o]).abs() < 1e-12);
            }
        }
    }

    #[test]
    fn xavier_bounds_and_zero_last() {
        let mlp = Mlp::new(&[52, 64, 64, 3], false);
        let p = mlp.init(1, &[30, 31, 32], true);
        let l0 = &mlp.layers[0];
        let lim = (6.0f64 / (52.0 + 64.0)).sqrt() as f32;
        let w0 = &p[l0.w_off..l0.w_off + 52 * 64];
        assert!(w0.iter().all(|v| v.abs() <= lim));
        assert!(w0.iter().any(|v| v.abs() > 0.9 * lim));
        let l2 = &mlp.layers[2];
        assert!(p[l2.w_off..].iter().all(|&v| v == 0.0));
        assert_eq!(p, mlp.init(1, &[30, 31, 32], true));
    }
}
