//! `xscale bench-geometry (--scene DIR | --scene-preset P) --out DIR [--steps N] [--rms LIST]
//! [--decimate R] [--deform on,off] [--refine off,on]`: how much an imperfect mesh costs, and what
//! refining it wins back (`experiments/bench_geometry.rs`, docs/geometry.md).

use super::common::RunArgs;
use crate::experiments::bench_geometry::{
    bench_geometry, check_proxies, GeometryOptions, ProxySpec, DISTANCE_SAMPLES,
};
use crate::experiments::variant::Runs;
use crate::synth::Preset;
use anyhow::{bail, Context, Result};
use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::sync::atomic::AtomicBool;

#[derive(clap::Args, Debug)]
pub struct Args {
    /// A scene directory holding `truth.ply` (the true surface; `xscale synth --write-truth`).
    #[arg(
        long,
        conflicts_with = "scene_preset",
        required_unless_present = "scene_preset"
    )]
    pub scene: Option<PathBuf>,
    /// Generate `xscale synth --preset P --write-truth` into OUT/scene (reused when it exists).
    #[arg(long, value_enum)]
    pub scene_preset: Option<Preset>,
    /// Seed of the generated scene.
    #[arg(long, default_value_t = 1)]
    pub synth_seed: u64,
    /// Output folder: meshes/, runs/, geometry.{md,csv,json}, geometry-{psnr,ssim}.png.
    #[arg(long)]
    pub out: PathBuf,
    /// Training configuration shared by every run (`--steps` = steps per run).
    #[command(flatten)]
    pub run: RunArgs,
    /// RMS displacements of the proxies, in % of the bounding-box diagonal (0 = the exact mesh;
    /// each value ≥ 0, once).
    #[arg(long, value_delimiter = ',', num_args = 1.., default_values_t = [0.0, 0.1, 0.3, 1.0], value_parser = super::common::parse_non_negative, allow_negative_numbers = true)]
    pub rms: Vec<f64>,
    /// Fraction of faces kept by the decimated proxy, in (0, 1] (0: no decimated proxy).
    #[arg(long, default_value_t = 0.1, value_parser = super::common::parse_fraction_or_zero, allow_negative_numbers = true)]
    pub decimate: f64,
    /// ξ settings to train each proxy with.
    #[arg(long, value_delimiter = ',', num_args = 1.., default_values_t = [Switch::On, Switch::Off])]
    pub deform: Vec<Switch>,
    /// Mesh refinement settings to train each proxy with (`on` = `[model.refine] enabled`, with
    /// the --config file's `[model.refine]` values, else the defaults).
    #[arg(long, value_delimiter = ',', num_args = 1.., default_values_t = [Switch::Off])]
    pub refine: Vec<Switch>,
    /// Area samples per geometry-error measurement.
    #[arg(long, default_value_t = DISTANCE_SAMPLES, value_parser = super::common::parse_positive)]
    pub samples: usize,
    /// Only errors and the final table.
    #[arg(long, short)]
    pub quiet: bool,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum Switch {
    On,
    Off,
}

impl std::fmt::Display for Switch {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            Switch::On => "on",
            Switch::Off => "off",
        })
    }
}

/// OUT/scene for `--scene-preset`: generated (with `truth.ply`) unless the whole scene of the
/// same preset and seed is there. An unfinished one (a generation stopped by a signal or killed:
/// `scene.toml` is written last) is generated again, which finishes it with the same bytes.
/// `stop` (the interrupt flag) stops the generation between views
/// ([`super::synth::progress_until`]).
fn synth_scene(
    preset: Preset,
    seed: u64,
    dir: &Path,
    stop: &AtomicBool,
    say: &mut dyn FnMut(String),
) -> Result<()> {
    let record = dir.join("synth.toml");
    if let (Ok(text), true) = (
        std::fs::read_to_string(&record),
        dir.join("truth.ply").is_file(),
    ) {
        let v: toml::Value = toml::from_str(&text)
            .with_context(|| format!("{}: not valid TOML", record.display()))?;
        let same = v.get("preset").and_then(|p| p.as_str()) == Some(preset.name())
            && v.get("seed").and_then(|s| s.as_integer()) == Some(seed as i64);
        if !same {
            bail!(
                "{}: holds another synthetic scene (not preset {} seed {seed}); choose another --out",
                dir.display(),
                preset.name()
            );
        }
        if dir.join("scene.toml").is_file() {
            say(format!("scene: reusing {}", dir.display()));
            return Ok(());
        }
    }
    say(format!(
        "scene: xscale synth --preset {} --seed {seed} --write-truth → {}",
        preset.name(),
        dir.display()
    ));
    crate::synth::generate(
        preset,
        seed,
        crate::synth::Lens::Pinhole,
        dir,
        true,
        &mut super::synth::progress_until(stop, say),
    )?;
    Ok(())
}

pub fn run(a: Args) -> Result<ExitCode> {
    let mut say = |m: String| {
        if !a.quiet {
            eprintln!("{m}");
        }
    };
    let base = a.run.resolve()?;
    let mut proxies: Vec<ProxySpec> = a.rms.iter().map(|&p| ProxySpec::Displaced(p)).collect();
    if a.decimate > 0.0 {
        proxies.push(ProxySpec::Decimated(a.decimate));
    }
    // Before the scene is synthesised or anything built: a proxy listed twice.
    check_proxies(&proxies)?;
    // Before the scene is synthesised, so that a signal stops that too (between views).
    let interrupt = super::common::on_interrupt(
        "stopping: the scene's generation after the view being rendered, a run in training at its next step with a checkpoint",
    );
    let dedup = |v: &[Switch]| {
        let mut out: Vec<bool> = Vec::new();
        for s in v {
            let b = *s == Switch::On;
            if !out.contains(&b) {
                out.push(b);
            }
        }
        out
    };
    let scene = match (&a.scene, a.scene_preset) {
        (Some(s), _) => s.clone(),
        (None, Some(p)) => {
            let dir = a.out.join("scene");
            if let Err(e) = synth_scene(p, a.synth_seed, &dir, interrupt, &mut say) {
                let Some(m) = super::synth::stopped_message(&e, &dir) else {
                    return Err(e);
                };
                eprintln!("{m}");
                return Ok(ExitCode::from(super::common::EXIT_STOPPED_UNSAVED));
            }
            dir
        }
        (None, None) => bail!("give --scene DIR or --scene-preset P"),
    };
    let opts = GeometryOptions {
        runs: Runs {
            base,
            quiet: a.quiet,
            interrupt: Some(interrupt),
        },
        proxies,
        deform: dedup(&a.deform),
        refine: dedup(&a.refine),
        samples: a.samples,
    };
    let Some(rep) = bench_geometry(&scene, &a.out, &opts, &mut say)? else {
        eprintln!(
            "stopped; run the same command again to continue (finished runs are reused, the stopped one continues from its checkpoint)"
        );
        return Ok(ExitCode::from(super::common::EXIT_STOPPED));
    };
    print!("{}", crate::experiments::bench_geometry::markdown(&rep));
    eprintln!(
        "wrote {}, geometry.csv, geometry.json, geometry-psnr.png, geometry-ssim.png",
        a.out.join("geometry.md").display()
    );
    Ok(ExitCode::SUCCESS)
}
