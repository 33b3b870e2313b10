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
use crate::model::params::Grads;
use crate::render::appearance::NewViewCodes;
use crate::render::ModelRenderer;
use crate::run::divergence::Guard;
use crate::run::report::Reporter;
use crate::run::run_dir::{
    prepare_run_dir, remove_run, run_checkpoint, RunLock, SceneFingerprint, SETTINGS_FILE,
};
use crate::scene::Camera;
use crate::train::config::{differences_but_steps, RunConfig};
use crate::train::memory::Job;
use crate::train::sampler::draw_batch;
use crate::train::setup::{prepare_until, Prepared};
use crate::train::state::TrainState;
use anyhow::{bail, Context, Result};
use std::path::Path;
use std::sync::atomic::{AtomicBool, Ordering};

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
    let refined = crate::refine::mesh::eval_tracer(state, prepared)?;
    let tracer = refined.as_ref().unwrap_or(&prepared.tracer);
    let renderer = ModelRenderer {
        model: &state.ckpt.model,
        params: &state.ckpt.params,
        tracer,
        gamma: state.cfg.model.gamma,
        background: prepared.scene.background,
    };
    let train: Vec<&Camera> = (prepared.train_views.iter())
        .map(|&j| &prepared.scene.views[j].camera)
        .collect();
    // The view's own row, or for a held-out view its neighbours' codes blended (the default
    // rule of `render::appearance`).
    let looks = NewViewCodes::new(
        &state.ckpt.model,
        &state.ckpt.params,
        Default::default(),
        train,
    );
    let mut scores = Vec::new();
    for &i in &views {
        if stop() {
            return Ok(None);
        }
        let look = looks.appearance(prepared.appearance_row(i), &prepared.scene.views[i].camera);
        let e = evaluate_view(&renderer, &prepared.scene, i, &look)?;
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
        crate::run::report::elapsed_at(run_dir, state.step).unwrap_or(0.0)
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
    if let Some(line) = crate::refine::mesh::write_refined(&state, &prepared, run_dir)? {
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
            let state = TrainState::init(run_cfg, &prepared, &mut |m| say(m))?;
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
        draw_batch(
            &prepared.samples,
            &prepared.tracer,
            tc.seed,
            k,
            tc.batch_pixels,
            tc.patch,
            tc.patched_pixels(),
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
    // Mesh refinement (`[model.refine]`) steps and draws batches itself (`refine/refiner.rs`).
    let mut refiner = crate::refine::refiner::Refiner::for_run(state, prepared, opts.interrupt)?;
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
        let what = match crate::run::run_dir::checkpoint_step(ckpt_path) {
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
