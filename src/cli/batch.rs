//! `xscale batch --scene DIR --size N --seed S --out FILE`: batch `--step` (default 0) of a run
//! with that seed, drawn from the scene's sample cache exactly as training draws it (SPEC §5, §6).

use crate::io::tensors::TensorFile;
use crate::model::checkpoint::batch_to_tensors;
use crate::train::config::RunConfig;
use crate::train::sampler::sample_batch;
use crate::train::setup::prepare;
use std::path::PathBuf;
use std::process::ExitCode;

#[derive(clap::Args, Debug)]
pub struct Args {
    /// Scene directory.
    #[arg(long)]
    pub scene: PathBuf,
    /// Pixels in the batch.
    #[arg(long)]
    pub size: usize,
    /// Seed of the batch draw (as `[train] seed`).
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Which step's batch.
    #[arg(long, default_value_t = 0)]
    pub step: u64,
    /// Preset (for γ and the image downsampling).
    #[arg(long, default_value = "cpu", value_parser = ["tiny", "cpu", "paper"])]
    pub preset: String,
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
    let mut cfg = RunConfig::resolve(&a.preset, a.config.as_deref())?;
    if let Some(g) = a.gamma {
        cfg.model.gamma = g;
    }
    cfg.validate()?;
    anyhow::ensure!(a.size > 0, "--size must be > 0");
    let p = prepare(&a.scene, &cfg, true, &mut |m| eprintln!("{m}"))?;
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
