//! The sample cache (SPEC §1, §8): every training view is cast once; what training needs of each
//! pixel that sees the mesh is kept in compact structure-of-arrays form.
//!
//! ## What is kept
//! - Pixels whose γ² rays all miss are not stored; views with no kept pixel are dropped and
//!   reported in [`SampleCache::dropped`] (and through the event callback — the library never
//!   prints).
//! - Kept pixels are stored view by view in input order, row-major inside a view.
//!
//! ## Position encoding: 32-bit fixed point
//! A normalised position `x_n ∈ [0,1]³` is stored per axis as `q = round(x_n · 2³²)` in a u32
//! (clamped to `0 ..= 2³²-1`; hits lie inside the bounding box, which maps strictly inside
//! `[0,1]` because the extent carries +1e-6). Decoding `q · 2⁻³²` is exact in f64. The error is
//! ≤ 2⁻³³ ≈ 1.2e-10 of the extent everywhere — uniform over the scene, so a 10 km scene keeps
//! ~1.2 mm absolute at any level, well inside the ≤1e-9 relative budget (a level-2048 cell is
//! 4.9e-4). Invalid sub-samples hold 0.
//!
//! ## Bytes per kept pixel
//! 12 per sub-sample slot (3 × u32, γ² slots: invalid slots are stored too, so a pixel's
//! sub-samples are at a fixed stride) + 2 valid mask (u16) + 12 view direction (f32×3) + 4
//! footprint (f32) + 8 pixel (u, v) (u32×2) + 4 view index (u32) + 12 target RGB (f32×3)
//! = 12γ² + 42 bytes: 54 (γ=1), 90 (γ=2), 234 (γ=4).
//!
//! ## Optional: triangle ids and barycentrics
//! Only when asked for (`keep_triangles`, for the vertex-feature
//! featurization): per sub-sample slot the triangle id (u32, `MISS` for an invalid slot) and
//! the barycentrics `(u, v)` of vertices 1 and 2 in the same 32-bit fixed point as positions
//! (error ≤ 2⁻³³, decoded exactly to f64): 12 more bytes per slot (γ=2: 138 bytes per pixel).

use super::advise_huge_pages;
use super::bvh::Tracer;
use super::cast::{cast_strip, check_gamma, strips, CamCtx, PixelSummary, Strip, SubSample};
use crate::scene::{Camera, Image};
use anyhow::{bail, Result};
use rayon::prelude::*;

/// One kept view's slice of the cache.
#[derive(Clone, Debug, PartialEq)]
pub struct CachedView {
    /// Index of the view in the list given to [`SampleCache::build`].
    pub view: usize,
    pub width: u32,
    pub height: u32,
    /// Range of this view's pixels in the cache arrays.
    pub start: usize,
    pub len: usize,
    /// Smallest footprint (normalised units) over the view's kept pixels (SPEC §8).
    pub footprint_min: f32,
    /// Histogram of the kept pixels' footprints (`raycast/footprint.rs`).
    pub footprints: super::footprint::FootprintHist,
    /// Whether a target image was given (else targets are 0).
    pub has_target: bool,
}

/// Progress / warning events of [`SampleCache::build`], in view order.
#[derive(Clone, Debug, PartialEq)]
pub enum CacheEvent {
    /// A view was cast: `kept` of `pixels` pixels see the mesh.
    ViewCast {
        view: usize,
        kept: usize,
        pixels: usize,
    },
    /// A view sees nothing and is dropped.
    ViewDropped { view: usize },
}

/// The compacted samples of all views (module docs).
#[derive(Clone, Debug, PartialEq)]
pub struct SampleCache {
    pub gamma: u32,
    pub views: Vec<CachedView>,
    /// Input indices of the views that were dropped (no pixel hits the mesh).
    pub dropped: Vec<usize>,
    /// `[pixels][γ²][3]` fixed-point normalised positions.
    positions: Vec<[u32; 3]>,
    /// `[pixels]` valid mask, bit j = sub-sample j.
    valid: Vec<u16>,
    /// `[pixels][3]` unit view direction.
    dirs: Vec<[f32; 3]>,
    /// `[pixels]` footprint, normalised units.
    footprint: Vec<f32>,
    /// `[pixels]` (u, v).
    pixel: Vec<[u32; 2]>,
    /// `[pixels]` input view index.
    view: Vec<u32>,
    /// `[pixels][3]` target RGB.
    target: Vec<[f32; 3]>,
    /// Keep triangle ids and barycentrics (module docs).
    keep_triangles: bool,
    /// `[pixels][γ²]` triangle id per slot (empty unless `keep_triangles`).
    triangles: Vec<u32>,
    /// `[pixels][γ²]` fixed-point barycentrics (u, v) (empty unless `keep_triangles`).
    bary: Vec<[u32; 2]>,
}

const SCALE: f64 = 4294967296.0; // 2^32

/// Encode a normalised coordinate as 32-bit fixed point (module docs).
#[inline]
#[allow(clippy::neg_cmp_op_on_partial_ord)] // `!(y > 0)` also takes NaN, on purpose
pub fn encode_coord(x: f64) -> u32 {
    // `(x·2³²).round().clamp(0, 2³²-1) as u32` bit for bit, without the libm `round` call (x86-64
    // has no half-away-from-zero rounding instruction): NaN and y ≤ 0 give 0, and below 2³² the
    // truncation is exact, as is the fraction `y - trunc(y)`.
    let y = x * SCALE;
    if !(y > 0.0) {
        return 0;
    }
    if y >= u32::MAX as f64 {
        return u32::MAX;
    }
    let t = y as u32;
    t + (y - t as f64 >= 0.5) as u32
}

/// Decode a fixed-point coordinate (exact in f64).
#[inline]
pub fn decode_coord(q: u32) -> f64 {
    q as f64 / SCALE
}

/// Every image of `views` checked against its camera first (a bad one costs no cast), then
/// every view cast by `add(i, camera, image)` in order: the whole-list builders of the cache and
/// the stream.
pub(crate) fn cast_all(
    views: &[(&Camera, Option<&Image>)],
    mut add: impl FnMut(usize, &Camera, Option<&Image>) -> Result<usize>,
) -> Result<()> {
    for (i, (cam, img)) in views.iter().enumerate() {
        check_image(i, cam, *img)?;
    }
    for (i, (cam, img)) in views.iter().enumerate() {
        add(i, cam, *img)?;
    }
    Ok(())
}

/// An image must have the camera's size and three values per pixel.
pub(crate) fn check_image(i: usize, cam: &Camera, img: Option<&Image>) -> Result<()> {
    if let Some(img) = img {
        if img.width != cam.width || img.height != cam.height {
            bail!(
                "view {i}: image is {}×{} but the camera is {}×{}",
                img.width,
                img.height,
                cam.width,
                cam.height
            );
        }
        if img.data.len() != 3 * img.width as usize * img.height as usize {
            bail!(
                "view {i}: image data has {} values, expected 3×{}×{}",
                img.data.len(),
                img.width,
                img.height
            );
        }
    }
    Ok(())
}

/// A mask must have one value per pixel of the camera.
pub(crate) fn check_mask(i: usize, cam: &Camera, mask: Option<&[bool]>) -> Result<()> {
    if let Some(m) = mask {
        let want = cam.width as usize * cam.height as usize;
        if m.len() != want {
            bail!(
                "view {i}: mask has {} values, expected {}×{}",
                m.len(),
                cam.width,
                cam.height
            );
        }
    }
    Ok(())
}

/// Keep the pixels of a cast strip of view `cam` that see the mesh (and lie inside the mask, if
/// any), with their targets from `img`.
fn compact(
    cam: &Camera,
    img: Option<&Image>,
    mask: Option<&[bool]>,
    strip: &Strip,
    keep_triangles: bool,
) -> Part {
    let (y0, subs, pixels) = (strip.y0, &*strip.subs, &*strip.pixels);
    let g2 = subs.len() / pixels.len().max(1);
    let inside = |k: usize| mask.is_none_or(|m| m[y0 as usize * cam.width as usize + k]);
    let kept = (0..pixels.len())
        .filter(|&k| pixels[k].valid != 0 && inside(k))
        .count();
    let mut p = Part::with_capacity(kept, g2, keep_triangles);
    for (k, px) in pixels.iter().enumerate() {
        if px.valid == 0 || !inside(k) {
            continue;
        }
        let (u, v) = (k as u32 % cam.width, y0 + k as u32 / cam.width);
        for ss in &subs[k * g2..(k + 1) * g2] {
            p.positions.push(if ss.hit() {
                ss.position.to_array().map(encode_coord)
            } else {
                [0; 3]
            });
            if keep_triangles {
                p.triangles.push(ss.triangle);
                p.bary.push(if ss.hit() {
                    [encode_coord(ss.u), encode_coord(ss.v)]
                } else {
                    [0; 2]
                });
            }
        }
        p.valid.push(px.valid);
        p.dirs.push(px.dir.as_vec3().to_array());
        p.footprint.push(px.footprint as f32);
        p.pixel.push([u, v]);
        p.target.push(match img {
            Some(im) => {
                let o = 3 * (v as usize * im.width as usize + u as usize);
                [im.data[o], im.data[o + 1], im.data[o + 2]]
            }
            None => [0.0; 3],
        });
    }
    p
}

/// Per-strip compacted output.
#[derive(Default)]
struct Part {
    positions: Vec<[u32; 3]>,
    valid: Vec<u16>,
    dirs: Vec<[f32; 3]>,
    footprint: Vec<f32>,
    pixel: Vec<[u32; 2]>,
    target: Vec<[f32; 3]>,
    triangles: Vec<u32>,
    bary: Vec<[u32; 2]>,
}

/// Append every part's `field` to `dst`, in part order, copying the parts in parallel (each into
/// its own range of `dst`'s spare capacity, so the result does not depend on the threads).
fn append_parts<T: Copy + Send + Sync>(
    dst: &mut Vec<T>,
    parts: &[Part],
    field: impl Fn(&Part) -> &[T] + Sync,
) {
    let total: usize = parts.iter().map(|p| field(p).len()).sum();
    dst.reserve(total);
    advise_huge_pages(dst);
    let mut spare = &mut dst.spare_capacity_mut()[..total];
    let mut slots = Vec::with_capacity(parts.len());
    for p in parts {
        let (a, b) = std::mem::take(&mut spare).split_at_mut(field(p).len());
        slots.push(a);
        spare = b;
    }
    slots
        .into_par_iter()
        .zip(parts.par_iter())
        .for_each(|(out, p)| {
            for (o, x) in out.iter_mut().zip(field(p)) {
                o.write(*x);
            }
        });
    // SAFETY: the `total` elements after the current length were all written above (the slots
    // tile `spare_capacity_mut()[..total]` and each is filled from a part of the same length).
    unsafe { dst.set_len(dst.len() + total) };
}

impl Part {
    fn with_capacity(pixels: usize, g2: usize, keep_triangles: bool) -> Part {
        let slots = if keep_triangles { pixels * g2 } else { 0 };
        Part {
            positions: Vec::with_capacity(pixels * g2),
            valid: Vec::with_capacity(pixels),
            dirs: Vec::with_capacity(pixels),
            footprint: Vec::with_capacity(pixels),
            pixel: Vec::with_capacity(pixels),
            target: Vec::with_capacity(pixels),
            triangles: Vec::with_capacity(slots),
            bary: Vec::with_capacity(slots),
        }
    }
}

impl SampleCache {
    /// An empty cache for multisampling factor `gamma` (1..=4), keeping each sub-sample's
    /// triangle id and barycentrics with `keep_triangles`.
    pub fn new(gamma: u32, keep_triangles: bool) -> Result<SampleCache> {
        check_gamma(gamma)?;
        Ok(SampleCache {
            gamma,
            views: Vec::new(),
            dropped: Vec::new(),
            positions: Vec::new(),
            valid: Vec::new(),
            dirs: Vec::new(),
            footprint: Vec::new(),
            pixel: Vec::new(),
            view: Vec::new(),
            target: Vec::new(),
            keep_triangles,
            triangles: Vec::new(),
            bary: Vec::new(),
        })
    }

    /// Cast every view and keep the pixels that see the mesh. `views[i]` is a camera and,
    /// optionally, its image (same size as the camera); `i` is the view index stored in the
    /// cache. With `keep_triangles`, each sub-sample's triangle id and barycentrics are kept too
    /// (module docs; the vertex-feature featurization). `on_event` receives the events of each
    /// view, in order. Views are cast one after another, each in parallel over constant-size
    /// strips, so the cache is bit-identical for any thread count.
    pub fn build(
        tracer: &Tracer,
        views: &[(&Camera, Option<&Image>)],
        gamma: u32,
        keep_triangles: bool,
        on_event: &mut dyn FnMut(CacheEvent),
    ) -> Result<SampleCache> {
        let mut c = SampleCache::new(gamma, keep_triangles)?;
        cast_all(views, |i, cam, img| {
            c.add_view(tracer, i, cam, img, None, on_event)
        })?;
        Ok(c)
    }

    /// Cast one view and append its kept pixels (so a caller can load one image at a time).
    /// `view` is the index stored with its pixels (e.g. the scene's view index); with an object
    /// `mask` (`[h*w]`), only pixels inside it are kept. Returns the number of kept pixels; a
    /// view with none is recorded in [`SampleCache::dropped`].
    pub fn add_view(
        &mut self,
        tracer: &Tracer,
        view: usize,
        cam: &Camera,
        img: Option<&Image>,
        mask: Option<&[bool]>,
        on_event: &mut dyn FnMut(CacheEvent),
    ) -> Result<usize> {
        check_image(view, cam, img)?;
        check_mask(view, cam, mask)?;
        let (gamma, g2) = (self.gamma, self.samples_per_pixel());
        let keep = self.keep_triangles;
        let ctx = CamCtx::new(tracer, cam);
        let parts: Vec<Part> = strips(cam.height)
            .into_par_iter()
            .map_init(
                || (tracer.scratch(), Vec::new(), Vec::new()),
                |(sc, subs, pixels), (y0, rows)| {
                    let npix = (rows * cam.width) as usize;
                    subs.resize(npix * g2, SubSample::default());
                    pixels.resize(npix, PixelSummary::default());
                    let mut strip = Strip {
                        y0,
                        rows,
                        subs: &mut subs[..npix * g2],
                        pixels: &mut pixels[..npix],
                    };
                    cast_strip(tracer, &ctx, gamma, sc, &mut strip);
                    compact(cam, img, mask, &strip, keep)
                },
            )
            .collect();
        let start = self.valid.len();
        append_parts(&mut self.positions, &parts, |p| &p.positions);
        append_parts(&mut self.valid, &parts, |p| &p.valid);
        append_parts(&mut self.dirs, &parts, |p| &p.dirs);
        append_parts(&mut self.footprint, &parts, |p| &p.footprint);
        append_parts(&mut self.pixel, &parts, |p| &p.pixel);
        append_parts(&mut self.target, &parts, |p| &p.target);
        append_parts(&mut self.triangles, &parts, |p| &p.triangles);
        append_parts(&mut self.bary, &parts, |p| &p.bary);
        let len = self.valid.len() - start;
        self.view.resize(self.valid.len(), view as u32);
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
        let footprint_min = self.footprint[start..]
            .iter()
            .copied()
            .fold(f32::INFINITY, f32::min);
        let mut footprints = super::footprint::FootprintHist::default();
        for &f in &self.footprint[start..] {
            footprints.add(f as f64);
        }
        self.views.push(CachedView {
            view,
            width: cam.width,
            height: cam.height,
            start,
            len,
            footprint_min,
            footprints,
            has_target: img.is_some(),
        });
        Ok(len)
    }

    /// Number of kept pixels.
    pub fn len(&self) -> usize {
        self.valid.len()
    }
    pub fn is_empty(&self) -> bool {
        self.valid.is_empty()
    }
    /// Sub-sample slots per pixel (γ²).
    pub fn samples_per_pixel(&self) -> usize {
        (self.gamma * self.gamma) as usize
    }
    /// Normalised position of sub-sample `j` of kept pixel `i` (zero if invalid).
    #[inline]
    pub fn position(&self, i: usize, j: usize) -> [f64; 3] {
        self.positions[i * self.samples_per_pixel() + j].map(decode_coord)
    }
    /// All γ² positions of kept pixel `i` into `out` (length γ²).
    pub fn positions_into(&self, i: usize, out: &mut [[f64; 3]]) {
        let g2 = self.samples_per_pixel();
        for (o, q) in out.iter_mut().zip(&self.positions[i * g2..(i + 1) * g2]) {
            *o = q.map(decode_coord);
        }
    }
    /// The raw fixed-point positions `[pixels][γ²]`.
    pub fn positions_fixed(&self) -> &[[u32; 3]] {
        &self.positions
    }
    /// Start loading the lines that the accessors of kept pixel `i` read (no effect on results;
    /// a batch gathers random pixels, so each of its reads is a cache miss otherwise).
    #[inline]
    pub fn prefetch(&self, i: usize) {
        use crate::memhint::prefetch;
        let g2 = self.samples_per_pixel();
        let pos = self.positions.as_ptr().wrapping_add(i * g2);
        prefetch(pos);
        prefetch((pos.wrapping_add(g2) as *const u8).wrapping_sub(1));
        prefetch(self.valid.as_ptr().wrapping_add(i));
        prefetch(self.dirs.as_ptr().wrapping_add(i));
        prefetch(self.view.as_ptr().wrapping_add(i));
        prefetch(self.target.as_ptr().wrapping_add(i));
        prefetch(self.footprint.as_ptr().wrapping_add(i));
    }
    #[inline]
    pub fn valid(&self, i: usize) -> u16 {
        self.valid[i]
    }
    #[inline]
    pub fn dir(&self, i: usize) -> [f32; 3] {
        self.dirs[i]
    }
    #[inline]
    pub fn footprint(&self, i: usize) -> f32 {
        self.footprint[i]
    }
    /// Pixel (u, v) of kept pixel `i`.
    #[inline]
    pub fn pixel(&self, i: usize) -> [u32; 2] {
        self.pixel[i]
    }
    /// Input view index of kept pixel `i`.
    #[inline]
    pub fn view_index(&self, i: usize) -> usize {
        self.view[i] as usize
    }
    #[inline]
    pub fn target(&self, i: usize) -> [f32; 3] {
        self.target[i]
    }
    /// Smallest footprint over all kept views (SPEC §8), `None` if the cache is empty.
    pub fn footprint_min(&self) -> Option<f32> {
        self.views.iter().map(|v| v.footprint_min).reduce(f32::min)
    }
    /// Whether triangle ids and barycentrics are kept (`keep_triangles` of [`SampleCache::new`]).
    pub fn has_triangles(&self) -> bool {
        self.keep_triangles
    }
    /// Triangle id and barycentrics `(u, v)` (decoded exactly to f64) of sub-sample `j` of kept
    /// pixel `i`: `(MISS, [0, 0])` for an invalid slot. Panics if the cache does not keep them.
    #[inline]
    pub fn surface_id(&self, i: usize, j: usize) -> (u32, [f64; 2]) {
        assert!(
            self.keep_triangles,
            "the sample cache keeps no triangle ids"
        );
        let k = i * self.samples_per_pixel() + j;
        (self.triangles[k], self.bary[k].map(decode_coord))
    }
    /// Bytes held by the per-pixel arrays.
    pub fn bytes(&self) -> usize {
        self.positions.len() * 12
            + self.len() * (2 + 12 + 4 + 8 + 4 + 12)
            + self.triangles.len() * 4
            + self.bary.len() * 8
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The branchy `encode_coord` equals the plain formula on ties, edges and random values.
    #[test]
    fn encode_coord_matches_round_clamp() {
        let plain = |x: f64| (x * SCALE).round().clamp(0.0, u32::MAX as f64) as u32;
        let mut xs = vec![
            0.0,
            -0.0,
            -1e-300,
            -0.3 / SCALE,
            -0.5 / SCALE,
            -0.7 / SCALE,
            0.49999999999999994 / SCALE,
            0.5 / SCALE,
            1.5 / SCALE,
            2.5 / SCALE,
            (u32::MAX as f64 - 0.5) / SCALE,
            (u32::MAX as f64 - 0.25) / SCALE,
            (u32::MAX as f64 - 0.75) / SCALE,
            1.0,
            1.0 + 1e-12,
            2.0,
            f64::INFINITY,
            f64::NEG_INFINITY,
            f64::NAN,
        ];
        let mut s = 0x9e3779b97f4a7c15u64;
        for _ in 0..200_000 {
            s = s
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            let u = (s >> 11) as f64 / (1u64 << 53) as f64;
            xs.push(u * 1.2 - 0.1);
            // Exact ties k + 0.5 at random k.
            xs.push(((s >> 32) as f64 + 0.5) / SCALE);
        }
        let bad: Vec<_> = xs
            .iter()
            .filter(|&&x| encode_coord(x) != plain(x))
            .map(|&x| (x, encode_coord(x), plain(x)))
            .take(5)
            .collect();
        assert!(bad.is_empty(), "encode_coord differs: {bad:?}");
    }
}
