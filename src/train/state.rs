//! The state of a training run at a step and one optimisation step on it (SPEC §1, §4.8):
//! configuration, model, parameters and Adam state; forward → explicit backward → Adam. The
//! loop that drives it (batches, progress, checkpoints, resume) is `run/`; the f64 step is
//! `precision.rs`, the mesh refinement's step `refine/`.

use crate::io::tensors::TensorFile;
use crate::model::batch::Batch;
use crate::model::checkpoint::Checkpoint;
use crate::model::params::{Grads, Group};
use crate::train::adam::AdamState;
use crate::train::config::{RunConfig, TableSize};
use crate::train::setup::Prepared;
use anyhow::{Context, Result};
use std::path::Path;
use std::time::Instant;

/// Everything that defines a run at a step: configuration, model, parameters, Adam state.
pub struct TrainState {
    pub cfg: RunConfig,
    pub ckpt: Checkpoint,
    pub adam: AdamState,
    /// Steps completed.
    pub step: u64,
}

/// What one step measured.
#[derive(Clone, Copy, Debug)]
pub struct StepStats {
    pub loss: f64,
    /// Mean squared error of the batch's RGB (for a running PSNR).
    pub mse: f64,
    /// Valid sub-samples evaluated.
    pub samples: usize,
    /// Wall seconds of the step's phases.
    pub timing: StepTiming,
}

/// Wall seconds of one step's phases (forward, backward, Adam, gradient zeroing).
#[derive(Clone, Copy, Debug, Default)]
pub struct StepTiming {
    pub forward: f64,
    pub backward: f64,
    pub adam: f64,
    pub zero: f64,
}

/// Adam's parameters: the model's layout, then the mesh refinement's (`refine/refiner.rs`), if any.
fn param_specs(ckpt: &Checkpoint) -> Vec<(String, Vec<usize>)> {
    let mut v = ckpt.model.layout.name_shapes();
    if let Some(r) = &ckpt.refine {
        v.extend(r.specs());
    }
    v
}

impl TrainState {
    /// A new run of `cfg` on a prepared scene: the model [`Prepared::init_model`] makes (grid
    /// H's level range resolved for the scene, its messages to `log`, checked against the memory
    /// budget) and fresh Adam state. The configuration it holds is the resolved one.
    pub fn init(
        cfg: RunConfig,
        prepared: &Prepared,
        log: &mut dyn FnMut(String),
    ) -> Result<TrainState> {
        let (cfg, ckpt) = prepared.init_model(cfg, log)?;
        let adam = AdamState::new(&param_specs(&ckpt));
        Ok(TrainState {
            cfg,
            ckpt,
            adam,
            step: 0,
        })
    }

    pub fn to_tensor_file(&self) -> Result<TensorFile> {
        let mut f = self.ckpt.to_tensor_file()?;
        // Tables sized from the scene also leave out the Adam state of entries no ray reached;
        // fixed tables (the `paper` and `tiny` presets) keep every row, as before.
        if self.cfg.train.table_size == TableSize::Auto {
            self.adam.save_compact(&mut f)?;
        } else {
            self.adam.save(&mut f)?;
        }
        f.set_meta("step", self.step.to_string());
        f.set_meta("run_config", self.cfg.to_toml());
        Ok(f)
    }

    pub fn from_tensor_file(f: &TensorFile) -> Result<TrainState> {
        let label = f
            .source
            .as_ref()
            .map_or("<checkpoint>".into(), |p| p.display().to_string());
        let ckpt = Checkpoint::from_tensor_file(f)?;
        let cfg = RunConfig::from_stored_toml(f.meta("run_config")?, &label)
            .with_context(|| format!("{label}: header metadata \"run_config\""))?;
        let step: u64 = f
            .meta("step")?
            .parse()
            .with_context(|| format!("{label}: \"step\""))?;
        let adam = AdamState::load(f, &param_specs(&ckpt))?;
        Ok(TrainState {
            cfg,
            ckpt,
            adam,
            step,
        })
    }

    pub fn save(&self, path: &Path) -> Result<()> {
        self.to_tensor_file()?.write_atomic(path)
    }

    pub fn load(path: &Path) -> Result<TrainState> {
        TrainState::from_tensor_file(&TensorFile::read(path)?)
    }

    /// One optimisation step on `batch`; `grads` must be zero on entry and is zero on exit.
    pub fn step(&mut self, batch: &Batch, grads: &mut Grads<f32>) -> Result<StepStats> {
        let model = &self.ckpt.model;
        let t0 = Instant::now();
        let fwd = model.forward(&self.ckpt.params, batch)?;
        let t1 = Instant::now();
        model.backward(&self.ckpt.params, batch, &fwd, grads);
        let t2 = Instant::now();
        let mse = batch_mse(&fwd, batch);
        self.apply_adam(grads);
        Ok(self.finish_step(grads, fwd.loss, mse, fwd.points.len(), [t0, t1, t2]))
    }

    /// The end of a step (after Adam): clear the touched lists and input gradients, advance the
    /// step, and report. `t` = the starts of forward, backward and Adam.
    pub(crate) fn finish_step(
        &mut self,
        grads: &mut Grads<f32>,
        loss: f64,
        mse: f64,
        samples: usize,
        t: [Instant; 3],
    ) -> StepStats {
        let t3 = Instant::now();
        for t in [
            &mut grads.touched_h,
            &mut grads.touched_d,
            &mut grads.touched_v,
        ] {
            t.entries.clear();
        }
        grads.positions.fill(0.0);
        grads.dirs.fill(0.0);
        self.step += 1;
        StepStats {
            loss,
            mse,
            samples,
            timing: StepTiming {
                forward: (t[1] - t[0]).as_secs_f64(),
                backward: (t[2] - t[1]).as_secs_f64(),
                adam: (t3 - t[2]).as_secs_f64(),
                zero: t3.elapsed().as_secs_f64(),
            },
        }
    }

    /// Adam on every parameter tensor at the current step (`self.step` is not advanced), zeroing
    /// each gradient as it is read: the grids' touched entries only (the touched lists are left
    /// for the caller to clear), every other tensor densely.
    pub fn apply_adam(&mut self, grads: &mut Grads<f32>) {
        let model = &self.ckpt.model;
        let (fh, fd) = model.grid_features();
        let k = self.step;
        let a = &self.cfg.train.adam;
        let Grads {
            params: gp,
            touched_h,
            touched_d,
            touched_v,
            ..
        } = grads;
        for t in &model.layout.tensors {
            let r = t.range();
            let (p, g) = (&mut self.ckpt.params[r.clone()], &mut gp[r.clone()]);
            match t.group {
                Group::GridH => self.adam.step_sparse_and_zero(
                    p,
                    g,
                    &touched_h.entries,
                    fh,
                    r.start,
                    &a.grid_h,
                    k,
                ),
                Group::GridD => self.adam.step_sparse_and_zero(
                    p,
                    g,
                    &touched_d.entries,
                    fd,
                    r.start,
                    &a.grid_d,
                    k,
                ),
                Group::Vertex => self.adam.step_sparse_and_zero(
                    p,
                    g,
                    &touched_v.entries,
                    t.shape[1],
                    r.start,
                    &a.vertex,
                    k,
                ),
                group => {
                    let cfg = match group {
                        Group::Shader => &a.shader,
                        Group::Deform => &a.deform,
                        _ => &a.appearance,
                    };
                    self.adam.step_dense(r, p, g, cfg, k);
                    g.fill(0.0);
                }
            }
        }
    }
}

/// Mean squared error of a forward pass's RGB against the batch targets (f64 sums).
pub fn batch_mse<R: crate::model::real::Real>(
    fwd: &crate::model::hfm::Forward<R>,
    batch: &Batch,
) -> f64 {
    let (mut se, mut n) = (0.0f64, 0usize);
    for c in &fwd.chunks {
        for (k, p) in c.pixels.clone().enumerate() {
            for ch in 0..3 {
                let d = c.rgb[k * 3 + ch].to_f64() - batch.target[p][ch] as f64;
                se += d * d;
            }
            n += 3;
        }
    }
    se / n.max(1) as f64
}
