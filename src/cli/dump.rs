//! `xscale dump --checkpoint FILE --batch FILE --out FILE [--precision f64|f32]`: evaluate a
//! checkpoint on a batch and write every intermediate, the loss and every gradient (SPEC §6) —
//! the golden file a backend compares against with `xscale compare`.

use crate::model::checkpoint::{dump, Checkpoint};
use crate::model::Batch;
use std::path::PathBuf;
use std::process::ExitCode;

#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum Precision {
    F64,
    F32,
}

#[derive(clap::Args, Debug)]
pub struct Args {
    /// Checkpoint (safetensors) written by `xscale init` or `xscale train`.
    #[arg(long)]
    pub checkpoint: PathBuf,
    /// Batch (safetensors) written by `xscale batch`.
    #[arg(long)]
    pub batch: PathBuf,
    /// Output dump (safetensors; written atomically).
    #[arg(long)]
    pub out: PathBuf,
    /// Instantiate the model in this precision (the dump's float dtype).
    #[arg(long, value_enum, default_value = "f64")]
    pub precision: Precision,
}

pub fn run(args: Args) -> anyhow::Result<ExitCode> {
    let ckpt = Checkpoint::load(&args.checkpoint)?;
    let batch = Batch::load(&args.batch)?;
    let file = match args.precision {
        Precision::F64 => dump::<f64>(&ckpt, &batch)?,
        Precision::F32 => dump::<f32>(&ckpt, &batch)?,
    };
    file.write_atomic(&args.out)?;
    let loss = file.get("loss")?.to_f64()?[0];
    eprintln!(
        "wrote {} ({} tensors, {} pixels, loss {loss:.9e}, {:?})",
        args.out.display(),
        file.tensors.len(),
        batch.n_pixels(),
        args.precision
    );
    Ok(ExitCode::SUCCESS)
}
