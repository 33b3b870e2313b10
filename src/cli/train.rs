//! `xscale train`: train on a scene directory into a run folder (see `run/trainer.rs`).

use super::common::RunArgs;
use crate::run::trainer::{train, TrainOptions};
use crate::train::config::{is_resumable, RunConfig};
use anyhow::bail;
use std::path::PathBuf;
use std::process::ExitCode;
use std::sync::atomic::Ordering;

#[derive(clap::Args, Debug)]
pub struct Args {
    /// Scene directory (mesh + cameras + images; see README "Formats"). With --resume it may be
    /// left out: the scene the run was trained on (RUN/scene.json) is used.
    #[arg(long, required_unless_present = "resume")]
    pub scene: Option<PathBuf>,
    /// Run folder (created): checkpoint, metrics.jsonl, config.toml, renders, eval.
    #[arg(long)]
    pub out: PathBuf,
    #[command(flatten)]
    pub run: RunArgs,
    /// Mesh file to train on instead of the scene's own (e.g. from `xscale decimate`); stored
    /// (absolute) in the run config, so `eval`/`render --run` use it too. The normalisation is
    /// that of this mesh.
    #[arg(long)]
    pub mesh: Option<PathBuf>,
    /// Continue from RUN/checkpoint.safetensors, bit-identically to an uninterrupted run. The
    /// run's stored configuration is used; `--steps N` sets the total (not the steps to add); a
    /// `--config` file may change the `[train]` keys that change no result (checkpoint_every,
    /// log_every, eval_every, eval_max_views, memory_gb, samples); any other option that
    /// differs from the run is an error (docs/runs.md).
    #[arg(long, conflicts_with = "overwrite")]
    pub resume: bool,
    /// Replace the run this folder already holds (without it, a folder holding a run is refused).
    #[arg(long)]
    pub overwrite: bool,
    /// Stop after this many steps with a checkpoint, as if interrupted (for resume tests).
    #[arg(long, hide = true)]
    pub stop_at: Option<u64>,
    /// Skip the final renders and held-out evaluation.
    #[arg(long)]
    pub no_eval: bool,
    /// Only errors.
    #[arg(long, short)]
    pub quiet: bool,
}

pub fn run(a: Args) -> anyhow::Result<ExitCode> {
    if let Some(pid) = crate::run::run_dir::RunLock::holder(&a.out) {
        bail!("{}", crate::run::run_dir::held_by(&a.out, pid));
    }
    let (cfg, scene) = if a.resume {
        resume_config(&a)?
    } else {
        let scene = a
            .scene
            .clone()
            .expect("clap requires --scene without --resume");
        let mut cfg = a.run.resolve()?;
        if let Some(m) = &a.mesh {
            cfg.train.mesh = Some(super::common::absolute_mesh_path(m, &scene));
        }
        (cfg, scene)
    };
    // (`train` validates the configuration before any work.)
    // First Ctrl-C: finish the step, write a checkpoint, exit. Second: exit at once.
    let interrupted = super::common::on_interrupt(
        "stopping: in training, after this step with a checkpoint; before or after, at once",
    );
    let opts = TrainOptions {
        resume: a.resume,
        overwrite: a.overwrite,
        stop_at: a.stop_at,
        interrupt: Some(interrupted),
        no_final_eval: a.no_eval,
        quiet: a.quiet,
        bar: false,
        settings: None,
    };
    let s = train(&scene, &a.out, cfg, &opts)?;
    Ok(
        match (s.interrupted && interrupted.load(Ordering::SeqCst), s.saved) {
            (false, _) => ExitCode::SUCCESS,
            (true, true) => ExitCode::from(super::common::EXIT_STOPPED),
            (true, false) => ExitCode::from(super::common::EXIT_STOPPED_UNSAVED),
        },
    )
}

/// For `--resume`: `--scene`, else the scene the run records in `RUN/scene.json` (the
/// fingerprint check in `train` then confirms it still holds what the run was trained on).
fn resume_scene(a: &Args) -> anyhow::Result<PathBuf> {
    if let Some(s) = &a.scene {
        return Ok(s.clone());
    }
    match crate::run::run_dir::SceneFingerprint::read(&a.out)? {
        Some(f) if f.scene.is_dir() => Ok(f.scene),
        Some(f) => bail!(
            "--resume: the run's scene {} (from {}) no longer exists; give --scene DIR",
            f.scene.display(),
            crate::run::run_dir::SceneFingerprint::path(&a.out).display()
        ),
        None => bail!(
            "--resume: {} does not record the run's scene (made by an older xscale); give --scene DIR",
            a.out.display()
        ),
    }
}

/// For `--resume`: the run's stored configuration with the total step count asked for
/// (`--steps`, else the stored one), and its scene ([`resume_scene`]). Every other option given
/// must agree with the run; a difference is an error naming the field (the stored
/// configuration always wins).
fn resume_config(a: &Args) -> anyhow::Result<(RunConfig, PathBuf)> {
    let ckpt = crate::run::run_dir::run_checkpoint(&a.out);
    if !ckpt.is_file() {
        bail!(
            "--resume: {} does not exist: nothing to resume (a run stopped before its first checkpoint leaves none); start the run without --resume (`xscale train --scene DIR --out {}`): in a folder without a checkpoint it starts afresh",
            ckpt.display(),
            a.out.display()
        );
    }
    let (_, stored) = crate::run::model::load_model(&ckpt)?;
    let mut stored = stored.ok_or_else(|| {
        anyhow::anyhow!(
            "{}: the checkpoint has no run configuration",
            ckpt.display()
        )
    })?;
    let scene = resume_scene(a)?;
    // The run's mesh file moved: --mesh gives its new place (the scene fingerprint then checks
    // it is the same mesh), and the run records it from here on.
    let mut mesh_given = a.mesh.clone();
    if let Some(m) = stored.train.mesh.clone().filter(|m| !m.exists()) {
        let Some(new) = mesh_given.take() else {
            bail!(
                "--resume: {}: the mesh the run trains on (train.mesh of its configuration) no longer exists; put it back, or give its new place with --mesh FILE (it must be the same mesh: the run checks)",
                m.display()
            );
        };
        stored.train.mesh = Some(super::common::absolute_mesh_path(&new, &scene));
    }
    let mut diffs: Vec<String> = Vec::new();
    let r = &a.run;
    if let Some(p) = r.preset.as_ref().filter(|p| **p != stored.preset) {
        diffs.push(format!(
            "--preset {p} (the run's preset is {})",
            stored.preset
        ));
    }
    if let Some(s) = r.seed.filter(|&s| s != stored.train.seed) {
        diffs.push(format!("--seed {s} (the run's is {})", stored.train.seed));
    }
    if let Some(b) = r.batch.filter(|&b| b != stored.train.batch_pixels) {
        diffs.push(format!(
            "--batch {b} (the run's is {})",
            stored.train.batch_pixels
        ));
    }
    if let Some(m) = &mesh_given {
        let m = super::common::absolute_mesh_path(m, &scene);
        // Compare files, not settings: the scene's own mesh named with --mesh is the run's mesh.
        let (run_mesh, label) = match &stored.train.mesh {
            Some(p) => (Some(p.clone()), p.display().to_string()),
            None => {
                let own = crate::scene::load::find_mesh(&scene).ok();
                let label = own.as_ref().map_or("the scene's own".to_string(), |p| {
                    format!("the scene's own, {}", p.display())
                });
                (own, label)
            }
        };
        let same = run_mesh.is_some_and(|p| std::fs::canonicalize(&p).unwrap_or(p) == m);
        if !same {
            diffs.push(format!(
                "--mesh {} (the run's mesh is {label})",
                m.display()
            ));
        }
    }
    // `[train] steps` in a --config file is the total asked for, as --steps (which wins).
    let mut steps = r.steps;
    let mut taken: Vec<String> = Vec::new();
    if let Some(file) = &r.config {
        let (given, d, total) = config_differences(file, &stored)?;
        // Keys that change no result are taken, not refused (`config::RESUMABLE_KEYS`).
        let (resumable, refused): (Vec<String>, Vec<String>) =
            d.into_iter().partition(|d| is_resumable(d));
        diffs.extend(refused);
        taken = resumable;
        if !taken.is_empty() {
            stored = stored.with_resumable(&given, &file.display().to_string())?;
        }
        steps = steps.or(total);
    }
    if !diffs.is_empty() {
        bail!(
            "--resume continues the run with its stored configuration, but these options differ from it:\n  {}\nleave them out to resume, or start a new run (another --out, or --overwrite)",
            diffs.join("\n  ")
        );
    }
    if !taken.is_empty() && !a.quiet {
        eprintln!(
            "--resume: {}: these change when the run logs, evaluates or checkpoints (or how it holds its samples), not what it computes, so the resumed run takes them",
            taken.join(", ")
        );
    }
    if let Some(n) = steps {
        stored.train.steps = n;
    }
    Ok((stored, scene))
}

/// A `--config` file's TOML, every key it sets whose value differs from the stored
/// configuration's, and the file's `[train] steps` (not a difference: it is the total asked
/// for, as `--steps`).
fn config_differences(
    file: &std::path::Path,
    stored: &RunConfig,
) -> anyhow::Result<(toml::Value, Vec<String>, Option<u64>)> {
    let text = crate::io::text::read(file)?;
    let origin = file.display().to_string();
    let (given, out) =
        crate::train::config::differences_but_steps(&text, &origin, stored, "the run")?;
    let steps = match given.get("train").and_then(|t| t.get("steps")) {
        None => None,
        Some(v) => Some(
            v.as_integer()
                .and_then(|n| u64::try_from(n).ok())
                .ok_or_else(|| {
                    anyhow::anyhow!(
                        "{}: [train] steps = {v}: expected a whole number ≥ 0",
                        file.display()
                    )
                })?,
        ),
    };
    let out = out
        .into_iter()
        .map(|d| format!("{d} (in {})", file.display()))
        .collect();
    Ok((given, out, steps))
}
