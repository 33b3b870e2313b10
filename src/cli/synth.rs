//! `xscale synth`: generate a cross-scale synthetic scene with independent ground truth
//! (see `src/synth/`).

use crate::synth::{self, Preset};
use anyhow::bail;
use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::sync::atomic::{AtomicBool, Ordering};

#[derive(clap::Args, Debug)]
pub struct Args {
    /// Parameter set: `tiny` (8 views, 64×48), `small` (40 views, 200×150) or `large` (104
    /// views, 1024×768: 82 Mpixels for memory/throughput benchmarks, ~110 MB of PNG).
    #[arg(long, value_enum, default_value = "tiny")]
    pub preset: Preset,
    /// Seed of every random choice (terrain, buildings, textures, cameras, proxy error).
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// Output scene directory: new, empty, or holding this same scene (same preset and seed,
    /// written again). Any other folder is refused unless --overwrite.
    #[arg(long)]
    pub out: PathBuf,
    /// Write into a folder holding another scene or other files: what synth writes there
    /// (synth.toml, scene.toml, mesh.ply, mesh.obj, truth.ply, images/, images_1/, cams_1/,
    /// sparse/, transforms.json) is removed first; nothing else is.
    #[arg(long)]
    pub overwrite: bool,
    /// Also write the fine true surface as `truth.ply` (large).
    #[arg(long)]
    pub write_truth: bool,
    /// The cameras' lens: `pinhole`, or `opencv` (the same views rendered through a phone-like
    /// barrel distortion and written as COLMAP OPENCV cameras).
    #[arg(long, value_enum, default_value = "pinhole")]
    pub lens: synth::Lens,
}

/// Every file and folder `xscale synth` writes into its output folder.
pub const SYNTH_FILES: [&str; 10] = [
    "synth.toml",
    "scene.toml",
    "mesh.ply",
    "mesh.obj",
    "truth.ply",
    "images",
    "images_1",
    "cams_1",
    "sparse",
    "transforms.json",
];

/// Whether synth may write into `args.out`: a new or empty folder, or one holding the scene
/// of the same preset and seed (written again, the same bytes), may; another synthetic scene
/// (runs trained on it would no longer match it) or a folder of other files (a real scene's
/// `images/` and `sparse/` would be overwritten) is refused unless `--overwrite`, which
/// removes what synth writes first (so no view of a larger earlier scene is left behind).
fn check_out(args: &Args) -> anyhow::Result<()> {
    let dir = &args.out;
    let Ok(mut entries) = std::fs::read_dir(dir) else {
        return Ok(()); // created
    };
    if entries.next().is_none() {
        return Ok(());
    }
    let record = dir.join("synth.toml");
    let earlier = std::fs::read_to_string(&record)
        .ok()
        .and_then(|t| t.parse::<toml::Table>().ok())
        .filter(|t| t.get("generator").and_then(|g| g.as_str()) == Some("xscale synth"));
    let what = match &earlier {
        Some(t) => {
            let preset = t.get("preset").and_then(|p| p.as_str()).unwrap_or("?");
            let seed = t.get("seed").map_or("?".to_string(), |s| s.to_string());
            let lens = t
                .get("params")
                .and_then(|p| p.get("lens"))
                .and_then(|l| l.as_str())
                .unwrap_or("pinhole");
            if preset == args.preset.name()
                && seed == args.seed.to_string()
                && lens == args.lens.name()
            {
                return Ok(()); // the same scene, written again
            }
            format!(
                "holds the synthetic scene of --preset {preset} --seed {seed} --lens {lens} ({}; runs trained on it would no longer match it)",
                record.display()
            )
        }
        None => "is not empty and holds no `xscale synth` scene (no synth.toml); synth writes images/, sparse/, mesh.ply, … there".to_string(),
    };
    if !args.overwrite {
        bail!(
            "{}: {what}. Choose a new or empty folder, or add --overwrite to replace what synth writes there",
            dir.display()
        );
    }
    crate::run::run_dir::remove_listed(dir, &SYNTH_FILES)
}

/// Seconds between progress lines (the last view is always said).
const PROGRESS_EVERY_S: f64 = 2.0;

/// Views written when a signal stopped `xscale synth`, of how many.
#[derive(Debug)]
struct Stopped(usize, usize);

impl std::fmt::Display for Stopped {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "stopped after {} of {} views", self.0, self.1)
    }
}

impl std::error::Error for Stopped {}

/// [`synth::generate`]'s `progress` for a command: `rendered I of N views (T s)` through `say` at least
/// every [`PROGRESS_EVERY_S`] and after the last view, and, once `stop` is set (the interrupt
/// flag), an end ([`Stopped`]) after the view just written — not after the last, when only the
/// camera files are left to write.
pub(super) fn progress_until<'a>(
    stop: &'a AtomicBool,
    say: &'a mut dyn FnMut(String),
) -> impl FnMut(usize, usize) -> anyhow::Result<()> + 'a {
    let t0 = std::time::Instant::now();
    let mut said = 0.0;
    move |i, n| {
        let t = t0.elapsed().as_secs_f64();
        if t - said >= PROGRESS_EVERY_S || i + 1 == n {
            say(format!("rendered {} of {n} views ({t:.1} s)", i + 1));
            said = t;
        }
        if stop.load(Ordering::SeqCst) && i + 1 < n {
            return Err(Stopped(i + 1, n).into());
        }
        Ok(())
    }
}

/// What a generation into `dir` stopped by [`progress_until`] left there and what to do, for the
/// user; `None` when `e` is another error.
pub(super) fn stopped_message(e: &anyhow::Error, dir: &Path) -> Option<String> {
    let s = e.downcast_ref::<Stopped>()?;
    Some(format!(
        "interrupted: {s}; {} holds an unfinished scene (synth.toml, the meshes and {} of the {} images; the camera files come last): run the same command again to finish it (it writes the same scene, byte for byte)",
        dir.display(),
        s.0,
        s.1
    ))
}

pub fn run(args: Args) -> anyhow::Result<ExitCode> {
    check_out(&args)?;
    let stop = super::common::on_interrupt("stopping after the view being rendered");
    let t0 = std::time::Instant::now();
    let generated = synth::generate(
        args.preset,
        args.seed,
        args.lens,
        &args.out,
        args.write_truth,
        &mut progress_until(stop, &mut |m| eprintln!("{m}")),
    );
    let summary = match generated {
        Err(e) => match stopped_message(&e, &args.out) {
            Some(m) => {
                eprintln!("{m}");
                return Ok(ExitCode::from(super::common::EXIT_STOPPED_UNSAVED));
            }
            None => return Err(e),
        },
        Ok(s) => s,
    };
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
