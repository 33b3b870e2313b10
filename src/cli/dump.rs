//! `xscale dump --checkpoint FILE --batch FILE --out FILE [--precision f64|f32]`: evaluate a
//! checkpoint on a batch and write every intermediate, the loss and every gradient (SPEC §6) —
//! the golden file a backend compares against with `xscale compare`.

use crate::io::tensors::TensorFile;
use crate::model::checkpoint::{dump_with, Checkpoint};
use crate::model::Batch;
use anyhow::Context;
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
    /// f64 dumps: pixels whose relative distance to a ReLU or L1 kink is at most this are kink
    /// pixels, and the dump carries how far a correct backend's gradients may be off there
    /// (`kink.*` tensors, docs/oracle.md §7); 0 writes no kink tensors. Default 2^-16
    /// (1.52587890625e-5); in [0, 1) (a margin is at most 1). Not for f32 dumps.
    #[arg(long, value_parser = parse_kink_threshold, allow_negative_numbers = true)]
    pub kink_threshold: Option<f64>,
}

/// `--kink-threshold`: a number in [0, 1); anything else is a usage error (exit 64).
fn parse_kink_threshold(s: &str) -> Result<f64, String> {
    match s.trim().parse::<f64>() {
        Ok(t) if (0.0..1.0).contains(&t) => Ok(t),
        _ => Err(
            "must be a number in [0, 1) (0 = no kink analysis; a relative margin is at most 1, \
             so 1 would make every unit a kink)"
                .into(),
        ),
    }
}

pub fn run(args: Args) -> anyhow::Result<ExitCode> {
    crate::io::atomic::writable_folder(&args.out)?;
    crate::io::atomic::not_an_input(
        &args.out,
        "--out",
        &[
            ("the checkpoint (--checkpoint)", &args.checkpoint),
            ("the batch (--batch)", &args.batch),
        ],
    )?;
    if args.kink_threshold.is_some() {
        anyhow::ensure!(
            args.precision == Precision::F64,
            "--kink-threshold: the kink analysis is part of the f64 oracle dump; an f32 dump has none \
             (drop the option, or use --precision f64)"
        );
    }
    let kink_threshold = args
        .kink_threshold
        .unwrap_or(crate::model::kink::DEFAULT_THRESHOLD);
    let ckpt = Checkpoint::load(&args.checkpoint)?;
    // The batch's size from its header and valid flags (N·S bytes), to refuse a dump that cannot
    // fit before the batch is read and evaluated.
    let valid = TensorFile::read_only(&args.batch, |n| n == "batch.valid")?;
    if let Some(&[n, s]) = valid.tensors.get("batch.valid").map(|t| &t.shape[..]) {
        check_dump_memory(&ckpt, n, s, args.precision)?;
    }
    let batch = Batch::load(&args.batch)?;
    // What does not fit this model (a view without an appearance row, a missing footprint) is
    // the batch file's error, named like its other errors.
    let label = || args.batch.display().to_string();
    ckpt.model.check_batch(&batch).with_context(label)?;
    let file = match args.precision {
        Precision::F64 => dump_with::<f64>(
            &ckpt,
            &batch,
            (kink_threshold > 0.0).then_some(kink_threshold),
        )?,
        Precision::F32 => dump_with::<f32>(&ckpt, &batch, None)?,
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
    if let Ok(k) = file.get("kink.pixels") {
        eprintln!(
            "kink pixels: {} (relative margin <= {:e})",
            k.numel(),
            kink_threshold
        );
    }
    Ok(ExitCode::SUCCESS)
}

/// [`crate::train::memory::check_dump`] for `ckpt` on a batch of `n` pixels × `s` sub-samples.
fn check_dump_memory(
    ckpt: &Checkpoint,
    n: usize,
    s: usize,
    precision: Precision,
) -> anyhow::Result<()> {
    let m = &ckpt.model;
    let deform = &m.cfg.deform;
    let features = m.feat_dim()
        + if deform.enabled {
            (deform.grid.levels * deform.grid.features + deform.hidden) as usize + m.feat_dim()
        } else {
            0
        };
    crate::train::memory::check_dump(n, s, features, m.layout.total, precision == Precision::F64)
}
