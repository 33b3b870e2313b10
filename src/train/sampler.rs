//! Deterministic batches (SPEC §5): slot `i` of batch `k` is kept pixel
//! `below(seed, Batch, k, i, pixels)` — a pure function of (seed, k, i), so batch k is the same
//! whatever happened before it (exact resume) and whatever the thread count.
//!
//! **Patch batches** (`[train] patch = k ≥ 2`, for the D-SSIM term, `model/ssim.rs`): the same
//! pixel budget as P = N/k² patches of k×k neighbouring pixels of one training view; pixel
//! (dx, dy) of patch j is row `j·k² + dy·k + dx`. Patch j of batch k tries up to
//! [`PATCH_TRIES`] origins, try t being kept pixel `below(seed, Patch, k, j·TRIES + t, pixels)`
//! (the patch's top-left pixel), and takes the first whose k×k pixels all lie in the image and
//! see the mesh. If none does, it takes the last try's patch with every pixel that does not see
//! the mesh (or lies outside the image) replaced by the origin pixel and marked 0 in
//! `Batch::patch_mask`: the D-SSIM term leaves out every window that covers it, the L1 term
//! counts the origin once more. A pure function of (seed, k, j) again. With `[train]
//! patch_pixels` = M < N, only the first M rows are patches; rows M..N are independent pixels,
//! slot i being kept pixel `below(seed, Batch, k, i, pixels)`, marked 0 in the patch mask (in
//! no SSIM window; the L1 term counts them as any pixel).
//!
//! Where a batch's surface samples come from is [`Samples`]: the [`RayStream`] (default: rays
//! cast when the batch is drawn, memory ~3 bytes per pixel) or the [`SampleCache`] (every
//! training ray cast once at setup and stored, `12γ²+42` bytes per kept pixel). Both number the
//! kept pixels the same way and give bit-identical batches (tested), so `train.samples` changes
//! speed and memory, never results. The default, `auto`, takes the cache when it is small (a
//! batch from the cache skips the per-batch ray casting: 0.45 against 4.3 ms of a 4,096-pixel
//! step on `small`, 2 threads) and the stream otherwise (`train/memory.rs` `resolve_samples`).

use crate::model::batch::Batch;
use crate::raycast::{RayStream, SampleCache, Tracer};
use crate::rng::{below, Purpose};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

/// Where training batches come from (`[train] samples`).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum SampleMode {
    /// The cache when it is small (`train/memory.rs` [`resolve_samples`]), else the stream.
    ///
    /// [`resolve_samples`]: crate::train::memory::resolve_samples
    #[default]
    Auto,
    /// Hit maps + photos; each batch's rays are cast when it is drawn.
    Stream,
    /// Every training ray cast once at setup and kept (the sample cache).
    Cache,
}

/// The training views' samples, streamed or cached (module docs).
pub enum Samples {
    Stream(RayStream),
    Cache(Box<SampleCache>),
}

impl Samples {
    /// No views yet, in mode `mode` (`auto` streams: [`crate::train::memory::resolve_samples`]
    /// has decided it before), for γ×γ rays per pixel, keeping each sub-sample's triangle and
    /// barycentrics when `keep_triangles` (the vertex featurization, the mesh refinement).
    pub fn empty(mode: SampleMode, gamma: u32, keep_triangles: bool) -> anyhow::Result<Samples> {
        Ok(match mode {
            SampleMode::Stream | SampleMode::Auto => {
                Samples::Stream(RayStream::new(gamma, keep_triangles)?)
            }
            SampleMode::Cache => Samples::Cache(Box::new(SampleCache::new(gamma, keep_triangles)?)),
        })
    }

    /// Number of kept pixels (pixels with at least one sub-sample on the mesh).
    pub fn len(&self) -> usize {
        match self {
            Samples::Stream(s) => s.len(),
            Samples::Cache(c) => c.len(),
        }
    }
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }
    /// Smallest pixel footprint of any kept view (SPEC §8).
    pub fn footprint_min(&self) -> Option<f32> {
        match self {
            Samples::Stream(s) => s.footprint_min(),
            Samples::Cache(c) => c.footprint_min(),
        }
    }
    /// The smallest, over kept views, of each view's `p`-quantile pixel footprint (normalised
    /// units; `raycast/footprint.rs`), `None` if nothing is kept.
    pub fn footprint_quantile_min(&self, p: f64) -> Option<f64> {
        let q: Vec<f64> = match self {
            Samples::Stream(s) => s
                .views
                .iter()
                .filter_map(|v| v.footprints.quantile(p))
                .collect(),
            Samples::Cache(c) => c
                .views
                .iter()
                .filter_map(|v| v.footprints.quantile(p))
                .collect(),
        };
        q.into_iter().reduce(f64::min)
    }

    /// Whether batches carry triangle ids and barycentrics (vertex featurization).
    pub fn has_triangles(&self) -> bool {
        match self {
            Samples::Stream(s) => s.keep_triangles,
            Samples::Cache(c) => c.has_triangles(),
        }
    }
    /// Bytes held.
    pub fn bytes(&self) -> usize {
        match self {
            Samples::Stream(s) => s.bytes(),
            Samples::Cache(c) => c.bytes(),
        }
    }
    pub fn mode(&self) -> SampleMode {
        match self {
            Samples::Stream(_) => SampleMode::Stream,
            Samples::Cache(_) => SampleMode::Cache,
        }
    }
    /// The batch of kept pixels `pixels` (row k = pixel `pixels[k]`).
    pub fn batch(&self, tracer: &Tracer, pixels: &[usize]) -> Batch {
        match self {
            Samples::Stream(s) => s.batch(tracer, pixels),
            Samples::Cache(c) => batch_from_pixels(c, pixels),
        }
    }
}

/// Slots per parallel chunk of [`batch_from_pixels`] (each slot is written from its own pixel
/// only, so the chunking does not change the batch).
const CACHE_BATCH_CHUNK: usize = 256;
/// How many pixels ahead [`batch_from_pixels`] prefetches a pixel's cached lines.
const CACHE_PREFETCH_AHEAD: usize = 16;

/// Fill `batch` with the cached pixels `pixels` (their appearance row = the cache's view index);
/// with triangle ids and barycentrics when the cache keeps them. Parallel over chunks of slots.
pub fn batch_from_pixels(cache: &SampleCache, pixels: &[usize]) -> Batch {
    let s = cache.samples_per_pixel();
    let n = pixels.len();
    let tri = cache.has_triangles();
    let mut b = Batch::zeros(n, s, tri);
    let c = CACHE_BATCH_CHUNK;
    pixels
        .par_chunks(c)
        .zip(b.positions.par_chunks_mut(c * s))
        .zip(b.valid.par_chunks_mut(c * s))
        .zip(b.dirs.par_chunks_mut(c))
        .zip(b.view.par_chunks_mut(c))
        .zip(b.target.par_chunks_mut(c))
        .zip(b.footprint.par_chunks_mut(c))
        .for_each(|((((((px, pos), valid), dirs), view), target), fp)| {
            for (k, &p) in px.iter().enumerate() {
                if let Some(&ahead) = px.get(k + CACHE_PREFETCH_AHEAD) {
                    cache.prefetch(ahead);
                }
                cache.positions_into(p, &mut pos[k * s..(k + 1) * s]);
                let mask = cache.valid(p);
                for j in 0..s {
                    valid[k * s + j] = ((mask >> j) & 1) as u8;
                }
                dirs[k] = cache.dir(p);
                view[k] = cache.view_index(p) as i32;
                target[k] = cache.target(p);
                fp[k] = cache.footprint(p);
            }
        });
    if tri {
        pixels
            .par_chunks(c)
            .zip(b.triangle.par_chunks_mut(c * s))
            .zip(b.bary.par_chunks_mut(c * s))
            .for_each(|((px, tri), bary)| {
                for (k, &p) in px.iter().enumerate() {
                    for j in 0..s {
                        (tri[k * s + j], bary[k * s + j]) = cache.surface_id(p, j);
                    }
                }
            });
    }
    b
}

/// The kept-pixel indices of batch `step` among `n` kept pixels.
pub fn batch_pixels(n: usize, seed: u64, step: u64, size: usize) -> Vec<usize> {
    (0..size as u64)
        .map(|i| below(seed, Purpose::Batch, step, i, n as u64) as usize)
        .collect()
}

/// Origins tried per patch before a partly covered patch is taken (module docs).
pub const PATCH_TRIES: u64 = 8;

impl Samples {
    /// (view slot, u, v) of kept pixel `i`.
    fn locate(&self, i: usize) -> (usize, u32, u32) {
        match self {
            Samples::Stream(s) => s.locate(i),
            Samples::Cache(c) => {
                let slot = c.views.partition_point(|v| v.start <= i) - 1;
                let [u, v] = c.pixel(i);
                (slot, u, v)
            }
        }
    }

    /// The kept index of pixel (u, v) of view slot `slot` (`None` outside the image or off
    /// the mesh). Both sources number a view's kept pixels in row-major order.
    fn index_at(&self, slot: usize, u: i64, v: i64) -> Option<usize> {
        if u < 0 || v < 0 || u > u32::MAX as i64 || v > u32::MAX as i64 {
            return None;
        }
        let (u, v) = (u as u32, v as u32);
        match self {
            Samples::Stream(s) => {
                let view = &s.views[slot];
                view.hits.index_of(u, v).map(|k| view.start + k)
            }
            Samples::Cache(c) => {
                let view = &c.views[slot];
                if u >= view.width || v >= view.height {
                    return None;
                }
                let (mut lo, mut hi) = (view.start, view.start + view.len);
                while lo < hi {
                    let mid = (lo + hi) / 2;
                    let [pu, pv] = c.pixel(mid);
                    if (pv, pu) < (v, u) {
                        lo = mid + 1;
                    } else {
                        hi = mid;
                    }
                }
                (lo < view.start + view.len && c.pixel(lo) == [u, v]).then_some(lo)
            }
        }
    }
}

/// The kept-pixel indices and patch mask of patch batch `step` (module docs): `patched / k²`
/// patches of side `k` (`patched` ≤ `size`, a multiple of k²), then `size − patched`
/// independent pixels (mask 0: in no SSIM window); the mask is empty when every row is in a
/// whole patch.
pub fn patch_pixels(
    samples: &Samples,
    seed: u64,
    step: u64,
    size: usize,
    k: usize,
    patched: usize,
) -> (Vec<usize>, Vec<u8>) {
    let n = samples.len() as u64;
    let k2 = k * k;
    let patches = patched.min(size) / k2;
    let mut pixels = Vec::with_capacity(size);
    let mut mask = Vec::with_capacity(size);
    let mut partial = false;
    let mut rows: Vec<Option<usize>> = Vec::with_capacity(k2);
    for j in 0..patches as u64 {
        let mut origin = 0;
        for t in 0..PATCH_TRIES {
            origin = below(seed, Purpose::Patch, step, j * PATCH_TRIES + t, n) as usize;
            let (slot, u, v) = samples.locate(origin);
            rows.clear();
            for dy in 0..k as i64 {
                for dx in 0..k as i64 {
                    rows.push(samples.index_at(slot, u as i64 + dx, v as i64 + dy));
                }
            }
            if rows.iter().all(Option::is_some) {
                break;
            }
        }
        for r in &rows {
            pixels.push(r.unwrap_or(origin));
            mask.push(r.is_some() as u8);
            partial |= r.is_none();
        }
    }
    for i in 0..(size - patches * k2) as u64 {
        pixels.push(below(seed, Purpose::Batch, step, i, n) as usize);
        mask.push(0);
        partial = true;
    }
    if !partial {
        mask.clear();
    }
    (pixels, mask)
}

/// Batch `step` of a run with `seed`: `size` independent pixels (`patch` ≤ 1), or `patched`
/// pixels in patches of side `patch` and the rest independent (module docs).
pub fn draw_batch(
    samples: &Samples,
    tracer: &Tracer,
    seed: u64,
    step: u64,
    size: usize,
    patch: u32,
    patched: usize,
) -> Batch {
    if patch <= 1 {
        return sample_batch(samples, tracer, seed, step, size);
    }
    let k = patch as usize;
    let (pixels, mask) = patch_pixels(samples, seed, step, size, k, patched);
    let mut b = samples.batch(tracer, &pixels);
    b.patch = k;
    b.patch_mask = mask;
    b
}

/// Batch `step` of a run with `seed`.
pub fn sample_batch(
    samples: &Samples,
    tracer: &Tracer,
    seed: u64,
    step: u64,
    size: usize,
) -> Batch {
    samples.batch(tracer, &batch_pixels(samples.len(), seed, step, size))
}
