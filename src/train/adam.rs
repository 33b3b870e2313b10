//! Adam with tiny-cuda-nn's rules (SPEC §4.8). This file owns the optimizer state (flat `m`, `v`,
//! `t` over the whole parameter buffer, saved per named parameter as `adam.m.<name>`,
//! `adam.v.<name>`, `adam.t.<name>`), the per-group hyperparameters and the learning-rate schedule.
//!
//! # The update (per scalar parameter `w` with gradient `g`, all in f32 as tiny-cuda-nn)
//! ```text
//! sparse group and g == 0   →  skip: w, m, v, t unchanged            (tcnn: non-matrix params)
//! dense group and l2 != 0   →  g = g + l2 * w                        (tcnn: matrix params only)
//! m = β1 * m + (1 - β1) * g
//! v = β2 * v + (1 - β2) * (g * g)
//! t = t + 1                                                          (u32, per parameter)
//! lr_t = lr_k * sqrt(1 - β2^t) / (1 - β1^t)                          (bias correction, own t)
//! w = w - (lr_t / (sqrt(v) + ε)) * m                                 (ε outside the sqrt)
//! ```
//! This is tiny-cuda-nn's `adam_step` kernel (read in `include/tiny-cuda-nn/optimizers/adam.h`):
//! non-matrix parameters (grids) with an exactly zero gradient return early, L2 is added to the
//! gradient of matrix (MLP) weights only, every parameter has its own step counter, and the step
//! divides the bias-corrected learning rate by `sqrt(v) + ε` before multiplying by `m`. Its other
//! options (AdaBound bounds, relative/absolute weight decay, clipping, loss scale) are not
//! implemented: with their defaults they are the identity. Note tcnn's default `l2_reg` is 1e-8;
//! ours is per group (default 1e-6 on MLPs as instant-ngp's NeRF config, 0 elsewhere).
//!
//! `g == 0` is IEEE equality, so `-0.0` is skipped too. Groups are "dense" (every parameter steps
//! every time, L2 allowed: the shader and deformation MLPs) or "sparse" (zero-gradient parameters
//! are skipped, no L2: grids H and D, appearance codes).
//!
//! # Numerics
//! Moments and weights are f32, operations in the order written above, unfused (no FMA). nvcc
//! contracts `a*b + c` into FMAs by default, so a CUDA port may differ by an ulp or so per step.
//! The bias-corrected rate `lr_t` is computed in f64 from the f32 hyperparameters (β^t by
//! exponentiation by squaring, so it is the same on every platform and libm) and rounded once to
//! f32; tcnn computes it in f32 with `powf`, which differs from ours by at most a few f32 ulps.
//!
//! # Learning-rate schedule (`lr_k` at 0-based global step `k`, the k-th call for this group)
//! ```text
//! lr_k = lr * warm(k) * decay(k)
//! warm(k)  = min(1, (k + 1) / warmup_steps)                 (1 if warmup_steps = 0; linear)
//! decay(k) = decay_base ^ n(k),  n(k) = 0 if decay_interval = 0 or min(k, decay_end) < decay_start,
//!            else floor((min(k, decay_end) - decay_start) / decay_interval) + 1
//! ```
//! `decay` is tiny-cuda-nn's `ExponentialDecay` optimizer (piecewise constant: the factor is
//! multiplied by `decay_base` at steps start, start + interval, … up to `decay_end`); warm-up is ours.
//! Computed in f64.
//!
//! # Cost and determinism
//! `step_sparse` touches only the listed entries, so its cost grows with the entries touched, not
//! with the table size (`benches/adam.rs`). Work is split into chunks of a constant size
//! ([`DENSE_CHUNK`] scalars, [`SPARSE_CHUNK`] entries) run in parallel; every scalar's update
//! depends only on its own state, so results are bit-identical for any thread count.

use crate::io::tensors::{DType, Tensor, TensorFile};
use anyhow::{bail, ensure, Context, Result};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use std::ops::Range;

/// One dense chunk: (chunk index, (w, state)).
type DenseChunk<'a> = (usize, (&'a mut [f32], &'a mut [Moments]));
/// One sparse chunk: (entries, first scalar, w, grad, state) over the chunk's region.
type SparseChunk<'a> = (
    &'a [u32],
    usize,
    &'a mut [f32],
    &'a mut [f32],
    &'a mut [Moments],
);
/// How many entries ahead a sparse step prefetches into L2 (`FAR_AHEAD`), then into L1
/// (`NEAR_AHEAD`): Adam waits on the lines of scattered entries, and L2 keeps more misses in
/// flight than L1's miss buffers (`docs/performance.md`, "Prefetching into L2").
const FAR_AHEAD: usize = 64;
const NEAR_AHEAD: usize = 16;

/// Scalars per parallel chunk in [`AdamState::step_dense`].
pub const DENSE_CHUNK: usize = 1 << 14;
/// Entries per parallel chunk in [`AdamState::step_sparse`].
pub const SPARSE_CHUNK: usize = 1 << 11;
/// Scalars per parallel chunk when the state is saved or loaded (no effect on the bytes).
const IO_CHUNK: usize = 1 << 16;

/// Learning-rate schedule of one group (see the module doc for the formula).
#[derive(Clone, Copy, Debug, Serialize, Deserialize, PartialEq)]
#[serde(default, deny_unknown_fields)]
pub struct LrSchedule {
    /// Linear warm-up length in steps (0 = none).
    pub warmup_steps: u32,
    /// First step at which the learning rate is multiplied by `decay_base`.
    pub decay_start: u32,
    /// Steps between decays (0 = no decay).
    pub decay_interval: u32,
    pub decay_base: f32,
    /// Last step at which a decay may happen.
    pub decay_end: u32,
}

impl Default for LrSchedule {
    fn default() -> Self {
        LrSchedule {
            warmup_steps: 0,
            decay_start: 0,
            decay_interval: 0,
            decay_base: 1.0,
            decay_end: u32::MAX,
        }
    }
}

impl LrSchedule {
    /// This schedule stretched from a run of `from` steps to one of `to` (`budget = "auto"`,
    /// spec §8): every step count scaled by `to / from` and rounded to the nearest step, so the
    /// decays fall at the same fractions of the run. `decay_end = u32::MAX` (no end) stays.
    pub fn stretched(&self, from: u64, to: u64) -> LrSchedule {
        let scale = |k: u32| -> u32 {
            if k == u32::MAX || from == 0 {
                return k;
            }
            ((k as u64 * to + from / 2) / from).min(u32::MAX as u64 - 1) as u32
        };
        LrSchedule {
            warmup_steps: scale(self.warmup_steps),
            decay_start: scale(self.decay_start),
            decay_interval: scale(self.decay_interval),
            decay_base: self.decay_base,
            decay_end: scale(self.decay_end),
        }
    }

    /// `warm(k) * decay(k)` at 0-based step `k`.
    pub fn factor(&self, k: u64) -> f64 {
        let warm = if self.warmup_steps == 0 {
            1.0
        } else {
            ((k + 1) as f64 / self.warmup_steps as f64).min(1.0)
        };
        let last = k.min(self.decay_end as u64);
        let n = if self.decay_interval == 0 || last < self.decay_start as u64 {
            0
        } else {
            (last - self.decay_start as u64) / self.decay_interval as u64 + 1
        };
        warm * pow_u64(self.decay_base as f64, n)
    }
}

/// Hyperparameters of one parameter group.
#[derive(Clone, Copy, Debug, Serialize, Deserialize, PartialEq)]
#[serde(default, deny_unknown_fields)]
pub struct AdamGroup {
    pub lr: f32,
    pub beta1: f32,
    pub beta2: f32,
    pub epsilon: f32,
    /// L2 regularisation added to the gradient (`g += l2 * w`); ignored in sparse groups.
    pub l2: f32,
    /// Skip parameters whose gradient is exactly zero (grids, appearance codes); no L2. Not read
    /// from config files: [`AdamConfig`] sets it by the group's role.
    #[serde(skip)]
    pub sparse: bool,
    pub schedule: LrSchedule,
}

impl Default for AdamGroup {
    /// instant-ngp's NeRF Adam: lr 1e-2, β1 0.9, β2 0.99, ε 1e-15, L2 1e-6 (dense groups only);
    /// dense; no schedule.
    fn default() -> Self {
        AdamGroup {
            lr: 1e-2,
            beta1: 0.9,
            beta2: 0.99,
            epsilon: 1e-15,
            l2: 1e-6,
            sparse: false,
            schedule: LrSchedule::default(),
        }
    }
}

impl AdamGroup {
    /// tiny-cuda-nn's Adam defaults (lr 1e-3, β1 0.9, β2 0.999, ε 1e-8, l2 1e-8 on dense groups).
    pub fn tcnn_default(sparse: bool) -> Self {
        AdamGroup {
            lr: 1e-3,
            beta1: 0.9,
            beta2: 0.999,
            epsilon: 1e-8,
            l2: if sparse { 0.0 } else { 1e-8 },
            sparse,
            schedule: LrSchedule::default(),
        }
    }

    /// Scheduled learning rate at 0-based step `k` (f64).
    pub fn lr_at(&self, k: u64) -> f64 {
        self.lr as f64 * self.schedule.factor(k)
    }

    fn check(&self) -> Result<()> {
        let bad: Vec<String> = [
            (
                !(self.lr.is_finite() && self.lr >= 0.0),
                format!("lr = {} (need a finite value >= 0)", self.lr),
            ),
            (
                !(0.0..1.0).contains(&self.beta1),
                format!("beta1 = {} (need 0 <= beta1 < 1)", self.beta1),
            ),
            (
                !(0.0..1.0).contains(&self.beta2),
                format!("beta2 = {} (need 0 <= beta2 < 1)", self.beta2),
            ),
            (
                !(self.epsilon.is_finite() && self.epsilon >= 0.0),
                format!("epsilon = {} (need a finite value >= 0)", self.epsilon),
            ),
            (
                !self.l2.is_finite(),
                format!("l2 = {} (need a finite value)", self.l2),
            ),
            (
                !self.schedule.decay_base.is_finite(),
                format!(
                    "schedule.decay_base = {} (need a finite value)",
                    self.schedule.decay_base
                ),
            ),
        ]
        .into_iter()
        .filter_map(|(b, m)| b.then_some(m))
        .collect();
        if !bad.is_empty() {
            bail!("{}", bad.join("; "));
        }
        Ok(())
    }
}

/// Hyperparameters of every group of the model (SPEC §4.8). In TOML, one table per group
/// (`[grid_h] lr = 1e-2`, missing keys take the defaults); `sparse` is set by role (shader and
/// deform dense, grids and appearance codes sparse), never read from the file.
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
#[serde(from = "AdamConfigFile")]
pub struct AdamConfig {
    pub shader: AdamGroup,
    pub deform: AdamGroup,
    pub grid_h: AdamGroup,
    pub grid_d: AdamGroup,
    pub appearance: AdamGroup,
    /// The vertex-feature table of the Fig. 2b baseline (sparse, like the grids).
    pub vertex: AdamGroup,
}

impl AdamConfig {
    /// Every group, for what applies to all of them alike.
    pub fn groups_mut(&mut self) -> [&mut AdamGroup; 6] {
        [
            &mut self.shader,
            &mut self.deform,
            &mut self.grid_h,
            &mut self.grid_d,
            &mut self.appearance,
            &mut self.vertex,
        ]
    }
}

impl Default for AdamConfig {
    /// instant-ngp's NeRF hyperparameters for every group (lr 1e-2, β2 0.99, ε 1e-15), L2 1e-6
    /// on the MLPs, grids and appearance codes sparse; no schedule.
    fn default() -> Self {
        AdamConfigFile::default().into()
    }
}

/// The file form of [`AdamConfig`] (before the roles set `sparse`).
#[derive(Deserialize, Default)]
#[serde(default, deny_unknown_fields)]
struct AdamConfigFile {
    shader: AdamGroup,
    deform: AdamGroup,
    grid_h: AdamGroup,
    grid_d: AdamGroup,
    appearance: AdamGroup,
    vertex: AdamGroup,
}

impl From<AdamConfigFile> for AdamConfig {
    fn from(f: AdamConfigFile) -> AdamConfig {
        let role = |g: AdamGroup, sparse: bool| AdamGroup { sparse, ..g };
        AdamConfig {
            shader: role(f.shader, false),
            deform: role(f.deform, false),
            grid_h: role(f.grid_h, true),
            grid_d: role(f.grid_d, true),
            appearance: role(f.appearance, true),
            vertex: role(f.vertex, true),
        }
    }
}

impl AdamConfig {
    /// Every group valid (finite, β in [0, 1), …).
    pub fn validate(&self) -> Result<()> {
        for (name, g) in [
            ("shader", &self.shader),
            ("deform", &self.deform),
            ("grid_h", &self.grid_h),
            ("grid_d", &self.grid_d),
            ("appearance", &self.appearance),
            ("vertex", &self.vertex),
        ] {
            g.check().with_context(|| format!("adam.{name}"))?;
        }
        Ok(())
    }
}

/// `x^n` by exponentiation by squaring (same result on every platform).
fn pow_u64(x: f64, mut n: u64) -> f64 {
    let (mut base, mut acc) = (x, 1.0f64);
    while n > 0 {
        if n & 1 == 1 {
            acc *= base;
        }
        base *= base;
        n >>= 1;
    }
    acc
}

/// The bias-correction factors of Adam, `(sqrt(1 - β2^t), 1 - β1^t)` for t = 1, 2, …, cached
/// across steps: they depend only on (β1, β2, t), and recomputing `β^t` per scalar cost more
/// than the rest of a sparse update (every entry of a sparse group has its own `t`). Only
/// caches values: results are the same bits as computing them on the spot.
#[derive(Clone, Debug, Default)]
pub struct BiasCache {
    /// One table per pair of betas seen.
    tables: Vec<BiasTable>,
    /// `lr_t` tables of the latest (lr_k, β1, β2) keys, most recent last (at most
    /// [`LR_TABLES`]): a step's groups usually share one key, which stays the same from step to
    /// step between learning-rate changes, so a table grows by one entry per step instead of
    /// being rebuilt (rebuilding cost O(k) per group and step: 23 µs per group at step 20,000).
    lr: Vec<LrTable>,
}

/// `(β1 bits, β2 bits, [t-1] → (sqrt(1 - β2^t), 1 - β1^t))`.
type BiasTable = (u32, u32, Vec<(f64, f64)>);

/// `((lr_k bits, β1 bits, β2 bits), [t] → lr_t)` (`[0]` unused).
type LrTable = ((u64, u32, u32), Vec<f32>);

/// How many `lr_t` tables [`BiasCache`] keeps (one per group configuration a step uses).
const LR_TABLES: usize = 8;

impl PartialEq for BiasCache {
    /// A cache is not state: two Adam states are equal whatever they have cached.
    fn eq(&self, _: &Self) -> bool {
        true
    }
}

impl BiasCache {
    /// `lr[t] = lr_k · sqrt(1 − β2^t) / (1 − β1^t)` (f64, rounded to f32) for 1 ≤ t ≤ t_max
    /// (`lr[0]` unused), from the cached factors; the table is kept for the next call with the
    /// same (lr_k, β1, β2), which only extends it.
    fn lr_table(&mut self, lr_k: f64, b1: f32, b2: f32, t_max: usize) -> &[f32] {
        let key = (b1.to_bits(), b2.to_bits());
        let i = match self.tables.iter().position(|e| (e.0, e.1) == key) {
            Some(i) => i,
            None => {
                self.tables.push((key.0, key.1, Vec::new()));
                self.tables.len() - 1
            }
        };
        let tab = &mut self.tables[i].2;
        for t in tab.len() + 1..=t_max {
            tab.push(bias_factors(b1, b2, t as u32));
        }
        let lr_key = (lr_k.to_bits(), key.0, key.1);
        let mut lr = match self.lr.iter().position(|e| e.0 == lr_key) {
            Some(j) => self.lr.remove(j),
            None => {
                if self.lr.len() == LR_TABLES {
                    self.lr.remove(0);
                }
                (lr_key, vec![0.0])
            }
        };
        let have = lr.1.len() - 1;
        if t_max > have {
            lr.1.extend(
                tab[have..t_max]
                    .iter()
                    .map(|&(s2, d1)| (lr_k * s2 / d1) as f32),
            );
        }
        self.lr.push(lr);
        &self.lr.last().unwrap().1[..=t_max]
    }
}

/// `(sqrt(1 - β2^t), 1 - β1^t)` in f64 (β^t by squaring).
fn bias_factors(b1: f32, b2: f32, t: u32) -> (f64, f64) {
    let b1t = pow_u64(b1 as f64, t as u64);
    let b2t = pow_u64(b2 as f64, t as u64);
    ((1.0 - b2t).sqrt(), 1.0 - b1t)
}

/// Per-step constants of a group, with `lr_t` tabulated for every step count a parameter can
/// have reached (t ≤ k + 1 at 0-based step k; a larger t, possible only when a caller repeats a
/// step index, is computed on the spot with the same expression).
#[derive(Clone)]
struct StepConsts<'a> {
    lr_k: f64,
    b1: f32,
    b2: f32,
    one_minus_b1: f32,
    one_minus_b2: f32,
    eps: f32,
    l2: f32,
    skip_zero: bool,
    /// `lr[t]` = `lr_t(t)` for 1 ≤ t < len (`lr[0]` unused).
    lr: &'a [f32],
}

impl StepConsts<'_> {
    /// The group's constants at 0-based step `k` (the `lr_t` table built in `cache`'s scratch).
    fn new<'a>(cfg: &AdamGroup, k: u64, sparse: bool, cache: &'a mut BiasCache) -> StepConsts<'a> {
        let lr_k = cfg.lr_at(k);
        let t_max = (k as usize).saturating_add(1);
        let table = cache.lr_table(lr_k, cfg.beta1, cfg.beta2, t_max);
        StepConsts {
            lr_k,
            b1: cfg.beta1,
            b2: cfg.beta2,
            one_minus_b1: 1.0 - cfg.beta1,
            one_minus_b2: 1.0 - cfg.beta2,
            eps: cfg.epsilon,
            l2: if sparse { 0.0 } else { cfg.l2 },
            skip_zero: sparse,
            lr: table,
        }
    }

    /// `lr_k * sqrt(1 - β2^t) / (1 - β1^t)` in f64, rounded to f32.
    #[inline]
    fn lr_t(&self, t: u32) -> f32 {
        match self.lr.get(t as usize) {
            Some(&v) => v,
            None => {
                let (s2, d1) = bias_factors(self.b1, self.b2, t);
                (self.lr_k * s2 / d1) as f32
            }
        }
    }

    /// One scalar's Adam update (module doc).
    #[inline]
    fn update(&self, w: &mut f32, g: f32, s: &mut Moments) {
        if self.skip_zero && g == 0.0 {
            return;
        }
        let g = if self.l2 != 0.0 { g + self.l2 * *w } else { g };
        s.m = self.b1 * s.m + self.one_minus_b1 * g;
        s.v = self.b2 * s.v + self.one_minus_b2 * (g * g);
        s.t = s.t.saturating_add(1);
        let lr_t = self.lr_t(s.t);
        let eff = lr_t / (s.v.sqrt() + self.eps);
        *w -= eff * s.m;
    }
}

/// Prefetch, with `hint` (`memhint::prefetch` or `prefetch_l2`), the lines of the entry at local
/// scalar offset `a` (`len` scalars): its first parameter and gradient, and the first and last
/// byte of its state record (which may lie on two lines). Pointer arithmetic only
/// (`wrapping_add`), so an address past a slice is harmless.
#[inline(always)]
fn prefetch_entry(
    hint: fn(*const u8),
    (w, g, st): (&[f32], &[f32], &[Moments]),
    a: usize,
    len: usize,
) {
    let s = st.as_ptr().wrapping_add(a) as *const u8;
    hint(w.as_ptr().wrapping_add(a) as *const u8);
    hint(g.as_ptr().wrapping_add(a) as *const u8);
    hint(s);
    hint(s.wrapping_add(len * std::mem::size_of::<Moments>() - 1));
}

/// One scalar's Adam state, stored together (12 bytes): a sparse step reads and writes all three
/// for each touched scalar at random places of a large table, so one cache line serves them.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
#[repr(C)]
pub struct Moments {
    /// First moment.
    pub m: f32,
    /// Second moment.
    pub v: f32,
    /// Steps this scalar has taken.
    pub t: u32,
}

/// One named parameter's place in the flat buffer.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct ParamSlot {
    pub name: String,
    pub shape: Vec<usize>,
    pub offset: usize,
}

impl ParamSlot {
    pub fn len(&self) -> usize {
        self.shape.iter().product()
    }
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }
    pub fn range(&self) -> Range<usize> {
        self.offset..self.offset + self.len()
    }
}

/// Adam state over a flat parameter buffer: `m`, `v` (f32) and `t` (u32) per scalar parameter,
/// laid out as the named parameters in `slots` (consecutive, in the order given).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct AdamState {
    /// Per scalar parameter, in the flat buffer's order.
    pub state: Vec<Moments>,
    pub slots: Vec<ParamSlot>,
    /// Bias-correction factors and the `lr_t` table (values only, not state).
    pub cache: BiasCache,
}

impl AdamState {
    /// Zero state for named parameters `(name, shape)`, laid out consecutively in this order.
    pub fn new<S: AsRef<str>>(params: &[(S, Vec<usize>)]) -> AdamState {
        let mut slots = Vec::with_capacity(params.len());
        let mut offset = 0;
        for (name, shape) in params {
            let slot = ParamSlot {
                name: name.as_ref().to_string(),
                shape: shape.clone(),
                offset,
            };
            offset += slot.len();
            slots.push(slot);
        }
        AdamState {
            state: crate::memhint::filled(offset, Moments::default()),
            slots,
            cache: BiasCache::default(),
        }
    }

    /// Zero state for `n` unnamed scalars (no slots; cannot be saved by name).
    pub fn with_len(n: usize) -> AdamState {
        AdamState {
            state: vec![Moments::default(); n],
            slots: Vec::new(),
            cache: BiasCache::default(),
        }
    }

    /// Number of scalar parameters.
    pub fn len(&self) -> usize {
        self.state.len()
    }
    pub fn is_empty(&self) -> bool {
        self.state.is_empty()
    }
    /// First moments of `range`.
    pub fn m(&self, range: Range<usize>) -> Vec<f32> {
        self.state[range].iter().map(|s| s.m).collect()
    }
    /// Second moments of `range`.
    pub fn v(&self, range: Range<usize>) -> Vec<f32> {
        self.state[range].iter().map(|s| s.v).collect()
    }
    /// Step counts of `range`.
    pub fn t(&self, range: Range<usize>) -> Vec<u32> {
        self.state[range].iter().map(|s| s.t).collect()
    }

    /// The slot of a named parameter.
    pub fn slot(&self, name: &str) -> Result<&ParamSlot> {
        self.slots.iter().find(|s| s.name == name).with_context(|| {
            format!(
                "Adam state has no parameter {name} (it has: {})",
                self.slots
                    .iter()
                    .map(|s| s.name.as_str())
                    .collect::<Vec<_>>()
                    .join(", ")
            )
        })
    }

    /// Flat range of a named parameter.
    pub fn range(&self, name: &str) -> Result<Range<usize>> {
        Ok(self.slot(name)?.range())
    }

    /// One Adam step on every scalar of a parameter. `params` and `grads` are that parameter's
    /// own buffers (length `range.len()`); `range` locates it in the flat state. A sparse `cfg`
    /// skips exactly-zero gradients. `global_step` is the 0-based step index `k` (schedule).
    ///
    /// # Panics
    /// If the lengths disagree or `range` is outside the state (programming errors).
    pub fn step_dense(
        &mut self,
        range: Range<usize>,
        params: &mut [f32],
        grads: &[f32],
        cfg: &AdamGroup,
        global_step: u64,
    ) {
        assert!(
            params.len() == range.len() && grads.len() == range.len() && range.end <= self.len(),
            "step_dense: params {} / grads {} / range {:?} / state {} disagree",
            params.len(),
            grads.len(),
            range,
            self.len()
        );
        let consts = StepConsts::new(cfg, global_step, cfg.sparse, &mut self.cache);
        let st = &mut self.state[range];
        let run = |(ci, (w, st)): DenseChunk| {
            let c = &consts;
            let g = &grads[ci * DENSE_CHUNK..ci * DENSE_CHUNK + w.len()];
            for ((w, &g), s) in w.iter_mut().zip(g).zip(st.iter_mut()) {
                c.update(w, g, s);
            }
        };
        if params.len() <= DENSE_CHUNK {
            run((0, (params, st)));
        } else {
            params
                .par_chunks_mut(DENSE_CHUNK)
                .zip(st.par_chunks_mut(DENSE_CHUNK))
                .enumerate()
                .for_each(run);
        }
    }

    /// One Adam step on the listed entries of a table only (sparse semantics: exactly-zero
    /// gradients skipped, no L2, whatever `cfg.sparse` says). Entry `e` is the `entry_len`
    /// scalars `params[e*entry_len ..][..entry_len]` (e.g. one hash-table entry of F features);
    /// its state lives at `base_offset + e*entry_len` in the flat state. `params` and `grads` are
    /// the table's own buffers. `entries` must be strictly increasing (sorted, no duplicates), as
    /// the grid backward's touched-entry list is. This form copies `grads` first (O(table size));
    /// the training loop's [`AdamState::step_sparse_and_zero`] costs O(entries.len() * entry_len).
    ///
    /// # Panics
    /// If `entries` is not strictly increasing, an entry is out of range, or lengths disagree.
    // A hot kernel (inner loop of a step): its arguments are the buffers and sizes it works on,
    // llm.c style; kept as they are rather than re-measure its speed behind a struct.
    #[allow(clippy::too_many_arguments)]
    pub fn step_sparse(
        &mut self,
        params: &mut [f32],
        grads: &[f32],
        entries: &[u32],
        entry_len: usize,
        base_offset: usize,
        cfg: &AdamGroup,
        global_step: u64,
    ) {
        let mut g = grads.to_vec();
        self.step_sparse_and_zero(
            params,
            &mut g,
            entries,
            entry_len,
            base_offset,
            cfg,
            global_step,
        );
    }

    /// [`AdamState::step_sparse`] that also sets the listed entries' gradients to zero as it
    /// reads them (the training loop's gradient zeroing, fused: the entries are read once).
    /// Same parameter and state bits as `step_sparse`.
    // A hot kernel (inner loop of a step): its arguments are the buffers and sizes it works on,
    // llm.c style; kept as they are rather than re-measure its speed behind a struct.
    #[allow(clippy::too_many_arguments)]
    pub fn step_sparse_and_zero(
        &mut self,
        params: &mut [f32],
        grads: &mut [f32],
        entries: &[u32],
        entry_len: usize,
        base_offset: usize,
        cfg: &AdamGroup,
        global_step: u64,
    ) {
        assert!(entry_len > 0, "step_sparse: entry_len must be > 0");
        assert!(
            grads.len() == params.len() && base_offset + params.len() <= self.len(),
            "step_sparse: params {} / grads {} / base_offset {} / state {} disagree",
            params.len(),
            grads.len(),
            base_offset,
            self.len()
        );
        let n_entries = params.len() / entry_len;
        assert!(
            entries.windows(2).all(|w| w[0] < w[1]),
            "step_sparse: entries must be strictly increasing"
        );
        if let Some(&last) = entries.last() {
            assert!(
                (last as usize) < n_entries,
                "step_sparse: entry {last} out of range (table has {n_entries} entries)"
            );
        }
        let consts = StepConsts::new(cfg, global_step, true, &mut self.cache);
        let region = base_offset..base_offset + params.len();
        // Split the table, its gradient and its state into disjoint regions, one per chunk of
        // entries.
        let mut parts = Vec::with_capacity(entries.len().div_ceil(SPARSE_CHUNK));
        let (mut w_rest, mut g_rest, mut s_rest) = (params, grads, &mut self.state[region]);
        let mut consumed = 0usize;
        for chunk in entries.chunks(SPARSE_CHUNK) {
            let start = chunk[0] as usize * entry_len;
            let end = (*chunk.last().unwrap() as usize + 1) * entry_len;
            let (_, w) = std::mem::take(&mut w_rest).split_at_mut(start - consumed);
            let (w, wr) = w.split_at_mut(end - start);
            let (_, g) = std::mem::take(&mut g_rest).split_at_mut(start - consumed);
            let (g, gr) = g.split_at_mut(end - start);
            let (_, st) = std::mem::take(&mut s_rest).split_at_mut(start - consumed);
            let (st, sr) = st.split_at_mut(end - start);
            (w_rest, g_rest, s_rest) = (wr, gr, sr);
            consumed = end;
            parts.push((chunk, start, w, g, st));
        }
        let run = |(chunk, start, w, g, st): SparseChunk| {
            let c = &consts;
            // The entries are scattered over a table of hundreds of MB: start loading the lines
            // of an entry well ahead into L2 (the chunk's first ones before the loop), then a few
            // entries ahead into L1 (no effect on results).
            let (l2, l1) = (
                crate::memhint::prefetch_l2::<u8>,
                crate::memhint::prefetch::<u8>,
            );
            for &e in chunk.iter().take(FAR_AHEAD) {
                prefetch_entry(l2, (w, g, st), e as usize * entry_len - start, entry_len);
            }
            for (i, &e) in chunk.iter().enumerate() {
                if let Some(&far) = chunk.get(i + FAR_AHEAD) {
                    prefetch_entry(l2, (w, g, st), far as usize * entry_len - start, entry_len);
                }
                if let Some(&near) = chunk.get(i + NEAR_AHEAD) {
                    prefetch_entry(l1, (w, g, st), near as usize * entry_len - start, entry_len);
                }
                let local = e as usize * entry_len - start;
                let r = local..local + entry_len;
                let (w, g, st) = (&mut w[r.clone()], &mut g[r.clone()], &mut st[r]);
                for ((w, g), s) in w.iter_mut().zip(g.iter_mut()).zip(st) {
                    c.update(w, *g, s);
                    *g = 0.0;
                }
            }
        };
        if parts.len() <= 1 {
            parts.into_iter().for_each(run);
        } else {
            parts.into_par_iter().for_each(run);
        }
    }

    /// Write `adam.m.<name>`, `adam.v.<name>` (F32) and `adam.t.<name>` (U32) for every slot,
    /// each with the parameter's shape.
    pub fn save(&self, f: &mut TensorFile) -> Result<()> {
        for s in &self.slots {
            insert_state(f, &s.name, &s.shape, &s.shape, self.state_bytes(s.range()))?;
        }
        Ok(())
    }

    /// [`AdamState::save`], but a slot's rows (its first dimension: a grid's entries) whose
    /// state is still zero — never stepped: entries and levels no training ray reached — are not
    /// written. Such a slot is stored as `adam.mask.<name>` (U8 `[ceil(rows / 8)]`, bit `r % 8`
    /// of byte `r / 8` set iff row `r` is kept; bits past the last row 0) and
    /// `adam.{m,v}.<name>` of shape `[k, …]` (the kept rows, ascending), `adam.t.<name>` of shape
    /// `[k]` (each kept row's first scalar's step count: a grid entry's features step together
    /// unless one has an exactly zero gradient) with `adam.t_exceptions.<name>` (U32 `[e, 3]`:
    /// kept row, scalar within the row, count; ascending; absent when `e = 0`) for the scalars
    /// whose count differs; a slot every row of which has stepped is written as by `save` (so is
    /// every dense group). [`AdamState::load`] reads either back (and the `adam.rows.<name>` row lists
    /// of earlier checkpoints) to the same state, so a resumed run is bit-identical.
    /// `train.table_size = "auto"` checkpoints use it (`train/state.rs`).
    pub fn save_compact(&self, f: &mut TensorFile) -> Result<()> {
        self.save_compact_with(f, &self.stepped_rows())
    }

    /// [`AdamState::save_compact`] with every slot's stepped rows already listed
    /// ([`AdamState::stepped_rows`]: a save that also needs them for the model file scans the
    /// state once).
    pub fn save_compact_with(
        &self,
        f: &mut TensorFile,
        stepped: &[(&str, Vec<u32>)],
    ) -> Result<()> {
        ensure!(
            stepped.len() == self.slots.len()
                && stepped
                    .iter()
                    .zip(&self.slots)
                    .all(|((n, _), s)| *n == s.name),
            "Adam state: the stepped-row lists do not match the slots"
        );
        for (s, (_, kept)) in self.slots.iter().zip(stepped) {
            let rows = s.shape.first().copied().unwrap_or(1);
            let row_len = s.len().checked_div(rows).unwrap_or(0);
            let st = &self.state[s.range()];
            if s.shape.is_empty() || kept.len() == rows {
                let [m, v, t] = self.state_bytes(s.range());
                insert_state(f, &s.name, &s.shape, &s.shape, [m, v, t])?;
                continue;
            }
            let row = |r: u32| &st[r as usize * row_len..(r as usize + 1) * row_len];
            let t_per_row = row_len > 1;
            // The scalars whose count is not their row's first: (kept row, scalar, count).
            let exceptions: Vec<u32> = if t_per_row {
                kept.par_iter()
                    .enumerate()
                    .flat_map_iter(|(k, &r)| {
                        let first = row(r)[0].t;
                        row(r)
                            .iter()
                            .enumerate()
                            .filter(move |(_, m)| m.t != first)
                            .flat_map(move |(j, m)| [k as u32, j as u32, m.t])
                    })
                    .collect()
            } else {
                Vec::new()
            };
            if !exceptions.is_empty() {
                f.insert(
                    format!("adam.t_exceptions.{}", s.name),
                    Tensor::from_bytes(
                        DType::U32,
                        vec![exceptions.len() / 3, 3],
                        exceptions.iter().flat_map(|x| x.to_le_bytes()).collect(),
                    )?,
                );
            }
            let mut shape = s.shape.clone();
            shape[0] = kept.len();
            let t_shape = if t_per_row {
                vec![kept.len()]
            } else {
                shape.clone()
            };
            let bytes = kept_moments_bytes(st, kept, row_len, t_per_row);
            insert_state(f, &s.name, &shape, &t_shape, bytes)?;
            let mut mask = vec![0u8; rows.div_ceil(8)];
            for &r in kept {
                mask[r as usize / 8] |= 1 << (r % 8);
            }
            f.insert(
                format!("adam.mask.{}", s.name),
                Tensor::from_bytes(DType::U8, vec![mask.len()], mask)?,
            );
        }
        Ok(())
    }

    /// The rows (first dimension: a grid's entries) of a slot whose state is not all zero,
    /// ascending: every row Adam has stepped. A row outside the list has never been stepped
    /// (every step adds 1 to a stepped scalar's `t`), so its parameters are still the ones
    /// it was initialised with. Empty for a scalar slot (shape `[]`).
    pub fn stepped_rows_of(&self, s: &ParamSlot) -> Vec<u32> {
        let rows = s.shape.first().copied().unwrap_or(1);
        let row_len = s.len().checked_div(rows).unwrap_or(0);
        if row_len == 0 || s.shape.is_empty() {
            return Vec::new();
        }
        let zero = |m: &Moments| m.m.to_bits() == 0 && m.v.to_bits() == 0 && m.t == 0;
        self.state[s.range()]
            .par_chunks(row_len)
            .enumerate()
            .filter(|(_, r)| !r.iter().all(zero))
            .map(|(i, _)| i as u32)
            .collect()
    }

    /// [`AdamState::stepped_rows_of`] every slot, in slot order, with its parameter's name.
    pub fn stepped_rows(&self) -> Vec<(&str, Vec<u32>)> {
        self.slots
            .iter()
            .map(|s| (s.name.as_str(), self.stepped_rows_of(s)))
            .collect()
    }

    /// The little-endian bytes of `m`, `v` and `t` over `range`, written in one pass over the
    /// state in parallel chunks (a checkpoint holds hundreds of MB of it).
    fn state_bytes(&self, range: Range<usize>) -> [Vec<u8>; 3] {
        moments_bytes(&self.state[range])
    }
}

/// `adam.m.<name>`, `adam.v.<name>` (F32) of `shape` and `adam.t.<name>` (U32) of `t_shape`.
fn insert_state(
    f: &mut TensorFile,
    name: &str,
    shape: &[usize],
    t_shape: &[usize],
    b: [Vec<u8>; 3],
) -> Result<()> {
    let [m, v, t] = b;
    for (kind, dtype, bytes, shape) in [
        ("m", DType::F32, m, shape),
        ("v", DType::F32, v, shape),
        ("t", DType::U32, t, t_shape),
    ] {
        f.insert(
            format!("adam.{kind}.{name}"),
            Tensor::from_bytes(dtype, shape.to_vec(), bytes)?,
        );
    }
    Ok(())
}

/// The little-endian bytes of `m`, `v` and `t` of the rows `kept` (of `row_len` moments each)
/// of `st` (`t` one count per row, the row's first, with `t_per_row`), written straight from
/// the state in parallel chunks (no packed copy of the rows: on `synth small` that copy cost a
/// checkpoint write ~100 MB of peak memory).
fn kept_moments_bytes(
    st: &[Moments],
    kept: &[u32],
    row_len: usize,
    t_per_row: bool,
) -> [Vec<u8>; 3] {
    let n = kept.len() * row_len;
    let t_len = if t_per_row { kept.len() } else { n };
    let (mut m, mut v, mut t) = (vec![0u8; n * 4], vec![0u8; n * 4], vec![0u8; t_len * 4]);
    let rows_per = IO_CHUNK.div_ceil(row_len.max(1)).max(1);
    let bytes = rows_per * row_len * 4;
    let t_bytes = if t_per_row { rows_per * 4 } else { bytes };
    m.par_chunks_mut(bytes)
        .zip(v.par_chunks_mut(bytes))
        .zip(t.par_chunks_mut(t_bytes))
        .zip(kept.par_chunks(rows_per))
        .for_each(|(((m, v), t), rows)| {
            for (k, &r) in rows.iter().enumerate() {
                let src = &st[r as usize * row_len..(r as usize + 1) * row_len];
                if t_per_row {
                    t[k * 4..k * 4 + 4].copy_from_slice(&src[0].t.to_le_bytes());
                }
                for (j, s) in src.iter().enumerate() {
                    let i = k * row_len + j;
                    let b = i * 4..i * 4 + 4;
                    m[b.clone()].copy_from_slice(&s.m.to_le_bytes());
                    v[b.clone()].copy_from_slice(&s.v.to_le_bytes());
                    if !t_per_row {
                        t[b].copy_from_slice(&s.t.to_le_bytes());
                    }
                }
            }
        });
    [m, v, t]
}

/// The little-endian bytes of `m`, `v` and `t` of `st`, in parallel chunks.
fn moments_bytes(st: &[Moments]) -> [Vec<u8>; 3] {
    let mut out = [0; 3].map(|_| vec![0u8; st.len() * 4]);
    let [m, v, t] = &mut out;
    m.par_chunks_mut(IO_CHUNK * 4)
        .zip(v.par_chunks_mut(IO_CHUNK * 4))
        .zip(t.par_chunks_mut(IO_CHUNK * 4))
        .zip(st.par_chunks(IO_CHUNK))
        .for_each(|(((m, v), t), st)| {
            for (i, s) in st.iter().enumerate() {
                let b = i * 4..i * 4 + 4;
                m[b.clone()].copy_from_slice(&s.m.to_le_bytes());
                v[b.clone()].copy_from_slice(&s.v.to_le_bytes());
                t[b].copy_from_slice(&s.t.to_le_bytes());
            }
        });
    out
}

impl AdamState {
    /// Read the state of named parameters `(name, shape)` (laid out as [`AdamState::new`]) from a
    /// file written by [`AdamState::save`]. Errors name the file, the tensor and the expected
    /// dtype/shape.
    pub fn load<S: AsRef<str>>(f: &TensorFile, params: &[(S, Vec<usize>)]) -> Result<AdamState> {
        let mut st = AdamState::new(params);
        for s in st.slots.clone() {
            // Rows kept by `save_compact` (absent: every row): its row mask, or the row list
            // of earlier checkpoints.
            let rows = if f.tensors.contains_key(&format!("adam.mask.{}", s.name)) {
                Some(mask_rows(f, &s)?)
            } else if f.tensors.contains_key(&format!("adam.rows.{}", s.name)) {
                Some(kept_rows(f, &s)?)
            } else {
                None
            };
            let mut shape = s.shape.clone();
            if let Some(r) = &rows {
                shape[0] = r.len();
            }
            let get = |kind: &str, dtype, shape: &[usize]| {
                f.get_checked(&format!("adam.{kind}.{}", s.name), dtype, shape)
                    .map(|t| &t.data[..])
            };
            // A compact slot's step counts may be one per row (`[k]`).
            let t_per_row = rows.is_some()
                && shape.len() > 1
                && f.tensors
                    .get(&format!("adam.t.{}", s.name))
                    .is_some_and(|t| t.shape == shape[..1]);
            let (m, v, t) = (
                get("m", DType::F32, &shape)?,
                get("v", DType::F32, &shape)?,
                get(
                    "t",
                    DType::U32,
                    if t_per_row { &shape[..1] } else { &shape },
                )?,
            );
            if let Some(rows) = rows {
                let row_len = s.len() / s.shape[0];
                let word =
                    |b: &[u8], i: usize| -> [u8; 4] { b[i * 4..i * 4 + 4].try_into().unwrap() };
                let out = &mut st.state[s.range()];
                for (k, &r) in rows.iter().enumerate() {
                    for j in 0..row_len {
                        let i = k * row_len + j;
                        out[r as usize * row_len + j] = Moments {
                            m: f32::from_le_bytes(word(m, i)),
                            v: f32::from_le_bytes(word(v, i)),
                            t: u32::from_le_bytes(word(t, if t_per_row { k } else { i })),
                        };
                    }
                }
                let name = format!("adam.t_exceptions.{}", s.name);
                if f.tensors.contains_key(&name) {
                    let label = f
                        .source
                        .as_ref()
                        .map_or("<checkpoint>".into(), |p| p.display().to_string());
                    let x = f.get(&name)?;
                    if !t_per_row || x.dtype != DType::U32 || x.shape.len() != 2 || x.shape[1] != 3
                    {
                        bail!(
                            "{label}: tensor {name} is {} {:?}, expected U32 [e, 3] beside a step count per row (adam.t.{} of shape [{}])",
                            x.dtype,
                            x.shape,
                            s.name,
                            rows.len()
                        );
                    }
                    let x = f.get_u32(&name)?;
                    let mut last = None;
                    for e in x.chunks_exact(3) {
                        let (k, j, t) = (e[0] as usize, e[1] as usize, e[2]);
                        if k >= rows.len() || j >= row_len || last.is_some_and(|l| l >= (k, j)) {
                            bail!(
                                "{label}: tensor {name}: entry ({k}, {j}) not ascending or beyond the {} kept rows of {row_len} scalars",
                                rows.len()
                            );
                        }
                        last = Some((k, j));
                        out[rows[k] as usize * row_len + j].t = t;
                    }
                }
                continue;
            }
            // Decoded straight from the file's bytes into the state, in parallel chunks.
            let word = |b: &[u8], i: usize| -> [u8; 4] { b[i * 4..i * 4 + 4].try_into().unwrap() };
            st.state[s.range()]
                .par_chunks_mut(IO_CHUNK)
                .enumerate()
                .for_each(|(c, out)| {
                    let [m, v, t] = [m, v, t].map(|b| &b[c * IO_CHUNK * 4..]);
                    for (i, o) in out.iter_mut().enumerate() {
                        *o = Moments {
                            m: f32::from_le_bytes(word(m, i)),
                            v: f32::from_le_bytes(word(v, i)),
                            t: u32::from_le_bytes(word(t, i)),
                        };
                    }
                });
        }
        Ok(st)
    }
}

/// The rows of a compact slot from its `adam.mask.<name>`, checked: U8 `[ceil(rows / 8)]`, no bit
/// set past the slot's rows.
fn mask_rows(f: &TensorFile, s: &ParamSlot) -> Result<Vec<u32>> {
    let name = format!("adam.mask.{}", s.name);
    let t = f.get(&name)?;
    let label = f
        .source
        .as_ref()
        .map_or("<checkpoint>".into(), |p| p.display().to_string());
    let n = s.shape.first().copied().unwrap_or(0);
    if t.dtype != DType::U8 || t.shape != [n.div_ceil(8)] || s.shape.is_empty() {
        bail!(
            "{label}: tensor {name} is {} {:?}, expected U8 [{}] (a bit per row of a parameter of shape {:?})",
            t.dtype,
            t.shape,
            n.div_ceil(8),
            s.shape
        );
    }
    let mut rows = Vec::new();
    for (i, &b) in t.data.iter().enumerate() {
        for bit in 0..8 {
            if b >> bit & 1 == 1 {
                let r = i * 8 + bit;
                if r >= n {
                    bail!("{label}: tensor {name}: row {r} beyond the parameter's {n} rows");
                }
                rows.push(r as u32);
            }
        }
    }
    Ok(rows)
}

/// The `adam.rows.<name>` of a compact slot (checkpoints before `adam.mask`), checked:
/// ascending, distinct, within the slot's rows.
fn kept_rows(f: &TensorFile, s: &ParamSlot) -> Result<Vec<u32>> {
    let name = format!("adam.rows.{}", s.name);
    let t = f.get(&name)?;
    let label = f
        .source
        .as_ref()
        .map_or("<checkpoint>".into(), |p| p.display().to_string());
    if t.dtype != DType::U32 || t.shape.len() != 1 || s.shape.is_empty() {
        bail!(
            "{label}: tensor {name} is {} {:?}, expected U32 [k] (rows of a parameter of shape {:?})",
            t.dtype,
            t.shape,
            s.shape
        );
    }
    let rows = f.get_u32(&name)?;
    let n = s.shape[0];
    if let Some(w) = rows.windows(2).find(|w| w[0] >= w[1]) {
        bail!(
            "{label}: tensor {name}: rows not ascending ({} then {})",
            w[0],
            w[1]
        );
    }
    if let Some(&r) = rows.last().filter(|&&r| r as usize >= n) {
        bail!("{label}: tensor {name}: row {r} beyond the parameter's {n} rows");
    }
    Ok(rows)
}

/// Sort and deduplicate a touched-entry list into the form [`AdamState::step_sparse`] requires.
pub fn normalize_entries(entries: &mut Vec<u32>) {
    entries.sort_unstable();
    entries.dedup();
}

/// Zero the gradients of the listed entries only (so clearing a sparse table's gradient costs
/// O(entries), like the step).
pub fn zero_entries(grads: &mut [f32], entries: &[u32], entry_len: usize) {
    for &e in entries {
        let b = e as usize * entry_len;
        grads[b..b + entry_len].fill(0.0);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// `save_compact` keeps the stepped rows only and reads back to the same state; a slot with
    /// every row stepped is written whole; a bad row list is an error naming the tensor.
    #[test]
    fn compact_state_round_trips_and_checks_its_rows() {
        let specs = [("a", vec![5, 2]), ("b", vec![3])];
        let mut st = AdamState::new(&specs);
        for (i, m) in st.state.iter_mut().enumerate() {
            // Rows 1 and 3 of `a` (one scalar of row 3) and every scalar of `b` have stepped.
            if matches!(i, 2 | 3 | 7) || i >= 10 {
                *m = Moments {
                    m: 0.5 + i as f32,
                    v: 0.25,
                    t: i as u32,
                };
            }
        }
        let mut f = TensorFile::default();
        st.save_compact(&mut f).unwrap();
        assert_eq!(f.get("adam.mask.a").unwrap().data, vec![0b1010]);
        assert_eq!(f.get("adam.m.a").unwrap().shape, vec![2, 2]);
        // One count per row (its first scalar's); the second scalars of rows 1 and 3 (counts 3
        // and 7) are the exceptions.
        assert_eq!(f.get_u32("adam.t.a").unwrap(), vec![2, 0]);
        assert_eq!(
            f.get_u32("adam.t_exceptions.a").unwrap(),
            vec![0, 1, 3, 1, 1, 7]
        );
        assert!(!f.tensors.contains_key("adam.mask.b"));
        assert_eq!(AdamState::load(&f, &specs).unwrap().state, st.state);
        // Rows whose scalars share a count: one count per row, read back the same.
        let mut even = st.clone();
        for i in [2, 3, 6, 7] {
            even.state[i] = Moments {
                m: 1.0,
                v: 0.5,
                t: 7,
            };
        }
        let mut g = TensorFile::default();
        even.save_compact(&mut g).unwrap();
        assert_eq!(g.get_u32("adam.t.a").unwrap(), vec![7, 7]);
        assert!(!g.tensors.contains_key("adam.t_exceptions.a"));
        assert_eq!(AdamState::load(&g, &specs).unwrap().state, even.state);
        // A bad exception list is an error naming it.
        for (x, want) in [
            (vec![1u32, 0, 5, 0, 0, 5], "not ascending"),
            (vec![2, 0, 5], "beyond"),
        ] {
            let mut h = f.clone();
            let n = x.len() / 3;
            let b: Vec<u8> = x.iter().flat_map(|v| v.to_le_bytes()).collect();
            h.insert(
                "adam.t_exceptions.a",
                Tensor::from_bytes(DType::U32, vec![n, 3], b).unwrap(),
            );
            let e = format!("{:#}", AdamState::load(&h, &specs).unwrap_err());
            assert!(e.contains("adam.t_exceptions.a") && e.contains(want), "{e}");
        }
        for (mask, want) in [
            (vec![0u8, 0], "expected U8 [1]"),
            (vec![0b10_0010], "beyond"),
        ] {
            let mut g = f.clone();
            let len = mask.len();
            g.insert(
                "adam.mask.a",
                Tensor::from_bytes(DType::U8, vec![len], mask).unwrap(),
            );
            let e = format!("{:#}", AdamState::load(&g, &specs).unwrap_err());
            assert!(e.contains("adam.mask.a") && e.contains(want), "{e}");
        }
        // The row lists of earlier checkpoints (`adam.rows`) still load.
        let mut old = f.clone();
        old.tensors.remove("adam.mask.a");
        let b: Vec<u8> = [1u32, 3].iter().flat_map(|r| r.to_le_bytes()).collect();
        old.insert(
            "adam.rows.a",
            Tensor::from_bytes(DType::U32, vec![2], b).unwrap(),
        );
        assert_eq!(AdamState::load(&old, &specs).unwrap().state, st.state);
        for (rows, want) in [(vec![3u32, 1], "not ascending"), (vec![1, 5], "beyond")] {
            let mut g = old.clone();
            let b: Vec<u8> = rows.iter().flat_map(|r| r.to_le_bytes()).collect();
            g.insert(
                "adam.rows.a",
                Tensor::from_bytes(DType::U32, vec![2], b).unwrap(),
            );
            let e = format!("{:#}", AdamState::load(&g, &specs).unwrap_err());
            assert!(e.contains("adam.rows.a") && e.contains(want), "{e}");
        }
    }

    /// The kept `lr_t` tables give the values of a fresh computation whatever the order of
    /// calls: one key growing step by step, keys interleaved, more keys than are kept, a
    /// smaller `t_max` after a larger one.
    #[test]
    fn lr_tables_kept_across_calls_equal_fresh_ones() {
        let fresh = |lr_k: f64, b1: f32, b2: f32, t_max: usize| -> Vec<f32> {
            std::iter::once(0.0)
                .chain((1..=t_max).map(|t| {
                    let (s2, d1) = bias_factors(b1, b2, t as u32);
                    (lr_k * s2 / d1) as f32
                }))
                .collect()
        };
        let mut cache = BiasCache::default();
        let keys: Vec<(f64, f32, f32)> = (0..LR_TABLES + 3)
            .map(|i| {
                (
                    1e-2 * (1.0 + i as f64 / 7.0),
                    0.9,
                    if i % 2 == 0 { 0.99 } else { 0.999 },
                )
            })
            .collect();
        let mut calls = Vec::new();
        for k in 1..40usize {
            calls.push((keys[0], k));
            calls.push((keys[k % keys.len()], k));
        }
        calls.push((keys[0], 5));
        calls.push((keys[3], 60));
        for ((lr_k, b1, b2), t_max) in calls {
            let got = cache.lr_table(lr_k, b1, b2, t_max).to_vec();
            let want = fresh(lr_k, b1, b2, t_max);
            assert_eq!(
                got.iter().map(|v| v.to_bits()).collect::<Vec<_>>(),
                want.iter().map(|v| v.to_bits()).collect::<Vec<_>>(),
                "lr_k {lr_k}, betas {b1} {b2}, t_max {t_max}"
            );
        }
        assert!(cache.lr.len() <= LR_TABLES);
    }

    #[test]
    fn pow_by_squaring() {
        assert_eq!(pow_u64(0.5, 0), 1.0);
        assert_eq!(pow_u64(0.5, 10), 1.0 / 1024.0);
        assert!((pow_u64(0.999, 1000) - 0.999f64.powi(1000)).abs() < 1e-14);
    }

    #[test]
    fn schedule_factors() {
        let s = LrSchedule {
            warmup_steps: 4,
            ..Default::default()
        };
        let f: Vec<f64> = (0..6).map(|k| s.factor(k)).collect();
        assert_eq!(f, vec![0.25, 0.5, 0.75, 1.0, 1.0, 1.0]);
        let s = LrSchedule {
            decay_start: 2,
            decay_interval: 3,
            decay_base: 0.5,
            decay_end: 9,
            ..Default::default()
        };
        let f: Vec<f64> = (0..14).map(|k| s.factor(k)).collect();
        // Decays at k = 2, 5, 8 (not 11: past decay_end).
        let want = [
            1.0, 1.0, 0.5, 0.5, 0.5, 0.25, 0.25, 0.25, 0.125, 0.125, 0.125, 0.125, 0.125, 0.125,
        ];
        assert_eq!(f, want);
    }

    #[test]
    fn config_toml_roundtrip_and_validation() {
        let c = AdamConfig::default();
        let text = toml::to_string(&c).unwrap();
        let back: AdamConfig = toml::from_str(&text).unwrap();
        assert_eq!(back, c);
        let partial: AdamConfig = toml::from_str("[grid_h]\nlr = 0.5\n").unwrap();
        assert_eq!(partial.grid_h.lr, 0.5);
        assert!(
            partial.grid_h.sparse,
            "role sets sparse even when the group is given"
        );
        assert!(!partial.shader.sparse && partial.appearance.sparse);
        assert!(toml::from_str::<AdamConfig>("[grid_h]\nsparse = false\n").is_err());
        assert!(partial.validate().is_ok());
        let mut bad = c.clone();
        bad.grid_d.beta2 = 1.0;
        assert!(format!("{:#}", bad.validate().unwrap_err()).contains("grid_d"));
    }
}
