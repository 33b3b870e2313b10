//! The refinement step driver: the mesh refinement during training (`[model.refine] enabled =
//! true`; the offset field is `field.rs`, the hit points and their gradient `hit.rs`, the figures
//! in docs/geometry.md).
//!
//! ## Schedule (steps k of a run of `train.steps` = T)
//! - `k < k0 = floor(start·T)`: the mesh is fixed (the features settle first); batches are cast
//!   against the training mesh exactly as without refinement (same bits).
//! - `k0 ≤ k < k1 = floor(stop·T)`: the mesh moves. Level j of the offset field (grids coarse to
//!   fine, then the per-vertex residual; `n = levels + per_vertex` levels) receives gradient from
//!   step `k0 + floor(j·coarse_to_fine·T / n)`; inactive levels stay zero. The position gradient
//!   goes through the hash-grid levels of at most `gradient_cells` cells per unit, from
//!   `gradient_cells[0]` at k0 to `[1]` at T − 1 (geometric): coarse to fine
//!   (`Grads::position_max_scale`).
//! - The vertex gradient is summed over `update_every` steps (in `refine.pending.*`); then the
//!   smoothness energy's gradient (times the steps summed) is added, the active levels take one
//!   Adam step (tiny-cuda-nn rules, sparse: untouched nodes keep their moments; state
//!   `adam.*.refine.*`), and the BVH is rebuilt from the moved mesh before the next batch is cast.
//!   The last update is at k1 − 1.
//! - `k ≥ k1`: the mesh is fixed again and the features converge on it.
//!
//! With `photo` > 0 the photo-consistency term of the training photos (`photo_term.rs`) adds its
//! vertex gradient at every moving step after the loss's (which is scaled by `features`, and not
//! computed at all when that is 0), into the same pending sums; with `optimizer = "gauss-newton"`
//! its curvature is gathered alongside (`refine.pending_h.*`) and an update divides the one by the
//! other instead of taking an Adam step (SPEC §4.11).
//! With `photo_rechoose`, every BVH rebuild (and a resumed run's first BVH) also chooses the photo
//! term's neighbour views again on the moved mesh.
//!
//! While the mesh moves, every batch's valid sub-samples are re-intersected with the current
//! plane of the triangle their ray hit (`hit::reintersect_batch`): between updates the
//! mesh does not change, so this reproduces the cast hit (up to the batch's 2⁻³² fixed point) and
//! gives the records the vertex gradient needs. A pixel none of whose rays hits the rebuilt mesh
//! is left out of its batch. The logged loss is the photometric loss alone.
//!
//! ## Determinism and resume
//! Every reduction runs in a fixed order (hits in batch order, vertices in ascending order,
//! grids node by node); re-intersection is per sub-sample; so results are bit-identical for any
//! thread count. Batch k is a pure function of (seed, k, the offsets its BVH was built from):
//! batch k+1 is cast while step k runs only when no rebuild is due before it. The checkpoint holds
//! the offsets the current BVH was built from (`refine.traced`) and the pending gradient sums, so
//! a resumed run rebuilds the same BVH and continues bit for bit. `refine.offsets` (what
//! eval/render apply) is brought up to date at every update and before every checkpoint,
//! evaluation and the end of the run.

use crate::model::batch::Batch;
use crate::model::params::Grads;
use crate::model::refine::{grid_name, RefineConfig, RefineOptimizer, VERTEX_NAME};
use crate::raycast::Tracer;
use crate::refine::diagnostics::Diagnostics;
use crate::refine::field::{self, field_backward, smoothness, Active, RefineGeom};
use crate::refine::hit::{
    hits_backward, hits_backward_anchored, reintersect_batch, reintersect_batch_anchored, RayHit,
};
use crate::refine::photo_term::{self, PhotoStats, PhotoTerm};
use crate::refine::trust::{self, TrustPool};
use crate::train::adam::{AdamGroup, LrSchedule};
use crate::train::sampler::{draw_batch, Samples};
use crate::train::setup::Prepared;
use crate::train::state::{batch_mse, StepStats, TrainState};
use anyhow::{ensure, Context, Result};
use glam::DVec3;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::Instant;

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
    /// `[train] patch` and the pixels drawn in patches (patch batches for the D-SSIM term).
    patch: u32,
    patched: usize,
    /// Steps after which the loop saves or evaluates (offsets are synced before).
    checkpoint_every: u64,
    eval_every: u64,
    interrupt: Option<&'static AtomicBool>,
    adam: AdamGroup,
    /// `XSCALE_REFINE_LOG` (a file) and `XSCALE_REFINE_TRUTH` (a mesh with the training mesh's
    /// vertices, e.g. a synthetic scene's exact surface): diagnostics at every update.
    diag: Option<Diagnostics>,
    /// `refine.traced` in f64: the offsets the current BVH was built from (set with it).
    traced: Vec<f64>,
    // Scratch, kept between steps.
    theta: Vec<f64>,
    d_theta: Vec<f64>,
    /// The photo term's curvature per vertex (`optimizer = "gauss-newton"`; else empty).
    d_curv: Vec<f64>,
    g32: Vec<f32>,
    /// Per active grid level at the last update: RMS of the summed gradient over the nodes it
    /// touched (diagnostics only).
    last_grad_rms: Vec<f64>,
    /// Acceptance batches' pool (`trust_batches` > 0; `trust.rs`).
    trust_pool: Option<TrustPool>,
    /// The field's parameters (grids, residual) before the update awaiting its acceptance test.
    trust_before: Option<(Vec<Vec<f32>>, Vec<f32>)>,
    /// The photo-consistency term (`photo` > 0; `photo_term.rs`).
    photo: Option<PhotoTerm>,
    /// Its sums since the last update (diagnostics only), and per view (with `diag`).
    photo_stats: PhotoStats,
    view_stats: Vec<PhotoStats>,
}

impl Refiner {
    /// The refiner of a run, `None` unless `[model.refine] enabled`.
    pub fn for_run(
        state: &mut TrainState,
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
            patch: state.cfg.train.patch,
            patched: state.cfg.train.patched_pixels(),
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
            traced: params.traced.iter().map(|&t| t as f64).collect(),
            theta: vec![0.0; nv],
            d_theta: vec![0.0; nv],
            d_curv: match cfg.optimizer {
                RefineOptimizer::GaussNewton => vec![0.0; nv],
                RefineOptimizer::Adam => Vec::new(),
            },
            g32: Vec::new(),
            last_grad_rms: Vec::new(),
            trust_pool: match cfg.trust_batches {
                0 => None,
                _ => Some(TrustPool::new(&prepared.samples, cfg.trust_holdout)?),
            },
            trust_before: None,
            photo: None,
            photo_stats: Default::default(),
            view_stats: Vec::new(),
            diag: Diagnostics::from_env(nv)?,
            cfg,
        };
        if r.cfg.photo > 0.0 {
            let Samples::Stream(stream) = &prepared.samples else {
                anyhow::bail!("model.refine: the photo-consistency term needs streamed samples");
            };
            let term = PhotoTerm::new(
                stream,
                &prepared.tracer,
                norm.center,
                &r.cfg,
                &prepared.train_names(),
                (r.start_step(), r.stop_step()),
            )?;
            if let Some(d) = &r.diag {
                let pairs: Vec<serde_json::Value> = term
                    .views
                    .iter()
                    .map(|v| {
                        serde_json::json!([
                            v.row,
                            v.neighbours
                                .iter()
                                .map(|&j| term.views[j].row)
                                .collect::<Vec<_>>()
                        ])
                    })
                    .collect();
                d.line(serde_json::json!({ "photo_pairs": pairs }))?;
            }
            r.photo = Some(term);
        }
        if r.needs_rebuild(state.step) {
            // Stopped right after an update, before its rebuild (the loop rebuilds only when it
            // draws a next batch): the offsets and BVH become those of the current parameters,
            // as the uninterrupted run made them.
            let p = state.ckpt.refine.as_mut().expect("refine params");
            field::sync_offsets(p, &r.cfg, &r.geom);
            p.traced = p.offsets.clone();
            r.traced = p.traced.iter().map(|&t| t as f64).collect();
        }
        if r.traced.iter().any(|&t| t != 0.0) {
            let t = Arc::new(r.build_tracer(&r.traced)?);
            // A resumed run: the neighbours of the mesh it was stopped on.
            if let Some(photo) = r.photo.as_mut().filter(|_| r.cfg.photo_rechoose) {
                photo.choose(&t);
            }
            r.tracer = Some(t);
        }
        Ok(Some(r))
    }

    /// First step at which the mesh moves.
    pub fn start_step(&self) -> u64 {
        (self.cfg.start * self.steps as f64).floor() as u64
    }

    /// First step at which the mesh is fixed again.
    pub fn stop_step(&self) -> u64 {
        ((self.cfg.stop * self.steps as f64).floor() as u64).max(self.start_step())
    }

    /// Whether the mesh moves at step k.
    pub fn moving(&self, k: u64) -> bool {
        (self.start_step()..self.stop_step()).contains(&k)
    }

    /// Whether the offsets take an Adam step at the end of step k.
    fn updates_after(&self, k: u64) -> bool {
        self.moving(k)
            && ((k + 1 - self.start_step()) % self.cfg.update_every as u64 == 0
                || k + 1 == self.stop_step())
    }

    /// The field levels active at step k.
    pub fn active(&self, k: u64) -> Active {
        let k0 = self.start_step();
        if !self.moving(k) {
            return Active {
                grids: 0,
                residual: false,
            };
        }
        let n = self.cfg.n_levels() as u64;
        let span = self.cfg.coarse_to_fine * self.steps as f64;
        let on = (0..n)
            .filter(|&j| k >= k0 + (j as f64 * span / n as f64).floor() as u64)
            .count();
        Active {
            grids: on.min(self.cfg.levels as usize),
            residual: on > self.cfg.levels as usize,
        }
    }

    /// `Grads::position_max_scale` at step k (`gradient_cells`, geometric from the first moving
    /// step to the last).
    pub fn gradient_scale(&self, k: u64) -> Option<f32> {
        let [g0, g1] = self.cfg.gradient_cells;
        if g0 <= 0.0 {
            return None;
        }
        Some(self.geometric(g0, g1, k, self.steps) as f32)
    }

    /// Adam's rate for the update after step k: `lr`, or geometric from `lr` at the first moving
    /// step to `lr_end` at the last (`lr_end` = 0: constant).
    fn lr_at(&self, k: u64) -> f32 {
        let (lr, end) = (self.cfg.lr as f64, self.cfg.lr_end as f64);
        if end <= 0.0 || lr <= 0.0 {
            return self.cfg.lr;
        }
        self.geometric(lr, end, k, self.stop_step()) as f32
    }

    /// Geometric from `from` at the first moving step to `to` at step `end − 1` (and after), by
    /// step k (`gradient_scale`, `lr_at`).
    fn geometric(&self, from: f64, to: f64, k: u64, end: u64) -> f64 {
        let k0 = self.start_step();
        let span = end.saturating_sub(k0 + 1).max(1) as f64;
        let f = (k.saturating_sub(k0) as f64 / span).min(1.0);
        from * (to / from).powf(f)
    }

    /// Whether the BVH is rebuilt before batch k is drawn (the offsets moved after step k − 1).
    fn needs_rebuild(&self, k: u64) -> bool {
        k > 0 && self.updates_after(k - 1)
    }

    fn build_tracer(&self, theta: &[f64]) -> Result<Tracer> {
        let mesh = self.geom.mesh_with(theta);
        ensure!(
            mesh.vertices.iter().all(|v| v.is_finite()),
            "model.refine: a refined vertex is not finite"
        );
        // In the local frame of the model's normalisation (SPEC §4.1), like the training mesh's.
        let t = Tracer::new(&mesh, &self.geom.norm)
            .context("rebuilding the BVH of the refined mesh")?;
        if !self.cfg.anchored {
            return Ok(t);
        }
        // Hits reported on the training mesh (`[model.refine] anchored`).
        t.anchored(&self.geom.mesh_with(&vec![0.0; self.geom.n_vertices()]))
    }

    /// Rebuild the BVH from the current offsets (and sync `offsets`, `traced`).
    fn rebuild(&mut self, state: &mut TrainState) -> Result<()> {
        self.install(state, None)
    }

    /// The BVH of the mesh at the current parameters' offsets, rounded to f32 as `refine.traced`
    /// stores them (what [`Refiner::install`] would build from them).
    fn candidate(&self, state: &TrainState) -> Result<Tracer> {
        let p = state.ckpt.refine.as_ref().expect("refine params");
        let theta: Vec<f64> = field::theta_all(p, &self.cfg, &self.geom)
            .into_iter()
            .map(|t| t as f32 as f64)
            .collect();
        self.build_tracer(&theta)
    }

    /// Make the current offsets the traced ones with their BVH (`built`: already built by the
    /// acceptance test from the current parameters; else built here).
    fn install(&mut self, state: &mut TrainState, built: Option<Tracer>) -> Result<()> {
        let p = state.ckpt.refine.as_mut().expect("refine params");
        let theta = field::theta_all(p, &self.cfg, &self.geom);
        if let Some(d) = &self.diag {
            d.record(
                state.step,
                &self.geom,
                &theta,
                &p.traced,
                &self.last_grad_rms,
                self.photo.as_ref().map(|_| self.photo_stats),
            )?;
        }
        if let (Some(d), Some(photo)) = (&self.diag, &self.photo) {
            d.views(state.step, &self.geom, &theta, photo, &self.view_stats)?;
        }
        self.photo_stats = Default::default();
        self.view_stats.clear();
        p.offsets = theta.iter().map(|&t| t as f32).collect();
        p.traced = p.offsets.clone();
        self.traced = p.traced.iter().map(|&t| t as f64).collect();
        let t = match built {
            Some(t) => t,
            None => self.build_tracer(&self.traced)?,
        };
        if let Some(photo) = self.photo.as_mut().filter(|_| self.cfg.photo_rechoose) {
            photo.choose(&t);
        }
        self.tracer = Some(Arc::new(t));
        Ok(())
    }

    /// The acceptance test of the update just made (`trust_batches` > 0; module docs of
    /// `trust.rs`): `Ok(Some(bvh))` if the proposed step, or one of its halvings, lowers the
    /// acceptance MSE (the parameters are left at the accepted point), `Ok(None)` if none does
    /// (the parameters are restored and the mesh does not move). `k` = the step just done.
    fn trust(
        &mut self,
        state: &mut TrainState,
        prepared: &Prepared,
        k: u64,
    ) -> Result<Option<Tracer>> {
        let (g0, v0) = self
            .trust_before
            .take()
            .expect("an update awaiting its test");
        let pool = self.trust_pool.as_ref().expect("trust pool");
        let (g1, v1) = {
            let p = state.ckpt.refine.as_ref().expect("refine params");
            (p.grids.clone(), p.vertex.clone())
        };
        let sets: Vec<Vec<usize>> = (0..self.cfg.trust_batches as u64)
            .map(|j| pool.pixels(self.seed, k, j, self.batch_pixels))
            .collect();
        let errors = |tracer: &Tracer, state: &TrainState| -> Result<Vec<Vec<Option<f64>>>> {
            sets.iter()
                .map(|px| {
                    trust::row_errors(
                        &state.ckpt.model,
                        &state.ckpt.params,
                        prepared.samples.batch(tracer, px),
                    )
                })
                .collect()
        };
        let before = errors(self.tracer.as_deref().unwrap_or(&prepared.tracer), state)?;
        let mut tried = Vec::new();
        for h in 0..=self.cfg.trust_halvings {
            let p = state.ckpt.refine.as_mut().expect("refine params");
            // The step scaled by 2^−h (h = 0: the proposed parameters themselves).
            let f = 0.5f64.powi(h as i32);
            let scale = |a: &[f32], b: &[f32]| -> Vec<f32> {
                if h == 0 {
                    return b.to_vec();
                }
                a.iter()
                    .zip(b)
                    .map(|(&a, &b)| (a as f64 + f * (b as f64 - a as f64)) as f32)
                    .collect()
            };
            p.grids = g0.iter().zip(&g1).map(|(a, b)| scale(a, b)).collect();
            p.vertex = scale(&v0, &v1);
            let tracer = self.candidate(state)?;
            let after = errors(&tracer, state)?;
            let (mb, ma) = trust::paired_mse(&before, &after);
            tried.push((f, mb, ma));
            if ma < mb * (1.0 - self.cfg.trust_margin) {
                self.log_trust(k, &tried, true)?;
                return Ok(Some(tracer));
            }
        }
        self.log_trust(k, &tried, false)?;
        let p = state.ckpt.refine.as_mut().expect("refine params");
        p.grids = g0;
        p.vertex = v0;
        p.offsets = p.traced.clone();
        Ok(None)
    }

    fn log_trust(&self, k: u64, tried: &[(f64, f64, f64)], accepted: bool) -> Result<()> {
        match &self.diag {
            Some(d) => d.line(serde_json::json!({"step": k + 1, "trust": {
                "accepted": accepted,
                "tried": tried.iter().map(|(f, b, a)| serde_json::json!({"scale": f, "mse_before": b, "mse_after": a})).collect::<Vec<_>>(),
            }})),
            None => Ok(()),
        }
    }

    /// After step k: the acceptance test of an update made at it (if any), then the BVH rebuild
    /// (accepted) or nothing (rejected: the mesh stays).
    fn after_update(&mut self, state: &mut TrainState, prepared: &Prepared, k: u64) -> Result<()> {
        if self.trust_before.is_none() {
            return self.rebuild(state);
        }
        match self.trust(state, prepared, k)? {
            Some(t) => self.install(state, Some(t)),
            None => Ok(()),
        }
    }

    /// Batch k: cast against the current BVH, with triangle ids.
    pub fn draw(&self, prepared: &Prepared, k: u64) -> Batch {
        draw_with(
            &prepared.samples,
            self.tracer.as_deref().unwrap_or(&prepared.tracer),
            self.seed,
            k,
            self.batch_pixels,
            (self.patch, self.patched),
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
                let (seed, n, patch, patched) =
                    (self.seed, self.batch_pixels, self.patch, self.patched);
                let (st, nb) = rayon::join(
                    || self.step(state, prepared, batch, grads),
                    || {
                        draw_with(
                            &prepared.samples,
                            tracer.as_deref().unwrap_or(&prepared.tracer),
                            seed,
                            k1,
                            n,
                            (patch, patched),
                        )
                    },
                );
                (st, Some(nb))
            }
            Some(k1) => {
                let st = self.step(state, prepared, batch, grads);
                if st.is_err() {
                    return (st, None);
                }
                if let Err(e) = self.after_update(state, prepared, k1 - 1) {
                    return (Err(e), None);
                }
                let nb = self.draw(prepared, k1);
                (st, Some(nb))
            }
            None => {
                let k = state.step;
                let st = self.step(state, prepared, batch, grads);
                if st.is_ok() && self.trust_before.is_some() {
                    // The run's last step made an update (stop = 1): test it; the offsets
                    // eval/render apply follow.
                    let tested = self.trust(state, prepared, k).map(|_| {
                        let p = state.ckpt.refine.as_mut().expect("refine params");
                        field::sync_offsets(p, &self.cfg, &self.geom);
                    });
                    if let Err(e) = tested {
                        return (Err(e), None);
                    }
                }
                (st, None)
            }
        }
    }

    /// One optimisation step (module docs); `grads` zero on entry and exit, as `TrainState::step`.
    pub fn step(
        &mut self,
        state: &mut TrainState,
        prepared: &Prepared,
        batch: &mut Batch,
        grads: &mut Grads<f32>,
    ) -> Result<StepStats> {
        let k = state.step;
        let active = self.active(k);
        let moving = self.moving(k);
        let t0 = Instant::now();
        // Cast against a moved mesh, a pixel of the training mesh's hit map may see nothing.
        if self.tracer.is_some() {
            batch.drop_empty_pixels();
        }
        let mut hits = if moving {
            self.reintersect(state, batch)?
        } else {
            Vec::new()
        };
        let holdout = self.cfg.trust_holdout;
        if holdout > 0 {
            // The validation views give no offset gradient (`trust.rs`).
            let s = batch.samples_per_pixel();
            hits.retain(|h| !trust::is_validation_row(batch.view[h.sample / s], holdout));
        }
        // The loss's gradient through the hit point is needed only if it moves the mesh.
        grads.inputs = moving && self.cfg.features > 0.0;
        grads.position_max_scale = self.gradient_scale(k);
        let model = &state.ckpt.model;
        let fwd = model.forward(&state.ckpt.params, batch)?;
        let t1 = Instant::now();
        model.backward(&state.ckpt.params, batch, &fwd, grads);
        let t2 = Instant::now();
        let mse = batch_mse(&fwd, batch);
        if moving {
            self.accumulate(state, prepared, &hits, &grads.positions, active);
            if self.updates_after(k) {
                self.update(state, active, k);
            }
        }
        grads.inputs = false;
        grads.position_max_scale = None;
        state.apply_adam(grads);
        let st = state.finish_step(grads, fwd.loss, mse, fwd.points.len(), [t0, t1, t2]);
        // `offsets` up to date whenever the loop may save, evaluate or stop after this step.
        let done = state.step;
        let due = |every: u64| every > 0 && done % every == 0;
        if done > self.start_step()
            && (done >= self.steps
                || due(self.checkpoint_every)
                || due(self.eval_every)
                || !st.loss.is_finite()
                || self.interrupt.is_some_and(|f| f.load(Ordering::SeqCst)))
        {
            let p = state.ckpt.refine.as_mut().expect("refine params");
            field::sync_offsets(p, &self.cfg, &self.geom);
        }
        Ok(st)
    }

    /// Re-intersect `batch` with the current mesh (module docs).
    fn reintersect(&mut self, state: &TrainState, batch: &mut Batch) -> Result<Vec<RayHit>> {
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
        field::theta_of(params, &self.cfg, geom, &used, &mut self.theta);
        let (origins, views) = (&self.origins, batch.view.clone());
        let origin = move |p: usize| origins[views[p] as usize];
        if self.cfg.anchored {
            // The rays were cast against the mesh at the `traced` offsets.
            return Ok(reintersect_batch_anchored(
                geom,
                &self.theta,
                &self.traced,
                batch,
                &origin,
                self.cfg.min_cos,
            ));
        }
        Ok(reintersect_batch(
            geom,
            &self.theta,
            batch,
            &origin,
            self.cfg.min_cos,
        ))
    }

    /// `∂L/∂θ` of a batch (times `features`), then the photo term's (`photo` > 0), into the
    /// pending sums of the active levels (module docs).
    fn accumulate(
        &mut self,
        state: &mut TrainState,
        prepared: &Prepared,
        hits: &[RayHit],
        d_positions: &[f32],
        active: Active,
    ) {
        let geom = &*self.geom;
        let w = self.cfg.features;
        let mut touched: Vec<u32> = Vec::new();
        if w > 0.0 {
            if self.cfg.anchored {
                hits_backward_anchored(geom, hits, d_positions, &mut self.d_theta);
            } else {
                hits_backward(geom, hits, d_positions, &mut self.d_theta);
            }
            touched.extend(hits.iter().flat_map(|h| h.tri));
            touched.sort_unstable();
            touched.dedup();
            if w != 1.0 {
                for &i in &touched {
                    self.d_theta[i as usize] *= w;
                }
            }
        }
        if let Some(photo) = &self.photo {
            let Samples::Stream(stream) = &prepared.samples else {
                unreachable!("checked when the refiner was built");
            };
            let k = state.step;
            let tracer = self.tracer.as_deref().unwrap_or(&prepared.tracer);
            let patches = photo.draw(stream, tracer, self.seed, k);
            let used = photo_term::patch_vertices(geom, &patches);
            let params = state.ckpt.refine.as_ref().expect("refine params");
            field::theta_of(params, &self.cfg, geom, &used, &mut self.theta);
            let evals = photo.evaluate(geom, &self.theta, &patches);
            let curv = (!self.d_curv.is_empty()).then_some(&mut self.d_curv[..]);
            let st = photo_term::accumulate(&evals, &mut self.d_theta, curv);
            self.photo_stats.add(&st);
            if let Some(d) = self.diag.as_mut() {
                self.view_stats
                    .resize(photo.views.len(), PhotoStats::default());
                for (p, e) in patches.iter().zip(&evals) {
                    if let Some(p) = p {
                        let s = &mut self.view_stats[p.view];
                        s.drawn += 1;
                        if let Some(e) = e {
                            s.valid += 1;
                            s.energy += e.energy;
                        }
                    }
                }
                d.seen.resize(geom.n_vertices(), false);
                for &i in &used {
                    d.seen[i as usize] = true;
                }
            }
            touched.extend(used);
            touched.sort_unstable();
            touched.dedup();
        }
        let params = state.ckpt.refine.as_mut().expect("refine params");
        let ng = params.grids.len();
        let gather = |d: &mut [f64], pending: &mut [Vec<f64>]| {
            gather_and_clear(&self.cfg, geom, &touched, d, active, ng, pending)
        };
        gather(&mut self.d_theta, &mut params.pending);
        if !self.d_curv.is_empty() {
            gather(&mut self.d_curv, &mut params.pending_h);
        }
    }

    /// One Adam step of the active levels on the pending sums (plus the smoothness gradient for
    /// every step summed), which are then cleared; the BVH is rebuilt before the next batch.
    fn update(&mut self, state: &mut TrainState, active: Active, k: u64) {
        let Active {
            grids: levels,
            residual,
        } = active;
        let k0 = self.start_step();
        let every = self.cfg.update_every as u64;
        let summed = (k - k0) % every + 1;
        self.adam.lr = self.lr_at(k);
        let TrainState { ckpt, adam, .. } = state;
        let params = ckpt.refine.as_mut().expect("refine params");
        let ng = params.grids.len();
        if self.cfg.trust_batches > 0 {
            self.trust_before = Some((params.grids.clone(), params.vertex.clone()));
        }
        if self.cfg.prior > 0.0 {
            // ∂/∂G of prior·Σ G² for every step summed (active levels only).
            let w = 2.0 * self.cfg.prior * summed as f64;
            for l in 0..levels.min(ng) {
                for (g, &x) in params.pending[l].iter_mut().zip(&params.grids[l]) {
                    *g += w * x as f64;
                }
            }
            if residual && !params.vertex.is_empty() {
                for (g, &x) in params.pending[ng].iter_mut().zip(&params.vertex) {
                    *g += w * x as f64;
                }
            }
        }
        if residual && !params.vertex.is_empty() {
            let mut d = vec![0.0f64; params.vertex.len()];
            smoothness(&self.cfg, &self.geom, &params.vertex, &mut d);
            for (p, g) in params.pending[ng].iter_mut().zip(&d) {
                *p += summed as f64 * g;
            }
        }
        self.last_grad_rms.clear();
        if self.cfg.optimizer == RefineOptimizer::GaussNewton {
            let n = (levels + residual as usize) as f64;
            let lr = self.adam.lr as f64;
            // The grids, then the per-vertex residual when there is one; each steps when active.
            let targets = params
                .grids
                .iter_mut()
                .chain((!params.vertex.is_empty()).then_some(&mut params.vertex));
            for (l, w) in targets.enumerate() {
                if (l < ng && l < levels) || (l == ng && residual) {
                    gauss_newton_step(
                        w,
                        &params.pending[l],
                        &params.pending_h[l],
                        lr,
                        n,
                        self.cfg.damping,
                    );
                }
                params.pending[l].fill(0.0);
                params.pending_h[l].fill(0.0);
            }
            return;
        }
        for l in 0..ng {
            if l < levels {
                if self.diag.is_some() {
                    let (s2, n) = params.pending[l]
                        .iter()
                        .filter(|g| **g != 0.0)
                        .fold((0.0, 0usize), |(s, n), g| (s + g * g, n + 1));
                    self.last_grad_rms.push((s2 / n.max(1) as f64).sqrt());
                }
                let r = adam
                    .range(&grid_name(l))
                    .expect("adam slot of a refine grid");
                self.g32.clear();
                self.g32.extend(params.pending[l].iter().map(|&g| g as f32));
                adam.step_dense(r, &mut params.grids[l], &self.g32, &self.adam, k);
            }
            params.pending[l].fill(0.0);
        }
        if !params.vertex.is_empty() {
            if residual {
                let r = adam.range(VERTEX_NAME).expect("adam slot of refine.vertex");
                self.g32.clear();
                self.g32
                    .extend(params.pending[ng].iter().map(|&g| g as f32));
                adam.step_dense(r, &mut params.vertex, &self.g32, &self.adam, k);
            }
            params.pending[ng].fill(0.0);
        }
    }
}

/// One Gauss–Newton step of a field level (`optimizer = "gauss-newton"`, SPEC §4.11):
/// `x_i −= lr · g_i / (n · h_i + λ)` with `λ = damping · mean(h_i > 0)`, in index order; entries
/// with `g_i = 0` are not touched, and a level with no curvature at all does not move.
fn gauss_newton_step(x: &mut [f32], g: &[f64], h: &[f64], lr: f64, n: f64, damping: f64) {
    let (sum, count) = h
        .iter()
        .filter(|&&v| v > 0.0)
        .fold((0.0f64, 0usize), |(s, c), &v| (s + v, c + 1));
    if count == 0 {
        return;
    }
    let lambda = damping * sum / count as f64;
    for ((x, &g), &h) in x.iter_mut().zip(g).zip(h) {
        let den = n * h + lambda;
        if g == 0.0 || den <= 0.0 {
            continue;
        }
        *x = (*x as f64 - lr * g / den) as f32;
    }
}

/// Batch k cast against `tracer` (pixels none of whose rays hit are dropped at use; a patch
/// batch that loses a pixel so becomes independent pixels, `Batch::drop_empty_pixels`).
fn draw_with(
    samples: &Samples,
    tracer: &Tracer,
    seed: u64,
    k: u64,
    n: usize,
    (patch, patched): (u32, usize),
) -> Batch {
    draw_batch(samples, tracer, seed, k, n, patch, patched)
}

/// Gather the per-vertex sums `d` of the `touched` vertices onto the offset field's pending sums
/// (`pending`: the `ng` grids, then the per-vertex residual when there is one) and clear them.
fn gather_and_clear(
    cfg: &RefineConfig,
    geom: &RefineGeom,
    touched: &[u32],
    d: &mut [f64],
    active: Active,
    ng: usize,
    pending: &mut [Vec<f64>],
) {
    let (grids, rest) = pending.split_at_mut(ng);
    let d_r: &mut [f64] = match rest.first_mut() {
        Some(v) => v,
        None => &mut [],
    };
    field_backward(cfg, geom, touched, d, active, grids, d_r);
    for &i in touched {
        d[i as usize] = 0.0;
    }
}
