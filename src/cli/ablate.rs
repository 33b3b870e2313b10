//! `xscale ablate --scene DIR --out DIR [--preset P] [--config FILE] [--steps N | --minutes M]
//! [--variants LIST] [--ratio R] [--subdivide K] [--append | --overwrite]`: train the paper's ablations (Table 4: without
//! deformation, without multisampling; Table 5: decimated mesh) and the vertex-feature baseline
//! (Fig. 2b) on one scene with one step budget, score the held-out views and write
//! `DIR/ablation.md` (a table like the paper's) and `DIR/ablation.json`. See
//! `src/experiments/ablate.rs` for the variants and how the baseline's feature width is chosen.

use super::common::RunArgs;
use crate::experiments::ablate::{run_ablation, AblateOptions, Variant};
use crate::experiments::variant::Runs;
use crate::run::run_dir::Existing;
use anyhow::Result;
use std::path::PathBuf;
use std::process::ExitCode;

#[derive(clap::Args, Debug)]
pub struct Args {
    /// Scene directory.
    #[arg(long)]
    pub scene: PathBuf,
    /// Output directory: one run folder per variant, meshes/, ablation.md, ablation.json.
    #[arg(long)]
    pub out: PathBuf,
    /// Base configuration shared by every variant (`--steps` = training steps per variant).
    #[command(flatten)]
    pub run: RunArgs,
    /// Instead of --steps: pick the step count so the full model trains about this many minutes
    /// (from a 20-step timing probe); every variant then uses that step count.
    #[arg(
        long,
        conflicts_with = "steps",
        value_parser = super::common::parse_positive_number,
        allow_negative_numbers = true
    )]
    pub minutes: Option<f64>,
    /// Comma-separated subset of the variants, run in table order (default: all).
    #[arg(long, value_enum, value_delimiter = ',', default_values_t = Variant::ALL)]
    pub variants: Vec<Variant>,
    /// Fraction of faces kept by the decimated-mesh variant [default: 0.1; with --append, the
    /// earlier ablation's, which a different value cannot change].
    #[arg(long, value_parser = super::common::parse_fraction, allow_negative_numbers = true)]
    pub ratio: Option<f64>,
    /// Subdivision levels of the vertex_subdiv variant, at most 6 (default: automatic).
    #[arg(long, value_parser = super::common::parse_levels)]
    pub subdivide: Option<u32>,
    /// Keep the earlier ablation in OUT (its variants not run again stay in the table; a variant
    /// run again replaces its result, and one stopped by Ctrl-C continues from its checkpoint).
    /// The step count, --ratio and base configuration must be the same.
    #[arg(long, conflicts_with = "overwrite")]
    pub append: bool,
    /// Replace the earlier ablation in OUT (without --append or --overwrite, a folder holding
    /// one is refused).
    #[arg(long)]
    pub overwrite: bool,
    /// Only errors and the final table.
    #[arg(long, short)]
    pub quiet: bool,
}

pub fn run(a: Args) -> Result<ExitCode> {
    let base = a.run.resolve()?;
    // Table order whatever order they were given in, each once.
    let variants: Vec<Variant> = Variant::ALL
        .into_iter()
        .filter(|v| a.variants.contains(v))
        .collect();
    let opts = AblateOptions {
        runs: Runs {
            base,
            interrupt: Some(super::common::on_interrupt(
                "stopping the variant in training at its next step; the finished ones are kept",
            )),
            quiet: a.quiet,
        },
        variants,
        ratio: a.ratio,
        subdivide: a.subdivide,
        minutes: a.minutes,
        steps_given: a.run.steps.is_some(),
        existing: Existing::from_flags(a.append, a.overwrite),
    };
    let rep = run_ablation(&a.scene, &a.out, &opts)?;
    if let Some(first) = rep.stopped.first() {
        let rest: Vec<&str> = rep.stopped.iter().map(|v| v.name()).collect();
        let done: Vec<&str> = rep.results.iter().map(|r| r.name.name()).collect();
        let steps = match a.minutes {
            Some(_) => format!(" --steps {} (in place of --minutes)", rep.steps),
            None => String::new(),
        };
        let kept = if done.is_empty() {
            "no variant had finished".to_string()
        } else {
            format!(
                "{} holds {}",
                a.out.join("ablation.md").display(),
                done.join(", ")
            )
        };
        eprintln!(
            "interrupted during {}: {kept}; finish with the same options and --append --variants {}{steps}",
            first.name(),
            rest.join(",")
        );
        return Ok(ExitCode::from(super::common::EXIT_STOPPED));
    }
    print!("{}", crate::experiments::ablate::markdown(&rep));
    eprintln!(
        "wrote {} and {}",
        a.out.join("ablation.md").display(),
        a.out.join("ablation.json").display()
    );
    Ok(ExitCode::SUCCESS)
}
