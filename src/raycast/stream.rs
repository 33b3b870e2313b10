//! Rays cast as batches are drawn (SPEC §1): the training views' hit maps and photos are kept,
//! not their surface samples, so memory grows by ~3 bytes per pixel instead of `12γ²+42`.
//!
//! ## What is kept per training view
//! - A **hit map**: one bit per pixel, set when at least one of its γ² rays hits the mesh (the
//!   pixels the [`SampleCache`](super::SampleCache) would keep), with the number of kept pixels
//!   before each row. Built once by casting the view at setup (in parallel over constant-size
//!   strips, like the cache), then the sub-samples are thrown away.
//! - The **photo** in the narrowest exact form ([`Targets`]): 8-bit images as `u8`, 16-bit
//!   as `u16`, anything else (EXR, downsampled images) as `f32`. A `u8`/`u16` store is used only
//!   when every value round-trips bit for bit through `k / 255` or `k / 65535`, so a target read
//!   back is the same `f32` the loader produced.
//! - The smallest pixel footprint of the view (SPEC §8).
//!
//! Kept pixels are numbered view by view in input order, row-major inside a view — the cache's
//! order — so a batch drawn by index (`train/sampler.rs`) picks the same pixels in both modes.
//!
//! ## Casting a batch
//! [`RayStream::batch`] locates each drawn pixel (view, u, v) by its kept index (binary search over
//! the views, then the rows, then a select in the row's bit words), casts its γ² rays as one packet
//! (`cast::cast_pixel`: the same directions, closest hit and f64 refinement as the whole-view
//! cast, so the same bits), quantises positions (and barycentrics) to the cache's 32-bit fixed
//! point, and rounds the pixel direction and footprint to f32 as the cache stores them. The
//! result is bit-identical to the batch the cache gives for the same pixel indices (tested).
//! Pixels are cast in parallel in chunks of [`BATCH_CHUNK`] (a constant), each writing its own
//! rows of the batch, so the batch does not depend on the thread count.
//!
//! ## Memory
//! 1 bit per pixel of hit map + 4 bytes per row + the photo (3 bytes per pixel for 8-bit
//! images, 6 for 16-bit, 12 for f32). The 80-megapixel `large` synthetic scene keeps ~250 MB.

use super::bvh::Tracer;
use super::cache::{decode_coord, encode_coord, CacheEvent};
use super::cast::{
    cast_pixel, cast_strip, check_gamma, strips, CamCtx, PixelSummary, Strip, SubSample,
};
use super::footprint::FootprintHist;
use crate::model::batch::Batch;
use crate::scene::{Camera, Image};
use anyhow::{bail, Result};
use rayon::prelude::*;

/// Pixels per parallel work item when casting a batch (a constant: determinism, SPEC §5).
pub const BATCH_CHUNK: usize = 64;

/// One bit per pixel: at least one of its γ² rays hits the mesh.
#[derive(Clone, Debug, PartialEq)]
pub struct HitMap {
    pub width: u32,
    pub height: u32,
    words_per_row: usize,
    /// `[height][words_per_row]`, bit `u % 64` of word `u / 64`.
    bits: Vec<u64>,
    /// `[height + 1]` kept pixels before each row (`row_start[height]` = all kept pixels).
    row_start: Vec<u32>,
}

impl HitMap {
    /// A hit map from its bit words: `[height][ceil(width/64)]`, bit `u % 64` of word `u / 64`.
    pub fn from_bits(width: u32, height: u32, bits: Vec<u64>) -> HitMap {
        let words_per_row = (width as usize).div_ceil(64);
        debug_assert_eq!(bits.len(), words_per_row * height as usize);
        let mut row_start = Vec::with_capacity(height as usize + 1);
        let mut n = 0u32;
        row_start.push(0);
        for r in bits
            .chunks_exact(words_per_row.max(1))
            .take(height as usize)
        {
            n += r.iter().map(|w| w.count_ones()).sum::<u32>();
            row_start.push(n);
        }
        row_start.resize(height as usize + 1, n);
        HitMap {
            width,
            height,
            words_per_row,
            bits,
            row_start,
        }
    }

    /// Number of pixels that see the mesh.
    pub fn len(&self) -> usize {
        self.row_start[self.height as usize] as usize
    }
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Whether pixel (u, v) sees the mesh.
    pub fn get(&self, u: u32, v: u32) -> bool {
        let w = self.bits[v as usize * self.words_per_row + u as usize / 64];
        w >> (u % 64) & 1 != 0
    }

    /// Pixel (u, v) of the `k`-th kept pixel in row-major order (`k < len()`).
    pub fn locate(&self, k: usize) -> (u32, u32) {
        let k = k as u32;
        // Last row whose start is ≤ k (rows without kept pixels share their start with the next).
        let v = self.row_start.partition_point(|&s| s <= k) - 1;
        let mut rem = k - self.row_start[v];
        let row = &self.bits[v * self.words_per_row..(v + 1) * self.words_per_row];
        for (i, &w) in row.iter().enumerate() {
            let c = w.count_ones();
            if rem < c {
                // Select the rem-th set bit of w.
                let mut w = w;
                for _ in 0..rem {
                    w &= w - 1;
                }
                return (i as u32 * 64 + w.trailing_zeros(), v as u32);
            }
            rem -= c;
        }
        unreachable!("kept index {k} beyond the row's count");
    }

    /// The kept index of pixel (u, v) (the inverse of [`HitMap::locate`]), `None` if it does not
    /// see the mesh or lies outside the image.
    pub fn index_of(&self, u: u32, v: u32) -> Option<usize> {
        if u >= self.width || v >= self.height || !self.get(u, v) {
            return None;
        }
        let row = &self.bits[v as usize * self.words_per_row..];
        let w = u as usize / 64;
        let before: u32 = row[..w].iter().map(|x| x.count_ones()).sum::<u32>()
            + (row[w] & ((1u64 << (u % 64)) - 1)).count_ones();
        Some((self.row_start[v as usize] + before) as usize)
    }

    pub fn bytes(&self) -> usize {
        self.bits.len() * 8 + self.row_start.len() * 4
    }
}

/// A view's photo, stored in the narrowest form that reproduces the loader's `f32` values bit
/// for bit (module docs).
#[derive(Clone, Debug, PartialEq)]
pub enum Targets {
    /// No photo (`init`): targets are zero.
    None,
    /// 8-bit values `k`, read back as `k as f32 / 255.0`.
    U8(Vec<u8>),
    /// 16-bit values `k`, read back as `k as f32 / 65535.0`.
    U16(Vec<u16>),
    /// Anything else, as loaded.
    F32(Vec<f32>),
}

impl Targets {
    /// The narrowest exact store for `img`'s values.
    pub fn from_image(img: &Image) -> Targets {
        fn exact<T: Copy>(data: &[f32], to: impl Fn(f32) -> Option<T>) -> Option<Vec<T>> {
            data.iter().map(|&v| to(v)).collect()
        }
        let u8s = exact(&img.data, |v| {
            let k = (v * 255.0).round();
            ((0.0..=255.0).contains(&k) && (k as u8 as f32 / 255.0).to_bits() == v.to_bits())
                .then_some(k as u8)
        });
        if let Some(d) = u8s {
            return Targets::U8(d);
        }
        let u16s = exact(&img.data, |v| {
            let k = (v * 65535.0).round();
            ((0.0..=65535.0).contains(&k) && (k as u16 as f32 / 65535.0).to_bits() == v.to_bits())
                .then_some(k as u16)
        });
        match u16s {
            Some(d) => Targets::U16(d),
            None => Targets::F32(img.data.clone()),
        }
    }

    /// RGB of the pixel whose first value is at `o` (= 3 · (v·width + u)).
    #[inline]
    pub fn rgb(&self, o: usize) -> [f32; 3] {
        match self {
            Targets::None => [0.0; 3],
            Targets::U8(d) => [d[o], d[o + 1], d[o + 2]].map(|k| k as f32 / 255.0),
            Targets::U16(d) => [d[o], d[o + 1], d[o + 2]].map(|k| k as f32 / 65535.0),
            Targets::F32(d) => [d[o], d[o + 1], d[o + 2]],
        }
    }

    pub fn bytes(&self) -> usize {
        match self {
            Targets::None => 0,
            Targets::U8(d) => d.len(),
            Targets::U16(d) => d.len() * 2,
            Targets::F32(d) => d.len() * 4,
        }
    }
}

/// One kept training view of a [`RayStream`].
#[derive(Clone, Debug)]
pub struct StreamView {
    /// Index of the view in the list given to [`RayStream::build`] (its appearance row).
    pub view: usize,
    pub camera: Camera,
    /// Kept index of this view's first kept pixel.
    pub start: usize,
    /// Smallest footprint (normalised units) over the view's kept pixels (SPEC §8).
    pub footprint_min: f32,
    /// Histogram of the kept pixels' footprints (`raycast/footprint.rs`).
    pub footprints: FootprintHist,
    pub hits: HitMap,
    pub targets: Targets,
}

/// The training views as hit maps and photos; batches are cast when drawn (module docs).
#[derive(Clone, Debug)]
pub struct RayStream {
    pub gamma: u32,
    pub views: Vec<StreamView>,
    /// Input indices of the views that were dropped (no pixel hits the mesh).
    pub dropped: Vec<usize>,
    /// Also give each sub-sample's triangle id and barycentrics (vertex featurization).
    pub keep_triangles: bool,
    total: usize,
}

/// Hit bits and smallest footprint of one strip of a view.
fn strip_hits(
    tracer: &Tracer,
    ctx: &CamCtx,
    cam: &Camera,
    mask: Option<&[bool]>,
    gamma: u32,
    (y0, rows): (u32, u32),
    buf: &mut (super::bvh::Scratch, Vec<SubSample>, Vec<PixelSummary>),
) -> (Vec<u64>, f32, FootprintHist) {
    let (sc, subs, pixels) = buf;
    let g2 = (gamma * gamma) as usize;
    let npix = (rows * cam.width) as usize;
    subs.resize(npix * g2, SubSample::default());
    pixels.resize(npix, PixelSummary::default());
    let mut strip = Strip {
        y0,
        rows,
        subs: &mut subs[..npix * g2],
        pixels: &mut pixels[..npix],
    };
    cast_strip(tracer, ctx, gamma, sc, &mut strip);
    let wpr = (cam.width as usize).div_ceil(64);
    let mut bits = vec![0u64; wpr * rows as usize];
    let mut fmin = f32::INFINITY;
    let mut hist = FootprintHist::default();
    for (k, px) in pixels[..npix].iter().enumerate() {
        let inside = mask.is_none_or(|m| m[y0 as usize * cam.width as usize + k]);
        if px.valid != 0 && inside {
            let (u, r) = (k % cam.width as usize, k / cam.width as usize);
            bits[r * wpr + u / 64] |= 1 << (u % 64);
            fmin = fmin.min(px.footprint as f32);
            // As the cache stores it: the f32 footprint.
            hist.add(px.footprint as f32 as f64);
        }
    }
    (bits, fmin, hist)
}

impl RayStream {
    /// An empty stream for multisampling factor `gamma` (1..=4).
    pub fn new(gamma: u32, keep_triangles: bool) -> Result<RayStream> {
        check_gamma(gamma)?;
        Ok(RayStream {
            gamma,
            views: Vec::new(),
            dropped: Vec::new(),
            keep_triangles,
            total: 0,
        })
    }

    /// Cast every view once for its hit map (see [`RayStream::add_view`]).
    pub fn build(
        tracer: &Tracer,
        views: &[(&Camera, Option<&Image>)],
        gamma: u32,
        keep_triangles: bool,
        on_event: &mut dyn FnMut(CacheEvent),
    ) -> Result<RayStream> {
        let mut s = RayStream::new(gamma, keep_triangles)?;
        super::cache::cast_all(views, |i, cam, img| {
            let targets = img.map_or(Targets::None, Targets::from_image);
            s.add_view(tracer, i, cam, targets, None, on_event)
        })?;
        Ok(s)
    }

    /// Cast one view for its hit map and keep it with its photo (so a caller can load one image
    /// at a time). `view` is the index stored with its pixels; with an object `mask` (`[h*w]`),
    /// only pixels inside it are kept, as in the cache. Returns the number of kept pixels; a view
    /// with none is recorded in [`RayStream::dropped`].
    pub fn add_view(
        &mut self,
        tracer: &Tracer,
        view: usize,
        cam: &Camera,
        targets: Targets,
        mask: Option<&[bool]>,
        on_event: &mut dyn FnMut(CacheEvent),
    ) -> Result<usize> {
        super::cache::check_mask(view, cam, mask)?;
        let want = 3 * cam.width as usize * cam.height as usize;
        let have = match &targets {
            Targets::None => want,
            Targets::U8(d) => d.len(),
            Targets::U16(d) => d.len(),
            Targets::F32(d) => d.len(),
        };
        if have != want {
            bail!(
                "view {view}: image has {have} values, expected 3×{}×{}",
                cam.width,
                cam.height
            );
        }
        let ctx = CamCtx::new(tracer, cam);
        let parts: Vec<(Vec<u64>, f32, FootprintHist)> = strips(cam.height)
            .into_par_iter()
            .map_init(
                || (tracer.scratch(), Vec::new(), Vec::new()),
                |buf, strip| strip_hits(tracer, &ctx, cam, mask, self.gamma, strip, buf),
            )
            .collect();
        let footprint_min = parts.iter().map(|p| p.1).fold(f32::INFINITY, f32::min);
        let mut footprints = FootprintHist::default();
        for p in &parts {
            footprints.merge(&p.2);
        }
        let bits: Vec<u64> = parts.into_iter().flat_map(|p| p.0).collect();
        let hits = HitMap::from_bits(cam.width, cam.height, bits);
        let len = hits.len();
        on_event(CacheEvent::ViewCast {
            view,
            kept: len,
            pixels: (cam.width * cam.height) as usize,
        });
        if len == 0 {
            self.dropped.push(view);
            on_event(CacheEvent::ViewDropped { view });
            return Ok(0);
        }
        self.views.push(StreamView {
            view,
            camera: cam.clone(),
            start: self.total,
            footprint_min,
            footprints,
            hits,
            targets,
        });
        self.total += len;
        Ok(len)
    }

    /// Number of kept pixels over all views.
    pub fn len(&self) -> usize {
        self.total
    }
    pub fn is_empty(&self) -> bool {
        self.total == 0
    }
    /// Sub-sample slots per pixel (γ²).
    pub fn samples_per_pixel(&self) -> usize {
        (self.gamma * self.gamma) as usize
    }
    /// Smallest footprint over all kept views (SPEC §8), `None` if nothing is kept.
    pub fn footprint_min(&self) -> Option<f32> {
        self.views.iter().map(|v| v.footprint_min).reduce(f32::min)
    }
    /// Bytes held (hit maps, photos, cameras).
    pub fn bytes(&self) -> usize {
        self.views
            .iter()
            .map(|v| v.hits.bytes() + v.targets.bytes() + std::mem::size_of::<StreamView>())
            .sum()
    }

    /// (slot in `views`, u, v) of kept pixel `i` (`i < len()`).
    pub fn locate(&self, i: usize) -> (usize, u32, u32) {
        let slot = self.views.partition_point(|v| v.start <= i) - 1;
        let v = &self.views[slot];
        let (x, y) = v.hits.locate(i - v.start);
        (slot, x, y)
    }

    /// Cast the kept pixels `pixels` into a batch (module docs): row `k` is pixel `pixels[k]`,
    /// its appearance row the view's input index.
    pub fn batch(&self, tracer: &Tracer, pixels: &[usize]) -> Batch {
        let s = self.samples_per_pixel();
        let n = pixels.len();
        let ctxs: Vec<CamCtx> = self
            .views
            .iter()
            .map(|v| CamCtx::new(tracer, &v.camera))
            .collect();
        // Cast in (view, row, column) order, so consecutive packets walk the same parts of the
        // BVH (a pixel's result does not depend on when it is cast); rows are then filled in
        // batch order.
        let mut order: Vec<(usize, u32, u32, usize)> = pixels
            .iter()
            .enumerate()
            .map(|(k, &i)| {
                let (slot, u, v) = self.locate(i);
                (slot, v, u, k)
            })
            .collect();
        order.sort_unstable();
        let keep = self.keep_triangles;
        // Each pixel's γ² sub-samples and summary, in cast order (chunks of BATCH_CHUNK pixels
        // written in place: no per-pixel arrays of the largest γ).
        let mut subs_all = vec![SubSample::default(); n * s];
        let mut sums = vec![PixelSummary::default(); n];
        subs_all
            .par_chunks_mut(BATCH_CHUNK * s)
            .zip(sums.par_chunks_mut(BATCH_CHUNK))
            .zip(order.par_chunks(BATCH_CHUNK))
            .for_each_init(
                || tracer.scratch(),
                |sc, ((sub, sum), chunk)| {
                    for (j, &(slot, v, u, _)) in chunk.iter().enumerate() {
                        sum[j] = cast_pixel(
                            tracer,
                            &ctxs[slot],
                            self.gamma,
                            u,
                            v,
                            sc,
                            &mut sub[j * s..(j + 1) * s],
                        );
                    }
                },
            );
        let mut b = Batch::zeros(n, s, keep);
        for (i, (&(slot, v, u, k), sum)) in order.iter().zip(&sums).enumerate() {
            let subs = &subs_all[i * s..(i + 1) * s];
            let sv = &self.views[slot];
            for (j, ss) in subs[..s].iter().enumerate() {
                let hit = ss.hit();
                let r = k * s + j;
                // The cache's 32-bit fixed point (cache.rs), decoded exactly.
                if hit {
                    b.positions[r] = ss
                        .position
                        .to_array()
                        .map(|x| decode_coord(encode_coord(x)));
                }
                b.valid[r] = hit as u8;
                if keep {
                    b.triangle[r] = ss.triangle;
                    if hit {
                        b.bary[r] = [ss.u, ss.v].map(|x| decode_coord(encode_coord(x)));
                    }
                }
            }
            debug_assert!(sum.valid != 0, "a kept pixel sees the mesh");
            b.dirs[k] = sum.dir.as_vec3().to_array();
            b.footprint[k] = sum.footprint as f32;
            b.view[k] = sv.view as i32;
            let o = 3 * (v as usize * sv.camera.width as usize + u as usize);
            b.target[k] = sv.targets.rgb(o);
        }
        b
    }
}
