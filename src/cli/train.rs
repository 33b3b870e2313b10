//! `xscale train`: train on a scene directory into a run folder (see `train/trainer.rs`).

use super::common::RunArgs;
use crate::train::trainer::{train, TrainOptions};
use std::path::PathBuf;
use std::process::ExitCode;
use std::sync::atomic::{AtomicBool, Ordering};

#[derive(clap::Args, Debug)]
pub struct Args {
    /// Scene directory (mesh + cameras + images; see README "Formats").
    #[arg(long)]
    pub scene: PathBuf,
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
    /// Continue from RUN/checkpoint.safetensors, bit-identically to an uninterrupted run.
    #[arg(long)]
    pub resume: bool,
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

static INTERRUPTED: AtomicBool = AtomicBool::new(false);

pub fn run(a: Args) -> anyhow::Result<ExitCode> {
    let mut cfg = a.run.resolve()?;
    if let Some(m) = &a.mesh {
        cfg.train.mesh = Some(super::common::absolute_mesh_path(m, &a.scene));
    }
    cfg.validate()?;
    // First Ctrl-C: finish the step, write a checkpoint, exit. Second: exit at once.
    let _ = ctrlc::set_handler(|| {
        if INTERRUPTED.swap(true, Ordering::SeqCst) {
            std::process::exit(130);
        }
        eprintln!("\ninterrupt: writing a checkpoint after this step (Ctrl-C again to abort)");
    });
    let opts = TrainOptions {
        resume: a.resume,
        stop_at: a.stop_at,
        interrupt: Some(&INTERRUPTED),
        no_final_eval: a.no_eval,
        quiet: a.quiet,
    };
    let s = train(&a.scene, &a.out, cfg, &opts)?;
    Ok(if s.interrupted && INTERRUPTED.load(Ordering::SeqCst) {
        ExitCode::from(130)
    } else {
        ExitCode::SUCCESS
    })
}
