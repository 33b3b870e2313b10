//! From a scene directory to what training needs (SPEC §1, §8): load the scene, build the BVH,
//! check the memory budget, cast every training view once (its hit map for the ray stream, or
//! all its samples for the cache — `train/sampler.rs`) while checking its photo against the mesh
//! (`raycast/consistency.rs`), and drop hash levels no view resolves.

use crate::model::checkpoint::{init_checkpoint_for_mesh, Checkpoint};
use crate::model::config::{per_level_scale_for, GridConfig};
use crate::model::hashgrid::tcnn_scales;
use crate::model::ModelConfig;
use crate::raycast::consistency::PhotoCheck;
use crate::raycast::{CacheEvent, Targets, Tracer};
use crate::scene::Camera;
use crate::scene::{LoadOptions, LoadReport, MaskSource, Scene};
use crate::train::config::{LevelRange, RunConfig, StepBudget, TableSize, TrainConfig};
use crate::train::memory;
use crate::train::sampler::{SampleMode, Samples};
use anyhow::{bail, Context, Result};
use std::path::Path;

/// A scene prepared for training or evaluation.
pub struct Prepared {
    pub scene: Scene,
    pub tracer: Tracer,
    /// Scene indices of the training views; the position in this list is the view's
    /// appearance-code row.
    pub train_views: Vec<usize>,
    /// Samples of the training views (input index = position in `train_views`).
    pub samples: Samples,
    /// The memory budget the setup was checked against ([`memory::check_job_against`]).
    pub budget: memory::Budget,
}

impl Prepared {
    /// The training views' names, by appearance row.
    pub fn train_names(&self) -> Vec<String> {
        self.train_views
            .iter()
            .map(|&v| self.scene.views[v].name.clone())
            .collect()
    }

    /// Width and height of each training view (after downsampling), by appearance row.
    pub fn train_sizes(&self) -> Vec<(u32, u32)> {
        view_sizes(&self.scene, &self.train_views)
    }

    /// The memory check of the setup again, for `cfg`'s model: the level range
    /// ([`resolve_levels`]) may have added levels since the setup saw the configured grid (a
    /// 1000× close-up: 37 instead of 16), so a model is checked before it is allocated.
    pub fn check_model(&self, cfg: &RunConfig) -> Result<()> {
        memory::check_job_against(
            cfg,
            &self.train_sizes(),
            self.scene.downsample,
            memory::Job::Train,
            self.budget.clone(),
        )
        .map(|_| ())
    }

    /// The first model of a new run of `cfg` on this scene, and the configuration it is made
    /// of: grid H's levels resolved from what the training views see ([`resolve_levels`], its
    /// messages to `log`), the model they size checked against the memory budget
    /// ([`Prepared::check_model`]), then initialised with `cfg.train.seed`, one appearance row per
    /// training view. Every new run, `xscale init` and the experiments start here.
    pub fn init_model(
        &self,
        mut cfg: RunConfig,
        log: &mut dyn FnMut(String),
    ) -> Result<(RunConfig, Checkpoint)> {
        for msg in resolve_levels(&mut cfg, &self.samples) {
            log(msg);
        }
        for msg in resolve_table_sizes(&mut cfg, &self.samples, &self.tracer) {
            log(msg);
        }
        log(resolve_budget(&mut cfg.train, self.samples.len()));
        self.check_model(&cfg)?;
        let ckpt = init_checkpoint_for_mesh(
            &cfg.model,
            cfg.train.seed,
            self.scene.normalization,
            self.train_views.len(),
            Some(&self.scene.mesh),
        )?;
        Ok((cfg, ckpt))
    }

    /// Appearance row of a scene view, or -1 (held-out / unknown view: mean code).
    pub fn appearance_row(&self, scene_view: usize) -> i32 {
        self.train_views
            .iter()
            .position(|&v| v == scene_view)
            .map_or(-1, |r| r as i32)
    }
}

/// Load `dir`, cast the training views with γ = `gamma`; with `with_images`, targets come from
/// the photos (else they are zero — enough for `init`). Messages go to `log`.
pub fn prepare(
    dir: &Path,
    cfg: &RunConfig,
    with_images: bool,
    log: &mut dyn FnMut(String),
) -> Result<Prepared> {
    prepare_until(dir, cfg, with_images, log, &|| false, memory::Job::Train)
}

/// The error [`prepare_until`] returns when `stop()` said so (Ctrl-C, SIGTERM) before it was
/// done: nothing is trained yet, so there is nothing to save (a callers tells it apart with
/// `downcast_ref`).
#[derive(Debug)]
pub struct StoppedInSetup;

impl std::fmt::Display for StoppedInSetup {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("stopped while the scene was being prepared, before training began")
    }
}

impl std::error::Error for StoppedInSetup {}

/// [`prepare`], giving up with [`StoppedInSetup`] between views once `stop()` says so: casting
/// a large scene's views takes seconds to minutes (`synth --preset large`: 12 s), which a
/// Ctrl-C used to sit through before training one step and writing a checkpoint of it. The
/// memory check is made for `job` (`xscale batch` sizes its one batch, not training steps:
/// [`memory::check_job`]).
pub fn prepare_until(
    dir: &Path,
    cfg: &RunConfig,
    with_images: bool,
    log: &mut dyn FnMut(String),
    stop: &dyn Fn() -> bool,
    job: memory::Job,
) -> Result<Prepared> {
    let (scene, report) = load_for_training(dir, cfg, log)?;
    let train_views = scene.train();
    let tracer = Tracer::new(&scene.mesh, &scene.normalization).context("building the BVH")?;
    let sizes = view_sizes(&scene, &train_views);
    let budget = memory::budget(cfg);
    let (mode, why) =
        memory::check_job_against(cfg, &sizes, scene.downsample, job, budget.clone())?;
    let t0 = std::time::Instant::now();
    let gamma = cfg.model.gamma;
    // The vertex featurization needs each sub-sample's triangle and barycentrics, the mesh
    // refinement its triangle (`refine/`).
    let keep_triangles = !cfg.model.featurization.is_hash() || cfg.model.refine.enabled;
    let mut samples = Samples::empty(mode, gamma, keep_triangles)?;
    // The photos against the mesh (`raycast/consistency.rs`): the training views, read as they go
    // by, then the held-out views (a wrong pose there spoils only the evaluation, found here before
    // a run is spent on it).
    let checked: Vec<usize> = train_views.iter().chain(&scene.test).copied().collect();
    let mut photo_check = with_images.then(|| {
        let cams: Vec<&Camera> = checked.iter().map(|&i| &scene.views[i].camera).collect();
        PhotoCheck::plan(&scene.mesh, &tracer, &cams)
    });
    let cast = CastViews {
        scene: &scene,
        tracer: &tracer,
        views: &train_views,
        images: with_images,
        alpha_without_images: true,
    }
    .into_samples(
        &mut samples,
        photo_check.as_mut(),
        stop,
        &mut |i, mask, e| {
            if let CacheEvent::ViewDropped { .. } = e {
                log(format!(
                    "warning: view {i} ({}) {}: dropped",
                    scene.views[i].name,
                    crate::scene::mask::drop_reason(mask)
                ));
            }
        },
    )?;
    if samples.is_empty() && cast.empty_masks == train_views.len() {
        bail!(
            "{}: no training pixel is inside its view's object mask (every mask, from the photos' alpha channels or masks/, is empty)",
            dir.display()
        );
    }
    if samples.is_empty() {
        bail!(
            "{}: no training pixel sees the mesh: check that the mesh and the cameras are in one frame and unit (`xscale cast` lists each view's share; a mesh from nerfstudio's ns-export: `xscale align-mesh`)",
            dir.display()
        );
    }
    if let Some(c) = &mut photo_check {
        finish_photo_check(c, &scene, &checked, train_views.len(), stop, log)?;
    }
    let all: u64 = sizes.iter().map(|&(w, h)| w as u64 * h as u64).sum();
    let agreed = report.frame_check.as_ref().filter(|(_, a)| a.agrees());
    let agreed = agreed.map(|(source, _)| source.as_path());
    if let Some(w) = few_hits_warning(samples.len() as u64, all, agreed) {
        log(w);
    }
    log(format!(
        "cast {} training views with γ={gamma} in {:.2} s: {} pixels see the mesh; {} {:.1} MB ({why})",
        train_views.len(),
        t0.elapsed().as_secs_f64(),
        samples.len(),
        match samples.mode() {
            SampleMode::Cache => "sample cache:",
            _ => "hit maps + photos (rays cast per batch):",
        },
        samples.bytes() as f64 / 1e6
    ));
    Ok(Prepared {
        scene,
        tracer,
        train_views,
        samples,
        budget,
    })
}

/// The scene of `dir` as `cfg` loads it (downsample, normalisation, mesh), with what loading it
/// found said through `log`: the views, the mesh, notes and warnings, the object masks. A scene
/// whose every view is held out is refused.
fn load_for_training(
    dir: &Path,
    cfg: &RunConfig,
    log: &mut dyn FnMut(String),
) -> Result<(Scene, LoadReport)> {
    let opts = LoadOptions {
        downsample: cfg.train.downsample,
        normalize: cfg.train.normalize,
        mesh: cfg.train.mesh.clone(),
        ..LoadOptions::default()
    };
    let (scene, report) = Scene::load_report(dir, &opts)?;
    let train_views = scene.train();
    log(format!(
        "scene {}: {} views ({} train, {} held out), {} format, mesh {} ({} triangles, {} degenerate dropped)",
        dir.display(),
        scene.views.len(),
        train_views.len(),
        scene.test.len(),
        report.format.name(),
        report.mesh_path.display(),
        scene.mesh.triangles.len(),
        report.mesh_stats.dropped_degenerate
    ));
    for n in &report.notes {
        log(n.clone());
    }
    for w in &report.warnings {
        log(format!("warning: {w}"));
    }
    if train_views.is_empty() {
        bail!(
            "{}: no training views (all {} are held out; by default every 7th view from the first is):              hold out fewer with `holdout_every = N` or `test_views = [...]` in {}",
            dir.display(),
            scene.views.len(),
            dir.join("scene.toml").display()
        );
    }
    if scene.has_masks() {
        // Mask files come from `masks/` or from transforms.json's `mask_path`: name the folder
        // of the first.
        let folder = scene.masks.iter().find_map(|m| match m {
            crate::scene::MaskSource::File(p) => p.parent(),
            _ => None,
        });
        log(format!(
            "object masks: {} of {} views from {}; training and scores use only pixels inside them",
            scene
                .masks
                .iter()
                .filter(|m| **m != MaskSource::None)
                .count(),
            scene.masks.len(),
            match folder {
                Some(f) => format!("mask files (in {})", f.display()),
                None => "the photos' alpha channels".to_string(),
            }
        ));
    }
    Ok((scene, report))
}

/// The photo check's held-out views (read after the training views were cast; a held-out photo
/// that cannot be read is the evaluation's error to report), then its messages through `log`.
/// `checked` lists the scene views the check was planned for: the `n_train` training views,
/// then the held-out ones.
fn finish_photo_check(
    c: &mut PhotoCheck,
    scene: &Scene,
    checked: &[usize],
    n_train: usize,
    stop: &dyn Fn() -> bool,
    log: &mut dyn FnMut(String),
) -> Result<()> {
    for (k, &i) in checked.iter().enumerate().skip(n_train) {
        if stop() {
            return Err(StoppedInSetup.into());
        }
        if c.wants(k) {
            if let Ok(img) = scene.load_image(i) {
                c.add_view(k, &img);
            }
        }
    }
    let name = |k: usize| {
        let held_out = if k >= n_train { " (held out)" } else { "" };
        format!("{}{held_out}", scene.views[checked[k]].name)
    };
    for m in c.result().messages(&name) {
        log(m);
    }
    Ok(())
}

/// Scene views cast one photo at a time (load, cast, keep what the samples keep) into the
/// training samples: `train`'s setup and `xscale cast`.
pub struct CastViews<'a> {
    pub scene: &'a Scene,
    pub tracer: &'a Tracer,
    /// Scene indices of the views; a view's input index in the samples is its position here.
    pub views: &'a [usize],
    /// Read the photos: the targets, and what the photo check compares (else targets are zero).
    pub images: bool,
    /// Without `images`, read a mask held in the photo's alpha channel all the same (which decodes
    /// the photo): the setup does, so its pixels are those a run trains on; `xscale cast
    /// --no-images` does not.
    pub alpha_without_images: bool,
}

impl CastViews<'_> {
    /// Cast every view into `samples`, each photo also added to `check` (as its view k = the
    /// position in `views`); `on_event(i, mask, event)` hears what the cast of scene view i did.
    /// Gives up with [`StoppedInSetup`] between views once `stop()` says so.
    pub fn into_samples(
        &self,
        samples: &mut Samples,
        mut check: Option<&mut PhotoCheck>,
        stop: &dyn Fn() -> bool,
        on_event: &mut OnViewEvent<'_>,
    ) -> Result<CastSummary> {
        let scene = self.scene;
        let mut out = CastSummary::default();
        for (k, &i) in self.views.iter().enumerate() {
            if stop() {
                return Err(StoppedInSetup.into());
            }
            let img = if self.images {
                Some(scene.load_image(i)?)
            } else {
                None
            };
            let t = std::time::Instant::now();
            // An alpha mask is the photo's own alpha channel: reading it decodes the photo.
            let mask = if !self.images
                && !self.alpha_without_images
                && scene.masks[i] == MaskSource::Alpha
            {
                None
            } else {
                scene.load_mask(i)?
            };
            let mask = mask.as_deref();
            out.empty_masks += crate::scene::mask::excludes_all(mask) as usize;
            if let (Some(c), Some(img)) = (check.as_deref_mut(), &img) {
                c.add_view(k, img);
            }
            let cam = &scene.views[i].camera;
            let mut on_event = |e| on_event(i, mask, e);
            match samples {
                Samples::Stream(s) => {
                    let t = img.as_ref().map_or(Targets::None, Targets::from_image);
                    s.add_view(self.tracer, k, cam, t, mask, &mut on_event)?
                }
                Samples::Cache(c) => {
                    c.add_view(self.tracer, k, cam, img.as_ref(), mask, &mut on_event)?
                }
            };
            out.cast_seconds += t.elapsed().as_secs_f64();
        }
        Ok(out)
    }
}

/// Hears what the cast of scene view `i` did, with the view's mask: `(i, mask, event)`.
pub type OnViewEvent<'a> = dyn FnMut(usize, Option<&[bool]>, CacheEvent) + 'a;

/// What [`CastViews::into_samples`] saw.
#[derive(Clone, Copy, Debug, Default)]
pub struct CastSummary {
    /// Views whose mask excludes every pixel.
    pub empty_masks: usize,
    /// Seconds reading the masks and casting (the photos' loading and checking left out).
    pub cast_seconds: f64,
}

/// Width and height of the scene views `views`.
fn view_sizes(scene: &Scene, views: &[usize]) -> Vec<(u32, u32)> {
    views
        .iter()
        .map(|&i| (scene.views[i].camera.width, scene.views[i].camera.height))
        .collect()
}

/// Below this share of the training views' pixels seeing the mesh, `train` warns: a scene's mesh
/// fills most of its photos (the synthetic scenes: 99–100 %; an object with masks, tens of
/// percent), while a mesh and cameras in different frames or units leave a few percent.
pub const FEW_HITS: f64 = 0.05;

/// The warning for `hits` of `pixels` training pixels seeing the mesh, when under [`FEW_HITS`].
/// `agreed`: the reconstruction's points file the mesh was found to agree with (`scene/points.rs`),
/// if any — then the frames are not the cause, the mesh's coverage is.
pub fn few_hits_warning(hits: u64, pixels: u64, agreed: Option<&Path>) -> Option<String> {
    let share = hits as f64 / pixels.max(1) as f64;
    (share < FEW_HITS).then(|| match agreed {
        None => format!(
            "warning: only {:.1} % of the training views' pixels see the mesh: check that the mesh and the cameras are in one frame and unit (`xscale cast` lists each view's share; a transforms.json with an applied_transform: scene.toml's applied_transform; a mesh from nerfstudio's ns-export: `xscale align-mesh`)",
            100.0 * share
        ),
        Some(points) => format!(
            "warning: only {:.1} % of the training views' pixels see the mesh, which agrees with the reconstruction's points ({}): it covers little of what the photos show (a trimmed or cropped mesh?); the rest of each photo is neither learned nor scored (`xscale cast` lists each view's share)",
            100.0 * share,
            points.display()
        ),
    })
}

/// Epochs over the training views' kept pixels that `budget = "auto"` trains (measured on `synth`
/// `small` and `cross`, docs/results.md "Training budget").
pub const BUDGET_EPOCHS: f64 = 12.0;

/// Fewest steps `budget = "auto"` chooses (a scene of a few views still trains its MLP and
/// appearance codes to convergence: the `tiny` scene's 15,000 pixels are 4 batches).
pub const BUDGET_MIN_STEPS: u64 = 1000;

/// Most steps `budget = "auto"` chooses: six times the fixed 2,000-step budget the rule replaced,
/// so a default run on a large scene takes at most about six times what it did. Measured on the
/// real `fox` capture (21 million training pixels, 1.1 epochs at 6,000 steps; seed 0, held-out
/// masked PSNR / SSIM / ꟻLIP): 6,000 steps 28.44 / 0.8321 / 0.1377, 12,000 steps 28.68 / 0.8352 /
/// 0.1368 — the SSIM that had kept it behind reprojection (ULR 0.8337); 2× the time (about 6
/// minutes on 2 cores). Scenes of fewer than 4 million kept pixels (`synth small`, `cross`, the
/// skull) choose below either cap; `synth --preset large` is 20,000 batches per epoch.
pub const BUDGET_MAX_STEPS: u64 = 12_000;

/// The steps `budget = "auto"` chooses for `pixels` kept training pixels in batches of `batch`:
/// `clamp(⌈BUDGET_EPOCHS · pixels / batch⌉ rounded up to a multiple of 100, BUDGET_MIN_STEPS,
/// BUDGET_MAX_STEPS)` — a pure function of the scene and the configuration, never of time.
pub fn budget_steps(pixels: usize, batch: usize) -> u64 {
    let epochs = BUDGET_EPOCHS * pixels as f64 / batch.max(1) as f64;
    let steps = (epochs.ceil() as u64).div_ceil(100) * 100;
    steps.clamp(BUDGET_MIN_STEPS, BUDGET_MAX_STEPS)
}

/// Resolve the step count of a new run in place (`train.budget`); returns the message saying
/// what was chosen and why (printed when the run starts). `pixels`: the training views' kept
/// pixels (those with a sub-sample on the mesh: the ones batches are drawn from).
pub fn resolve_budget(train: &mut TrainConfig, pixels: usize) -> String {
    match train.budget {
        StepBudget::Fixed => format!(
            "training budget (fixed): {} steps of {} pixels",
            train.steps, train.batch_pixels
        ),
        StepBudget::Auto => {
            // The preset's learning-rate schedule is written for its own `steps`: stretched to
            // the chosen count, its decays fall at the same fractions of the run (spec §8).
            let written_for = train.steps;
            train.steps = budget_steps(pixels, train.batch_pixels);
            for g in train.adam.groups_mut() {
                g.schedule = g.schedule.stretched(written_for, train.steps);
            }
            let epochs = train.steps as f64 * train.batch_pixels as f64 / pixels.max(1) as f64;
            format!(
                "training budget (auto): {} steps of {} pixels = {epochs:.1} epochs over the {pixels} training pixels ({BUDGET_EPOCHS} epochs, within {BUDGET_MIN_STEPS}..{BUDGET_MAX_STEPS} steps; --steps N or [train] steps fixes it; learning-rate decays at the same fractions of the run)",
                train.steps, train.batch_pixels
            )
        }
    }
}

/// Which footprint sets the finest level in `level_range = "auto"`: the smallest over training
/// views of each view's [`LEVEL_QUANTILE`]-quantile pixel footprint — the closest views' typical
/// pixel, not their single smallest one (a pixel at a grazing angle or at the edge of a near
/// object can be many times smaller than the rest of its view and would spend levels on nothing),
/// and not a quantile over all pixels (a few close-ups among many aerial views would be outvoted).
pub const LEVEL_QUANTILE: f64 = 0.1;

/// The finest level's cells in `level_range = "auto"` are this many times finer than that
/// footprint (a cell per pixel footprint resolves a pixel's worth of detail; measured in the
/// finest-resolution sweep, `docs/cross-scale.md`).
pub const CELLS_PER_FOOTPRINT: f64 = 1.0;

/// The finest level `level_range = "auto"` sets, in cells per normalised unit: half the largest
/// scale a grid holds ([`crate::model::hashgrid::MAX_SCALE`]), so that [`tcnn_scales`]' f32
/// rounding cannot push the last level past it. Only a view whose pixels cover under 2e-9 of the
/// scene reaches it (a focal length 10^6 times too long, a camera almost touching the mesh):
/// without the cap such a view made every run fail building the model ("scale of level 57 is
/// 1291043200"). Cells this small are still 8 steps of the 2^-32 training positions (SPEC §1.2).
pub const AUTO_FINEST_MAX: f64 = crate::model::hashgrid::MAX_SCALE as f64 / 2.0;

/// Resolve the hash-grid levels of a new run from what the training views see (SPEC §8), in
/// place; returns the messages saying what was chosen and why.
///
/// 1. `train.level_range = "auto"` (the `cpu` preset): grid H's finest resolution follows the
///    footprints (`N_max = CELLS_PER_FOOTPRINT / fp`, `fp` as [`LEVEL_QUANTILE`] says, in cells per
///    normalised unit; at least `2·N0`). Levels are added while the configured per-level scale b
///    would not reach it — `L = max(L_cfg, 1 + ⌈log_b(N_max / N0)⌉)` ([`auto_levels`]) — and then
///    `per_level_scale = (N_max / N0)^(1/(L-1))` (tiny-cuda-nn's formula), so the levels stay about
///    as far apart as configured however wide the scene's range of scales is. (Stretching a fixed
///    L = 16 to the close-ups' resolution thinned the levels the aerial views use and cost them
///    0.5–0.8 dB on `synth --preset cross`; adding levels gained close-ups 3.4 dB and aerial
///    views 0.5 dB over the fixed range, `docs/cross-scale.md`.)
/// 2. `train.drop_fine_levels`: grid H levels finer than the finest footprint of any training view
///    are dropped ([`drop_fine_levels`]).
///
/// The vertex featurization has no levels: nothing changes.
pub fn resolve_levels(cfg: &mut RunConfig, samples: &Samples) -> Vec<String> {
    let mut out = Vec::new();
    if !cfg.model.featurization.is_hash() {
        return out;
    }
    let g = &mut cfg.model.grid_h;
    match cfg.train.level_range {
        LevelRange::Auto => {
            if let Some(fp) = samples.footprint_quantile_min(LEVEL_QUANTILE) {
                let n0 = g.base_resolution as f64;
                let wanted = (CELLS_PER_FOOTPRINT / fp).max(2.0 * n0);
                let finest = wanted.min(AUTO_FINEST_MAX);
                if finest < wanted {
                    out.push(format!(
                        "warning: grid H level range (auto): the closest views' pixels are {fp:.3e} of the scene, finer than a grid level can hold; the finest level is capped at {finest:.0} cells per unit instead of {wanted:.3e} (a focal length or a camera position wrong? `xscale cast` lists each view's smallest footprint)"
                    ));
                }
                let before = tcnn_scales(g).last().copied().unwrap_or(0.0);
                g.levels = auto_levels(n0, finest, g.per_level_scale, g.levels);
                g.per_level_scale = per_level_scale_for(n0, finest, g.levels);
                g.finest_resolution = Some(finest);
                out.push(format!(
                    "grid H level range (auto): the closest views' pixels are {fp:.3e} of the scene ({} % quantile of each view's footprints, smallest over views): finest level {finest:.0} cells per unit (was {:.0}), per_level_scale {:.6} over {} levels from {n0}",
                    (LEVEL_QUANTILE * 100.0).round(),
                    before + 1.0,
                    g.per_level_scale,
                    g.levels
                ));
            }
        }
        LevelRange::Fixed => out.push(format!(
            "grid H level range (fixed): per_level_scale {:.6}, finest level {:.0} cells per unit",
            g.per_level_scale,
            tcnn_scales(g).last().copied().unwrap_or(0.0) + 1.0
        )),
    }
    if cfg.train.drop_fine_levels {
        if let Some(fp) = samples.footprint_min() {
            if let Some(msg) = drop_fine_levels(&mut cfg.model, fp as f64) {
                out.push(msg);
            }
        }
    }
    out
}

/// `log2_table_size = "auto"`: a hashed level gets at least this many entries per surface cell
/// the training rays reach at that level (`2^ceil(log2(TABLE_HEADROOM · cells))`: at most an
/// eighth of a table's entries hold a cell, so collisions stay rare). Measured on `synth small`
/// (600 steps, seed 0, masked held-out PSNR): 4 entries 35.00 dB against 34.99 dB with 2^19 on
/// every level; about 0.5 entries per cell (the load 2^19 has on the finest levels) scored
/// 34.53 dB, 1 entry 34.44 dB, 2 entries 34.65 dB — collisions on the middle levels cost more
/// than the fine levels' tolerance of them suggested. 8 since 2026-11-29: with grid D's 5 levels,
/// 4 entries put `synth tiny` 0.16 dB below the fixed 2^19 tables (3 seeds; the held-out close-up
/// reads cells no training ray reached, which collide with trained ones), 8 entries 0.02 dB below;
/// `small` and `cross` the same with either, their tables mostly at the ceiling (docs/changelog.md).
pub const TABLE_HEADROOM: f64 = 8.0;
/// The smallest `T_l` of `log2_table_size = "auto"` (also that of a level no ray reaches).
pub const TABLE_FLOOR_LOG2: u32 = 12;
/// The largest `T_l` of `log2_table_size = "auto"`: the `cpu` preset's fixed 2^19. With 2^21
/// `synth small`'s model grew 3.5× (its finest levels reach ~1 M cells each) and its steps slowed
/// for the same held-out PSNR at the same steps, so the rule only shrinks what a scene leaves
/// empty (`docs/changelog.md`). A scene that needs more sets `log2_table_size` itself.
pub const TABLE_CEILING_LOG2: u32 = 19;
/// The training pixels `log2_table_size = "auto"` counts cells of, at most (every
/// `⌈kept / this⌉`-th kept pixel, all its sub-samples).
pub const TABLE_SAMPLE_PIXELS: usize = 1 << 16;

/// Distinct grid-H cells (level by level) the training rays reach: the sub-samples of every
/// `stride`-th kept pixel (`stride = ⌈kept / TABLE_SAMPLE_PIXELS⌉`), at each level the footprint
/// weighting gives a weight > 0 (every level without it). Cell of a point at level l:
/// `⌊fma(scale_l, x_n, 0.5)⌋` per axis (f64), as the grid locates it. With `stride > 1` the count
/// of the subset, `d_s` of `n_s` points, is extrapolated to `d_s · (1 + (stride − 1) · d_s / n_s)`
/// (all cells found when points share cells, `stride ×` when each point has a cell of its own).
/// Pure and deterministic: the same pixels in the same order whatever the thread count.
pub fn reached_cells(
    grid: &GridConfig,
    weighted: bool,
    samples: &Samples,
    tracer: &Tracer,
) -> Vec<f64> {
    let scales = tcnn_scales(grid);
    let nl = scales.len();
    let kept = samples.len();
    if kept == 0 {
        return vec![0.0; nl];
    }
    let stride = kept.div_ceil(TABLE_SAMPLE_PIXELS);
    let pixels: Vec<usize> = (0..kept).step_by(stride).collect();
    let mut cells: Vec<Vec<u64>> = vec![Vec::new(); nl];
    let mut points = vec![0u64; nl];
    for chunk in pixels.chunks(8192) {
        let b = samples.batch(tracer, chunk);
        let s = b.samples_per_pixel();
        for (l, &sc) in scales.iter().enumerate() {
            let sc = sc as f64;
            let keys = &mut cells[l];
            for px in 0..b.n_pixels() {
                if weighted
                    && !b.footprint.is_empty()
                    && crate::model::level_weight::weight(b.footprint[px] as f64 * sc) <= 0.0
                {
                    continue;
                }
                for j in px * s..(px + 1) * s {
                    if b.valid[j] == 0 {
                        continue;
                    }
                    let x = b.positions[j];
                    let c = x.map(|v| sc.mul_add(v, 0.5).floor() as i64 as u64);
                    keys.push(cell_key(c));
                    points[l] += 1;
                }
            }
            keys.sort_unstable();
            keys.dedup();
        }
    }
    cells
        .iter()
        .zip(&points)
        .map(|(k, &n)| {
            let d = k.len() as f64;
            if n == 0 {
                0.0
            } else {
                d * (1.0 + (stride as f64 - 1.0) * d / n as f64)
            }
        })
        .collect()
}

/// A 64-bit hash of a cell (a collision of two keys only lowers an estimate by one).
fn cell_key(c: [u64; 3]) -> u64 {
    let mut h = 0x9E37_79B9_7F4A_7C15u64;
    for v in c {
        h = (h ^ v).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        h ^= h >> 29;
    }
    h.wrapping_mul(0x94D0_49BB_1331_11EB) ^ (h >> 32)
}

/// `T_l` of `log2_table_size = "auto"` for a level reaching `cells` surface cells:
/// `ceil(log2(TABLE_HEADROOM · cells))` (f64) within [`TABLE_FLOOR_LOG2`], [`TABLE_CEILING_LOG2`].
pub fn auto_log2_size(cells: f64) -> u32 {
    let want = (TABLE_HEADROOM * cells).max(1.0).log2().ceil();
    (want as u32).clamp(TABLE_FLOOR_LOG2, TABLE_CEILING_LOG2)
}

/// Resolve grid H's table sizes of a new run (SPEC §8), in place; returns the messages saying
/// what was chosen. `train.table_size = "auto"` (the `cpu` preset, `[model.grid_h]
/// log2_table_size = "auto"`): level l holds at most `2^T_l` entries, `T_l` =
/// [`auto_log2_size`] of the cells [`reached_cells`] counts, except that a level dense at the
/// configured `log2_table_size` stays dense (`T_l = T`); `log2_table_size` becomes the largest `T_l`. Grid D (ξ) too,
/// every level counted at every hit (ξ is not footprint-weighted), never above its configured
/// `log2_table_size`. `fixed` keeps the configured
/// size(s). Run after [`resolve_levels`] (the sizes are per resolved level).
pub fn resolve_table_sizes(cfg: &mut RunConfig, samples: &Samples, tracer: &Tracer) -> Vec<String> {
    let mut out = Vec::new();
    if !cfg.model.featurization.is_hash() {
        return out;
    }
    let auto = cfg.train.table_size == TableSize::Auto;
    let weighted = !cfg.model.level_weight.is_none();
    let deform = cfg.model.deform.enabled;
    // Grid H (levels weighted by footprint), then grid D (ξ reads every level at every hit).
    // Grid D never grows past its configured size (`docs/changelog.md`, "Grid D's tables"): the
    // rule sized it up to 2^19 where the preset has 2^17, for no measured gain.
    let grids: Vec<(&str, &mut GridConfig, bool, bool)> = if deform {
        vec![
            ("H", &mut cfg.model.grid_h, weighted, false),
            ("D", &mut cfg.model.deform.grid, false, true),
        ]
    } else {
        vec![("H", &mut cfg.model.grid_h, weighted, false)]
    };
    for (name, g, weighted, capped) in grids {
        let configured = g.log2_table_size;
        let mut counted = 0.0;
        let cells = auto.then(|| {
            let t0 = std::time::Instant::now();
            let cells = reached_cells(g, weighted, samples, tracer);
            counted = t0.elapsed().as_secs_f64();
            // A level dense at the configured size stays dense (and as it was).
            let fixed = crate::model::hashgrid::HashGrid::try_new(g).ok();
            let t: Vec<u32> = cells
                .iter()
                .enumerate()
                .map(|(l, &c)| match &fixed {
                    Some(f) if f.dense[l] => configured,
                    _ if capped => auto_log2_size(c).min(configured),
                    _ => auto_log2_size(c),
                })
                .collect();
            g.log2_table_size = t.iter().copied().max().unwrap_or(TABLE_FLOOR_LOG2);
            g.log2_table_sizes = Some(t);
            cells
        });
        let Ok(grid) = crate::model::hashgrid::HashGrid::try_new(g) else {
            continue; // the model's construction reports it
        };
        let per_level: Vec<String> = (0..g.levels as usize)
            .map(|l| {
                let n = grid.level_entries(l);
                let kind = if grid.dense[l] { "dense" } else { "hashed" };
                match &cells {
                    Some(c) => format!("{l}: {:.0} cells → {n} {kind}", c[l]),
                    None => format!("{l}: {n} {kind}"),
                }
            })
            .collect();
        let mode = if cells.is_some() {
            let ceiling = if capped {
                TABLE_CEILING_LOG2.min(configured)
            } else {
                TABLE_CEILING_LOG2
            };
            format!(
                "auto: ≥ {TABLE_HEADROOM} entries per surface cell the training rays reach, 2^{TABLE_FLOOR_LOG2}..2^{ceiling}, dense levels kept; cells counted in {counted:.1} s"
            )
        } else if let Some(t) = &g.log2_table_sizes {
            format!("fixed: log2 sizes {t:?}")
        } else {
            format!("fixed: at most 2^{} entries per level", g.log2_table_size)
        };
        out.push(format!(
            "grid {name} tables ({mode}): {} entries, {} parameters (levels {})",
            grid.n_entries(),
            grid.n_params(),
            per_level.join(", ")
        ));
    }
    out
}

/// The number of grid H levels for `level_range = "auto"`: at least `levels`, and enough that
/// levels `per_level_scale` apart reach `finest` from `n0` (at most `MAX_LEVELS`).
pub fn auto_levels(n0: f64, finest: f64, per_level_scale: f64, levels: u32) -> u32 {
    let need = 1.0 + ((finest / n0).ln() / per_level_scale.ln() - 1e-9).ceil();
    let need = if need.is_finite() { need.max(1.0) } else { 1.0 };
    (need as u32)
        .max(levels)
        .min(crate::model::hashgrid::MAX_LEVELS)
}

/// Number of levels of `grid` whose cells are not finer than `footprint` (normalised units):
/// level l is kept while `1 / scale_l ≥ footprint`; at least one level is kept (SPEC §8).
pub fn levels_resolved(grid: &GridConfig, footprint: f64) -> u32 {
    let scales = tcnn_scales(grid);
    let kept = scales
        .iter()
        .take_while(|&&s| 1.0 / (s as f64) >= footprint)
        .count();
    kept.max(1) as u32
}

/// Apply SPEC §8 to a model config: drop grid-H levels finer than the finest footprint seen in
/// any training view. Returns a message saying what was dropped and why, if anything was.
pub fn drop_fine_levels(model: &mut ModelConfig, footprint_min: f64) -> Option<String> {
    let all = model.grid_h.levels;
    let kept = levels_resolved(&model.grid_h, footprint_min).min(all);
    if kept == all {
        return None;
    }
    let scales = tcnn_scales(&model.grid_h);
    model.grid_h.levels = kept;
    Some(format!(
        "grid H: keeping {kept} of {all} levels; levels {kept}..{} have cells of {:.3e}..{:.3e} (normalised), finer than the finest pixel footprint {:.3e} of any training view",
        all - 1,
        1.0 / scales[kept as usize] as f64,
        1.0 / scales[all as usize - 1] as f64,
        footprint_min
    ))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The automatic budget is epochs over the kept pixels, within its floor and cap, and only
    /// when asked for.
    #[test]
    fn budget_follows_the_pixels() {
        assert_eq!(budget_steps(0, 4096), BUDGET_MIN_STEPS);
        assert_eq!(budget_steps(100_000_000, 4096), BUDGET_MAX_STEPS);
        let (a, b) = (budget_steps(1_000_000, 4096), budget_steps(2_000_000, 4096));
        assert!(a > BUDGET_MIN_STEPS && b < BUDGET_MAX_STEPS, "{a} {b}");
        assert!(
            b >= 2 * a - 100 && b <= 2 * a,
            "twice the pixels, twice the steps: {a} {b}"
        );
        assert_eq!(a % 100, 0);
        let want = (BUDGET_EPOCHS * 1_000_000.0 / 4096.0).ceil() as u64;
        assert!(a >= want && a < want + 100, "{a} {want}");
        let mut t = TrainConfig::for_preset("cpu").unwrap();
        assert_eq!(t.budget, StepBudget::Auto);
        let written_for = t.steps;
        let before = t.adam.grid_h.schedule;
        let msg = resolve_budget(&mut t, 1_000_000);
        assert_eq!(t.steps, a);
        assert!(msg.contains(&format!("{a} steps")), "{msg}");
        // The preset's decays at the same fractions of the chosen run.
        let after = t.adam.grid_h.schedule;
        if before.decay_interval > 0 {
            let frac = |k: u32, n: u64| k as f64 / n as f64;
            assert!(
                (frac(after.decay_start, a) - frac(before.decay_start, written_for)).abs() < 1e-3,
                "{before:?} {after:?}"
            );
            assert!(
                (frac(after.decay_end, a) - frac(before.decay_end, written_for)).abs() < 1e-3,
                "{before:?} {after:?}"
            );
        }
        // Resolving the stored result again (a run's config.toml given back) changes nothing.
        let again = t.clone();
        resolve_budget(&mut t, 1_000_000);
        assert_eq!(format!("{:?}", t.adam), format!("{:?}", again.adam));
        let mut t = TrainConfig::for_preset("tiny").unwrap();
        assert_eq!(t.budget, StepBudget::Fixed);
        resolve_budget(&mut t, 2_000_000);
        assert_eq!(t.steps, 300, "a fixed budget is left as it is");
    }

    #[test]
    fn few_hits_are_flagged() {
        assert_eq!(few_hits_warning(18_429, 18_432, None), None);
        assert_eq!(few_hits_warning(1_000, 20_000, None), None, "5 % is enough");
        let w = few_hits_warning(999, 20_000, None).unwrap();
        assert!(w.contains("align-mesh"), "{w}");
        assert!(
            w.contains("only 5.0 % of the training views' pixels") && w.contains("one frame"),
            "{w}"
        );
        assert!(few_hits_warning(0, 0, None).is_some());
        // Frames found to agree with the reconstruction's points: the mesh's coverage is named.
        let w = few_hits_warning(999, 20_000, Some(Path::new("sparse/0/points3D.bin"))).unwrap();
        assert!(
            w.contains("agrees with the reconstruction's points (sparse/0/points3D.bin)")
                && w.contains("trimmed or cropped")
                && !w.contains("one frame"),
            "{w}"
        );
    }

    #[test]
    fn level_dropping() {
        let mut m = ModelConfig::cpu();
        // Footprint larger than every cell: only level 0 survives.
        assert_eq!(levels_resolved(&m.grid_h, 1.0), 1);
        // Tiny footprint: every level is resolved.
        assert_eq!(levels_resolved(&m.grid_h, 1e-9), 16);
        // Cells of level l are 1/scale_l; with a footprint between two levels' cells the finer is dropped.
        let scales = tcnn_scales(&m.grid_h);
        let fp = 0.5 * (1.0 / scales[9] as f64 + 1.0 / scales[10] as f64);
        assert_eq!(levels_resolved(&m.grid_h, fp), 10);
        let msg = drop_fine_levels(&mut m, fp).unwrap();
        assert_eq!(m.grid_h.levels, 10);
        assert!(msg.contains("10 of 16"), "{msg}");
        assert!(drop_fine_levels(&mut m, fp).is_none());
    }
}
