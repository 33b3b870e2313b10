//! `xscale case [--scene DIR] --out CASE`: everything a backend's CI compares against, in one
//! folder, from one command (docs/oracle.md §1):
//!
//! | file | what |
//! |---|---|
//! | `config.toml` | the run config: by default the `tiny` preset with `positions = "tcnn"` and `level_weight = "none"`, which tiny-cuda-nn can reproduce |
//! | `checkpoint.safetensors` | the model after `--steps` training steps (every parameter non-trivial; no Adam state) |
//! | `batch.safetensors` | `--size` pixels (batch step 1000 of the seed, one training never drew), with `--invalid` of the sub-samples marked invalid and the first `--mean-view` pixels given `view = -1` |
//! | `oracle.safetensors` | `xscale dump --precision f64` of the two (every intermediate, the loss, every gradient, the kink account) |
//! | `tolerances.toml` | the tolerance set `--tolerances` (default `f32`) |
//! | `manifest.json` | every tensor a backend must write (name, shape, dtype, meaning), the switches it may turn on and the tensors they add (`model::manifest`) |
//! | `scene/` | without `--scene`: the bundled tiny scene (`xscale synth --preset tiny --seed 1`, the files of `fixtures/tiny`) |
//!
//! Deterministic: the same command writes the same bytes, so running it twice into the same
//! folder is harmless (a folder that holds anything but an earlier case is refused).

use crate::io::tensors::TensorFile;
use crate::model::checkpoint::{dump_with, Checkpoint};
use crate::model::Batch;
use crate::rng::{self, Purpose};
use anyhow::{bail, Context, Result};
use clap::Parser;
use std::collections::BTreeMap;
use std::ffi::{OsStr, OsString};
use std::path::{Path, PathBuf};
use std::process::ExitCode;

#[derive(clap::Args, Debug, Clone)]
pub struct Args {
    /// Scene directory [default: the bundled tiny scene, written to CASE/scene].
    #[arg(long)]
    pub scene: Option<PathBuf>,
    /// Case folder to write (new, empty, or an earlier case, which is rewritten).
    #[arg(long)]
    pub out: PathBuf,
    /// Preset [default: tiny, or the --config file's]. Without --config the case overrides it to
    /// be backend-safe: `positions = "tcnn"`, `level_weight = "none"`.
    #[arg(long, value_parser = ["tiny", "cpu", "paper"])]
    pub preset: Option<String>,
    /// Run config (TOML) to use as it is instead of the backend-safe default (the manifest then
    /// says which of its switches tiny-cuda-nn cannot reproduce).
    #[arg(long)]
    pub config: Option<PathBuf>,
    /// Training steps before the checkpoint is taken (0 = a fresh initialisation, whose ξ is
    /// exactly zero and leaves grid D's and ξ's first layer's gradients at zero).
    #[arg(long, default_value_t = 20)]
    pub steps: u64,
    /// Pixels in the batch (at least 1).
    #[arg(long, default_value_t = 256, value_parser = super::common::parse_positive)]
    pub size: usize,
    /// Seed of training and of the batch.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Share of the sub-samples marked invalid (a pixel keeps at least one), so a backend's
    /// pooling over valid sub-samples is tested (the tiny scene's rays almost never miss).
    #[arg(long, default_value_t = 0.3, value_parser = parse_share)]
    pub invalid: f64,
    /// Pixels (the first ones) given `view = -1`, the mean appearance code [default: size / 16].
    #[arg(long)]
    pub mean_view: Option<usize>,
    /// Built-in tolerance set written as tolerances.toml (f32, f64, fp16, grid-exact, exact).
    #[arg(long, default_value = "f32")]
    pub tolerances: String,
}

fn parse_share(s: &str) -> Result<f64, String> {
    match s.trim().parse::<f64>() {
        Ok(p) if (0.0..1.0).contains(&p) => Ok(p),
        _ => Err("must be a number in [0, 1)".into()),
    }
}

/// The files of a case folder (relative names).
pub const CASE_FILES: [&str; 7] = [
    "config.toml",
    "checkpoint.safetensors",
    "batch.safetensors",
    "oracle.safetensors",
    "tolerances.toml",
    "manifest.json",
    "scene",
];

/// The run config a case uses without `--config`.
fn default_config(preset: &str, steps: u64, seed: u64) -> String {
    format!(
        "# Written by `xscale case`: the {preset} preset in a configuration tiny-cuda-nn can reproduce.\n\
         preset = \"{preset}\"\n\
         [model]\n\
         positions = \"tcnn\"      # x rounded to f32, p = fma(scale, x, 0.5) in f32, as tiny-cuda-nn's fp32 grid\n\
         level_weight = \"none\"   # Eqs. 2 and 4 as the paper writes them (no footprint weighting)\n\
         [train]\n\
         steps = {steps}\n\
         seed = {seed}\n"
    )
}

/// Marks a case folder whose command has not finished (removed at the end): an interrupted case
/// is rewritten by the next run like a finished one.
const INCOMPLETE: &str = ".case-incomplete";

/// Refuse a folder that holds anything but an earlier (or interrupted) case.
fn check_out(out: &Path) -> Result<()> {
    let Ok(entries) = std::fs::read_dir(out) else {
        return Ok(());
    };
    let is_case = out.join(INCOMPLETE).is_file()
        || std::fs::read_to_string(out.join("manifest.json"))
            .map(|t| t.contains("\"xscale-case-1\""))
            .unwrap_or(false);
    for e in entries.flatten() {
        let name = e.file_name().to_string_lossy().to_string();
        let ours = CASE_FILES.contains(&name.as_str()) || name.starts_with(".case-");
        if !(is_case && ours) {
            bail!(
                "--out {}: the folder holds {name:?} and is not an earlier case; give a new or empty folder",
                out.display()
            );
        }
    }
    Ok(())
}

/// Mark sub-samples invalid (`Purpose::Case`) and give the first `mean_view` pixels view −1.
fn edit_batch(b: &mut Batch, seed: u64, invalid: f64, mean_view: usize, codes: bool) {
    let n = b.n_pixels();
    let s = b.samples_per_pixel();
    if s > 1 && invalid > 0.0 {
        for i in 0..n {
            for j in 0..s {
                let k = i * s + j;
                if rng::uniform_f64(seed, Purpose::Case, 0, k as u64) < invalid {
                    b.valid[k] = 0;
                }
            }
            if b.valid[i * s..(i + 1) * s].iter().all(|&v| v == 0) {
                b.valid[i * s] = 1;
            }
            for j in 0..s {
                if b.valid[i * s + j] == 0 {
                    // As `xscale batch` stores a miss.
                    b.positions[i * s + j] = [0.0; 3];
                    if !b.triangle.is_empty() {
                        b.triangle[i * s + j] = u32::MAX;
                        b.bary[i * s + j] = [0.0; 2];
                    }
                }
            }
        }
    }
    if codes {
        for v in b.view.iter_mut().take(mean_view) {
            *v = -1;
        }
    }
}

/// A command of the case stopped by a signal: its exit code.
#[derive(Debug)]
struct Stopped(ExitCode);

impl std::fmt::Display for Stopped {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("stopped")
    }
}

impl std::error::Error for Stopped {}

/// Run one `xscale` command line in this process; a command stopped by a signal is [`Stopped`].
fn xscale(args: &[&OsStr]) -> Result<()> {
    let argv = std::iter::once(OsStr::new("xscale")).chain(args.iter().copied());
    let cli = super::Cli::try_parse_from(argv)
        .map_err(|e| anyhow::anyhow!("internal command line: {e}"))?;
    let code = super::run(cli)?;
    if code != ExitCode::SUCCESS {
        return Err(Stopped(code).into());
    }
    Ok(())
}

pub fn run(a: Args) -> Result<ExitCode> {
    let out = a.out.clone();
    match make(a) {
        Err(e) if e.downcast_ref::<Stopped>().is_some() => {
            eprintln!(
                "case: stopped before {} was complete; the same command makes it again",
                out.display()
            );
            Ok(e.downcast_ref::<Stopped>().unwrap().0)
        }
        r => r,
    }
}

fn make(a: Args) -> Result<ExitCode> {
    let out = &a.out;
    open_case(out)?;
    let tol_text =
        crate::io::compare::builtin_tolerance_text(&a.tolerances).with_context(|| {
            format!(
                "--tolerances {:?}: not a built-in set ({})",
                a.tolerances,
                crate::io::compare::builtin_tolerance_names().join(", ")
            )
        })?;
    let scene = case_scene(&a)?;
    let config = case_config(&a)?;
    let cmd = Commands {
        scene: scene.as_os_str().to_owned(),
        config: config.as_os_str().to_owned(),
        preset: preset_args(&a)?,
    };

    // The checkpoint: `--steps` training steps, Adam state left out.
    let tmp = out.join(".case-train");
    if tmp.exists() {
        std::fs::remove_dir_all(&tmp).with_context(|| format!("{}", tmp.display()))?;
    }
    let ckpt = case_checkpoint(&a, &cmd, &tmp)?;
    ckpt.save(out.join("checkpoint.safetensors"))?;
    let batch = case_batch(&a, &cmd, &tmp, &ckpt)?;
    std::fs::remove_dir_all(&tmp).with_context(|| format!("{}", tmp.display()))?;

    // The oracle: the f64 dump with its kink account.
    eprintln!("case: the f64 oracle dump");
    let dump = dump_with::<f64>(&ckpt, &batch, Some(crate::model::kink::DEFAULT_THRESHOLD))?;
    dump.write_atomic(out.join("oracle.safetensors"))?;
    crate::io::atomic::write_bytes(&out.join("tolerances.toml"), tol_text)?;

    let manifest = write_manifest(&a, &ckpt, &batch, &dump)?;
    std::fs::remove_file(out.join(INCOMPLETE))
        .with_context(|| format!("{}", out.join(INCOMPLETE).display()))?;
    report(&a, &batch, &dump, &manifest)?;
    Ok(ExitCode::SUCCESS)
}

/// Make (or take back) the case folder, marked unfinished until the end.
fn open_case(out: &Path) -> Result<()> {
    // The folder's parent must exist (a typo costs no work); the folder itself is created.
    if !out.is_dir() {
        crate::io::atomic::writable_folder(out)?;
    }
    check_out(out)?;
    std::fs::create_dir_all(out).with_context(|| format!("{}: cannot create", out.display()))?;
    crate::io::atomic::write_bytes(&out.join(INCOMPLETE), "xscale case: not finished\n")?;
    // The process's one interrupt handler (its message is the first installer's): a signal stops
    // the command under way at its next safe point, then the case.
    super::common::on_interrupt("stopping the case (the same command makes it again)");
    Ok(())
}

/// The scene: `--scene`, or the bundled tiny scene written to CASE/scene.
fn case_scene(a: &Args) -> Result<PathBuf> {
    if let Some(s) = &a.scene {
        return Ok(s.clone());
    }
    let dir = a.out.join("scene");
    eprintln!("case: the bundled tiny scene -> {}", dir.display());
    let d = dir.as_os_str().to_owned();
    xscale(&[
        "synth".as_ref(),
        "--preset".as_ref(),
        "tiny".as_ref(),
        "--seed".as_ref(),
        "1".as_ref(),
        "--out".as_ref(),
        &d,
    ])?;
    Ok(dir)
}

/// CASE/config.toml: a copy of `--config`, or the backend-safe default.
fn case_config(a: &Args) -> Result<PathBuf> {
    let config = a.out.join("config.toml");
    match &a.config {
        Some(c) => {
            let text = crate::io::text::read(c)?;
            crate::io::atomic::write_bytes(&config, text)?;
        }
        None => {
            let preset = a.preset.as_deref().unwrap_or("tiny");
            crate::io::atomic::write_bytes(&config, default_config(preset, a.steps, a.seed))?;
        }
    }
    Ok(config)
}

/// The `--preset` the case's commands are given. With --config: --preset if given, else the
/// file's `preset`, else tiny (not the commands' default cpu: a case is the oracle's tiny model
/// unless asked otherwise).
fn preset_args(a: &Args) -> Result<Vec<OsString>> {
    Ok(match (&a.config, &a.preset) {
        (None, _) => vec![],
        (Some(_), Some(p)) => vec!["--preset".into(), p.into()],
        (Some(c), None) => match super::common::config_file_preset(c)? {
            Some(_) => vec![],
            None => vec!["--preset".into(), "tiny".into()],
        },
    })
}

/// What every command of the case is given: the scene, the config and the preset.
struct Commands {
    scene: OsString,
    config: OsString,
    preset: Vec<OsString>,
}

impl Commands {
    /// Run `xscale NAME --scene S --config C REST… [--preset P]`.
    fn run(&self, name: &str, rest: &[&OsStr]) -> Result<()> {
        let mut args: Vec<&OsStr> = vec![
            name.as_ref(),
            "--scene".as_ref(),
            &self.scene,
            "--config".as_ref(),
            &self.config,
        ];
        args.extend(rest);
        args.extend(self.preset.iter().map(|s| s.as_os_str()));
        xscale(&args)
    }
}

/// The model after `--steps` training steps (a fresh initialisation for 0), made in `tmp`.
fn case_checkpoint(a: &Args, cmd: &Commands, tmp: &Path) -> Result<Checkpoint> {
    let seed = a.seed.to_string();
    if a.steps > 0 {
        eprintln!("case: training {} steps", a.steps);
        let steps = a.steps.to_string();
        cmd.run(
            "train",
            &[
                "--steps".as_ref(),
                steps.as_ref(),
                "--seed".as_ref(),
                seed.as_ref(),
                "--no-eval".as_ref(),
                "--quiet".as_ref(),
                "--out".as_ref(),
                tmp.as_os_str(),
            ],
        )?;
        Checkpoint::load(tmp.join("checkpoint.safetensors"))
    } else {
        let f = tmp.join("init.safetensors");
        std::fs::create_dir_all(tmp)?;
        cmd.run(
            "init",
            &[
                "--seed".as_ref(),
                seed.as_ref(),
                "--out".as_ref(),
                f.as_os_str(),
            ],
        )?;
        Checkpoint::load(&f)
    }
}

/// The batch: step 1000 of the seed (one training never drew), edited ([`edit_batch`]), written
/// to CASE/batch.safetensors.
fn case_batch(a: &Args, cmd: &Commands, tmp: &Path, ckpt: &Checkpoint) -> Result<Batch> {
    let raw = tmp.join("batch.safetensors");
    let (size, seed) = (a.size.to_string(), a.seed.to_string());
    cmd.run(
        "batch",
        &[
            "--size".as_ref(),
            size.as_ref(),
            "--seed".as_ref(),
            seed.as_ref(),
            "--step".as_ref(),
            "1000".as_ref(),
            "--out".as_ref(),
            raw.as_os_str(),
        ],
    )?;
    let mut batch = Batch::load(&raw)?;
    let mean_view = a.mean_view.unwrap_or(a.size / 16).min(batch.n_pixels());
    edit_batch(
        &mut batch,
        a.seed,
        a.invalid,
        mean_view,
        ckpt.model.appearance_dim() > 0,
    );
    ckpt.model.check_batch(&batch)?;
    let mut bf = TensorFile::new();
    crate::model::checkpoint::batch_to_tensors(&mut bf, &batch)?;
    bf.write_atomic(a.out.join("batch.safetensors"))?;
    Ok(batch)
}

/// CASE/manifest.json: every tensor a backend writes, and the case's files.
fn write_manifest(
    a: &Args,
    ckpt: &Checkpoint,
    batch: &Batch,
    dump: &TensorFile,
) -> Result<serde_json::Value> {
    let mut files = BTreeMap::new();
    files.insert("config", "config.toml".to_string());
    files.insert("checkpoint", "checkpoint.safetensors".to_string());
    files.insert("batch", "batch.safetensors".to_string());
    files.insert("oracle", "oracle.safetensors".to_string());
    files.insert("tolerances", "tolerances.toml".to_string());
    files.insert("tolerance_set", a.tolerances.clone());
    if a.scene.is_none() {
        files.insert("scene", "scene".to_string());
    }
    let manifest = crate::model::manifest::manifest_json(ckpt, batch, dump, &files)?;
    crate::io::atomic::write_bytes(
        &a.out.join("manifest.json"),
        serde_json::to_string_pretty(&manifest)? + "\n",
    )?;
    Ok(manifest)
}

/// What the case holds, and what a backend does with it.
fn report(a: &Args, batch: &Batch, dump: &TensorFile, manifest: &serde_json::Value) -> Result<()> {
    let out = &a.out;
    let required = manifest["tensors"]
        .as_array()
        .map_or(0, |t| t.iter().filter(|e| e["required"] == true).count());
    let kink = dump.get("kink.pixels").map_or(0, |t| t.numel());
    eprintln!(
        "wrote {}: checkpoint ({} steps), batch ({} pixels × {} sub-samples, {} invalid, {} with view -1), \
         f64 oracle dump (loss {:.9e}, {} kink pixels), tolerances ({}), manifest ({} tensors a backend writes{})",
        out.display(),
        a.steps,
        batch.n_pixels(),
        batch.samples_per_pixel(),
        batch.valid.iter().filter(|&&v| v == 0).count(),
        batch.view.iter().filter(|&&v| v < 0).count(),
        dump.get("loss")?.to_f64()?[0],
        kink,
        a.tolerances,
        required,
        if manifest["tcnn_reproducible"] == true {
            "; tiny-cuda-nn can reproduce this configuration"
        } else {
            "; NOT reproducible by tiny-cuda-nn, see manifest.json switches"
        }
    );
    eprintln!(
        "next: your backend reads {0}/checkpoint.safetensors and {0}/batch.safetensors and writes mine.safetensors; \
         xscale compare {0}/oracle.safetensors mine.safetensors --tolerances {0}/tolerances.toml",
        out.display()
    );
    Ok(())
}
