//! `xscale bench-geometry`: how much an imperfect mesh costs (docs/geometry.md).
//!
//! On a synthetic scene whose true surface is known (`truth.ply`), proxies of that surface are
//! built ([`ProxySpec`]): the exact mesh, the exact mesh with every vertex moved along its normal
//! by a smooth field of RMS 0.1 %, 0.3 % and 1 % of the bounding-box diagonal
//! (`synth/perturb.rs`, wavelength [`WAVELENGTH_FRACTION`] of the diagonal), and the exact mesh
//! decimated to a fraction of its faces. Each proxy's geometry error against the true surface is
//! measured (mean / RMS point-to-surface distance of area samples, `scene/distance.rs`; also the
//! RMS of the truth's samples to the proxy, which sees holes and lost relief). Each proxy is then
//! trained with the deformation ξ on and off (and, with `refine`, with the joint mesh refinement
//! of `refine/`), with one step budget and seed, and its held-out views scored (masked
//! PSNR / SSIM, SPEC §7), split into close-up and far views by `scale_summary`'s near/far split.
//!
//! Output (`OUT/`): `scene/` (the synthetic scene, rendered once and reused), `meshes/<proxy>.ply`,
//! `runs/<variant>/` (ordinary run folders: `xscale eval/render --run` work on them),
//! `geometry.csv`, `geometry.md`, `geometry-psnr.png`, `geometry-ssim.png`. A run folder whose
//! `bench.json` records the same variant settings and that holds an `eval.json` is reused, not
//! retrained (so an interrupted benchmark continues where it stopped, and a new variant can be
//! added without retraining the others). Ctrl-C / SIGTERM stops the run in training at its next
//! step with a checkpoint; the same command then continues that run from it
//! (`run_dir::stopped_run_of`). A run killed outright continues from its latest periodic
//! checkpoint, a tenth of the run apart (`config::tool_checkpoint_every`).

use crate::eval::plot::{lines_png, Axes, Curve};
use crate::eval::protocol::{mean_score, scale_summary, ViewScore};
use crate::experiments::variant::Runs;
use crate::scene::distance::{surface_distance, DistanceStats, SurfaceIndex};
use crate::scene::mesh::{decimate_report, load_mesh, write_ply};
use crate::scene::Mesh;
use crate::synth::perturb::displace_along_normals;
use crate::train::config::RunConfig;
use anyhow::{anyhow, bail, ensure, Context, Result};
use serde::{Deserialize, Serialize};
use std::fmt::Write as _;
use std::path::{Path, PathBuf};

/// Wavelength of the displacement field as a fraction of the bounding-box diagonal.
pub const WAVELENGTH_FRACTION: f64 = 0.2;
/// Seed of the displacement field (fixed: every RMS level displaces along the same field shape).
pub const FIELD_SEED: u64 = 7;
/// Area samples per geometry-error measurement.
pub const DISTANCE_SAMPLES: usize = 200_000;

/// One proxy of the true surface.
#[derive(Clone, Debug, PartialEq)]
pub enum ProxySpec {
    /// Displaced along vertex normals, RMS = this percentage of the bounding-box diagonal (0 =
    /// the exact mesh).
    Displaced(f64),
    /// Quadric-decimated to this fraction of the faces (no displacement).
    Decimated(f64),
}

impl ProxySpec {
    pub fn name(&self) -> String {
        match self {
            ProxySpec::Displaced(p) if *p == 0.0 => "exact".into(),
            ProxySpec::Displaced(p) => format!("rms{p}"),
            ProxySpec::Decimated(r) => format!("dec{}", (r * 100.0).round()),
        }
    }
    /// `Ok` when a proxy can be built with this value, else what is wrong with it.
    pub fn check(&self) -> std::result::Result<(), String> {
        match self {
            ProxySpec::Displaced(p) if !(p.is_finite() && *p >= 0.0) => {
                Err(format!("displacement RMS {p} % is not a number ≥ 0"))
            }
            ProxySpec::Decimated(r) if !(*r > 0.0 && *r <= 1.0) => {
                Err(format!("decimation ratio {r} is not in (0, 1]"))
            }
            _ => Ok(()),
        }
    }
    pub fn description(&self) -> String {
        match self {
            ProxySpec::Displaced(p) if *p == 0.0 => "the exact true surface".into(),
            ProxySpec::Displaced(p) => format!("smooth displacement, RMS {p} % of the diagonal"),
            ProxySpec::Decimated(r) => format!("decimated to {} % of the faces", r * 100.0),
        }
    }
}

/// How to run the benchmark.
#[derive(Clone, Debug)]
pub struct GeometryOptions {
    /// The base configuration every run is derived from, and how they train. An interrupt ends
    /// the benchmark without its report; the same command continues it.
    pub runs: Runs,
    pub proxies: Vec<ProxySpec>,
    /// ξ settings to train each proxy with (true = on).
    pub deform: Vec<bool>,
    /// Refinement settings to train each proxy with (true = `[model.refine] enabled`).
    pub refine: Vec<bool>,
    /// Area samples per distance measurement.
    pub samples: usize,
}

/// A proxy with its geometry error against the truth.
#[derive(Clone, Debug, Serialize)]
pub struct ProxyResult {
    pub name: String,
    pub description: String,
    pub path: PathBuf,
    pub faces: usize,
    pub vertices: usize,
    /// Proxy → truth.
    pub to_truth: DistanceStats,
    /// Truth → proxy.
    pub from_truth: DistanceStats,
}

/// Scores of a group of views.
#[derive(Clone, Debug, Serialize, Deserialize, Default)]
pub struct GroupScore {
    pub views: usize,
    pub psnr_masked: f64,
    pub ssim_masked: f64,
}

/// One trained variant.
#[derive(Clone, Debug, Serialize)]
pub struct VariantResult {
    pub name: String,
    pub proxy: String,
    pub deform: bool,
    pub refine: bool,
    pub steps: u64,
    pub train_seconds: f64,
    pub all: GroupScore,
    pub near: GroupScore,
    pub far: GroupScore,
    /// Geometry error of the refined mesh (`RUN/refined.ply`) against the truth (refine only).
    pub refined_to_truth: Option<DistanceStats>,
    pub run: PathBuf,
}

/// The whole benchmark.
#[derive(Clone, Debug, Serialize)]
pub struct GeometryReport {
    pub scene: PathBuf,
    pub diagonal: f64,
    pub preset: String,
    pub steps: u64,
    pub batch_pixels: usize,
    pub seed: u64,
    pub proxies: Vec<ProxyResult>,
    pub variants: Vec<VariantResult>,
}

/// What `bench.json` records about a run, to decide whether it can be reused.
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
struct VariantKey {
    proxy: String,
    mesh: PathBuf,
    deform: bool,
    refine: bool,
    /// `RunConfig::results_toml` of the run (its checkpoint interval left out).
    config: String,
}

fn group(scores: &[ViewScore]) -> GroupScore {
    let m = mean_score(scores);
    GroupScore {
        views: scores.len(),
        psnr_masked: m.psnr_masked,
        ssim_masked: m.ssim_masked,
    }
}

/// All / close-up / far scores of a run's held-out views.
pub fn split_scores(views: &[ViewScore]) -> (GroupScore, GroupScore, GroupScore) {
    let all = group(views);
    match scale_summary(views).near_far {
        Some((_, n, f)) => (
            all,
            GroupScore {
                views: n.views.len(),
                psnr_masked: n.mean.psnr_masked,
                ssim_masked: n.mean.ssim_masked,
            },
            GroupScore {
                views: f.views.len(),
                psnr_masked: f.mean.psnr_masked,
                ssim_masked: f.mean.ssim_masked,
            },
        ),
        None => (all, GroupScore::default(), GroupScore::default()),
    }
}

/// Every proxy's value can be built, and no two proxies are the same (`--rms 0,0` would train
/// and list the same variants twice): checked before anything is made.
pub fn check_proxies(specs: &[ProxySpec]) -> Result<()> {
    ensure!(!specs.is_empty(), "no proxies to build");
    for (i, spec) in specs.iter().enumerate() {
        spec.check().map_err(|e| anyhow!(e))?;
        if specs[..i].iter().any(|t| t.name() == spec.name()) {
            bail!(
                "proxy {} ({}) is listed twice: give each --rms value once",
                spec.name(),
                spec.description()
            );
        }
    }
    Ok(())
}

/// Build the proxy meshes of `truth` into `dir` and measure them.
pub fn build_proxies(
    truth: &Mesh,
    specs: &[ProxySpec],
    dir: &Path,
    samples: usize,
    say: &mut dyn FnMut(String),
) -> Result<Vec<ProxyResult>> {
    check_proxies(specs)?;
    std::fs::create_dir_all(dir).with_context(|| format!("{}: cannot create", dir.display()))?;
    let diag = truth.diagonal();
    let index = SurfaceIndex::new(truth);
    let mut out = Vec::new();
    for spec in specs {
        let mesh = match spec {
            ProxySpec::Displaced(p) => displace_along_normals(
                truth,
                FIELD_SEED,
                p / 100.0 * diag,
                WAVELENGTH_FRACTION * diag,
            ),
            ProxySpec::Decimated(r) => decimate_report(truth, *r)?.0,
        };
        let path = dir.join(format!("{}.ply", spec.name()));
        write_ply(&path, &mesh)?;
        let to_truth = surface_distance(&mesh, &index, samples);
        let from_truth = surface_distance(truth, &SurfaceIndex::new(&mesh), samples);
        say(format!(
            "proxy {}: {} faces; distance to the truth mean {:.4} / RMS {:.4} ({:.3} % of the diagonal); truth to proxy RMS {:.4}",
            spec.name(),
            mesh.triangles.len(),
            to_truth.mean,
            to_truth.rms,
            100.0 * to_truth.rms / diag,
            from_truth.rms
        ));
        out.push(ProxyResult {
            name: spec.name(),
            description: spec.description(),
            path: std::fs::canonicalize(&path).unwrap_or(path),
            faces: mesh.triangles.len(),
            vertices: mesh.vertices.len(),
            to_truth,
            from_truth,
        });
    }
    Ok(out)
}

/// The scene's true surface: `DIR/truth.ply`.
pub fn load_truth(scene: &Path) -> Result<Mesh> {
    let p = scene.join("truth.ply");
    if !p.is_file() {
        bail!(
            "{}: no truth.ply (the true surface the proxies are made from); make the scene with `xscale synth --write-truth` or use --scene-preset",
            scene.display()
        );
    }
    Ok(load_mesh(&p)?.0)
}

/// Variant run folder name.
pub fn variant_name(proxy: &str, deform: bool, refine: bool) -> String {
    format!(
        "{proxy}_{}{}",
        if deform { "xi" } else { "noxi" },
        if refine { "_refine" } else { "" }
    )
}

/// Run the benchmark on `scene` (which must hold `truth.ply`) into `out`.
pub fn bench_geometry(
    scene: &Path,
    out: &Path,
    opts: &GeometryOptions,
    say: &mut dyn FnMut(String),
) -> Result<Option<GeometryReport>> {
    check_proxies(&opts.proxies)?;
    ensure!(
        !opts.deform.is_empty() && !opts.refine.is_empty(),
        "no variants to train"
    );
    let mut base = opts.runs.base.clone();
    base.validate()?;
    crate::train::config::set_tool_run(&mut base);
    let truth = load_truth(scene)?;
    let diag = truth.diagonal();
    say(format!(
        "true surface: {} faces, bounding-box diagonal {diag:.3}",
        truth.triangles.len()
    ));
    let proxies = build_proxies(
        &truth,
        &opts.proxies,
        &out.join("meshes"),
        opts.samples,
        say,
    )?;
    let index = SurfaceIndex::new(&truth);
    let runs = out.join("runs");
    let mut variants = Vec::new();
    for p in &proxies {
        for &deform in &opts.deform {
            for &refine in &opts.refine {
                let mut cfg = base.clone();
                cfg.model.deform.enabled = deform;
                cfg.train.mesh = Some(p.path.clone());
                // Off: the paper's fixed mesh (the default table, so an earlier run of the same
                // variant is reused whatever `[model.refine]` values the base config carries);
                // on: the base config's `[model.refine]` values, enabled.
                if refine {
                    cfg.model.refine.enabled = true;
                    cfg.validate()?;
                } else {
                    cfg.model.refine = Default::default();
                }
                let name = variant_name(&p.name, deform, refine);
                let run = PlannedRun {
                    dir: runs.join(&name),
                    key: VariantKey {
                        proxy: p.name.clone(),
                        mesh: p.path.clone(),
                        deform,
                        refine,
                        config: cfg.results_toml(),
                    },
                    name: name.clone(),
                    cfg,
                };
                let Some(v) = run_variant(run, scene, &index, opts, say)? else {
                    return Ok(None);
                };
                say(format!(
                    "   {name}: masked PSNR {:.2} (close-up {:.2}, far {:.2}), SSIM {:.4}, {:.0} s{}",
                    v.all.psnr_masked,
                    v.near.psnr_masked,
                    v.far.psnr_masked,
                    v.all.ssim_masked,
                    v.train_seconds,
                    v.refined_to_truth
                        .map_or(String::new(), |d| format!(
                            ", refined mesh RMS distance {:.4} (proxy {:.4})",
                            d.rms, p.to_truth.rms
                        ))
                ));
                variants.push(v);
            }
        }
    }
    let rep = GeometryReport {
        scene: scene.to_path_buf(),
        diagonal: diag,
        preset: base.preset.clone(),
        steps: base.train.steps,
        batch_pixels: base.train.batch_pixels,
        seed: base.train.seed,
        proxies,
        variants,
    };
    write_outputs(out, &rep)?;
    Ok(Some(rep))
}

/// Scores and timing a run folder recorded (`eval.json`, `metrics.jsonl`).
fn recorded(dir: &Path) -> Result<(Vec<ViewScore>, u64, f64)> {
    let p = dir.join("eval.json");
    let text =
        std::fs::read_to_string(&p).with_context(|| format!("{}: cannot read", p.display()))?;
    let v: serde_json::Value =
        serde_json::from_str(&text).with_context(|| format!("{}: not JSON", p.display()))?;
    let views: Vec<ViewScore> = v
        .get("views")
        .and_then(|x| x.as_array())
        .context("eval.json: no views")?
        .iter()
        .map(|x| {
            let g = |k: &str| x.get(k).and_then(|y| y.as_f64()).unwrap_or(f64::NAN);
            ViewScore {
                view: x.get("view").and_then(|y| y.as_str()).unwrap_or("").into(),
                psnr: g("psnr"),
                ssim: g("ssim"),
                flip: g("flip"),
                psnr_masked: g("psnr_masked"),
                ssim_masked: g("ssim_masked"),
                flip_masked: g("flip_masked"),
                hit_fraction: g("hit_fraction"),
                mask_miss: x.get("mask_miss").and_then(|y| y.as_f64()),
                footprint: x.get("footprint").and_then(|y| y.as_f64()),
            }
        })
        .collect();
    let step = v.get("step").and_then(|x| x.as_u64()).unwrap_or(0);
    // The training time: the last metrics line's elapsed seconds before the final evaluation.
    let seconds =
        crate::run::report::elapsed_recorded(&dir.join("metrics.jsonl")).unwrap_or(f64::NAN);
    Ok((views, step, seconds))
}

/// One run of the benchmark: its name and folder, its configuration, and what its `bench.json`
/// records to tell whether a run there can be reused.
struct PlannedRun {
    name: String,
    dir: PathBuf,
    cfg: RunConfig,
    key: VariantKey,
}

/// Train (or reuse) one run on `scene` and score it: its held-out views, and with refinement
/// its refined mesh against the `truth`; `None` when an interrupt stopped its training.
fn run_variant(
    run: PlannedRun,
    scene: &Path,
    truth: &SurfaceIndex,
    opts: &GeometryOptions,
    say: &mut dyn FnMut(String),
) -> Result<Option<VariantResult>> {
    let PlannedRun {
        name,
        dir,
        cfg,
        key,
    } = run;
    let (name, dir, key) = (name.as_str(), dir.as_path(), &key);
    let key_path = dir.join("bench.json");
    let reuse = std::fs::read_to_string(&key_path)
        .ok()
        .and_then(|t| serde_json::from_str::<VariantKey>(&t).ok())
        .is_some_and(|k| &k == key)
        && dir.join("eval.json").is_file();
    let steps = cfg.train.steps;
    let (views, seconds) = if reuse {
        say(format!("== {name}: reusing {}", dir.display()));
        let (views, step, seconds) = recorded(dir)?;
        ensure!(
            step == steps,
            "{}: eval.json is at step {step}, expected {steps}",
            dir.display()
        );
        (views, seconds)
    } else {
        say(format!(
            "== {name}: {} steps of {} pixels → {}",
            steps,
            cfg.train.batch_pixels,
            dir.display()
        ));
        let _ = std::fs::remove_file(&key_path);
        // A run stopped halfway (Ctrl-C, SIGTERM) continues from its checkpoint.
        let resume = crate::run::run_dir::stopped_run_of(dir, &cfg);
        if resume {
            say(format!("   {name}: continuing the stopped run"));
        }
        let s = opts
            .runs
            .train(scene, dir, &cfg, resume)
            .with_context(|| format!("bench-geometry variant {name}"))?;
        if s.interrupted {
            return Ok(None);
        }
        ensure!(
            !s.views.is_empty(),
            "{name}: the run has no final evaluation"
        );
        std::fs::write(&key_path, serde_json::to_string_pretty(key)?)
            .with_context(|| format!("{}: cannot write", key_path.display()))?;
        // The seconds a later call reads back (`recorded`), so the table does not change when
        // the run is reused.
        let seconds = recorded(dir)
            .ok()
            .map(|r| r.2)
            .filter(|t| t.is_finite())
            .unwrap_or(s.seconds);
        (s.views, seconds)
    };
    let (all, near, far) = split_scores(&views);
    let refined_to_truth = if key.refine {
        let p = dir.join("refined.ply");
        let m = load_mesh(&p)
            .with_context(|| format!("{name}: the refined mesh"))?
            .0;
        Some(surface_distance(&m, truth, opts.samples))
    } else {
        None
    };
    Ok(Some(VariantResult {
        name: name.to_string(),
        proxy: key.proxy.clone(),
        deform: key.deform,
        refine: key.refine,
        steps,
        train_seconds: seconds,
        all,
        near,
        far,
        refined_to_truth,
        run: dir.to_path_buf(),
    }))
}

const CSV_HEADER: &str = "variant,proxy,deform,refine,proxy_rms_pct,proxy_mean,proxy_rms,truth_to_proxy_rms,refined_mean,refined_rms,steps,train_s,psnr_masked,ssim_masked,psnr_near,ssim_near,psnr_far,ssim_far,views_near,views_far";

/// `geometry.csv`: one line per variant.
pub fn csv(rep: &GeometryReport) -> String {
    let mut s = String::from(CSV_HEADER);
    s.push('\n');
    for v in &rep.variants {
        let p = rep.proxies.iter().find(|p| p.name == v.proxy);
        let (pm, pr, tr) = p.map_or((f64::NAN, f64::NAN, f64::NAN), |p| {
            (p.to_truth.mean, p.to_truth.rms, p.from_truth.rms)
        });
        let (rm, rr) = v
            .refined_to_truth
            .map_or((f64::NAN, f64::NAN), |d| (d.mean, d.rms));
        let _ = writeln!(
            s,
            "{},{},{},{},{:.4},{:.5},{:.5},{:.5},{:.5},{:.5},{},{:.1},{:.3},{:.4},{:.3},{:.4},{:.3},{:.4},{},{}",
            v.name,
            v.proxy,
            v.deform,
            v.refine,
            100.0 * pr / rep.diagonal,
            pm,
            pr,
            tr,
            rm,
            rr,
            v.steps,
            v.train_seconds,
            v.all.psnr_masked,
            v.all.ssim_masked,
            v.near.psnr_masked,
            v.near.ssim_masked,
            v.far.psnr_masked,
            v.far.ssim_masked,
            v.near.views,
            v.far.views
        );
    }
    s
}

/// `geometry.md`: the proxies and the table of variants.
pub fn markdown(rep: &GeometryReport) -> String {
    let mut s = String::new();
    let _ = writeln!(s, "# Geometry sensitivity: {}\n", rep.scene.display());
    let _ = writeln!(
        s,
        "Preset `{}`, {} steps of {} pixels, seed {}; held-out masked PSNR / SSIM (SPEC §7), close-up and far views split at the geometric mean of the finest and coarsest view footprints. Bounding-box diagonal {:.2}. Produced by `xscale bench-geometry`.\n",
        rep.preset, rep.steps, rep.batch_pixels, rep.seed, rep.diagonal
    );
    let _ = writeln!(
        s,
        "| proxy | faces | proxy→truth mean | proxy→truth RMS | RMS % diag | truth→proxy RMS |"
    );
    let _ = writeln!(s, "|---|---:|---:|---:|---:|---:|");
    for p in &rep.proxies {
        let _ = writeln!(
            s,
            "| `{}` ({}) | {} | {:.4} | {:.4} | {:.3} | {:.4} |",
            p.name,
            p.description,
            p.faces,
            p.to_truth.mean,
            p.to_truth.rms,
            100.0 * p.to_truth.rms / rep.diagonal,
            p.from_truth.rms
        );
    }
    let _ = writeln!(
        s,
        "\n| variant | ξ | refine | PSNR all | SSIM all | PSNR close-up | SSIM close-up | PSNR far | SSIM far | refined→truth RMS | train s |"
    );
    let _ = writeln!(s, "|---|---|---|---:|---:|---:|---:|---:|---:|---:|---:|");
    for v in &rep.variants {
        let _ = writeln!(
            s,
            "| `{}` | {} | {} | {:.2} | {:.4} | {:.2} | {:.4} | {:.2} | {:.4} | {} | {:.0} |",
            v.name,
            if v.deform { "on" } else { "off" },
            if v.refine { "on" } else { "off" },
            v.all.psnr_masked,
            v.all.ssim_masked,
            v.near.psnr_masked,
            v.near.ssim_masked,
            v.far.psnr_masked,
            v.far.ssim_masked,
            v.refined_to_truth
                .map_or("–".into(), |d| format!("{:.4}", d.rms)),
            v.train_seconds
        );
    }
    s
}

/// The sensitivity plots: masked PSNR (SSIM) against the proxy's measured RMS distance to the
/// truth (% of the diagonal), one curve per (views, ξ, refine) over the displaced proxies; the
/// decimated proxies' points circled.
pub fn plots(out: &Path, rep: &GeometryReport) -> Result<()> {
    let rms_pct = |proxy: &str| {
        rep.proxies
            .iter()
            .find(|p| p.name == proxy)
            .map_or(f64::NAN, |p| 100.0 * p.to_truth.rms / rep.diagonal)
    };
    let displaced = |proxy: &str| !proxy.starts_with("dec");
    for (file, metric, ylabel) in [
        ("geometry-psnr.png", 0, "held-out masked PSNR (dB)"),
        ("geometry-ssim.png", 1, "held-out masked SSIM"),
    ] {
        let pick = |g: &GroupScore| {
            if metric == 0 {
                g.psnr_masked
            } else {
                g.ssim_masked
            }
        };
        let mut curves = Vec::new();
        let mut marks = Vec::new();
        let mut settings: Vec<(bool, bool)> =
            rep.variants.iter().map(|v| (v.deform, v.refine)).collect();
        settings.dedup();
        settings.sort();
        settings.dedup();
        for (deform, refine) in settings {
            for (views, near) in [("close-up", true), ("far", false)] {
                let mut pts: Vec<(f64, f64)> = rep
                    .variants
                    .iter()
                    .filter(|v| v.deform == deform && v.refine == refine)
                    .filter_map(|v| {
                        let y = pick(if near { &v.near } else { &v.far });
                        let x = rms_pct(&v.proxy);
                        if displaced(&v.proxy) {
                            Some((x, y))
                        } else {
                            marks.push((x, y));
                            None
                        }
                    })
                    .collect();
                pts.sort_by(|a, b| a.0.total_cmp(&b.0));
                curves.push(Curve {
                    name: format!(
                        "{views}, ξ {}{}",
                        if deform { "on" } else { "off" },
                        if refine { ", refined" } else { "" }
                    ),
                    points: pts,
                });
            }
        }
        lines_png(
            &out.join(file),
            &Axes {
                title: &format!("{} steps of the {} preset", rep.steps, rep.preset),
                x_desc: "proxy's RMS distance to the true surface (% of the bounding-box diagonal)",
                y_desc: ylabel,
                log_x: false,
            },
            &curves,
            &marks,
            "decimated proxy",
        )?;
    }
    Ok(())
}

fn write_outputs(out: &Path, rep: &GeometryReport) -> Result<()> {
    let w = |name: &str, text: String| {
        let p = out.join(name);
        std::fs::write(&p, text).with_context(|| format!("{}: cannot write", p.display()))
    };
    w("geometry.csv", csv(rep))?;
    w("geometry.md", markdown(rep))?;
    w("geometry.json", serde_json::to_string_pretty(rep)?)?;
    plots(out, rep)
}
