//! The paper's ablations and the baseline it argues against, on one scene with one step budget
//! (`xscale ablate`): Table 4 (featurization enhancements), Table 5 (mesh resolution) and the
//! vertex-feature featurization of Fig. 2b.
//!
//! Variants (each a run folder `OUT/<name>/` written by the ordinary trainer, so every one can
//! be re-evaluated or rendered with `xscale eval/render --run`):
//! - `full`: the preset as it is (cpu: grid H, ξ on, γ = 2) — Table 4 "Full Implementation".
//! - `no_deform`: `[model.deform] enabled = false` — Table 4 "w/o Deformation".
//! - `no_multisampling`: `[model] gamma = 1` — Table 4 "w/o Multisampling".
//! - `mesh10`: the full model on the scene mesh decimated to `ratio` (10%) of its faces with
//!   quadric error metrics (`scene::mesh::decimate`) — Table 5.
//! - `vertex`: the Fig. 2b baseline on the scene mesh: Z features per vertex, Z chosen so the
//!   parameter count matches the full model's, clamped to `1..=Z_MAX` (256; beyond a few dozen,
//!   width buys little expressiveness — a triangle's interpolated features span a 2-D affine
//!   patch whatever Z is — so the cap only matters for meshes far too coarse for parity).
//! - `vertex_subdiv`: the same on the mesh midpoint-subdivided `k` times, `k` the smallest level
//!   with `P_full / V_k ≤ Z_SUBDIV` (16), so the baseline gets a parameter budget comparable to
//!   the hash grid's at a moderate Z (the small proxy meshes are far too coarse for that). The
//!   subdivided surface is the same surface; only the feature discretisation is finer.
//! - `ulr`: no learning at all: the held-out views rendered by unstructured lumigraph rendering
//!   of the training photos on the scene mesh (`render/ulr.rs`), zero training time.
//!
//! Every variant but `ulr` trains `steps` steps with the same seed and batch size, then is scored on every
//! held-out view (SPEC §7: masked = the pixels whose rays hit the mesh; full = every pixel, the render
//! against the photo as it is). The
//! table goes to `OUT/ablation.md`, the numbers to `OUT/ablation.json`. `minutes` (when no step
//! count is given) sets the step count from a 20-step timing probe of the full model so that
//! the full model trains for about that long; every variant then uses that same step count.

use crate::eval::protocol::ViewScore;
use crate::experiments::variant::{ulr_scores, Runs};
use crate::model::config::Featurization;
use crate::run::run_dir::Existing;
use crate::run::trainer::{train, TrainOptions};
use crate::scene::mesh::{decimate_report, subdivide, write_ply};
use crate::scene::{LoadOptions, Mesh, Scene};
use crate::train::config::RunConfig;
use anyhow::{bail, ensure, Context, Result};
use serde::{Deserialize, Serialize};
use std::fmt::Write as _;
use std::path::{Path, PathBuf};

/// The fraction of faces `mesh10` keeps unless told (the paper's Table 5: 10 %).
pub const DEFAULT_RATIO: f64 = 0.1;

/// Largest vertex feature width the `vertex` variant uses.
pub const Z_MAX: u32 = 256;
/// Target vertex feature width of the `vertex_subdiv` variant.
pub const Z_SUBDIV: u32 = 16;
/// Most subdivision levels `vertex_subdiv` will use (× 1024 faces).
pub const MAX_SUBDIV: u32 = 5;

/// One ablation variant (module doc), in table order.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum Variant {
    #[value(name = "full")]
    Full,
    #[value(name = "no_deform")]
    NoDeform,
    #[value(name = "no_multisampling")]
    NoMultisampling,
    #[value(name = "mesh10")]
    Mesh10,
    #[value(name = "vertex")]
    Vertex,
    #[value(name = "vertex_subdiv")]
    VertexSubdiv,
    #[value(name = "ulr")]
    Ulr,
}

impl Variant {
    /// Every variant, in table order.
    pub const ALL: [Variant; 7] = [
        Variant::Full,
        Variant::NoDeform,
        Variant::NoMultisampling,
        Variant::Mesh10,
        Variant::Vertex,
        Variant::VertexSubdiv,
        Variant::Ulr,
    ];

    /// The name used on the command line, as the run folder and in the reports.
    pub fn name(self) -> &'static str {
        match self {
            Variant::Full => "full",
            Variant::NoDeform => "no_deform",
            Variant::NoMultisampling => "no_multisampling",
            Variant::Mesh10 => "mesh10",
            Variant::Vertex => "vertex",
            Variant::VertexSubdiv => "vertex_subdiv",
            Variant::Ulr => "ulr",
        }
    }

    pub fn description(self) -> &'static str {
        match self {
            Variant::Full => "full model (hash grid H + deformation ξ + multisampling)",
            Variant::NoDeform => "w/o deformation (Eq. 5 off)",
            Variant::NoMultisampling => "w/o multisampling (γ = 1)",
            Variant::Mesh10 => "full model on the decimated mesh",
            Variant::Vertex => "vertex features (Fig. 2b) on the scene mesh",
            Variant::VertexSubdiv => "vertex features (Fig. 2b) on the subdivided mesh",
            Variant::Ulr => "no learning: unstructured lumigraph rendering of the training photos",
        }
    }
}

impl Serialize for Variant {
    fn serialize<S: serde::Serializer>(&self, s: S) -> std::result::Result<S::Ok, S::Error> {
        s.serialize_str(self.name())
    }
}

impl<'de> Deserialize<'de> for Variant {
    fn deserialize<D: serde::Deserializer<'de>>(d: D) -> std::result::Result<Self, D::Error> {
        let s = String::deserialize(d)?;
        Variant::ALL
            .into_iter()
            .find(|v| v.name() == s)
            .ok_or_else(|| serde::de::Error::custom(format!("unknown ablation variant {s:?}")))
    }
}

/// How to run the ablation.
#[derive(Clone, Debug)]
pub struct AblateOptions {
    /// The base configuration every variant is derived from, and how they train. An interrupt
    /// ends the ablation with the variants it finished ([`AblationReport::stopped`]).
    pub runs: Runs,
    /// Variants to run, in table order.
    pub variants: Vec<Variant>,
    /// Face ratio of the decimated mesh (`mesh10`); `None`: the earlier ablation's when appending,
    /// else [`DEFAULT_RATIO`].
    pub ratio: Option<f64>,
    /// Subdivision levels of `vertex_subdiv` (`None` = automatic, see the module doc).
    pub subdivide: Option<u32>,
    /// Set the step count from a timing probe so the full model trains about this long.
    pub minutes: Option<f64>,
    /// Whether the step count was given (`--steps`) rather than taken from the preset.
    pub steps_given: bool,
    /// What to do with an earlier ablation in the output folder (`OUT/ablation.json`).
    pub existing: Existing,
}

/// One variant's result.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct VariantResult {
    pub name: Variant,
    pub description: String,
    pub featurization: String,
    pub gamma: u32,
    pub deform: bool,
    /// Mesh used: file, faces, vertices.
    pub mesh: String,
    pub mesh_faces: usize,
    pub mesh_vertices: usize,
    /// Z (vertex featurization) or L·F (hash), the pooled feature width.
    pub feature_width: usize,
    /// Total parameters (layout.total).
    pub params: usize,
    /// params / params of `full` (when `full` ran).
    pub params_ratio: Option<f64>,
    pub steps: u64,
    /// Training loop wall time (excludes the ray cast and the final evaluation).
    pub train_seconds: f64,
    pub mean: ViewScore,
    pub views: Vec<ViewScore>,
}

/// The whole ablation.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct AblationReport {
    pub scene: PathBuf,
    pub preset: String,
    pub steps: u64,
    pub batch_pixels: usize,
    pub seed: u64,
    /// The base configuration every variant is derived from (TOML, its step count included);
    /// empty in reports written before it was recorded.
    #[serde(default)]
    pub base_config: String,
    /// The fraction of faces `mesh10` keeps (`--ratio`), shared by the whole table; absent in
    /// reports written before it was recorded.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub ratio: Option<f64>,
    pub results: Vec<VariantResult>,
    /// The claims, checked on the measured numbers.
    pub claims: Vec<Claim>,
    /// When interrupted: the variants asked for that did not finish (the first was stopped
    /// mid-training), in table order. Not stored in `ablation.json`.
    #[serde(skip)]
    pub stopped: Vec<Variant>,
}

#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct Claim {
    pub claim: String,
    /// `None` when a variant it needs did not run.
    pub holds: Option<bool>,
    pub measured: String,
}

/// Parameters of the shader + appearance codes for a feature width (what a vertex model has
/// besides its table), used to pick Z.
fn vertex_param_count(base: &RunConfig, n_vertices: usize, z: u32, train_views: usize) -> usize {
    let s = &base.model.shader;
    let (w, h) = (s.width as usize, s.hidden_layers as usize);
    let a = base.model.appearance_dim as usize;
    let din = z as usize + 16 + a;
    let mut mlp = 0;
    let mut prev = din;
    for _ in 0..h {
        mlp += prev * w + if s.bias { w } else { 0 };
        prev = w;
    }
    mlp += prev * 3 + if s.bias { 3 } else { 0 };
    n_vertices * z as usize + mlp + a * train_views
}

/// The Z (1..=z_max) whose vertex model's parameter count is closest to `target`.
pub fn choose_z(
    base: &RunConfig,
    n_vertices: usize,
    target: usize,
    z_max: u32,
    train_views: usize,
) -> u32 {
    (1..=z_max)
        .min_by_key(|&z| {
            let p = vertex_param_count(base, n_vertices, z, train_views) as f64;
            // Distance in log space (a ratio), as "within 2×" is.
            ((p / target as f64).ln().abs() * 1e6) as u64
        })
        .unwrap_or(1)
}

/// Run every requested variant on `scene` into `out`; writes `ablation.md` and `ablation.json`
/// after every variant (so an interrupted ablation keeps the variants it finished). An earlier
/// ablation in `out` is handled as `opts.existing` says: refused, kept (`Append`: its variants
/// not run again stay in the table; the step count and base configuration must be the same) or
/// replaced.
pub fn run_ablation(scene: &Path, out: &Path, opts: &AblateOptions) -> Result<AblationReport> {
    check_options(opts)?;
    let earlier = earlier_ablation(out, opts)?;
    let ratio = table_ratio(out, opts, earlier.as_ref())?;
    std::fs::create_dir_all(out).with_context(|| format!("{}: cannot create", out.display()))?;
    let say = |s: String| {
        if !opts.runs.quiet {
            eprintln!("{s}");
        }
    };
    let mut base = opts.runs.base.clone();
    base.validate()?;
    ensure!(
        base.model.featurization.is_hash(),
        "ablate: the base configuration must be a hash model (the vertex variants are derived from it)"
    );
    let ctx = Shared::load(scene, out, &base, ratio, opts.subdivide)?;
    // A --subdivide that cannot fit is refused before the first variant trains, not hours later.
    if let (true, Some(k)) = (
        opts.variants.contains(&Variant::VertexSubdiv),
        opts.subdivide,
    ) {
        check_subdivision(&ctx.mesh, k, &format!("--subdivide {k}"))?;
    }
    std::fs::create_dir_all(&ctx.mesh_dir)
        .with_context(|| format!("{}: cannot create", ctx.mesh_dir.display()))?;
    base.train.steps = step_budget(scene, out, opts, &base, earlier.as_ref(), &say)?;
    crate::train::config::set_tool_run(&mut base);
    let base_config = base.results_toml();
    let mut results = match earlier {
        Some(old) => kept_results(old, scene, opts, &base, &base_config, &say)?,
        None => Vec::new(),
    };
    let interrupted = || {
        opts.runs
            .interrupt
            .is_some_and(|f| f.load(std::sync::atomic::Ordering::SeqCst))
    };
    let report_of = |results: &[VariantResult]| AblationReport {
        scene: scene.to_path_buf(),
        preset: base.preset.clone(),
        steps: base.train.steps,
        batch_pixels: base.train.batch_pixels,
        seed: base.train.seed,
        base_config: base_config.clone(),
        ratio: Some(ratio),
        claims: check_claims(results),
        results: results.to_vec(),
        stopped: Vec::new(),
    };
    for (k, &v) in opts.variants.iter().enumerate() {
        let stop = |results: &[VariantResult]| AblationReport {
            stopped: opts.variants[k..].to_vec(),
            ..report_of(results)
        };
        if interrupted() {
            return Ok(stop(&results));
        }
        let full_params = results
            .iter()
            .find(|r| r.name == Variant::Full)
            .map(|r| r.params);
        let r = if v == Variant::Ulr {
            ulr_variant(&ctx, &say)?
        } else {
            let variant = configure(v, &base, &ctx, full_params, &say)?;
            let run = out.join(v.name());
            match run_variant(variant, &ctx, &run, full_params, opts, &say)? {
                Some(r) => r,
                None => return Ok(stop(&results)),
            }
        };
        results.push(r);
        results.sort_by_key(|r| Variant::ALL.iter().position(|&v| v == r.name));
        write_report(out, &report_of(&results))?;
    }
    Ok(report_of(&results))
}

/// Options only a later variant uses, checked before the first one trains.
fn check_options(opts: &AblateOptions) -> Result<()> {
    ensure!(!opts.variants.is_empty(), "no variants to run");
    if let (true, Some(r)) = (opts.variants.contains(&Variant::Mesh10), opts.ratio) {
        ensure!(
            r.is_finite() && r > 0.0 && r <= 1.0,
            "--ratio {r}: must be in (0, 1] (the fraction of faces mesh10 keeps)"
        );
    }
    if let (true, Some(k)) = (
        opts.variants.contains(&Variant::VertexSubdiv),
        opts.subdivide,
    ) {
        ensure!(k <= 6, "--subdivide {k}: at most 6 levels (× 4096 faces)");
    }
    Ok(())
}

/// The earlier ablation in `out` that this one adds to (`--append`), `None` when there is none
/// or it is to be replaced; one there without `--append` or `--overwrite` is refused. Read before
/// anything is written or trained: a refusal or a bad file loses nothing.
fn earlier_ablation(out: &Path, opts: &AblateOptions) -> Result<Option<AblationReport>> {
    let json = out.join("ablation.json");
    let earlier = match opts.existing {
        Existing::Overwrite => None,
        _ if !json.is_file() => None,
        _ => Some(read_report(&json).context("an earlier ablation (--overwrite replaces it)")?),
    };
    if let (Some(old), Existing::Refuse) = (&earlier, opts.existing) {
        bail!(
            "{}: holds an earlier ablation ({} steps per variant: {}); add --append to run variants into it (a variant run again replaces its result), --overwrite to replace it, or choose another --out",
            json.display(),
            old.steps,
            variant_names(&old.results)
        );
    }
    Ok(earlier)
}

/// The fraction of faces `mesh10` keeps. One table, one decimation ratio: an appended ablation
/// keeps the earlier one (its mesh10 row, kept or run again, is judged by the same Table 5
/// claim).
fn table_ratio(out: &Path, opts: &AblateOptions, earlier: Option<&AblationReport>) -> Result<f64> {
    let earlier_ratio = earlier.and_then(recorded_ratio);
    if let (Some(r), Some(then)) = (opts.ratio, earlier_ratio) {
        if r != then {
            bail!(
                "--append: the earlier ablation in {} has --ratio {then} (the fraction of faces mesh10 keeps); the variants of one table share it (leave out --ratio, or give --ratio {then})",
                out.display()
            );
        }
    }
    Ok(opts.ratio.or(earlier_ratio).unwrap_or(DEFAULT_RATIO))
}

/// The steps every variant trains: the base configuration's, an appended ablation's earlier
/// count (one table, one step budget), or (`--minutes`) what a timing probe of the full model
/// says fits.
fn step_budget(
    scene: &Path,
    out: &Path,
    opts: &AblateOptions,
    base: &RunConfig,
    earlier: Option<&AblationReport>,
    say: &dyn Fn(String),
) -> Result<u64> {
    match earlier {
        Some(old) => {
            if opts.minutes.is_some() || (opts.steps_given && base.train.steps != old.steps) {
                bail!(
                    "--append: the earlier ablation in {} ran {} steps per variant; the variants of one table share a step count (leave out --steps/--minutes, or give --steps {})",
                    out.display(),
                    old.steps,
                    old.steps
                );
            }
            Ok(old.steps)
        }
        None => match opts.minutes {
            Some(m) => {
                let steps = probe_steps(scene, &out.join("probe"), base, m)?;
                say(format!(
                    "probe: {steps} steps for {m} min of the full model"
                ));
                Ok(steps)
            }
            None => Ok(base.train.steps),
        },
    }
}

/// The earlier ablation's results this one keeps (the variants it does not run again), once it
/// is found to be the same ablation (scene and base configuration).
fn kept_results(
    old: AblationReport,
    scene: &Path,
    opts: &AblateOptions,
    base: &RunConfig,
    base_config: &str,
    say: &dyn Fn(String),
) -> Result<Vec<VariantResult>> {
    same_ablation(&old, scene, base, base_config)?;
    let (again, kept): (Vec<_>, Vec<_>) = old
        .results
        .into_iter()
        .partition(|r| opts.variants.contains(&r.name));
    if !kept.is_empty() {
        say(format!(
            "--append: keeping {} from the earlier ablation",
            variant_names(&kept)
        ));
    }
    if !again.is_empty() {
        say(format!(
            "--append: {} run again (their earlier results are replaced)",
            variant_names(&again)
        ));
    }
    Ok(kept)
}

/// `OUT/ablation.json` as written by [`run_ablation`].
pub fn read_report(path: &Path) -> Result<AblationReport> {
    let text = std::fs::read_to_string(path)
        .with_context(|| format!("{}: cannot read", path.display()))?;
    serde_json::from_str(&text)
        .with_context(|| format!("{}: not an ablation report (ablation.json)", path.display()))
}

/// The `--ratio` an earlier ablation decimated `mesh10` with: recorded, or (reports from before
/// it was) read from its mesh10 row's mesh, `meshes/decimated_<ratio>.ply`.
fn recorded_ratio(old: &AblationReport) -> Option<f64> {
    old.ratio.or_else(|| {
        let r = old.results.iter().find(|r| r.name == Variant::Mesh10)?;
        let stem = Path::new(&r.mesh).file_stem()?.to_str()?;
        stem.strip_prefix("decimated_")?.parse().ok()
    })
}

/// The variants' names, comma-separated.
fn variant_names(results: &[VariantResult]) -> String {
    let names: Vec<&str> = results.iter().map(|r| r.name.name()).collect();
    names.join(", ")
}

/// An error naming what differs when this ablation's scene or base configuration is not the
/// earlier one's (the variants of one table must share them).
fn same_ablation(
    old: &AblationReport,
    scene: &Path,
    base: &RunConfig,
    base_config: &str,
) -> Result<()> {
    let canon = |p: &Path| std::fs::canonicalize(p).unwrap_or_else(|_| p.to_path_buf());
    let mut diffs = Vec::new();
    if canon(&old.scene) != canon(scene) {
        diffs.push(format!(
            "scene {} (the earlier ablation's is {})",
            scene.display(),
            old.scene.display()
        ));
    }
    if old.base_config.is_empty() {
        // A report from before the configuration was recorded: what it does say.
        let said = [
            ("preset", base.preset.clone(), old.preset.clone()),
            (
                "batch",
                base.train.batch_pixels.to_string(),
                old.batch_pixels.to_string(),
            ),
            ("seed", base.train.seed.to_string(), old.seed.to_string()),
        ];
        for (what, now, then) in said.into_iter().filter(|(_, n, t)| n != t) {
            diffs.push(format!("{what} {now} (the earlier ablation's is {then})"));
        }
    } else {
        let parse = |t: &str| toml::from_str::<toml::Value>(t);
        let (now, then) = (
            parse(base_config).expect("a RunConfig serialises"),
            parse(&old.base_config).context("the earlier ablation's base_config")?,
        );
        diffs.extend(crate::train::config::toml_differences(
            &now,
            &then,
            "the earlier ablation",
        ));
    }
    if !diffs.is_empty() {
        bail!(
            "--append: this ablation differs from the earlier one, and the variants of one table must share their scene and base configuration:\n  {}\nrun with the earlier options, or use another --out (or --overwrite)",
            diffs.join("\n  ")
        );
    }
    Ok(())
}

/// What every variant shares: the scene, its mesh and where derived meshes go.
struct Shared<'a> {
    scene: &'a Path,
    load: LoadOptions,
    mesh: Mesh,
    mesh_path: String,
    mesh_dir: PathBuf,
    n_train: usize,
    ratio: f64,
    subdivide: Option<u32>,
    /// The base configuration's γ: the ULR baseline casts its pixels as the models do.
    gamma: u32,
}

impl<'a> Shared<'a> {
    /// The scene's own mesh (or the base configuration's `train.mesh`) and what every variant
    /// shares; a scene without held-out views is refused (nothing to evaluate).
    fn load(
        scene: &'a Path,
        out: &Path,
        base: &RunConfig,
        ratio: f64,
        subdivide: Option<u32>,
    ) -> Result<Shared<'a>> {
        let load = LoadOptions {
            downsample: base.train.downsample,
            normalize: base.train.normalize,
            mesh: base.train.mesh.clone(),
            ..LoadOptions::default()
        };
        let (sc, report) = Scene::load_report(scene, &load)?;
        if sc.test.is_empty() {
            bail!(
                "{}: the scene has no held-out views to evaluate",
                scene.display()
            );
        }
        Ok(Shared {
            scene,
            load,
            mesh_dir: out.join("meshes"),
            mesh_path: report.mesh_path.display().to_string(),
            n_train: sc.views.len() - sc.test.len(),
            mesh: sc.mesh,
            ratio,
            subdivide,
            gamma: base.model.gamma,
        })
    }
}

/// The mesh a variant trained on: file, faces, vertices.
type UsedMesh = (String, usize, usize);

/// A variant ready to train: its configuration and the mesh it trains on.
struct Configured {
    variant: Variant,
    cfg: RunConfig,
    mesh: UsedMesh,
}

/// The step count that makes the full model train about `minutes` (a 20-step timing probe).
fn probe_steps(scene: &Path, probe_dir: &Path, base: &RunConfig, minutes: f64) -> Result<u64> {
    ensure!(minutes > 0.0, "--minutes must be positive");
    let mut cfg = base.clone();
    cfg.train.steps = 20;
    cfg.train.budget = crate::train::config::StepBudget::Fixed;
    cfg.train.eval_every = 0;
    cfg.train.checkpoint_every = 0;
    let s = train(
        scene,
        probe_dir,
        cfg,
        &TrainOptions {
            no_final_eval: true,
            quiet: true,
            // An ablation re-run into the same folder replaces its variant runs.
            overwrite: true,
            ..TrainOptions::default()
        },
    )?;
    let per_step = s.seconds / s.steps.max(1) as f64;
    let _ = std::fs::remove_dir_all(probe_dir);
    Ok(((minutes * 60.0 / per_step).floor() as u64).max(1))
}

/// The variant's configuration (and the mesh it trains on, written under `meshes/` when derived).
fn configure(
    v: Variant,
    base: &RunConfig,
    ctx: &Shared,
    full_params: Option<usize>,
    say: &dyn Fn(String),
) -> Result<Configured> {
    let mut cfg = base.clone();
    let mut used: UsedMesh = (
        ctx.mesh_path.clone(),
        ctx.mesh.triangles.len(),
        ctx.mesh.vertices.len(),
    );
    match v {
        Variant::Full => {}
        Variant::Ulr => unreachable!("ULR trains nothing (ulr_variant)"),
        Variant::NoDeform => cfg.model.deform.enabled = false,
        Variant::NoMultisampling => cfg.model.gamma = 1,
        Variant::Mesh10 => {
            let (m, r) = decimate_report(&ctx.mesh, ctx.ratio)?;
            let path = ctx.mesh_dir.join(format!("decimated_{}.ply", ctx.ratio));
            write_ply(&path, &m)?;
            say(format!(
                "mesh10: decimated {} → {} faces (target {}), relative error {:.2e} → {}",
                r.faces_in,
                r.faces_out,
                r.faces_target,
                r.relative_error,
                path.display()
            ));
            used = (
                path.display().to_string(),
                m.triangles.len(),
                m.vertices.len(),
            );
            cfg.train.mesh = Some(std::fs::canonicalize(&path).unwrap_or(path));
        }
        Variant::Vertex | Variant::VertexSubdiv => {
            let target = match full_params {
                Some(p) => p,
                None => hash_params(ctx.scene, base)?,
            };
            let m = if v == Variant::Vertex {
                ctx.mesh.clone()
            } else {
                let (m, path) = subdivided(ctx, target, say)?;
                used = (
                    path.display().to_string(),
                    m.triangles.len(),
                    m.vertices.len(),
                );
                cfg.train.mesh = Some(std::fs::canonicalize(&path).unwrap_or(path));
                m
            };
            let z = choose_z(base, m.vertices.len(), target, Z_MAX, ctx.n_train);
            say(format!(
                "{}: Z = {z} features per vertex on {} vertices (closest to the hash model's {target} parameters, Z ≤ {Z_MAX})",
                v.name(),
                m.vertices.len()
            ));
            cfg.model.featurization = Featurization::Vertex;
            cfg.model.vertex_features = z;
            // The baseline has no hash grid: no deformation (grid D) and no level weighting.
            cfg.model.deform.enabled = false;
            cfg.model.level_weight = crate::model::config::LevelWeight::None;
        }
    }
    Ok(Configured {
        variant: v,
        cfg,
        mesh: used,
    })
}

/// The hash model's parameter count on this scene, from an initialisation-only model of `base`
/// (used to size the vertex baselines when `full` did not run first).
fn hash_params(scene: &Path, base: &RunConfig) -> Result<usize> {
    let prepared = crate::train::setup::prepare(scene, base, false, &mut |_| {})?;
    let (_, ckpt) = prepared.init_model(base.clone(), &mut |_| {})?;
    Ok(ckpt.model.layout.total)
}

/// Refuse, before subdividing, `levels` rounds of `mesh` for `vertex_subdiv` that cannot fit in
/// memory (the check `xscale subdivide` makes: an allocation that fails aborted the ablation
/// without a word, exit 134); `what` names the request.
fn check_subdivision(mesh: &Mesh, levels: u32, what: &str) -> Result<()> {
    crate::scene::remesh::check_subdivide(
        mesh,
        levels,
        &format!("vertex_subdiv: {what}"),
        "give --subdivide fewer levels, or leave vertex_subdiv out of --variants",
    )
}

/// `vertex_subdiv`'s mesh: subdivided `ctx.subdivide` levels, or the smallest k with
/// `target / V_k ≤ Z_SUBDIV` (module doc); written to `meshes/subdivided_<k>.ply`.
fn subdivided(ctx: &Shared, target: usize, say: &dyn Fn(String)) -> Result<(Mesh, PathBuf)> {
    let levels = match ctx.subdivide {
        Some(k) => k,
        None => {
            // Vertex counts by subdividing one level at a time.
            let mut k = 0;
            let mut m = ctx.mesh.clone();
            while k < MAX_SUBDIV && target as f64 / m.vertices.len() as f64 > Z_SUBDIV as f64 {
                check_subdivision(&m, 1, &format!("subdivision level {} (automatic)", k + 1))?;
                m = subdivide(&m, 1)?;
                k += 1;
            }
            k.max(1)
        }
    };
    let what = match ctx.subdivide {
        Some(k) => format!("--subdivide {k}"),
        None => format!("{levels} subdivision levels (automatic)"),
    };
    check_subdivision(&ctx.mesh, levels, &what)?;
    let m = subdivide(&ctx.mesh, levels)?;
    let path = ctx.mesh_dir.join(format!("subdivided_{levels}.ply"));
    write_ply(&path, &m)?;
    say(format!(
        "vertex_subdiv: {levels} subdivision levels: {} → {} faces, {} vertices → {}",
        ctx.mesh.triangles.len(),
        m.triangles.len(),
        m.vertices.len(),
        path.display()
    ));
    Ok((m, path))
}

/// Train one variant into `run_dir` and collect its scores (returned by the trainer); `None`
/// when an interrupt stopped its training.
fn run_variant(
    variant: Configured,
    ctx: &Shared,
    run_dir: &Path,
    full_params: Option<usize>,
    opts: &AblateOptions,
    say: &dyn Fn(String),
) -> Result<Option<VariantResult>> {
    let Configured {
        variant: v,
        cfg,
        mesh: used_mesh,
    } = variant;
    say(format!(
        "== {}: {} ({} steps of {} pixels) → {}",
        v.name(),
        v.description(),
        cfg.train.steps,
        cfg.train.batch_pixels,
        run_dir.display()
    ));
    // A variant stopped halfway (the command an interrupt prints) continues from its checkpoint.
    let resume =
        opts.existing != Existing::Overwrite && crate::run::run_dir::stopped_run_of(run_dir, &cfg);
    if resume {
        say(format!(
            "   {}: continuing the stopped run in {}",
            v.name(),
            run_dir.display()
        ));
    }
    let summary = opts
        .runs
        .train(ctx.scene, run_dir, &cfg, resume)
        .with_context(|| format!("ablation variant {}", v.name()))?;
    if summary.interrupted {
        return Ok(None);
    }
    // The model only: its Adam state (three quarters of the file) is not needed here.
    let ckpt = crate::model::checkpoint::Checkpoint::load(run_dir.join("checkpoint.safetensors"))?;
    let params = ckpt.model.layout.total;
    let mean = summary
        .final_scores
        .clone()
        .context("the run has no final evaluation")?;
    let r = VariantResult {
        name: v,
        description: v.description().to_string(),
        featurization: if cfg.model.featurization.is_hash() {
            "hash".into()
        } else {
            "vertex".into()
        },
        gamma: cfg.model.gamma,
        deform: cfg.model.deform.enabled,
        mesh: used_mesh.0,
        mesh_faces: used_mesh.1,
        mesh_vertices: used_mesh.2,
        feature_width: ckpt.model.feat_dim(),
        params,
        params_ratio: full_params
            .or((v == Variant::Full).then_some(params))
            .map(|f| params as f64 / f as f64),
        steps: summary.steps,
        train_seconds: summary.seconds,
        mean,
        views: summary.views,
    };
    say(format!(
        "   {}: PSNR masked {:.2} / full {:.2}, SSIM masked {:.4}, {} params, {:.1} s",
        v.name(),
        r.mean.psnr_masked,
        r.mean.psnr,
        r.mean.ssim_masked,
        r.params,
        r.train_seconds
    ));
    Ok(Some(r))
}

/// The ULR baseline (`render::ulr`) on the held-out views: no training, no parameters.
fn ulr_variant(ctx: &Shared, say: &dyn Fn(String)) -> Result<VariantResult> {
    let v = Variant::Ulr;
    say(format!("== ulr: {}", v.description()));
    let sc = Scene::load(ctx.scene, &ctx.load)?;
    let tracer = crate::raycast::Tracer::new(&sc.mesh, &sc.normalization)?;
    let sources = crate::render::ulr::training_sources(&sc)?;
    let views = ulr_scores(&sc, &tracer, &sources, ctx.gamma)?;
    let mean = crate::eval::protocol::mean_score(&views);
    say(format!(
        "   ulr: PSNR masked {:.2} / full {:.2}, SSIM masked {:.4}, no training",
        mean.psnr_masked, mean.psnr, mean.ssim_masked
    ));
    Ok(VariantResult {
        name: v,
        description: v.description().to_string(),
        featurization: "none (photos)".into(),
        gamma: 1,
        deform: false,
        mesh: ctx.mesh_path.clone(),
        mesh_faces: ctx.mesh.triangles.len(),
        mesh_vertices: ctx.mesh.vertices.len(),
        feature_width: 0,
        params: 0,
        params_ratio: None,
        steps: 0,
        train_seconds: 0.0,
        mean,
        views,
    })
}

/// `OUT/ablation.md` and `OUT/ablation.json`, each written whole or not at all.
fn write_report(out: &Path, rep: &AblationReport) -> Result<()> {
    crate::io::atomic::write_bytes(&out.join("ablation.md"), markdown(rep))?;
    crate::io::atomic::write_bytes(
        &out.join("ablation.json"),
        serde_json::to_string_pretty(rep)?,
    )
}

/// The claims on the measured masked PSNR.
fn check_claims(results: &[VariantResult]) -> Vec<Claim> {
    let get = |n: Variant| {
        results
            .iter()
            .find(|r| r.name == n)
            .map(|r| r.mean.psnr_masked)
    };
    let mut out = Vec::new();
    let mut diff = |claim: &str, a: Variant, b: Variant, test: &dyn Fn(f64) -> bool| {
        let (holds, measured) = match (get(a), get(b)) {
            (Some(x), Some(y)) => (
                Some(test(x - y)),
                format!(
                    "{} {x:.2} dB − {} {y:.2} dB = {:+.2} dB",
                    a.name(),
                    b.name(),
                    x - y
                ),
            ),
            _ => (None, format!("needs {} and {}", a.name(), b.name())),
        };
        out.push(Claim {
            claim: claim.to_string(),
            holds,
            measured,
        });
    };
    diff(
        "the full model beats the vertex-feature baseline by ≥ 2 dB (masked PSNR)",
        Variant::Full,
        Variant::Vertex,
        &|d| d >= 2.0,
    );
    diff(
        "the full model beats the parameter-matched (subdivided) vertex baseline by ≥ 2 dB",
        Variant::Full,
        Variant::VertexSubdiv,
        &|d| d >= 2.0,
    );
    diff(
        "removing deformation costs PSNR (Table 4)",
        Variant::Full,
        Variant::NoDeform,
        &|d| d > 0.0,
    );
    diff(
        "removing multisampling costs PSNR (Table 4)",
        Variant::Full,
        Variant::NoMultisampling,
        &|d| d > 0.0,
    );
    diff(
        "w/o multisampling is worse than w/o deformation (Table 4 ordering)",
        Variant::NoDeform,
        Variant::NoMultisampling,
        &|d| d > 0.0,
    );
    diff(
        "the decimated mesh costs ≤ 1 dB (Table 5)",
        Variant::Full,
        Variant::Mesh10,
        &|d| d <= 1.0,
    );
    diff(
        "learning beats reprojecting the photos: the full model over the ULR baseline (masked PSNR)",
        Variant::Full,
        Variant::Ulr,
        &|d| d > 0.0,
    );
    out
}

/// The markdown table (`ablation.md`).
pub fn markdown(rep: &AblationReport) -> String {
    let mut s = String::new();
    let _ = writeln!(s, "# Ablation: {}\n", rep.scene.display());
    let _ = writeln!(
        s,
        "Preset `{}`, {} steps of {} pixels, seed {}, every variant the same budget; scores are means over all held-out views (SPEC §7: masked = the pixels whose rays hit the mesh; full = every pixel, the render against the photo as it is, so a silhouette error of the mesh counts). Produced by `xscale ablate`.\n",
        rep.preset, rep.steps, rep.batch_pixels, rep.seed
    );
    let _ = writeln!(
        s,
        "| variant | featurization | mesh faces | γ | ξ | feature width | params | params / full | PSNR masked | SSIM masked | PSNR full | SSIM full | train s |"
    );
    let _ = writeln!(
        s,
        "|---|---|---:|---:|---|---:|---:|---:|---:|---:|---:|---:|---:|"
    );
    for r in &rep.results {
        let _ = writeln!(
            s,
            "| {} | {} | {} | {} | {} | {} | {} | {} | {:.2} | {:.4} | {:.2} | {:.4} | {:.1} |",
            r.name.name(),
            r.featurization,
            r.mesh_faces,
            r.gamma,
            if r.deform { "on" } else { "off" },
            r.feature_width,
            r.params,
            r.params_ratio.map_or("–".into(), |x| format!("{x:.2}")),
            r.mean.psnr_masked,
            r.mean.ssim_masked,
            r.mean.psnr,
            r.mean.ssim,
            r.train_seconds
        );
    }
    let _ = writeln!(s, "\nVariants:\n");
    for r in &rep.results {
        let _ = writeln!(
            s,
            "- `{}`: {}; mesh `{}` ({} faces, {} vertices).",
            r.name.name(),
            r.description,
            r.mesh,
            r.mesh_faces,
            r.mesh_vertices
        );
    }
    let _ = writeln!(s, "\nClaims (masked PSNR):\n");
    for c in &rep.claims {
        let verdict = match c.holds {
            Some(true) => "holds",
            Some(false) => "does NOT hold",
            None => "not measured",
        };
        let _ = writeln!(s, "- {}: **{verdict}** ({})", c.claim, c.measured);
    }
    let _ = writeln!(
        s,
        "\nPaper, for orientation (TW-Pavilion, GigaNVS; PSNR / SSIM / LPIPS): Table 4 full 23.02 / 0.786 / 0.113, w/o deformation 22.77 / 0.775 / 0.131, w/o multisampling 22.24 / 0.752 / 0.140; Table 5 10M faces 23.02 / 0.786 / 0.113, 1M faces 22.84 / 0.782 / 0.114."
    );
    s
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn z_matches_the_parameter_budget() {
        let base = RunConfig::preset("cpu").unwrap();
        // 1M vertices and a 13.7M-parameter hash model: Z ≈ 13.7.
        let z = choose_z(&base, 1_000_000, 13_700_000, 64, 34);
        assert!((13..=14).contains(&z), "{z}");
        let p = vertex_param_count(&base, 1_000_000, z, 34) as f64;
        assert!((p / 13.7e6 - 1.0).abs() < 0.05, "{p}");
        // A tiny mesh saturates at Z_MAX.
        assert_eq!(choose_z(&base, 4000, 13_700_000, 64, 34), 64);
        // Shader: (Z+16+4)·64 + 64·64 + 64·3, codes 4·34.
        assert_eq!(
            vertex_param_count(&base, 10, 8, 34),
            80 + 28 * 64 + 64 * 64 + 64 * 3 + 4 * 34
        );
    }
}
