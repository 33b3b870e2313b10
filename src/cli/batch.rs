//! `xscale batch --scene DIR --size N --seed S --out FILE`: batch `--step` (default 0) of a run
//! with that seed, drawn from the scene's sample cache exactly as training draws it (SPEC §5, §6).

use super::common::{parse_positive, resolve_config};
use crate::io::tensors::TensorFile;
use crate::model::checkpoint::batch_to_tensors;
use crate::train::memory::Job;
use crate::train::sampler::sample_batch;
use crate::train::setup::prepare_until;
use std::path::PathBuf;
use std::process::ExitCode;

#[derive(clap::Args, Debug)]
pub struct Args {
    /// Scene directory.
    #[arg(long)]
    pub scene: PathBuf,
    /// Pixels in the batch (at least 1).
    #[arg(long, value_parser = parse_positive)]
    pub size: usize,
    /// Seed of the batch draw (as `[train] seed`).
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Which step's batch.
    #[arg(long, default_value_t = 0)]
    pub step: u64,
    /// Preset (for γ and the image downsampling) [default: cpu]; must agree with a `preset` the
    /// --config file gives.
    #[arg(long, value_parser = ["tiny", "cpu", "paper"])]
    pub preset: Option<String>,
    /// TOML overrides (as `xscale train --config`).
    #[arg(long)]
    pub config: Option<PathBuf>,
    /// Override γ (sub-samples per pixel = γ²).
    #[arg(long)]
    pub gamma: Option<u32>,
    /// Batch file to write (safetensors, tensor names in docs/spec.md).
    #[arg(long)]
    pub out: PathBuf,
}

pub fn run(a: Args) -> anyhow::Result<ExitCode> {
    crate::io::atomic::writable_folder(&a.out)?;
    let mut cfg = resolve_config(a.preset.as_deref(), a.config.as_deref())?;
    if let Some(g) = a.gamma {
        cfg.model.gamma = g;
    }
    cfg.validate()?;
    // The memory check sizes this batch (refused before the scene is cast and the batch drawn
    // when it cannot fit), not training steps.
    let job = Job::Batch { pixels: a.size };
    let p = prepare_until(
        &a.scene,
        &cfg,
        true,
        &mut |m| eprintln!("{m}"),
        &|| false,
        job,
    )?;
    let b = sample_batch(&p.samples, &p.tracer, a.seed, a.step, a.size);
    b.validate()?;
    let mut f = TensorFile::new();
    batch_to_tensors(&mut f, &b)?;
    f.write_atomic(&a.out)?;
    eprintln!(
        "wrote {} ({} pixels × {} sub-samples)",
        a.out.display(),
        b.n_pixels(),
        b.samples_per_pixel()
    );
    Ok(ExitCode::SUCCESS)
}
