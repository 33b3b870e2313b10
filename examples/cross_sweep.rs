//! The level-range sweep of `docs/cross-scale.md`: on `xscale synth --preset cross`, train the
//! `cpu` preset with grid H's finest level fixed at 2k … 32k cells (levels added about the
//! preset's per-level scale apart, as `level_range = "auto"` does) × table 2^19 / 2^20, plus the
//! preset's fixed range and the automatic one, and score close-ups and aerial views apart.
//!
//!     cargo run --release --example cross_sweep -- SCENE_DIR OUT_DIR [SEED [CONFIG,CONFIG…]]
//!
//! With a list of configurations (e.g. `auto,g32768_t19`) only those run: the repeats with other
//! seeds that tell a real difference from seed noise; the plot is drawn for a full sweep only.
//! Each configuration trains into `OUT_DIR/<name>` (2000 steps, ~1.5–2.5 min each on 2 cores);
//! a configuration whose run folder already holds `eval.json` is read, not retrained, so an
//! interrupted sweep continues. Writes `OUT_DIR/sweep.csv` (config, finest, table, levels,
//! held-out masked PSNR of the near (close-up) and far (aerial) halves, seconds) and
//! `OUT_DIR/sweep.png`.

use anyhow::{Context, Result};
use std::path::{Path, PathBuf};
use xscale::eval::plot::{lines_png, Axes, Curve};
use xscale::model::config::per_level_scale_for;
use xscale::run::trainer::{train, TrainOptions};
use xscale::train::config::{LevelRange, RunConfig};
use xscale::train::setup::auto_levels;

const FINEST: [f64; 5] = [2048.0, 4096.0, 8192.0, 16384.0, 32768.0];
const TABLES: [u32; 2] = [19, 20];

struct Row {
    name: String,
    finest: f64,
    table: u32,
    levels: u32,
    close: f64,
    aerial: f64,
    seconds: f64,
}

/// `(name, config)` of every run of the sweep.
fn configs(seed: u64) -> Result<Vec<(String, RunConfig)>> {
    let cpu = || -> Result<RunConfig> {
        let mut c = RunConfig::preset("cpu")?;
        c.train.seed = seed;
        Ok(c)
    };
    let preset_scale = cpu()?.model.grid_h.per_level_scale;
    let mut out = Vec::new();
    let mut fixed = cpu()?;
    fixed.train.level_range = LevelRange::Fixed;
    out.push(("fixed".to_string(), fixed));
    out.push(("auto".to_string(), cpu()?));
    for t in TABLES {
        for f in FINEST {
            let mut c = cpu()?;
            let g = &mut c.model.grid_h;
            g.levels = auto_levels(16.0, f, preset_scale, g.levels);
            g.per_level_scale = per_level_scale_for(16.0, f, g.levels);
            g.finest_resolution = Some(f);
            g.log2_table_size = t;
            c.train.level_range = LevelRange::Fixed;
            c.train.table_size = xscale::train::config::TableSize::Fixed;
            out.push((format!("g{f}_t{t}"), c));
        }
    }
    Ok(out)
}

/// Scores of a finished run: (near, far) masked PSNR from `eval.json`, and the seconds trained.
fn scores(run: &Path) -> Result<(f64, f64, f64, u32, f64, u32)> {
    let p = run.join("eval.json");
    let v: serde_json::Value = serde_json::from_str(
        &std::fs::read_to_string(&p).with_context(|| format!("{}", p.display()))?,
    )?;
    let nf = &v["by_scale"]["near_far"];
    let psnr = |g: &serde_json::Value| g["mean"]["psnr_masked"].as_f64().unwrap_or(f64::NAN);
    let cfg = RunConfig::from_toml_str(
        &std::fs::read_to_string(run.join("config.toml"))?,
        "cpu",
        "config.toml",
    )?;
    let g = &cfg.model.grid_h;
    let finest = g
        .finest_resolution
        .unwrap_or(16.0 * g.per_level_scale.powi(g.levels as i32 - 1));
    let metrics = std::fs::read_to_string(run.join("metrics.jsonl")).unwrap_or_default();
    let seconds = metrics
        .lines()
        .filter_map(|l| serde_json::from_str::<serde_json::Value>(l).ok())
        .filter_map(|v| v["elapsed_s"].as_f64())
        .fold(f64::NAN, |_, x| x);
    Ok((
        psnr(&nf[1]),
        psnr(&nf[2]),
        finest,
        g.log2_table_size,
        seconds,
        g.levels,
    ))
}

fn main() -> Result<()> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    anyhow::ensure!(
        args.len() >= 2,
        "usage: cross_sweep SCENE_DIR OUT_DIR [SEED [CONFIG,CONFIG…]]"
    );
    let (scene, out) = (PathBuf::from(&args[0]), PathBuf::from(&args[1]));
    let seed: u64 = args.get(2).map_or(Ok(0), |s| s.parse())?;
    let only: Option<Vec<&str>> = args.get(3).map(|s| s.split(',').collect());
    let all = configs(seed)?;
    if let Some(o) = &only {
        for n in o {
            anyhow::ensure!(
                all.iter().any(|(a, _)| a == n),
                "no configuration named {n} (there are: {})",
                all.iter()
                    .map(|(a, _)| a.as_str())
                    .collect::<Vec<_>>()
                    .join(", ")
            );
        }
    }
    let mut rows = Vec::new();
    for (name, cfg) in all {
        if only.as_ref().is_some_and(|o| !o.contains(&name.as_str())) {
            continue;
        }
        let run = out.join(&name);
        if !run.join("eval.json").is_file() {
            eprintln!("training {name} …");
            let opts = TrainOptions {
                overwrite: true,
                quiet: true,
                ..Default::default()
            };
            train(&scene, &run, cfg, &opts)?;
        }
        let (close, aerial, finest, table, seconds, levels) = scores(&run)?;
        eprintln!(
            "{name:>14}: finest {finest:.0}, 2^{table}, {levels} levels: close-ups {close:.2} dB, aerial {aerial:.2} dB ({seconds:.0} s)"
        );
        rows.push(Row {
            name,
            finest,
            table,
            levels,
            close,
            aerial,
            seconds,
        });
    }
    let mut csv = String::from("config,finest,log2_table,levels,psnr_close,psnr_aerial,seconds\n");
    for r in &rows {
        csv += &format!(
            "{},{:.0},{},{},{:.3},{:.3},{:.1}\n",
            r.name, r.finest, r.table, r.levels, r.close, r.aerial, r.seconds
        );
    }
    std::fs::write(out.join("sweep.csv"), csv)?;
    eprintln!("wrote {}", out.join("sweep.csv").display());
    if only.is_some() {
        return Ok(());
    }
    let mut curves = Vec::new();
    for t in TABLES {
        for (what, close) in [("close-ups", true), ("aerial", false)] {
            curves.push(Curve {
                name: format!("{what}, table 2^{t}"),
                points: rows
                    .iter()
                    .filter(|r| r.name.starts_with('g') && r.table == t)
                    .map(|r| (r.finest, if close { r.close } else { r.aerial }))
                    .collect(),
            });
        }
    }
    let marks: Vec<(f64, f64)> = rows
        .iter()
        .filter(|r| r.name == "auto")
        .flat_map(|r| [(r.finest, r.close), (r.finest, r.aerial)])
        .collect();
    lines_png(
        &out.join("sweep.png"),
        &Axes {
            title: "synth --preset cross: held-out masked PSNR against grid H's finest level",
            x_desc: "finest level, cells per scene extent (log scale)",
            y_desc: "held-out masked PSNR (dB)",
            log_x: true,
        },
        &curves,
        &marks,
        "level_range = auto (table 2^19)",
    )?;
    Ok(())
}
