//! `xscale init --scene DIR --preset P --seed S --out FILE`: a freshly initialised checkpoint for a
//! scene (appearance rows = its training views, hash levels dropped as SPEC §8 says).

use super::common::resolve_config;
use crate::train::setup::prepare;
use std::path::PathBuf;
use std::process::ExitCode;

#[derive(clap::Args, Debug)]
pub struct Args {
    /// Scene directory (its mesh and views size the model: normalisation, level range,
    /// appearance codes).
    #[arg(long)]
    pub scene: PathBuf,
    /// Preset: tiny, cpu or paper [default: cpu]; must agree with a `preset` the --config file
    /// gives.
    #[arg(long, value_parser = ["tiny", "cpu", "paper"])]
    pub preset: Option<String>,
    /// TOML overrides (as `xscale train --config`).
    #[arg(long)]
    pub config: Option<PathBuf>,
    /// Seed of the parameter initialisation.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Checkpoint file to write (safetensors).
    #[arg(long)]
    pub out: PathBuf,
}

pub fn run(a: Args) -> anyhow::Result<ExitCode> {
    crate::io::atomic::writable_folder(&a.out)?;
    let mut cfg = resolve_config(a.preset.as_deref(), a.config.as_deref())?;
    cfg.train.seed = a.seed;
    let p = prepare(&a.scene, &cfg, false, &mut |m| eprintln!("{m}"))?;
    let (cfg, ck) = p.init_model(cfg, &mut |m| eprintln!("{m}"))?;
    let mut f = ck.to_tensor_file()?;
    f.set_meta("run_config", cfg.to_toml());
    f.write_atomic(&a.out)?;
    eprintln!(
        "wrote {} ({} parameters)",
        a.out.display(),
        ck.model.layout.total
    );
    Ok(ExitCode::SUCCESS)
}
