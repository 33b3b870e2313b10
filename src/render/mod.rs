//! Rendering (SPEC §1 last stage): cast γ×γ rays for any camera in bands of rows, evaluate the
//! model on the pixels that hit the mesh, paint misses in a background colour (white in the
//! official protocol; the scene's `background`), plus camera paths between two views and the
//! hit-mask / footprint / side-by-side images.

pub mod appearance;
pub mod ulr;

pub use appearance::Appearance;

use crate::model::hfm::{Hfm, Pixels};
use crate::raycast::{cast_rows_into, Tracer, ViewCast};
use crate::scene::{Camera, Image};
use anyhow::Result;
use glam::{DMat3, DQuat, DVec3};

/// Pixels per forward call while rendering (bounds memory; results do not depend on it because
/// every pixel's colour is computed independently).
pub const RENDER_CHUNK: usize = 8192;

/// Sub-samples cast per band of rows while rendering: a frame is cast and shaded one band of
/// rows at a time, so a frame of any size holds at most ~11.5 MB of sub-samples (88 bytes each),
/// which stay in the last-level cache between the cast and the shading. Results do not depend
/// on it (every pixel is independent). 2¹⁷ rather than 2²⁰ (2026-11-27, the 1.08-MP render of
/// docs/performance.md, alternating A/B runs of the whole command, twice): faster in wall and
/// CPU time, a lower peak, the same PNG bytes; 2¹⁵ was no faster than 2¹⁷ (docs/changelog.md).
pub const RENDER_BAND_SAMPLES: usize = 1 << 17;

/// White: the official protocol's colour for pixels whose rays all miss.
pub const WHITE: [f32; 3] = [1.0; 3];

/// A rendered view.
#[derive(Clone, Debug)]
pub struct Rendered {
    /// RGB in `[0,1]`; pixels whose rays all miss have the background colour.
    pub image: Image,
    /// `[h*w]` at least one sub-sample hit the mesh.
    pub hit: Vec<bool>,
    /// `[h*w]` pixel footprint on the surface (normalised units), 0 for misses.
    pub footprint: Vec<f32>,
}

/// Rows per band holding at most `band_samples` sub-samples (at least one row).
fn band_rows_for(width: u32, gamma: u32, band_samples: usize) -> u32 {
    let per_row = (width as usize * (gamma * gamma) as usize).max(1);
    (band_samples / per_row).clamp(1, u32::MAX as usize) as u32
}

/// A model rendered on a mesh: the model and its parameters, the BVH its rays are cast against
/// (and its features queried on), γ×γ rays per pixel, and the colour of pixels whose rays all
/// miss. What changes from frame to frame is the camera and the view's appearance row.
#[derive(Clone, Copy)]
pub struct ModelRenderer<'a> {
    pub model: &'a Hfm,
    pub params: &'a [f32],
    pub tracer: &'a Tracer,
    pub gamma: u32,
    pub background: [f32; 3],
}

impl ModelRenderer<'_> {
    /// Render `camera` in `appearance` (a row, −1 for the mean code, or a code of its own:
    /// `render::appearance`); pixels whose rays all miss get the background. Cast and shaded in
    /// bands of rows ([`RENDER_BAND_SAMPLES`]).
    pub fn render(&self, camera: &Camera, appearance: &Appearance) -> Result<Rendered> {
        self.render_in_bands(camera, appearance, RENDER_BAND_SAMPLES)
    }

    /// [`ModelRenderer::render`] with bands of at most `band_samples` sub-samples (at least one
    /// row each; `usize::MAX`: the whole frame at once). The frame does not depend on it
    /// (tests/render.rs).
    pub fn render_in_bands(
        &self,
        camera: &Camera,
        appearance: &Appearance,
        band_samples: usize,
    ) -> Result<Rendered> {
        let (model, params, gamma) = (self.model, self.params, self.gamma);
        let (view_row, code) = appearance.row_and_code();
        let bufs = crate::model::hfm::InferBuffers::new();
        // Once per frame: the MLPs' transposed weights and the code of view −1.
        let shared = model.infer_shared(params, code)?;
        let mut px = CastPixels::default();
        let mut rgb = Vec::new();
        render_in_bands(
            self.tracer,
            camera,
            gamma,
            self.background,
            band_samples,
            |cast, _, colours| {
                let hits = tile_order_hits(cast);
                for chunk in hits.chunks(RENDER_CHUNK) {
                    px.fill(model, cast, chunk, view_row);
                    rgb.resize(chunk.len() * 3, 0.0);
                    model.infer_pixels(params, &px.pixels(), &shared, &bufs, &mut rgb)?;
                    for (&i, c) in chunk.iter().zip(rgb.chunks_exact(3)) {
                        colours[i * 3..i * 3 + 3].copy_from_slice(c);
                    }
                }
                Ok(())
            },
        )
    }
}

/// Pixels per side of the square tiles [`tile_order_hits`] visits a band in: a tile's pixels
/// are shaded together, so the table rows a pixel gathers are still cached when the pixels
/// below it gather them (in row order they were evicted by the rest of the row).
pub const RENDER_TILE: usize = 16;

/// The band's pixels whose rays hit the mesh (indices into `cast.pixels`), tile by tile
/// ([`RENDER_TILE`]; tiles in row order, pixels in row order inside a tile). The order changes
/// no colour: every pixel is computed on its own.
fn tile_order_hits(cast: &ViewCast) -> Vec<usize> {
    let w = cast.width as usize;
    let rows = cast.pixels.len() / w.max(1);
    let mut hits = Vec::with_capacity(cast.pixels.len());
    let tile = RENDER_TILE;
    for ty in (0..rows).step_by(tile) {
        for tx in (0..w).step_by(tile) {
            for y in ty..(ty + tile).min(rows) {
                let row = y * w;
                for i in row + tx..row + (tx + tile).min(w) {
                    if cast.pixels[i].valid != 0 {
                        hits.push(i);
                    }
                }
            }
        }
    }
    hits
}

/// The frame loop every renderer shares: cast `camera` with γ×γ rays per pixel in bands of rows
/// (at most `band_samples` sub-samples each, at least one row), take each pixel's hit (any of its
/// rays hits) and footprint from the cast, and let `shade(cast, y0, colours)` write the RGB of
/// the band's pixels into `colours` (`[pixels·3]`, the band's rows of the frame, filled with
/// `background` beforehand; `y0` is the band's first row).
pub fn render_in_bands(
    tracer: &Tracer,
    camera: &Camera,
    gamma: u32,
    background: [f32; 3],
    band_samples: usize,
    mut shade: impl FnMut(&ViewCast, u32, &mut [f32]) -> Result<()>,
) -> Result<Rendered> {
    let (w, h) = (camera.width as usize, camera.height as usize);
    let mut data: Vec<f32> = background.iter().copied().cycle().take(w * h * 3).collect();
    let mut hit = vec![false; w * h];
    let mut footprint = vec![0.0f32; w * h];
    let band = band_rows_for(camera.width, gamma, band_samples);
    let mut cast = ViewCast::default();
    for y0 in (0..camera.height).step_by(band as usize) {
        let rows = band.min(camera.height - y0);
        cast_rows_into(tracer, camera, gamma, y0, rows, &mut cast)?;
        let off = y0 as usize * w;
        for (i, p) in cast.pixels.iter().enumerate() {
            hit[off + i] = p.valid != 0;
            footprint[off + i] = p.footprint as f32;
        }
        let n = cast.pixels.len();
        shade(&cast, y0, &mut data[off * 3..(off + n) * 3])?;
    }
    Ok(Rendered {
        image: Image {
            width: w as u32,
            height: h as u32,
            data,
        },
        hit,
        footprint,
    })
}

/// Pixels per parallel piece of [`CastPixels::fill`].
const FILL_PIECE: usize = 512;

/// What the model reads of a chunk of cast pixels (`Hfm::infer_pixels`), built straight from
/// the cast: each pixel's hit sub-samples in sub-sample order (the points the prologue of the
/// batch `Batch { positions, valid, .. }` would compact, in the same order), its direction,
/// footprint and appearance row. Kept across a frame's chunks, so its vectors are not made
/// again.
#[derive(Default)]
struct CastPixels {
    start: Vec<usize>,
    points: Vec<[f64; 3]>,
    triangles: Vec<u32>,
    bary: Vec<[f64; 2]>,
    dirs: Vec<[f32; 3]>,
    footprint: Vec<f32>,
    view: Vec<i32>,
}

impl CastPixels {
    /// The cast pixels `chunk` (indices into `cast.pixels`), in parallel pieces.
    fn fill(&mut self, model: &Hfm, cast: &ViewCast, chunk: &[usize], view_row: i32) {
        use rayon::prelude::*;
        let s = (cast.gamma * cast.gamma) as usize;
        let subs = |i: usize| &cast.subs[i * s..(i + 1) * s];
        let n = chunk.len();
        self.start.clear();
        self.start.push(0);
        let mut total = 0;
        // A pixel's hit mask (`PixelSummary::valid`, bit j: sub-sample j hit) counts its
        // points without reading its sub-samples on this thread.
        for &i in chunk {
            total += cast.pixels[i].valid.count_ones() as usize;
            self.start.push(total);
        }
        let ids = model.vertex.is_some();
        // Every element is written below: a reused vector is only cut or grown to length.
        self.points.resize(total, [0.0; 3]);
        self.triangles.resize(if ids { total } else { 0 }, 0);
        self.bary.resize(if ids { total } else { 0 }, [0.0; 2]);
        self.dirs.resize(n, [0.0; 3]);
        self.footprint.resize(n, 0.0);
        self.view.clear();
        self.view.resize(n, view_row);
        // Disjoint pieces: FILL_PIECE pixels and their points each.
        let mut pieces = Vec::with_capacity(n.div_ceil(FILL_PIECE));
        let (mut points, mut triangles, mut bary) = (
            &mut self.points[..],
            &mut self.triangles[..],
            &mut self.bary[..],
        );
        for (((k, pix), dirs), footprint) in (chunk.chunks(FILL_PIECE).enumerate())
            .zip(self.dirs.chunks_mut(FILL_PIECE))
            .zip(self.footprint.chunks_mut(FILL_PIECE))
        {
            let a = k * FILL_PIECE;
            let m = self.start[(a + FILL_PIECE).min(n)] - self.start[a];
            let (p, rest) = std::mem::take(&mut points).split_at_mut(m);
            points = rest;
            let (t, b) = if ids {
                let (t, rt) = std::mem::take(&mut triangles).split_at_mut(m);
                let (b, rb) = std::mem::take(&mut bary).split_at_mut(m);
                (triangles, bary) = (rt, rb);
                (t, b)
            } else {
                (&mut [][..], &mut [][..])
            };
            pieces.push((pix, dirs, footprint, p, t, b));
        }
        pieces
            .into_par_iter()
            .for_each(|(pix, dirs, footprint, p, t, b)| {
                let mut k = 0;
                for (j, &i) in pix.iter().enumerate() {
                    let c = &cast.pixels[i];
                    dirs[j] = c.dir.as_vec3().to_array();
                    footprint[j] = c.footprint as f32;
                    for x in subs(i).iter().filter(|x| x.hit()) {
                        p[k] = x.position.to_array();
                        if ids {
                            t[k] = x.triangle;
                            b[k] = [x.u, x.v];
                        }
                        k += 1;
                    }
                }
                assert_eq!(k, p.len(), "the cast's hit masks count its hits");
            });
    }

    fn pixels(&self) -> Pixels<'_> {
        Pixels {
            start: &self.start,
            points: &self.points,
            triangles: &self.triangles,
            bary: &self.bary,
            dirs: &self.dirs,
            footprint: &self.footprint,
            view: &self.view,
            target: &[],
        }
    }
}

/// Camera `i` of `n` on the straight path from `a` to `b` (both ends included): rotation by
/// slerp, centre by lerp, intrinsics interpolated linearly; the image size is `a`'s. Between an
/// aerial view and a close-up its middle frames look past the scene; `render --path` uses
/// [`fly_camera`].
pub fn interpolate_camera(a: &Camera, b: &Camera, i: usize, n: usize) -> Camera {
    let s = if n <= 1 {
        0.0
    } else {
        i as f64 / (n - 1) as f64
    };
    let qa = DQuat::from_mat3(&a.rotation);
    let mut qb = DQuat::from_mat3(&b.rotation);
    if qa.dot(qb) < 0.0 {
        qb = -qb;
    }
    let rot = DMat3::from_quat(qa.slerp(qb, s).normalize());
    let centre = a.center().lerp(b.center(), s);
    let lerp = |x: f64, y: f64| x + (y - x) * s;
    Camera {
        width: a.width,
        height: a.height,
        fx: lerp(a.fx, b.fx),
        fy: lerp(a.fy, b.fy),
        cx: lerp(a.cx, b.cx),
        cy: lerp(a.cy, b.cy),
        distortion: a.distortion,
        rotation: rot,
        translation: -(rot * centre),
    }
}

/// Where a camera looks: the first mesh hit of its optical axis, else the point of the axis
/// closest to the mesh's bounding-box centre (at least a bounding-box diagonal away when that is
/// behind the camera).
pub fn look_at_point(
    tracer: &crate::raycast::Tracer,
    mesh: &crate::scene::Mesh,
    c: &Camera,
) -> DVec3 {
    let o = c.center();
    let axis = (c.rotation.transpose() * DVec3::Z).normalize();
    if let Some(h) = tracer.closest_hit(o, axis) {
        return o + axis * h.t;
    }
    let (lo, hi) = mesh.bbox();
    let t = (0.5 * (lo + hi) - o).dot(axis);
    o + axis * if t > 0.0 { t } else { (hi - lo).length() }
}

/// Camera `i` of `n` on a fly-through from `a` to `b` that keeps the scene in view, where `ta`
/// and `tb` are the points the end cameras look at ([`look_at_point`]): the look-at point moves
/// linearly, the distance to it geometrically (so an aerial-to-close-up path spends its frames
/// evenly across scales instead of rushing through them at the end), the viewing direction turns
/// by slerp, and the orientation is the slerp of the ends' orientations turned so that its optical
/// axis points at the look-at point. Intrinsics are interpolated linearly; the size is `a`'s.
/// At `i = 0` and `i = n − 1` the end cameras are reproduced (to rounding).
pub fn fly_camera(a: &Camera, b: &Camera, ta: DVec3, tb: DVec3, i: usize, n: usize) -> Camera {
    let s = if n <= 1 {
        0.0
    } else {
        i as f64 / (n - 1) as f64
    };
    let (ca, cb) = (a.center(), b.center());
    let (da, db) = (
        (ta - ca).length().max(1e-300),
        (tb - cb).length().max(1e-300),
    );
    let (ua, ub) = ((ta - ca) / da, (tb - cb) / db);
    let target = ta.lerp(tb, s);
    let dist = da.powf(1.0 - s) * db.powf(s);
    let dir = (DQuat::IDENTITY.slerp(DQuat::from_rotation_arc(ua, ub), s) * ua).normalize();
    let centre = target - dir * dist;
    let mut c = interpolate_camera(a, b, i, n);
    // Turn the slerped orientation so its optical axis is `dir` (a world-space rotation).
    let axis = (c.rotation.transpose() * DVec3::Z).normalize();
    let fix = DMat3::from_quat(DQuat::from_rotation_arc(axis, dir));
    let rot = c.rotation * fix.transpose();
    c.rotation = rot;
    c.translation = -(rot * centre);
    c
}

/// A white/black image of the hit mask.
pub fn mask_image(hit: &[bool], w: u32, h: u32) -> Image {
    let data = hit.iter().flat_map(|&m| [m as u8 as f32; 3]).collect();
    Image {
        width: w,
        height: h,
        data,
    }
}

/// The colour of `render --footprint`'s pixels whose rays all miss the mesh: red, off the grey
/// ramp of the hit pixels, so a miss is never taken for the finest footprint (black).
pub const FOOTPRINT_MISS: [f32; 3] = [1.0, 0.0, 0.0];

/// log-scaled footprint (finest black … coarsest white over the range of the image's hit
/// pixels); pixels whose rays all miss (`hit` false) are [`FOOTPRINT_MISS`].
pub fn footprint_image(fp: &[f32], hit: &[bool], w: u32, h: u32) -> Image {
    let logs: Vec<f64> = fp
        .iter()
        .zip(hit)
        .filter(|&(&f, &m)| m && f > 0.0)
        .map(|(&f, _)| (f as f64).ln())
        .collect();
    let lo = logs.iter().cloned().fold(f64::INFINITY, f64::min);
    let hi = logs.iter().cloned().fold(f64::NEG_INFINITY, f64::max);
    let span = (hi - lo).max(1e-12);
    let data = fp
        .iter()
        .zip(hit)
        .flat_map(|(&f, &m)| {
            if !m {
                return FOOTPRINT_MISS;
            }
            let v = if f > 0.0 {
                (((f as f64).ln() - lo) / span) as f32
            } else {
                0.0
            };
            [v, v, v]
        })
        .collect();
    Image {
        width: w,
        height: h,
        data,
    }
}

/// Error heat map: mean absolute error over channels, scaled so 0.25 saturates, black → red →
/// yellow → white.
pub fn heat_map(a: &Image, b: &Image) -> Image {
    let data = a
        .data
        .chunks_exact(3)
        .zip(b.data.chunks_exact(3))
        .flat_map(|(p, q)| {
            let e = ((p[0] - q[0]).abs() + (p[1] - q[1]).abs() + (p[2] - q[2]).abs()) / 3.0;
            let x = (e / 0.25).clamp(0.0, 1.0) * 3.0;
            [
                x.min(1.0),
                (x - 1.0).clamp(0.0, 1.0),
                (x - 2.0).clamp(0.0, 1.0),
            ]
        })
        .collect();
    Image {
        width: a.width,
        height: a.height,
        data,
    }
}

/// A ꟻLIP error map (`[h*w]` values in [0, 1]) in ꟻLIP's magma colour map.
pub fn flip_image(map: &[f32], w: u32, h: u32) -> Image {
    let f = nv_flip::FlipImageFloat::with_data(w, h, map);
    let rgb = f.apply_color_lut(&nv_flip::magma_lut()).to_vec();
    Image {
        width: w,
        height: h,
        data: rgb.iter().map(|&v| v as f32 / 255.0).collect(),
    }
}

/// The colour [`comparison`] outlines the pixels the mesh misses in: cyan, off the heat map's
/// black–red–yellow–white and ꟻLIP's magma.
pub const MISS_OUTLINE: [f32; 3] = [0.0, 1.0, 1.0];

/// The pixels that outline the region the mesh misses: misses within `width` pixels (in x or
/// y) of a hit pixel — the miss side of every silhouette the mesh leaves.
pub fn miss_outline(hit: &[bool], w: u32, h: u32, width: u32) -> Vec<bool> {
    let (w, h, r) = (w as usize, h as usize, width as i64);
    let mut out = vec![false; w * h];
    for y in 0..h {
        for x in 0..w {
            if hit[y * w + x] {
                continue;
            }
            out[y * w + x] = (-r..=r).any(|d| {
                let (xx, yy) = (x as i64 + d, y as i64 + d);
                (d != 0)
                    && ((xx >= 0 && (xx as usize) < w && hit[y * w + xx as usize])
                        || (yy >= 0 && (yy as usize) < h && hit[yy as usize * w + x]))
            });
        }
    }
    out
}

/// The side-by-side of a scored view, as the full-image scores see it: render | photo as it is
/// | |error| heat map | ꟻLIP map, the two error maps over every pixel (a pixel the mesh misses
/// shows the render's background against the photo), and the region the mesh misses outlined
/// in [`MISS_OUTLINE`] on all four (the masked scores leave it out).
pub fn comparison(pred: &Image, photo: &Image, hit: &[bool], flip: &[f32]) -> Image {
    let heat = heat_map(pred, photo);
    let f = flip_image(flip, pred.width, pred.height);
    let outline = miss_outline(hit, pred.width, pred.height, 2);
    let mut panels = [pred.clone(), photo.clone(), heat, f];
    for p in panels.iter_mut() {
        for (px, &o) in p.data.chunks_exact_mut(3).zip(&outline) {
            if o {
                px.copy_from_slice(&MISS_OUTLINE);
            }
        }
    }
    side_by_side(&panels.iter().collect::<Vec<_>>())
}

/// Images of equal height side by side.
pub fn side_by_side(images: &[&Image]) -> Image {
    let h = images[0].height;
    let w: u32 = images.iter().map(|i| i.width).sum();
    let mut data = Vec::with_capacity((w * h * 3) as usize);
    for r in 0..h as usize {
        for img in images {
            let iw = img.width as usize * 3;
            data.extend_from_slice(&img.data[r * iw..(r + 1) * iw]);
        }
    }
    Image {
        width: w,
        height: h,
        data,
    }
}
