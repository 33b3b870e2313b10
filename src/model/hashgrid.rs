//! Multi-resolution hash grid with tiny-cuda-nn semantics (SPEC §4.2, the paper's Eq. 2).
//!
//! Owns: the per-level geometry (scales, resolutions, sizes, dense/hashed), the table
//! initialisation, and the three passes `forward` / `backward_table` / `backward_points`.
//!
//! API contract (the pipeline codes against this):
//! - points are normalised positions `x_n ∈ [0,1]^3` as `[f64; 3]` (values outside are legal and
//!   wrap exactly as tiny-cuda-nn's index arithmetic does);
//! - `out` is `[M, L*F]` row-major (point-major, then level, then feature);
//! - the table is `[entries, F]` (level-major, then entry, then feature), `offsets[l]` is the
//!   first entry of level l (`offsets[L]` = total entries);
//! - backward passes *accumulate* into their outputs.
//!
//! # Numerics (checked against tiny-cuda-nn `encodings/grid.h`, `common_device.h`)
//! ```text
//! log2b   = log2f((float)b)                              (f32, as tcnn's host code)
//! scale_l = exp2f(l * log2b) * N0 - 1                    (f32; product then difference)
//! res_l   = (u32)ceilf(scale_l) + 1
//! size_l  = min(next_multiple_of_8(min(res_l^3, 2^31-1)), 2^T_l)
//! dense_l = res_l <= 1625 && res_l^3 <= size_l           (else hashed, size_l = 2^T_l)
//! p = fma(scale_l, x, 0.5); c = (u32)(i32)floor(p); t = p - c   (exact; the i32 conversion
//!                                             saturates, NaN → i32::MIN, output NaN)
//! w = t | t*t*(3-2t) ;  corner k: bit d of k → c_d+1 with w_d, else c_d with 1-w_d
//! weight_k = ((w_0' * w_1') * w_2')                      (d = 0, 1, 2 order; tcnn starts at 1*)
//! index_k  = dense:  (c_x + c_y*res + c_z*res^2) mod size   (u32 wrapping, no clamping:
//!                                                     the +1 corner at the upper face wraps)
//!            hashed: (c_x ^ c_y*2654435761 ^ c_z*805459861) mod 2^T_l (u32 wrapping)
//! T_l = T for every level (tiny-cuda-nn), or `log2_table_sizes[l]` (a documented extension)
//! out[l*F+f] = fma(w_7, v_7, … fma(w_1, v_1, fma(w_0, v_0, 0)))     (k order)
//! ```
//! Precision modes: [`PositionMode::Tcnn`] rounds `x` to f32 and computes `p` with an f32 FMA, so
//! with `R = f32` the forward pass is bit-identical to tiny-cuda-nn's fp32 build given the same
//! scale table (its device `exp2f` under fast-math may differ from ours by an ulp; that is why
//! the scale table is saved with the model). [`PositionMode::F64`] computes `p` with an f64 FMA
//! from the f64 position and hands only the exact fraction `t` (rounded once to `R`) to the model
//! float: fine levels of km-scale scenes keep their sub-cell precision in an f32 model. Weights and
//! interpolation are in `R` in both modes (f64 throughout for an f64 model).
//!
//! Backward into the table: `d_table[index_k*F+f] += weight_k * d_out[l*F+f]` (product rounded,
//! then added — the value tcnn hands to its atomic add). Backward into positions follows tcnn's
//! `dy_dx` formula: for each axis d and the four edges along d,
//! `g[f][d] += ((scale * w_a') * w_b') * (v_right - v_left) * dw_d/dt`, then
//! `d_x[d] += Σ_{l,f} d_out[l*F+f] * g[f][d]` in (l, f) order, accumulated with `mul_add`.
//! These gradients are deterministic but not claimed bit-identical to tcnn (nvcc contracts
//! those expressions into FMAs at its discretion, and tcnn's table gradient uses atomics).
//!
//! # Determinism and parallelism (SPEC §5)
//! `forward` and `backward_points` run in parallel over chunks of [`CHUNK_POINTS`] points (a
//! constant); every output element is written by exactly one chunk. `backward_table` walks the
//! points in sequential chunks of [`BWD_TABLE_CHUNK`] and, inside a chunk, runs the levels in
//! parallel: each level's slice of the table is disjoint and is accumulated in point order, so
//! the result is bit-identical for any thread count, with no atomics.
//!
//! # Speed
//! Within a chunk the work is level-major (one level's constants in registers, one level's table
//! slice hot in cache) and F and the dense/hashed choice are compile-time in the inner loops.
//! Points go through in blocks of 64: pass 1 computes cells, weights and corner indices for the
//! whole block in structure-of-arrays form (vectorised by the compiler) and prefetches the table
//! rows; pass 2 gathers/scatters, so many cache misses are in flight at once (the `cpu` preset's
//! table is 49 MB). A point in the same cell as the point before it (a pixel's γ² sub-samples;
//! neighbouring pixels at the coarse levels) has the same corner rows: the forward pass issues no
//! prefetch for it and the scalar pass 2 reuses the rows it holds. For f32 tables with F = 2 (every
//! preset's grids) and AVX2, the forward's pass 2 runs four points per vector
//! (`x86::interp_f32x2`, the same fma chain per lane). The kernels are compiled twice, for baseline x86-64 and with `fma,avx2`,
//! selected at run time (`is_x86_feature_detected!`); both give identical bits (an FMA is exactly
//! rounded whether done in hardware or by libm; without the feature `mul_add` is a slow libm
//! call). No per-call allocation beyond a few per-level descriptors; the touched bitmap of
//! `backward_table` is a reused thread-local buffer.

use crate::model::config::{GridConfig, Interpolation, PositionMode};
use crate::model::Real;
use crate::rng::{self, Purpose};
use anyhow::{bail, ensure};
use rayon::prelude::*;
use std::cell::RefCell;

/// Points per parallel work item in `forward` and `backward_points` (a constant, SPEC §5).
pub const CHUNK_POINTS: usize = 512;
/// Points per sequential step of `backward_table` (levels run in parallel inside a step).
pub const BWD_TABLE_CHUNK: usize = 16384;
/// tiny-cuda-nn's `MAX_BASES[3]`: the largest resolution whose dense index cannot overflow u32.
pub const MAX_DENSE_RESOLUTION: u32 = 0x659;
/// tiny-cuda-nn's coherent-prime hash factors for y and z (x uses 1).
pub const PRIME_Y: u32 = 2_654_435_761;
pub const PRIME_Z: u32 = 805_459_861;
/// tiny-cuda-nn's `MAX_N_LEVELS`.
pub const MAX_LEVELS: u32 = 128;
/// The largest per-level scale a grid holds: `p = scale·x + 0.5` must fit an i32 for x in [0, 1].
pub const MAX_SCALE: f32 = 1.0e9;

/// Geometry of a grid: per-level scales (saved with the model), resolutions, sizes, dense flags.
#[derive(Clone, Debug, PartialEq)]
pub struct HashGrid {
    pub cfg: GridConfig,
    /// `scale_l` (f32), as saved in `grid_*.scales`.
    pub scales: Vec<f32>,
    /// `res_l = ceil(scale_l) + 1`.
    pub resolutions: Vec<u32>,
    /// First entry of each level, and the total at the end (`grid_*.offsets`, L+1 values).
    pub offsets: Vec<u32>,
    /// Whether level l is indexed densely (no hashing).
    pub dense: Vec<bool>,
}

/// The set of table entries a backward pass wrote to, so Adam and gradient zeroing cost what the
/// batch touched rather than the table size (SPEC §4.8, §8).
///
/// `backward_table` keeps `entries` sorted ascending and unique, and merges into what is already
/// there (several backward calls in one step give the union). A point-level whose `d_out` slice
/// is entirely zero contributes nothing and is not recorded; otherwise all 8 corners are
/// recorded, including a corner whose interpolation weight is exactly 0 (its gradient
/// contribution is then 0; Adam skips entries whose gradient is exactly zero anyway, SPEC §4.8).
/// The caller clears `entries` when it zeroes the gradient.
#[derive(Clone, Debug, Default)]
pub struct Touched {
    /// Entry indices (each entry is F floats), unique, in a deterministic order.
    pub entries: Vec<u32>,
}

/// Check a grid configuration: what `HashGrid::try_new` accepts.
pub fn validate_config(cfg: &GridConfig) -> anyhow::Result<()> {
    ensure!(
        (1..=MAX_LEVELS).contains(&cfg.levels),
        "grid: levels = {} must be in 1..={MAX_LEVELS}",
        cfg.levels
    );
    ensure!(
        matches!(cfg.features, 1 | 2 | 4 | 8),
        "grid: features = {} must be one of 1, 2, 4, 8",
        cfg.features
    );
    ensure!(
        cfg.log2_table_size <= 31,
        "grid: log2_table_size = {} must be at most 31",
        cfg.log2_table_size
    );
    if let Some(t) = &cfg.log2_table_sizes {
        ensure!(
            t.len() == cfg.levels as usize,
            "grid: log2_table_sizes has {} values, expected one per level ({})",
            t.len(),
            cfg.levels
        );
        if let Some((l, v)) = t.iter().enumerate().find(|(_, &v)| v > 31) {
            bail!("grid: log2_table_sizes[{l}] = {v} must be at most 31");
        }
    }
    ensure!(
        cfg.base_resolution.is_finite() && cfg.base_resolution >= 1.0,
        "grid: base_resolution = {} must be a finite number >= 1",
        cfg.base_resolution
    );
    ensure!(
        cfg.per_level_scale.is_finite() && cfg.per_level_scale > 0.0,
        "grid: per_level_scale = {} must be a finite number > 0",
        cfg.per_level_scale
    );
    Ok(())
}

/// The first level (and its scale) whose scale [`tcnn_scales`] makes one a grid cannot hold
/// (outside [0, 1e9], as [`HashGrid::with_scales`] requires): a `per_level_scale` below 1 makes
/// the finer levels' negative.
pub fn first_bad_scale(cfg: &GridConfig) -> Option<(usize, f32)> {
    tcnn_scales(cfg)
        .into_iter()
        .enumerate()
        .find(|(_, s)| !(s.is_finite() && (0.0..=MAX_SCALE).contains(s)))
}

/// The per-level scales exactly as tiny-cuda-nn computes them on the host:
/// `log2b = log2f((float)b)`, `scale_l = exp2f(l * log2b) * N0 - 1.0f`, all in f32.
/// (On the device nvcc may fuse `* N0 - 1` into an FMA; for power-of-two N0, as in every preset,
/// the product is exact and both agree.)
pub fn tcnn_scales(cfg: &GridConfig) -> Vec<f32> {
    let log2b = (cfg.per_level_scale as f32).log2();
    (0..cfg.levels)
        .map(|l| (l as f32 * log2b).exp2() * cfg.base_resolution - 1.0)
        .collect()
}

/// `min(next_multiple_of_8(min(res^3, 2^31-1)), 2^T)` (tcnn's `params_in_level` for a hash grid;
/// with per-level sizes, `T = T_l`).
pub fn level_size(res: u32, log2_table_size: u32) -> u32 {
    // Saturating: res^3 overflows u64 from res = 2^21.34 (scales up to 1e9 are valid), and a
    // wrapped cube made the level 0 entries long (found by cargo fuzz, checkpoint target).
    let cube = (res as u64).saturating_pow(3);
    let capped = cube.min((u32::MAX / 2) as u64);
    let padded = capped.div_ceil(8) * 8;
    padded.min(1u64 << log2_table_size) as u32
}

/// `n` values U(-1e-4, 1e-4) from the counter-based generator (`Purpose::InitTable`,
/// a = `tensor_id`, b = element index; `-1e-4 + 2e-4*u` in f64, rounded once to f32): the
/// initialisation of every feature table (hash grids, vertex features).
pub fn init_uniform_table(n: usize, seed: u64, tensor_id: u64) -> Vec<f32> {
    const INIT_CHUNK: usize = 1 << 16;
    let init = TableInit::new(seed, tensor_id);
    let mut t = vec![0.0f32; n];
    t.par_chunks_mut(INIT_CHUNK)
        .enumerate()
        .for_each(|(ci, c)| {
            for (j, v) in c.iter_mut().enumerate() {
                *v = init.value((ci * INIT_CHUNK + j) as u64);
            }
        });
    t
}

/// Element `e` of [`init_uniform_table`].
#[inline]
pub fn init_value(seed: u64, tensor_id: u64, e: u64) -> f32 {
    TableInit::new(seed, tensor_id).value(e)
}

/// The initial values of one table ([`init_value`] with the seed and tensor id fixed, drawn
/// once): a loader completing a table stored by its stepped rows draws the others one by one
/// (`model/checkpoint.rs`).
#[derive(Clone, Copy, Debug)]
pub struct TableInit(rng::Keyed);

impl TableInit {
    #[inline]
    pub fn new(seed: u64, tensor_id: u64) -> TableInit {
        TableInit(rng::Keyed::new(seed, Purpose::InitTable, tensor_id))
    }

    /// Element `e`: `f32(-1e-4 + 2e-4 · uniform_f64(seed, InitTable, tensor_id, e))`.
    #[inline]
    pub fn value(self, e: u64) -> f32 {
        (-1e-4 + 2e-4 * self.0.uniform_f64(e)) as f32
    }
}

impl HashGrid {
    /// Scales computed as tiny-cuda-nn does (log2(b) in f32). Panics on an invalid config (see
    /// [`validate_config`]; use [`HashGrid::try_new`] to get an error instead).
    pub fn new(cfg: &GridConfig) -> HashGrid {
        HashGrid::try_new(cfg).unwrap_or_else(|e| panic!("{e:#}"))
    }

    /// As [`HashGrid::new`], returning an error for an invalid config.
    pub fn try_new(cfg: &GridConfig) -> anyhow::Result<HashGrid> {
        validate_config(cfg)?;
        HashGrid::with_scales(cfg, tcnn_scales(cfg))
    }

    /// From a saved scale table (a loader never recomputes scales).
    pub fn with_scales(cfg: &GridConfig, scales: Vec<f32>) -> anyhow::Result<HashGrid> {
        validate_config(cfg)?;
        ensure!(
            scales.len() == cfg.levels as usize,
            "grid: scale table has {} values, expected one per level ({})",
            scales.len(),
            cfg.levels
        );
        let mut resolutions = Vec::with_capacity(scales.len());
        let mut offsets = Vec::with_capacity(scales.len() + 1);
        let mut dense = Vec::with_capacity(scales.len());
        let mut total: u64 = 0;
        for (l, &s) in scales.iter().enumerate() {
            if !(s.is_finite() && (0.0..=MAX_SCALE).contains(&s)) {
                bail!("grid: scale of level {l} is {s}, expected a finite number in [0, 1e9]");
            }
            let res = s.ceil() as u32 + 1;
            let size = level_size(res, cfg.log2_table_size_of(l));
            resolutions.push(res);
            dense
                .push(res <= MAX_DENSE_RESOLUTION && (res as u64).saturating_pow(3) <= size as u64);
            offsets.push(total as u32);
            total += size as u64;
            ensure!(
                total <= u32::MAX as u64,
                "grid: {total} entries up to level {l} do not fit the u32 offset table"
            );
        }
        offsets.push(total as u32);
        Ok(HashGrid {
            cfg: cfg.clone(),
            scales,
            resolutions,
            offsets,
            dense,
        })
    }

    /// Output width L*F.
    pub fn out_dim(&self) -> usize {
        (self.cfg.levels * self.cfg.features) as usize
    }
    /// Total entries over all levels.
    pub fn n_entries(&self) -> usize {
        *self.offsets.last().unwrap_or(&0) as usize
    }
    /// Parameter count: entries × F.
    pub fn n_params(&self) -> usize {
        self.n_entries() * self.cfg.features as usize
    }
    /// Entries of level l.
    pub fn level_entries(&self, l: usize) -> usize {
        (self.offsets[l + 1] - self.offsets[l]) as usize
    }

    /// Initial table, U(-1e-4, 1e-4) from the counter-based generator
    /// (`Purpose::InitTable`, a = tensor_id, b = element index; `-1e-4 + 2e-4*u` in f64, rounded
    /// once to f32).
    pub fn init_table(&self, seed: u64, tensor_id: u64) -> Vec<f32> {
        init_uniform_table(self.n_params(), seed, tensor_id)
    }

    /// The 8 corners of `x` at level `l`: global entry indices (`offsets[l] + local`) and
    /// interpolation weights, in corner order k (bit d of k set = upper corner along axis d).
    ///
    /// This is the scalar *reference* of the passes: [`HashGrid::forward`] and the backward
    /// passes compute the same corners and weights with the `*_block` functions (the same
    /// operations in the same order, arranged one corner at a time over 64 points so the
    /// compiler vectorises them), then interpolate as an fma chain in corner order
    /// `acc = w_k·v_k + acc`, k = 0..8. A backend author can port this function and that chain;
    /// `corners_is_the_scalar_reference_of_the_passes` (tests/hashgrid.rs) ties them together
    /// bit for bit.
    pub fn corners<R: Real>(
        &self,
        l: usize,
        x: &[f64; 3],
        mode: PositionMode,
    ) -> ([u32; 8], [R; 8]) {
        let g = self.level(l, mode);
        let (c, t) = locate::<R>(g.scale, g.tcnn, x);
        let w = corner_weights(interp(t, g.smooth));
        let local = if g.dense {
            g.dense_ix().corners(c)
        } else {
            g.hash_ix().corners(c)
        };
        (local.map(|i| i + self.offsets[l]), w)
    }

    fn level(&self, l: usize, mode: PositionMode) -> Level {
        let size = self.offsets[l + 1] - self.offsets[l];
        let res = self.resolutions[l];
        Level {
            scale: self.scales[l],
            tcnn: mode == PositionMode::Tcnn,
            smooth: self.cfg.interpolation == Interpolation::Smoothstep,
            dense: self.dense[l],
            res,
            size,
            offset: self.offsets[l] as usize,
        }
    }

    /// Encode M points: `out[M, L*F]` (overwritten).
    pub fn forward<R: Real>(
        &self,
        table: &[R],
        points: &[[f64; 3]],
        mode: PositionMode,
        out: &mut [R],
    ) {
        self.forward_active(table, points, mode, out, &[])
    }

    /// [`HashGrid::forward`] evaluating, for point i, only its first `active[i]` levels (the
    /// others' outputs are 0 and their tables are not read); `active` empty = every level.
    pub fn forward_active<R: Real>(
        &self,
        table: &[R],
        points: &[[f64; 3]],
        mode: PositionMode,
        out: &mut [R],
        active: &[u8],
    ) {
        assert!(
            active.is_empty() || active.len() == points.len(),
            "hashgrid forward: active has {} entries for {} points",
            active.len(),
            points.len()
        );
        let lf = self.out_dim();
        assert_eq!(
            table.len(),
            self.n_params(),
            "hashgrid forward: table length"
        );
        assert_eq!(out.len(), points.len() * lf, "hashgrid forward: out length");
        let fast = has_fma();
        out.par_chunks_mut(CHUNK_POINTS * lf)
            .zip(points.par_chunks(CHUNK_POINTS))
            .enumerate()
            .for_each(|(ci, (o, p))| {
                let mut sc = BlockScratch::new();
                let act = if active.is_empty() {
                    &[][..]
                } else {
                    &active[ci * CHUNK_POINTS..ci * CHUNK_POINTS + p.len()]
                };
                for l in 0..self.cfg.levels as usize {
                    if !act.is_empty() && act.iter().all(|&a| a as usize <= l) {
                        // No point evaluates level l, hence none evaluates a finer one: their
                        // outputs are 0, written as one fill per row.
                        o.chunks_exact_mut(lf)
                            .for_each(|r| r[l * self.cfg.features as usize..].fill(R::ZERO));
                        break;
                    }
                    let g = self.level(l, mode);
                    let tab = &table[g.offset * self.cfg.features as usize..]
                        [..g.size as usize * self.cfg.features as usize];
                    kernels::forward_level(
                        fast,
                        self.cfg.features,
                        &g,
                        tab,
                        p,
                        o,
                        lf,
                        l,
                        act,
                        &mut sc,
                        fast,
                    );
                }
            });
    }

    /// Accumulate `d_table += ∂L/∂table` from `d_out[M, L*F]`, and record touched entries
    /// (merged into `touched`, sorted ascending, unique; see [`Touched`]).
    pub fn backward_table<R: Real>(
        &self,
        points: &[[f64; 3]],
        mode: PositionMode,
        d_out: &[R],
        d_table: &mut [R],
        touched: &mut Touched,
    ) {
        let lf = self.out_dim();
        let nf = self.cfg.features as usize;
        let nl = self.cfg.levels as usize;
        assert_eq!(
            d_table.len(),
            self.n_params(),
            "hashgrid backward_table: d_table length"
        );
        assert_eq!(
            d_out.len(),
            points.len() * lf,
            "hashgrid backward_table: d_out length"
        );
        let fast = has_fma();

        // Per-level touched bitmaps, each word-aligned, in one reusable all-zero buffer.
        let mut word_off = Vec::with_capacity(nl + 1);
        let mut nw = 0usize;
        for l in 0..nl {
            word_off.push(nw);
            nw += self.level_entries(l).div_ceil(64);
        }
        word_off.push(nw);
        let mut bits = BITMAP.with(|b| std::mem::take(&mut *b.borrow_mut()));
        if bits.len() < nw {
            bits.resize(nw, 0);
        }
        debug_assert!(bits.iter().all(|&w| w == 0));
        // Entries already recorded (an earlier backward in the same step) join the union.
        for &e in &touched.entries {
            let l = self.offsets.partition_point(|&o| o <= e) - 1;
            assert!(
                l < nl,
                "hashgrid backward_table: touched entry {e} is not in this grid"
            );
            let local = (e - self.offsets[l]) as usize;
            bits[word_off[l] + local / 64] |= 1u64 << (local % 64);
        }

        // Split the gradient and the bitmap into disjoint per-level slices.
        let mut work: Vec<(usize, &mut [R], &mut [u64])> = Vec::with_capacity(nl);
        {
            let mut dt_rest = &mut d_table[..];
            let mut bm_rest = &mut bits[..nw];
            for l in 0..nl {
                let (dt, r) = dt_rest.split_at_mut(self.level_entries(l) * nf);
                dt_rest = r;
                let (bm, r) = bm_rest.split_at_mut(word_off[l + 1] - word_off[l]);
                bm_rest = r;
                work.push((l, dt, bm));
            }
        }
        for (ci, p) in points.chunks(BWD_TABLE_CHUNK).enumerate() {
            let dout = &d_out[ci * BWD_TABLE_CHUNK * lf..][..p.len() * lf];
            work.par_iter_mut().for_each(|(l, dt, bm)| {
                let g = self.level(*l, mode);
                kernels::backward_table_level(fast, self.cfg.features, &g, p, dout, lf, *l, dt, bm);
            });
        }

        // Extract sorted unique entries, zeroing the bitmap as it is read: each level's bits are
        // counted, then every level writes its own slice of the list in parallel (the list is
        // the same as a serial walk over the levels in order).
        let level_bits: Vec<&mut [u64]> = work.into_iter().map(|(_, _, bm)| bm).collect();
        let counts: Vec<usize> = level_bits
            .par_iter()
            .map(|b| b.iter().map(|w| w.count_ones() as usize).sum())
            .collect();
        // The list is written in place of its spare capacity (no zero-fill first: 2.3 MB, serial,
        // for grid H's 567k entries per `cpu` step); every slot is written before `set_len`.
        let total: usize = counts.iter().sum();
        touched.entries.clear();
        touched.entries.reserve(total);
        let mut level_out: Vec<&mut [std::mem::MaybeUninit<u32>]> = Vec::with_capacity(nl);
        {
            let mut rest = &mut touched.entries.spare_capacity_mut()[..total];
            for &c in &counts {
                let (o, r) = rest.split_at_mut(c);
                rest = r;
                level_out.push(o);
            }
        }
        level_bits
            .into_par_iter()
            .zip(level_out)
            .enumerate()
            .for_each(|(l, (b, out))| {
                let base = self.offsets[l];
                let mut k = 0;
                for (wi, w) in b.iter_mut().enumerate() {
                    let mut m = *w;
                    *w = 0;
                    while m != 0 {
                        out[k].write(base + (wi as u32) * 64 + m.trailing_zeros());
                        k += 1;
                        m &= m - 1;
                    }
                }
                assert_eq!(k, out.len(), "hashgrid backward_table: touched count");
            });
        // SAFETY: the `total` slots after the (cleared) length were each written above: every
        // level wrote exactly its count (asserted), and the levels' slices tile `..total`.
        unsafe { touched.entries.set_len(total) };
        BITMAP.with(|b| *b.borrow_mut() = bits);
    }

    /// Accumulate `d_points[M, 3] += ∂L/∂x_n`.
    pub fn backward_points<R: Real>(
        &self,
        table: &[R],
        points: &[[f64; 3]],
        mode: PositionMode,
        d_out: &[R],
        d_points: &mut [R],
    ) {
        let lf = self.out_dim();
        let nf = self.cfg.features as usize;
        assert_eq!(
            table.len(),
            self.n_params(),
            "hashgrid backward_points: table length"
        );
        assert_eq!(
            d_out.len(),
            points.len() * lf,
            "hashgrid backward_points: d_out length"
        );
        assert_eq!(
            d_points.len(),
            points.len() * 3,
            "hashgrid backward_points: d_points length"
        );
        let fast = has_fma();
        d_points
            .par_chunks_mut(CHUNK_POINTS * 3)
            .zip(points.par_chunks(CHUNK_POINTS))
            .zip(d_out.par_chunks(CHUNK_POINTS * lf))
            .for_each(|((dp, p), dout)| {
                // Per-point sums over (l, f), added to d_points once at the end (tcnn order).
                let mut acc = [[R::ZERO; 3]; CHUNK_POINTS];
                for l in 0..self.cfg.levels as usize {
                    let g = self.level(l, mode);
                    let tab = &table[g.offset * nf..][..g.size as usize * nf];
                    kernels::backward_points_level(
                        fast,
                        self.cfg.features,
                        &g,
                        tab,
                        p,
                        dout,
                        lf,
                        l,
                        &mut acc,
                    );
                }
                for (d, a) in dp.chunks_exact_mut(3).zip(acc.iter()) {
                    d[0] += a[0];
                    d[1] += a[1];
                    d[2] += a[2];
                }
            });
    }
}

thread_local! {
    /// Reusable touched-entry bitmap of the thread that calls `backward_table` (all zero at rest).
    static BITMAP: RefCell<Vec<u64>> = const { RefCell::new(Vec::new()) };
}

static FORCE_PORTABLE: std::sync::atomic::AtomicBool = std::sync::atomic::AtomicBool::new(false);

/// Use the baseline (portable) build of the kernels even where `fma,avx2` is available. For
/// tests, which check that both builds give identical bits; process-wide.
#[doc(hidden)]
pub fn force_portable_kernels(on: bool) {
    FORCE_PORTABLE.store(on, std::sync::atomic::Ordering::Relaxed);
}

/// Whether the `fma,avx2` build of the kernels can run here (checked once, cached by std).
#[inline]
fn has_fma() -> bool {
    if FORCE_PORTABLE.load(std::sync::atomic::Ordering::Relaxed) {
        return false;
    }
    #[cfg(any(target_arch = "x86", target_arch = "x86_64"))]
    {
        std::arch::is_x86_feature_detected!("fma") && std::arch::is_x86_feature_detected!("avx2")
    }
    #[cfg(not(any(target_arch = "x86", target_arch = "x86_64")))]
    {
        false
    }
}

/// Per-level constants of one pass.
#[derive(Clone, Copy, Debug)]
struct Level {
    scale: f32,
    tcnn: bool,
    smooth: bool,
    dense: bool,
    res: u32,
    size: u32,
    /// First entry of the level.
    offset: usize,
}

impl Level {
    #[inline(always)]
    fn dense_ix(&self) -> DenseIx {
        DenseIx {
            res: self.res,
            res2: self.res.wrapping_mul(self.res),
            size: self.size,
            magic: (u64::MAX / self.size as u64).wrapping_add(1),
        }
    }
    #[inline(always)]
    fn hash_ix(&self) -> HashIx {
        debug_assert!(self.size.is_power_of_two());
        HashIx {
            mask: self.size - 1,
        }
    }
}

/// Cell and fraction of one point at one level: `p = fma(scale, x, 0.5)`, `c = floor(p)`,
/// `t = p - c` (exact in the precision of `p`), `t` then rounded once to `R`.
#[inline(always)]
fn locate<R: Real>(scale: f32, tcnn: bool, x: &[f64; 3]) -> ([u32; 3], [R; 3]) {
    let mut c = [0u32; 3];
    let mut t = [R::ZERO; 3];
    if tcnn {
        for d in 0..3 {
            let p = scale.mul_add(x[d] as f32, 0.5);
            let fl = p.floor();
            c[d] = to_i32_clamped(fl as f64) as u32;
            t[d] = R::from_f32(p - fl);
        }
    } else {
        let s = scale as f64;
        for d in 0..3 {
            let p = s.mul_add(x[d], 0.5);
            let fl = p.floor();
            c[d] = to_i32_clamped(fl) as u32;
            t[d] = R::from_f64(p - fl);
        }
    }
    (c, t)
}

/// `v as i32` for an integer-valued `v`: saturating at the i32 range like `as i32` (and like
/// CUDA's float→int conversion); NaN → i32::MIN (the output is NaN anyway, as t is NaN).
/// Cheaper than Rust's `as` once vectorised. Used by both the scalar and the block paths.
#[inline(always)]
fn to_i32_clamped(v: f64) -> i32 {
    let v = v.max(i32::MIN as f64).min(i32::MAX as f64);
    // SAFETY: v is finite and within the i32 range after the clamp (max/min drop NaN).
    unsafe { v.to_int_unchecked::<i32>() }
}

/// `w(t)`: t (linear) or `(t*t)*(3-2t)` (smoothstep).
#[inline(always)]
fn interp<R: Real>(t: [R; 3], smooth: bool) -> [R; 3] {
    if smooth {
        let three = R::from_f32(3.0);
        let two = R::from_f32(2.0);
        t.map(|t| t * t * (three - two * t))
    } else {
        t
    }
}

/// Trilinear corner weights in corner order k, each the product in axis order d = 0, 1, 2.
#[inline(always)]
fn corner_weights<R: Real>(w: [R; 3]) -> [R; 8] {
    let a = [
        [R::ONE - w[0], w[0]],
        [R::ONE - w[1], w[1]],
        [R::ONE - w[2], w[2]],
    ];
    let mut out = [R::ZERO; 8];
    for (k, o) in out.iter_mut().enumerate() {
        *o = a[0][k & 1] * a[1][(k >> 1) & 1] * a[2][k >> 2];
    }
    out
}

/// Corner index of a level (local entry index, < size).
trait Indexer: Copy {
    fn corners(self, c: [u32; 3]) -> [u32; 8];
}

/// Dense level: `(x + y*res + z*res^2) mod size`, u32 wrapping.
#[derive(Clone, Copy)]
struct DenseIx {
    res: u32,
    res2: u32,
    size: u32,
    /// Lemire's fastmod constant `floor((2^64-1)/size) + 1` (exact `a mod size` for all u32 a).
    magic: u64,
}

#[inline(always)]
fn fastmod(a: u32, magic: u64, d: u32) -> u32 {
    let low = magic.wrapping_mul(a as u64);
    ((low as u128 * d as u128) >> 64) as u32
}

impl Indexer for DenseIx {
    #[inline(always)]
    fn corners(self, c: [u32; 3]) -> [u32; 8] {
        let xs = [c[0], c[0].wrapping_add(1)];
        let ys = [
            c[1].wrapping_mul(self.res),
            c[1].wrapping_add(1).wrapping_mul(self.res),
        ];
        let zs = [
            c[2].wrapping_mul(self.res2),
            c[2].wrapping_add(1).wrapping_mul(self.res2),
        ];
        let mut out = [0u32; 8];
        for (k, o) in out.iter_mut().enumerate() {
            let i = xs[k & 1]
                .wrapping_add(ys[(k >> 1) & 1])
                .wrapping_add(zs[k >> 2]);
            *o = fastmod(i, self.magic, self.size);
        }
        out
    }
}

/// Hashed level: `(x ^ y*PRIME_Y ^ z*PRIME_Z) mod 2^T`, u32 wrapping.
#[derive(Clone, Copy)]
struct HashIx {
    mask: u32,
}

impl Indexer for HashIx {
    #[inline(always)]
    fn corners(self, c: [u32; 3]) -> [u32; 8] {
        let xs = [c[0], c[0].wrapping_add(1)];
        let ys = [
            c[1].wrapping_mul(PRIME_Y),
            c[1].wrapping_add(1).wrapping_mul(PRIME_Y),
        ];
        let zs = [
            c[2].wrapping_mul(PRIME_Z),
            c[2].wrapping_add(1).wrapping_mul(PRIME_Z),
        ];
        let mut out = [0u32; 8];
        for (k, o) in out.iter_mut().enumerate() {
            *o = (xs[k & 1] ^ ys[(k >> 1) & 1] ^ zs[k >> 2]) & self.mask;
        }
        out
    }
}

/// Corner indices of a block of points, one corner at a time over all points (SoA, so the
/// compiler can vectorise the hash).
trait BlockIndexer: Indexer {
    fn corners_block(self, n: usize, c: &[[u32; BLOCK]; 3], idx: &mut [[u32; BLOCK]; 8]);
}

impl BlockIndexer for HashIx {
    #[inline(always)]
    fn corners_block(self, n: usize, c: &[[u32; BLOCK]; 3], idx: &mut [[u32; BLOCK]; 8]) {
        for (k, row) in idx.iter_mut().enumerate() {
            let (bx, by, bz) = ((k & 1) as u32, ((k >> 1) & 1) as u32, (k >> 2) as u32);
            for j in 0..n {
                let x = c[0][j].wrapping_add(bx);
                let y = c[1][j].wrapping_add(by).wrapping_mul(PRIME_Y);
                let z = c[2][j].wrapping_add(bz).wrapping_mul(PRIME_Z);
                row[j] = (x ^ y ^ z) & self.mask;
            }
        }
    }
}

impl BlockIndexer for DenseIx {
    #[inline(always)]
    fn corners_block(self, n: usize, c: &[[u32; BLOCK]; 3], idx: &mut [[u32; BLOCK]; 8]) {
        // Fast path: for x in [0,1] every corner index is below 2*size (c_d <= res-1, so the
        // index is at most res + res^2 + res^3 < 2 res^3 <= 2 size), and `mod size` is one
        // conditional subtraction. If any lane of the block falls outside, redo the block with
        // the exact general modulo. Same results either way (wrapping adds are associative).
        let mut base = [0u32; BLOCK];
        for j in 0..n {
            base[j] = c[0][j]
                .wrapping_add(c[1][j].wrapping_mul(self.res))
                .wrapping_add(c[2][j].wrapping_mul(self.res2));
        }
        let mut ok = true;
        for (k, row) in idx.iter_mut().enumerate() {
            let off = (k & 1) as u32
                + if (k >> 1) & 1 == 1 { self.res } else { 0 }
                + if k >> 2 == 1 { self.res2 } else { 0 };
            for j in 0..n {
                let i = base[j].wrapping_add(off);
                let r = if i >= self.size {
                    i.wrapping_sub(self.size)
                } else {
                    i
                };
                ok &= r < self.size;
                row[j] = r;
            }
        }
        if ok {
            return;
        }
        for j in 0..n {
            let ids = self.corners([c[0][j], c[1][j], c[2][j]]);
            for k in 0..8 {
                idx[k][j] = ids[k];
            }
        }
    }
}

/// Points prepared together (corners computed and table rows prefetched before they are
/// gathered): enough independent cache misses in flight to hide most of the latency of a table
/// that does not fit the cache. Does not affect results.
const BLOCK: usize = 64;

/// The block loops run over `xs.len()` rounded up to a multiple of 8 (a runtime bound, so the
/// compiler emits one vector loop instead of unrolling 64 iterations); lanes past `xs.len()`
/// are computed from x = 0 and ignored.
#[inline(always)]
fn block_len(n: usize) -> usize {
    n.next_multiple_of(8).min(BLOCK)
}

/// `locate` for a block, SoA: `c[d][j]`, `t[d][j]` for `j < block_len(xs.len())`. `xd` is
/// scratch (the points transposed; the padding lanes set to 0).
#[inline(always)]
fn locate_block<R: Real>(
    scale: f32,
    tcnn: bool,
    xs: &[[f64; 3]],
    xd: &mut [[f64; BLOCK]; 3],
    c: &mut [[u32; BLOCK]; 3],
    t: &mut [[R; BLOCK]; 3],
) {
    let n = block_len(xs.len());
    for (j, x) in xs.iter().enumerate() {
        xd[0][j] = x[0];
        xd[1][j] = x[1];
        xd[2][j] = x[2];
    }
    for row in xd.iter_mut() {
        row[xs.len()..n].fill(0.0);
    }
    for d in 0..3 {
        if tcnn {
            for j in 0..n {
                let p = scale.mul_add(xd[d][j] as f32, 0.5);
                let fl = p.floor();
                c[d][j] = to_i32_clamped(fl as f64) as u32;
                t[d][j] = R::from_f32(p - fl);
            }
        } else {
            let s = scale as f64;
            for j in 0..n {
                let p = s.mul_add(xd[d][j], 0.5);
                let fl = p.floor();
                c[d][j] = to_i32_clamped(fl) as u32;
                t[d][j] = R::from_f64(p - fl);
            }
        }
    }
}

/// Per-axis `w(t)` (in place) and, if asked, `dw/dt`, for a block.
#[inline(always)]
fn interp_block<R: Real>(
    n: usize,
    smooth: bool,
    t: &mut [[R; BLOCK]; 3],
    dw: Option<&mut [[R; BLOCK]; 3]>,
) {
    if !smooth {
        if let Some(dw) = dw {
            *dw = [[R::ONE; BLOCK]; 3];
        }
        return;
    }
    let (two, three, six) = (R::from_f32(2.0), R::from_f32(3.0), R::from_f32(6.0));
    if let Some(dw) = dw {
        for d in 0..3 {
            for j in 0..n {
                let v = t[d][j];
                dw[d][j] = six * v * (R::ONE - v);
            }
        }
    }
    for row in t.iter_mut() {
        for v in row[..n].iter_mut() {
            *v = *v * *v * (three - two * *v);
        }
    }
}

/// Trilinear corner weights for a block: `w8[k][j]`, each the product in axis order 0, 1, 2
/// (`om` is scratch: `1 − w`).
#[inline(always)]
fn corner_weights_block<R: Real>(
    n: usize,
    w: &[[R; BLOCK]; 3],
    om: &mut [[R; BLOCK]; 3],
    w8: &mut [[R; BLOCK]; 8],
) {
    for d in 0..3 {
        for j in 0..n {
            om[d][j] = R::ONE - w[d][j];
        }
    }
    for (k, row) in w8.iter_mut().enumerate() {
        let a = if k & 1 == 1 { &w[0] } else { &om[0] };
        let b = if (k >> 1) & 1 == 1 { &w[1] } else { &om[1] };
        let c = if k >> 2 == 1 { &w[2] } else { &om[2] };
        for j in 0..n {
            row[j] = a[j] * b[j] * c[j];
        }
    }
}

/// The forward kernel's per-block arrays, made once per chunk of points and kept across its
/// levels and blocks: a block writes every lane it reads before reading it, so nothing is cleared
/// between blocks (clearing these ~10 KB for every block of every level was a visible share of a
/// render's time).
pub(crate) struct BlockScratch<R> {
    xd: [[f64; BLOCK]; 3],
    c: [[u32; BLOCK]; 3],
    w: [[R; BLOCK]; 3],
    om: [[R; BLOCK]; 3],
    idx: [[u32; BLOCK]; 8],
    w8: [[R; BLOCK]; 8],
}

impl<R: Real> BlockScratch<R> {
    pub(crate) fn new() -> Self {
        BlockScratch {
            xd: [[0.0; BLOCK]; 3],
            c: [[0; BLOCK]; 3],
            w: [[R::ZERO; BLOCK]; 3],
            om: [[R::ZERO; BLOCK]; 3],
            idx: [[0; BLOCK]; 8],
            w8: [[R::ZERO; BLOCK]; 8],
        }
    }
}

use crate::memhint::prefetch_l2;

/// Prefetch the table rows of point j's corners into L2. A block's pass 1 issues these for all
/// its points before pass 2 gathers them, far more lines than L1's miss buffers hold, so they go
/// to L2 (`prefetcht1`), which keeps many more misses in flight. All eight corners: the
/// x-neighbours k and k+1 usually share a line, but not always (a carry out of the low index
/// bits), and prefetching only the even ones was measured slower (`docs/performance.md`).
#[inline(always)]
fn prefetch_corners<R, const F: usize>(tab: &[R], idx: &[[u32; BLOCK]; 8], j: usize) {
    for row in idx {
        prefetch_l2(tab.as_ptr().wrapping_add(row[j] as usize * F));
    }
}

/// Hand-vectorised pieces of the kernels (x86-64 with AVX2 and FMA, selected at run time).
#[cfg(target_arch = "x86_64")]
mod x86 {
    use super::BLOCK;
    use std::arch::x86_64::*;

    /// Pass 2 of the forward kernel for an f32 table with F = 2 (a row is 8 bytes): for each
    /// point j < n with `live[j]` set (−1), `out[j·lf .. j·lf + 2] = Σ_k w8[k][j] · row(idx[k][j])`
    /// as the fma chain in corner order from +0, exactly the scalar pass's operations, four points
    /// at a time; a point j < n with `live[j] = 0` gets +0, as in the scalar pass. A group of four
    /// with no live point reads no row; in a mixed group the other lanes' rows are read too and
    /// their results cleared. Rows are fetched with plain 8-byte loads: `vgatherdpd` gave the same
    /// bits but took ~9 % more CPU time for the render (Zen 4, 2026-11-29), though it is fewer
    /// instructions.
    ///
    /// # Safety
    /// fma and avx2 are available; `live` is −1 or 0, and 0 from n to n rounded up to 4; for every
    /// j below n rounded up to 4, `tab + 2·idx[k][j]` is two readable floats; for j < n,
    /// `out + j·lf` is two writable floats.
    #[target_feature(enable = "avx2,fma")]
    pub(super) unsafe fn interp_f32x2(
        tab: *const f32,
        idx: &[[u32; BLOCK]; 8],
        w8: &[[f32; BLOCK]; 8],
        live: &[i64; BLOCK],
        n: usize,
        out: *mut f32,
        lf: usize,
    ) {
        let dup = _mm256_setr_epi32(0, 0, 1, 1, 2, 2, 3, 3);
        let mut j = 0;
        while j < n {
            // SAFETY: j + 4 <= BLOCK (n <= BLOCK, j a multiple of 4 below n), so the
            // four-lane reads of `live`, `idx` and `w8` are in bounds; every row read is at an
            // index of a lane below n rounded up to 4, and the stores write points < n only (the
            // caller's promises).
            unsafe {
                let mask = _mm256_loadu_pd(live.as_ptr().add(j) as *const f64);
                let any = _mm256_movemask_pd(mask) != 0;
                let mut acc = _mm256_setzero_ps();
                if any {
                    let t = tab as *const f64;
                    for k in 0..8 {
                        let ix = &idx[k];
                        let a = _mm_loadh_pd(
                            _mm_load_sd(t.add(ix[j] as usize)),
                            t.add(ix[j + 1] as usize),
                        );
                        let b = _mm_loadh_pd(
                            _mm_load_sd(t.add(ix[j + 2] as usize)),
                            t.add(ix[j + 3] as usize),
                        );
                        let v = _mm256_insertf128_pd::<1>(_mm256_castpd128_pd256(a), b);
                        let w4 = _mm_loadu_ps(w8[k].as_ptr().add(j));
                        let w = _mm256_permutevar8x32_ps(_mm256_castps128_ps256(w4), dup);
                        acc = _mm256_fmadd_ps(w, _mm256_castpd_ps(v), acc);
                    }
                }
                let acc = _mm256_castps_pd(_mm256_and_ps(acc, _mm256_castpd_ps(mask)));
                let (lo, hi) = (_mm256_castpd256_pd128(acc), _mm256_extractf128_pd::<1>(acc));
                let row = |q: usize| out.add((j + q) * lf) as *mut f64;
                _mm_store_sd(row(0), lo);
                if j + 1 < n {
                    _mm_storeh_pd(row(1), lo);
                }
                if j + 2 < n {
                    _mm_store_sd(row(2), hi);
                }
                if j + 3 < n {
                    _mm_storeh_pd(row(3), hi);
                }
            }
            j += 4;
        }
    }
}

/// The inner loops, generic over R, F and the indexer, with a runtime-selected `fma,avx2` build.
#[allow(clippy::needless_range_loop)] // index loops over SoA blocks read best as they are
mod kernels {
    use super::*;

    /// Calls `$body` with `$F` bound to the const feature count and `$ix` to the level's indexer.
    macro_rules! dispatch {
        ($nf:expr, $g:expr, |$F:ident, $ix:ident| $body:expr) => {
            match ($nf, $g.dense) {
                (1, true) => {
                    const $F: usize = 1;
                    let $ix = $g.dense_ix();
                    $body
                }
                (1, false) => {
                    const $F: usize = 1;
                    let $ix = $g.hash_ix();
                    $body
                }
                (2, true) => {
                    const $F: usize = 2;
                    let $ix = $g.dense_ix();
                    $body
                }
                (2, false) => {
                    const $F: usize = 2;
                    let $ix = $g.hash_ix();
                    $body
                }
                (4, true) => {
                    const $F: usize = 4;
                    let $ix = $g.dense_ix();
                    $body
                }
                (4, false) => {
                    const $F: usize = 4;
                    let $ix = $g.hash_ix();
                    $body
                }
                (8, true) => {
                    const $F: usize = 8;
                    let $ix = $g.dense_ix();
                    $body
                }
                (8, false) => {
                    const $F: usize = 8;
                    let $ix = $g.hash_ix();
                    $body
                }
                _ => unreachable!("features validated to 1, 2, 4, 8"),
            }
        };
    }

    /// Defines `$name` (runtime switch), `$name_fma` (`fma,avx2` build) and `$name_plain`
    /// around the generic `$imp::<R, F, I>`. Both builds compute identical bits.
    macro_rules! kernel {
        ($name:ident, $fma:ident, $plain:ident, $imp:ident, ($($arg:ident : $ty:ty),*)) => {
            // A hot kernel (inner loop of a step): its arguments are the buffers and sizes it works on,
            // llm.c style; kept as they are rather than re-measure its speed behind a struct.
            #[allow(clippy::too_many_arguments)]
            pub(super) fn $name<R: Real>(fast: bool, nf: u32, g: &Level, $($arg: $ty),*) {
                #[cfg(any(target_arch = "x86", target_arch = "x86_64"))]
                {
                    if fast {
                        // SAFETY: `fast` is true only if the CPU reports fma and avx2.
                        return unsafe { $fma::<R>(nf, g, $($arg),*) };
                    }
                }
                let _ = fast;
                $plain::<R>(nf, g, $($arg),*)
            }

            #[cfg(any(target_arch = "x86", target_arch = "x86_64"))]
            #[target_feature(enable = "fma,avx2")]
            // A hot kernel (inner loop of a step): its arguments are the buffers and sizes it works on,
            // llm.c style; kept as they are rather than re-measure its speed behind a struct.
            #[allow(clippy::too_many_arguments)]
            unsafe fn $fma<R: Real>(nf: u32, g: &Level, $($arg: $ty),*) {
                dispatch!(nf, g, |F, ix| $imp::<R, F, _>(g, ix, $($arg),*))
            }

            #[inline(never)]
            // A hot kernel (inner loop of a step): its arguments are the buffers and sizes it works on,
            // llm.c style; kept as they are rather than re-measure its speed behind a struct.
            #[allow(clippy::too_many_arguments)]
            fn $plain<R: Real>(nf: u32, g: &Level, $($arg: $ty),*) {
                dispatch!(nf, g, |F, ix| $imp::<R, F, _>(g, ix, $($arg),*))
            }
        };
    }

    // ---------------------------------------------------------------- forward

    kernel!(forward_level, forward_level_fma, forward_level_plain, forward_level_impl,
        (tab: &[R], pts: &[[f64; 3]], out: &mut [R], lf: usize, l: usize, active: &[u8],
         sc: &mut BlockScratch<R>, simd: bool));

    /// One level for a chunk of points: `out[i, l*F..(l+1)*F] = Σ_k w_k · table[idx_k]` (Eq. 2).
    #[inline(always)]
    // A hot kernel (inner loop of a step): its arguments are the buffers and sizes it works on,
    // llm.c style; kept as they are rather than re-measure its speed behind a struct.
    #[allow(clippy::too_many_arguments)]
    fn forward_level_impl<R: Real, const F: usize, I: BlockIndexer>(
        g: &Level,
        ix: I,
        tab: &[R],        // [size, F], this level only
        pts: &[[f64; 3]], // [n]
        out: &mut [R],    // [n, L*F]
        lf: usize,
        l: usize,
        active: &[u8], // [n] levels evaluated per point, or empty = all
        sc: &mut BlockScratch<R>,
        simd: bool, // the CPU has fma and avx2 (the `fma,avx2` build calls with `true`)
    ) {
        assert_eq!(tab.len(), g.size as usize * F);
        assert!(out.len() >= pts.len() * lf);
        assert!(active.is_empty() || active.len() >= pts.len());
        // A point whose active-level count is ≤ l skips this level (output 0, no gather).
        let on = |i: usize| active.is_empty() || active[i] as usize > l;
        let BlockScratch {
            xd,
            c,
            w,
            om,
            idx,
            w8,
        } = sc;
        let mut same = [false; BLOCK];
        // `x86::interp_f32x2` takes pass 2 of f32 tables with two features (every preset's grids)
        // where the CPU has AVX2: the same operations on four points at a time.
        let simd_f32x2 =
            simd && F == 2 && std::any::TypeId::of::<R>() == std::any::TypeId::of::<f32>();
        #[cfg(not(target_arch = "x86_64"))]
        let _ = simd_f32x2; // the AVX2 pass is x86-64 only
        let mut live = [0i64; BLOCK];
        for (b, xs) in pts.chunks(BLOCK).enumerate() {
            // Pass 1: corners and weights of the block, prefetching the table rows.
            locate_block(g.scale, g.tcnn, xs, xd, c, w);
            interp_block(block_len(xs.len()), g.smooth, w, None);
            corner_weights_block(block_len(xs.len()), w, om, w8);
            ix.corners_block(block_len(xs.len()), c, idx);
            // A point in the same cell as the point before it (both evaluating the level) has the
            // same 8 corner rows: it reuses the rows that point gathered, and nothing is
            // prefetched for it. Consecutive points share cells often: a pixel's γ² sub-samples
            // are consecutive, and so are neighbouring pixels at the levels coarser than a pixel.
            let mut prev_on = false;
            for j in 0..xs.len() {
                let (now, p) = (on(b * BLOCK + j), j.saturating_sub(1));
                same[j] = now
                    && prev_on
                    && c[0][j] == c[0][p]
                    && c[1][j] == c[1][p]
                    && c[2][j] == c[2][p];
                if now && !same[j] {
                    prefetch_corners::<R, F>(tab, idx, j);
                }
                live[j] = -(now as i64);
                prev_on = now;
            }
            #[cfg(target_arch = "x86_64")]
            if simd_f32x2 {
                live[xs.len()..xs.len().next_multiple_of(4)].fill(0);
                // SAFETY: `simd` promises fma and avx2. R is f32 (TypeId above), so `tab`, `w8` and
                // `out` are f32 buffers of the lengths asserted above; every lane the function reads
                // (below xs.len() rounded up to 4 ≤ block_len) holds an index < size, computed in
                // pass 1; it writes rows b·BLOCK + j < pts.len() only, at columns l·2..l·2+2 < lf.
                unsafe {
                    x86::interp_f32x2(
                        tab.as_ptr() as *const f32,
                        idx,
                        &*(w8 as *const [[R; BLOCK]; 8] as *const [[f32; BLOCK]; 8]),
                        &live,
                        xs.len(),
                        (out.as_mut_ptr() as *mut f32).add(b * BLOCK * lf + l * F),
                        lf,
                    )
                };
                continue;
            }
            // Pass 2: gather and interpolate (Eq. 2), fma chain in corner order; `v` holds the
            // corner rows of the last point gathered (the same values whether gathered again or
            // not, so the bits do not depend on the sharing).
            let mut v = [[R::ZERO; F]; 8];
            for j in 0..xs.len() {
                if !on(b * BLOCK + j) {
                    out[(b * BLOCK + j) * lf + l * F..][..F].fill(R::ZERO);
                    continue;
                }
                if !same[j] {
                    for k in 0..8 {
                        let e = idx[k][j] as usize * F;
                        // SAFETY: idx < size (mod / mask), and tab.len() == size * F.
                        let row = unsafe { tab.get_unchecked(e..e + F) };
                        v[k].copy_from_slice(row);
                    }
                }
                let mut acc = [R::ZERO; F];
                for k in 0..8 {
                    for f in 0..F {
                        acc[f] = w8[k][j].mul_add(v[k][f], acc[f]);
                    }
                }
                out[(b * BLOCK + j) * lf + l * F..][..F].copy_from_slice(&acc);
            }
        }
    }

    // ---------------------------------------------------------------- backward (table)

    kernel!(backward_table_level, backward_table_level_fma, backward_table_level_plain,
        backward_table_level_impl,
        (pts: &[[f64; 3]], d_out: &[R], lf: usize, l: usize, d_tab: &mut [R], bits: &mut [u64]));

    /// One level, points in order: `d_table[idx_k, f] += w_k · d_out[i, l*F+f]`.
    #[inline(always)]
    // A hot kernel (inner loop of a step): its arguments are the buffers and sizes it works on,
    // llm.c style; kept as they are rather than re-measure its speed behind a struct.
    #[allow(clippy::too_many_arguments)]
    fn backward_table_level_impl<R: Real, const F: usize, I: BlockIndexer>(
        g: &Level,
        ix: I,
        pts: &[[f64; 3]], // [n]
        d_out: &[R],      // [n, L*F]
        lf: usize,
        l: usize,
        d_tab: &mut [R],  // [size, F], this level only
        bits: &mut [u64], // [ceil(size/64)]
    ) {
        assert_eq!(d_tab.len(), g.size as usize * F);
        assert_eq!(bits.len(), (g.size as usize).div_ceil(64));
        assert!(d_out.len() >= pts.len() * lf);
        let mut xd = [[0.0f64; BLOCK]; 3];
        let mut c = [[0u32; BLOCK]; 3];
        let mut w = [[R::ZERO; BLOCK]; 3];
        let mut om = [[R::ZERO; BLOCK]; 3];
        let mut idx = [[0u32; BLOCK]; 8];
        let mut w8 = [[R::ZERO; BLOCK]; 8];
        let mut grs = [[R::ZERO; F]; BLOCK];
        let mut live = [false; BLOCK];
        for (b, xs) in pts.chunks(BLOCK).enumerate() {
            // Pass 1: corners and weights, prefetching the gradient rows.
            locate_block(g.scale, g.tcnn, xs, &mut xd, &mut c, &mut w);
            interp_block(block_len(xs.len()), g.smooth, &mut w, None);
            corner_weights_block(block_len(xs.len()), &w, &mut om, &mut w8);
            ix.corners_block(block_len(xs.len()), &c, &mut idx);
            for j in 0..xs.len() {
                grs[j].copy_from_slice(&d_out[(b * BLOCK + j) * lf + l * F..][..F]);
                // An all-zero d_out slice contributes nothing and is not recorded as touched.
                live[j] = grs[j].iter().any(|&v| v != R::ZERO);
                if live[j] {
                    prefetch_corners::<R, F>(d_tab, &idx, j);
                }
            }
            // Pass 2: scatter, in point order.
            for j in 0..xs.len() {
                if !live[j] {
                    continue;
                }
                for k in 0..8 {
                    let e = idx[k][j] as usize;
                    // SAFETY: e < size (mod / mask); d_tab.len() == size*F, bits cover size bits.
                    unsafe {
                        let d = d_tab.get_unchecked_mut(e * F..e * F + F);
                        for f in 0..F {
                            d[f] += w8[k][j] * grs[j][f];
                        }
                        *bits.get_unchecked_mut(e / 64) |= 1u64 << (e % 64);
                    }
                }
            }
        }
    }

    // ---------------------------------------------------------------- backward (points)

    kernel!(backward_points_level, backward_points_level_fma, backward_points_level_plain,
        backward_points_level_impl,
        (tab: &[R], pts: &[[f64; 3]], d_out: &[R], lf: usize, l: usize, acc: &mut [[R; 3]]));

    /// One level for a chunk of points: `acc[i][d] += Σ_f d_out[i, l*F+f] · ∂out[l*F+f]/∂x_d`
    /// (fma chain in f order), with
    /// `∂out/∂x_d = Σ_{4 edges along d} ((scale·w_a')·w_b') · (v_hi - v_lo) · dw_d/dt`.
    #[inline(always)]
    // A hot kernel (inner loop of a step): its arguments are the buffers and sizes it works on,
    // llm.c style; kept as they are rather than re-measure its speed behind a struct.
    #[allow(clippy::too_many_arguments)]
    fn backward_points_level_impl<R: Real, const F: usize, I: BlockIndexer>(
        g: &Level,
        ix: I,
        tab: &[R],        // [size, F], this level only
        pts: &[[f64; 3]], // [n]
        d_out: &[R],      // [n, L*F]
        lf: usize,
        l: usize,
        acc: &mut [[R; 3]], // [>= n]
    ) {
        assert_eq!(tab.len(), g.size as usize * F);
        assert!(d_out.len() >= pts.len() * lf);
        assert!(acc.len() >= pts.len());
        let scale = R::from_f32(g.scale);
        let mut xd = [[0.0f64; BLOCK]; 3];
        let mut c = [[0u32; BLOCK]; 3];
        let mut w = [[R::ZERO; BLOCK]; 3];
        let mut dw = [[R::ZERO; BLOCK]; 3];
        let mut idx = [[0u32; BLOCK]; 8];
        let mut v = [[[R::ZERO; BLOCK]; F]; 8];
        for (b, xs) in pts.chunks(BLOCK).enumerate() {
            // Pass 1: corners, weights and dw/dt, prefetching the table rows.
            locate_block(g.scale, g.tcnn, xs, &mut xd, &mut c, &mut w);
            interp_block(block_len(xs.len()), g.smooth, &mut w, Some(&mut dw));
            ix.corners_block(block_len(xs.len()), &c, &mut idx);
            for j in 0..xs.len() {
                prefetch_corners::<R, F>(tab, &idx, j);
            }
            // Pass 2a: gather the corner values, SoA `v[k][f][j]` (padding lanes have valid
            // indices too: they were computed from x = 0).
            let nb = block_len(xs.len());
            for j in 0..nb {
                for k in 0..8 {
                    let e = idx[k][j] as usize * F;
                    // SAFETY: idx < size (mod / mask), and tab.len() == size * F.
                    let s = unsafe { tab.get_unchecked(e..e + F) };
                    for f in 0..F {
                        v[k][f][j] = s[f];
                    }
                }
            }
            let mut om = [[R::ZERO; BLOCK]; 3];
            for d in 0..3 {
                for j in 0..nb {
                    om[d][j] = R::ONE - w[d][j];
                }
            }
            // Pass 2b: differentiate, one axis at a time across the block's points.
            for d in 0..3 {
                // The two other axes, ascending (tcnn's non_grad_dim order).
                let (a, b2) = match d {
                    0 => (1, 2),
                    1 => (0, 2),
                    _ => (0, 1),
                };
                let mut gd = [[R::ZERO; BLOCK]; F];
                for e in 0..4 {
                    let (ba, bb) = (e & 1, (e >> 1) & 1);
                    let wa = if ba == 1 { &w[a] } else { &om[a] };
                    let wb = if bb == 1 { &w[b2] } else { &om[b2] };
                    let lo = (ba << a) | (bb << b2);
                    let hi = lo | (1 << d);
                    for f in 0..F {
                        let (vh, vl, g) = (&v[hi][f], &v[lo][f], &mut gd[f]);
                        for j in 0..nb {
                            let wt = scale * wa[j] * wb[j];
                            g[j] += wt * (vh[j] - vl[j]) * dw[d][j];
                        }
                    }
                }
                for j in 0..xs.len() {
                    let i = b * BLOCK + j;
                    let gr = &d_out[i * lf + l * F..][..F];
                    let mut s = acc[i][d];
                    for f in 0..F {
                        s = gr[f].mul_add(gd[f][j], s);
                    }
                    acc[i][d] = s;
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn fastmod_is_exact() {
        for d in [
            1u32,
            3,
            7,
            8,
            4096,
            12168,
            205384,
            1 << 19,
            (1 << 31),
            u32::MAX,
        ] {
            let m = (u64::MAX / d as u64).wrapping_add(1);
            for k in 0..20_000u64 {
                let a = (rng::bits(1, Purpose::Test, d as u64, k) as u32) >> (k % 32);
                assert_eq!(fastmod(a, m, d), a % d, "a={a} d={d}");
            }
            for a in [
                0u32,
                1,
                d.wrapping_sub(1),
                d,
                d.wrapping_add(1),
                u32::MAX,
                u32::MAX - 1,
            ] {
                assert_eq!(fastmod(a, m, d), a % d, "a={a} d={d}");
            }
        }
    }

    #[test]
    fn invalid_configs_are_errors() {
        let good = crate::model::ModelConfig::tiny().grid_h;
        assert!(HashGrid::try_new(&good).is_ok());
        let mut c = good.clone();
        c.features = 3;
        assert!(HashGrid::try_new(&c)
            .unwrap_err()
            .to_string()
            .contains("features"));
        let mut c = good.clone();
        c.levels = 0;
        assert!(HashGrid::try_new(&c).is_err());
        let mut c = good.clone();
        c.per_level_scale = f64::NAN;
        assert!(HashGrid::try_new(&c).is_err());
        let mut c = good.clone();
        c.log2_table_size = 32;
        assert!(HashGrid::try_new(&c).is_err());
        let e = HashGrid::with_scales(&good, vec![1.0, 2.0]).unwrap_err();
        assert!(e.to_string().contains("scale table has 2 values"), "{e}");
        let e = HashGrid::with_scales(&good, vec![1.0, 2.0, f32::NAN, 3.0]).unwrap_err();
        assert!(e.to_string().contains("level 2"), "{e}");
    }

    #[test]
    fn level_size_rule() {
        assert_eq!(level_size(16, 19), 4096);
        assert_eq!(level_size(23, 19), 12168); // 12167 → next multiple of 8
        assert_eq!(level_size(81, 19), 1 << 19); // 531441 > 2^19
        assert_eq!(level_size(2000, 31), 1 << 31); // capped at 2^31-1 → 2^31
        assert_eq!(level_size(2000, 20), 1 << 20);
    }
}
