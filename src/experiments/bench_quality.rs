//! `xscale bench-quality`: run time against error. Trains each configuration for the same
//! wall-clock budget on one scene, evaluates the held-out views at `budget · 2^-k` (k = 5 … 0;
//! evaluation time is not counted), and writes `bench.csv` (appended as it goes), `pareto.png`
//! (masked PSNR against seconds, one curve per configuration, the Pareto front marked) and a
//! summary: the front, and the best configuration for each time budget.
//!
//! Configurations ([`CONFIGS`]): the presets, and the `cpu` preset with one change each (table
//! size, level spacing, batch size, γ, deformation, f64 arithmetic), plus `ulr`, the no-learning
//! baseline: nothing is trained, so its one row has 0 training seconds (`wall_s`; its setup,
//! loading the scene and the photos, is `setup_s`; rendering and scoring the held-out views is
//! evaluation, not counted, as for the others), drawn as a level across the plot.
//!
//! The rows of one `bench.csv` share a scene and a budget, recorded beside it in `bench.json`;
//! `--append` refuses another scene or `--minutes`, and a `bench.csv` without `bench.json`
//! (written before it was recorded), whose rows it cannot check.

use crate::eval::plot::{pareto_front, pareto_png, Curve};
use crate::eval::protocol::{mean_score, scale_summary};
use crate::experiments::variant::ulr_scores;
use crate::model::params::Grads;
use crate::run::trainer::evaluate_until;
use crate::train::config::RunConfig;
use crate::train::memory::Job;
use crate::train::sampler::sample_batch;
use crate::train::setup::{prepare_until, StoppedInSetup};
use crate::train::state::TrainState;
use anyhow::{anyhow, bail, Context, Result};
use std::io::Write;
use std::path::Path;
use std::time::Instant;

/// Every configuration: name and what it is.
pub const CONFIGS: [(&str, &str); 14] = [
    (
        "tiny",
        "the tiny preset (4 levels, 2^12 table): a smoke test",
    ),
    ("cpu", "the cpu preset (default)"),
    ("paper", "the paper preset (official code's settings)"),
    (
        "cpu-table17",
        "cpu with log2_table_size = 17 (a quarter of the table)",
    ),
    (
        "cpu-table19",
        "cpu with fixed 2^19 tables on every level (the cpu default before log2_table_size = \"auto\")",
    ),
    (
        "cpu-table21",
        "cpu with log2_table_size = 21 (4x the table)",
    ),
    (
        "cpu-spacing1.6",
        "cpu with grid H levels added about 1.6x apart (16 levels on small instead of 22)",
    ),
    (
        "cpu-spacing2",
        "cpu with grid H levels added about 2x apart (11 levels on small instead of 22)",
    ),
    ("cpu-batch1k", "cpu with 1,024-pixel batches"),
    ("cpu-batch16k", "cpu with 16,384-pixel batches"),
    ("cpu-gamma1", "cpu with gamma = 1 (no multisampling)"),
    ("cpu-no-deform", "cpu without the deformation xi"),
    (
        "cpu-refine",
        "cpu with photo-consistency mesh refinement ([model.refine] enabled = true)",
    ),
    (
        "cpu-f64",
        "cpu with the model's forward and backward in f64 (Adam and parameters f32)",
    ),
];

/// The run configuration of `name` (`None` for `ulr`).
pub fn config(name: &str) -> Result<Option<RunConfig>> {
    let cpu = || RunConfig::preset("cpu");
    let c = match name {
        "ulr" => return Ok(None),
        "tiny" | "cpu" | "paper" => RunConfig::preset(name)?,
        "cpu-table17" | "cpu-table19" | "cpu-table21" => {
            let mut c = cpu()?;
            c.model.grid_h.log2_table_size = name["cpu-table".len()..].parse()?;
            c.train.table_size = crate::train::config::TableSize::Fixed;
            c
        }
        "cpu-spacing1.6" | "cpu-spacing2" => {
            // The automatic level range with a wider spacing: as many levels as it takes.
            let mut c = cpu()?;
            c.model.grid_h.per_level_scale = if name == "cpu-spacing2" { 2.0 } else { 1.6 };
            c.model.grid_h.levels = 1;
            c
        }
        "cpu-batch1k" | "cpu-batch16k" => {
            let mut c = cpu()?;
            c.train.batch_pixels = if name == "cpu-batch1k" { 1024 } else { 16384 };
            c
        }
        "cpu-gamma1" => {
            let mut c = cpu()?;
            c.model.gamma = 1;
            c
        }
        "cpu-no-deform" => {
            let mut c = cpu()?;
            c.model.deform.enabled = false;
            c
        }
        "cpu-refine" => {
            let mut c = cpu()?;
            c.model.refine.enabled = true;
            c
        }
        "cpu-f64" => {
            let mut c = cpu()?;
            c.train.arithmetic = crate::train::config::Arithmetic::F64;
            c
        }
        _ => bail!(
            "unknown configuration {name:?}: expected some of {}, ulr",
            CONFIGS.map(|c| c.0).join(", ")
        ),
    };
    Ok(Some(c))
}

/// Every name in `configs` is a configuration ([`config`]) and listed once (a configuration
/// listed twice would be trained twice and replace its own rows).
pub fn check_configs(configs: &[String]) -> Result<()> {
    for (i, c) in configs.iter().enumerate() {
        config(c)?;
        if configs[..i].contains(c) {
            bail!("configuration {c:?} is listed twice");
        }
    }
    Ok(())
}

/// One evaluation.
#[derive(Clone, Debug)]
pub struct Row {
    pub config: String,
    pub setup_s: f64,
    pub wall_s: f64,
    pub step: u64,
    pub psnr_masked: f64,
    pub ssim_masked: f64,
    pub psnr_near: f64,
    pub psnr_far: f64,
}

const HEADER: &str = "config,setup_s,wall_s,step,psnr_masked,ssim_masked,psnr_near,psnr_far";

impl Row {
    fn csv(&self) -> String {
        format!(
            "{},{:.3},{:.3},{},{:.4},{:.5},{:.4},{:.4}",
            self.config,
            self.setup_s,
            self.wall_s,
            self.step,
            self.psnr_masked,
            self.ssim_masked,
            self.psnr_near,
            self.psnr_far
        )
    }
}

/// The close-up / aerial split of a log line: `(near 27.50, far 35.51)`, or words when the
/// held-out views are of one scale (NaN in `bench.csv`: no split, `scale_summary`).
fn near_far_words(near: f64, far: f64) -> String {
    if near.is_nan() || far.is_nan() {
        "(held-out views of one scale: no near/far split)".into()
    } else {
        format!("(near {near:.2}, far {far:.2})")
    }
}

fn near_far(scores: &[crate::eval::protocol::ViewScore]) -> (f64, f64) {
    match scale_summary(scores).near_far {
        Some((_, n, f)) => (n.mean.psnr_masked, f.mean.psnr_masked),
        None => (f64::NAN, f64::NAN),
    }
}

/// Train configuration `name` for `budget_s` seconds on `scene`, logging a row at each
/// evaluation (at `budget · 2^-k`); `Ok(false)` when `stop()` said so before a step (the rows
/// logged so far stand).
fn bench_one(
    scene: &Path,
    name: &str,
    budget_s: f64,
    log: &mut dyn FnMut(Row),
    stop: &dyn Fn() -> bool,
) -> Result<bool> {
    let t_setup = Instant::now();
    let Some(mut cfg) = config(name)? else {
        // ULR: render the held-out views from the training photos. It trains nothing: 0 training
        // seconds; the render and its scores are its evaluation, not counted as for the others.
        let opts = crate::scene::LoadOptions::default();
        let sc = crate::scene::Scene::load(scene, &opts)?;
        let tracer = crate::raycast::Tracer::new(&sc.mesh, &sc.normalization)?;
        let sources = crate::render::ulr::training_sources(&sc)?;
        let setup_s = t_setup.elapsed().as_secs_f64();
        // Cast as the `cpu` configurations cast their pixels (γ = 2).
        let gamma = crate::model::ModelConfig::cpu().gamma;
        let scores = ulr_scores(&sc, &tracer, &sources, gamma)?;
        let m = mean_score(&scores);
        let (pn, pf) = near_far(&scores);
        log(Row {
            config: name.into(),
            setup_s,
            wall_s: 0.0,
            step: 0,
            psnr_masked: m.psnr_masked,
            ssim_masked: m.ssim_masked,
            psnr_near: pn,
            psnr_far: pf,
        });
        return Ok(true);
    };
    let prepared = match prepare_until(scene, &cfg, true, &mut |_| {}, stop, Job::Train) {
        Err(e) if e.downcast_ref::<StoppedInSetup>().is_some() => return Ok(false),
        r => r?,
    };
    if prepared.scene.test.is_empty() {
        bail!(
            "{}: the scene holds no view out to evaluate",
            scene.display()
        );
    }
    cfg.train.steps = u64::MAX / 4;
    cfg.train.budget = crate::train::config::StepBudget::Fixed;
    let mut state = TrainState::init(cfg, &prepared, &mut |_| {})?;
    let mut grads = Grads::new(&state.ckpt.model.layout);
    grads.inputs = false;
    let mut f64s = crate::train::precision::F64Step::for_config(&state);
    let setup_s = t_setup.elapsed().as_secs_f64();
    let (seed, px) = (state.cfg.train.seed, state.cfg.train.batch_pixels);
    let mut trained = 0.0f64;
    for k in (0..=5).rev() {
        let until = budget_s / f64::from(1u32 << k);
        while trained < until {
            if stop() {
                return Ok(false);
            }
            let t = Instant::now();
            let b = sample_batch(&prepared.samples, &prepared.tracer, seed, state.step, px);
            let st = state.step_in(&b, &mut grads, f64s.as_mut())?;
            trained += t.elapsed().as_secs_f64();
            if !st.loss.is_finite() {
                bail!("{name}: the loss became {} at step {}", st.loss, state.step);
            }
        }
        let Some(scores) = evaluate_until(&state, &prepared, 0, None, stop)? else {
            return Ok(false);
        };
        let m = mean_score(&scores);
        let (pn, pf) = near_far(&scores);
        log(Row {
            config: name.into(),
            setup_s,
            wall_s: trained,
            step: state.step,
            psnr_masked: m.psnr_masked,
            ssim_masked: m.ssim_masked,
            psnr_near: pn,
            psnr_far: pf,
        });
    }
    Ok(true)
}

pub use crate::run::run_dir::Existing;

/// Run the benchmark: every row (also in `OUT/bench.csv`, appended as each evaluation
/// finishes, so an interrupted run keeps what it measured; plotted in `OUT/pareto.png`) and the
/// configurations not finished — empty unless `stop()` (Ctrl-C) said so (checked before each
/// training step and between the views being cast or evaluated), then the stopped one first
/// (its rows up to its last evaluation are kept; `--append` runs it again). An existing
/// `OUT/bench.csv` is handled as `existing` says.
pub fn bench_quality(
    scene: &Path,
    out: &Path,
    configs: &[String],
    minutes: f64,
    existing: Existing,
    say: &mut dyn FnMut(String),
    stop: &dyn Fn() -> bool,
) -> Result<(Vec<Row>, Vec<String>)> {
    if !(minutes > 0.0 && minutes.is_finite()) {
        bail!("--minutes {minutes}: expected a positive number");
    }
    check_configs(configs)?;
    std::fs::create_dir_all(out).with_context(|| format!("{}: cannot create", out.display()))?;
    let csv_path = out.join("bench.csv");
    // Rows kept from an earlier run (read before anything is written, so a bad file stops the
    // run with the file and line named and loses nothing).
    let mut rows: Vec<Row> = Vec::new();
    if csv_path.exists() && existing != Existing::Overwrite {
        let old =
            read_rows(&csv_path).context("an earlier run's results (--overwrite replaces them)")?;
        if existing == Existing::Refuse && !old.is_empty() {
            bail!(
                "{}: holds an earlier run's results ({} rows: {}); add --append to add this run's configurations to them (a configuration run again replaces its rows), --overwrite to replace them, or choose another --out",
                csv_path.display(),
                old.len(),
                config_names(&old).join(", ")
            );
        }
        let (again, kept): (Vec<Row>, Vec<Row>) =
            old.into_iter().partition(|r| configs.contains(&r.config));
        if !kept.is_empty() || !again.is_empty() {
            same_bench(out, scene, minutes)?;
        }
        if !again.is_empty() {
            say(format!(
                "--append: {} earlier rows of {} are replaced by this run's",
                again.len(),
                config_names(&again).join(", ")
            ));
        }
        rows = kept;
    }
    let record = Record {
        scene: std::fs::canonicalize(scene).unwrap_or_else(|_| scene.to_path_buf()),
        minutes,
    };
    crate::io::atomic::write_bytes(&out.join(RECORD), serde_json::to_string_pretty(&record)?)?;
    // The kept rows replace the old file whole (or not at all), then this run appends to it.
    let mut kept = format!("{HEADER}\n");
    for r in &rows {
        kept += &format!("{}\n", r.csv());
    }
    crate::io::atomic::write_atomic(&csv_path, true, |tmp| {
        std::fs::write(tmp, &kept).with_context(|| format!("{}: cannot write", tmp.display()))
    })?;
    let mut csv = std::fs::OpenOptions::new()
        .append(true)
        .open(&csv_path)
        .with_context(|| format!("{}: cannot open", csv_path.display()))?;
    let mut stopped = Vec::new();
    for (k, name) in configs.iter().enumerate() {
        if stop() {
            stopped = configs[k..].to_vec();
            break;
        }
        say(match name.as_str() {
            "ulr" => "== ulr (nothing trained: 0 s of training)".to_string(),
            _ => format!("== {name} ({minutes:.1} min of training)"),
        });
        let mut log = |r: Row| {
            let _ = writeln!(csv, "{}", r.csv());
            let _ = csv.flush();
            say(format!(
                "   {:>8.1} s  step {:>6}  masked PSNR {:.2}  SSIM {:.4}  {}",
                r.wall_s,
                r.step,
                r.psnr_masked,
                r.ssim_masked,
                near_far_words(r.psnr_near, r.psnr_far)
            ));
            rows.push(r);
        };
        let finished = bench_one(scene, name, minutes * 60.0, &mut log, stop)
            .with_context(|| format!("configuration {name}"))?;
        if !finished {
            stopped = configs[k..].to_vec();
            break;
        }
    }
    let title = scene
        .file_name()
        .map_or("scene".into(), |n| n.to_string_lossy().to_string());
    // Stopped before its first evaluation: nothing measured, no plot (an earlier one stays).
    if !rows.is_empty() || stopped.is_empty() {
        plot(out, &title, &rows, say)?;
    }
    Ok((rows, stopped))
}

/// What the rows of one `bench.csv` share, recorded beside it in `OUT/bench.json`.
#[derive(serde::Serialize, serde::Deserialize, Debug)]
struct Record {
    /// The scene, as an absolute path.
    scene: std::path::PathBuf,
    /// The training budget per configuration, `--minutes`.
    minutes: f64,
}

/// The file beside `bench.csv` recording its [`Record`].
const RECORD: &str = "bench.json";

/// An error naming what differs when this run's scene or budget is not that of the rows in
/// `OUT/bench.csv` (or when they were written without a record, so nothing can be checked).
fn same_bench(out: &Path, scene: &Path, minutes: f64) -> Result<()> {
    let path = out.join(RECORD);
    let csv = out.join("bench.csv");
    if !path.exists() {
        bail!(
            "--append: {} holds rows from an older xscale that did not record their scene and --minutes ({} is missing), so this run cannot be checked against them; --overwrite replaces them, or choose another --out (--replot still draws them)",
            csv.display(),
            path.display()
        );
    }
    let text = crate::io::text::read(&path)?;
    let then: Record = serde_json::from_str(&text)
        .with_context(|| format!("{}: not a bench-quality record", path.display()))?;
    let canon = |p: &Path| std::fs::canonicalize(p).unwrap_or_else(|_| p.to_path_buf());
    let mut diffs = Vec::new();
    if canon(scene) != canon(&then.scene) {
        diffs.push(format!(
            "scene {} (the earlier run's is {})",
            scene.display(),
            then.scene.display()
        ));
    }
    if minutes != then.minutes {
        diffs.push(format!(
            "--minutes {minutes} (the earlier run's is {})",
            then.minutes
        ));
    }
    if !diffs.is_empty() {
        bail!(
            "--append: this run differs from the earlier one in {}, and the rows of one bench must share their scene and budget:\n  {}\nrun with the earlier options, or use another --out (or --overwrite)",
            csv.display(),
            diffs.join("\n  ")
        );
    }
    Ok(())
}

/// Draw `OUT/pareto.png` from `rows` (one curve per configuration, in order of first appearance)
/// and say the Pareto front.
fn plot(out: &Path, scene_name: &str, rows: &[Row], say: &mut dyn FnMut(String)) -> Result<()> {
    let configs = config_names(rows);
    let curves: Vec<Curve> = configs
        .iter()
        .map(|c| Curve {
            name: c.to_string(),
            points: rows
                .iter()
                .filter(|r| r.config == *c)
                // ULR trains nothing (rows written before that was so hold its render time).
                .map(|r| {
                    let t = if r.config == "ulr" { 0.0 } else { r.wall_s };
                    (t, r.psnr_masked)
                })
                .collect(),
        })
        .collect();
    let title = format!("{scene_name}: held-out masked PSNR against training time");
    pareto_png(&out.join("pareto.png"), &title, &curves)?;
    say("Pareto front (no configuration is better in less time):".into());
    for (t, p, c) in pareto_front(&curves) {
        say(format!("  {t:>8.1} s  {p:6.2} dB  {c}"));
    }
    Ok(())
}

/// The configurations of `rows`, each once, in order of first appearance.
fn config_names(rows: &[Row]) -> Vec<&str> {
    let mut names: Vec<&str> = Vec::new();
    for r in rows {
        if !names.contains(&r.config.as_str()) {
            names.push(&r.config);
        }
    }
    names
}

/// Read `OUT/bench.csv` back (for instance after concatenating runs made apart) and redraw
/// `OUT/pareto.png`; returns the rows.
pub fn replot(out: &Path, scene_name: &str, say: &mut dyn FnMut(String)) -> Result<Vec<Row>> {
    let path = out.join("bench.csv");
    let rows = read_rows(&path)?;
    if rows.is_empty() {
        bail!("{}: no rows", path.display());
    }
    plot(out, scene_name, &rows, say)?;
    Ok(rows)
}

/// The rows of a `bench.csv` (header lines, also repeated ones from concatenated runs, and blank
/// lines skipped); a malformed line is an error naming the file and line.
pub fn read_rows(path: &Path) -> Result<Vec<Row>> {
    let text = std::fs::read_to_string(path)
        .with_context(|| format!("{}: cannot read", path.display()))?;
    let mut rows = Vec::new();
    for (i, line) in text.lines().enumerate() {
        if line.trim().is_empty() || line == HEADER {
            continue;
        }
        let bad = |what: &str| {
            anyhow!(
                "{}: line {}: {what} (expected {HEADER})",
                path.display(),
                i + 1
            )
        };
        let f: Vec<&str> = line.split(',').collect();
        if f.len() != 8 {
            return Err(bad(&format!("{} fields", f.len())));
        }
        let num = |k: usize| -> Result<f64> {
            f[k].parse::<f64>()
                .map_err(|_| bad(&format!("field {} is not a number: {:?}", k + 1, f[k])))
        };
        rows.push(Row {
            config: f[0].to_string(),
            setup_s: num(1)?,
            wall_s: num(2)?,
            step: num(3)? as u64,
            psnr_masked: num(4)?,
            ssim_masked: num(5)?,
            psnr_near: num(6)?,
            psnr_far: num(7)?,
        });
    }
    Ok(rows)
}

#[cfg(test)]
mod tests {
    use super::near_far_words;

    /// A scene whose held-out views are of one scale has no near/far split: the log line says
    /// so instead of printing `near NaN, far NaN` (a real 5-photo scene with one held-out view).
    #[test]
    fn near_far_without_a_split_is_words_not_nan() {
        assert_eq!(near_far_words(27.5, 35.514), "(near 27.50, far 35.51)");
        let w = near_far_words(f64::NAN, f64::NAN);
        assert!(!w.contains("NaN") && w.contains("one scale"), "{w}");
    }
}
