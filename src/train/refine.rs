//! Joint refinement of the mesh during training (`[model.refine] enabled = true`; the geometry
//! and its gradient are in `model/refine.rs`, the figures in docs/geometry.md).
//!
//! ## Schedule (steps k of a run of `train.steps` = T)
//! - `k < start·T`: the mesh is fixed (the features settle first); batches are cast against the
//!   training mesh exactly as without refinement.
//! - From `k0 = floor(start·T)`: level j of the offset field (grids coarse to fine, then the
//!   per-vertex residual; `n = levels + per_vertex` levels) is optimised from step
//!   `k0 + floor(j·coarse_to_fine·T / n)`. Inactive levels get no gradient (they stay zero).
//! - Each batch's valid sub-samples are re-intersected with the current plane of the triangle
//!   their ray hit (`model::refine::intersect`), so positions follow the mesh every step; the BVH
//!   is rebuilt from the current offsets before drawing batch k whenever `k > k0` and
//!   `(k − k0) % rebuild_every == 0` (then the triangle each ray hits is chosen again). A pixel
//!   none of whose rays hits the rebuilt mesh is left out of its batch.
//!
//! ## A step while the mesh moves
//! forward → backward with `grad.batch.positions` → `∂L/∂θ` through the hit points
//! (`hits_backward`) → plus the smoothness energy's gradient on the residual → into the active
//! levels (`theta_backward`) → Adam (tiny-cuda-nn rules, sparse: untouched nodes keep their
//! moments; state `adam.*.refine.*` in the checkpoint) next to the model's groups. The logged loss
//! is the photometric loss alone.
//!
//! ## Determinism and resume
//! Every reduction runs in a fixed order (hits in batch order, vertices in ascending order,
//! grids node by node); re-intersection is per sub-sample; so results are bit-identical for any
//! thread count. Batch k is a pure function of (seed, k, the offsets its BVH was built from):
//! batch k+1 is cast while step k runs only when no rebuild is due before it. The checkpoint holds
//! the offsets the current BVH was built from (`refine.traced`), so a resumed run rebuilds the
//! same BVH and continues bit for bit. `refine.offsets` (what eval/render apply) is brought up to
//! date before every checkpoint, evaluation and the end of the run.

use crate::model::batch::Batch;
use crate::model::params::Grads;
use crate::model::refine::{
    field_backward, grid_name, hits_backward, reintersect_batch, smoothness, RayHit, RefineConfig,
    RefineGeom, VERTEX_NAME,
};
use crate::raycast::Tracer;
use crate::train::adam::{AdamGroup, LrSchedule};
use crate::train::config::RunConfig;
use crate::train::sampler::{sample_batch, SampleMode, Samples};
use crate::train::setup::Prepared;
use crate::train::trainer::{batch_mse, StepStats, TrainState};
use anyhow::{ensure, Context, Result};
use glam::DVec3;
use rayon::prelude::*;
use std::path::Path;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::Instant;

/// Turn refinement on in a run configuration (the defaults of `[model.refine]`).
pub fn enable(cfg: &mut RunConfig) -> Result<()> {
    cfg.model.refine.enabled = true;
    cfg.validate()
}

/// The checks a run configuration with refinement must pass (called by `RunConfig::validate`).
pub fn validate(cfg: &RunConfig) -> Result<()> {
    let r = &cfg.model.refine;
    r.validate().context("model.refine")?;
    if !r.enabled {
        return Ok(());
    }
    ensure!(
        cfg.model.featurization.is_hash(),
        "model.refine: the mesh refinement needs featurization = \"hash\""
    );
    ensure!(
        cfg.train.samples == SampleMode::Stream,
        "model.refine: the mesh moves, so rays must be cast as batches are drawn: set [train] samples = \"stream\""
    );
    ensure!(
        cfg.train.arithmetic == crate::train::config::Arithmetic::F32,
        "model.refine: runs in f32 arithmetic only (remove [train] arithmetic = \"f64\")"
    );
    Ok(())
}

/// The refinement side of a training run (module docs).
pub struct Refiner {
    cfg: RefineConfig,
    geom: Arc<RefineGeom>,
    /// BVH of the mesh at `traced` offsets (`None`: the training mesh, `prepared.tracer`).
    tracer: Option<Arc<Tracer>>,
    /// Camera centre of each appearance row (training view), local frame.
    origins: Vec<DVec3>,
    steps: u64,
    seed: u64,
    batch_pixels: usize,
    /// Steps after which the loop saves or evaluates (offsets are synced before).
    checkpoint_every: u64,
    eval_every: u64,
    interrupt: Option<&'static AtomicBool>,
    adam: AdamGroup,
    // Scratch, kept between steps.
    theta: Vec<f64>,
    d_theta: Vec<f64>,
    d_grids: Vec<Vec<f64>>,
    d_vertex: Vec<f64>,
    g32: Vec<f32>,
}

impl Refiner {
    /// The refiner of a run, `None` unless `[model.refine] enabled`.
    pub fn for_run(
        state: &TrainState,
        prepared: &Prepared,
        interrupt: Option<&'static AtomicBool>,
    ) -> Result<Option<Refiner>> {
        let cfg = state.cfg.model.refine.clone();
        if !cfg.enabled {
            return Ok(None);
        }
        let params = state
            .ckpt
            .refine
            .as_ref()
            .context("[model.refine] is enabled but the checkpoint has no refine.* tensors")?;
        let norm = state.ckpt.normalization;
        ensure!(
            norm == prepared.scene.normalization,
            "model.refine: the model's normalisation differs from the scene mesh's (refinement needs the training mesh)"
        );
        let mesh = &prepared.scene.mesh;
        ensure!(
            params.n_vertices() == mesh.vertices.len(),
            "the checkpoint refines a mesh of {} vertices but the scene's mesh has {}",
            params.n_vertices(),
            mesh.vertices.len()
        );
        ensure!(
            prepared.samples.has_triangles(),
            "model.refine: the batches carry no triangle ids (internal: prepare the scene with refinement on)"
        );
        let geom = Arc::new(RefineGeom::new(mesh, &norm));
        let origins = prepared
            .train_views
            .iter()
            .map(|&i| prepared.scene.views[i].camera.center() - norm.center)
            .collect();
        let nv = geom.n_vertices();
        let mut r = Refiner {
            geom,
            tracer: None,
            origins,
            steps: state.cfg.train.steps,
            seed: state.cfg.train.seed,
            batch_pixels: state.cfg.train.batch_pixels,
            checkpoint_every: state.cfg.train.checkpoint_every,
            eval_every: state.cfg.train.eval_every,
            interrupt,
            adam: AdamGroup {
                lr: cfg.lr,
                beta1: cfg.beta1,
                beta2: cfg.beta2,
                epsilon: cfg.epsilon,
                l2: 0.0,
                sparse: true,
                schedule: LrSchedule::default(),
            },
            theta: vec![0.0; nv],
            d_theta: vec![0.0; nv],
            d_grids: params.grids.iter().map(|g| vec![0.0; g.len()]).collect(),
            d_vertex: vec![0.0; params.vertex.len()],
            g32: Vec::new(),
            cfg,
        };
        if params.traced.iter().any(|&t| t != 0.0) {
            let traced: Vec<f64> = params.traced.iter().map(|&t| t as f64).collect();
            r.tracer = Some(Arc::new(r.build_tracer(&traced)?));
        }
        Ok(Some(r))
    }

    /// First step at which the mesh moves.
    pub fn start_step(&self) -> u64 {
        (self.cfg.start * self.steps as f64).floor() as u64
    }

    /// Active (grid levels, residual) at step k.
    pub fn active(&self, k: u64) -> (usize, bool) {
        let k0 = self.start_step();
        if k < k0 {
            return (0, false);
        }
        let n = self.cfg.n_levels() as u64;
        let span = self.cfg.coarse_to_fine * self.steps as f64;
        let on = (0..n)
            .filter(|&j| k >= k0 + (j as f64 * span / n as f64).floor() as u64)
            .count();
        let grids = on.min(self.cfg.levels as usize);
        (grids, on > self.cfg.levels as usize)
    }

    /// `Grads::position_max_scale` at step k (`gradient_cells`, geometric from the first moving
    /// step to the last).
    pub fn gradient_scale(&self, k: u64) -> Option<f32> {
        let [g0, g1] = self.cfg.gradient_cells;
        if g0 <= 0.0 {
            return None;
        }
        let k0 = self.start_step();
        let span = self.steps.saturating_sub(k0 + 1).max(1) as f64;
        let f = (k.saturating_sub(k0) as f64 / span).min(1.0);
        Some((g0 * (g1 / g0).powf(f)) as f32)
    }

    fn needs_rebuild(&self, k: u64) -> bool {
        let k0 = self.start_step();
        k > k0 && (k - k0) % self.cfg.rebuild_every as u64 == 0
    }

    fn build_tracer(&self, theta: &[f64]) -> Result<Tracer> {
        let mesh = self.geom.mesh_with(theta);
        ensure!(
            mesh.vertices.iter().all(|v| v.is_finite()),
            "model.refine: a refined vertex is not finite"
        );
        // In the local frame of the model's normalisation (SPEC §4.1), like the training mesh's.
        Tracer::new(&mesh, &self.geom.norm).context("rebuilding the BVH of the refined mesh")
    }

    /// Rebuild the BVH from the current offsets (and sync `offsets`, `traced`).
    fn rebuild(&mut self, state: &mut TrainState) -> Result<()> {
        let p = state.ckpt.refine.as_mut().expect("refine params");
        let theta = p.theta_all(&self.cfg, &self.geom);
        p.offsets = theta.iter().map(|&t| t as f32).collect();
        p.traced = p.offsets.clone();
        let traced: Vec<f64> = p.traced.iter().map(|&t| t as f64).collect();
        self.tracer = Some(Arc::new(self.build_tracer(&traced)?));
        Ok(())
    }

    /// Batch k: cast against the current BVH, with triangle ids.
    pub fn draw(&self, prepared: &Prepared, k: u64) -> Batch {
        draw_with(
            &prepared.samples,
            self.tracer.as_deref().unwrap_or(&prepared.tracer),
            self.seed,
            k,
            self.batch_pixels,
        )
    }

    /// Step `state` on `batch` and draw batch `next` (if any), rebuilding the BVH first when one
    /// is due (module docs).
    pub fn step_and_draw(
        &mut self,
        state: &mut TrainState,
        prepared: &Prepared,
        batch: &mut Batch,
        grads: &mut Grads<f32>,
        next: Option<u64>,
    ) -> (Result<StepStats>, Option<Batch>) {
        match next {
            Some(k1) if !self.needs_rebuild(k1) => {
                let tracer = self.tracer.clone();
                let (seed, n) = (self.seed, self.batch_pixels);
                let (st, nb) = rayon::join(
                    || self.step(state, batch, grads),
                    || {
                        draw_with(
                            &prepared.samples,
                            tracer.as_deref().unwrap_or(&prepared.tracer),
                            seed,
                            k1,
                            n,
                        )
                    },
                );
                (st, Some(nb))
            }
            Some(k1) => {
                let st = self.step(state, batch, grads);
                if st.is_err() {
                    return (st, None);
                }
                if let Err(e) = self.rebuild(state) {
                    return (Err(e), None);
                }
                let nb = self.draw(prepared, k1);
                (st, Some(nb))
            }
            None => (self.step(state, batch, grads), None),
        }
    }

    /// One optimisation step (module docs); `grads` zero on entry and exit, as `TrainState::step`.
    pub fn step(
        &mut self,
        state: &mut TrainState,
        batch: &mut Batch,
        grads: &mut Grads<f32>,
    ) -> Result<StepStats> {
        let k = state.step;
        let (levels, residual) = self.active(k);
        let moving = k >= self.start_step();
        let t0 = Instant::now();
        let hits = if moving {
            self.reintersect(state, batch)?
        } else {
            Vec::new()
        };
        grads.inputs = moving;
        grads.position_max_scale = self.gradient_scale(k);
        let model = &state.ckpt.model;
        let fwd = model.forward(&state.ckpt.params, batch)?;
        let t1 = Instant::now();
        model.backward(&state.ckpt.params, batch, &fwd, grads);
        let t2 = Instant::now();
        let mse = batch_mse(&fwd, batch);
        if moving && (levels > 0 || residual) {
            self.geometry_step(state, &hits, &grads.positions, levels, residual, k);
        }
        grads.inputs = false;
        state.apply_adam(grads);
        let st = state.finish_step(grads, fwd.loss, mse, fwd.points.len(), [t0, t1, t2]);
        // `offsets` up to date whenever the loop may save, evaluate or stop after this step.
        let done = state.step;
        let due = |every: u64| every > 0 && done % every == 0;
        if moving
            && (done >= self.steps
                || due(self.checkpoint_every)
                || due(self.eval_every)
                || !st.loss.is_finite()
                || self.interrupt.is_some_and(|f| f.load(Ordering::SeqCst)))
        {
            state
                .ckpt
                .refine
                .as_mut()
                .expect("refine params")
                .sync_offsets(&self.cfg, &self.geom);
        }
        Ok(st)
    }

    /// Re-intersect `batch` with the current mesh (module docs), after leaving out pixels no ray
    /// of which hit the current BVH.
    fn reintersect(&mut self, state: &TrainState, batch: &mut Batch) -> Result<Vec<RayHit>> {
        drop_empty_pixels(batch);
        ensure!(
            batch.triangle.len() == batch.positions.len(),
            "model.refine: the batch carries no triangle ids"
        );
        let geom = &*self.geom;
        let params = state.ckpt.refine.as_ref().expect("refine params");
        // θ of every vertex the batch's triangles use.
        let mut used: Vec<u32> = batch
            .triangle
            .iter()
            .zip(&batch.valid)
            .filter(|(_, &v)| v != 0)
            .flat_map(|(&t, _)| geom.triangles[t as usize])
            .collect();
        used.sort_unstable();
        used.dedup();
        let cfg = &self.cfg;
        let th: Vec<f64> = used
            .par_iter()
            .with_min_len(1024)
            .map(|&i| params.theta(cfg, geom, i as usize))
            .collect();
        for (&i, &t) in used.iter().zip(&th) {
            self.theta[i as usize] = t;
        }
        let (origins, views) = (&self.origins, batch.view.clone());
        let origin = move |p: usize| origins[views[p] as usize];
        Ok(reintersect_batch(
            geom,
            &self.theta,
            batch,
            &origin,
            self.cfg.min_cos,
        ))
    }

    /// `∂L/∂θ` → the active levels → Adam (module docs).
    fn geometry_step(
        &mut self,
        state: &mut TrainState,
        hits: &[RayHit],
        d_positions: &[f32],
        levels: usize,
        residual: bool,
        k: u64,
    ) {
        let geom = &*self.geom;
        hits_backward(geom, hits, d_positions, &mut self.d_theta);
        let mut touched: Vec<u32> = hits.iter().flat_map(|h| h.tri).collect();
        touched.sort_unstable();
        touched.dedup();
        let TrainState { ckpt, adam, .. } = state;
        let params = ckpt.refine.as_mut().expect("refine params");
        field_backward(
            &self.cfg,
            geom,
            &touched,
            &self.d_theta,
            levels,
            residual,
            &mut self.d_grids,
            &mut self.d_vertex,
        );
        for &i in &touched {
            self.d_theta[i as usize] = 0.0;
        }
        if residual {
            smoothness(&self.cfg, geom, &params.vertex, &mut self.d_vertex);
        }
        for l in 0..levels {
            let name = grid_name(l);
            let r = adam.range(&name).expect("adam slot of a refine grid");
            self.g32.clear();
            self.g32.extend(self.d_grids[l].iter().map(|&g| g as f32));
            adam.step_dense(r, &mut params.grids[l], &self.g32, &self.adam, k);
            self.d_grids[l].fill(0.0);
        }
        if residual {
            let r = adam.range(VERTEX_NAME).expect("adam slot of refine.vertex");
            self.g32.clear();
            self.g32.extend(self.d_vertex.iter().map(|&g| g as f32));
            adam.step_dense(r, &mut params.vertex, &self.g32, &self.adam, k);
            self.d_vertex.fill(0.0);
        }
    }
}

/// Batch k cast against `tracer` (pixels none of whose rays hit are dropped at use).
fn draw_with(samples: &Samples, tracer: &Tracer, seed: u64, k: u64, n: usize) -> Batch {
    sample_batch(samples, tracer, seed, k, n)
}

/// Remove the pixels none of whose sub-samples is valid (possible once the mesh has moved).
pub fn drop_empty_pixels(b: &mut Batch) {
    let s = b.samples_per_pixel();
    let n = b.n_pixels();
    if s == 0 {
        return;
    }
    let keep: Vec<bool> = (0..n)
        .map(|i| b.valid[i * s..(i + 1) * s].iter().any(|&v| v != 0))
        .collect();
    if keep.iter().all(|&k| k) {
        return;
    }
    let mut w = 0;
    for (i, &k) in keep.iter().enumerate() {
        if !k {
            continue;
        }
        if w != i {
            for j in 0..s {
                b.positions[w * s + j] = b.positions[i * s + j];
                b.valid[w * s + j] = b.valid[i * s + j];
                if !b.triangle.is_empty() {
                    b.triangle[w * s + j] = b.triangle[i * s + j];
                    b.bary[w * s + j] = b.bary[i * s + j];
                }
            }
            b.dirs[w] = b.dirs[i];
            b.view[w] = b.view[i];
            b.target[w] = b.target[i];
            if !b.footprint.is_empty() {
                b.footprint[w] = b.footprint[i];
            }
        }
        w += 1;
    }
    b.positions.truncate(w * s);
    b.valid.truncate(w * s);
    if !b.triangle.is_empty() {
        b.triangle.truncate(w * s);
        b.bary.truncate(w * s);
    }
    b.dirs.truncate(w);
    b.view.truncate(w);
    b.target.truncate(w);
    if !b.footprint.is_empty() {
        b.footprint.truncate(w);
    }
}

/// The BVH to evaluate a state with: the refined mesh's when it refines one, else `None`.
pub fn eval_tracer(state: &TrainState, prepared: &Prepared) -> Result<Option<Tracer>> {
    match &state.ckpt.refine {
        Some(p) => {
            let m = crate::model::refine::refined_mesh(
                &prepared.scene.mesh,
                &state.ckpt.normalization,
                &p.offsets,
            )?;
            Ok(Some(Tracer::new(&m, &state.ckpt.normalization)?))
        }
        None => Ok(None),
    }
}

/// `RUN/refined.ply`: the training mesh with the offsets of `state` (written at the end of a run
/// that refines the mesh; nothing otherwise).
pub fn write_refined(state: &TrainState, prepared: &Prepared, run_dir: &Path) -> Result<()> {
    let Some(p) = &state.ckpt.refine else {
        return Ok(());
    };
    let m = crate::model::refine::refined_mesh(
        &prepared.scene.mesh,
        &state.ckpt.normalization,
        &p.offsets,
    )?;
    crate::scene::mesh::write_ply(&run_dir.join("refined.ply"), &m)
}
