//! `xscale synth`: generate a cross-scale synthetic scene with independent ground truth
//! (see `src/synth/`).

use crate::synth::{self, Preset};
use std::path::PathBuf;
use std::process::ExitCode;

#[derive(clap::Args, Debug)]
pub struct Args {
    /// Parameter set: `tiny` (8 views, 64×48), `small` (40 views, 200×150) or `large` (104
    /// views, 1024×768: 82 Mpixels for memory/throughput benchmarks, ~110 MB of PNG).
    #[arg(long, value_enum, default_value = "tiny")]
    pub preset: Preset,
    /// Seed of every random choice (terrain, buildings, textures, cameras, proxy error).
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// Output scene directory (created if needed; existing files are overwritten).
    #[arg(long)]
    pub out: PathBuf,
    /// Also write the fine true surface as `truth.ply` (large).
    #[arg(long)]
    pub write_truth: bool,
}

/// Build, render and write scene (`preset`, `seed`) into `dir` (`truth.ply` too with
/// `write_truth`); `progress(i, n)` after view i of n is written.
pub fn generate(
    preset: Preset,
    seed: u64,
    dir: &std::path::Path,
    write_truth: bool,
    progress: &mut dyn FnMut(usize, usize),
) -> anyhow::Result<synth::Summary> {
    let s = synth::build(preset, seed);
    let summary = s.summary();
    let n = s.views.len();
    let sh = s.shader();
    let spp = s.params.spp_side;
    // One view rendered and written at a time (the `large` preset's 104 views would hold 1 GB).
    synth::output::write_with(
        &s,
        &mut |i| synth::render::render(&sh, &s.views[i].camera, spp),
        &summary,
        dir,
        write_truth,
        &mut |i| progress(i, n),
    )?;
    Ok(summary)
}

pub fn run(args: Args) -> anyhow::Result<ExitCode> {
    let t0 = std::time::Instant::now();
    let summary = generate(
        args.preset,
        args.seed,
        &args.out,
        args.write_truth,
        &mut |i, n| {
            if n > 40 && (i + 1) % 10 == 0 {
                eprintln!("rendered {} of {n} views", i + 1);
            }
        },
    )?;
    println!(
        "synth: preset {} seed {} → {} ({:.1} s)",
        args.preset.name(),
        args.seed,
        args.out.display(),
        t0.elapsed().as_secs_f64()
    );
    println!("{summary}");
    Ok(ExitCode::SUCCESS)
}
