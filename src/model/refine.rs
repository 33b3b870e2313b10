//! The mesh refinement's part of the model (beyond the paper; SPEC §4.11, docs/geometry.md): its
//! configuration (`[model.refine]`, [`RefineConfig`]) and the parameters of the offset field as a
//! checkpoint stores them ([`RefineParams`]: the grids, the per-vertex residual, the offsets eval
//! and render apply). What they mean and how they are computed and trained is `src/refine/`.

use anyhow::{bail, ensure, Result};
use serde::{Deserialize, Serialize};

/// `[model.refine]`: joint refinement of the mesh (module docs; schedule in `refine/refiner.rs`).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct RefineConfig {
    /// Move the mesh (off by default: the paper's fixed mesh).
    pub enabled: bool,
    /// Fraction of `train.steps` before the mesh starts to move (the features settle first).
    pub start: f64,
    /// Fraction of `train.steps` over which the field's levels are switched on after `start`,
    /// coarsest first (level k of the `levels + per_vertex` levels at `start + k·coarse_to_fine/n`).
    pub coarse_to_fine: f64,
    /// Grid levels of the offset field.
    pub levels: u32,
    /// Cells per unit of the coarsest grid (each level doubles it).
    pub base_resolution: u32,
    /// A per-vertex residual as the finest level.
    pub per_vertex: bool,
    /// Weight of the membrane (Laplacian) energy of the per-vertex residual.
    pub laplacian: f64,
    /// Weight of the thin-plate (bi-Laplacian) energy of the per-vertex residual.
    pub bilaplacian: f64,
    /// The vertex gradient goes through the hash-grid levels (H and D) of at most this many cells
    /// per unit only, from `[0]` when the mesh starts moving to `[1]` at the end of the run
    /// (geometric interpolation): coarse to fine. `[0, 0]` = every level (the exact gradient).
    /// Fine levels carry texture, not shape: through them the gradient on a proxy is noise
    /// (`examples/refine_probe.rs`, docs/geometry.md).
    pub gradient_cells: [f64; 2],
    /// Fraction of `train.steps` after which the mesh stops moving (the features converge on the
    /// final mesh).
    pub stop: f64,
    /// The vertex gradient is summed over this many steps, then the offsets take one Adam step
    /// and the BVH is rebuilt from the moved mesh (a batch's gradient alone is mostly noise on the
    /// coarse grids: `examples/refine_probe.rs`).
    pub update_every: u32,
    /// Sub-samples whose ray meets the triangle's plane at |cos| below this give no vertex gradient.
    pub min_cos: f64,
    /// Adam on the offset parameters (sparse: untouched nodes keep their moments).
    pub lr: f32,
    /// Learning rate of the last update before `stop` (geometric from `lr` at the first update;
    /// 0 = `lr` throughout). Adam's steps are about `lr` whatever the gradient's size, so once the
    /// coarse error is gone a constant rate random-walks the mesh on the noise (docs/geometry.md).
    pub lr_end: f32,
    pub beta1: f32,
    pub beta2: f32,
    pub epsilon: f32,
    /// Query the feature grids (H and D) at the *training* mesh's point with the barycentrics at
    /// which the ray hits the moved triangle, instead of at the moved hit: the features stay
    /// attached to the surface as it moves, and the offsets learn only from what the moved
    /// geometry changes (which surface point each ray sees: parallax). Off by default.
    pub anchored: bool,
    /// Acceptance test of every update (a trust region; 0 = off, docs/geometry.md §3): the
    /// photometric MSE of this many fixed batches (`train.batch_pixels` pixels each, a pure
    /// function of the seed and the update's step, `refine/trust.rs`) is measured with the rays
    /// cast against the mesh before and after the proposed update; the update is kept only if
    /// the MSE falls by more than `trust_margin` (relative), else its step is halved and tried
    /// again, at most `trust_halvings` times, then dropped (the mesh stays where it was).
    #[serde(skip_serializing_if = "is_zero_u32")]
    pub trust_batches: u32,
    /// Relative fall of the acceptance MSE an update must achieve (0: any fall).
    #[serde(skip_serializing_if = "is_zero_f64")]
    pub trust_margin: f64,
    /// Halvings of a rejected update's step before it is dropped.
    #[serde(skip_serializing_if = "is_two")]
    pub trust_halvings: u32,
    /// Validation views for the acceptance test (0 = off): the training views whose appearance
    /// row r has `r % trust_holdout == trust_holdout − 1` give no offset gradient (the features
    /// still train on them), and the acceptance batches are drawn from them only, so the test
    /// sees geometry that fits the other views but not these.
    #[serde(skip_serializing_if = "is_zero_u32")]
    pub trust_holdout: u32,
    /// Weight of an L2 prior `prior · Σ_l Σ_nodes G_l² (+ Σ_i r_i²)` pulling the offset field
    /// towards zero (added to the summed gradient at each update, times the steps summed).
    #[serde(skip_serializing_if = "is_zero_f64")]
    pub prior: f64,
    /// Weight of the loss's gradient through the hit point (the learned features' signal);
    /// 0 = the mesh is moved by the photo-consistency term (and smoothness, prior) only.
    /// Always written; absent (a table written before issue #39) = 1, the value such a build
    /// left out.
    #[serde(default = "one_f64")]
    pub features: f64,
    /// Weight of the multi-view photo-consistency energy of the training photos (0 = off;
    /// `refine/photo.rs`, `refine/photo_term.rs`). Always written; absent (a table written
    /// before issue #39) = 0.
    #[serde(default)]
    pub photo: f64,
    /// Reference patches drawn per training step.
    #[serde(skip_serializing_if = "is_default_photo_pixels")]
    pub photo_pixels: u32,
    /// Side of a patch in pixels (odd; 1 = single pixels, huber only).
    #[serde(skip_serializing_if = "is_default_photo_patch")]
    pub photo_patch: u32,
    /// `zncc` or `huber` (`refine/photo.rs`).
    #[serde(skip_serializing_if = "is_default_measure")]
    pub photo_measure: PhotoMeasure,
    /// Image levels (photos box-downsampled by 2^l), from `[0]` when the mesh starts moving to
    /// `[1]` at its last update, in equal spans of steps (coarse to fine).
    #[serde(skip_serializing_if = "is_default_photo_levels")]
    pub photo_levels: [u32; 2],
    /// Neighbour views kept per training view (the best by shared, visible, well-triangulated
    /// surface; `refine/photo_term.rs`).
    #[serde(skip_serializing_if = "is_default_photo_neighbours")]
    pub photo_neighbours: u32,
    /// Range of the angle (degrees) between the two views' rays at the surface for a pair.
    #[serde(skip_serializing_if = "is_default_photo_angle")]
    pub photo_angle: [f64; 2],
    /// Largest ratio of the two views' pixel footprints at the surface for a pair.
    #[serde(skip_serializing_if = "is_default_photo_scale")]
    pub photo_scale: f64,
    /// The training mesh is taken to be off by up to this many pixel footprints of the coarsest
    /// training view (a mesh made from the far views); each view's deepest image level is chosen
    /// so that this displacement is at most [`PHOTO_PULL`] of its pixels there (at least
    /// `photo_levels[0]`; `refine/photo_term.rs`): views much finer than the coarsest (close-ups)
    /// start deeper and go coarse to fine over more levels. 0 (the default) = every view uses
    /// `photo_levels`. Opt-in with the next two (`configs/refine-cross.toml`): on an exact mesh
    /// it moves the surface more than the defaults (docs/geometry.md §5). Always written, like
    /// the next two; absent (a table written before the cross-scale refinement) = 0, false, false.
    #[serde(default)]
    pub photo_reach: f64,
    /// Weight each view's patches by the inverse of the number of training views in its scale
    /// band (footprint ratio within `photo_scale`), normalised to a mean of 1: a few close views
    /// count as much as many far ones.
    #[serde(default)]
    pub photo_balance: bool,
    /// Choose the neighbour views again from the moved mesh at every BVH rebuild (else once,
    /// from the training mesh).
    #[serde(default)]
    pub photo_rechoose: bool,
    /// How the offset field steps at an update: `adam` (tiny-cuda-nn rules) or `gauss-newton`
    /// (the summed gradient over the photo term's summed curvature: `refine/refiner.rs`).
    /// Always written; absent (a table written before issue #39) = `adam`.
    #[serde(default)]
    pub optimizer: RefineOptimizer,
    /// Levenberg damping of the Gauss–Newton step, relative to the mean curvature of the level's
    /// nodes that have one.
    #[serde(skip_serializing_if = "is_default_damping")]
    pub damping: f64,
}

/// How a reference patch and its reprojection are compared.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "lowercase")]
pub enum PhotoMeasure {
    /// One minus the zero-mean normalised cross-correlation of the patch (RGB, per-channel means).
    #[default]
    Zncc,
    /// Mean Huber penalty of the colour differences.
    Huber,
}

impl PhotoMeasure {
    pub fn name(self) -> &'static str {
        match self {
            PhotoMeasure::Zncc => "zncc",
            PhotoMeasure::Huber => "huber",
        }
    }
}

/// The offset field's step rule (`[model.refine] optimizer`).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "kebab-case")]
pub enum RefineOptimizer {
    #[default]
    Adam,
    /// `Δ = −lr · G / (n · H + λ)` per node (G the summed gradient, H the photo term's summed
    /// curvature spread over the nodes, n the active field levels, λ = damping · mean H).
    GaussNewton,
}

const DAMPING: f64 = 0.1;

fn is_default_damping(v: &f64) -> bool {
    *v == DAMPING
}

const PHOTO_PIXELS: u32 = 1024;
const PHOTO_PATCH: u32 = 5;
const PHOTO_LEVELS: [u32; 2] = [2, 0];
const PHOTO_NEIGHBOURS: u32 = 4;
const PHOTO_ANGLE: [f64; 2] = [5.0, 45.0];
const PHOTO_SCALE: f64 = 2.0;
/// Pixels a patch's energy pulls in from (`photo_reach`): about half a 5×5 patch.
pub const PHOTO_PULL: f64 = 2.0;

/// Deepest image level the photo term uses.
pub const PHOTO_MAX_LEVEL: u32 = 8;

/// The deepest image level, from `l0` up to [`PHOTO_MAX_LEVEL`], at which a `w × h` photo holds a
/// patch and its pull-in on either side (`patch + 2·⌈PHOTO_PULL⌉` pixels high and wide), else `l0`
/// (`refine::photo_term::level_cap`; the memory estimate counts the levels it allows).
pub fn photo_level_cap(w: u32, h: u32, l0: u32, patch: u32) -> u32 {
    let side = patch + 2 * PHOTO_PULL.ceil() as u32;
    let mut l = l0;
    while l < PHOTO_MAX_LEVEL && (w.min(h) >> (l + 1)) >= side {
        l += 1;
    }
    l
}

fn one_f64() -> f64 {
    1.0
}
fn is_default_photo_pixels(v: &u32) -> bool {
    *v == PHOTO_PIXELS
}
fn is_default_photo_patch(v: &u32) -> bool {
    *v == PHOTO_PATCH
}
fn is_default_measure(v: &PhotoMeasure) -> bool {
    *v == PhotoMeasure::default()
}
fn is_default_photo_levels(v: &[u32; 2]) -> bool {
    *v == PHOTO_LEVELS
}
fn is_default_photo_neighbours(v: &u32) -> bool {
    *v == PHOTO_NEIGHBOURS
}
fn is_default_photo_angle(v: &[f64; 2]) -> bool {
    *v == PHOTO_ANGLE
}
fn is_default_photo_scale(v: &f64) -> bool {
    *v == PHOTO_SCALE
}

fn is_zero_u32(v: &u32) -> bool {
    *v == 0
}
fn is_zero_f64(v: &f64) -> bool {
    *v == 0.0
}
fn is_two(v: &u32) -> bool {
    *v == 2
}

impl Default for RefineConfig {
    /// The best measured setting (docs/geometry.md §4): the mesh moved by the multi-view
    /// photo-consistency of the training photos (Gauss–Newton steps on zncc of 5×5 patches,
    /// image levels 2 → 0, the offset field's grids switched on coarse to fine over the first
    /// 60 % of the run), the features anchored to the training mesh and left out of the mesh's
    /// gradient. `[model.refine] enabled = true` alone turns it on. The refinement through the
    /// learned features' gradient (docs/geometry.md §3) is [`RefineConfig::learned`].
    fn default() -> Self {
        RefineConfig {
            anchored: true,
            features: 0.0,
            photo: 1.0,
            optimizer: RefineOptimizer::GaussNewton,
            lr: 1.0,
            start: 0.0,
            stop: 0.6,
            coarse_to_fine: 0.6,
            ..RefineConfig::learned()
        }
    }
}

impl RefineConfig {
    /// The defaults before the photo-consistency term became the default (issue #39): the mesh
    /// moved by Adam on the loss's gradient through the hit point of the learned features
    /// (docs/geometry.md §3). A stored `[model.refine]` table that lacks `features`, `photo` or
    /// `optimizer` was written by such a build, which left them out at these values.
    pub fn learned() -> Self {
        RefineConfig {
            enabled: false,
            start: 0.3,
            coarse_to_fine: 0.3,
            levels: 5,
            base_resolution: 4,
            per_vertex: false,
            laplacian: 0.0,
            bilaplacian: 1e-3,
            gradient_cells: [32.0, 512.0],
            stop: 0.85,
            update_every: 20,
            min_cos: 0.1,
            lr: 1e-4,
            lr_end: 0.0,
            beta1: 0.9,
            beta2: 0.99,
            epsilon: 1e-15,
            anchored: false,
            trust_batches: 0,
            trust_margin: 0.0,
            trust_halvings: 2,
            trust_holdout: 0,
            prior: 0.0,
            features: 1.0,
            photo: 0.0,
            photo_pixels: PHOTO_PIXELS,
            photo_patch: PHOTO_PATCH,
            photo_measure: PhotoMeasure::default(),
            photo_levels: PHOTO_LEVELS,
            photo_neighbours: PHOTO_NEIGHBOURS,
            photo_angle: PHOTO_ANGLE,
            photo_scale: PHOTO_SCALE,
            photo_reach: 0.0,
            photo_balance: false,
            photo_rechoose: false,
            optimizer: RefineOptimizer::default(),
            damping: DAMPING,
        }
    }
}

impl RefineConfig {
    /// The default (absent from a config's TOML, so configs without refinement are unchanged).
    pub fn is_default(&self) -> bool {
        *self == RefineConfig::default()
    }

    pub fn validate(&self) -> Result<()> {
        let mut bad = Vec::new();
        self.check_field(&mut bad);
        self.check_adam(&mut bad);
        self.check_trust(&mut bad);
        self.check_weights(&mut bad);
        self.check_photo(&mut bad);
        self.check_gauss_newton(&mut bad);
        if !bad.is_empty() {
            bail!("{}", bad.join("; "));
        }
        Ok(())
    }

    /// The offset field and its schedule (each problem into `bad`, in the order [`RefineConfig::validate`] names them).
    fn check_field(&self, bad: &mut Vec<String>) {
        let frac = |x: f64| (0.0..=1.0).contains(&x);
        if !frac(self.start) {
            bad.push(format!(
                "start = {} (a fraction of train.steps, in [0, 1])",
                self.start
            ));
        }
        if !frac(self.coarse_to_fine) {
            bad.push(format!(
                "coarse_to_fine = {} (a fraction of train.steps, in [0, 1])",
                self.coarse_to_fine
            ));
        }
        if self.levels > 8 {
            bad.push(format!("levels = {} (at most 8)", self.levels));
        }
        if self.levels > 0 && !(1..=64).contains(&self.base_resolution) {
            bad.push(format!(
                "base_resolution = {} (1..=64)",
                self.base_resolution
            ));
        }
        if self.levels > 0 && (self.base_resolution as u64) << (self.levels - 1) > 256 {
            bad.push(format!(
                "base_resolution · 2^(levels−1) = {} cells per unit (at most 256)",
                (self.base_resolution as u64) << (self.levels - 1)
            ));
        }
        if self.levels == 0 && !self.per_vertex {
            bad.push("levels = 0 and per_vertex = false: nothing can move".into());
        }
        for (k, v) in [
            ("laplacian", self.laplacian),
            ("bilaplacian", self.bilaplacian),
        ] {
            if !(v.is_finite() && v >= 0.0) {
                bad.push(format!("{k} = {v} (a finite value ≥ 0)"));
            }
        }
        let [g0, g1] = self.gradient_cells;
        if !(g0.is_finite() && g1.is_finite() && g0 >= 0.0 && g1 >= 0.0 && (g0 > 0.0) == (g1 > 0.0))
        {
            bad.push(format!(
                "gradient_cells = [{g0}, {g1}] (two finite values > 0, or [0, 0] for every level)"
            ));
        }
        if !frac(self.stop) || self.stop < self.start {
            bad.push(format!(
                "stop = {} (a fraction of train.steps, in [start, 1] = [{}, 1])",
                self.stop, self.start
            ));
        }
        if self.update_every == 0 {
            bad.push("update_every = 0 (at least 1)".into());
        }
        if !(0.0..1.0).contains(&self.min_cos) {
            bad.push(format!("min_cos = {} (in [0, 1))", self.min_cos));
        }
    }

    /// Adam's settings.
    fn check_adam(&self, bad: &mut Vec<String>) {
        if !(self.lr.is_finite() && self.lr >= 0.0) {
            bad.push(format!("lr = {} (a finite value ≥ 0)", self.lr));
        }
        if !(self.lr_end.is_finite() && self.lr_end >= 0.0) {
            bad.push(format!("lr_end = {} (a finite value ≥ 0)", self.lr_end));
        }
        if !(0.0..1.0).contains(&self.beta1) || !(0.0..1.0).contains(&self.beta2) {
            bad.push(format!(
                "beta1 = {}, beta2 = {} (each in [0, 1))",
                self.beta1, self.beta2
            ));
        }
        if !(self.epsilon.is_finite() && self.epsilon >= 0.0) {
            bad.push(format!("epsilon = {} (a finite value ≥ 0)", self.epsilon));
        }
    }

    /// The trust region.
    fn check_trust(&self, bad: &mut Vec<String>) {
        if !(self.trust_margin.is_finite() && (0.0..1.0).contains(&self.trust_margin)) {
            bad.push(format!("trust_margin = {} (in [0, 1))", self.trust_margin));
        }
        if self.trust_halvings > 16 {
            bad.push(format!(
                "trust_halvings = {} (at most 16)",
                self.trust_halvings
            ));
        }
        if self.trust_batches > 64 {
            bad.push(format!(
                "trust_batches = {} (at most 64)",
                self.trust_batches
            ));
        }
        if self.trust_holdout == 1 {
            bad.push("trust_holdout = 1 (every view would be held out: 0 = off, or ≥ 2)".into());
        }
        if self.trust_holdout > 0 && self.trust_batches == 0 {
            bad.push(format!(
                "trust_holdout = {} needs trust_batches > 0 (the held-out views serve the acceptance test)",
                self.trust_holdout
            ));
        }
    }

    /// The weights of the prior, the feature gradient and the photo term.
    fn check_weights(&self, bad: &mut Vec<String>) {
        if !(self.prior.is_finite() && self.prior >= 0.0) {
            bad.push(format!("prior = {} (a finite value ≥ 0)", self.prior));
        }
        if !(self.features.is_finite() && self.features >= 0.0) {
            bad.push(format!("features = {} (a finite value ≥ 0)", self.features));
        }
        if !(self.photo.is_finite() && self.photo >= 0.0) {
            bad.push(format!("photo = {} (a finite value ≥ 0)", self.photo));
        }
        if self.enabled && self.features == 0.0 && self.photo == 0.0 {
            bad.push(
                "features = 0 and photo = 0: nothing would move the mesh (set photo > 0, or features > 0)"
                    .into(),
            );
        }
    }

    /// The photo term.
    fn check_photo(&self, bad: &mut Vec<String>) {
        if !(1..=1 << 16).contains(&self.photo_pixels) {
            bad.push(format!(
                "photo_pixels = {} (1..=65536 patches per step)",
                self.photo_pixels
            ));
        }
        if self.photo_patch % 2 == 0 || !(1..=15).contains(&self.photo_patch) {
            bad.push(format!(
                "photo_patch = {} (an odd side in 1..=15 pixels)",
                self.photo_patch
            ));
        }
        if self.photo_measure == PhotoMeasure::Zncc && self.photo_patch < 3 {
            bad.push(format!(
                "photo_patch = {} with photo_measure = \"zncc\" (a correlation needs a patch of at least 3×3; use \"huber\" for single pixels)",
                self.photo_patch
            ));
        }
        let [l0, l1] = self.photo_levels;
        if l0 > 8 || l1 > l0 {
            bad.push(format!(
                "photo_levels = [{l0}, {l1}] (coarse to fine: [0] ≥ [1], at most 8)"
            ));
        }
        if !(1..=64).contains(&self.photo_neighbours) {
            bad.push(format!(
                "photo_neighbours = {} (1..=64)",
                self.photo_neighbours
            ));
        }
        let [a0, a1] = self.photo_angle;
        if !(a0.is_finite() && a1.is_finite() && 0.0 <= a0 && a0 < a1 && a1 <= 90.0) {
            bad.push(format!(
                "photo_angle = [{a0}, {a1}] (degrees, 0 ≤ [0] < [1] ≤ 90)"
            ));
        }
        if !(self.photo_scale.is_finite() && self.photo_scale >= 1.0) {
            bad.push(format!("photo_scale = {} (≥ 1)", self.photo_scale));
        }
        if !(self.photo_reach.is_finite() && self.photo_reach >= 0.0) {
            bad.push(format!(
                "photo_reach = {} (coarsest-view footprints, a finite value ≥ 0)",
                self.photo_reach
            ));
        }
    }

    /// The Gauss–Newton step.
    fn check_gauss_newton(&self, bad: &mut Vec<String>) {
        if !(self.damping.is_finite() && self.damping >= 0.0) {
            bad.push(format!("damping = {} (a finite value ≥ 0)", self.damping));
        }
        if self.enabled && self.optimizer == RefineOptimizer::GaussNewton && self.photo == 0.0 {
            bad.push(
                "optimizer = \"gauss-newton\" needs the photo term's curvature: set photo > 0"
                    .into(),
            );
        }
    }

    /// Cells per unit of grid level l.
    pub fn resolution(&self, l: u32) -> usize {
        (self.base_resolution as usize) << l
    }

    /// Number of field levels (grids, then the per-vertex residual).
    pub fn n_levels(&self) -> u32 {
        self.levels + self.per_vertex as u32
    }
}

/// The offset field's parameters and the offsets derived from them (f32, saved in checkpoints).
#[derive(Clone, Debug, PartialEq)]
pub struct RefineParams {
    /// `[levels][(R_l + 1)³]`.
    pub grids: Vec<Vec<f32>>,
    /// `[V]` per-vertex residual (empty without `per_vertex`).
    pub vertex: Vec<f32>,
    /// `[V]` θ at the last [`RefineParams::sync_offsets`] (what eval/render apply).
    pub offsets: Vec<f32>,
    /// `[V]` θ the current BVH was built from (resume rebuilds it exactly).
    pub traced: Vec<f32>,
    /// Gradients summed since the last update (f64), one per grid level, then the residual's
    /// (saved, so a run resumed between two updates continues exactly).
    pub pending: Vec<Vec<f64>>,
    /// The photo term's curvature summed since the last update, shaped as `pending`
    /// (`optimizer = "gauss-newton"` only; else empty).
    pub pending_h: Vec<Vec<f64>>,
}

/// Tensor name of grid level l.
pub fn grid_name(l: usize) -> String {
    format!("refine.grid.{l}")
}
pub const VERTEX_NAME: &str = "refine.vertex";
pub const OFFSETS_NAME: &str = "refine.offsets";
pub const TRACED_NAME: &str = "refine.traced";

/// Tensor name of the pending gradient of tensor `name` (`refine.grid.{l}` or `refine.vertex`).
pub fn pending_name(name: &str) -> String {
    format!("refine.pending.{}", name.trim_start_matches("refine."))
}

/// Tensor name of the pending curvature of tensor `name` (`optimizer = "gauss-newton"`).
pub fn pending_h_name(name: &str) -> String {
    format!("refine.pending_h.{}", name.trim_start_matches("refine."))
}

impl RefineParams {
    /// Zero offsets for a mesh of `n_vertices`.
    pub fn zeros(cfg: &RefineConfig, n_vertices: usize) -> RefineParams {
        let grids: Vec<Vec<f32>> = (0..cfg.levels)
            .map(|l| vec![0.0; (cfg.resolution(l) + 1).pow(3)])
            .collect();
        let vertex = if cfg.per_vertex {
            vec![0.0; n_vertices]
        } else {
            Vec::new()
        };
        let pending: Vec<Vec<f64>> = grids
            .iter()
            .chain(std::iter::once(&vertex).filter(|v| !v.is_empty()))
            .map(|g| vec![0.0; g.len()])
            .collect();
        let pending_h = match cfg.optimizer {
            RefineOptimizer::GaussNewton => pending.clone(),
            RefineOptimizer::Adam => Vec::new(),
        };
        RefineParams {
            grids,
            vertex,
            offsets: vec![0.0; n_vertices],
            traced: vec![0.0; n_vertices],
            pending,
            pending_h,
        }
    }

    pub fn n_vertices(&self) -> usize {
        self.offsets.len()
    }

    /// `(name, shape)` of the optimised tensors (grids, then the residual), for Adam.
    pub fn specs(&self) -> Vec<(String, Vec<usize>)> {
        let mut v: Vec<(String, Vec<usize>)> = self
            .grids
            .iter()
            .enumerate()
            .map(|(l, g)| (grid_name(l), vec![g.len()]))
            .collect();
        if !self.vertex.is_empty() {
            v.push((VERTEX_NAME.into(), vec![self.vertex.len()]));
        }
        v
    }

    /// Write the tensors into a checkpoint file.
    pub fn to_tensors(&self, f: &mut crate::io::tensors::TensorFile) -> Result<()> {
        use crate::io::tensors::Tensor;
        for (l, g) in self.grids.iter().enumerate() {
            f.insert(grid_name(l), Tensor::f32(vec![g.len()], g)?);
        }
        if !self.vertex.is_empty() {
            f.insert(
                VERTEX_NAME,
                Tensor::f32(vec![self.vertex.len()], &self.vertex)?,
            );
        }
        let n = self.offsets.len();
        f.insert(OFFSETS_NAME, Tensor::f32(vec![n], &self.offsets)?);
        f.insert(TRACED_NAME, Tensor::f32(vec![n], &self.traced)?);
        for ((name, shape), p) in self.specs().iter().zip(&self.pending) {
            f.insert(pending_name(name), Tensor::f64(shape.clone(), p)?);
        }
        for ((name, shape), p) in self.specs().iter().zip(&self.pending_h) {
            f.insert(pending_h_name(name), Tensor::f64(shape.clone(), p)?);
        }
        Ok(())
    }

    /// Read them back (shapes from `cfg`; the vertex count from `refine.offsets`); every value
    /// must be finite.
    pub fn from_tensors(
        f: &crate::io::tensors::TensorFile,
        cfg: &RefineConfig,
        label: &str,
    ) -> Result<RefineParams> {
        use crate::io::tensors::DType;
        let off = f.get(OFFSETS_NAME).map_err(|_| {
            anyhow::anyhow!("{label}: the config has [model.refine] enabled but there is no {OFFSETS_NAME} tensor")
        })?;
        ensure!(
            off.shape.len() == 1,
            "{label}: {OFFSETS_NAME} has shape {:?}, expected [vertices]",
            off.shape
        );
        let n = off.shape[0];
        let read = |name: &str, len: usize| -> Result<Vec<f32>> {
            let v = f.get_checked(name, DType::F32, &[len])?.to_f32()?;
            if let Some(k) = v.iter().position(|x| !x.is_finite()) {
                bail!("{label}: {name}[{k}] = {} is not finite", v[k]);
            }
            Ok(v)
        };
        let mut p = RefineParams::zeros(cfg, n);
        for l in 0..p.grids.len() {
            let len = p.grids[l].len();
            p.grids[l] = read(&grid_name(l), len)?;
        }
        if cfg.per_vertex {
            p.vertex = read(VERTEX_NAME, n)?;
        }
        p.offsets = read(OFFSETS_NAME, n)?;
        p.traced = read(TRACED_NAME, n)?;
        let specs = p.specs();
        let read64 = |pn: String, shape: &[usize]| -> Result<Vec<f64>> {
            let v = f.get_checked(&pn, DType::F64, shape)?.to_f64()?;
            if let Some(k) = v.iter().position(|x| !x.is_finite()) {
                bail!("{label}: {pn}[{k}] = {} is not finite", v[k]);
            }
            Ok(v)
        };
        for ((name, shape), pend) in specs.iter().zip(p.pending.iter_mut()) {
            *pend = read64(pending_name(name), shape)?;
        }
        for ((name, shape), pend) in specs.iter().zip(p.pending_h.iter_mut()) {
            *pend = read64(pending_h_name(name), shape)?;
        }
        Ok(p)
    }
}
