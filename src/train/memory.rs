//! The memory budget of a training run: an estimate made before anything large is allocated,
//! checked against `[train] memory_gb` (or, when that is 0, against the memory the system says is
//! available, `sysmem.rs`).
//!
//! ## The estimate (bytes)
//! - **samples** (`train/sampler.rs`): stream — per training view `w·h·3` (8-bit photo; 16-bit
//!   photos take twice that, EXR and downsampled photos four times: the estimate takes the
//!   photo's stored form from the downsample factor, and 3 bytes otherwise) + `w·h/8` hit map;
//!   cache — `w·h·(12γ²+42)`, every pixel assumed to see the mesh (an upper bound; `24γ²` with
//!   the triangle ids and barycentrics of the vertex featurization), plus one f32 photo
//!   (`12·w·h`) while it is cast; auto — whichever of the two [`resolve_samples`] picks;
//! - **model**: 20 bytes per parameter (f32 value, gradient, Adam m, v, step count);
//! - **photo**: with mesh refinement's photo-consistency term (`[model.refine] photo` > 0), every
//!   training view's f32 RGB copies at the image levels `photo_levels[1] ..= photo_levels[0]`
//!   (`12·⌈w/2^l⌉·⌈h/2^l⌉` bytes at level l; `refine/photo_term.rs`), with `photo_reach` > 0
//!   up to the view's last usable level (`model::refine::photo_level_cap`) instead of `photo_levels[0]`;
//! - **step**: [`STEP_BYTES_PER_SAMPLE`] per sub-sample of a batch (forward activations kept for
//!   the backward pass, gradients of the inputs, touched-entry lists), measured on the `cpu`
//!   preset (see the constant);
//! - a fixed [`BASE_BYTES`] (code, allocator slack, a small mesh's BVH). The mesh's BVH is not in
//!   the estimate: building it is checked on its own against the available memory
//!   (`raycast::bvh::BVH_BYTES_PER_TRIANGLE`), before the setup reaches this check.
//!
//! It errs on the high side; a run that fails the check names the figures and what to change.

use crate::model::hfm::Hfm;
use crate::sysmem::{available_bytes, size};
use crate::train::config::RunConfig;
use crate::train::sampler::SampleMode;
use anyhow::Result;

/// Step scratch per sub-sample of a batch. Measured: peak RSS of `xscale train --preset cpu` on the
/// `small` scene at batch 4,096 and 65,536 pixels (γ = 2), difference / (61,440 · 4) ≈ 1.1 kB,
/// rounded up.
pub const STEP_BYTES_PER_SAMPLE: u64 = 1536;
/// Fixed overhead.
pub const BASE_BYTES: u64 = 200 << 20;

/// What a run is estimated to need, by part (bytes).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Estimate {
    pub samples: u64,
    pub model: u64,
    pub photo: u64,
    pub step: u64,
    pub base: u64,
}

impl Estimate {
    pub fn total(&self) -> u64 {
        // Saturating: a batch size near usize::MAX must read as too large, not wrap.
        [self.samples, self.model, self.photo, self.step, self.base]
            .into_iter()
            .fold(0, u64::saturating_add)
    }
}

/// `samples = "auto"` takes the sample cache when its estimate is at most this many bytes …
pub const AUTO_CACHE_MAX_BYTES: u64 = 2_000_000_000;
/// … and at most this share of the memory budget (`train.memory_gb`, or what is available).
pub const AUTO_CACHE_BUDGET_SHARE: f64 = 0.25;

/// Bytes of the training samples, cached (`cache`) or streamed.
fn sample_bytes(cfg: &RunConfig, cache: bool, sizes: &[(u32, u32)], downsample: u32) -> u64 {
    let g2 = (cfg.model.gamma * cfg.model.gamma) as u64;
    // A slot's position (3 × u32), plus its triangle id and barycentrics (3 × u32) when the run
    // keeps them (`train/setup.rs`: the vertex featurization, the mesh refinement).
    let keeps_triangles = !cfg.model.featurization.is_hash() || cfg.model.refine.enabled;
    let slot = if keeps_triangles { 24 } else { 12 };
    let photo_bytes = if downsample > 1 { 12 } else { 3 };
    let per_view: u64 = sizes
        .iter()
        .map(|&(w, h)| {
            let px = w as u64 * h as u64;
            if cache {
                px * (slot * g2 + 42)
            } else {
                px * photo_bytes + px.div_ceil(8)
            }
        })
        .sum();
    let cast_photo = if cache {
        sizes
            .iter()
            .map(|&(w, h)| 12 * w as u64 * h as u64)
            .max()
            .unwrap_or(0)
    } else {
        0
    };
    per_view + cast_photo
}

/// A budget in bytes with the words that name it; `None` when the system gives no reading.
pub type Budget = Option<(u64, String)>;

/// The budget a run is checked against: `train.memory_gb` when > 0, else the available memory
/// (when the system reports it), with the words that name it.
pub fn budget(cfg: &RunConfig) -> Budget {
    if cfg.train.memory_gb > 0.0 {
        Some((
            (cfg.train.memory_gb * 1e9) as u64,
            format!("the budget train.memory_gb = {}", cfg.train.memory_gb),
        ))
    } else {
        available_bytes().map(|a| (a, "the memory available on this machine".to_string()))
    }
}

/// What `train.samples` means for this run, and why: `stream` and `cache` as given; `auto` is the
/// cache when the cache's estimate (every pixel kept, as in [`estimate`]) is at most
/// [`AUTO_CACHE_MAX_BYTES`] and at most [`AUTO_CACHE_BUDGET_SHARE`] of the budget, and the mesh
/// does not move (mesh refinement casts against the moving mesh); else the stream. Both give the
/// same batches bit for bit, so the choice changes speed and memory only (a cached batch skips
/// casting its rays: 0.45 against 4.3 ms of a 4,096-pixel `cpu` step on `small`, 2 threads).
pub fn resolve_samples(
    cfg: &RunConfig,
    sizes: &[(u32, u32)],
    downsample: u32,
) -> (SampleMode, String) {
    resolve_within(cfg, sizes, downsample, budget(cfg).map(|(b, _)| b))
}

/// [`resolve_samples`] against a budget already read (`None`: the system does not say).
fn resolve_within(
    cfg: &RunConfig,
    sizes: &[(u32, u32)],
    downsample: u32,
    budget: Option<u64>,
) -> (SampleMode, String) {
    match cfg.train.samples {
        SampleMode::Auto => {}
        m => return (m, "as configured".into()),
    }
    if cfg.model.refine.enabled {
        return (
            SampleMode::Stream,
            "auto: the mesh refinement moves the mesh".into(),
        );
    }
    let bytes = sample_bytes(cfg, true, sizes, downsample);
    let cap = match budget {
        Some(b) => AUTO_CACHE_MAX_BYTES.min((b as f64 * AUTO_CACHE_BUDGET_SHARE) as u64),
        None => AUTO_CACHE_MAX_BYTES,
    };
    if bytes <= cap {
        (
            SampleMode::Cache,
            format!(
                "auto: a cache of at most {} fits the {} allowed",
                size(bytes as f64),
                size(cap as f64)
            ),
        )
    } else {
        (
            SampleMode::Stream,
            format!(
                "auto: a cache would take up to {}, more than the {} allowed",
                size(bytes as f64),
                size(cap as f64)
            ),
        )
    }
}

/// The estimate for a run over training views of sizes `sizes` (after downsampling), with its
/// samples as [`resolve_samples`] chooses them.
pub fn estimate(cfg: &RunConfig, sizes: &[(u32, u32)], downsample: u32) -> Result<Estimate> {
    let mode = resolve_samples(cfg, sizes, downsample).0;
    estimate_for(cfg, mode, sizes, downsample)
}

/// [`estimate`] with the samples resolved to `mode`.
fn estimate_for(
    cfg: &RunConfig,
    mode: SampleMode,
    sizes: &[(u32, u32)],
    downsample: u32,
) -> Result<Estimate> {
    let g2 = (cfg.model.gamma * cfg.model.gamma) as u64;
    let samples = sample_bytes(cfg, mode == SampleMode::Cache, sizes, downsample);
    let params = if cfg.model.featurization.is_hash() {
        Hfm::new(&cfg.model)?.layout.total as u64
    } else {
        0 // the vertex table depends on the mesh; counted by the caller's base
    };
    let r = &cfg.model.refine;
    let photo = if r.enabled && r.photo > 0.0 {
        let [hi, lo] = r.photo_levels;
        let (reach, patch) = (r.photo_reach > 0.0, r.photo_patch);
        sizes
            .iter()
            .flat_map(|&(w, h)| {
                let top = match reach {
                    true => crate::model::refine::photo_level_cap(w, h, hi, patch),
                    false => hi,
                };
                (lo..=top).map(move |l| {
                    let f = 1u64 << l.min(31);
                    12 * (w as u64).div_ceil(f) * (h as u64).div_ceil(f)
                })
            })
            .sum()
    } else {
        0
    };
    Ok(Estimate {
        samples,
        model: 20 * params,
        photo,
        step: cfg.train.batch_pixels as u64 * g2 * STEP_BYTES_PER_SAMPLE,
        base: BASE_BYTES,
    })
}

fn gb(b: u64) -> f64 {
    b as f64 / 1e9
}

/// What the memory check sizes: a training run, or the one batch `xscale batch` writes.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Job {
    /// Training (and `init`): the model with Adam, and steps of `train.batch_pixels` pixels.
    Train,
    /// `xscale batch --size PIXELS`: the samples and one batch of `PIXELS` pixels as tensors,
    /// [`BATCH_BYTES_PER_SAMPLE`] per sub-sample plus [`BATCH_BYTES_PER_PIXEL`]; no model.
    Batch { pixels: usize },
}

/// `xscale batch`: bytes per sub-sample of the batch it writes (position f64 ×3, valid flag) and
/// per pixel (direction, target, view, footprint, the drawn pixel's index), each held about three
/// times: the batch, its tensors, the written bytes. Measured: peak RSS of `xscale batch --preset
/// tiny` on `fixtures/tiny` (γ = 2) at 1 M and 4 M pixels, 388 MB and 1,513 MB: 384 bytes per
/// pixel (the file holds 132), against 4 · 80 + 112 = 432 here.
pub const BATCH_BYTES_PER_SAMPLE: u64 = 80;
pub const BATCH_BYTES_PER_PIXEL: u64 = 112;

/// `xscale dump`: bytes per sub-sample and feature (grid H's `L·F`, plus, with the deformation,
/// grid D's `L·F`, ξ's hidden width and its output `L·F`) at f64 (half that at f32), and per
/// pixel: forward activations, gradients and the dump's tensors. Measured: see [`check_dump`].
pub const DUMP_BYTES_PER_SAMPLE_FEATURE: u64 = 40;
pub const DUMP_BYTES_PER_PIXEL: u64 = 2048;

/// Fail, before anything large is allocated, when the estimate exceeds the budget:
/// `train.memory_gb` when > 0, else the available memory (when the system reports it).
/// Returns the sample source the run is to use and why ([`resolve_samples`], decided against
/// the same budget reading as the check).
pub fn check_budget(
    cfg: &RunConfig,
    sizes: &[(u32, u32)],
    downsample: u32,
) -> Result<(SampleMode, String)> {
    check_job(cfg, sizes, downsample, Job::Train)
}

/// [`check_budget`] for `job`.
pub fn check_job(
    cfg: &RunConfig,
    sizes: &[(u32, u32)],
    downsample: u32,
    job: Job,
) -> Result<(SampleMode, String)> {
    check_job_against(cfg, sizes, downsample, job, budget(cfg))
}

/// [`check_job`] against a budget already read. A run's setup reads it once and checks the model
/// again once the level range has resized it (`TrainState::init`) against that same reading: a
/// new one would see the samples already allocated and count them twice.
pub fn check_job_against(
    cfg: &RunConfig,
    sizes: &[(u32, u32)],
    downsample: u32,
    job: Job,
    budget: Budget,
) -> Result<(SampleMode, String)> {
    let (mode, why) = resolve_within(cfg, sizes, downsample, budget.as_ref().map(|(b, _)| *b));
    let mut e = estimate_for(cfg, mode, sizes, downsample)?;
    let g2 = cfg.model.gamma * cfg.model.gamma;
    let (what, pixels, flag, per_pixel) = match job {
        Job::Train => (
            "this run",
            cfg.train.batch_pixels,
            "--batch",
            g2 as u64 * STEP_BYTES_PER_SAMPLE,
        ),
        Job::Batch { pixels } => {
            let per_pixel = g2 as u64 * BATCH_BYTES_PER_SAMPLE + BATCH_BYTES_PER_PIXEL;
            e.model = 0;
            e.photo = 0;
            e.step = (pixels as u64).saturating_mul(per_pixel);
            ("this batch", pixels, "--size", per_pixel)
        }
    };
    let Some((budget, budget_words)) = budget.or_else(|| beyond_addressing(&e)) else {
        return Ok((mode, why));
    };
    if e.total() <= budget {
        return Ok((mode, why));
    }
    let pixels_in_views: u64 = sizes.iter().map(|&(w, h)| w as u64 * h as u64).sum();
    let mut hints = Vec::new();
    if e.samples > budget / 3 {
        if mode == SampleMode::Cache {
            hints.push(
                "stream the rays instead of caching them ([train] samples = \"stream\")".into(),
            );
        }
        // A config key: `train` and `batch` have no --downsample flag (only cast, render and
        // eval do), and the advice used to name one.
        hints.push(format!(
            "downsample the photos ([train] downsample = {})",
            cfg.train.downsample * 2
        ));
        hints.push("hold out or remove views (scene.toml test_views / holdout_every)".into());
    }
    if e.step > budget / 3 {
        let mut smaller = pixels / 4;
        if let Job::Batch { .. } = job {
            // A quarter of an absurd size is still absurd: at most what fits.
            let room = budget.saturating_sub(e.total().saturating_sub(e.step));
            smaller = smaller.min((room / per_pixel.max(1)) as usize);
        }
        hints.push(format!("a smaller batch ({flag} {})", smaller.max(1)));
    }
    if e.model > budget / 3 {
        hints.push("a smaller hash table ([model.grid_h] log2_table_size)".into());
        if cfg.model.grid_h.finest_resolution.is_some()
            && cfg.train.level_range == crate::train::config::LevelRange::Auto
        {
            // Set by `resolve_levels`: the closest views asked for these levels.
            hints.push(format!(
                "fewer grid H levels than the {} the closest views ask for ([train] level_range = \"fixed\")",
                cfg.model.grid_h.levels
            ));
        }
    }
    if e.photo > budget / 3 {
        let [hi, lo] = cfg.model.refine.photo_levels;
        hints.push(format!(
            "the photo-consistency term without full-resolution photos ([model.refine] photo_levels = [{}, {}])",
            hi.max(1),
            lo.max(1)
        ));
    }
    let mut parts = vec![format!(
        "{} training views ({:.1} Mpixels) take {:.2} GB as {}",
        sizes.len(),
        pixels_in_views as f64 / 1e6,
        gb(e.samples),
        match mode {
            SampleMode::Cache => "the sample cache",
            _ => "hit maps + photos",
        }
    )];
    if job == Job::Train {
        parts.push(format!("the model and Adam {:.2} GB", gb(e.model)));
    }
    if e.photo > 0 {
        parts.push(format!(
            "the photo-consistency term's image levels {:.2} GB",
            gb(e.photo)
        ));
    }
    parts.push(format!(
        "{} of {pixels} pixels × γ²={g2} {:.2} GB",
        if job == Job::Train {
            "a step"
        } else {
            "a batch"
        },
        gb(e.step)
    ));
    Err(refusal(what, &e, budget, &budget_words, parts, hints))
}

/// `xscale dump`: fail before evaluating when a dump of `pixels` pixels × `samples` sub-samples
/// of a model of `params` parameters and `features` values per sub-sample
/// ([`DUMP_BYTES_PER_SAMPLE_FEATURE`]) in f64 (`f64_dump`, else f32) cannot fit in the available
/// memory: [`DUMP_BYTES_PER_SAMPLE_FEATURE`] per sub-sample and feature (half in f32),
/// [`DUMP_BYTES_PER_PIXEL`] per pixel, the model 24 bytes per parameter. Measured: peak RSS of
/// `xscale dump` on `xscale batch --preset cpu` batches of `fixtures/tiny` (γ = 2) of 20,000 and
/// 100,000 pixels; per pixel, f64 with the kink analysis: golden `cpu-t10` (112 features)
/// 15.1 KB, `tiny-f64-linear` (28 features) 5.2 KB, i.e. 30 bytes per sub-sample and feature
/// plus 1.8 KB; f32 `cpu-t10` 8.0 KB. The constants (40 and 2,048) err on the high side:
/// 20.0 KB and 6.5 KB per pixel for those two models.
pub fn check_dump(
    pixels: usize,
    samples: usize,
    features: usize,
    params: usize,
    f64_dump: bool,
) -> Result<()> {
    let per_feature = if f64_dump {
        DUMP_BYTES_PER_SAMPLE_FEATURE
    } else {
        DUMP_BYTES_PER_SAMPLE_FEATURE / 2
    };
    let per_pixel = (samples as u64)
        .saturating_mul(features as u64)
        .saturating_mul(per_feature)
        .saturating_add(DUMP_BYTES_PER_PIXEL);
    let e = Estimate {
        samples: 0,
        model: 24 * params as u64,
        photo: 0,
        step: (pixels as u64).saturating_mul(per_pixel),
        base: BASE_BYTES,
    };
    let available = available_bytes().map(|a| (a, "the memory available on this machine".into()));
    let Some((budget, budget_words)) = available.or_else(|| beyond_addressing(&e)) else {
        return Ok(());
    };
    if e.total() <= budget {
        return Ok(());
    }
    let parts = vec![
        format!("the model {:.2} GB", gb(e.model)),
        format!(
            "a batch of {pixels} pixels × {samples} sub-samples {:.2} GB",
            gb(e.step)
        ),
    ];
    let room = budget.saturating_sub(e.total().saturating_sub(e.step));
    let hints = vec![format!(
        "a smaller batch (xscale batch --size {})",
        (pixels / 4).min((room / per_pixel.max(1)) as usize).max(1)
    )];
    Err(refusal(
        "this dump",
        &e,
        budget,
        &budget_words,
        parts,
        hints,
    ))
}

/// Without a reading of the memory: a budget only an estimate beyond what a process can address
/// exceeds (so a batch size near `usize::MAX` is still refused, not a capacity overflow).
fn beyond_addressing(e: &Estimate) -> Option<(u64, String)> {
    let max = isize::MAX as u64;
    (e.total() > max).then(|| (max, "the most a process can address".to_string()))
}

/// The error of a job (`what`: "this run") whose estimate `e` exceeds `budget` (named by
/// `budget_words`): its parts, the fixed overhead, and what to change (`hints`).
fn refusal(
    what: &str,
    e: &Estimate,
    budget: u64,
    budget_words: &str,
    parts: Vec<String>,
    hints: Vec<String>,
) -> anyhow::Error {
    anyhow::anyhow!(
        "{what} needs about {:.2} GB but {budget_words} is {:.2} GB: {}, fixed {:.2} GB. To fit: {}",
        gb(e.total()),
        gb(budget),
        parts.join(", "),
        gb(e.base),
        if hints.is_empty() {
            "raise train.memory_gb".to_string()
        } else {
            hints.join("; ")
        }
    )
}
