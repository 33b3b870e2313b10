//! The photo-consistency term of the mesh refinement (`[model.refine] photo` > 0; the energy of a
//! patch and its derivative are in `refine/photo.rs`; SPEC §4.11, docs/geometry.md §4): which
//! pixels, which neighbour view, at which image level, and visibility.
//!
//! ## Setup (once per run, from the training mesh)
//! - Every training view keeps f32 copies of its photo box-downsampled by `2^l` for the levels
//!   `photo_levels[1] ..= photo_levels[0]` (12 bytes per pixel at level 0, a quarter of that per
//!   level above), and its camera (with its lens distortion) at each level.
//! - Neighbours: a 16 × 12 grid of pixel-centre rays of view i is cast against the *training*
//!   mesh; a hit x counts for view j ≠ i when it projects inside j, j sees it (the ray from j's
//!   centre towards x hits x's triangle or reaches at least (1 − [`VISIBILITY_TOLERANCE`]) of the
//!   distance), the angle between the two rays at x is within `photo_angle`, and the ratio of the
//!   two pixel footprints at x (distance × pixel angle) is within `[1/photo_scale, photo_scale]`.
//!   View i keeps the `photo_neighbours` views with the most such hits (ties: lower index), each
//!   with at least [`MIN_SHARED`] of them. Fixed for the run (so a resumed run has the same).
//!
//! ## A step k (while the mesh moves)
//! Image level `l` = `photo_levels[0]` for the first of `n = [0] − [1] + 1` equal spans of the
//! moving steps, down to `[1]` for the last. Patch slot s = 0 … `photo_pixels` − 1:
//! - kept pixel `below(seed, RefinePhoto, k, 2s, kept)` (over all training views, as a batch's
//!   pixels are drawn) gives view i and pixel (u, v); the patch is centred on level-l pixel
//!   `(u >> l, v >> l)` and must lie inside the level-l image;
//! - its neighbour is `neighbours_i[below(seed, RefinePhoto, k, 2s + 1, |neighbours_i|)]`;
//! - its `p²` pixel-centre rays (level-l camera) are cast against the current BVH; every ray must
//!   hit, and every hit must be visible from the neighbour (as above, current BVH); else the
//!   patch is dropped.
//!
//! The patches are drawn and evaluated in parallel in chunks of [`PHOTO_CHUNK`] (each patch
//! independent) and their vertex gradients summed in slot order on one thread: the result does not
//! depend on the thread count, and everything is a pure function of (seed, k, the BVH), so a
//! resumed run draws the same patches.

use crate::model::refine::RefineConfig;
use crate::raycast::{Packet, RayStream, Scratch, Tracer};
use crate::refine::field::RefineGeom;
use crate::refine::photo::{
    patch_eval, Neighbour, PatchEval, PatchPoint, PhotoCamera, PhotoImage, Scoring,
};
use crate::refine::trust::is_validation_row;
use crate::rng::{below, Purpose};
use crate::scene::Image;
use anyhow::{ensure, Result};
use glam::DVec3;
use rayon::prelude::*;

/// Patches per parallel work item (a constant: SPEC §5.2; each patch is independent).
pub const PHOTO_CHUNK: usize = 16;
/// A hit is visible from a view when the view's ray towards it reaches this close to it
/// (relative to the distance) or hits its triangle.
pub const VISIBILITY_TOLERANCE: f64 = 0.01;
/// Pixel-centre rays per view used to choose its neighbours (columns, rows).
pub const PROBE_GRID: [u32; 2] = [16, 12];
/// Fewest probe hits a neighbour must share with its view.
pub const MIN_SHARED: usize = 8;

/// One training view as the photo term sees it.
#[derive(Clone, Debug)]
pub struct PhotoView {
    /// Appearance row (the stream's view index).
    pub row: usize,
    /// Camera at levels 0 ..= `photo_levels[0]`.
    pub cams: Vec<PhotoCamera>,
    /// Photo at each level (`None` below `photo_levels[1]`).
    pub images: Vec<Option<PhotoImage>>,
    /// Neighbour views (slots), best first.
    pub neighbours: Vec<usize>,
    /// Takes part (not a trust-region validation view).
    pub active: bool,
}

/// A drawn patch (module docs).
#[derive(Clone, Debug)]
pub struct Patch {
    /// Slot of the reference view and of its neighbour.
    pub view: usize,
    pub neighbour: usize,
    pub level: u32,
    pub points: Vec<PatchPoint>,
}

/// The patches of step k are drawn from the training views' `stream` (kept pixels, photos) with
/// the run's `seed`, at image level `level`, their rays cast against `tracer`.
#[derive(Clone, Copy)]
struct StepDraw<'a> {
    stream: &'a RayStream,
    tracer: &'a Tracer,
    seed: u64,
    k: u64,
    level: u32,
}

/// The photo-consistency term of a run (module docs).
pub struct PhotoTerm {
    pub views: Vec<PhotoView>,
    /// Kept pixels over all training views (the stream's numbering).
    total: usize,
    cfg: RefineConfig,
}

/// Sums of one step's (or update's) patches.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct PhotoStats {
    pub drawn: u64,
    pub valid: u64,
    pub energy: f64,
}

impl PhotoStats {
    pub fn add(&mut self, o: &PhotoStats) {
        self.drawn += o.drawn;
        self.valid += o.valid;
        self.energy += o.energy;
    }
}

/// Closest hits (mesh triangle, f64 distance) of rays from `o` (local frame) along unit `dirs`.
///
/// One ray per packet: the photo term's rays are not coherent enough to trace together (a
/// coarse level's patch spreads over many photo pixels, visibility rays go to scattered points),
/// and a group traversal visits the union of its rays' nodes, 5–50× slower here than one ray at
/// a time. A ray's result does not depend on the packet it is traced in.
fn trace_from(
    tracer: &Tracer,
    scratch: &mut Scratch,
    o: DVec3,
    dirs: &[DVec3],
) -> Vec<Option<(u32, f64)>> {
    let o32 = o.as_vec3().to_array();
    let mut p = Packet::default();
    dirs.iter()
        .map(|d| {
            p.set(0, o32, d.as_vec3().to_array());
            tracer.trace(&p, scratch)[0].map(|(tri, t32)| (tri, tracer.refine(o, *d, tri, t32).t))
        })
        .collect()
}

/// Whether local point `x` on triangle `tri` is seen from `o` (module docs), for many points.
fn visible_from(
    tracer: &Tracer,
    scratch: &mut Scratch,
    o: DVec3,
    points: &[(DVec3, u32)],
) -> Vec<bool> {
    let dirs: Vec<DVec3> = points
        .iter()
        .map(|(x, _)| (*x - o).normalize_or_zero())
        .collect();
    let hits = trace_from(tracer, scratch, o, &dirs);
    points
        .iter()
        .zip(hits)
        .map(|((x, tri), h)| match h {
            Some((t2, t)) => {
                let dist = (*x - o).length();
                t2 == *tri || t >= dist * (1.0 - VISIBILITY_TOLERANCE)
            }
            None => false,
        })
        .collect()
}

/// The image of a stream view (its photo as loaded).
fn stream_image(v: &crate::raycast::StreamView) -> Image {
    let n = v.camera.width as usize * v.camera.height as usize;
    let mut data = Vec::with_capacity(3 * n);
    for i in 0..n {
        data.extend(v.targets.rgb(3 * i));
    }
    Image {
        width: v.camera.width,
        height: v.camera.height,
        data,
    }
}

impl PhotoTerm {
    /// Set up from the training views (`stream`) and the training mesh's BVH (module docs).
    /// `center` is the normalisation centre; `names[r]` names the view of appearance row r in
    /// errors.
    pub fn new(
        stream: &RayStream,
        tracer: &Tracer,
        center: DVec3,
        cfg: &RefineConfig,
        names: &[String],
    ) -> Result<PhotoTerm> {
        let [l0, l1] = cfg.photo_levels;
        let mut views = Vec::with_capacity(stream.views.len());
        for v in &stream.views {
            let name = names
                .get(v.view)
                .map_or_else(|| v.view.to_string(), |n| n.clone());
            let cam = PhotoCamera::new(&v.camera, center);
            let cams: Vec<PhotoCamera> = (0..=l0).map(|l| cam.level(l)).collect();
            ensure!(
                cams[l0 as usize].width as usize >= cfg.photo_patch as usize
                    && cams[l0 as usize].height as usize >= cfg.photo_patch as usize,
                "model.refine: photo_levels[0] = {l0} leaves view {name} at {}×{} pixels, smaller than a photo_patch of {} (lower photo_levels)",
                cams[l0 as usize].width,
                cams[l0 as usize].height,
                cfg.photo_patch
            );
            let img = stream_image(v);
            let images = (0..=l0)
                .map(|l| {
                    (l >= l1).then(|| {
                        PhotoImage::from_image(&crate::scene::image::downsample(&img, 1 << l))
                    })
                })
                .collect();
            views.push(PhotoView {
                row: v.view,
                cams,
                images,
                neighbours: Vec::new(),
                active: !is_validation_row(v.view as i32, cfg.trust_holdout),
            });
        }
        let lists: Vec<Vec<usize>> = (0..views.len())
            .into_par_iter()
            .map_init(
                || tracer.scratch(),
                |sc, i| choose_neighbours(tracer, sc, &views, i, cfg),
            )
            .collect();
        for (v, l) in views.iter_mut().zip(lists) {
            v.neighbours = l;
        }
        Ok(PhotoTerm {
            total: stream.len(),
            views,
            cfg: cfg.clone(),
        })
    }

    /// Draw and cast the patches of step k at image level l against `tracer` (module docs);
    /// `None` for a dropped slot.
    pub fn draw(
        &self,
        stream: &RayStream,
        tracer: &Tracer,
        seed: u64,
        k: u64,
        level: u32,
    ) -> Vec<Option<Patch>> {
        let n = self.cfg.photo_pixels as usize;
        let draw = StepDraw {
            stream,
            tracer,
            seed,
            k,
            level,
        };
        (0..n)
            .into_par_iter()
            .with_min_len(PHOTO_CHUNK)
            .map_init(|| tracer.scratch(), |sc, s| self.draw_one(&draw, sc, s))
            .collect()
    }

    /// Patch slot `s` of `draw` (module docs), `None` when it is dropped.
    fn draw_one(&self, draw: &StepDraw, sc: &mut Scratch, s: usize) -> Option<Patch> {
        let StepDraw {
            stream,
            tracer,
            seed,
            k,
            level,
        } = *draw;
        if self.total == 0 {
            return None;
        }
        let idx = below(
            seed,
            Purpose::RefinePhoto,
            k,
            2 * s as u64,
            self.total as u64,
        );
        let (slot, u, v) = stream.locate(idx as usize);
        let view = &self.views[slot];
        if !view.active || view.neighbours.is_empty() {
            return None;
        }
        let j = view.neighbours[below(
            seed,
            Purpose::RefinePhoto,
            k,
            2 * s as u64 + 1,
            view.neighbours.len() as u64,
        ) as usize];
        let cam = &view.cams[level as usize];
        let img = view.images[level as usize].as_ref()?;
        let r = (self.cfg.photo_patch / 2) as i64;
        let (cu, cv) = ((u >> level) as i64, (v >> level) as i64);
        if cu < r || cv < r || cu + r >= cam.width as i64 || cv + r >= cam.height as i64 {
            return None;
        }
        let mut pix = Vec::with_capacity((2 * r as usize + 1).pow(2));
        for b in -r..=r {
            for a in -r..=r {
                pix.push(((cu + a) as u32, (cv + b) as u32));
            }
        }
        let dirs: Vec<DVec3> = pix
            .iter()
            .map(|&(x, y)| cam.ray(x as f64 + 0.5, y as f64 + 0.5))
            .collect();
        let hits = trace_from(tracer, sc, cam.origin, &dirs);
        let mut pts = Vec::with_capacity(hits.len());
        for (d, h) in dirs.iter().zip(&hits) {
            let (tri, t) = (*h)?;
            pts.push((cam.origin + *d * t, tri));
        }
        let other = &self.views[j].cams[level as usize];
        if !visible_from(tracer, sc, other.origin, &pts)
            .iter()
            .all(|&v| v)
        {
            return None;
        }
        let points = pix
            .iter()
            .zip(&dirs)
            .zip(&pts)
            .map(|((&(x, y), &d), &(_, tri))| PatchPoint {
                tri,
                d,
                reference: img.pixel(x, y),
            })
            .collect();
        Some(Patch {
            view: slot,
            neighbour: j,
            level,
            points,
        })
    }

    /// Energy and vertex gradient of each drawn patch at offsets `theta` (read at the patches'
    /// vertices only), in slot order.
    pub fn evaluate(
        &self,
        geom: &RefineGeom,
        theta: &[f64],
        patches: &[Option<Patch>],
    ) -> Vec<Option<PatchEval>> {
        let scoring = Scoring {
            measure: self.cfg.photo_measure,
            min_cos: self.cfg.min_cos,
            weight: self.cfg.photo / self.cfg.photo_pixels as f64,
        };
        patches
            .par_iter()
            .with_min_len(PHOTO_CHUNK)
            .map(|p| {
                let p = p.as_ref()?;
                let j = &self.views[p.neighbour];
                let neighbour = Neighbour {
                    cam: &j.cams[p.level as usize],
                    img: j.images[p.level as usize].as_ref()?,
                };
                let origin = self.views[p.view].cams[p.level as usize].origin;
                patch_eval(geom, theta, origin, &p.points, neighbour, scoring)
            })
            .collect()
    }
}

/// The vertices of the drawn patches' triangles (ascending, once each).
pub fn patch_vertices(geom: &RefineGeom, patches: &[Option<Patch>]) -> Vec<u32> {
    let mut v: Vec<u32> = patches
        .iter()
        .flatten()
        .flat_map(|p| p.points.iter().flat_map(|q| geom.triangles[q.tri as usize]))
        .collect();
    v.sort_unstable();
    v.dedup();
    v
}

/// Add the evaluated patches' gradients into `d_theta` and, given `d_curv`, their curvatures
/// spread over their vertices (`curvature · share`) into it, in slot order; their sums.
pub fn accumulate(
    evals: &[Option<PatchEval>],
    d_theta: &mut [f64],
    mut d_curv: Option<&mut [f64]>,
) -> PhotoStats {
    let mut st = PhotoStats {
        drawn: evals.len() as u64,
        ..PhotoStats::default()
    };
    for e in evals.iter().flatten() {
        st.valid += 1;
        st.energy += e.energy;
        for &(v, g) in &e.grad {
            d_theta[v as usize] += g;
        }
        if let Some(c) = d_curv.as_deref_mut() {
            for (&(v, _), &s) in e.grad.iter().zip(&e.share) {
                c[v as usize] += e.curvature * s;
            }
        }
    }
    st
}

/// View i's neighbours (module docs).
fn choose_neighbours(
    tracer: &Tracer,
    sc: &mut Scratch,
    views: &[PhotoView],
    i: usize,
    cfg: &RefineConfig,
) -> Vec<usize> {
    let vi = &views[i];
    if !vi.active {
        return Vec::new();
    }
    let cam = &vi.cams[0];
    let [gw, gh] = PROBE_GRID;
    let dirs: Vec<DVec3> = (0..gh)
        .flat_map(|b| (0..gw).map(move |a| (a, b)))
        .map(|(a, b)| {
            cam.ray(
                (a as f64 + 0.5) * cam.width as f64 / gw as f64,
                (b as f64 + 0.5) * cam.height as f64 / gh as f64,
            )
        })
        .collect();
    let pts: Vec<(DVec3, u32)> = trace_from(tracer, sc, cam.origin, &dirs)
        .into_iter()
        .zip(&dirs)
        .filter_map(|(h, d)| h.map(|(tri, t)| (cam.origin + *d * t, tri)))
        .collect();
    let [a0, a1] = cfg.photo_angle.map(f64::to_radians);
    let mut scored: Vec<(usize, usize)> = Vec::new();
    for (j, vj) in views.iter().enumerate() {
        if j == i || !vj.active {
            continue;
        }
        let cj = &vj.cams[0];
        let seen = visible_from(tracer, sc, cj.origin, &pts);
        let count = pts
            .iter()
            .zip(&seen)
            .filter(|((x, _), &vis)| {
                if !vis {
                    return false;
                }
                let Some((p, _)) = cj.project(*x) else {
                    return false;
                };
                if !(p[0] >= 0.0
                    && p[1] >= 0.0
                    && p[0] < cj.width as f64
                    && p[1] < cj.height as f64)
                {
                    return false;
                }
                let (ri, rj) = (*x - cam.origin, *x - cj.origin);
                let angle = (ri.dot(rj) / (ri.length() * rj.length()))
                    .clamp(-1.0, 1.0)
                    .acos();
                let ratio = (rj.length() * cj.pixel_angle()) / (ri.length() * cam.pixel_angle());
                (a0..=a1).contains(&angle)
                    && ratio <= cfg.photo_scale
                    && ratio * cfg.photo_scale >= 1.0
            })
            .count();
        if count >= MIN_SHARED {
            scored.push((j, count));
        }
    }
    scored.sort_by(|a, b| b.1.cmp(&a.1).then(a.0.cmp(&b.0)));
    scored
        .into_iter()
        .take(cfg.photo_neighbours as usize)
        .map(|(j, _)| j)
        .collect()
}
