//! Run configuration: a preset (SPEC §9) plus any TOML overrides, resolved once and saved in the
//! run folder (`config.toml`) and in every checkpoint.
//!
//! File form (every field optional; unknown keys are an error naming them):
//! ```toml
//! preset = "cpu"                 # tiny | cpu | paper: the base that the tables below override
//! [model]                        # ModelConfig (src/model/config.rs)
//! gamma = 1
//! deform.enabled = false
//! [train]                        # TrainConfig below
//! steps = 3000
//! [train.adam.grid_h]            # AdamGroup (src/train/adam.rs)
//! lr = 1e-2
//! ```

use crate::model::ModelConfig;
use crate::scene::NormalizeMode;
use crate::train::adam::{AdamConfig, LrSchedule};
use crate::train::sampler::SampleMode;
use anyhow::{bail, ensure, Context, Result};
use serde::{Deserialize, Serialize};
use std::path::Path;

/// How grid H's level range is chosen (`[train] level_range`).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum LevelRange {
    /// The configured `per_level_scale` (the `tiny` and `paper` presets: the official code's
    /// fixed scale).
    #[default]
    Fixed,
    /// The finest level follows the footprints the training views see (`cpu`).
    Auto,
}

/// How grid H's table sizes are chosen (`[model.grid_h] log2_table_size = "auto"` or an integer).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum TableSize {
    /// Every level `2^log2_table_size` entries at most (tiny-cuda-nn; the `tiny` and `paper`
    /// presets, an integer `log2_table_size`).
    #[default]
    Fixed,
    /// Each hashed level sized from the surface cells the training rays reach at that level
    /// (`cpu`; `train/setup.rs` `resolve_table_sizes`).
    Auto,
}

impl TableSize {
    pub fn is_fixed(&self) -> bool {
        *self == TableSize::Fixed
    }
}

/// How a run's step count is chosen (`[train] budget`).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum StepBudget {
    /// `train.steps` as configured (the `tiny` and `paper` presets; any run given `--steps` or
    /// `[train] steps`).
    #[default]
    Fixed,
    /// The scene's size sets it (the `cpu` preset): a fixed number of epochs over the training
    /// views' kept pixels, within a floor and a cap (`train/setup.rs` [`resolve_budget`]). The
    /// chosen count is written to `train.steps` when a run starts, so `RUN/config.toml` and the
    /// checkpoint hold it.
    ///
    /// [`resolve_budget`]: crate::train::setup::resolve_budget
    Auto,
}

/// Everything about a training run that is not the model.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TrainConfig {
    /// Optimisation steps (with `budget = "auto"`: chosen when the run starts, and stored).
    pub steps: u64,
    /// How `steps` is chosen: `fixed` (as given) or `auto` (the `cpu` preset: from the number of
    /// training pixels, `train/setup.rs` `resolve_budget`). `--steps`, or `[train] steps` in a
    /// config file that does not also set `budget = "auto"`, fix it. Absent from older configs
    /// (= fixed, as they were trained).
    #[serde(default)]
    pub budget: StepBudget,
    /// Pixels per batch (each with γ² sub-samples).
    pub batch_pixels: usize,
    /// Seed of initialisation and batch selection (SPEC §5).
    pub seed: u64,
    /// Evaluate on held-out views every N steps (0 = only at the end).
    pub eval_every: u64,
    /// At most this many held-out views in a periodic evaluation (0 = all); the final one uses all.
    pub eval_max_views: usize,
    /// Write a checkpoint every N steps (0 = only at the end).
    pub checkpoint_every: u64,
    /// Append to `metrics.jsonl` (and print when not on a terminal) every N steps and at the last.
    /// 0 counts as 1 (every step) — unlike `eval_every` and `checkpoint_every`, whose 0 means
    /// none before the end (docs/runs.md).
    pub log_every: u64,
    /// Integer image downsample factor.
    pub downsample: u32,
    pub normalize: NormalizeMode,
    /// Drop hash levels finer than the finest pixel footprint of any training view (SPEC §8).
    pub drop_fine_levels: bool,
    /// How grid H's level range is chosen at the start of a run (SPEC §8, `train/setup.rs`
    /// `resolve_levels`): `auto` (the `cpu` preset) makes the finest level follow the closest
    /// training views' pixel footprints; `fixed` keeps the configured `per_level_scale`. A config
    /// file that sets `[model.grid_h] per_level_scale` or `finest_resolution` fixes it. Absent
    /// from older configs (= fixed, as they were trained).
    #[serde(default)]
    pub level_range: LevelRange,
    /// How grid H's table sizes are chosen at the start of a run (SPEC §8, `train/setup.rs`
    /// `resolve_table_sizes`): set in a config file as `[model.grid_h] log2_table_size = "auto"`
    /// (the `cpu` preset) or an integer (`fixed`). The sizes chosen are saved as grid H's
    /// `log2_table_sizes`. Absent when `fixed` (so the `paper` and `tiny` presets' configs and
    /// checkpoints are byte for byte those of the builds before it) and from older configs (=
    /// fixed, as they were trained). A config without it laid over the `cpu` preset as a
    /// `--config` stays fixed: its integer `log2_table_size` says so.
    #[serde(default, skip_serializing_if = "TableSize::is_fixed")]
    pub table_size: TableSize,
    pub adam: AdamConfig,
    /// Mesh file to use instead of the scene's own (e.g. a decimated one, `xscale decimate`);
    /// `xscale train --mesh` stores it absolute, so `eval`/`render --run` find it again. The
    /// normalisation is that of the mesh used (SPEC §4.1).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub mesh: Option<std::path::PathBuf>,
    /// Where batches come from: `auto` (default: the cache when it is small, else the stream;
    /// `train/memory.rs` `resolve_samples`), `stream` (rays cast as batches are drawn, ~3 bytes
    /// per pixel) or `cache` (every ray cast once and stored, `12γ²+42` bytes per pixel). Same
    /// batches bit for bit (`train/sampler.rs`); absent from older configs (= auto).
    #[serde(default)]
    pub samples: SampleMode,
    /// Memory budget in GB checked before allocating (`train/memory.rs`); 0 = the memory
    /// the system reports as available.
    #[serde(default)]
    pub memory_gb: f64,
    /// Arithmetic of the model's forward and backward in training: `f32` (default) or `f64`
    /// (`train/precision.rs`: the gradient is rounded once to f32 and Adam, the parameters and
    /// the checkpoint stay f32). Absent from older configs (= f32).
    #[serde(default)]
    pub arithmetic: Arithmetic,
    /// Side k of the square pixel patches a batch is drawn in (`train/sampler.rs`; 0 = single
    /// pixels): `batch_pixels / k²` patches of k×k neighbouring pixels of one view, for the
    /// D-SSIM term (`[model] ssim_weight`). Absent when 0 (the `tiny` and `paper` presets,
    /// configs written before it).
    #[serde(default, skip_serializing_if = "is_zero_u32")]
    pub patch: u32,
    /// How many of a patch batch's `batch_pixels` are in patches (a multiple of `patch²`; the
    /// rest are independent pixels, which cover more of the scene per step); 0 = all of them.
    /// Absent when 0.
    #[serde(default, skip_serializing_if = "is_zero_usize")]
    pub patch_pixels: usize,
}

fn is_zero_usize(v: &usize) -> bool {
    *v == 0
}

impl TrainConfig {
    /// Pixels of a batch drawn in patches (`patch_pixels`, 0 = all; 0 without patches).
    pub fn patched_pixels(&self) -> usize {
        match (self.patch, self.patch_pixels) {
            (0, _) => 0,
            (_, 0) => self.batch_pixels,
            (_, m) => m,
        }
    }
}

fn is_zero_u32(v: &u32) -> bool {
    *v == 0
}

/// `[train] arithmetic`.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Arithmetic {
    #[default]
    F32,
    F64,
}

impl TrainConfig {
    pub fn for_preset(name: &str) -> Result<TrainConfig> {
        let mut adam = AdamConfig::default();
        // Grids learn fast with a large rate (instant-ngp); the MLPs and codes are smaller.
        adam.shader.lr = 1e-2;
        adam.deform.lr = 1e-3;
        adam.appearance.lr = 1e-3;
        let base = TrainConfig {
            steps: 2000,
            budget: if name == "cpu" {
                StepBudget::Auto
            } else {
                StepBudget::Fixed
            },
            batch_pixels: 4096,
            seed: 0,
            eval_every: 500,
            eval_max_views: 2,
            checkpoint_every: 500,
            log_every: 25,
            downsample: 1,
            normalize: NormalizeMode::PerAxis,
            drop_fine_levels: true,
            level_range: if name == "cpu" {
                LevelRange::Auto
            } else {
                LevelRange::Fixed
            },
            table_size: if name == "cpu" {
                TableSize::Auto
            } else {
                TableSize::Fixed
            },
            adam,
            mesh: None,
            samples: SampleMode::Auto,
            memory_gb: 0.0,
            arithmetic: Arithmetic::F32,
            patch: 0,
            patch_pixels: 0,
        };
        Ok(match name {
            "tiny" => TrainConfig {
                steps: 300,
                batch_pixels: 1024,
                eval_every: 100,
                checkpoint_every: 100,
                log_every: 10,
                ..base
            },
            "cpu" => {
                let mut adam = base.adam.clone();
                // Measured on a real capture (instant-ngp's fox, 2,000 steps, held-out masked
                // PSNR / SSIM / ꟻLIP; docs/results.md#real): the grids' and MLPs' rate halved at
                // steps 1000, 1250, 1500 and 1750 (1/16 from then on) took 27.67 / 0.816 / 0.149
                // to 27.75 / 0.820 / 0.144; the appearance codes at 1e-2 instead of 1e-3 (each
                // photo's exposure and white balance learnt within the budget) to 27.75 / 0.816
                // / 0.149. Written for the preset's 2,000 steps; `budget = "auto"` stretches
                // them to the chosen count (setup::resolve_budget), and the stored config holds the
                // stretched steps, so a resumed run is the uninterrupted one.
                let fall = LrSchedule {
                    decay_start: 1000,
                    decay_interval: 250,
                    decay_base: 0.5,
                    decay_end: 1750,
                    ..LrSchedule::default()
                };
                for g in [
                    &mut adam.shader,
                    &mut adam.deform,
                    &mut adam.grid_h,
                    &mut adam.grid_d,
                ] {
                    g.schedule = fall;
                }
                adam.appearance.lr = 1e-2;
                TrainConfig { adam, ..base }
            }
            "paper" => TrainConfig {
                batch_pixels: 8192,
                ..base
            },
            _ => bail!("unknown preset {name:?}: expected one of tiny, cpu, paper"),
        })
    }
}

/// A resolved run configuration.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RunConfig {
    pub preset: String,
    pub model: ModelConfig,
    pub train: TrainConfig,
}

/// Merge `over` into `base` table by table (values in `over` win).
fn merge(base: &mut toml::Value, over: toml::Value) {
    match (base, over) {
        (toml::Value::Table(b), toml::Value::Table(o)) => {
            for (k, v) in o {
                match b.get_mut(&k) {
                    Some(bv) if bv.is_table() && v.is_table() => merge(bv, v),
                    _ => {
                        b.insert(k, v);
                    }
                }
            }
        }
        (b, o) => *b = o,
    }
}

impl RunConfig {
    pub fn preset(name: &str) -> Result<RunConfig> {
        Ok(RunConfig {
            preset: name.to_string(),
            model: ModelConfig::preset(name)?,
            train: TrainConfig::for_preset(name)?,
        })
    }

    /// The preset (`preset` key of the text, else `default_preset`) with the text's tables laid
    /// over it. `origin` names the source in errors.
    pub fn from_toml_str(text: &str, default_preset: &str, origin: &str) -> Result<RunConfig> {
        let mut over: toml::Value =
            toml::from_str(text).with_context(|| format!("{origin}: not valid TOML"))?;
        table_size_key(&mut over, origin)?;
        let preset = over
            .get("preset")
            .and_then(|p| p.as_str())
            .unwrap_or(default_preset)
            .to_string();
        let base = RunConfig::preset(&preset).with_context(|| format!("{origin}: preset"))?;
        let mut v = toml::Value::try_from(&base).context("serialising the preset")?;
        // The `[model.refine]` keys a file leaves out take the section's defaults: laid over the
        // preset's table whole, since a table read alone takes the values older builds left out
        // for `features`, `photo` and `optimizer` (`model/refine.rs`).
        if let Some(m) = v.get_mut("model").and_then(|m| m.as_table_mut()) {
            if !m.contains_key("refine") {
                let r =
                    toml::Value::try_from(&base.model.refine).context("serialising the preset")?;
                m.insert("refine".to_string(), r);
            }
        }
        merge(&mut v, over);
        described(v, origin, text)
    }
}

/// `[model.grid_h] log2_table_size = "auto"` becomes `[train] table_size = "auto"` (the
/// preset's `log2_table_size` stays, the ceiling's reference); an integer there, or per-level
/// `log2_table_sizes`, makes it `fixed`.
fn table_size_key(over: &mut toml::Value, origin: &str) -> Result<()> {
    let Some(g) = over
        .get_mut("model")
        .and_then(|m| m.get_mut("grid_h"))
        .and_then(|g| g.as_table_mut())
    else {
        return Ok(());
    };
    let mode = match g.get("log2_table_size") {
        Some(toml::Value::String(s)) if s == "auto" => {
            g.remove("log2_table_size");
            if g.contains_key("log2_table_sizes") {
                bail!("{origin}: [model.grid_h] log2_table_size = \"auto\" chooses each level's size itself; remove log2_table_sizes or give log2_table_size as an integer");
            }
            "auto"
        }
        Some(toml::Value::String(s)) => bail!(
            "{origin}: [model.grid_h] log2_table_size = {s:?}: expected \"auto\" or an integer (log2 of the entries per level, e.g. 19)"
        ),
        Some(_) => "fixed",
        None if g.contains_key("log2_table_sizes") => "fixed",
        None => return Ok(()),
    };
    let train = over
        .as_table_mut()
        .expect("a TOML document is a table")
        .entry("train")
        .or_insert_with(|| toml::Value::Table(Default::default()));
    if let Some(t) = train.as_table_mut() {
        // An explicit `[train] table_size` (a stored `RUN/config.toml`) is kept with an integer.
        if mode == "auto" || !t.contains_key("table_size") {
            t.insert("table_size".into(), toml::Value::String(mode.into()));
        }
    }
    Ok(())
}

impl RunConfig {
    /// A configuration a run stored (`RUN/config.toml`, a checkpoint's `run_config`): complete
    /// as written, so it is read as it stands, not laid over its preset. A key it lacks takes
    /// its serde default — what the build that wrote it meant: a key skipped when it holds its
    /// default (`model.level_weight = "none"`), or one added after that build (`level_range`).
    /// Laid over the `cpu` preset, a run trained with `level_weight = "none"` read back as
    /// `"footprint"`.
    pub fn from_stored_toml(text: &str, origin: &str) -> Result<RunConfig> {
        let v: toml::Value =
            toml::from_str(text).with_context(|| format!("{origin}: not valid TOML"))?;
        described(v, origin, text)
    }

    /// Preset `preset`, overridden by the file `path` if given. A user config that sets grid H's
    /// `per_level_scale` or `finest_resolution` fixes the level range (`finest_resolution`
    /// gives `per_level_scale = (finest / N0)^(1/(L-1))`; giving both, or `finest_resolution` with
    /// `[train] level_range = "auto"`, is an error). `per_level_scale` together with
    /// `level_range = "auto"` keeps the automatic range and sets the spacing its levels are
    /// added at (SPEC §8).
    pub fn resolve(preset: &str, path: Option<&Path>) -> Result<RunConfig> {
        match path {
            None => RunConfig::preset(preset),
            Some(p) => {
                let text = crate::io::text::read(p)?;
                let origin = p.display().to_string();
                let mut cfg = RunConfig::from_toml_str(&text, preset, &origin)?;
                let over: toml::Value =
                    toml::from_str(&text).with_context(|| format!("{origin}: not valid TOML"))?;
                let grid = over.get("model").and_then(|m| m.get("grid_h"));
                let has = |k: &str| grid.is_some_and(|g| g.get(k).is_some());
                let auto_asked = over
                    .get("train")
                    .and_then(|t| t.get("level_range"))
                    .and_then(|v| v.as_str())
                    == Some("auto");
                let (scale, mut finest) = (has("per_level_scale"), has("finest_resolution"));
                if scale && finest {
                    // A run's own config.toml stores both, in agreement: its per_level_scale is
                    // what it trained with, its finest_resolution the level that spacing reached
                    // before finer levels were dropped. Given back, it means that spacing.
                    if !scale_reaches_finest(&cfg.model.grid_h) {
                        bail!("{origin}: give [model.grid_h] per_level_scale or finest_resolution, not both (these disagree: per_level_scale {} from base_resolution {} reaches no level at finest_resolution {})",
                            cfg.model.grid_h.per_level_scale,
                            cfg.model.grid_h.base_resolution,
                            cfg.model.grid_h.finest_resolution.unwrap_or(f64::NAN));
                    }
                    finest = false;
                }
                if finest && auto_asked {
                    bail!(
                        "{origin}: [train] level_range = \"auto\" chooses grid H's finest level itself; remove [model.grid_h] finest_resolution or the level_range line"
                    );
                }
                // With `level_range = "auto"`, a configured per_level_scale is the spacing the
                // automatic range adds levels at (`auto_levels`), not a fixed range.
                if (scale || finest) && !auto_asked {
                    cfg.train.level_range = LevelRange::Fixed;
                }
                // `[train] steps` fixes the budget, unless the file also asks for the automatic
                // one (a run's own config.toml, which stores the count the rule chose: given
                // again, the rule chooses it again).
                let train_key = |k: &str| over.get("train").and_then(|t| t.get(k));
                if train_key("steps").is_some()
                    && train_key("budget").and_then(|v| v.as_str()) != Some("auto")
                {
                    cfg.train.budget = StepBudget::Fixed;
                }
                if let Some(f) = cfg.model.grid_h.finest_resolution.filter(|_| finest) {
                    let g = &mut cfg.model.grid_h;
                    g.per_level_scale = crate::model::config::per_level_scale_for(
                        g.base_resolution as f64,
                        f,
                        g.levels,
                    );
                }
                validated(cfg, &origin, &text)
            }
        }
    }

    pub fn to_toml(&self) -> String {
        toml::to_string(self).expect("a RunConfig always serialises")
    }

    /// The settings that decide what a run computes, as TOML: [`to_toml`](Self::to_toml) with
    /// `train.checkpoint_every` set to 0, since a checkpoint changes no result (a resumed run
    /// writes the same bytes, SPEC §5). Tools that reuse or continue their earlier runs
    /// (`ablate`, `bench-geometry`) compare this, so a change of checkpoint interval — theirs
    /// included, [`tool_checkpoint_every`] — does not make them train a run again.
    pub fn results_toml(&self) -> String {
        let mut c = self.clone();
        c.train.checkpoint_every = 0;
        c.to_toml()
    }

    /// `[model.refine]`'s own checks, then what the mesh refinement needs of the rest of the
    /// run: hash features, streamed samples (the mesh moves, so rays are cast as batches are
    /// drawn), f32 arithmetic.
    fn validate_refine(&self) -> Result<()> {
        let r = &self.model.refine;
        r.validate().context("model.refine")?;
        if !r.enabled {
            return Ok(());
        }
        ensure!(
            self.model.featurization.is_hash(),
            "model.refine: the mesh refinement needs featurization = \"hash\""
        );
        ensure!(
            self.train.samples != SampleMode::Cache,
            "model.refine: the mesh moves, so rays must be cast as batches are drawn: set [train] samples = \"stream\""
        );
        ensure!(
            self.train.arithmetic == Arithmetic::F32,
            "model.refine: runs in f32 arithmetic only (remove [train] arithmetic = \"f64\")"
        );
        Ok(())
    }

    pub fn validate(&self) -> Result<()> {
        let t = &self.train;
        if t.batch_pixels == 0 {
            bail!("train.batch_pixels must be > 0");
        }
        if t.downsample == 0 {
            bail!("train.downsample must be ≥ 1");
        }
        if !(t.memory_gb >= 0.0 && t.memory_gb.is_finite()) {
            bail!(
                "train.memory_gb must be a number ≥ 0 (0 = what the system has available), got {}",
                t.memory_gb
            );
        }
        if !(1..=4).contains(&self.model.gamma) {
            bail!("model.gamma must be 1..=4, got {}", self.model.gamma);
        }
        let m = &self.model;
        if m.loss == crate::model::config::LossKind::SmoothL1
            && !(m.smooth_l1_delta > 0.0 && m.smooth_l1_delta.is_finite())
        {
            bail!(
                "model.smooth_l1_delta must be a number > 0 (the δ of loss = \"smooth_l1\"), got {}",
                m.smooth_l1_delta
            );
        }
        if !(0.0..1.0).contains(&m.ssim_weight) {
            bail!(
                "model.ssim_weight must be in [0, 1) (λ of (1−λ)·L1 + λ·D-SSIM), got {}",
                m.ssim_weight
            );
        }
        if t.patch == 1 || t.patch > 64 {
            bail!(
                "train.patch must be 0 (single pixels) or a patch side in 2..=64, got {}",
                t.patch
            );
        }
        let k2 = (t.patch * t.patch) as usize;
        if t.patch > 0 && t.patched_pixels() % k2 != 0 {
            bail!(
                "train.{} = {} is not a whole number of {}×{} patches (train.patch): use a multiple of {k2}",
                if t.patch_pixels == 0 { "batch_pixels" } else { "patch_pixels" },
                t.patched_pixels(),
                t.patch,
                t.patch
            );
        }
        if t.patch_pixels > t.batch_pixels {
            bail!(
                "train.patch_pixels = {} is more than train.batch_pixels = {}",
                t.patch_pixels,
                t.batch_pixels
            );
        }
        if m.ssim_weight > 0.0 && t.patch == 0 {
            bail!(
                "model.ssim_weight = {} needs patch batches: set [train] patch (e.g. 8), or ssim_weight = 0",
                m.ssim_weight
            );
        }
        t.adam.validate().context("train.adam")?;
        self.validate_refine()?;
        let sh = &self.model.shader;
        if sh.width == 0 && sh.hidden_layers > 0 {
            bail!(
                "model.shader.width = 0 with {} hidden layers: a hidden layer needs width >= 1",
                sh.hidden_layers
            );
        }
        if self.model.deform.enabled && self.model.deform.hidden == 0 {
            bail!("model.deform.hidden must be >= 1 when the deformation is enabled");
        }
        if !self.model.featurization.is_hash() {
            if self.model.vertex_features == 0 {
                bail!("model.vertex_features must be > 0 with featurization = \"vertex\"");
            }
            if self.model.deform.enabled {
                bail!("featurization = \"vertex\" runs without deformation: set [model.deform] enabled = false");
            }
            if !self.model.level_weight.is_none() {
                bail!("model.level_weight weights hash-grid levels; featurization = \"vertex\" has none: set [model] level_weight = \"none\"");
            }
            return Ok(());
        }
        crate::model::hashgrid::validate_config(&self.model.grid_h).context("model.grid_h")?;
        let mut grids = vec![("model.grid_h", &self.model.grid_h)];
        if self.model.deform.enabled {
            crate::model::hashgrid::validate_config(&self.model.deform.grid)
                .context("model.deform.grid")?;
            grids.push(("model.deform.grid", &self.model.deform.grid));
        }
        // Checked here, before a scene is loaded (it used to surface only when the model was
        // built, as `config: grid_h: grid: scale of level 3 is -0.5`, naming no key).
        for (key, g) in grids {
            if let Some((l, s)) = crate::model::hashgrid::first_bad_scale(g) {
                bail!(
                    "{key}.per_level_scale = {} gives level {l} a scale of {s} (base_resolution {} × per_level_scale^{l} − 1 must be in [0, 1e9]): use a per_level_scale of at least 1",
                    g.per_level_scale,
                    g.base_resolution
                );
            }
        }
        Ok(())
    }
}

/// The run configuration the TOML value `v` (read from `text`, named `origin`) describes, or an
/// error at the line of the key it names.
fn described(v: toml::Value, origin: &str, text: &str) -> Result<RunConfig> {
    let cfg: RunConfig = match v.try_into() {
        Ok(c) => c,
        Err(e) => {
            let at = where_in(origin, text, &e.to_string());
            return Err(anyhow::Error::new(e)
                .context(format!("{at}: does not describe a run configuration")));
        }
    };
    validated(cfg, origin, text)
}

/// `cfg` if it validates, else the error with the file (and the line of the key it names,
/// when the file sets it).
fn validated(cfg: RunConfig, origin: &str, text: &str) -> Result<RunConfig> {
    match cfg.validate() {
        Ok(()) => Ok(cfg),
        Err(e) => {
            let at = where_in(origin, text, &format!("{e:#}"));
            Err(e.context(format!("{at}: invalid configuration")))
        }
    }
}

/// `origin:LINE` when an error message names a key (`… in `train.seed``, `unknown field `x``
/// in a table, or a leading `model.gamma …`) that the TOML `text` sets on line LINE, else
/// `origin`.
fn where_in(origin: &str, text: &str, msg: &str) -> String {
    let quoted = |after: &str| {
        msg.find(after)
            .map(|i| &msg[i + after.len()..])
            .and_then(|r| r.split('`').next())
            .map(str::to_string)
    };
    let table = quoted("in `");
    let keys: Vec<String> = match (quoted("unknown field `"), &table) {
        (Some(f), Some(t)) => vec![format!("{t}.{f}")],
        (Some(f), None) => vec![f],
        (None, Some(t)) => vec![t.clone()],
        // Validation's messages start with the field (`model.gamma must …`), sometimes behind
        // its table (`train.adam: adam.shader: lr = …`).
        (None, None) => msg
            .split_whitespace()
            .take_while(|w| w.ends_with(':') || w.contains('.'))
            .map(|w| w.trim_end_matches(':').to_string())
            .filter(|w| w.contains('.'))
            .collect(),
    };
    // The most specific key the file sets; validation names some without their top table.
    let line = keys.iter().rev().find_map(|k| {
        [k.clone(), format!("train.{k}"), format!("model.{k}")]
            .iter()
            .find_map(|k| line_of_key(text, k))
    });
    match line {
        Some(line) => format!("{origin}:{line}"),
        None => origin.to_string(),
    }
}

/// The 1-based line on which a TOML `text` sets the dotted key `path` (a `key = …` line under
/// the header of its table) or opens the table `path` (its header); dotted keys, quoted keys
/// and `[[…]]` headers are read, inline tables are not.
pub fn line_of_key(text: &str, path: &str) -> Option<usize> {
    let norm = |k: &str| -> String {
        k.split('.')
            .map(|p| p.trim().trim_matches('"').trim_matches('\''))
            .collect::<Vec<_>>()
            .join(".")
    };
    let mut table = String::new();
    for (i, line) in text.lines().enumerate() {
        let l = line.trim();
        if l.starts_with('#') || l.is_empty() {
            continue;
        }
        if let Some(h) = l.strip_prefix('[') {
            let h = h.trim_start_matches('[');
            table = norm(h.split(']').next().unwrap_or(""));
            if table == path {
                return Some(i + 1);
            }
            continue;
        }
        if let Some((k, _)) = l.split_once('=') {
            let k = norm(k);
            let full = if table.is_empty() {
                k
            } else {
                format!("{table}.{k}")
            };
            if full == path {
                return Some(i + 1);
            }
        }
    }
    None
}

/// Settings for the runs a tool trains one after another (`ablate`, `bench-geometry`): no
/// periodic evaluation (the final one is the result) and checkpoints [`tool_checkpoint_every`]
/// apart, so a killed run continues from one. The tools compare
/// [`RunConfig::results_toml`], which leaves the interval out, so runs of builds that saved none
/// are still reused.
/// Their runs share one step count (the variants of a table are compared at equal steps, not at
/// what each one's kept pixels would choose), so the budget is fixed at `train.steps`.
pub fn set_tool_run(cfg: &mut RunConfig) {
    cfg.train.budget = StepBudget::Fixed;
    cfg.train.eval_every = 0;
    cfg.train.checkpoint_every = tool_checkpoint_every(cfg.train.steps);
}

/// The checkpoint interval of the runs a tool trains one after another (`ablate`,
/// `bench-geometry`): about every tenth of the run, at least 1,000 steps apart, so a run killed
/// outright (SIGKILL, the OOM killer, a reboot) loses at most a tenth of itself while a
/// 2,000-step run saves once. A save costs 0.3–1 s on `small` (`docs/performance.md`,
/// "Checkpoints") and counts in the run's training time.
pub fn tool_checkpoint_every(steps: u64) -> u64 {
    steps.div_ceil(10).max(1000)
}

/// The `[train]` keys that decide when a run logs, evaluates and checkpoints, and how it holds its
/// samples in memory, never what it computes: a run resumed with other values trains the same
/// bits (SPEC §5; both sample sources give the same batches, `train/sampler.rs`). `--resume`
/// takes them from a `--config` file instead of refusing them ([`RunConfig::with_resumable`]).
pub const RESUMABLE_KEYS: [&str; 6] = [
    "checkpoint_every",
    "log_every",
    "eval_every",
    "eval_max_views",
    "memory_gb",
    "samples",
];

/// Whether a difference listed by [`toml_differences`] is one of a [`RESUMABLE_KEYS`].
pub fn is_resumable(difference: &str) -> bool {
    RESUMABLE_KEYS
        .iter()
        .any(|k| difference.starts_with(&format!("train.{k} = ")))
}

impl RunConfig {
    /// This configuration with the [`RESUMABLE_KEYS`] that `over` (a configuration as TOML,
    /// whole or in part) sets taken from it; `origin` names `over` in an error (a value of the
    /// wrong type).
    pub fn with_resumable(&self, over: &toml::Value, origin: &str) -> Result<RunConfig> {
        let mut v = toml::Value::try_from(self).expect("a RunConfig serialises");
        let (Some(train), Some(given)) = (v.get_mut("train"), over.get("train")) else {
            return Ok(self.clone());
        };
        for k in RESUMABLE_KEYS {
            if let (Some(x), Some(t)) = (given.get(k), train.as_table_mut()) {
                t.insert(k.to_string(), x.clone());
            }
        }
        v.try_into()
            .with_context(|| format!("{origin}: [train] {}", RESUMABLE_KEYS.join(", ")))
    }
}

/// The TOML `text` (read from `origin`) and every key it sets to another value than `cfg` has
/// ([`toml_differences`], `have_name` naming `cfg`), `train.steps` aside: a run's total, which a
/// resume may change.
pub fn differences_but_steps(
    text: &str,
    origin: &str,
    cfg: &RunConfig,
    have_name: &str,
) -> Result<(toml::Value, Vec<String>)> {
    let given: toml::Value =
        toml::from_str(text).with_context(|| format!("{origin}: not valid TOML"))?;
    let have: toml::Value = toml::from_str(&cfg.to_toml()).expect("a RunConfig serialises");
    let mut out = toml_differences(&given, &have, have_name);
    out.retain(|d| !d.starts_with("train.steps "));
    Ok((given, out))
}

/// Every key `given` sets whose value differs from `have`'s, as `key.path = value (HAVE has
/// other)` or `(HAVE has no such setting)`, `HAVE` being `have_name` ("the run"); integers and
/// floats compare by value (1 == 1.0). Keys of `have` that `given` leaves out are not listed.
pub fn toml_differences(given: &toml::Value, have: &toml::Value, have_name: &str) -> Vec<String> {
    let mut out = Vec::new();
    walk(given, have, String::new(), have_name, &mut out);
    return out;

    fn walk(g: &toml::Value, h: &toml::Value, key: String, name: &str, out: &mut Vec<String>) {
        match g {
            toml::Value::Table(t) => {
                for (k, v) in t {
                    let sub = if key.is_empty() {
                        k.clone()
                    } else {
                        format!("{key}.{k}")
                    };
                    match h.get(k) {
                        Some(hv) => walk(v, hv, sub, name, out),
                        None => out.push(format!("{sub} = {v} ({name} has no such setting)")),
                    }
                }
            }
            _ => {
                let same = match (g, h) {
                    (toml::Value::Integer(a), toml::Value::Float(b))
                    | (toml::Value::Float(b), toml::Value::Integer(a)) => *a as f64 == *b,
                    _ => g == h,
                };
                if !same {
                    out.push(format!("{key} = {g} ({name} has {h})"));
                }
            }
        }
    }
}

/// Whether grid `g`'s `per_level_scale` reaches its `finest_resolution` at some level at or past
/// its last one (`base · s^(L'-1) = finest` for an integer `L' ≥ levels`, to 1e-6 in `L'`): the
/// pair a run stores in its `config.toml` after resolving its level range and dropping the levels
/// finer than any footprint.
fn scale_reaches_finest(g: &crate::model::config::GridConfig) -> bool {
    let Some(finest) = g.finest_resolution else {
        return false;
    };
    let at = 1.0 + (finest / g.base_resolution as f64).ln() / g.per_level_scale.ln();
    at.is_finite() && (at - at.round()).abs() < 1e-6 && at.round() >= g.levels as f64
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A run's stored config.toml (grid H resolved by the automatic range, finer levels dropped:
    /// both per_level_scale and finest_resolution written) is accepted back as `--config`, as the
    /// spacing it trained with; a pair that disagrees is still refused.
    #[test]
    fn a_stored_config_is_accepted_as_a_config() {
        let mut cfg = RunConfig::preset("cpu").unwrap();
        let g = &mut cfg.model.grid_h;
        g.levels = 18;
        g.per_level_scale = crate::model::config::per_level_scale_for(16.0, 3370.5, 18);
        g.finest_resolution = Some(3370.5);
        g.levels = 15;
        cfg.train.steps = 1200;
        let dir = std::env::temp_dir().join(format!("xscale-stored-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("config.toml");
        std::fs::write(&path, cfg.to_toml()).unwrap();
        let back = RunConfig::resolve("cpu", Some(&path)).unwrap();
        assert_eq!(
            back.model.grid_h.per_level_scale,
            cfg.model.grid_h.per_level_scale
        );
        assert_eq!(back.model.grid_h.levels, 15);
        assert_eq!(back.train.level_range, LevelRange::Auto);
        assert_eq!(back.train.budget, cfg.train.budget);
        let mut bad = cfg.clone();
        bad.model.grid_h.finest_resolution = Some(3000.0);
        std::fs::write(&path, bad.to_toml()).unwrap();
        let e = RunConfig::resolve("cpu", Some(&path)).unwrap_err();
        assert!(format!("{e:#}").contains("disagree"), "{e:#}");
        std::fs::remove_dir_all(&dir).ok();
    }

    #[test]
    fn keys_are_found_on_their_lines() {
        let text = "# c\npreset = \"tiny\"\n\n[model]\ngamma = 7\n[model.shader]\n width = 0 \n[train]\nadam.shader.lr = 1\n\"seed\" = 2\n";
        assert_eq!(line_of_key(text, "preset"), Some(2));
        assert_eq!(line_of_key(text, "model.gamma"), Some(5));
        assert_eq!(line_of_key(text, "model.shader"), Some(6));
        assert_eq!(line_of_key(text, "model.shader.width"), Some(7));
        assert_eq!(line_of_key(text, "train.adam.shader.lr"), Some(9));
        assert_eq!(line_of_key(text, "train.seed"), Some(10));
        assert_eq!(line_of_key(text, "train.steps"), None);
        let e = format!(
            "{:#}",
            RunConfig::from_toml_str("[train]\nseed = 1\nstep = 5\n", "tiny", "c.toml")
                .unwrap_err()
        );
        assert!(e.starts_with("c.toml:3: "), "{e}");
        let e = format!(
            "{:#}",
            RunConfig::from_toml_str("\n[model]\ngamma = 9\n", "tiny", "c.toml").unwrap_err()
        );
        assert!(e.starts_with("c.toml:3: invalid configuration"), "{e}");
    }

    #[test]
    fn smooth_l1_needs_a_positive_delta() {
        // δ = 0 divided by zero in ρ(r) = 0.5·r²/δ: every loss and gradient NaN.
        for bad in ["0", "-0.01", "nan"] {
            let text = format!("[model]\nloss = \"smooth_l1\"\nsmooth_l1_delta = {bad}\n");
            let e = format!(
                "{:#}",
                RunConfig::from_toml_str(&text, "cpu", "c.toml").unwrap_err()
            );
            assert!(e.starts_with("c.toml:3: invalid configuration"), "{e}");
            assert!(
                e.contains("model.smooth_l1_delta must be a number > 0"),
                "{e}"
            );
        }
        // The other losses do not read δ: a stored 0 stays accepted.
        let text = "[model]\nloss = \"l1\"\nsmooth_l1_delta = 0\n";
        assert!(RunConfig::from_toml_str(text, "cpu", "c.toml").is_ok());
        let text = "[model]\nloss = \"smooth_l1\"\nsmooth_l1_delta = 0.02\n";
        assert!(RunConfig::from_toml_str(text, "cpu", "c.toml").is_ok());
    }

    #[test]
    fn overrides_and_roundtrip() {
        let c = RunConfig::from_toml_str(
            "preset = \"tiny\"\n[model]\ngamma = 1\n[model.deform]\nenabled = false\n[train]\nsteps = 7\n[train.adam.grid_h]\nlr = 0.5\n",
            "cpu",
            "test.toml",
        )
        .unwrap();
        assert_eq!(c.preset, "tiny");
        assert_eq!(c.model.gamma, 1);
        assert!(!c.model.deform.enabled);
        assert_eq!(c.model.grid_h.levels, 4, "untouched fields keep the preset");
        assert_eq!(c.train.steps, 7);
        assert_eq!(c.train.adam.grid_h.lr, 0.5);
        assert!(c.train.adam.grid_h.sparse, "roles are not overridable");
        let back = RunConfig::from_toml_str(&c.to_toml(), "cpu", "roundtrip").unwrap();
        assert_eq!(back, c);
    }

    /// A stored configuration reads back as the run it describes, under every preset and
    /// either level weighting: as a checkpoint's `run_config` and as a `--config` laid over
    /// any preset (`RUN/config.toml` reproduces the run). `level_weight = "none"` under the
    /// `cpu` preset read back as `"footprint"` while it was left out of the TOML.
    #[test]
    fn stored_configs_read_back_as_written() {
        use crate::model::config::LevelWeight;
        for preset in ["tiny", "cpu", "paper"] {
            for lw in [LevelWeight::None, LevelWeight::Footprint] {
                let mut c = RunConfig::preset(preset).unwrap();
                c.model.level_weight = lw;
                let text = c.to_toml();
                let stored = RunConfig::from_stored_toml(&text, "ckpt").unwrap();
                assert_eq!(stored, c, "{preset} {lw:?}");
                for over in ["tiny", "cpu", "paper"] {
                    let given = RunConfig::from_toml_str(&text, over, "config.toml").unwrap();
                    assert_eq!(given, c, "{preset} {lw:?} given under {over}");
                }
            }
        }
        // A key a stored config lacks takes its serde default (what the build that wrote it
        // meant), not the preset's: a `cpu` run from before level weighting had none.
        let mut old = RunConfig::preset("cpu").unwrap().to_toml();
        old = old.replace("level_weight = \"footprint\"\n", "");
        let c = RunConfig::from_stored_toml(&old, "old").unwrap();
        assert_eq!(c.model.level_weight, LevelWeight::None);
        // Errors still name the file and line.
        let e = RunConfig::from_stored_toml("preset = \"cpu\"\n[model]\ngamma = 2\n", "ck")
            .unwrap_err();
        assert!(format!("{e:#}").contains("ck"), "{e:#}");
    }

    /// The key tools compare to reuse a run leaves out its checkpoint interval, and only it:
    /// runs an earlier build trained with none match runs now trained with one.
    #[test]
    fn results_toml_leaves_out_the_checkpoint_interval_only() {
        let mut a = RunConfig::preset("cpu").unwrap();
        a.train.checkpoint_every = 0;
        let mut b = a.clone();
        b.train.checkpoint_every = tool_checkpoint_every(20_000);
        assert_eq!(b.train.checkpoint_every, 2_000);
        assert_ne!(a.to_toml(), b.to_toml());
        assert_eq!(a.results_toml(), b.results_toml());
        assert_eq!(
            a.results_toml(),
            a.to_toml(),
            "an interval of 0 is written as is"
        );
        b.train.eval_every += 1;
        assert_ne!(a.results_toml(), b.results_toml());
        assert_eq!(tool_checkpoint_every(2_000), 1_000);
        assert_eq!(
            tool_checkpoint_every(500),
            1_000,
            "a short run is not saved on the way"
        );
    }

    /// Every configuration the repository ships (`configs/`) is valid under every preset
    /// (`configs/ablations/vertex.toml` was refused under the default `cpu` preset, whose level
    /// weighting a vertex model cannot have).
    #[test]
    fn shipped_configs_resolve_under_every_preset() {
        let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("configs");
        let mut files = Vec::new();
        let mut todo = vec![dir];
        while let Some(d) = todo.pop() {
            for e in std::fs::read_dir(&d).unwrap().flatten() {
                let p = e.path();
                if p.is_dir() {
                    todo.push(p);
                } else if p.extension().is_some_and(|x| x == "toml") {
                    files.push(p);
                }
            }
        }
        assert!(files.len() >= 8, "{files:?}");
        let mut bad = Vec::new();
        for f in &files {
            for preset in ["tiny", "cpu", "paper"] {
                if let Err(e) = RunConfig::resolve(preset, Some(f)) {
                    bad.push(format!("{} under {preset}: {e:#}", f.display()));
                }
            }
        }
        assert!(bad.is_empty(), "{}", bad.join("\n"));
    }

    #[test]
    fn bad_keys_are_named() {
        let e = RunConfig::from_toml_str("[train]\nstepz = 3\n", "tiny", "x.toml").unwrap_err();
        let msg = format!("{e:#}");
        assert!(msg.contains("x.toml") && msg.contains("stepz"), "{msg}");
        let e = RunConfig::from_toml_str("[model]\ngamma = 9\n", "tiny", "y.toml").unwrap_err();
        assert!(format!("{e:#}").contains("gamma"), "{e:#}");
    }
}
