//! Mesh refinement through the ray–triangle hit point (beyond the paper; docs/geometry.md).
//!
//! The paper's mesh is fixed. Here the vertices of the training mesh may move along their
//! normals, and the photometric loss moves them: a hit point moves along its ray when its
//! triangle moves along the triangle's normal (tangential motion only re-parametrises the
//! surface), so the loss's gradient with respect to the hit position (`grad.batch.positions`)
//! gives one with respect to the vertices.
//!
//! ## Parametrisation
//! Vertex i of the base mesh (the training mesh as loaded; local frame `v − center`, f64) moves to
//! ```text
//! v_i(θ) = v_i + (θ_i · s) · m_i          s = max(extent)  (the largest axis of the SPEC §4.1 normalisation)
//! θ_i    = Σ_l trilinear(G_l, u_i) + r_i  u_i = (v_i − center) / s + 0.5  (isotropic unit coordinates)
//! ```
//! `m_i` is the unit area-weighted vertex normal of the base mesh (`synth::perturb::vertex_normals`,
//! zero for an unused vertex), `G_l` (l = 0 … levels−1) are dense scalar grids of
//! `R_l = base_resolution · 2^l` cells per unit ((R_l + 1)³ nodes, node `x + y(R+1) + z(R+1)²`,
//! cell `c = clamp(floor(u·R), 0, R−1)`, fraction `u·R − c`), and `r_i` a per-vertex residual. The
//! grids are the coarse-to-fine part: a coarse node gathers the gradient of every vertex in its
//! cells, so an error that is smooth over the mesh is corrected even though a batch touches few
//! vertices; levels are switched on coarse first (`train/refine.rs`). Offsets are in units of
//! `s`, so learning rates do not depend on the scene's units. The normalisation (centre and
//! extent) stays the one of the base mesh throughout: refined vertices may leave the unit cube
//! (the hash grid wraps, SPEC §4.2).
//!
//! ## Hit point and its gradient
//! For a valid sub-sample of a training batch: its triangle T = (k0, k1, k2) (from the ray cast),
//! the ray origin `o` (the camera centre, local frame) and the unit direction `d` from `o` to the
//! cast hit. With the current vertices a, b, c of T, Möller–Trumbore (f64, as `raycast/bvh.rs`)
//! gives `t` and barycentrics `β = (1 − u − v, u, v)`; the position is `x_n = (o + t·d) / extent + 0.5`.
//! With `n = (b − a) × (c − a)` and `g = ∂L/∂x_n ⊘ extent` (per axis: the normalisation's chain
//! rule, so ∂L/∂x in local units),
//! ```text
//! ∂L/∂v_k = (g·d) · β_k · n / (n·d)                 (k ∈ T)
//! ∂L/∂θ_k = s · (g·d) · β_k · (n·m_k) / (n·d)
//! ```
//! which is the exact derivative of the plane intersection (the hit moves along `d` by
//! `Σ_k β_k n·δv_k / (n·d)`). Held constant (data, as in the fixed-mesh model): the ray (`o`, `d`),
//! the triangle each sub-sample hits (chosen by the BVH of the last rebuild), which sub-samples
//! are valid, the pixel's view direction and its footprint (level weighting, SPEC §4.10). A
//! sub-sample is left at its cast position with no vertex gradient when the ray is within
//! `acos(min_cos)` of the triangle's plane (`|n·d| < min_cos·|n|`: the hit would run off along the
//! ray), when `t` is not finite and positive, or when a barycentric lies outside [−0.5, 1.5] (the
//! triangle moved far since the BVH was built).
//!
//! ## Smoothness
//! On the per-vertex residual (the grids are smooth by construction), with `N(i)` the vertices
//! sharing an edge with i, `E` the undirected edges and `(Lr)_i = r_i − mean_{j∈N(i)} r_j`:
//! ```text
//! E_smooth = laplacian · (1/|E|) Σ_{(i,j)∈E} (r_i − r_j)²  +  bilaplacian · (1/V) Σ_i (Lr)_i²
//! ```
//! (f64, sums in vertex / edge order, so deterministic).

use crate::model::batch::Batch;
use crate::model::photo::PhotoMeasure;
use crate::model::Real;
use crate::scene::{Mesh, Normalization};
use anyhow::{bail, ensure, Result};
use glam::DVec3;
use serde::{Deserialize, Serialize};

/// `[model.refine]`: joint refinement of the mesh (module docs; schedule in `train/refine.rs`).
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
    /// function of the seed and the update's step, `train/trust.rs`) is measured with the rays
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
    #[serde(skip_serializing_if = "is_one_f64")]
    pub features: f64,
    /// Weight of the multi-view photo-consistency energy of the training photos (0 = off;
    /// `model/photo.rs`, `train/photo.rs`).
    #[serde(skip_serializing_if = "is_zero_f64")]
    pub photo: f64,
    /// Reference patches drawn per training step.
    #[serde(skip_serializing_if = "is_default_photo_pixels")]
    pub photo_pixels: u32,
    /// Side of a patch in pixels (odd; 1 = single pixels, huber only).
    #[serde(skip_serializing_if = "is_default_photo_patch")]
    pub photo_patch: u32,
    /// `zncc` or `huber` (model/photo.rs).
    #[serde(skip_serializing_if = "is_default_measure")]
    pub photo_measure: PhotoMeasure,
    /// Image levels (photos box-downsampled by 2^l), from `[0]` when the mesh starts moving to
    /// `[1]` at its last update, in equal spans of steps (coarse to fine).
    #[serde(skip_serializing_if = "is_default_photo_levels")]
    pub photo_levels: [u32; 2],
    /// Neighbour views kept per training view (the best by shared, visible, well-triangulated
    /// surface; `train/photo.rs`).
    #[serde(skip_serializing_if = "is_default_photo_neighbours")]
    pub photo_neighbours: u32,
    /// Range of the angle (degrees) between the two views' rays at the surface for a pair.
    #[serde(skip_serializing_if = "is_default_photo_angle")]
    pub photo_angle: [f64; 2],
    /// Largest ratio of the two views' pixel footprints at the surface for a pair.
    #[serde(skip_serializing_if = "is_default_photo_scale")]
    pub photo_scale: f64,
    /// How the offset field steps at an update: `adam` (tiny-cuda-nn rules) or `gauss-newton`
    /// (the summed gradient over the photo term's summed curvature: `train/refine.rs`).
    #[serde(skip_serializing_if = "is_default_optimizer")]
    pub optimizer: RefineOptimizer,
    /// Levenberg damping of the Gauss–Newton step, relative to the mean curvature of the level's
    /// nodes that have one.
    #[serde(skip_serializing_if = "is_default_damping")]
    pub damping: f64,
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

fn is_default_optimizer(v: &RefineOptimizer) -> bool {
    *v == RefineOptimizer::default()
}
fn is_default_damping(v: &f64) -> bool {
    *v == DAMPING
}

const PHOTO_PIXELS: u32 = 1024;
const PHOTO_PATCH: u32 = 5;
const PHOTO_LEVELS: [u32; 2] = [2, 0];
const PHOTO_NEIGHBOURS: u32 = 4;
const PHOTO_ANGLE: [f64; 2] = [5.0, 45.0];
const PHOTO_SCALE: f64 = 2.0;

fn is_one_f64(v: &f64) -> bool {
    *v == 1.0
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
    fn default() -> Self {
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
        let frac = |x: f64| (0.0..=1.0).contains(&x);
        let mut bad = Vec::new();
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
        if !(self.damping.is_finite() && self.damping >= 0.0) {
            bad.push(format!("damping = {} (a finite value ≥ 0)", self.damping));
        }
        if self.enabled && self.optimizer == RefineOptimizer::GaussNewton && self.photo == 0.0 {
            bad.push(
                "optimizer = \"gauss-newton\" needs the photo term's curvature: set photo > 0"
                    .into(),
            );
        }
        if !bad.is_empty() {
            bail!("{}", bad.join("; "));
        }
        Ok(())
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

/// What the base mesh fixes (module docs): local-frame vertices, normals, unit coordinates,
/// edges. Built once per run from the training mesh and the model's normalisation.
#[derive(Clone, Debug)]
pub struct RefineGeom {
    /// The vertices as loaded (world frame).
    pub world: Vec<DVec3>,
    /// `v_i − center` (f64).
    pub base: Vec<DVec3>,
    /// Unit area-weighted vertex normals (zero for unused vertices).
    pub normals: Vec<DVec3>,
    /// `(v_i − center)/s + 0.5`, clamped to [0, 1].
    pub unit: Vec<DVec3>,
    pub triangles: Vec<[u32; 3]>,
    /// `s = max(extent)`.
    pub scale: f64,
    pub norm: Normalization,
    /// CSR neighbours: vertex i's are `nbr[nbr_start[i]..nbr_start[i+1]]` (ascending).
    pub nbr_start: Vec<u32>,
    pub nbr: Vec<u32>,
    /// Undirected edges (i < j), ascending.
    pub edges: Vec<[u32; 2]>,
}

impl RefineGeom {
    pub fn new(mesh: &Mesh, norm: &Normalization) -> RefineGeom {
        let scale = norm.extent.max_element();
        let base: Vec<DVec3> = mesh.vertices.iter().map(|&v| v - norm.center).collect();
        let normals = crate::synth::perturb::vertex_normals(mesh);
        let unit = base
            .iter()
            .map(|&v| (v / scale + DVec3::splat(0.5)).clamp(DVec3::ZERO, DVec3::ONE))
            .collect();
        let mut edges: Vec<[u32; 2]> = mesh
            .triangles
            .iter()
            .flat_map(|t| [[t[0], t[1]], [t[1], t[2]], [t[2], t[0]]])
            .filter(|e| e[0] != e[1])
            .map(|[a, b]| [a.min(b), a.max(b)])
            .collect();
        edges.sort_unstable();
        edges.dedup();
        let nv = mesh.vertices.len();
        let mut deg = vec![0u32; nv + 1];
        for e in &edges {
            deg[e[0] as usize + 1] += 1;
            deg[e[1] as usize + 1] += 1;
        }
        for i in 0..nv {
            deg[i + 1] += deg[i];
        }
        let mut fill = deg.clone();
        let mut nbr = vec![0u32; deg[nv] as usize];
        for e in &edges {
            for (a, b) in [(e[0], e[1]), (e[1], e[0])] {
                nbr[fill[a as usize] as usize] = b;
                fill[a as usize] += 1;
            }
        }
        for i in 0..nv {
            nbr[deg[i] as usize..deg[i + 1] as usize].sort_unstable();
        }
        RefineGeom {
            world: mesh.vertices.clone(),
            base,
            normals,
            unit,
            triangles: mesh.triangles.clone(),
            scale,
            norm: *norm,
            nbr_start: deg,
            nbr,
            edges,
        }
    }

    pub fn n_vertices(&self) -> usize {
        self.base.len()
    }

    /// Vertex i (local frame) at offset θ_i.
    #[inline]
    pub fn position(&self, i: usize, theta: f64) -> DVec3 {
        self.base[i] + self.normals[i] * (theta * self.scale)
    }

    /// The mesh (world frame) with offsets `theta`; a vertex whose offset is exactly 0 keeps its
    /// loaded coordinates bit for bit (so zero offsets give the training mesh itself).
    pub fn mesh_with(&self, theta: &[f64]) -> Mesh {
        Mesh {
            vertices: (0..self.n_vertices())
                .map(|i| {
                    if theta[i] == 0.0 {
                        self.world[i]
                    } else {
                        self.position(i, theta[i]) + self.norm.center
                    }
                })
                .collect(),
            triangles: self.triangles.clone(),
        }
    }

    fn neighbours(&self, i: usize) -> &[u32] {
        &self.nbr[self.nbr_start[i] as usize..self.nbr_start[i + 1] as usize]
    }
}

/// Node indices and trilinear weights of unit point `u` in a grid of `r` cells per axis.
#[inline]
pub fn trilinear(r: usize, u: DVec3) -> ([usize; 8], [f64; 8]) {
    let mut c = [0usize; 3];
    let mut f = [0f64; 3];
    for a in 0..3 {
        let p = u[a] * r as f64;
        let ci = (p.floor().max(0.0) as usize).min(r - 1);
        c[a] = ci;
        f[a] = p - ci as f64;
    }
    let n = r + 1;
    let mut idx = [0usize; 8];
    let mut w = [0f64; 8];
    for k in 0..8 {
        let (bx, by, bz) = (k & 1, (k >> 1) & 1, (k >> 2) & 1);
        idx[k] = (c[0] + bx) + (c[1] + by) * n + (c[2] + bz) * n * n;
        let wx = if bx == 1 { f[0] } else { 1.0 - f[0] };
        let wy = if by == 1 { f[1] } else { 1.0 - f[1] };
        let wz = if bz == 1 { f[2] } else { 1.0 - f[2] };
        w[k] = wx * wy * wz;
    }
    (idx, w)
}

/// `θ_i = Σ_l trilinear(G_l, u_i) + r_i` (module docs) from grids `[levels][(R_l+1)³]` and the
/// residual `r` (empty: none), in f64 whatever the parameters' type.
pub fn field_theta<R: Real>(
    cfg: &RefineConfig,
    geom: &RefineGeom,
    grids: &[Vec<R>],
    r: &[R],
    i: usize,
) -> f64 {
    let mut th = 0.0f64;
    for (l, g) in grids.iter().enumerate() {
        let (idx, w) = trilinear(cfg.resolution(l as u32), geom.unit[i]);
        for k in 0..8 {
            th += w[k] * g[idx[k]].to_f64();
        }
    }
    if !r.is_empty() {
        th += r[i].to_f64();
    }
    th
}

/// Accumulate `∂L/∂θ_i = d_theta[i]` of the listed vertices (in list order) into the gradients
/// of grid levels `< levels` (`d_grids[l]`) and, if `residual`, of the residual (`d_r`).
#[allow(clippy::too_many_arguments)]
pub fn field_backward(
    cfg: &RefineConfig,
    geom: &RefineGeom,
    vertices: &[u32],
    d_theta: &[f64],
    levels: usize,
    residual: bool,
    d_grids: &mut [Vec<f64>],
    d_r: &mut [f64],
) {
    for &i in vertices {
        let (i, g) = (i as usize, d_theta[i as usize]);
        if g == 0.0 {
            continue;
        }
        for (l, dg) in d_grids.iter_mut().enumerate().take(levels) {
            let (idx, w) = trilinear(cfg.resolution(l as u32), geom.unit[i]);
            for k in 0..8 {
                dg[idx[k]] += w[k] * g;
            }
        }
        if residual && !d_r.is_empty() {
            d_r[i] += g;
        }
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

    /// θ_i from the parameters ([`field_theta`] with every level).
    pub fn theta(&self, cfg: &RefineConfig, geom: &RefineGeom, i: usize) -> f64 {
        field_theta(cfg, geom, &self.grids, &self.vertex, i)
    }

    /// θ of every vertex (parallel, each vertex independent).
    pub fn theta_all(&self, cfg: &RefineConfig, geom: &RefineGeom) -> Vec<f64> {
        use rayon::prelude::*;
        (0..geom.n_vertices())
            .into_par_iter()
            .with_min_len(4096)
            .map(|i| self.theta(cfg, geom, i))
            .collect()
    }

    /// Recompute `offsets` from the parameters.
    pub fn sync_offsets(&mut self, cfg: &RefineConfig, geom: &RefineGeom) {
        self.offsets = self
            .theta_all(cfg, geom)
            .into_iter()
            .map(|t| t as f32)
            .collect();
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

/// A valid sub-sample re-intersected with its triangle's current plane (module docs).
#[derive(Clone, Copy, Debug)]
pub struct RayHit {
    /// Index into the batch's `[N*S]` sub-samples.
    pub sample: usize,
    pub tri: [u32; 3],
    pub o: DVec3,
    pub d: DVec3,
    pub t: f64,
    /// Barycentrics of the triangle's three corners.
    pub beta: [f64; 3],
    /// `(b − a) × (c − a)`, unnormalised.
    pub n: DVec3,
    /// The moved triangle's edges `b − a`, `c − a` (for the anchored gradient).
    pub e: [DVec3; 2],
}

/// Möller–Trumbore of the ray `o + t·d` with triangle (a, b, c) (f64, as `raycast/bvh.rs`):
/// `(t, [1−u−v, u, v], n)`, or `None` when the ray is within `acos(min_cos)` of the plane, `t`
/// is not finite and positive, or a barycentric is outside [−0.5, 1.5].
pub fn intersect(
    o: DVec3,
    d: DVec3,
    [a, b, c]: [DVec3; 3],
    min_cos: f64,
) -> Option<(f64, [f64; 3], DVec3)> {
    let (e1, e2) = (b - a, c - a);
    let p = d.cross(e2);
    let det = e1.dot(p);
    let n = e1.cross(e2);
    let nn = n.length();
    // det = −n·d.
    if nn.is_nan() || nn <= 0.0 || det.abs() < min_cos * nn {
        return None;
    }
    let inv = 1.0 / det;
    let s = o - a;
    let q = s.cross(e1);
    let (t, u, v) = (e2.dot(q) * inv, s.dot(p) * inv, d.dot(q) * inv);
    let beta = [1.0 - u - v, u, v];
    if !(t.is_finite() && t > 0.0) || beta.iter().any(|&x| !(-0.5..=1.5).contains(&x)) {
        return None;
    }
    Some((t, beta, n))
}

/// Sub-samples per parallel work item of [`reintersect_batch`] (a constant, SPEC §5.2; every
/// sub-sample is independent, so it does not enter the results).
pub const HIT_CHUNK: usize = 1024;

/// Move every valid sub-sample of `batch` (which must carry triangle ids) to its triangle's plane
/// at offsets `theta` (indexed by vertex; only the batch's triangles' vertices are read) and
/// return the hits that carry a vertex gradient, in batch order (module docs). The ray of a
/// sub-sample runs from `origin(pixel)` (local frame) through its position in `batch`; a
/// sub-sample [`intersect`] rejects keeps its position.
pub fn reintersect_batch(
    geom: &RefineGeom,
    theta: &[f64],
    batch: &mut Batch,
    origin: &(dyn Fn(usize) -> DVec3 + Sync),
    min_cos: f64,
) -> Vec<RayHit> {
    reintersect_with(geom, theta, None, batch, origin, min_cos)
}

/// [`reintersect_batch`] for `[model.refine] anchored = true`: the batch's positions are on the
/// training mesh (an anchored tracer's), so the ray of a sub-sample runs from `origin(pixel)`
/// through the point with the batch's barycentrics (`bary`) on the mesh at offsets `traced` (the
/// mesh the rays were cast against); the position written is the *training* mesh's point with the
/// barycentrics of the hit on the mesh at `theta`.
pub fn reintersect_batch_anchored(
    geom: &RefineGeom,
    theta: &[f64],
    traced: &[f64],
    batch: &mut Batch,
    origin: &(dyn Fn(usize) -> DVec3 + Sync),
    min_cos: f64,
) -> Vec<RayHit> {
    reintersect_with(geom, theta, Some(traced), batch, origin, min_cos)
}

fn reintersect_with(
    geom: &RefineGeom,
    theta: &[f64],
    traced: Option<&[f64]>,
    batch: &mut Batch,
    origin: &(dyn Fn(usize) -> DVec3 + Sync),
    min_cos: f64,
) -> Vec<RayHit> {
    use rayon::prelude::*;
    let s = batch.samples_per_pixel();
    let extent = geom.norm.extent;
    let (valid, triangle, positions) = (&batch.valid, &batch.triangle, &batch.positions);
    let bary = &batch.bary;
    let out: Vec<Option<(DVec3, RayHit)>> = (0..positions.len())
        .into_par_iter()
        .with_min_len(HIT_CHUNK)
        .map(|j| {
            if valid[j] == 0 {
                return None;
            }
            let tri = geom.triangles[triangle[j] as usize];
            let o = origin(j / s);
            let x = match traced {
                None => (DVec3::from_array(positions[j]) - DVec3::splat(0.5)) * extent,
                Some(tr) => {
                    let [u, v] = bary[j];
                    let w = [1.0 - u - v, u, v];
                    (0..3).fold(DVec3::ZERO, |acc, c| {
                        let i = tri[c] as usize;
                        acc + geom.position(i, tr[i]) * w[c]
                    })
                }
            };
            let d = (x - o).normalize_or_zero();
            let v = tri.map(|i| geom.position(i as usize, theta[i as usize]));
            let (t, beta, n) = intersect(o, d, v, min_cos)?;
            let hit = match traced {
                None => o + d * t,
                // The training mesh's point with the moved hit's barycentrics.
                Some(_) => (0..3).fold(DVec3::ZERO, |acc, c| {
                    acc + geom.position(tri[c] as usize, 0.0) * beta[c]
                }),
            };
            let p = hit / extent + DVec3::splat(0.5);
            Some((
                p,
                RayHit {
                    sample: j,
                    tri,
                    o,
                    d,
                    t,
                    beta,
                    n,
                    e: [v[1] - v[0], v[2] - v[0]],
                },
            ))
        })
        .collect();
    let mut hits = Vec::with_capacity(out.len());
    for (p, h) in out.into_iter().flatten() {
        batch.positions[h.sample] = p.to_array();
        hits.push(h);
    }
    hits
}

/// ∂L/∂x in local units of sub-sample `j` from `grad.batch.positions` (x_n = x / extent + 0.5 per
/// axis).
#[inline]
fn local_gradient<R: Real>(d_positions: &[R], j: usize, inv_extent: DVec3) -> DVec3 {
    let k = j * 3;
    DVec3::new(
        d_positions[k].to_f64(),
        d_positions[k + 1].to_f64(),
        d_positions[k + 2].to_f64(),
    ) * inv_extent
}

/// `∂L/∂θ` of the hits (module docs), accumulated into `d_theta` in hit order. `d_positions` is
/// `grad.batch.positions` `[N*S*3]`; `inv_extent` the normalisation's `1/extent` per axis.
pub fn hits_backward<R: Real>(
    geom: &RefineGeom,
    hits: &[RayHit],
    d_positions: &[R],
    d_theta: &mut [f64],
) {
    let inv_extent = DVec3::ONE / geom.norm.extent;
    for h in hits {
        let g = local_gradient(d_positions, h.sample, inv_extent);
        for (i, v) in crate::model::photo::plane_hit_chain(geom, h.tri, h.beta, h.n, h.d, g) {
            d_theta[i as usize] += v;
        }
    }
}

/// `∂L/∂θ` of anchored hits ([`reintersect_batch_anchored`]; docs/geometry.md §3), accumulated
/// into `d_theta` in hit order. The query point is `x₀ = Σ β_k v⁰_k` (training mesh), so
/// `∂L/∂β` restricted to the plane is `c = J₀ᵀ g` (`J₀ = [b⁰−a⁰, c⁰−a⁰]`), pulled back to the
/// moved plane as `h = J G⁻¹ c` (`J` the moved edges, `G = JᵀJ`). Moving the material point of
/// the hit by `w = Σ β_k δv_k` moves the hit in the plane by `δt·d − w` with
/// `δt = n·w / n·d`, so `∂L/∂w = (h·d) n / (n·d) − h` and `∂L/∂θ_k = s β_k m_k · ∂L/∂w`.
pub fn hits_backward_anchored<R: Real>(
    geom: &RefineGeom,
    hits: &[RayHit],
    d_positions: &[R],
    d_theta: &mut [f64],
) {
    let inv_extent = DVec3::ONE / geom.norm.extent;
    for h in hits {
        let g = local_gradient(d_positions, h.sample, inv_extent);
        let base = h.tri.map(|i| geom.base[i as usize]);
        let c = [g.dot(base[1] - base[0]), g.dot(base[2] - base[0])];
        let [e1, e2] = h.e;
        let (g11, g12, g22) = (e1.dot(e1), e1.dot(e2), e2.dot(e2));
        let det = g11 * g22 - g12 * g12;
        if det.is_nan() || det <= 0.0 {
            continue;
        }
        // G⁻¹ c, then h = J (G⁻¹ c).
        let y = [
            (g22 * c[0] - g12 * c[1]) / det,
            (g11 * c[1] - g12 * c[0]) / det,
        ];
        let hv = e1 * y[0] + e2 * y[1];
        let dw = h.n * (hv.dot(h.d) / h.n.dot(h.d)) - hv;
        for c in 0..3 {
            let i = h.tri[c] as usize;
            d_theta[i] += geom.scale * h.beta[c] * dw.dot(geom.normals[i]);
        }
    }
}

/// `E_smooth` of the residual `r` and its gradient added into `d_r` (module docs).
pub fn smoothness<R: Real>(cfg: &RefineConfig, geom: &RefineGeom, r: &[R], d_r: &mut [f64]) -> f64 {
    if r.is_empty() {
        return 0.0;
    }
    let mut e = 0.0f64;
    if cfg.laplacian > 0.0 && !geom.edges.is_empty() {
        let w = cfg.laplacian / geom.edges.len() as f64;
        for &[i, j] in &geom.edges {
            let (i, j) = (i as usize, j as usize);
            let diff = r[i].to_f64() - r[j].to_f64();
            e += w * diff * diff;
            d_r[i] += 2.0 * w * diff;
            d_r[j] -= 2.0 * w * diff;
        }
    }
    if cfg.bilaplacian > 0.0 {
        let nv = geom.n_vertices();
        let w = cfg.bilaplacian / nv as f64;
        // y = L r, then ∂/∂r of w·Σ y² = 2w·Lᵀy.
        let mut y = vec![0.0f64; nv];
        for (i, yi) in y.iter_mut().enumerate() {
            let nb = geom.neighbours(i);
            if nb.is_empty() {
                continue;
            }
            let m: f64 = nb.iter().map(|&j| r[j as usize].to_f64()).sum::<f64>() / nb.len() as f64;
            *yi = r[i].to_f64() - m;
            e += w * *yi * *yi;
        }
        for (i, &yi) in y.iter().enumerate() {
            let nb = geom.neighbours(i);
            if nb.is_empty() || yi == 0.0 {
                continue;
            }
            let g = 2.0 * w * yi;
            d_r[i] += g;
            let share = g / nb.len() as f64;
            for &j in nb {
                d_r[j as usize] -= share;
            }
        }
    }
    e
}

/// The base mesh with the checkpoint's offsets applied (eval/render), checking the vertex count.
pub fn refined_mesh(mesh: &Mesh, norm: &Normalization, offsets: &[f32]) -> Result<Mesh> {
    ensure!(
        offsets.len() == mesh.vertices.len(),
        "the model refines a mesh of {} vertices, but the scene's mesh has {}: pass the training mesh with --mesh",
        offsets.len(),
        mesh.vertices.len()
    );
    let geom = RefineGeom::new(mesh, norm);
    let theta: Vec<f64> = offsets.iter().map(|&t| t as f64).collect();
    Ok(geom.mesh_with(&theta))
}
