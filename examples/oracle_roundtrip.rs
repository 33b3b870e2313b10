//! The oracle loop a GPU backend runs, with the library: load a checkpoint and a batch, run the
//! forward and the backward pass, write a dump, and compare it with a reference dump under a
//! tolerance file (docs/oracle.md).
//!
//!     cargo run --release --example oracle_roundtrip [CASE_DIR] [OUT]
//!
//! CASE_DIR defaults to `fixtures/golden/tiny-f64-linear` (a checkpoint, a batch, the independent
//! PyTorch float64 dump `ref_f64.safetensors`; the tolerances are `fixtures/golden/tolerances-f64.toml`). A backend replaces step
//! 2 with its own kernels and writes the same tensor names.

use anyhow::Result;
use std::path::{Path, PathBuf};
use xscale::io::compare::{compare_files, Report, Tolerances};
use xscale::model::checkpoint::{dump, Checkpoint};
use xscale::model::params::Grads;
use xscale::model::Batch;

/// Run the loop on `case` and write the dump to `out`; returns the comparison report.
pub fn run(case: &Path, out: &Path) -> Result<Report> {
    // 1. The inputs: a checkpoint (model config + parameters) and a batch (positions, validity,
    //    directions, views, targets of N pixels × γ² sub-samples).
    let ckpt = Checkpoint::load(case.join("checkpoint.safetensors"))?;
    let batch = Batch::load(case.join("batch.safetensors"))?;
    // 2. Forward and backward in f64 (what `dump` does; shown here step by step).
    let params: Vec<f64> = ckpt.params.iter().map(|&v| v as f64).collect();
    let fwd = ckpt.model.forward(&params, &batch)?;
    let mut grads = Grads::<f64>::new(&ckpt.model.layout);
    ckpt.model.backward(&params, &batch, &fwd, &mut grads);
    // 3. Every intermediate, the loss and every gradient under their names (docs/spec.md §6).
    let file = dump::<f64>(&ckpt, &batch)?;
    file.write_atomic(out)?;
    // 4. Compare with the reference under the case's tolerance file (exit code 0/1/2 in the CLI).
    //    (The golden cases share `fixtures/golden/tolerances-f64.toml`; a case may carry its own.)
    let own = case.join("tolerances-f64.toml");
    let tol_path = if own.is_file() {
        own
    } else {
        case.parent().unwrap_or(case).join("tolerances-f64.toml")
    };
    let tol = Tolerances::read(tol_path)?;
    compare_files(case.join("ref_f64.safetensors"), out, &tol)
}

#[allow(dead_code)] // not called when the tests include this file
fn main() -> Result<()> {
    let args: Vec<String> = std::env::args().collect();
    let case = PathBuf::from(args.get(1).map_or("fixtures/golden/tiny-f64-linear", |s| s));
    let out = args.get(2).map_or_else(
        || std::env::temp_dir().join("xscale-oracle-roundtrip.safetensors"),
        PathBuf::from,
    );
    let report = run(&case, &out)?;
    print!("{}", report.to_table());
    std::process::exit(report.exit_code() as i32);
}
