//! Command-line front end. Each subcommand's arguments and driver live in its own file here;
//! the work itself lives in the library modules.

use clap::{Parser, Subcommand};
use std::process::ExitCode;

pub mod ablate;
pub mod align_mesh;
pub mod batch;
pub mod bench_geometry;
pub mod bench_quality;
pub mod case;
pub mod cast;
pub mod common;
pub mod compare;
pub mod decimate;
pub mod dump;
pub mod eval;
pub mod init;
pub mod mesh_distance;
pub mod out_dir;
pub mod prepare;
pub mod render;
pub mod synth;
pub mod train;

#[derive(Parser, Debug)]
#[command(
    name = "xscale",
    version,
    about = "Hash featurized manifold (XScale-NVS) on the CPU"
)]
pub struct Cli {
    /// Worker threads (default: all cores). Results do not depend on it.
    #[arg(long, global = true)]
    pub threads: Option<usize>,
    #[command(subcommand)]
    pub command: Command,
}

#[derive(Subcommand, Debug)]
pub enum Command {
    /// Photos to a scene: COLMAP's CPU pipeline, then a mesh of its points (Delaunay graph cut).
    Prepare(prepare::Args),
    /// Generate a cross-scale synthetic scene with independent ground truth.
    Synth(synth::Args),
    /// Load a scene, cast its rays once and report what the sample cache holds.
    Cast(cast::Args),
    /// Write a freshly initialised checkpoint.
    Init(init::Args),
    /// Write a deterministic batch drawn from a scene's sample cache.
    Batch(batch::Args),
    /// Write every intermediate, the loss and every gradient for a checkpoint and a batch.
    Dump(dump::Args),
    /// Write a backend test case: checkpoint, batch, f64 oracle dump, tolerances and a manifest of
    /// every tensor a backend must produce.
    Case(case::Args),
    /// Compare two safetensors files tensor by tensor.
    Compare(compare::Args),
    /// Train on a scene.
    Train(train::Args),
    /// Render views or a camera path from a checkpoint.
    Render(render::Args),
    /// PSNR / SSIM on held-out views.
    Eval(eval::Args),
    /// Decimate a mesh to a fraction of its faces (quadric error metrics).
    Decimate(decimate::Args),
    /// Subdivide a mesh (midpoint, 1→4 per level).
    Subdivide(decimate::SubdivideArgs),
    /// Bring a mesh exported by nerfstudio (ns-export) into the scene's camera frame.
    AlignMesh(align_mesh::Args),
    /// Geometry error of a mesh against a reference surface (mean / RMS point-to-surface distance).
    MeshDistance(mesh_distance::Args),
    /// Train the paper's ablations and the vertex-feature baseline; write a comparison table.
    Ablate(ablate::Args),
    /// Run time against error: train configurations for a time budget, write bench.csv and pareto.png
    BenchQuality(bench_quality::Args),
    /// How much an imperfect mesh costs: proxies of a synthetic scene's true surface, trained with
    /// ξ (and mesh refinement) on and off; writes geometry.md/.csv and plots
    BenchGeometry(bench_geometry::Args),
}

/// The `xscale` program: parse `args` (the program name first), run the command, print an error
/// as `error: …` on stderr. Exit codes (docs/runs.md): 0 done, 1 a check failed, 2 an error at
/// run time (bad input, I/O, a refused run folder, divergence), 64 a usage error (unknown flag,
/// bad value: sysexits' EX_USAGE), 130 stopped by a signal with a checkpoint written, 3 stopped
/// by a signal with nothing saved. (`src/main.rs`, and `python -m xscale` in the Python package.)
pub fn main_with<I, T>(args: I) -> ExitCode
where
    I: IntoIterator<Item = T>,
    T: Into<std::ffi::OsString> + Clone,
{
    let cli = match Cli::try_parse_from(args) {
        Ok(c) => c,
        Err(e) => {
            let _ = e.print();
            // --help and --version are not errors.
            return ExitCode::from(if e.use_stderr() { 64 } else { 0 });
        }
    };
    match run(cli) {
        Ok(code) => code,
        Err(e) => {
            // Not `eprintln!`, which panics when stderr is a closed pipe.
            use std::io::Write;
            let mut err = std::io::stderr();
            let _ = writeln!(err, "error: {e:#}");
            if hit_file_size_limit(&e) {
                let _ = writeln!(
                    err,
                    "hint: the process has a file-size limit (`ulimit -f` shows it); raise it or write \
                     to a folder without one"
                );
            }
            ExitCode::from(2)
        }
    }
}

/// The number an [`ExitCode`] stands for (0–255; `ExitCode` itself does not say).
pub fn exit_code_value(code: ExitCode) -> u8 {
    (0..=u8::MAX)
        .find(|&k| ExitCode::from(k) == code)
        .unwrap_or(1)
}

/// EFBIG anywhere in the error: as an `io::Error` in the chain, or in the text where a writer
/// (the PNG encoder, safetensors) kept only the message, which ends in "(os error 27)" on Linux.
fn hit_file_size_limit(e: &anyhow::Error) -> bool {
    let kind = e.chain().any(|c| {
        c.downcast_ref::<std::io::Error>()
            .is_some_and(|io| io.kind() == std::io::ErrorKind::FileTooLarge)
    });
    #[cfg(unix)]
    let text = format!("{e:#}").contains(&format!("(os error {})", libc::EFBIG));
    #[cfg(not(unix))]
    let text = false;
    kind || text
}

/// Run a parsed command line. `Ok(code)` is the process exit code; errors exit with 2.
pub fn run(cli: Cli) -> anyhow::Result<ExitCode> {
    if let Some(n) = cli.threads {
        // More threads than cores only adds contention (results never depend on the count);
        // a huge count would spend minutes creating threads. 0 is rayon's "all cores".
        let cores = std::thread::available_parallelism().map_or(1, |c| c.get());
        let cap = 4 * cores;
        let n = if n > cap {
            eprintln!("--threads {n}: using {cap} (4 × the {cores} cores this machine has)");
            cap
        } else {
            n
        };
        rayon::ThreadPoolBuilder::new()
            .num_threads(n)
            .build_global()?;
    }
    // A failed command leaves no empty output folder behind (`out_dir.rs`).
    let (created, no_work) = output_folder(&cli.command);
    let created = created.map(|d| out_dir::Created::before(&d));
    let result = dispatch(cli.command);
    if let Some(c) = created {
        if !matches!(&result, Ok(code) if *code == ExitCode::SUCCESS) {
            c.clean_up(no_work);
        }
    }
    result
}

/// Files a command writes before its first result, removed with its folder when it fails.
type NoWork = &'static dyn Fn(&std::path::Path) -> Vec<std::path::PathBuf>;

/// The folder a command writes its results into (for a file, the folder that holds it).
fn output_folder(c: &Command) -> (Option<std::path::PathBuf>, NoWork) {
    let none: NoWork = &|_| Vec::new();
    let parent = |p: &std::path::Path| p.parent().map(|d| d.to_path_buf());
    match c {
        Command::Train(a) => (Some(a.out.clone()), none),
        Command::Synth(a) => (Some(a.out.clone()), none),
        Command::Render(a) => (Some(a.out.clone()), none),
        Command::Ablate(a) => (Some(a.out.clone()), none),
        Command::BenchGeometry(a) => (Some(a.out.clone()), none),
        Command::BenchQuality(a) if !a.replot => (a.out.clone(), &out_dir::bench_quality_no_work),
        Command::Eval(a) => (a.out.clone(), none),
        Command::Init(a) => (parent(&a.out), none),
        Command::Decimate(a) => (parent(&a.out), none),
        Command::Subdivide(a) => (parent(&a.out), none),
        Command::AlignMesh(a) => (parent(&a.out), none),
        _ => (None, none),
    }
}

fn dispatch(command: Command) -> anyhow::Result<ExitCode> {
    match command {
        Command::Prepare(a) => prepare::run(a),
        Command::Synth(a) => synth::run(a),
        Command::Cast(a) => cast::run(a),
        Command::Init(a) => init::run(a),
        Command::Batch(a) => batch::run(a),
        Command::Dump(a) => dump::run(a),
        Command::Case(a) => case::run(a),
        Command::Compare(a) => compare::run(a),
        Command::Train(a) => train::run(a),
        Command::Render(a) => render::run(a),
        Command::Eval(a) => eval::run(a),
        Command::Decimate(a) => decimate::run(a),
        Command::Subdivide(a) => decimate::run_subdivide(a),
        Command::MeshDistance(a) => mesh_distance::run(a),
        Command::AlignMesh(a) => align_mesh::run(a),
        Command::Ablate(a) => ablate::run(a),
        Command::BenchQuality(a) => bench_quality::run(a),
        Command::BenchGeometry(a) => bench_geometry::run(a),
    }
}
