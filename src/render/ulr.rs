//! A classic no-learning baseline: unstructured lumigraph rendering (Buehler et al. 2001) on the
//! mesh. A pixel's centre ray hits the mesh at `P`; `P` is projected into each training photo
//! that sees it (inside the image, and visible: the photo's own ray towards `P` reaches `P`
//! first); the `K` photos with the smallest penalty are blended in linear RGB with ULR's weights.
//! Nothing is learned, so it shows what simply reprojecting the photos achieves.
//!
//! ```text
//! angle_j = ∠(ray of the rendered pixel, ray of photo j) at P                       (radians)
//! res_j   = max(0, footprint_j / footprint − 1),  footprint = distance / focal length
//! p_j     = angle_j + BETA · res_j
//! w_j     = (1 − p_j / p_(K+1)) / p_j   over the K smallest p_j  (p_(K+1): the next one, or
//!           2·max when fewer than K+1 photos see P), normalised to sum 1
//! colour  = Σ w_j · bilinear(photo_j, projection of P)   in linear RGB, then back to sRGB
//! ```
//! Which pixels are hits, and their footprints, are the model's: the pixel's γ×γ rays are cast
//! as the model's are (`raycast::cast_rows_into`) and any hit makes it a hit, so both methods are
//! scored on the same pixels. A hit pixel whose centre ray misses (the mesh ends inside it) or
//! whose centre hit no photo sees takes the mean, in linear RGB, of the blends at its rays' hits.
//! (Until 2026-11-27 the centre ray alone decided: ULR's masked scores then covered fewer pixels
//! than the model's wherever the mesh ends inside pixels — a real COLMAP workspace whose mesh
//! meets 3 % of a view: 2.8 against 3.0 %.) Pixels whose rays all miss, or whose hits no photo
//! sees, get the background colour. Deterministic (a pure function per pixel; pixels in parallel).

use super::Rendered;
use crate::raycast::Tracer;
use crate::scene::{Camera, Image};
use anyhow::Result;
use glam::DVec3;
use rayon::prelude::*;

/// Photos blended per pixel.
pub const K: usize = 4;
/// Weight of the resolution penalty against the angle (radians).
pub const BETA: f64 = 0.1;

/// A training photo for ULR: its camera and its pixels in linear RGB.
pub struct Source {
    pub camera: Camera,
    pub linear: Image,
}

fn to_linear(v: f32) -> f32 {
    if v <= 0.04045 {
        v / 12.92
    } else {
        ((v + 0.055) / 1.055).powf(2.4)
    }
}

fn to_srgb(v: f32) -> f32 {
    let v = v.clamp(0.0, 1.0);
    if v <= 0.0031308 {
        12.92 * v
    } else {
        1.055 * v.powf(1.0 / 2.4) - 0.055
    }
}

/// The training photos of a scene as ULR sources.
pub fn training_sources(scene: &crate::scene::Scene) -> anyhow::Result<Vec<Source>> {
    scene
        .train()
        .iter()
        .map(|&j| {
            Ok(Source::new(
                scene.views[j].camera.clone(),
                &scene.load_image(j)?,
            ))
        })
        .collect()
}

impl Source {
    /// A photo (sRGB-encoded values, as loaded) and its camera.
    pub fn new(camera: Camera, photo: &Image) -> Source {
        let mut linear = photo.clone();
        linear.data.iter_mut().for_each(|v| *v = to_linear(*v));
        Source { camera, linear }
    }

    /// Bilinear sample at continuous pixel coordinates (pixel centres at +0.5), clamped.
    fn sample(&self, x: f64, y: f64) -> [f32; 3] {
        let (w, h) = (self.linear.width as i64, self.linear.height as i64);
        let (fx, fy) = (x - 0.5, y - 0.5);
        let (x0, y0) = (fx.floor(), fy.floor());
        let (tx, ty) = ((fx - x0) as f32, (fy - y0) as f32);
        let px = |xi: i64, yi: i64| {
            let (xi, yi) = (xi.clamp(0, w - 1), yi.clamp(0, h - 1));
            let o = 3 * (yi * w + xi) as usize;
            [
                self.linear.data[o],
                self.linear.data[o + 1],
                self.linear.data[o + 2],
            ]
        };
        let (x0, y0) = (x0 as i64, y0 as i64);
        let (a, b, c, d) = (
            px(x0, y0),
            px(x0 + 1, y0),
            px(x0, y0 + 1),
            px(x0 + 1, y0 + 1),
        );
        std::array::from_fn(|i| {
            let top = a[i] + (b[i] - a[i]) * tx;
            let bot = c[i] + (d[i] - c[i]) * tx;
            top + (bot - top) * ty
        })
    }
}

/// The ULR colour (linear RGB) of the surface point `p` seen along unit `dir` from `eye` with
/// focal length `f` (pixels); `None` when no photo sees it.
fn blend(
    tracer: &Tracer,
    sources: &[Source],
    eye: DVec3,
    dir: DVec3,
    p: DVec3,
    f: f64,
) -> Option<[f64; 3]> {
    let fp = (p - eye).length() / f;
    let mut cand: Vec<(f64, usize, f64, f64)> = Vec::new();
    for (j, s) in sources.iter().enumerate() {
        let Some((x, y)) = s.camera.project(p) else {
            continue;
        };
        if !(x >= 0.0 && y >= 0.0 && x < s.camera.width as f64 && y < s.camera.height as f64) {
            continue;
        }
        let c = s.camera.center();
        let to_p = p - c;
        let dist = to_p.length();
        // Visible: the photo's ray towards P hits nothing before P.
        match tracer.closest_hit(c, to_p) {
            Some(h) if h.t >= dist * (1.0 - 1e-4) - 1e-9 => {}
            _ => continue,
        }
        let angle = dir.dot(to_p / dist).clamp(-1.0, 1.0).acos();
        let fpj = dist / s.camera.fx;
        let res = (fpj / fp - 1.0).max(0.0);
        cand.push((angle + BETA * res, j, x, y));
    }
    if cand.is_empty() {
        return None;
    }
    cand.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
    let thresh = if cand.len() > K {
        cand[K].0
    } else {
        2.0 * cand.last().unwrap().0
    };
    let mut acc = [0.0f64; 3];
    let mut wsum = 0.0;
    for &(p_j, j, x, y) in cand.iter().take(K) {
        let w = if thresh <= 0.0 {
            1.0
        } else {
            (1.0 - p_j / thresh).max(0.0) / p_j.max(1e-9)
        };
        let c = sources[j].sample(x, y);
        for i in 0..3 {
            acc[i] += w * c[i] as f64;
        }
        wsum += w;
    }
    if wsum <= 0.0 {
        // Every candidate at the threshold (e.g. one photo): plain mean of the K best.
        let n = cand.len().min(K) as f64;
        acc = [0.0; 3];
        for &(_, j, x, y) in cand.iter().take(K) {
            let c = sources[j].sample(x, y);
            for i in 0..3 {
                acc[i] += c[i] as f64 / n;
            }
        }
        wsum = 1.0;
    }
    Some(acc.map(|v| v / wsum))
}

/// Render `camera` by ULR from `sources`, its hit pixels those of `gamma`×`gamma` rays (module
/// docs), cast in the same bands of rows as the model's renders (`render::render_in_bands`).
pub fn render_ulr(
    tracer: &Tracer,
    sources: &[Source],
    camera: &Camera,
    gamma: u32,
    background: [f32; 3],
) -> Result<Rendered> {
    let (w, g2) = (camera.width as usize, (gamma * gamma) as usize);
    let eye = camera.center();
    let band = super::RENDER_BAND_SAMPLES;
    super::render_in_bands(
        tracer,
        camera,
        gamma,
        background,
        band,
        |cast, y0, colours| {
            (colours
                .par_chunks_mut(3)
                .zip(cast.subs.par_chunks(g2))
                .enumerate())
            .filter(|(_, (_, subs))| subs.iter().any(|s| s.hit()))
            .for_each(|(i, (out, subs))| {
                // The centre ray first: a training view reproduces its own photo's pixels.
                let (u, v) = (i % w, y0 as usize + i / w);
                let d = camera.dir_world(u as f64 + 0.5, v as f64 + 0.5);
                let centre = tracer.closest_hit(eye, d);
                if let Some(c) =
                    centre.and_then(|h| blend(tracer, sources, eye, d, eye + d * h.t, camera.fx))
                {
                    out.copy_from_slice(&c.map(|v| to_srgb(v as f32)));
                    return;
                }
                // The mesh ends inside this pixel, or no photo sees the centre's hit: the mean
                // of the rays that hit and are seen (the background when none is).
                let (mut acc, mut n) = ([0.0f64; 3], 0u32);
                for s in subs.iter().filter(|s| s.hit()) {
                    if let Some(c) =
                        blend(tracer, sources, eye, s.dir, eye + s.dir * s.t, camera.fx)
                    {
                        (0..3).for_each(|k| acc[k] += c[k]);
                        n += 1;
                    }
                }
                if n > 0 {
                    out.copy_from_slice(&acc.map(|v| to_srgb((v / n as f64) as f32)));
                }
            });
            Ok(())
        },
    )
}
