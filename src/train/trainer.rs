//! The training loop (SPEC §1): deterministic batches → forward → explicit backward → Adam, with
//! progress, `metrics.jsonl`, periodic held-out evaluation, atomic checkpoints, exact resume and
//! a clean stop on Ctrl-C.
//!
//! Run folder:
//! ```text
//! RUN/config.toml              the resolved run configuration (preset + overrides + dropped levels)
//! RUN/checkpoint.safetensors   latest checkpoint: parameters, Adam state, step (atomic rename)
//! RUN/checkpoint-time.json     the run's training time at that checkpoint (not in it: below)
//! RUN/metrics.jsonl            one JSON object per log line / evaluation
//! RUN/render/NAME.png          final renders of the held-out views
//! RUN/eval/NAME.png            prediction | ground truth | error heat map
//! RUN/eval.json                final per-view and mean scores
//! ```
//! Exact resume: batch k depends only on (seed, k); the checkpoint holds the f32 parameters and
//! the whole Adam state (m, v and per-parameter t); nothing in a checkpoint depends on wall time.
//! So a run stopped at step k and resumed writes the same bytes as one never stopped.

use crate::eval::protocol::{evaluate_view, write_evaluated, ViewScore};
use crate::io::tensors::TensorFile;
use crate::model::batch::Batch;
use crate::model::checkpoint::{init_checkpoint_for_mesh, Checkpoint};
use crate::model::params::{Grads, Group};
use crate::train::adam::AdamState;
use crate::train::config::{differences_but_steps, RunConfig};
use crate::train::divergence::Guard;
use crate::train::memory::Job;
use crate::train::report::Reporter;
use crate::train::run_dir::{
    prepare_run_dir, remove_run, RunLock, SceneFingerprint, SETTINGS_FILE,
};
use crate::train::sampler::sample_batch;
use crate::train::setup::{prepare_until, resolve_levels, Prepared};
use anyhow::{bail, Context, Result};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
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

/// Adam's parameters: the model's layout, then the mesh refinement's (`train/refine.rs`), if any.
fn param_specs(ckpt: &Checkpoint) -> Vec<(String, Vec<usize>)> {
    let mut v = ckpt.model.layout.name_shapes();
    if let Some(r) = &ckpt.refine {
        v.extend(r.specs());
    }
    v
}

impl TrainState {
    /// A fresh run for a prepared scene (`cfg.model` already has its levels resolved).
    pub fn init(cfg: RunConfig, prepared: &Prepared) -> Result<TrainState> {
        prepared.check_model(&cfg)?;
        let norm = prepared.scene.normalization;
        let ckpt = init_checkpoint_for_mesh(
            &cfg.model,
            cfg.train.seed,
            norm,
            prepared.train_views.len(),
            Some(&prepared.scene.mesh),
        )?;
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
        self.adam.save(&mut f)?;
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

/// How a training run is driven (not part of its result).
#[derive(Default)]
pub struct TrainOptions {
    /// Continue from `RUN/checkpoint.safetensors`: the stored configuration is used, except
    /// `train.steps`, taken from the `cfg` passed in (the total; not below the stored step).
    pub resume: bool,
    /// Replace the run a non-empty folder holds (its files only; see `run_dir.rs`). Without it
    /// (and without `resume`) such a folder is refused.
    pub overwrite: bool,
    /// Stop (with a checkpoint) once this many steps are done, as if interrupted.
    pub stop_at: Option<u64>,
    /// Set by a Ctrl-C handler: stop with a checkpoint at the next step.
    pub interrupt: Option<&'static AtomicBool>,
    /// Skip the final renders and evaluation.
    pub no_final_eval: bool,
    /// Print nothing but errors.
    pub quiet: bool,
    /// With `quiet`: still show the progress bar on a terminal (a tool training its runs).
    pub bar: bool,
    /// A tool's settings for a fresh run (`ablate`, `bench-geometry`: the configuration it asked
    /// for), written to `RUN/variant.toml` once the folder is prepared, so the tool can tell its
    /// own stopped run later (`run_dir::stopped_run_of`).
    pub settings: Option<String>,
}

impl TrainOptions {
    /// Whether the interrupt flag is raised.
    pub fn stopped(&self) -> bool {
        self.interrupt.is_some_and(|f| f.load(Ordering::SeqCst))
    }
}

/// How a run ended.
pub struct TrainSummary {
    pub steps: u64,
    pub interrupted: bool,
    /// Whether the run's checkpoint holds its work (false only when it was stopped before
    /// training began: nothing was saved, the folder holds what it held).
    pub saved: bool,
    /// The mean over the held-out views (`None` without a final evaluation).
    pub final_scores: Option<ViewScore>,
    /// Each held-out view's scores, as in `eval.json` (empty without a final evaluation).
    pub views: Vec<ViewScore>,
    pub seconds: f64,
}

impl TrainSummary {
    /// A run stopped by an interrupt at `steps`, without a final evaluation.
    fn stopped(steps: u64, seconds: f64) -> TrainSummary {
        TrainSummary {
            steps,
            interrupted: true,
            saved: true,
            final_scores: None,
            views: Vec::new(),
            seconds,
        }
    }
}

/// Keep only the metrics lines of steps ≤ `step` (resume rewrites history from there on), without
/// the closing lines of a run that finished at `step` (its final evaluation and peak memory): the
/// resume writes its own, so a resumed finished run has one of each, and no `elapsed_s` of an
/// evaluation before the time it continues from.
fn truncate_metrics(path: &Path, step: u64) -> Result<()> {
    let Ok(text) = std::fs::read_to_string(path) else {
        return Ok(());
    };
    let kept: String = text
        .lines()
        .filter(|l| {
            let Ok(v) = serde_json::from_str::<serde_json::Value>(l) else {
                return false;
            };
            let closing = v.get("final").is_some() || v.get("peak_rss_bytes").is_some();
            v.get("step")
                .and_then(|s| s.as_u64())
                .is_some_and(|s| s < step || (s == step && !closing))
        })
        .map(|l| format!("{l}\n"))
        .collect();
    // Whole or not at all: a kill during the rewrite must not cost the run its history.
    crate::io::atomic::write_bytes(path, kept)
}

/// Render and score held-out views (`max` = 0: all). Writes renders and side-by-sides under
/// `out` if given.
pub fn evaluate(
    state: &TrainState,
    prepared: &Prepared,
    max: usize,
    out: Option<&Path>,
) -> Result<Vec<ViewScore>> {
    Ok(evaluate_until(state, prepared, max, out, &|| false)?.expect("never stopped"))
}

/// [`evaluate`], giving up between views once `stop()` says so (`None` then): a large scene's
/// final evaluation takes tens of seconds (`synth --preset large`: 33 s for 15 views), which a
/// Ctrl-C used to sit through.
pub fn evaluate_until(
    state: &TrainState,
    prepared: &Prepared,
    max: usize,
    out: Option<&Path>,
    stop: &dyn Fn() -> bool,
) -> Result<Option<Vec<ViewScore>>> {
    let views: Vec<usize> = if max == 0 {
        prepared.scene.test.clone()
    } else {
        prepared.scene.test.iter().copied().take(max).collect()
    };
    let refined = crate::train::refine::eval_tracer(state, prepared)?;
    let tracer = refined.as_ref().unwrap_or(&prepared.tracer);
    let mut scores = Vec::new();
    for &i in &views {
        if stop() {
            return Ok(None);
        }
        let look = prepared.appearance(&state.ckpt.model, &state.ckpt.params, i);
        let e = evaluate_view(
            &state.ckpt.model,
            &state.ckpt.params,
            tracer,
            &prepared.scene,
            i,
            state.cfg.model.gamma,
            &look,
            prepared.scene.background,
        )?;
        if let Some(dir) = out {
            let name = &prepared.scene.views[i].name;
            write_evaluated(&e, name, Some(&dir.join("render")), Some(&dir.join("eval")))?;
        }
        scores.push(e.scored.score);
    }
    Ok(Some(scores))
}

/// Train on `scene_dir` into `run_dir`.
pub fn train(
    scene_dir: &Path,
    run_dir: &Path,
    cfg: RunConfig,
    opts: &TrainOptions,
) -> Result<TrainSummary> {
    // Before any work: an invalid configuration would otherwise train and only fail when its
    // checkpoint is read back.
    cfg.validate()?;
    if run_dir.exists() && !run_dir.is_dir() {
        bail!(
            "{}: is a file, not a run folder; give --out a folder (new or holding a run)",
            run_dir.display()
        );
    }
    std::fs::create_dir_all(run_dir)
        .with_context(|| format!("{}: cannot create the run folder", run_dir.display()))?;
    let _lock = RunLock::acquire(run_dir)?;
    let replaced = prepare_run_dir(run_dir, opts.resume, opts.overwrite)?;
    let ckpt_path = run_checkpoint(run_dir);
    let (mut state, prepared) = match open_run(scene_dir, run_dir, cfg, opts, &replaced) {
        Err(e)
            if e.downcast_ref::<crate::train::setup::StoppedInSetup>()
                .is_some() =>
        {
            // Nothing trained, nothing to save: the folder holds what it held (a resumed
            // run's checkpoint untouched), so the same command starts again.
            eprintln!("{e}; nothing new to save: run the same command again");
            return Ok(TrainSummary {
                saved: false,
                ..TrainSummary::stopped(0, 0.0)
            });
        }
        r => r?,
    };
    let tc = state.cfg.train.clone();
    // A resumed run's time runs on from its checkpoint's.
    let before = if opts.resume {
        crate::train::report::elapsed_at(run_dir, state.step).unwrap_or(0.0)
    } else {
        0.0
    };
    let mut rep = Reporter::open(run_dir, opts.quiet, opts.bar, tc.steps, state.step, before)?;
    rep.model(&state);
    // The step the run's checkpoint holds: a resumed run's is on disk already.
    let mut saved = opts.resume.then_some(state.step);
    let interrupted = run_loop(
        &mut state, &prepared, &ckpt_path, opts, &mut rep, &mut saved,
    )?;
    rep.loop_done();
    // Not again when it holds this step (nothing trained since a resume, or a periodic
    // checkpoint just before an interrupt).
    if saved != Some(state.step) {
        save_checkpoint(&state, &ckpt_path)?;
        rep.checkpointed(state.step)?;
    }
    if let Some(line) = crate::train::refine::write_refined(&state, &prepared, run_dir)? {
        rep.say(line);
    }
    let seconds = rep.elapsed();
    if interrupted || state.step < tc.steps {
        rep.say(format!(
            "stopped at step {} of {}; checkpoint written to {} (continue with --resume)",
            state.step,
            tc.steps,
            ckpt_path.display()
        ));
        return Ok(TrainSummary::stopped(state.step, seconds));
    }
    rep.trained(state.step, seconds, &ckpt_path)?;
    let (mut final_scores, mut views) = (None, Vec::new());
    if !opts.no_final_eval && prepared.scene.test.is_empty() {
        rep.say(
            "no held-out views in this scene (scene.toml holds none out): no final evaluation"
                .into(),
        );
    }
    if !opts.no_final_eval && !prepared.scene.test.is_empty() {
        let Some(scores) = evaluate_until(&state, &prepared, 0, Some(run_dir), &|| opts.stopped())?
        else {
            rep.say(format!(
                "the final evaluation was stopped; training is done and its checkpoint written: `xscale eval --run {}` (or `train --resume`) scores the held-out views",
                run_dir.display()
            ));
            return Ok(TrainSummary::stopped(state.step, seconds));
        };
        final_scores = Some(rep.final_eval(state.step, &scores, run_dir)?);
        views = scores;
    }
    Ok(TrainSummary {
        steps: state.step,
        interrupted: false,
        saved: true,
        final_scores,
        views,
        seconds,
    })
}

/// The run's state and prepared scene: resumed from `RUN/checkpoint.safetensors` (its stored
/// configuration wins; `metrics.jsonl` is cut back to its step) or freshly initialised (the
/// level range resolved for the scene). Only once the scene is prepared and the state made — no
/// error left that would stop the run — does it touch the folder: the earlier run's files
/// `replaced` are removed ([`prepare_run_dir`]) and `scene.json`, `config.toml` (and a tool's
/// settings) written.
fn open_run(
    scene_dir: &Path,
    run_dir: &Path,
    cfg: RunConfig,
    opts: &TrainOptions,
    replaced: &[&str],
) -> Result<(TrainState, Prepared)> {
    // `-q` silences progress, never a warning.
    let say = |s: String| {
        if !opts.quiet || s.starts_with("warning:") {
            eprintln!("{s}");
        }
    };
    let ckpt_path = run_checkpoint(run_dir);
    let metrics_path = run_dir.join("metrics.jsonl");
    let resumed = if opts.resume {
        if !ckpt_path.exists() {
            bail!("--resume: {} does not exist", ckpt_path.display());
        }
        let mut st = TrainState::load(&ckpt_path)?;
        // A hand-edited config.toml is not what the run trains with: say so (it is rewritten
        // from the checkpoint's below).
        let config_file = run_dir.join("config.toml");
        if let Ok(text) = std::fs::read_to_string(&config_file) {
            let origin = config_file.display().to_string();
            let edited = match differences_but_steps(&text, &origin, &st.cfg, "the checkpoint") {
                Ok((_, d)) => d.join(", "),
                Err(e) => format!("{e:#}"),
            };
            if !edited.is_empty() {
                say(format!(
                    "warning: {origin} differs from the run's checkpoint ({edited}): a resume trains with the checkpoint's configuration and rewrites config.toml from it; for other settings start a new run"
                ));
            }
        }
        // A resumed run keeps its configuration; `cfg.train.steps` is the total asked for.
        if cfg.train.steps < st.step {
            bail!(
                "--resume: the run is already at step {}; --steps {} would be fewer (give a total of at least {})",
                st.step,
                cfg.train.steps,
                st.step
            );
        }
        st.cfg.train.steps = cfg.train.steps;
        // Settings that change no result are the caller's (`train --resume --config` may change
        // them: `config::RESUMABLE_KEYS`).
        let given = toml::Value::try_from(&cfg).expect("a RunConfig serialises");
        st.cfg = st.cfg.with_resumable(&given, "the run configuration")?;
        // The mesh's place may have moved (`xscale train --resume --mesh`, which passes the
        // stored configuration with the new place); the scene fingerprint below checks it is
        // the same mesh.
        if cfg.train.mesh.is_some() {
            st.cfg.train.mesh = cfg.train.mesh.clone();
        }
        say(format!(
            "resuming {} at step {} of {}",
            ckpt_path.display(),
            st.step,
            st.cfg.train.steps
        ));
        Some(st)
    } else {
        None
    };
    let run_cfg = resumed.as_ref().map_or(cfg, |s| s.cfg.clone());
    let stop = || opts.stopped();
    let prepared = prepare_until(
        scene_dir,
        &run_cfg,
        true,
        &mut |m| say(m),
        &stop,
        Job::Train,
    )?;
    let fingerprint = SceneFingerprint::of(scene_dir, &prepared.scene);
    if resumed.is_some() {
        if let Some(stored) = SceneFingerprint::read(run_dir)? {
            stored.check_same(&fingerprint)?;
        }
    }
    let state = match resumed {
        Some(s) => {
            truncate_metrics(&metrics_path, s.step)?;
            s
        }
        None => {
            let mut cfg = run_cfg;
            for msg in resolve_levels(&mut cfg, &prepared.samples) {
                say(msg);
            }
            let state = TrainState::init(cfg, &prepared)?;
            remove_run(run_dir, replaced)?;
            if let Some(settings) = &opts.settings {
                crate::io::atomic::write_bytes(&run_dir.join(SETTINGS_FILE), settings)?;
            }
            state
        }
    };
    fingerprint.write(run_dir)?;
    crate::io::atomic::write_bytes(&run_dir.join("config.toml"), state.cfg.to_toml())?;
    Ok((state, prepared))
}

/// Steps until the configured count, `opts.stop_at` or an interrupt (then `Ok(true)`), with
/// periodic evaluations and checkpoints (`saved`: the step of the last). A non-finite loss saves the state aside and fails.
fn run_loop(
    state: &mut TrainState,
    prepared: &Prepared,
    ckpt_path: &Path,
    opts: &TrainOptions,
    rep: &mut Reporter,
    saved: &mut Option<u64>,
) -> Result<bool> {
    let tc = state.cfg.train.clone();
    let mut grads = Grads::new(&state.ckpt.model.layout);
    grads.inputs = false; // positions and directions are data, not parameters
    let stop = opts.stop_at.unwrap_or(u64::MAX).min(tc.steps);
    let draw = |k: u64| {
        sample_batch(
            &prepared.samples,
            &prepared.tracer,
            tc.seed,
            k,
            tc.batch_pixels,
        )
    };
    let a = &tc.adam;
    let warmup = [
        &a.shader,
        &a.deform,
        &a.grid_h,
        &a.grid_d,
        &a.appearance,
        &a.vertex,
    ]
    .iter()
    .map(|g| g.schedule.warmup_steps as u64)
    .max()
    .unwrap_or(0);
    let mut guard = Guard::new(warmup, state.step);
    let mut f64s = crate::train::precision::F64Step::for_config(state);
    // Mesh refinement (`[model.refine]`) steps and draws batches itself (`train/refine.rs`).
    let mut refiner = crate::train::refine::Refiner::for_run(state, prepared, opts.interrupt)?;
    let mut next = (state.step < stop).then(|| match &refiner {
        Some(r) => r.draw(prepared, state.step),
        None => draw(state.step),
    });
    while let Some(mut batch) = next.take() {
        // Batch k+1 is drawn (its rays cast) while step k runs: a pure function of (seed, k+1),
        // so overlapping it changes no result, only fills the cores the step leaves idle.
        let k1 = state.step + 1;
        let (st, nb) = match refiner.as_mut() {
            Some(r) => r.step_and_draw(
                state,
                prepared,
                &mut batch,
                &mut grads,
                (k1 < stop).then_some(k1),
            ),
            None => rayon::join(
                || state.step_in(&batch, &mut grads, f64s.as_mut()),
                || (k1 < stop).then(|| draw(k1)),
            ),
        };
        next = nb;
        let st = st?;
        if !st.loss.is_finite() {
            let aside = ckpt_path.with_file_name("checkpoint-diverged.safetensors");
            state.save(&aside)?;
            bail!(
                "step {}: loss is {} (diverged); state saved to checkpoint-diverged.safetensors",
                state.step,
                st.loss
            );
        }
        let k = state.step;
        rep.step(k, &st, batch.n_pixels(), tc.log_every)?;
        if let Some(why) = guard.step(k, st.loss) {
            let aside = ckpt_path.with_file_name("checkpoint-diverged.safetensors");
            state.save(&aside)?;
            let kept = if ckpt_path.is_file() {
                format!(
                    "the last checkpoint before it, {}, is kept",
                    ckpt_path.display()
                )
            } else {
                "no earlier checkpoint was written".to_string()
            };
            bail!(
                "step {k}: training diverged: {why}. The state is saved to checkpoint-diverged.safetensors; {kept}"
            );
        }
        if tc.eval_every > 0
            && k % tc.eval_every == 0
            && k < tc.steps
            && !prepared.scene.test.is_empty()
        {
            let scores = evaluate(state, prepared, tc.eval_max_views, None)?;
            rep.eval(k, &scores)?;
        }
        if tc.checkpoint_every > 0 && k % tc.checkpoint_every == 0 && k < tc.steps {
            save_checkpoint(state, ckpt_path)?;
            rep.checkpointed(k)?;
            *saved = Some(k);
        }
        if opts.stopped() {
            return Ok(true);
        }
    }
    Ok(false)
}

/// Write the run's checkpoint; when that fails (a full disk, a quota), say what the run still
/// has: the checkpoint file is written whole or not at all, so the previous one is intact.
fn save_checkpoint(state: &TrainState, ckpt_path: &Path) -> Result<()> {
    state.save(ckpt_path).map_err(|e| {
        let what = match crate::train::run_dir::checkpoint_step(ckpt_path) {
            Some(step) => format!(
                "{} still holds step {step}; once the cause (below) is mended, e.g. room made, continue with --resume",
                ckpt_path.display()
            ),
            None => "no earlier checkpoint was written".to_string(),
        };
        e.context(format!(
            "step {}: the checkpoint could not be written; {what}",
            state.step
        ))
    })
}

/// `RUN/checkpoint.safetensors` of a run folder.
pub fn run_checkpoint(run: &Path) -> PathBuf {
    run.join("checkpoint.safetensors")
}
