//! Ground-truth rendering of the true surface, and pixel-footprint statistics.
//!
//! Each pixel (u, v) covers [u, u+1)×[v, v+1) (SPEC §2); it is the box-filtered mean of
//! `spp_side²` rays at the stratified sub-pixel offsets ((a+0.5)/s, (b+0.5)/s), summed in the
//! fixed order b-major, a-minor (deterministic). Rays that miss see [`super::shade::sky`].
//! Parallelism: rayon over fixed tiles of [`TILE_ROWS`] rows; every pixel is a pure function of
//! the scene, so the result does not depend on the thread count.
//!
//! Footprint convention: the footprint of a ray at distance t is `t·sqrt(Ω)`, Ω the pixel's
//! solid angle `cos³θ/(fx·fy)` (θ = angle to the optical axis) — the side of the pixel's
//! cross-section perpendicular to the ray. Surface obliquity is not included in the reported
//! figures; the texture LOD divides by `max(|n·d|, 0.25)` to account for it.

use super::shade::{sky, Shader};
use crate::scene::{Camera, Image};
use glam::DVec3;
use rayon::prelude::*;

/// Rows per parallel work item (a constant of the code, SPEC §5).
pub const TILE_ROWS: usize = 4;

/// Pixel solid angle's square root at image point (x, y): `cos^1.5 θ / sqrt(fx fy)`.
#[inline]
pub fn pixel_angle(cam: &Camera, x: f64, y: f64) -> f64 {
    let d = cam.dir_camera(x, y);
    let cos = 1.0 / d.length();
    cos.powf(1.5) / (cam.fx * cam.fy).sqrt()
}

/// Render one view: `spp_side²` rays per pixel, box filter.
pub fn render(shader: &Shader, cam: &Camera, spp_side: u32) -> Image {
    let (w, h) = (cam.width as usize, cam.height as usize);
    let mut data = vec![0f32; w * h * 3]; // [h, w, 3]
    let o = cam.center();
    let s = spp_side as usize;
    let inv = 1.0 / s as f64;
    let rot_t = cam.rotation.transpose();
    data.par_chunks_mut(TILE_ROWS * w * 3)
        .enumerate()
        .for_each(|(tile, chunk)| {
            for (r, row) in chunk.chunks_mut(w * 3).enumerate() {
                let v = tile * TILE_ROWS + r;
                for u in 0..w {
                    let mut acc = DVec3::ZERO;
                    for b in 0..s {
                        for a in 0..s {
                            let x = u as f64 + (a as f64 + 0.5) * inv;
                            let y = v as f64 + (b as f64 + 0.5) * inv;
                            let dc = cam.dir_camera(x, y);
                            let d = (rot_t * dc).normalize();
                            acc += match shader.surface.trace(o, d, 0.0, f64::INFINITY) {
                                Some(hit) => {
                                    let cos = 1.0 / dc.length();
                                    let ray_fp =
                                        hit.t * cos.powf(1.5) / (cam.fx * cam.fy).sqrt() * inv;
                                    let fp = ray_fp / hit.normal.dot(d).abs().max(0.25);
                                    shader.shade(&hit, d, fp)
                                }
                                None => sky(d),
                            };
                        }
                    }
                    let c = acc / (s * s) as f64;
                    row[3 * u] = c.x as f32;
                    row[3 * u + 1] = c.y as f32;
                    row[3 * u + 2] = c.z as f32;
                }
            }
        });
    Image {
        width: cam.width,
        height: cam.height,
        data,
    }
}

/// Footprints (m) of the pixel-centre rays that hit, and the fraction of pixels that hit.
pub fn footprints(surface: &super::surface::TrueSurface, cam: &Camera) -> (Vec<f64>, f64) {
    footprints_strided(surface, cam, 1)
}

/// [`footprints`] over every `stride`-th row and column.
pub fn footprints_strided(
    surface: &super::surface::TrueSurface,
    cam: &Camera,
    stride: u32,
) -> (Vec<f64>, f64) {
    let o = cam.center();
    let stride = stride.max(1);
    let rows: Vec<Vec<f64>> = (0..cam.height)
        .step_by(stride as usize)
        .collect::<Vec<u32>>()
        .into_par_iter()
        .map(|v| {
            let mut out = Vec::new();
            for u in (0..cam.width).step_by(stride as usize) {
                let (x, y) = (u as f64 + 0.5, v as f64 + 0.5);
                if let Some(hit) = surface.trace(o, cam.dir_world(x, y), 0.0, f64::INFINITY) {
                    out.push(hit.t * pixel_angle(cam, x, y));
                }
            }
            out
        })
        .collect();
    let fp: Vec<f64> = rows.into_iter().flatten().collect();
    let n = cam.width.div_ceil(stride) as f64 * cam.height.div_ceil(stride) as f64;
    let frac = fp.len() as f64 / n;
    (fp, frac)
}
