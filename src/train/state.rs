//! The state of a training run at a step and one optimisation step on it (SPEC §1, §4.8):
//! configuration, model, parameters and Adam state; forward → explicit backward → Adam. The
//! loop that drives it (batches, progress, checkpoints, resume) is `run/`; the f64 step is
//! `precision.rs`, the mesh refinement's step `refine/`.

use crate::io::atomic::rename_durable;
use crate::io::tensors::TensorFile;
use crate::model::batch::Batch;
use crate::model::checkpoint::{Checkpoint, FORMAT, OPTIMIZER_KEY};
use crate::model::params::{Grads, Group};
use crate::train::adam::AdamState;
use crate::train::config::{RunConfig, TableSize};
use crate::train::setup::Prepared;
use anyhow::{bail, ensure, Context, Result};
use std::path::{Path, PathBuf};
use std::time::Instant;

/// The optimizer state file of a model file: `checkpoint*.safetensors` →
/// `optimizer*.safetensors` in the same folder (`RUN/optimizer.safetensors`,
/// `RUN/optimizer-diverged.safetensors`), any other name `<stem>.optimizer.safetensors`.
pub fn optimizer_path(model: &Path) -> PathBuf {
    let name = model
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_default();
    let opt = match name.strip_prefix("checkpoint") {
        Some(rest) => format!("optimizer{rest}"),
        None => {
            let stem = name.strip_suffix(".safetensors").unwrap_or(&name);
            format!("{stem}.optimizer.safetensors")
        }
    };
    model.with_file_name(opt)
}

/// Where [`TrainState::save`] writes the optimizer state before the model is committed:
/// `optimizer.next.safetensors` beside `optimizer.safetensors`.
pub fn optimizer_next_path(model: &Path) -> PathBuf {
    let p = optimizer_path(model);
    let name = p.file_name().unwrap().to_string_lossy().into_owned();
    let stem = name.strip_suffix(".safetensors").unwrap_or(&name);
    p.with_file_name(format!("{stem}.next.safetensors"))
}

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

    /// The run's two files (SPEC §6.2): the model (`RUN/checkpoint.safetensors`: what render,
    /// eval, dump and compare read; with `step` and `run_config`) and the optimizer state
    /// (`RUN/optimizer.safetensors`: Adam's `adam.*`, read only to resume), paired by the step
    /// and the model's [`Checkpoint::params_digest`]. Tables sized from the scene
    /// (`train.table_size = "auto"`) leave out what no training ray reached: the Adam state of
    /// those rows, and a table's rows in the model file where fewer than half of them stepped
    /// ([`Checkpoint::to_tensor_file_stepped`]); fixed tables (the `paper` and `tiny` presets)
    /// write every row, as before.
    pub fn to_tensor_files(&self) -> Result<(TensorFile, TensorFile)> {
        let auto = self.cfg.train.table_size == TableSize::Auto;
        // Every slot's stepped rows, found once for both files.
        let stepped = if auto {
            self.adam.stepped_rows()
        } else {
            Vec::new()
        };
        let mut model = if auto {
            self.ckpt
                .to_tensor_file_stepped(self.cfg.train.seed, &|name| {
                    stepped
                        .iter()
                        .find(|(n, _)| *n == name)
                        .map(|(_, rows)| rows.clone())
                        .with_context(|| format!("Adam state has no parameter {name}"))
                })?
        } else {
            self.ckpt.to_tensor_file()?
        };
        model.set_meta("step", self.step.to_string());
        model.set_meta("run_config", self.cfg.to_toml());
        let mut opt = TensorFile::new();
        if auto {
            self.adam.save_compact_with(&mut opt, &stepped)?;
        } else {
            self.adam.save(&mut opt)?;
        }
        opt.set_meta("format", FORMAT);
        opt.set_meta("step", self.step.to_string());
        opt.set_meta(OPTIMIZER_KEY, self.ckpt.params_digest());
        Ok((model, opt))
    }

    /// A run from a checkpoint holding its Adam state too (`adam.*` in the model file: the
    /// layout before the optimizer state had its own file, still read to resume such runs).
    pub fn from_tensor_file(f: &TensorFile) -> Result<TrainState> {
        let label = f.label();
        ensure!(
            f.tensors.keys().any(|k| k.starts_with("adam.")),
            "{label}: holds no optimizer state (adam.*): a run's Adam state is in its own file beside it (optimizer.safetensors); resume reads the pair (TrainState::load)"
        );
        Self::from_tensor_files(f, f)
    }

    /// A run from its model file and the file holding its Adam state (the same file for the
    /// older single-file layout). Errors name the files and what was expected.
    pub fn from_tensor_files(model: &TensorFile, opt: &TensorFile) -> Result<TrainState> {
        let label = model.label();
        let ckpt = Checkpoint::from_tensor_file(model)?;
        let cfg = RunConfig::from_stored_toml(model.meta("run_config")?, &label)
            .with_context(|| format!("{label}: header metadata \"run_config\""))?;
        let step: u64 = model
            .meta("step")?
            .parse()
            .with_context(|| format!("{label}: \"step\""))?;
        if !std::ptr::eq(model, opt) {
            let opt_label = opt.label();
            let opt_step = opt.meta("step")?;
            let digest = opt.meta(OPTIMIZER_KEY).with_context(|| {
                format!("{opt_label}: not an optimizer state file (no \"{OPTIMIZER_KEY}\")")
            })?;
            let own = ckpt.params_digest();
            ensure!(
                opt_step == step.to_string() && digest == own,
                "{opt_label} is not the optimizer state of {label}: it was saved at step {opt_step} with a model of digest {digest}, the model is at step {step} with digest {own}. \
                 The two are written together: copy both files of one run and step"
            );
        }
        let adam = AdamState::load(opt, &param_specs(&ckpt))?;
        Ok(TrainState {
            cfg,
            ckpt,
            adam,
            step,
        })
    }

    /// Write the pair atomically: the optimizer state to its `.next` file, then the model over
    /// `path` (the commit: a crash before it leaves the previous pair, after it the new model
    /// with the new state in `.next`, which [`TrainState::load`] takes), then the `.next` file
    /// renamed over the optimizer file. Each write is whole or absent and fsynced
    /// (`io/atomic.rs`).
    pub fn save(&self, path: &Path) -> Result<()> {
        let (model, opt) = self.to_tensor_files()?;
        let (opt_path, next) = (optimizer_path(path), optimizer_next_path(path));
        opt.write_atomic(&next)?;
        model.write_atomic(path)?;
        rename_durable(&next, &opt_path)
    }

    /// The run saved at `path` ([`TrainState::save`]): the model file and its optimizer state
    /// (`optimizer_path`; its `.next` file if the save was cut between the two renames), or a
    /// model file of the older layout holding the Adam state itself.
    pub fn load(path: &Path) -> Result<TrainState> {
        let model = TensorFile::read(path)?;
        if model.tensors.keys().any(|k| k.starts_with("adam.")) {
            return TrainState::from_tensor_file(&model);
        }
        let (opt_path, next) = (optimizer_path(path), optimizer_next_path(path));
        if !opt_path.is_file() && !next.is_file() {
            bail!(
                "{}: resuming needs the run's optimizer state {}, which is missing (the model file alone renders and scores, but cannot continue training)",
                path.display(),
                opt_path.display()
            );
        }
        let first = if opt_path.is_file() {
            TensorFile::read(&opt_path).and_then(|opt| TrainState::from_tensor_files(&model, &opt))
        } else {
            Err(anyhow::anyhow!("{} is missing", opt_path.display()))
        };
        match first {
            Ok(st) => Ok(st),
            // A save cut between the model's rename and the optimizer's: the new state is
            // in `.next`.
            Err(e) if next.is_file() => {
                let st = TrainState::from_tensor_files(&model, &TensorFile::read(&next)?)
                    .map_err(|e2| e.context(format!("nor is {}: {e2:#}", next.display())))?;
                rename_durable(&next, &opt_path)?;
                Ok(st)
            }
            Err(e) => Err(e),
        }
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
