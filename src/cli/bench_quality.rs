//! `xscale bench-quality --scene DIR --out DIR [--minutes M] [--configs a,b] [--append |
//! --overwrite] [--list]`: run time
//! against error (`experiments/bench_quality.rs`).

use crate::experiments::bench_quality::{bench_quality, check_configs, replot, Existing, CONFIGS};
use std::path::PathBuf;
use std::process::ExitCode;

#[derive(clap::Args, Debug)]
pub struct Args {
    /// Scene directory (it must hold views out for evaluation).
    #[arg(long, required_unless_present_any = ["list", "replot"])]
    pub scene: Option<PathBuf>,
    /// Output folder: bench.csv, pareto.png.
    #[arg(long, required_unless_present = "list")]
    pub out: Option<PathBuf>,
    /// Training wall-clock budget per configuration, in minutes.
    #[arg(long, default_value_t = 1.0, value_parser = super::common::parse_positive_number, allow_negative_numbers = true)]
    pub minutes: f64,
    /// Comma-separated configurations, each once (default: all; see --list).
    #[arg(long, value_parser = parse_configs)]
    pub configs: Option<Configs>,
    /// List the configurations and exit.
    #[arg(long)]
    pub list: bool,
    /// Keep the rows of OUT/bench.csv from an earlier run and add this run's (a configuration
    /// run again replaces its earlier rows); the plot shows them all. The scene and --minutes
    /// must be those recorded in OUT/bench.json.
    #[arg(long, conflicts_with_all = ["overwrite", "replot"])]
    pub append: bool,
    /// Replace OUT/bench.csv if an earlier run left one (without --append or --overwrite, such
    /// a folder is refused).
    #[arg(long, conflicts_with = "replot")]
    pub overwrite: bool,
    /// Train nothing: redraw OUT/pareto.png from OUT/bench.csv (e.g. after merging runs).
    #[arg(long, conflicts_with_all = ["configs", "list"])]
    pub replot: bool,
}

/// The names `--configs` gave.
#[derive(Clone, Debug)]
pub struct Configs(pub Vec<String>);

/// `--configs a,b`: names of [`CONFIGS`] and `ulr`, each once. The whole list is parsed at once
/// so that a name listed twice is a usage error (exit 64) like an unknown one; a parser of one
/// name at a time cannot see it (it exited 2 from `bench_quality`).
fn parse_configs(s: &str) -> std::result::Result<Configs, String> {
    let names: Vec<String> = s.split(',').map(|n| n.trim().to_string()).collect();
    check_configs(&names).map_err(|e| format!("{e:#}"))?;
    Ok(Configs(names))
}

pub fn run(a: Args) -> anyhow::Result<ExitCode> {
    if a.list {
        for (n, d) in CONFIGS {
            println!("{n:<14} {d}");
        }
        println!(
            "{:<14} the no-learning ULR baseline (nothing trained: 0 s of training)",
            "ulr"
        );
        return Ok(ExitCode::SUCCESS);
    }
    let configs: Vec<String> = match &a.configs {
        Some(Configs(given)) => given.clone(),
        None => CONFIGS
            .iter()
            .map(|c| c.0.to_string())
            .chain(["ulr".to_string()])
            .collect(),
    };
    if a.replot {
        let out = a.out.unwrap();
        let name = a.scene.as_ref().unwrap_or(&out);
        let name = name
            .file_name()
            .map_or("scene".into(), |n| n.to_string_lossy().to_string());
        replot(&out, &name, &mut |m| eprintln!("{m}"))?;
        eprintln!("wrote {}", out.join("pareto.png").display());
        return Ok(ExitCode::SUCCESS);
    }
    let (scene, out) = (a.scene.unwrap(), a.out.unwrap());
    let existing = Existing::from_flags(a.append, a.overwrite);
    let flag = super::common::on_interrupt(
        "stopping the configuration in training at its next step; the rows measured are kept",
    );
    let stop = || flag.load(std::sync::atomic::Ordering::SeqCst);
    let (rows, stopped) = bench_quality(
        &scene,
        &out,
        &configs,
        a.minutes,
        existing,
        &mut |m| eprintln!("{m}"),
        &stop,
    )?;
    if rows.is_empty() {
        eprintln!(
            "no row measured: {} holds none",
            out.join("bench.csv").display()
        );
    } else {
        eprintln!(
            "wrote {} ({} rows) and {}",
            out.join("bench.csv").display(),
            rows.len(),
            out.join("pareto.png").display()
        );
    }
    if let Some(first) = stopped.first() {
        eprintln!(
            "interrupted during {first}; finish with the same options and --append --configs {}",
            stopped.join(",")
        );
        return Ok(ExitCode::from(super::common::EXIT_STOPPED));
    }
    Ok(ExitCode::SUCCESS)
}
