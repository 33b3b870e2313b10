//! `xscale compare A B`: tensor-by-tensor comparison of two safetensors files (SPEC §6).
//! Definitions of the errors and of the tolerance file: `io::compare`.
//! Exit code 0 = all within limits, 1 = a limit exceeded, 2 = bad input. With no tolerance file and
//! no `--max-*` limit the comparison is exact (strict); a NaN fails unless `--allow-nan`.

use crate::io::compare::{compare_files, parse_limit, report_json, Rule, Tolerances};
use anyhow::Context;
use std::path::PathBuf;
use std::process::ExitCode;

#[derive(clap::Args, Debug)]
pub struct Args {
    /// First file (e.g. the reference / oracle dump).
    pub a: PathBuf,
    /// Second file (e.g. the backend's dump).
    pub b: PathBuf,
    /// Tolerance rules: a built-in set (`f32`, `f64`, `fp16`, `grid-exact`, `exact`; docs/oracle.md
    /// §7) or a TOML file (`[[rule]] pattern = "fwd.*"`, `max_abs`, `max_rel`, `max_ulp`,
    /// `max_rel_peak`, `reason`, `required`, `ignore`; `[default]`; `strict`). A file named like a
    /// set is given as `./f32`.
    #[arg(long)]
    pub tolerances: Option<String>,
    /// Also write the report as JSON to this file.
    #[arg(long)]
    pub json: Option<PathBuf>,
    /// Strict: tensors without a rule must be exactly equal; tensors in only one file are errors.
    #[arg(long)]
    pub strict: bool,
    /// Default rule's abs limit (replaces the file's `[default]` when any --max-* is given; the
    /// float limits take a number >= 0).
    #[arg(long, value_parser = parse_limit, allow_negative_numbers = true)]
    pub max_abs: Option<f64>,
    /// Default rule's rel limit.
    #[arg(long, value_parser = parse_limit, allow_negative_numbers = true)]
    pub max_rel: Option<f64>,
    /// Default rule's ULP limit.
    #[arg(long)]
    pub max_ulp: Option<u64>,
    /// Default rule's limit on abs error / the tensor's largest |value|.
    #[arg(long, value_parser = parse_limit, allow_negative_numbers = true)]
    pub max_rel_peak: Option<f64>,
    /// Accept NaN where both files have it (by default any NaN fails its tensor).
    #[arg(long)]
    pub allow_nan: bool,
    /// Ignore the `kink.slack.*` tensors of an f64 dump: elements a correct backend may get wrong
    /// at a ReLU or L1 kink then fail like any other (docs/oracle.md §7).
    #[arg(long)]
    pub no_kink_slack: bool,
    /// Print only failures and the summary.
    #[arg(long, short)]
    pub quiet: bool,
}

pub fn run(args: Args) -> anyhow::Result<ExitCode> {
    let mut tol = match &args.tolerances {
        Some(spec) => Tolerances::resolve(spec)?,
        None => Tolerances::default(),
    };
    let limits_given = args.max_abs.is_some()
        || args.max_rel.is_some()
        || args.max_ulp.is_some()
        || args.max_rel_peak.is_some();
    if args.strict {
        tol.strict = true;
    }
    if args.allow_nan {
        tol.allow_nan = true;
    }
    if args.no_kink_slack {
        tol.kink_slack = false;
    }
    if args.tolerances.is_none() && !limits_given {
        // Nothing said: the strictest rule. Every tensor must be exactly equal, and a tensor in
        // only one file is an error (a comparison must not pass by default).
        tol.strict = true;
        if !args.quiet {
            println!("no --tolerances or --max-* given: exact comparison (strict)");
        }
    }
    if limits_given {
        tol.default = Some(Rule {
            pattern: String::new(),
            max_abs: args.max_abs,
            max_rel: args.max_rel,
            max_ulp: args.max_ulp,
            max_rel_peak: args.max_rel_peak,
            reason: Some("command line".into()),
            ..Rule::default()
        });
    }
    let report = compare_files(&args.a, &args.b, &tol)?;
    let table = report.to_table();
    if args.quiet {
        for line in table.lines() {
            if !line.starts_with("ok ")
                && !line.starts_with("norule")
                && !line.starts_with("ignored")
                && !line.starts_with("status")
            {
                println!("{line}");
            }
        }
    } else {
        print!("{table}");
    }
    if let Some(j) = &args.json {
        std::fs::write(j, report_json(&report)?)
            .with_context(|| format!("{}: cannot write JSON report", j.display()))?;
    }
    Ok(ExitCode::from(report.exit_code()))
}
