//! γ×γ rays per pixel for one camera (SPEC §2): sub-sample positions, the per-pixel view
//! direction and the pixel footprint (SPEC §8).
//!
//! ## Rays
//! Sub-sample `j = b·γ + a` (a = column, b = row inside the pixel, a, b ∈ 0..γ) of pixel (u, v)
//! is the ray through the continuous image point `(u + (a+0.5)/γ, v + (b+0.5)/γ)`, i.e. the points
//! a rasterizer at γW×γH samples; γ = 1 gives the pixel centre. Directions are exactly
//! `Camera::dir_world` (f64, unit, distortion undone), origins the camera centre.
//!
//! ## Work split (determinism, speed)
//! The image is cut into strips of [`STRIP_ROWS`] pixel rows (a constant, never derived from the
//! thread count), cast in parallel with rayon and concatenated in strip order, so the output is
//! bit-identical for any number of threads. Inside a strip the sub-sample grid (γW × γ·rows) is
//! walked in blocks of 16 sub-samples, each traced as one packet: 4×4 when the strip's sub-sample
//! rows allow (γ = 2: 2×2 pixels; γ = 4: one pixel), else 8×2 (γ = 1: 8×2 pixels; γ = 3). The
//! rays of a block are coherent, so one interval box test per node serves all of them. (The
//! packet a ray is traced in does not change its result; see `bvh.rs`.) Normalised image
//! coordinates are computed once per sub-sample column and row, and the hits' f64 vertices are
//! fetched for the whole packet before any refinement, so their cache misses overlap.
//!
//! ## Footprint
//! For a pinhole camera the solid angle of a pixel whose ray makes angle θ_c with the optical
//! axis is `Ω = cos³θ_c / (fx·fy)`; at distance r it covers the area `Ω r² / |cos θ_n|` of a
//! surface whose normal makes angle θ_n with the ray. The footprint stored is the side of the
//! square of that area, `r · sqrt(Ω / |cos θ_n|)` (|cos θ_n| clamped at 1e-6), averaged over the
//! pixel's valid sub-samples, in normalised units: divided by the **largest** axis of the
//! normalisation extent (the smallest normalised size along any axis, so level dropping stays
//! conservative). Lens distortion's local magnification is ignored (a few % for real lenses).

use super::bvh::{Packet, Scratch, Tracer, MAX_LANES};
use crate::scene::Camera;
use anyhow::{bail, Result};
use glam::{DMat3, DVec3};
use rayon::prelude::*;

/// Pixel rows per parallel work item.
pub const STRIP_ROWS: u32 = 2;
/// Largest supported multisampling factor (the valid mask is 16 bits).
pub const MAX_GAMMA: u32 = 4;

/// Triangle id of a missed sub-sample.
pub const MISS: u32 = u32::MAX;

/// One sub-sample ray's result.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct SubSample {
    /// Mesh triangle hit, or [`MISS`].
    pub triangle: u32,
    /// Distance from the camera centre (world units).
    pub t: f64,
    /// Barycentrics of vertices 1 and 2 (f64 refinement).
    pub u: f64,
    pub v: f64,
    /// Hit position in normalised coordinates: `(o_local + t·d) / extent + 0.5` (f64).
    pub position: DVec3,
    /// Unit world direction of the ray.
    pub dir: DVec3,
    /// Footprint of this ray's pixel at its hit (module docs), normalised units; 0 for a miss.
    pub footprint: f64,
}

impl SubSample {
    #[inline]
    pub fn hit(&self) -> bool {
        self.triangle != MISS
    }
}

/// Per-pixel summary.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct PixelSummary {
    /// Bit j set: sub-sample j hit.
    pub valid: u16,
    /// Normalised sum of the valid sub-sample directions (zero if none).
    pub dir: DVec3,
    /// Footprint in normalised units (module docs); 0 if no sub-sample hit.
    pub footprint: f64,
}

/// All sub-samples of one view.
#[derive(Clone, Debug, Default)]
pub struct ViewCast {
    pub width: u32,
    pub height: u32,
    pub gamma: u32,
    /// `[height][width][γ²]`, sub-sample order `b·γ + a`.
    pub subs: Vec<SubSample>,
    /// `[height][width]`.
    pub pixels: Vec<PixelSummary>,
}

impl ViewCast {
    /// The γ² sub-samples of pixel (u, v).
    pub fn pixel_subs(&self, u: u32, v: u32) -> &[SubSample] {
        let g2 = (self.gamma * self.gamma) as usize;
        let i = (v as usize * self.width as usize + u as usize) * g2;
        &self.subs[i..i + g2]
    }
    pub fn pixel(&self, u: u32, v: u32) -> &PixelSummary {
        &self.pixels[v as usize * self.width as usize + u as usize]
    }
}

/// Continuous image offset of sub-sample `j` inside its pixel: `((a+0.5)/γ, (b+0.5)/γ)`.
#[inline]
pub fn sub_offset(gamma: u32, j: u32) -> (f64, f64) {
    let (a, b) = (j % gamma, j / gamma);
    let g = gamma as f64;
    ((a as f64 + 0.5) / g, (b as f64 + 0.5) / g)
}

/// Camera data precomputed once per view.
pub(crate) struct CamCtx<'a> {
    cam: &'a Camera,
    rt: DMat3,
    /// Camera centre in the tracer's local frame (f64) and as f32.
    origin: DVec3,
    origin32: [f32; 3],
    axis: DVec3,
    /// 1 / sqrt(fx·fy).
    inv_sqrt_f: f64,
    inv_extent: DVec3,
    inv_extent_max: f64,
}

impl<'a> CamCtx<'a> {
    pub(crate) fn new(tracer: &Tracer, cam: &'a Camera) -> CamCtx<'a> {
        let n = tracer.normalization();
        let origin = cam.center() - n.center;
        let rt = cam.rotation.transpose();
        CamCtx {
            cam,
            rt,
            origin,
            origin32: origin.as_vec3().to_array(),
            axis: rt.z_axis,
            inv_sqrt_f: 1.0 / (cam.fx * cam.fy).abs().sqrt(),
            inv_extent: n.extent.recip(),
            inv_extent_max: 1.0 / n.extent.max_element(),
        }
    }

    /// Normalised image coordinates `((x - cx)/fx, (y - cy)/fy)`, as `Camera::dir_camera`
    /// computes them (one division per sub-sample column or row, not per ray).
    #[inline]
    fn xn(&self, x: f64) -> f64 {
        (x - self.cam.cx) / self.cam.fx
    }
    #[inline]
    fn yn(&self, y: f64) -> f64 {
        (y - self.cam.cy) / self.cam.fy
    }

    /// Exactly `Camera::dir_world(x, y)` from `xn(x)`, `yn(y)`, with the transpose hoisted.
    #[inline]
    fn dir(&self, xn: f64, yn: f64) -> DVec3 {
        (self.rt * self.cam.distortion.undistort_dir(xn, yn)).normalize()
    }
}

/// Check a multisampling factor.
pub fn check_gamma(gamma: u32) -> Result<()> {
    if !(1..=MAX_GAMMA).contains(&gamma) {
        bail!("multisampling factor γ = {gamma}: expected 1..={MAX_GAMMA}");
    }
    Ok(())
}

/// A strip of pixel rows `y0 .. y0+rows` of a view as cast: each pixel's summary (`pixels`,
/// `[rows][width]`) and its sub-samples (`subs`, `[rows][width][γ²]`).
pub(crate) struct Strip<'a> {
    pub y0: u32,
    pub rows: u32,
    pub subs: &'a mut [SubSample],
    pub pixels: &'a mut [PixelSummary],
}

/// Cast `strip`'s rows with γ×γ rays per pixel; every element of its buffers is overwritten.
pub(crate) fn cast_strip(
    tracer: &Tracer,
    ctx: &CamCtx,
    gamma: u32,
    scratch: &mut Scratch,
    strip: &mut Strip,
) {
    let (y0, rows) = (strip.y0, strip.rows);
    let (subs, pixels) = (&mut *strip.subs, &mut *strip.pixels);
    // γ as a constant, so the sub-sample index arithmetic has no run-time divisions.
    match gamma {
        1 => cast_strip_g::<1>(tracer, ctx, y0, rows, scratch, subs, pixels),
        2 => cast_strip_g::<2>(tracer, ctx, y0, rows, scratch, subs, pixels),
        3 => cast_strip_g::<3>(tracer, ctx, y0, rows, scratch, subs, pixels),
        4 => cast_strip_g::<4>(tracer, ctx, y0, rows, scratch, subs, pixels),
        _ => unreachable!("γ is checked by the callers"),
    }
}

fn cast_strip_g<const G: u32>(
    tracer: &Tracer,
    ctx: &CamCtx,
    y0: u32,
    rows: u32,
    scratch: &mut Scratch,
    subs: &mut [SubSample],
    pixels: &mut [PixelSummary],
) {
    let w = ctx.cam.width;
    let g = G;
    let g2 = (g * g) as usize;
    let npix = (w * rows) as usize;
    assert!(subs.len() == npix * g2 && pixels.len() == npix);
    let (sw, sh) = (w * g, rows * g);
    // Sub-sample (sx, sy) of the strip → index into `subs`; its continuous image point is
    // (x(sx), y(sy)), normalised once per column and row.
    let locate = |sx: u32, sy: u32| {
        let (u, a) = (sx / g, sx % g);
        let (vr, b) = (sy / g, sy % g);
        (vr * w + u) as usize * g2 + (b * g + a) as usize
    };
    let xn: Vec<f64> = (0..sw)
        .map(|sx| ctx.xn((sx / g) as f64 + ((sx % g) as f64 + 0.5) / g as f64))
        .collect();
    let yn: Vec<f64> = (0..sh)
        .map(|sy| ctx.yn((y0 + sy / g) as f64 + ((sy % g) as f64 + 0.5) / g as f64))
        .collect();
    // Blocks of 16 sub-samples, one packet each: 4×4 when the strip's sub-sample rows allow
    // (γ = 2: 2×2 pixels; γ = 4: one pixel), else 8×2.
    let bh: u32 = if sh % 4 == 0 { 4 } else { 2 };
    let bw: u32 = MAX_LANES as u32 / bh;
    for by in (0..sh).step_by(bh as usize) {
        for bx in (0..sw).step_by(bw as usize) {
            let mut p = Packet::default();
            let mut lane_idx = [0usize; MAX_LANES];
            let mut lane_dir = [DVec3::ZERO; MAX_LANES];
            for l in 0..MAX_LANES {
                let (sx, sy) = (bx + l as u32 % bw, by + l as u32 / bw);
                if sx >= sw || sy >= sh {
                    continue;
                }
                let d = ctx.dir(xn[sx as usize], yn[sy as usize]);
                lane_idx[l] = locate(sx, sy);
                lane_dir[l] = d;
                p.set(l, ctx.origin32, d.as_vec3().to_array());
            }
            let out = trace_block(tracer, ctx, &p, &lane_dir, scratch);
            for l in 0..MAX_LANES {
                if p.active >> l & 1 != 0 {
                    // Every sub-sample of the strip is in exactly one block: all are written here.
                    subs[lane_idx[l]] = out[l];
                }
            }
        }
    }
    for (px, out) in subs.chunks_exact(g2).zip(pixels.iter_mut()) {
        *out = summarize(px);
    }
}

/// Trace one packet of sub-sample rays from the camera centre (lane `l` has direction
/// `lane_dir[l]`; only the packet's active lanes are meaningful in the result) and refine the
/// hits in f64. A ray's result does not depend on the packet it is traced in (see `bvh.rs`), so
/// the strip cast and the per-pixel cast of the ray stream give the same bits.
#[inline]
fn trace_block(
    tracer: &Tracer,
    ctx: &CamCtx,
    p: &Packet,
    lane_dir: &[DVec3; MAX_LANES],
    scratch: &mut Scratch,
) -> [SubSample; MAX_LANES] {
    let hits = tracer.trace_leaves(p, scratch);
    // The hit triangles' f64 vertices first: independent loads, so their cache misses
    // overlap instead of stalling each refinement in turn.
    let mut verts = [[DVec3::ZERO; 3]; MAX_LANES];
    for (v, h) in verts.iter_mut().zip(&hits) {
        if let Some((j, _)) = h {
            *v = tracer.leaf_local(*j);
        }
    }
    let mut out = [SubSample::default(); MAX_LANES];
    for l in 0..MAX_LANES {
        if p.active >> l & 1 == 0 {
            continue;
        }
        let d = lane_dir[l];
        out[l] = match hits[l] {
            None => SubSample {
                triangle: MISS,
                dir: d,
                ..Default::default()
            },
            Some((j, t32)) => {
                let tri = tracer.leaf_triangle(j);
                let (h, sec_n) = tracer.refine_with_sec_at(ctx.origin, d, verts[l], tri, t32);
                // An anchored tracer reports the anchor mesh's point (`Tracer::anchored`).
                let local = tracer
                    .anchor_point(j, h.u, h.v)
                    .unwrap_or(ctx.origin + h.t * d);
                // Footprint (module docs): r · sqrt(Ω / |cos θ_n|), Ω = cos³θ_c / (fx fy),
                // |cos θ_n| clamped at 1e-6.
                let cos_c = d.dot(ctx.axis).abs();
                let sec_n = sec_n.min(1e6);
                let fp = h.t * ctx.inv_sqrt_f * (cos_c * cos_c * cos_c * sec_n).sqrt();
                SubSample {
                    triangle: tri,
                    t: h.t,
                    u: h.u,
                    v: h.v,
                    position: local * ctx.inv_extent + DVec3::splat(0.5),
                    dir: d,
                    footprint: fp * ctx.inv_extent_max,
                }
            }
        };
    }
    out
}

/// A pixel's summary from its γ² sub-samples: the valid mask, the normalised sum of the valid
/// directions and the mean footprint of the valid sub-samples (SPEC §2).
#[inline]
pub fn summarize(px: &[SubSample]) -> PixelSummary {
    let mut s = PixelSummary::default();
    let mut dsum = DVec3::ZERO;
    let mut fsum = 0.0;
    let mut n = 0u32;
    for (j, ss) in px.iter().enumerate() {
        if !ss.hit() {
            continue;
        }
        s.valid |= 1 << j;
        dsum += ss.dir;
        fsum += ss.footprint;
        n += 1;
    }
    if n > 0 {
        s.dir = dsum.normalize_or_zero();
        s.footprint = fsum / n as f64;
    }
    s
}

/// Cast the γ² sub-sample rays of pixel (u, v) as one packet into `subs` (length γ², order
/// `b·γ + a`) and return its summary: the same bits as the strip cast of the whole view gives
/// for that pixel (same directions, same per-ray closest hit and refinement).
pub(crate) fn cast_pixel(
    tracer: &Tracer,
    ctx: &CamCtx,
    gamma: u32,
    u: u32,
    v: u32,
    scratch: &mut Scratch,
    subs: &mut [SubSample],
) -> PixelSummary {
    let g = gamma;
    let g2 = (g * g) as usize;
    debug_assert!(g2 <= MAX_LANES && subs.len() == g2);
    let mut p = Packet::default();
    let mut lane_dir = [DVec3::ZERO; MAX_LANES];
    for j in 0..g2 as u32 {
        let (a, b) = (j % g, j / g);
        // As the strip cast: x(sx) = u + (a + 0.5)/γ, normalised per column/row.
        let x = ctx.xn(u as f64 + (a as f64 + 0.5) / g as f64);
        let y = ctx.yn(v as f64 + (b as f64 + 0.5) / g as f64);
        let d = ctx.dir(x, y);
        lane_dir[j as usize] = d;
        p.set(j as usize, ctx.origin32, d.as_vec3().to_array());
    }
    let out = trace_block(tracer, ctx, &p, &lane_dir, scratch);
    subs.copy_from_slice(&out[..g2]);
    summarize(subs)
}

/// Strip start rows of an image.
pub(crate) fn strips(height: u32) -> Vec<(u32, u32)> {
    (0..height)
        .step_by(STRIP_ROWS as usize)
        .map(|y0| (y0, STRIP_ROWS.min(height - y0)))
        .collect()
}

/// Cast every pixel of one camera with γ×γ rays (parallel over strips, deterministic).
pub fn cast_view(tracer: &Tracer, camera: &Camera, gamma: u32) -> Result<ViewCast> {
    cast_rows(tracer, camera, gamma, 0, camera.height)
}

/// Cast the pixel rows `y0 .. y0+rows` of a camera (`ViewCast::height` = `rows`; pixel (u, r)
/// of the result is image pixel (u, y0 + r)). A pixel's result does not depend on the band it
/// is cast in, so tiled rendering gives the same image as one whole-view cast.
pub fn cast_rows(
    tracer: &Tracer,
    camera: &Camera,
    gamma: u32,
    y0: u32,
    rows: u32,
) -> Result<ViewCast> {
    let mut out = ViewCast::default();
    cast_rows_into(tracer, camera, gamma, y0, rows, &mut out)?;
    Ok(out)
}

/// [`cast_rows`] into `out`, reusing its buffers (a frame cast band by band touches fresh
/// memory only once).
pub fn cast_rows_into(
    tracer: &Tracer,
    camera: &Camera,
    gamma: u32,
    y0: u32,
    rows: u32,
    out: &mut ViewCast,
) -> Result<()> {
    check_gamma(gamma)?;
    if y0.checked_add(rows).is_none_or(|e| e > camera.height) {
        bail!(
            "rows {y0}..{} are outside the {}-row image",
            y0 as u64 + rows as u64,
            camera.height
        );
    }
    let ctx = CamCtx::new(tracer, camera);
    let (w, h) = (camera.width as usize, rows as usize);
    let g2 = (gamma * gamma) as usize;
    // Filled in parallel on huge pages: at 1024×768, γ=2 this is 277 MB, and 4 KiB page faults
    // serialise the threads. Every element is written by `cast_strip`, so a buffer reused from
    // the previous band (as long or longer) is only cut to length, not filled again.
    let subs = &mut out.subs;
    if subs.capacity() < w * h * g2 {
        *subs = Vec::with_capacity(w * h * g2);
        super::advise_huge_pages(subs);
    }
    if subs.len() >= w * h * g2 {
        subs.truncate(w * h * g2);
    } else {
        subs.clear();
        subs.par_extend(rayon::iter::repeat_n(SubSample::default(), w * h * g2));
    }
    let pixels = &mut out.pixels;
    if pixels.len() >= w * h {
        pixels.truncate(w * h);
    } else {
        pixels.clear();
        pixels.resize(w * h, PixelSummary::default());
    }
    let strip = STRIP_ROWS as usize;
    subs.par_chunks_mut(strip * w * g2)
        .zip(pixels.par_chunks_mut(strip * w))
        .enumerate()
        .for_each_init(
            || tracer.scratch(),
            |sc, (k, (s, p))| {
                let y = y0 + (k * strip) as u32;
                let r = (p.len() / w.max(1)) as u32;
                let mut strip = Strip {
                    y0: y,
                    rows: r,
                    subs: s,
                    pixels: p,
                };
                cast_strip(tracer, &ctx, gamma, sc, &mut strip)
            },
        );
    out.width = camera.width;
    out.height = rows;
    out.gamma = gamma;
    Ok(())
}
