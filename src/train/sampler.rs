//! Deterministic batches from the sample cache (SPEC §5): slot `i` of batch `k` is cached pixel
//! `below(seed, Batch, k, i, pixels)` — a pure function of (seed, k, i), so batch k is the same
//! whatever happened before it (exact resume) and whatever the thread count.

use crate::model::batch::Batch;
use crate::raycast::SampleCache;
use crate::rng::{below, Purpose};

/// Fill `batch` with the cached pixels `pixels` (their appearance row = the cache's view index);
/// with triangle ids and barycentrics when the cache keeps them.
pub fn batch_from_pixels(cache: &SampleCache, pixels: &[usize]) -> Batch {
    let s = cache.samples_per_pixel();
    let n = pixels.len();
    let mut b = Batch {
        positions: vec![[0.0; 3]; n * s],
        valid: vec![0; n * s],
        dirs: Vec::with_capacity(n),
        view: Vec::with_capacity(n),
        target: Vec::with_capacity(n),
        ..Batch::default()
    };
    if cache.has_triangles() {
        b.triangle = vec![u32::MAX; n * s];
        b.bary = vec![[0.0; 2]; n * s];
    }
    for (slot, &p) in pixels.iter().enumerate() {
        cache.positions_into(p, &mut b.positions[slot * s..(slot + 1) * s]);
        let mask = cache.valid(p);
        for j in 0..s {
            b.valid[slot * s + j] = ((mask >> j) & 1) as u8;
        }
        b.dirs.push(cache.dir(p));
        b.view.push(cache.view_index(p) as i32);
        b.target.push(cache.target(p));
        if cache.has_triangles() {
            for j in 0..s {
                (b.triangle[slot * s + j], b.bary[slot * s + j]) = cache.surface_id(p, j);
            }
        }
    }
    b
}

/// The cached pixels of batch `step`.
pub fn batch_pixels(cache: &SampleCache, seed: u64, step: u64, size: usize) -> Vec<usize> {
    let n = cache.len() as u64;
    (0..size as u64)
        .map(|i| below(seed, Purpose::Batch, step, i, n) as usize)
        .collect()
}

/// Batch `step` of a run with `seed`.
pub fn sample_batch(cache: &SampleCache, seed: u64, step: u64, size: usize) -> Batch {
    batch_from_pixels(cache, &batch_pixels(cache, seed, step, size))
}
