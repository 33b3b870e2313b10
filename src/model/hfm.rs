//! The hash featurized manifold pipeline (the paper's Eq. 2–5) with its explicit backward.
//!
//! Per pixel n and each VALID sub-sample j (invalid ones are never evaluated):
//! ```text
//! F_H(x_j)                        grid H                                   (Eq. 2)
//! δ_j = ξ([F_D(x_j), SH(d_n)])    grid D + 1-hidden-layer ReLU MLP, linear (Eq. 5)
//! F'_j = F_H(x_j) + δ_j
//! pooled_n = (Σ_j F'_j) / count_n   (sum in sub-sample order)              (Eq. 4)
//! z_n = shader([pooled_n, SH(d_n), code(view_n)])  ReLU MLP, linear out
//! rgb_n = σ(z_n)                                                            (Eq. 3)
//! L = mean over pixels, channels of ρ(rgb − target)                         (SPEC §4.7)
//! ```
//! `code(−1)` is the mean of all appearance rows (a view without a code).
//!
//! Featurization switch (`cfg.featurization`): with `vertex`, F_H(x_j) is replaced by the
//! vertex-feature baseline F_V(x_j) of Fig. 2b (`src/model/vertex.rs`, barycentric interpolation
//! of per-vertex vectors, from the batch's `triangle`/`bary`); ξ must be off; the rest is the
//! same code. In that mode `grid_h` is structure only (not in the layout, not evaluated, not
//! saved) and ∂L/∂positions is zero (positions do not enter the model).
//!
//! Determinism (SPEC §5): pixels are processed in chunks of [`PIXEL_CHUNK`] (a constant), in
//! parallel; every per-chunk partial (MLP weight gradients, loss sums) is combined in chunk
//! order afterwards; grid-table gradients are scattered by the grid's own `backward_table` over
//! all valid sub-samples in batch order; appearance-code gradients are added in pixel order.
//! Results are bit-identical whatever the thread count.
//!
//! Backward order of accumulation into one buffer (part of the definition):
//! ∂L/∂SH(d_n) = shader part, then ξ's part for j ascending; ∂L/∂x_j = grid H's part, then grid
//! D's; ∂L/∂codes: pixels with a code in pixel order, then the mean-code pixels' sum / views
//! added to every row.

use crate::model::batch::Batch;
use crate::model::config::{LevelWeight, ModelConfig};
use crate::model::hashgrid::HashGrid;
use crate::model::level_weight::{apply_level_weights, level_weights};
use crate::model::loss::{loss_backward, loss_forward, sigmoid_backward, sigmoid_forward};
use crate::model::mlp::{Mlp, MlpActs};
use crate::model::params::{Grads, Group, ParamLayout};
use crate::model::sh::{sh_backward, sh_forward, SH_DIM};
use crate::model::ssim::{combine as ssim_combine, ssim_backward, ssim_forward};
use crate::model::vertex::{vertex_backward, vertex_forward, VertexTable};
use crate::model::Real;
use anyhow::{ensure, Context, Result};
use rayon::prelude::*;
use std::ops::Range;
use std::sync::Arc;

/// Pixels per parallel work item. A constant of the code (never derived from the thread count).
pub const PIXEL_CHUNK: usize = 128;

/// Tensor ids of the initialisation streams (`rng::Purpose::InitTable/InitWeights`, `a` = id).
pub const TENSOR_ID_GRID_H: u64 = 0;
pub const TENSOR_ID_GRID_D: u64 = 1;
pub const TENSOR_ID_VERTEX: u64 = 2;
pub const TENSOR_ID_DEFORM: u64 = 100; // + layer index
pub const TENSOR_ID_SHADER: u64 = 200; // + layer index

/// The model's structure: grids, MLPs and the parameter layout (the numbers live in a flat
/// parameter buffer, see [`ParamLayout`]).
#[derive(Clone, Debug)]
pub struct Hfm {
    pub cfg: ModelConfig,
    /// Grid H (structure only when `vertex` is set, see the module doc).
    pub grid_h: HashGrid,
    /// The vertex-feature table, when `cfg.featurization = "vertex"`.
    pub vertex: Option<VertexTable>,
    /// Grid D, when the deformation is enabled.
    pub grid_d: Option<HashGrid>,
    /// ξ: `[L_D·F_D + 16] → hidden → [L·F]`, biases iff `cfg.shader.bias` (one switch for both
    /// networks), last layer zero at initialisation.
    pub deform: Option<Mlp>,
    /// Shader: `[L·F + 16 + A] → width × hidden_layers → 3`.
    pub shader: Mlp,
    pub layout: ParamLayout,
    r_grid_h: Range<usize>,
    r_vertex: Range<usize>,
    r_grid_d: Range<usize>,
    pub(crate) r_deform: Range<usize>,
    pub(crate) r_shader: Range<usize>,
    r_codes: Range<usize>,
}

/// Forward results of one chunk of pixels `pixels` (sub-samples `samples` in the compacted
/// list of valid sub-samples).
#[derive(Clone, Debug, Default)]
pub struct ChunkFwd<R> {
    pub pixels: Range<usize>,
    pub samples: Range<usize>,
    /// `[v, L·F]` F_H at each valid sub-sample (Eq. 2).
    pub grid_h: Vec<R>,
    /// `[v, L]` footprint level weights (SPEC §4.10), empty without level weighting.
    pub level_w: Vec<R>,
    /// `[v, L_D·F_D]` F_D.
    pub grid_d: Vec<R>,
    /// `[v, L_D·F_D + 16]` ξ's input.
    pub deform_in: Vec<R>,
    /// ξ's activations; `deform.out` `[v, L·F]` is the delta of Eq. 5.
    pub deform: MlpActs<R>,
    /// `[n, 16]`.
    pub sh: Vec<R>,
    /// `[n, L·F]` (Eq. 4).
    pub pooled: Vec<R>,
    /// `[n, L·F + 16 + A]`.
    pub shader_in: Vec<R>,
    /// Shader activations; `shader.out` `[n, 3]` are the logits.
    pub shader: MlpActs<R>,
    /// `[n, 3]` σ(logits) (Eq. 3).
    pub rgb: Vec<R>,
    /// Σ ρ over the chunk (f64).
    pub loss_sum: f64,
}

/// One chunk buffer per thread of the pool for [`Hfm::infer_pixels`] (and
/// [`Hfm::infer_coded`]): a thread only ever takes its own (uncontended), and keeps it across
/// chunks and calls, so a frame's chunks grow (and zero-fill) no buffer again. The colours do
/// not depend on the buffers.
pub struct InferBuffers<R>(Vec<std::sync::Mutex<ChunkFwd<R>>>);

impl<R: Real> InferBuffers<R> {
    pub fn new() -> Self {
        InferBuffers(
            (0..rayon::current_num_threads().max(1))
                .map(|_| std::sync::Mutex::new(ChunkFwd::default()))
                .collect(),
        )
    }

    /// The calling thread's buffer (a thread outside the pool shares the first).
    fn for_this_thread(&self) -> std::sync::MutexGuard<'_, ChunkFwd<R>> {
        let i = rayon::current_thread_index().unwrap_or(0) % self.0.len();
        // A poisoned buffer (a panic in another chunk) holds nothing the next chunk reads first.
        self.0[i].lock().unwrap_or_else(|e| e.into_inner())
    }
}

impl<R: Real> Default for InferBuffers<R> {
    fn default() -> Self {
        Self::new()
    }
}

/// Forward results of a batch.
#[derive(Clone, Debug)]
pub struct Forward<R> {
    pub chunks: Vec<ChunkFwd<R>>,
    /// `[N+1]`: pixel n's valid sub-samples are `start[n]..start[n+1]` of the compacted list.
    pub start: Vec<usize>,
    /// `[V]` positions of the valid sub-samples, in batch order.
    pub points: Vec<[f64; 3]>,
    /// `[V]` index into the batch's `[N*S]` sub-samples of each valid sub-sample.
    pub sample_index: Vec<usize>,
    /// `[V]` triangle and barycentrics of each valid sub-sample (vertex featurization only).
    pub triangles: Vec<u32>,
    pub bary: Vec<[f64; 2]>,
    /// `[A]` mean of all appearance rows (used for view −1).
    pub code_mean: Vec<R>,
    /// Loss (mean over pixels and channels), f64.
    pub loss: f64,
}

/// What every chunk of a forward pass shares (see `Hfm::prologue`): the batch's valid
/// sub-samples compacted, and what depends on the parameters alone.
struct Prologue<R> {
    start: Vec<usize>,
    points: Vec<[f64; 3]>,
    sample_index: Vec<usize>,
    triangles: Vec<u32>,
    bary: Vec<[f64; 2]>,
    shared: Shared<R>,
}

impl<R> Prologue<R> {
    /// The pixels of `batch` as the chunks read them.
    fn pixels<'a>(&'a self, batch: &'a Batch) -> Pixels<'a> {
        Pixels {
            start: &self.start,
            points: &self.points,
            triangles: &self.triangles,
            bary: &self.bary,
            dirs: &batch.dirs,
            footprint: &batch.footprint,
            view: &batch.view,
            target: &batch.target,
        }
    }
}

/// What every chunk of a forward pass shares that depends on the parameters alone: the mean
/// appearance code (or the code given for view −1) and the MLPs' transposed weights. A frame
/// makes it once ([`Hfm::infer_shared`]) for all its pixels.
pub struct Shared<R> {
    code_mean: Vec<R>,
    wt_shader: Vec<Vec<R>>,
    wt_deform: Option<Vec<Vec<R>>>,
}

/// Pixels as a forward pass reads them, their valid sub-samples already compacted (CSR by
/// pixel): what [`Hfm::forward`] makes of a [`Batch`], or what a renderer builds straight from
/// its cast ([`Hfm::infer_pixels`]), so nothing is copied into a batch first.
#[derive(Clone, Copy, Debug)]
pub struct Pixels<'a> {
    /// `[n+1]`: pixel i's valid sub-samples are `start[i]..start[i+1]` of `points` (at least
    /// one each).
    pub start: &'a [usize],
    /// `[V]` positions of the valid sub-samples, pixel by pixel in sub-sample order.
    pub points: &'a [[f64; 3]],
    /// `[V]` triangle and barycentrics of each valid sub-sample (vertex featurization only,
    /// else empty).
    pub triangles: &'a [u32],
    pub bary: &'a [[f64; 2]],
    /// `[n]` unit view directions.
    pub dirs: &'a [[f32; 3]],
    /// `[n]` pixel footprints (SPEC §6.3; empty without the footprint level weighting).
    pub footprint: &'a [f32],
    /// `[n]` appearance rows (−1: the shared code).
    pub view: &'a [i32],
    /// `[n]` targets; empty: no loss is summed (rendering).
    pub target: &'a [[f32; 3]],
}

impl Pixels<'_> {
    pub fn n_pixels(&self) -> usize {
        self.dirs.len()
    }
}

/// `v` at length `len` for a stage that writes every element: what a reused buffer held is
/// left in place instead of being zeroed first (only a grown tail is zero-filled).
fn fit<R: Real>(v: &mut Vec<R>, len: usize) {
    v.resize(len, R::ZERO);
}

/// One chunk's backward partials.
struct ChunkGrad<R> {
    d_shader: Vec<R>,
    d_deform: Vec<R>,
    /// `[n, A]`.
    d_code: Vec<R>,
    /// `[n, 3]`.
    d_dirs: Vec<R>,
    /// `[v, 3]`.
    d_points: Vec<R>,
}

impl Hfm {
    /// Structure for a config, with grid scales computed as tiny-cuda-nn does. A vertex
    /// featurization needs the mesh: use [`Hfm::with_vertex`].
    pub fn new(cfg: &ModelConfig) -> Result<Hfm> {
        ensure!(
            cfg.featurization.is_hash(),
            "config: featurization = \"vertex\" needs the mesh's faces (Hfm::with_vertex)"
        );
        let gh = HashGrid::try_new(&cfg.grid_h).context("config: grid_h")?;
        let gd = if cfg.deform.enabled {
            Some(HashGrid::try_new(&cfg.deform.grid).context("config: deform.grid")?)
        } else {
            None
        };
        Hfm::with_grids(cfg, gh, gd)
    }

    /// The vertex-feature baseline (Fig. 2b) over a mesh with `cfg.vertex_count` vertices and
    /// these faces (triangle ids of a ray cast index them).
    pub fn with_vertex(cfg: &ModelConfig, faces: Arc<[[u32; 3]]>) -> Result<Hfm> {
        ensure!(
            !cfg.featurization.is_hash(),
            "config: Hfm::with_vertex needs featurization = \"vertex\""
        );
        ensure!(
            !cfg.deform.enabled,
            "config: the vertex featurization runs without deformation (set [model.deform] enabled = false)"
        );
        let vt = VertexTable::new(
            cfg.vertex_count as usize,
            cfg.vertex_features as usize,
            faces,
        )
        .context("config")?;
        let gh = HashGrid::try_new(&cfg.grid_h).context("config: grid_h")?;
        Hfm::build(cfg, gh, None, Some(vt))
    }

    /// Structure with given grids (e.g. built from a checkpoint's saved scales).
    pub fn with_grids(
        cfg: &ModelConfig,
        grid_h: HashGrid,
        grid_d: Option<HashGrid>,
    ) -> Result<Hfm> {
        ensure!(
            cfg.featurization.is_hash(),
            "config: featurization = \"vertex\" needs the mesh's faces (Hfm::with_vertex)"
        );
        Hfm::build(cfg, grid_h, grid_d, None)
    }

    fn build(
        cfg: &ModelConfig,
        grid_h: HashGrid,
        grid_d: Option<HashGrid>,
        vertex: Option<VertexTable>,
    ) -> Result<Hfm> {
        ensure!(
            cfg.grid_h.levels > 0 && cfg.grid_h.features > 0,
            "config: grid_h has no features"
        );
        ensure!(
            cfg.deform.enabled == grid_d.is_some(),
            "config: deform.enabled = {} but grid D is {}",
            cfg.deform.enabled,
            if grid_d.is_some() {
                "present"
            } else {
                "absent"
            }
        );
        let lf = match &vertex {
            Some(vt) => vt.features,
            None => grid_h.out_dim(),
        };
        let a = cfg.appearance_dim as usize;
        let mut layout = ParamLayout::default();
        let fh = cfg.grid_h.features as usize;
        let (mut r_grid_h, mut r_vertex) = (0..0, 0..0);
        match &vertex {
            None => r_grid_h = layout.push("grid_h.table", &[grid_h.n_entries(), fh], Group::GridH),
            Some(vt) => {
                r_vertex = layout.push(
                    "vertex.features",
                    &[vt.n_vertices, vt.features],
                    Group::Vertex,
                )
            }
        }
        let mut r_grid_d = 0..0;
        let mut r_deform = 0..0;
        let mut deform = None;
        if let Some(gd) = &grid_d {
            ensure!(cfg.deform.hidden > 0, "config: deform.hidden must be > 0");
            r_grid_d = layout.push(
                "grid_d.table",
                &[gd.n_entries(), cfg.deform.grid.features as usize],
                Group::GridD,
            );
            let mlp = Mlp::new(
                &[gd.out_dim() + SH_DIM, cfg.deform.hidden as usize, lf],
                cfg.shader.bias,
            );
            r_deform = push_mlp(&mut layout, "deform", &mlp, Group::Deform);
            deform = Some(mlp);
        }
        let mut dims = vec![lf + SH_DIM + a];
        dims.extend(std::iter::repeat_n(
            cfg.shader.width as usize,
            cfg.shader.hidden_layers as usize,
        ));
        dims.push(3);
        let shader = Mlp::new(&dims, cfg.shader.bias);
        let r_shader = push_mlp(&mut layout, "shader", &shader, Group::Shader);
        let r_codes = if a > 0 {
            layout.push(
                "appearance.codes",
                &[cfg.appearance_views as usize, a],
                Group::Appearance,
            )
        } else {
            0..0
        };
        Ok(Hfm {
            cfg: cfg.clone(),
            grid_h,
            vertex,
            grid_d,
            deform,
            shader,
            layout,
            r_grid_h,
            r_vertex,
            r_grid_d,
            r_deform,
            r_shader,
            r_codes,
        })
    }

    /// Freshly initialised parameters (f32) in the layout: grids U(±1e-4), MLPs Xavier-uniform,
    /// ξ's last layer zero, biases zero, appearance codes zero.
    pub fn init_params(&self, seed: u64) -> Vec<f32> {
        let mut p = vec![0.0f32; self.layout.total];
        match &self.vertex {
            None => p[self.r_grid_h.clone()]
                .copy_from_slice(&self.grid_h.init_table(seed, TENSOR_ID_GRID_H)),
            Some(vt) => {
                p[self.r_vertex.clone()].copy_from_slice(&vt.init_table(seed, TENSOR_ID_VERTEX))
            }
        }
        if let (Some(gd), Some(mlp)) = (&self.grid_d, &self.deform) {
            p[self.r_grid_d.clone()].copy_from_slice(&gd.init_table(seed, TENSOR_ID_GRID_D));
            let ids: Vec<u64> = (0..mlp.layers.len() as u64)
                .map(|k| TENSOR_ID_DEFORM + k)
                .collect();
            p[self.r_deform.clone()].copy_from_slice(&mlp.init(seed, &ids, true));
        }
        let ids: Vec<u64> = (0..self.shader.layers.len() as u64)
            .map(|k| TENSOR_ID_SHADER + k)
            .collect();
        p[self.r_shader.clone()].copy_from_slice(&self.shader.init(seed, &ids, false));
        p
    }

    /// Width of the per-sub-sample feature: `L·F` of grid H, or Z (vertex featurization).
    pub fn feat_dim(&self) -> usize {
        match &self.vertex {
            Some(vt) => vt.features,
            None => self.grid_h.out_dim(),
        }
    }
    pub fn appearance_dim(&self) -> usize {
        self.cfg.appearance_dim as usize
    }
    pub fn appearance_views(&self) -> usize {
        if self.appearance_dim() > 0 {
            self.cfg.appearance_views as usize
        } else {
            0
        }
    }

    /// Check a batch against this model (shapes, validity, view rows).
    pub fn check_batch(&self, batch: &Batch) -> Result<()> {
        batch.validate()?;
        ensure!(
            self.cfg.level_weight == LevelWeight::None || !batch.footprint.is_empty(),
            "batch: the footprint level weighting (model.level_weight) needs batch.footprint"
        );
        if let Some(vt) = &self.vertex {
            ensure!(
                !batch.triangle.is_empty(),
                "batch: the vertex featurization needs batch.triangle and batch.bary"
            );
            for (k, (&t, &v)) in batch.triangle.iter().zip(&batch.valid).enumerate() {
                ensure!(
                    v == 0 || (t as usize) < vt.faces.len(),
                    "batch: sub-sample {k}: triangle {t} is not one of the model's {} faces",
                    vt.faces.len()
                );
            }
        }
        let views = self.appearance_views() as i32;
        if self.appearance_dim() > 0 {
            for (i, &v) in batch.view.iter().enumerate() {
                ensure!(
                    v < views,
                    "batch: pixel {i}: view {v} has no appearance code (the model has {views} rows)"
                );
            }
        }
        Ok(())
    }

    /// Forward pass over a batch (parallel over pixel chunks).
    pub fn forward<R: Real>(&self, params: &[R], batch: &Batch) -> Result<Forward<R>> {
        let pre = self.prologue(params, batch)?;
        let n = batch.n_pixels();
        let px = pre.pixels(batch);
        let chunks: Vec<ChunkFwd<R>> = (0..n.div_ceil(PIXEL_CHUNK))
            .into_par_iter()
            .map(|c| {
                let mut f = ChunkFwd::default();
                self.forward_chunk(&mut f, params, &px, &pre.shared, c);
                f
            })
            .collect();
        let mut sum = 0.0f64;
        for ch in &chunks {
            sum += ch.loss_sum; // chunk order
        }
        let mut loss = sum / (3 * n) as f64;
        if let Some(k) = self.ssim_patch(batch) {
            let rgb = batch_rgb(&chunks);
            let (s, m) = ssim_forward(k, &rgb, &batch.target, &batch.patch_mask);
            loss = ssim_combine(self.cfg.ssim_weight, loss, s, m);
        }
        Ok(Forward {
            chunks,
            start: pre.start,
            points: pre.points,
            sample_index: pre.sample_index,
            triangles: pre.triangles,
            bary: pre.bary,
            code_mean: pre.shared.code_mean,
            loss,
        })
    }

    /// The colours only (`[N, 3]` σ(logits), the same bits as [`Hfm::forward`]'s `rgb`), for
    /// rendering: no activations are kept, and each worker thread reuses one chunk's buffers.
    pub fn infer<R: Real>(&self, params: &[R], batch: &Batch) -> Result<Vec<R>> {
        self.infer_coded(params, batch, None)
    }

    /// [`Hfm::infer`] with `code` (`[A]`) in place of the mean code for the pixels of view −1
    /// (`None`: the mean, as `infer`). Rendering a view that has no row of its own with a code
    /// blended from its neighbours' (`render::appearance`).
    pub fn infer_coded<R: Real>(
        &self,
        params: &[R],
        batch: &Batch,
        code: Option<&[R]>,
    ) -> Result<Vec<R>> {
        let bufs = InferBuffers::new();
        let mut pre = self.prologue(params, batch)?;
        if let Some(c) = code {
            self.check_code(c)?;
            pre.shared.code_mean = c.to_vec();
        }
        let mut rgb = vec![R::ZERO; batch.n_pixels() * 3];
        let px = pre.pixels(batch);
        rgb.par_chunks_mut(PIXEL_CHUNK * 3)
            .enumerate()
            .for_each(|(c, out)| {
                let mut f = bufs.for_this_thread();
                self.forward_chunk(&mut f, params, &px, &pre.shared, c);
                out.copy_from_slice(&f.rgb);
            });
        Ok(rgb)
    }

    /// A code given for view −1 has the model's appearance dimension.
    fn check_code<R>(&self, c: &[R]) -> Result<()> {
        ensure!(
            c.len() == self.appearance_dim(),
            "appearance code of {} values, the model's codes have {}",
            c.len(),
            self.appearance_dim()
        );
        Ok(())
    }

    /// What [`Hfm::infer_pixels`] shares across a frame's pixels: the MLPs' transposed weights
    /// and `code` (`[A]`) for the pixels of view −1 (`None`: the mean of all codes), checked
    /// against the layout.
    pub fn infer_shared<R: Real>(&self, params: &[R], code: Option<&[R]>) -> Result<Shared<R>> {
        self.check_params(params)?;
        let mut shared = self.shared(params);
        if let Some(c) = code {
            self.check_code(c)?;
            shared.code_mean = c.to_vec();
        }
        Ok(shared)
    }

    /// The colours (`[n, 3]` σ(logits) into `rgb`) of pixels whose valid sub-samples are already
    /// compacted: the same bits as [`Hfm::infer_coded`] of the batch they came from (its
    /// prologue compacts the same points in the same order), without the batch. `shared` from
    /// [`Hfm::infer_shared`] with the same `params`. The pixels are checked chunk by chunk, in
    /// parallel, as `infer_coded` checks a batch (a pixel without a valid sub-sample, a
    /// non-finite position or direction, a view without a code are errors).
    pub fn infer_pixels<R: Real>(
        &self,
        params: &[R],
        px: &Pixels<'_>,
        shared: &Shared<R>,
        bufs: &InferBuffers<R>,
        rgb: &mut [R],
    ) -> Result<()> {
        self.check_params(params)?;
        let n = px.n_pixels();
        ensure!(
            px.start.len() == n + 1
                && px.start[0] == 0
                && px.start[n] == px.points.len()
                && px.view.len() == n
                && rgb.len() == n * 3
                && (px.target.is_empty() || px.target.len() == n),
            "pixels: {n} directions, {} starts (first {:?}, last {:?}) for {} points, {} views, {} targets, {} colours",
            px.start.len(),
            px.start.first(),
            px.start.last(),
            px.points.len(),
            px.view.len(),
            px.target.len(),
            rgb.len() / 3
        );
        ensure!(
            px.footprint.len() == n
                || (px.footprint.is_empty() && self.cfg.level_weight == LevelWeight::None),
            "pixels: {} footprints for {n} pixels (the footprint level weighting needs one each)",
            px.footprint.len()
        );
        ensure!(
            self.vertex.is_none()
                || (px.triangles.len() == px.points.len() && px.bary.len() == px.points.len()),
            "pixels: the vertex featurization needs a triangle and barycentrics per point"
        );
        rgb.par_chunks_mut(PIXEL_CHUNK * 3)
            .enumerate()
            .try_for_each(|(c, out)| {
                self.check_pixels(px, c * PIXEL_CHUNK..(c * PIXEL_CHUNK + PIXEL_CHUNK).min(n))?;
                let mut f = bufs.for_this_thread();
                self.forward_chunk(&mut f, params, px, shared, c);
                out.copy_from_slice(&f.rgb);
                Ok(())
            })
    }

    /// [`Hfm::infer_pixels`]'s checks of `pixels` (what `Batch::validate` and
    /// [`Hfm::check_batch`] ask of a batch's).
    fn check_pixels(&self, px: &Pixels<'_>, pixels: Range<usize>) -> Result<()> {
        let views = self.appearance_views() as i32;
        for i in pixels {
            let (a, b) = (px.start[i], px.start[i + 1]);
            ensure!(
                a < b && b <= px.points.len(),
                "pixel {i}: no valid sub-sample ({a}..{b})"
            );
            for (j, p) in px.points[a..b].iter().enumerate() {
                ensure!(
                    p.iter().all(|v| v.is_finite()),
                    "pixel {i} valid sub-sample {j}: position {p:?} is not finite"
                );
            }
            if let Some(vt) = &self.vertex {
                for k in a..b {
                    let (t, w) = (px.triangles[k], px.bary[k]);
                    ensure!(
                        (t as usize) < vt.faces.len() && w.iter().all(|v| v.is_finite()),
                        "pixel {i}: triangle {t} (barycentrics {w:?}) is not one of the model's {} faces",
                        vt.faces.len()
                    );
                }
            }
            let d = px.dirs[i];
            ensure!(
                d.iter().all(|v| v.is_finite()),
                "pixel {i}: direction {d:?} is not finite"
            );
            if let Some(f) = px.footprint.get(i) {
                ensure!(
                    f.is_finite() && *f >= 0.0,
                    "pixel {i}: footprint {f} is not a finite number ≥ 0"
                );
            }
            let v = px.view[i];
            ensure!(
                v >= -1 && (self.appearance_dim() == 0 || v < views),
                "pixel {i}: view {v} has no appearance code (the model has {views} rows)"
            );
        }
        Ok(())
    }

    /// `params` has the layout's length.
    fn check_params<R>(&self, params: &[R]) -> Result<()> {
        ensure!(
            params.len() == self.layout.total,
            "parameters: {} values, the layout needs {}",
            params.len(),
            self.layout.total
        );
        Ok(())
    }

    /// [`Shared`] of `params`: the mean code and the MLPs' transposed weights.
    fn shared<R: Real>(&self, params: &[R]) -> Shared<R> {
        Shared {
            code_mean: self.code_mean(params),
            wt_shader: self
                .shader
                .transpose_weights(&params[self.r_shader.clone()]),
            wt_deform: self
                .deform
                .as_ref()
                .map(|m| m.transpose_weights(&params[self.r_deform.clone()])),
        }
    }

    /// What every chunk of a forward pass shares: the batch checked, its valid sub-samples
    /// compacted (CSR by pixel), the mean appearance code, the MLPs' transposed weights.
    fn prologue<R: Real>(&self, params: &[R], batch: &Batch) -> Result<Prologue<R>> {
        self.check_params(params)?;
        self.check_batch(batch)?;
        let n = batch.n_pixels();
        let s = batch.samples_per_pixel();
        let mut start = Vec::with_capacity(n + 1);
        let mut points = Vec::with_capacity(n * s);
        let mut sample_index = Vec::with_capacity(n * s);
        let (mut triangles, mut bary) = (Vec::new(), Vec::new());
        let ids = self.vertex.is_some();
        start.push(0);
        for i in 0..n {
            for j in 0..s {
                let k = i * s + j;
                if batch.valid[k] != 0 {
                    points.push(batch.positions[k]);
                    sample_index.push(k);
                    if ids {
                        triangles.push(batch.triangle[k]);
                        bary.push(batch.bary[k]);
                    }
                }
            }
            start.push(points.len());
        }
        Ok(Prologue {
            shared: self.shared(params),
            start,
            points,
            sample_index,
            triangles,
            bary,
        })
    }

    /// `[views, A]` the appearance codes within `params` (empty when A = 0).
    pub fn codes<'a, R: Real>(&self, params: &'a [R]) -> &'a [R] {
        &params[self.r_codes.clone()]
    }

    /// `[A]` mean of all appearance rows ([`appearance_mean`]).
    fn code_mean<R: Real>(&self, params: &[R]) -> Vec<R> {
        appearance_mean(
            &params[self.r_codes.clone()],
            self.appearance_dim(),
            self.appearance_views(),
        )
    }

    /// Chunk `c` (pixels `c·PIXEL_CHUNK ..`) of a forward pass into `f`, reusing its buffers.
    fn forward_chunk<R: Real>(
        &self,
        f: &mut ChunkFwd<R>,
        params: &[R],
        px: &Pixels<'_>,
        shared: &Shared<R>,
        c: usize,
    ) {
        let p0 = c * PIXEL_CHUNK;
        let pixels = p0..(p0 + PIXEL_CHUNK).min(px.n_pixels());
        let (start, points) = (px.start, px.points);
        let ids = (px.triangles, px.bary);
        let code_mean = &shared.code_mean[..];
        let wt_shader = &shared.wt_shader[..];
        let wt_deform = shared.wt_deform.as_deref();
        let mode = self.cfg.positions;
        let lf = self.feat_dim();
        let a = self.appearance_dim();
        let samples = start[pixels.start]..start[pixels.end];
        let (n, v) = (pixels.len(), samples.len());
        let pts = &points[samples.clone()];
        f.pixels = pixels.clone();
        f.samples = samples.clone();
        // Eq. 2: F_H at every valid sub-sample (or Fig. 2b's F_V: vertex featurization); every
        // element is written below (a skipped level as 0), as are the other buffers `fit` sizes.
        fit(&mut f.grid_h, v * lf);
        let local_start: Vec<usize> = start[pixels.start..=pixels.end]
            .iter()
            .map(|&x| x - samples.start)
            .collect();
        // SPEC §4.10: the weights of each sub-sample's levels, and how many levels it evaluates.
        let mut active = Vec::new();
        let mut weights_all_one = false;
        if self.cfg.level_weight == LevelWeight::Footprint {
            let nl = self.grid_h.scales.len();
            fit(&mut f.level_w, v * nl);
            active = vec![0u8; v];
            weights_all_one = level_weights(
                &self.grid_h.scales,
                &local_start,
                &px.footprint[pixels.clone()],
                &mut f.level_w,
                &mut active,
            );
        }
        match &self.vertex {
            None => {
                self.grid_h.forward_active(
                    &params[self.r_grid_h.clone()],
                    pts,
                    mode,
                    &mut f.grid_h,
                    &active,
                );
                // x · 1 is x: a chunk whose weights are all 1 is left as it is.
                if !f.level_w.is_empty() && !weights_all_one {
                    let nf = self.cfg.grid_h.features as usize;
                    apply_level_weights(&f.level_w, lf / nf, nf, &mut f.grid_h);
                }
            }
            Some(vt) => vertex_forward(
                vt,
                &params[self.r_vertex.clone()],
                &ids.0[samples.clone()],
                &ids.1[samples.clone()],
                &mut f.grid_h,
            ),
        }
        // SH(d_n).
        fit(&mut f.sh, n * SH_DIM);
        sh_forward(&px.dirs[pixels.clone()], &mut f.sh);
        // Eq. 5: δ_j = ξ([F_D(x_j), SH(d_n)]).
        if let (Some(gd), Some(mlp), Some(wt)) = (&self.grid_d, &self.deform, wt_deform) {
            let ld = gd.out_dim();
            fit(&mut f.grid_d, v * ld);
            gd.forward(&params[self.r_grid_d.clone()], pts, mode, &mut f.grid_d);
            let din = ld + SH_DIM;
            fit(&mut f.deform_in, v * din);
            for i in 0..n {
                let sh = &f.sh[i * SH_DIM..(i + 1) * SH_DIM];
                for j in start[pixels.start + i]..start[pixels.start + i + 1] {
                    let r = j - samples.start;
                    let row = &mut f.deform_in[r * din..(r + 1) * din];
                    row[..ld].copy_from_slice(&f.grid_d[r * ld..(r + 1) * ld]);
                    row[ld..].copy_from_slice(sh);
                }
            }
            mlp.forward(
                &params[self.r_deform.clone()],
                wt,
                &f.deform_in,
                v,
                &mut f.deform,
            );
        }
        // Eq. 4: pooled_n = (Σ_j F'_j) / count_n, F'_j = F_H(x_j) + δ_j.
        fit(&mut f.pooled, n * lf);
        let delta = self.deform.as_ref().map(|_| &f.deform.out[..]);
        pool_forward(&local_start, &f.grid_h, delta, lf, &mut f.pooled);
        // Shader input [pooled, SH(d), code(view)].
        let din = lf + SH_DIM + a;
        fit(&mut f.shader_in, n * din);
        let codes = &params[self.r_codes.clone()];
        for i in 0..n {
            let row = &mut f.shader_in[i * din..(i + 1) * din];
            row[..lf].copy_from_slice(&f.pooled[i * lf..(i + 1) * lf]);
            row[lf..lf + SH_DIM].copy_from_slice(&f.sh[i * SH_DIM..(i + 1) * SH_DIM]);
            if a > 0 {
                let vw = px.view[pixels.start + i];
                let code = if vw >= 0 {
                    &codes[vw as usize * a..(vw as usize + 1) * a]
                } else {
                    code_mean
                };
                row[lf + SH_DIM..].copy_from_slice(code);
            }
        }
        // Eq. 3: shader MLP → σ → rgb.
        self.shader.forward(
            &params[self.r_shader.clone()],
            wt_shader,
            &f.shader_in,
            n,
            &mut f.shader,
        );
        fit(&mut f.rgb, n * 3);
        sigmoid_forward(&f.shader.out, &mut f.rgb);
        // Rendering has no targets: no loss.
        f.loss_sum = match px.target.get(pixels) {
            Some(t) if !t.is_empty() => {
                loss_forward(self.cfg.loss, self.cfg.smooth_l1_delta, &f.rgb, t)
            }
            _ => 0.0,
        };
    }

    /// Backward pass: ACCUMULATES ∂L/∂params, ∂L/∂positions `[N*S*3]` and ∂L/∂dirs `[N*3]` into
    /// `grads` (input-gradient buffers are sized to the batch if empty). `fwd` must come from
    /// [`Hfm::forward`] with the same parameters and batch.
    // A hand-written backward pass (llm.c style): every stage in reverse order in one function.
    #[allow(clippy::too_many_lines)]
    pub fn backward<R: Real>(
        &self,
        params: &[R],
        batch: &Batch,
        fwd: &Forward<R>,
        grads: &mut Grads<R>,
    ) {
        let n = batch.n_pixels();
        let s = batch.samples_per_pixel();
        assert_eq!(
            grads.params.len(),
            self.layout.total,
            "gradient buffer layout"
        );
        let inputs = grads.inputs;
        if inputs && grads.positions.len() != n * s * 3 {
            grads.positions = vec![R::ZERO; n * s * 3];
        }
        if inputs && grads.dirs.len() != n * 3 {
            grads.dirs = vec![R::ZERO; n * 3];
        }
        // SPEC §4.7: with patches, (1−λ)·ρ + λ·D-SSIM; the D-SSIM gradient of every row first.
        let ssim = self.ssim_patch(batch);
        let lambda = ssim.map_or(0.0, |_| self.cfg.ssim_weight);
        let scale = R::from_f64((1.0 - lambda) / (3 * n) as f64);
        let d_ssim: Vec<R> = match ssim {
            Some(k) => {
                let rgb = batch_rgb(&fwd.chunks);
                let m = ssim_forward(k, &rgb, &batch.target, &batch.patch_mask).1;
                let mut d = vec![R::ZERO; n * 3];
                if m > 0 {
                    ssim_backward(
                        k,
                        &rgb,
                        &batch.target,
                        &batch.patch_mask,
                        -lambda / m as f64,
                        &mut d,
                    );
                }
                d
            }
            None => Vec::new(),
        };
        // The chunks write their rows of ∂L/∂F_H and ∂L/∂F_D straight into one buffer each, in
        // batch order (the grids' table backward reads them there; no copy after).
        let v_all = fwd.points.len();
        let lf = self.feat_dim();
        let ld = self.grid_d.as_ref().map_or(0, |g| g.out_dim());
        let position_max_scale = grads.position_max_scale;
        let (rows_h, rows_d) = (&mut grads.rows_h, &mut grads.rows_d);
        rows_h.resize(v_all * lf, R::ZERO);
        rows_d.resize(v_all * ld, R::ZERO);
        let cg: Vec<ChunkGrad<R>> = {
            let (mut rest_h, mut rest_d) = (&mut rows_h[..], &mut rows_d[..]);
            let mut parts = Vec::with_capacity(fwd.chunks.len());
            for ch in &fwd.chunks {
                let v = ch.samples.len();
                let (h, rh) = std::mem::take(&mut rest_h).split_at_mut(v * lf);
                let (d, rd) = std::mem::take(&mut rest_d).split_at_mut(v * ld);
                (rest_h, rest_d) = (rh, rd);
                parts.push((ch, h, d));
            }
            parts
                .into_par_iter()
                .map(|(ch, d_feat, d_grid_d)| {
                    self.backward_chunk(
                        params,
                        batch,
                        fwd,
                        ch,
                        scale,
                        d_ssim.get(ch.pixels.start * 3..ch.pixels.end * 3),
                        inputs,
                        position_max_scale,
                        d_feat,
                        d_grid_d,
                    )
                })
                .collect()
        };

        // Combine MLP weight gradients in chunk order.
        for c in &cg {
            add_into(&mut grads.params[self.r_shader.clone()], &c.d_shader);
            if self.deform.is_some() {
                add_into(&mut grads.params[self.r_deform.clone()], &c.d_deform);
            }
        }
        // Direction and position gradients (each pixel / sub-sample written by one chunk).
        for (ch, c) in fwd.chunks.iter().zip(&cg).filter(|_| inputs) {
            add_into(
                &mut grads.dirs[ch.pixels.start * 3..ch.pixels.end * 3],
                &c.d_dirs,
            );
            for (r, j) in ch.samples.clone().enumerate() {
                let k = fwd.sample_index[j];
                add_into(
                    &mut grads.positions[k * 3..k * 3 + 3],
                    &c.d_points[r * 3..r * 3 + 3],
                );
            }
        }
        // Appearance codes: pixels with a code in pixel order, then the mean-code pixels.
        let a = self.appearance_dim();
        if a > 0 {
            let views = self.appearance_views();
            let d_code: Vec<R> = cg.iter().flat_map(|c| c.d_code.iter().copied()).collect();
            appearance_backward(
                &batch.view,
                &d_code,
                a,
                views,
                &mut grads.params[self.r_codes.clone()],
            );
        }
        // Grid tables: one scatter over all valid sub-samples in batch order (H and D write
        // disjoint buffers, so they run concurrently).
        let mode = self.cfg.positions;
        let (d_feat, d_gd) = (&rows_h[..], &rows_d[..]);
        let (before_d, from_d) = grads.params.split_at_mut(
            self.r_grid_d
                .start
                .max(self.r_grid_h.end)
                .max(self.r_vertex.end),
        );
        if let Some(vt) = &self.vertex {
            // Fig. 2b backward (no grid D: deformation is off in this mode).
            vertex_backward(
                vt,
                &fwd.triangles,
                &fwd.bary,
                d_feat,
                &mut before_d[self.r_vertex.clone()],
                &mut grads.touched_v,
            );
            return;
        }
        let d_table_h = &mut before_d[self.r_grid_h.clone()];
        let touched_h = &mut grads.touched_h;
        let touched_d = &mut grads.touched_d;
        let points = &fwd.points;
        rayon::join(
            || {
                self.grid_h
                    .backward_table(points, mode, d_feat, d_table_h, touched_h)
            },
            || {
                if let Some(gd) = &self.grid_d {
                    let len = self.r_grid_d.len();
                    gd.backward_table(points, mode, d_gd, &mut from_d[..len], touched_d);
                }
            },
        );
    }

    // A hot kernel (inner loop of a step): its arguments are the buffers and sizes it works on,
    // llm.c style; kept as they are rather than re-measure its speed behind a struct.
    #[allow(clippy::too_many_arguments)]
    fn backward_chunk<R: Real>(
        &self,
        params: &[R],
        batch: &Batch,
        fwd: &Forward<R>,
        ch: &ChunkFwd<R>,
        scale: R,
        d_ssim: Option<&[R]>, // [n, 3] the D-SSIM term's ∂L/∂rgb of the chunk's rows
        inputs: bool,
        position_max_scale: Option<f32>,
        d_feat: &mut [R], // [v, L·F] out: ∂L/∂F'_j (= ∂L/∂F_H(x_j) = ∂L/∂δ_j), then weighted
        d_grid_d: &mut [R], // [v, L_D·F_D] out (empty without ξ)
    ) -> ChunkGrad<R> {
        let mode = self.cfg.positions;
        let lf = self.feat_dim();
        let a = self.appearance_dim();
        let (n, v) = (ch.pixels.len(), ch.samples.len());
        let pts = &fwd.points[ch.samples.clone()];
        // Loss and σ.
        let mut d_rgb = vec![R::ZERO; n * 3];
        loss_backward(
            self.cfg.loss,
            self.cfg.smooth_l1_delta,
            &ch.rgb,
            &batch.target[ch.pixels.clone()],
            scale,
            &mut d_rgb,
        );
        if let Some(d) = d_ssim {
            add_into(&mut d_rgb, d);
        }
        let mut d_logits = vec![R::ZERO; n * 3];
        sigmoid_backward(&ch.rgb, &d_rgb, &mut d_logits);
        // Shader (Eq. 3).
        let din = lf + SH_DIM + a;
        let mut d_shader = vec![R::ZERO; self.shader.n_params];
        let mut d_in = vec![R::ZERO; n * din];
        self.shader.backward(
            &params[self.r_shader.clone()],
            &ch.shader_in,
            n,
            &ch.shader,
            d_logits,
            &mut d_shader,
            Some(&mut d_in),
        );
        let mut d_sh = vec![R::ZERO; n * SH_DIM];
        let mut d_code = vec![R::ZERO; n * a];
        for i in 0..n {
            let row = &d_in[i * din..(i + 1) * din];
            d_sh[i * SH_DIM..(i + 1) * SH_DIM].copy_from_slice(&row[lf..lf + SH_DIM]);
            d_code[i * a..(i + 1) * a].copy_from_slice(&row[lf + SH_DIM..]);
        }
        // Eq. 4 backward: ∂L/∂F'_j = ∂L/∂pooled_n / count_n.
        debug_assert_eq!(d_feat.len(), v * lf);
        let local_start: Vec<usize> = fwd.start[ch.pixels.start..=ch.pixels.end]
            .iter()
            .map(|&x| x - ch.samples.start)
            .collect();
        pool_backward(&local_start, &d_in, din, lf, d_feat);
        let mut d_points = vec![R::ZERO; if inputs { v * 3 } else { 0 }];
        // Eq. 5 backward through ξ and into SH(d) and F_D.
        let mut d_deform = Vec::new();
        if let (Some(gd), Some(mlp)) = (&self.grid_d, &self.deform) {
            let ld = gd.out_dim();
            let ddin = ld + SH_DIM;
            d_deform = vec![R::ZERO; mlp.n_params];
            let mut d_din = vec![R::ZERO; v * ddin];
            mlp.backward(
                &params[self.r_deform.clone()],
                &ch.deform_in,
                v,
                &ch.deform,
                d_feat.to_vec(),
                &mut d_deform,
                Some(&mut d_din),
            );
            debug_assert_eq!(d_grid_d.len(), v * ld);
            for i in 0..n {
                let p = ch.pixels.start + i;
                for r in fwd.start[p] - ch.samples.start..fwd.start[p + 1] - ch.samples.start {
                    let row = &d_din[r * ddin..(r + 1) * ddin];
                    d_grid_d[r * ld..(r + 1) * ld].copy_from_slice(&row[..ld]);
                    add_into(&mut d_sh[i * SH_DIM..(i + 1) * SH_DIM], &row[ld..]);
                }
            }
            // SPEC §4.10: from here on d_feat is the gradient of grid H's (weighted) output.
            self.weight_grad(ch, d_feat);
            // Position gradient: grid H first (below), then grid D — keep that order.
            if inputs {
                self.grid_h.backward_points(
                    &params[self.r_grid_h.clone()],
                    pts,
                    mode,
                    &coarse_levels(&self.grid_h, d_feat, position_max_scale),
                    &mut d_points,
                );
                gd.backward_points(
                    &params[self.r_grid_d.clone()],
                    pts,
                    mode,
                    &coarse_levels(gd, d_grid_d, position_max_scale),
                    &mut d_points,
                );
            }
        } else if self.vertex.is_none() {
            self.weight_grad(ch, d_feat);
        }
        if inputs && self.vertex.is_none() && self.deform.is_none() {
            // (Vertex featurization: positions do not enter the model; their gradient is 0.)
            self.grid_h.backward_points(
                &params[self.r_grid_h.clone()],
                pts,
                mode,
                &coarse_levels(&self.grid_h, d_feat, position_max_scale),
                &mut d_points,
            );
        }
        // SH backward into the directions.
        let mut d_dirs = vec![R::ZERO; if inputs { n * 3 } else { 0 }];
        if inputs {
            sh_backward(&batch.dirs[ch.pixels.clone()], &d_sh, &mut d_dirs);
        }
        ChunkGrad {
            d_shader,
            d_deform,
            d_code,
            d_dirs,
            d_points,
        }
    }

    /// The patch side when the D-SSIM term applies to `batch` (λ > 0 and a patch batch).
    fn ssim_patch(&self, batch: &Batch) -> Option<usize> {
        (self.cfg.ssim_weight > 0.0 && batch.patch > 0).then_some(batch.patch)
    }

    /// `d_feat[v, L·F] *= level_w[v, L]` when the chunk was weighted (SPEC §4.10).
    fn weight_grad<R: Real>(&self, ch: &ChunkFwd<R>, d_feat: &mut [R]) {
        if !ch.level_w.is_empty() {
            let nf = self.cfg.grid_h.features as usize;
            let nl = self.feat_dim() / nf;
            apply_level_weights(&ch.level_w, nl, nf, d_feat);
        }
    }

    /// Forward + backward: accumulates gradients into `grads`, returns the loss.
    pub fn loss_and_grad<R: Real>(
        &self,
        params: &[R],
        batch: &Batch,
        grads: &mut Grads<R>,
    ) -> Result<f64> {
        let fwd = self.forward(params, batch)?;
        self.backward(params, batch, &fwd, grads);
        Ok(fwd.loss)
    }

    /// Features touched sets for sparse zeroing: `(F_H, F_D)`.
    pub fn grid_features(&self) -> (usize, usize) {
        (
            self.cfg.grid_h.features as usize,
            self.cfg.deform.grid.features as usize,
        )
    }
}

/// `d_out` `[v, L·F]` of `grid` with the columns of levels finer than `max_scale` cells per unit
/// zeroed (`Grads::position_max_scale`), borrowed unchanged when every level is kept.
fn coarse_levels<'a, R: Real>(
    grid: &HashGrid,
    d_out: &'a [R],
    max_scale: Option<f32>,
) -> std::borrow::Cow<'a, [R]> {
    let Some(m) = max_scale else {
        return std::borrow::Cow::Borrowed(d_out);
    };
    let kept = grid.scales.iter().take_while(|&&s| s <= m).count();
    if kept == grid.scales.len() {
        return std::borrow::Cow::Borrowed(d_out);
    }
    let f = grid.cfg.features as usize;
    let od = grid.out_dim();
    let mut v = d_out.to_vec();
    for row in v.chunks_exact_mut(od) {
        row[kept * f..].fill(R::ZERO);
    }
    std::borrow::Cow::Owned(v)
}

/// The `[N, 3]` colours of a forward pass's chunks, in batch order.
fn batch_rgb<R: Real>(chunks: &[ChunkFwd<R>]) -> Vec<R> {
    chunks.iter().flat_map(|c| c.rgb.iter().copied()).collect()
}

/// `[A]` mean of the appearance rows `codes [views, A]` (the code of `view = −1`, SPEC §4.6): the
/// rows summed in row order from +0, then divided by `views`; zeros when `a` or `views` is 0.
pub fn appearance_mean<R: Real>(codes: &[R], a: usize, views: usize) -> Vec<R> {
    let mut m = vec![R::ZERO; a];
    if a == 0 || views == 0 {
        return m;
    }
    for row in codes.chunks_exact(a) {
        for (mi, &v) in m.iter_mut().zip(row) {
            *mi += v;
        }
    }
    let inv = R::from_f64(views as f64);
    for v in m.iter_mut() {
        *v = *v / inv;
    }
    m
}

/// Accumulate `d_codes [views, A] += ∂L/∂codes` from the pixels' code gradients `d_code [N, A]`
/// (SPEC §4.6): pixels with a row (`view[n] ≥ 0`) added to it in pixel order; then the sum of the
/// `view = −1` pixels' gradients (pixel order, from +0) divided by `views` added to every row.
pub fn appearance_backward<R: Real>(
    view: &[i32],
    d_code: &[R],
    a: usize,
    views: usize,
    d_codes: &mut [R],
) {
    if a == 0 {
        return;
    }
    let mut mean_acc = vec![R::ZERO; a];
    let mut any_mean = false;
    for (&vw, dc) in view.iter().zip(d_code.chunks_exact(a)) {
        if vw >= 0 {
            add_into(&mut d_codes[vw as usize * a..(vw as usize + 1) * a], dc);
        } else {
            any_mean = true;
            add_into(&mut mean_acc, dc);
        }
    }
    if any_mean && views > 0 {
        let inv = R::from_f64(views as f64);
        for m in mean_acc.iter_mut() {
            *m = *m / inv;
        }
        for row in d_codes.chunks_exact_mut(a) {
            add_into(row, &mean_acc);
        }
    }
}

/// Eq. 4 forward: `out[n, lf] = (Σ_{j ∈ start[n]..start[n+1]} (feat[j] + delta[j])) / count_n`,
/// summed in sub-sample order starting from +0, then divided by the count (overwrites `out`).
/// `start [n+1]` indexes the rows of `feat`/`delta` `[v, lf]`.
pub fn pool_forward<R: Real>(
    start: &[usize],
    feat: &[R],
    delta: Option<&[R]>,
    lf: usize,
    out: &mut [R],
) {
    for (i, w) in start.windows(2).enumerate() {
        let cnt = R::from_f64((w[1] - w[0]) as f64);
        let o = &mut out[i * lf..(i + 1) * lf];
        o.fill(R::ZERO);
        for r in w[0]..w[1] {
            let g = &feat[r * lf..(r + 1) * lf];
            match delta {
                Some(d) => {
                    for ((o, &g), &d) in o.iter_mut().zip(g).zip(&d[r * lf..(r + 1) * lf]) {
                        *o += g + d;
                    }
                }
                None => add_into(o, g),
            }
        }
        for v in o.iter_mut() {
            *v = *v / cnt;
        }
    }
}

/// Eq. 4 backward: `d_feat[j] = d_pooled[n] / count_n` for every valid sub-sample j of pixel n
/// (OVERWRITES `d_feat [v, lf]`, which is both ∂L/∂F_H(x_j) and ∂L/∂δ_j). `d_pooled` rows have
/// stride `stride` (the pooled block is the first `lf` columns).
pub fn pool_backward<R: Real>(
    start: &[usize],
    d_pooled: &[R],
    stride: usize,
    lf: usize,
    d_feat: &mut [R],
) {
    for (i, w) in start.windows(2).enumerate() {
        let cnt = R::from_f64((w[1] - w[0]) as f64);
        let dp = &d_pooled[i * stride..i * stride + lf];
        for r in w[0]..w[1] {
            for (d, &g) in d_feat[r * lf..(r + 1) * lf].iter_mut().zip(dp) {
                *d = g / cnt;
            }
        }
    }
}

/// `dst += src` element-wise.
#[inline]
fn add_into<R: Real>(dst: &mut [R], src: &[R]) {
    for (d, &s) in dst.iter_mut().zip(src) {
        *d += s;
    }
}

/// Push an MLP's tensors (`<net>.layers.{i}.weight` [out, in], `.bias` [out]) contiguously.
fn push_mlp(layout: &mut ParamLayout, net: &str, mlp: &Mlp, group: Group) -> Range<usize> {
    let start = layout.total;
    for (i, l) in mlp.layers.iter().enumerate() {
        let r = layout.push(
            &format!("{net}.layers.{i}.weight"),
            &[l.out_dim, l.in_dim],
            group,
        );
        debug_assert_eq!(r.start - start, l.w_off);
        if let Some(b) = l.b_off {
            let r = layout.push(&format!("{net}.layers.{i}.bias"), &[l.out_dim], group);
            debug_assert_eq!(r.start - start, b);
        }
    }
    start..layout.total
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn bad_inputs_are_named_errors() {
        let mut cfg = ModelConfig::tiny();
        cfg.appearance_views = 2;
        let m = Hfm::new(&cfg).unwrap();
        let p: Vec<f64> = m.init_params(1).iter().map(|&v| v as f64).collect();
        let mut b = Batch::random(1, 10, 4, 2, 0.3);
        m.forward(&p, &b).unwrap();
        b.view[4] = 2;
        let e = m.forward(&p, &b).unwrap_err().to_string();
        assert!(e.contains("pixel 4") && e.contains("view 2"), "{e}");
        b.view[4] = 0;
        let e = m.forward(&p[1..], &b).unwrap_err().to_string();
        assert!(e.contains("parameters"), "{e}");
        let mut bad = cfg.clone();
        bad.grid_h.features = 3;
        assert!(Hfm::new(&bad).is_err());
    }

    /// `infer` (rendering's path: buffers reused per thread, no backward state) gives the same
    /// bits as `forward`'s colours, in f32 and f64, over several chunks, with invalid
    /// sub-samples, view codes and ξ on (fails if a reused buffer keeps a previous chunk's data).
    #[test]
    fn infer_is_forward_rgb_bit_for_bit() {
        let mut cfg = ModelConfig::cpu();
        cfg.appearance_views = 4;
        let m = Hfm::new(&cfg).unwrap();
        let p32 = m.init_params(7);
        let p64: Vec<f64> = p32.iter().map(|&v| v as f64).collect();
        let n = 3 * PIXEL_CHUNK + 57;
        let mut b = Batch::random(5, n, 4, 4, 0.3);
        assert!(b.valid.contains(&0));
        // Footprints from finer than the finest cell to coarser than level 0's (level weighting).
        b.footprint = (0..n)
            .map(|i| 10f32.powf(-4.0 + 3.0 * ((i * 37) % 101) as f32 / 100.0))
            .collect();
        let rgb = |f: Forward<f32>| -> Vec<f32> {
            f.chunks
                .iter()
                .flat_map(|c| c.rgb.iter().copied())
                .collect()
        };
        let want = rgb(m.forward(&p32, &b).unwrap());
        let got = m.infer(&p32, &b).unwrap();
        assert_eq!(got.len(), 3 * n);
        let diff = want
            .iter()
            .zip(&got)
            .filter(|(a, b)| a.to_bits() != b.to_bits());
        assert_eq!(diff.count(), 0, "f32 infer differs from forward");
        let want: Vec<f64> = m
            .forward(&p64, &b)
            .unwrap()
            .chunks
            .iter()
            .flat_map(|c| c.rgb.iter().copied())
            .collect();
        assert_eq!(m.infer(&p64, &b).unwrap(), want, "f64 infer differs");
    }

    /// `infer_pixels` (the renderer's path: valid sub-samples compacted by the caller, no
    /// batch) gives `infer`'s bits with the mean code and with a code given for view −1, and
    /// refuses pixels a batch would be refused for.
    #[test]
    fn infer_pixels_is_infer_bit_for_bit() {
        let mut cfg = ModelConfig::cpu();
        cfg.appearance_views = 4;
        let m = Hfm::new(&cfg).unwrap();
        let p = m.init_params(7);
        let n = 2 * PIXEL_CHUNK + 31;
        let mut b = Batch::random(9, n, 4, 4, 0.3);
        b.footprint = (0..n)
            .map(|i| 10f32.powf(-4.0 + 3.0 * ((i * 37) % 101) as f32 / 100.0))
            .collect();
        let mut start = vec![0];
        let mut points = Vec::new();
        for i in 0..n {
            for j in 0..4 {
                if b.valid[i * 4 + j] != 0 {
                    points.push(b.positions[i * 4 + j]);
                }
            }
            start.push(points.len());
        }
        let px = Pixels {
            start: &start,
            points: &points,
            triangles: &[],
            bary: &[],
            dirs: &b.dirs,
            footprint: &b.footprint,
            view: &b.view,
            target: &[],
        };
        let bufs = InferBuffers::new();
        let code = [0.25f32, -0.5, 0.75, 0.1][..cfg.appearance_dim as usize].to_vec();
        for c in [None, Some(&code[..])] {
            let want = m.infer_coded(&p, &b, c).unwrap();
            let shared = m.infer_shared(&p, c).unwrap();
            let mut got = vec![0.0f32; 3 * n];
            m.infer_pixels(&p, &px, &shared, &bufs, &mut got).unwrap();
            let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
            assert!(
                bits(&got) == bits(&want),
                "code {c:?}: infer_pixels differs"
            );
        }
        let shared = m.infer_shared(&p, None).unwrap();
        let mut rgb = vec![0.0f32; 3 * n];
        // A pixel without a valid sub-sample, a view without a code, a missing footprint.
        let mut empty = start.clone();
        empty[5] = empty[4];
        let mut e = px;
        e.start = &empty;
        // (start[5] = start[4] leaves pixel 4 empty)
        let err = m
            .infer_pixels(&p, &e, &shared, &bufs, &mut rgb)
            .unwrap_err();
        assert!(
            err.to_string().contains("pixel 4: no valid sub-sample"),
            "{err}"
        );
        let mut views = b.view.clone();
        views[n - 1] = 4;
        let mut e = px;
        e.view = &views;
        let err = m
            .infer_pixels(&p, &e, &shared, &bufs, &mut rgb)
            .unwrap_err();
        assert!(err.to_string().contains("has no appearance code"), "{err}");
        let mut e = px;
        e.footprint = &[];
        assert!(m.infer_pixels(&p, &e, &shared, &bufs, &mut rgb).is_err());
    }

    /// Switching parts off removes their tensors and changes the shader input width.
    #[test]
    fn layout_follows_switches() {
        let mut cfg = ModelConfig::tiny();
        cfg.appearance_views = 5;
        let m = Hfm::new(&cfg).unwrap();
        let names: Vec<&str> = m.layout.tensors.iter().map(|t| t.name.as_str()).collect();
        assert_eq!(
            names,
            [
                "grid_h.table",
                "grid_d.table",
                "deform.layers.0.weight",
                "deform.layers.1.weight",
                "shader.layers.0.weight",
                "shader.layers.1.weight",
                "appearance.codes"
            ]
        );
        assert_eq!(
            m.layout.get("shader.layers.0.weight").unwrap().shape,
            [16, 8 + 16 + 2]
        );
        assert_eq!(
            m.layout.get("deform.layers.0.weight").unwrap().shape,
            [8, 4 + 16]
        );
        assert_eq!(
            m.layout.get("deform.layers.1.weight").unwrap().shape,
            [8, 8]
        );
        cfg.deform.enabled = false;
        cfg.appearance_dim = 0;
        cfg.shader.bias = true;
        let m = Hfm::new(&cfg).unwrap();
        let names: Vec<&str> = m.layout.tensors.iter().map(|t| t.name.as_str()).collect();
        assert_eq!(
            names,
            [
                "grid_h.table",
                "shader.layers.0.weight",
                "shader.layers.0.bias",
                "shader.layers.1.weight",
                "shader.layers.1.bias"
            ]
        );
        assert_eq!(
            m.layout.get("shader.layers.0.weight").unwrap().shape,
            [16, 8 + 16]
        );
    }
}
