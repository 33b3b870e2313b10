//! The memory budget of a training run: an estimate made before anything large is allocated,
//! checked against `[train] memory_gb` (or, when that is 0, against the memory the system says is
//! available), and the peak resident memory reported at the end of a run.
//!
//! ## The estimate (bytes)
//! - **samples** (`train/sampler.rs`): stream — per training view `w·h·3` (8-bit photo; 16-bit
//!   photos take twice that, EXR and downsampled photos four times: the estimate takes the
//!   photo's stored form from the downsample factor, and 3 bytes otherwise) + `w·h/8` hit map;
//!   cache — `w·h·(12γ²+42)`, every pixel assumed to see the mesh (an upper bound), plus one f32
//!   photo (`12·w·h`) while it is cast; auto — whichever of the two [`resolve_samples`] picks;
//! - **model**: 20 bytes per parameter (f32 value, gradient, Adam m, v, step count);
//! - **photo**: with mesh refinement's photo-consistency term (`[model.refine] photo` > 0), every
//!   training view's f32 RGB copies at the image levels `photo_levels[1] ..= photo_levels[0]`
//!   (`12·⌈w/2^l⌉·⌈h/2^l⌉` bytes at level l; `train/photo.rs`);
//! - **step**: [`STEP_BYTES_PER_SAMPLE`] per sub-sample of a batch (forward activations kept for
//!   the backward pass, gradients of the inputs, touched-entry lists), measured on the `cpu`
//!   preset (see the constant);
//! - a fixed [`BASE_BYTES`] (BVH, code, allocator slack) plus 64 bytes per mesh triangle for the
//!   BVH and the f64 mesh are added by the caller when known.
//!
//! It errs on the high side; a run that fails the check names the figures and what to change.

use crate::model::hfm::Hfm;
use crate::train::config::RunConfig;
use crate::train::sampler::SampleMode;
use anyhow::{bail, Result};

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
        self.samples + self.model + self.photo + self.step + self.base
    }
}

/// `samples = "auto"` takes the sample cache when its estimate is at most this many bytes …
pub const AUTO_CACHE_MAX_BYTES: u64 = 2_000_000_000;
/// … and at most this share of the memory budget (`train.memory_gb`, or what is available).
pub const AUTO_CACHE_BUDGET_SHARE: f64 = 0.25;

/// Bytes of the training samples, cached (`cache`) or streamed.
fn sample_bytes(cfg: &RunConfig, cache: bool, sizes: &[(u32, u32)], downsample: u32) -> u64 {
    let g2 = (cfg.model.gamma * cfg.model.gamma) as u64;
    let photo_bytes = if downsample > 1 { 12 } else { 3 };
    let per_view: u64 = sizes
        .iter()
        .map(|&(w, h)| {
            let px = w as u64 * h as u64;
            if cache {
                px * (12 * g2 + 42)
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

/// The budget a run is checked against: `train.memory_gb` when > 0, else the available memory
/// (when the system reports it), with the words that name it.
fn budget(cfg: &RunConfig) -> Option<(u64, String)> {
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
                size(bytes),
                size(cap)
            ),
        )
    } else {
        (
            SampleMode::Stream,
            format!(
                "auto: a cache would take up to {}, more than the {} allowed",
                size(bytes),
                size(cap)
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
        sizes
            .iter()
            .flat_map(|&(w, h)| {
                (lo..=hi).map(move |l| {
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

/// Memory the system reports as available (Linux `MemAvailable`), if known; less when the
/// process's address space is limited (`ulimit -v`, RLIMIT_AS): what the limit leaves of it.
pub fn available_bytes() -> Option<u64> {
    let text = std::fs::read_to_string("/proc/meminfo").ok()?;
    let line = text.lines().find(|l| l.starts_with("MemAvailable:"))?;
    let kb: u64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(address_space_left().map_or(kb * 1024, |left| left.min(kb * 1024)))
}

/// What the address-space limit (`ulimit -v`) leaves this process (the limit less its `VmSize`),
/// when there is a limit.
fn address_space_left() -> Option<u64> {
    #[cfg(unix)]
    {
        let mut lim = libc::rlimit {
            rlim_cur: 0,
            rlim_max: 0,
        };
        // SAFETY: getrlimit writes the struct it is given.
        if unsafe { libc::getrlimit(libc::RLIMIT_AS, &mut lim) } != 0
            || lim.rlim_cur == libc::RLIM_INFINITY
        {
            return None;
        }
        // `rlim_t` is u64 on Linux, not on every Unix.
        #[allow(clippy::unnecessary_cast)]
        let limit = lim.rlim_cur as u64;
        Some(limit.saturating_sub(status_kb("VmSize:").unwrap_or(0) * 1024))
    }
    #[cfg(not(unix))]
    None
}

/// A `KEY: N kB` line of `/proc/self/status`.
fn status_kb(key: &str) -> Option<u64> {
    let text = std::fs::read_to_string("/proc/self/status").ok()?;
    let line = text.lines().find(|l| l.starts_with(key))?;
    line.split_whitespace().nth(1)?.parse().ok()
}

/// Refuse, before allocating, `need` bytes that `what` would take when more than the memory
/// available ([`available_bytes`]; nothing is refused where the system does not say): an
/// allocation that fails aborts the process without a word (`memory allocation of N bytes
/// failed`, exit 134). `fix` says what to change.
pub fn check_fits(need: u64, what: &str, fix: &str) -> Result<()> {
    match available_bytes() {
        Some(avail) if need > avail => bail!(
            "{what} would take about {} in memory, and {} are available; {fix}",
            size(need),
            size(avail)
        ),
        _ => Ok(()),
    }
}

/// Peak resident memory of this process so far (Linux `VmHWM`), if known.
pub fn peak_rss_bytes() -> Option<u64> {
    Some(status_kb("VmHWM:")? * 1024)
}

fn gb(b: u64) -> f64 {
    b as f64 / 1e9
}

/// `b` bytes in MB below 1 GB, else in GB.
fn size(b: u64) -> String {
    if b < 1_000_000_000 {
        format!("{:.1} MB", b as f64 / 1e6)
    } else {
        format!("{:.2} GB", gb(b))
    }
}

/// Fail, before anything large is allocated, when the estimate exceeds the budget:
/// `train.memory_gb` when > 0, else the available memory (when the system reports it).
/// Returns the sample source the run is to use and why ([`resolve_samples`], decided against
/// the same budget reading as the check).
pub fn check_budget(
    cfg: &RunConfig,
    sizes: &[(u32, u32)],
    downsample: u32,
) -> Result<(SampleMode, String)> {
    let budget = budget(cfg);
    let (mode, why) = resolve_within(cfg, sizes, downsample, budget.as_ref().map(|(b, _)| *b));
    let e = estimate_for(cfg, mode, sizes, downsample)?;
    let Some((budget, what)) = budget else {
        return Ok((mode, why));
    };
    if e.total() <= budget {
        return Ok((mode, why));
    }
    let pixels: u64 = sizes.iter().map(|&(w, h)| w as u64 * h as u64).sum();
    let mut hints = Vec::new();
    if e.samples > budget / 3 {
        if mode == SampleMode::Cache {
            hints.push(
                "stream the rays instead of caching them ([train] samples = \"stream\")".into(),
            );
        }
        hints.push(format!(
            "downsample the photos (--downsample {})",
            cfg.train.downsample * 2
        ));
        hints.push("hold out or remove views (scene.toml test_views / holdout_every)".into());
    }
    if e.step > budget / 3 {
        hints.push(format!(
            "a smaller batch (--batch {})",
            (cfg.train.batch_pixels / 4).max(1)
        ));
    }
    if e.model > budget / 3 {
        hints.push("a smaller hash table ([model.grid_h] log2_table_size)".into());
    }
    if e.photo > budget / 3 {
        let [hi, lo] = cfg.model.refine.photo_levels;
        hints.push(format!(
            "the photo-consistency term without full-resolution photos ([model.refine] photo_levels = [{}, {}])",
            hi.max(1),
            lo.max(1)
        ));
    }
    bail!(
        "this run needs about {:.2} GB but {what} is {:.2} GB: {} training views ({:.1} Mpixels) take {:.2} GB as {}, the model and Adam {:.2} GB,{} a step of {} pixels × γ²={} {:.2} GB, fixed {:.2} GB. To fit: {}",
        gb(e.total()),
        gb(budget),
        sizes.len(),
        pixels as f64 / 1e6,
        gb(e.samples),
        match mode {
            SampleMode::Cache => "the sample cache",
            _ => "hit maps + photos",
        },
        gb(e.model),
        if e.photo > 0 {
            format!(" the photo-consistency term's image levels {:.2} GB,", gb(e.photo))
        } else {
            String::new()
        },
        cfg.train.batch_pixels,
        cfg.model.gamma * cfg.model.gamma,
        gb(e.step),
        gb(e.base),
        if hints.is_empty() {
            "raise train.memory_gb".to_string()
        } else {
            hints.join("; ")
        }
    )
}
