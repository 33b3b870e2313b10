//! The photo-consistency term of the mesh refinement (`[model.refine] photo` > 0; the energy of a
//! patch and its derivative are in `refine/photo.rs`; SPEC §4.11, docs/geometry.md §4): which
//! pixels, which neighbour view, at which image level, and visibility.
//!
//! ## Setup (once per run, from the training mesh)
//! - Probes: a 16 × 12 grid of pixel-centre rays of each training view is cast against the
//!   *training* mesh. The view's footprint `f_i` is the median over its probe hits x of
//!   `|x − o_i| / √(f_x f_y)` (NaN without hits); `F` is the largest footprint of the active views
//!   (the coarsest view: the mesh is taken to come from such views).
//! - Levels: view i's last usable level `cap_i` is the largest `l ≥ photo_levels[0]` (at most
//!   [`PHOTO_MAX_LEVEL`](crate::model::refine::PHOTO_MAX_LEVEL)) at which its image is at least `photo_patch + 2·⌈PHOTO_PULL⌉` pixels high and
//!   wide (a patch and its pull-in on either side); `photo_levels[0]` when `photo_reach` = 0. With `photo_reach` = r > 0 the mesh is
//!   taken to be off by up to `r·F`, which is `r·F/f_i` of view i's pixels; its deepest level is
//!   `top_i = min(cap_i, max(photo_levels[0], ⌈log2(r·F / (f_i · PHOTO_PULL))⌉))`, the level at
//!   which that displacement is at most [`PHOTO_PULL`] pixels (r = 0 or no footprint:
//!   `photo_levels[0]`). Views whose footprint is within a few times the coarsest keep
//!   `photo_levels[0]`; close-ups of a far-view mesh start deeper.
//! - Every training view keeps f32 copies of its photo box-downsampled by `2^l` for the levels
//!   `photo_levels[1] ..= cap_i` (a neighbour needs its photo at the reference's level, which
//!   may be deeper than its own top) (12 bytes per pixel at level 0, a quarter of that per level
//!   above), and its camera (with its lens distortion) at each level `0 ..= cap_i`.
//! - Weights (`photo_balance`): `c_i` = the active views whose footprint is within
//!   `[f_i/photo_scale, f_i·photo_scale]` (i included); `w_i = mean_j(c_j) / c_i`, so each scale
//!   band weighs about the same whatever its number of views (1 without `photo_balance`, or for a
//!   view without footprint).
//!
//! ## Neighbours (on a mesh)
//! The probe hits of view i on the mesh of a BVH: a hit x counts for view j ≠ i when it
//! projects inside j, j sees it (the ray from j's centre towards x hits x's triangle or reaches
//! at least (1 − [`VISIBILITY_TOLERANCE`]) of the distance), the angle between the two rays at x
//! is within `photo_angle`, and the ratio of the two pixel footprints at x (distance × pixel
//! angle) is within `[1/photo_scale, photo_scale]` (the same scale band). View i keeps the
//! `photo_neighbours` views with the most such hits (ties: lower index), each with at least
//! [`MIN_SHARED`] of them. Chosen on the training mesh at setup and, with `photo_rechoose`, again
//! on the moved mesh at every BVH rebuild (a pure function of the offsets the BVH is built
//! from, which a checkpoint holds: a resumed run has the same).
//!
//! ## A step k (while the mesh moves)
//! View i's image level is `top_i` for the first of `n_i = top_i − photo_levels[1] + 1` equal
//! spans of the moving steps, down to `photo_levels[1]` for the last ([`level_at`]). Patch slot
//! s = 0 … `photo_pixels` − 1:
//! - kept pixel `below(seed, RefinePhoto, k, 2s, kept)` (over all training views, as a batch's
//!   pixels are drawn) gives view i and pixel (u, v); the patch is centred on level-l pixel
//!   `(u >> l, v >> l)` (l = view i's level at k) and must lie inside the level-l image;
//! - its neighbour is `neighbours_i[below(seed, RefinePhoto, k, 2s + 1, |neighbours_i|)]`, which
//!   must have a photo at level l;
//! - its `p²` pixel-centre rays (level-l camera) are cast against the current BVH; every ray must
//!   hit, and every hit must be visible from the neighbour (as above, current BVH); else the
//!   patch is dropped. Its energy is weighted by `w_i`.
//!
//! The patches are drawn and evaluated in parallel in chunks of [`PHOTO_CHUNK`] (each patch
//! independent) and their vertex gradients summed in slot order on one thread: the result does not
//! depend on the thread count, and everything is a pure function of (seed, k, the BVH), so a
//! resumed run draws the same patches.

use crate::model::refine::{photo_level_cap, RefineConfig, PHOTO_PULL};
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
    /// Camera at levels 0 ..= the view's last level (`cap`, module docs).
    pub cams: Vec<PhotoCamera>,
    /// Photo at each level (`None` below `photo_levels[1]`).
    pub images: Vec<Option<PhotoImage>>,
    /// Neighbour views (slots), best first.
    pub neighbours: Vec<usize>,
    /// Takes part (not a trust-region validation view).
    pub active: bool,
    /// Median pixel footprint of its probe hits on the training mesh (scene units; NaN when no
    /// probe hit).
    pub footprint: f64,
    /// Its deepest image level `L_i` (module docs).
    pub top: u32,
    /// Weight of its patches (`photo_balance`; else 1).
    pub weight: f64,
    /// The training-mesh triangles its probe rays hit (ascending; diagnostics).
    pub probe_triangles: Vec<u32>,
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
}

/// The photo-consistency term of a run (module docs).
pub struct PhotoTerm {
    pub views: Vec<PhotoView>,
    /// Kept pixels over all training views (the stream's numbering).
    total: usize,
    cfg: RefineConfig,
    /// The moving steps `[k0, k1)` (the level schedule).
    span: (u64, u64),
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
        span: (u64, u64),
    ) -> Result<PhotoTerm> {
        let [l0, l1] = cfg.photo_levels;
        let mut views = Vec::with_capacity(stream.views.len());
        for v in &stream.views {
            let name = names
                .get(v.view)
                .map_or_else(|| v.view.to_string(), |n| n.clone());
            let cam = PhotoCamera::new(&v.camera, center);
            // Levels above L0 only for the cross-scale levels (`photo_reach`).
            let cap = if cfg.photo_reach > 0.0 {
                level_cap(&cam, l0, cfg.photo_patch)
            } else {
                l0
            };
            let cams: Vec<PhotoCamera> = (0..=cap).map(|l| cam.level(l)).collect();
            ensure!(
                cams[l0 as usize].width as usize >= cfg.photo_patch as usize
                    && cams[l0 as usize].height as usize >= cfg.photo_patch as usize,
                "model.refine: photo_levels[0] = {l0} leaves view {name} at {}×{} pixels, smaller than a photo_patch of {} (lower photo_levels)",
                cams[l0 as usize].width,
                cams[l0 as usize].height,
                cfg.photo_patch
            );
            views.push(PhotoView {
                row: v.view,
                cams,
                images: Vec::new(),
                neighbours: Vec::new(),
                active: !is_validation_row(v.view as i32, cfg.trust_holdout),
                footprint: f64::NAN,
                top: l0,
                weight: 1.0,
                probe_triangles: Vec::new(),
            });
        }
        // Footprints and probe triangles on the training mesh (fixed for the run).
        let probes: Vec<(f64, Vec<u32>)> = views
            .par_iter()
            .map_init(
                || tracer.scratch(),
                |sc, v| {
                    let pts = probe(tracer, sc, &v.cams[0]);
                    let mut f: Vec<f64> = pts
                        .iter()
                        .map(|(x, _)| (*x - v.cams[0].origin).length() * v.cams[0].pixel_angle())
                        .collect();
                    f.sort_by(f64::total_cmp);
                    let median = f.get(f.len() / 2).copied().unwrap_or(f64::NAN);
                    let mut vs: Vec<u32> = pts.iter().map(|(_, t)| *t).collect();
                    vs.sort_unstable();
                    vs.dedup();
                    (median, vs)
                },
            )
            .collect();
        for (v, (f, vs)) in views.iter_mut().zip(probes) {
            v.footprint = f;
            v.probe_triangles = vs;
        }
        plan_views(&mut views, cfg);
        // Photos at levels L1 ..= cap (a neighbour may need a deeper one than the view's own top).
        for (v, sv) in views.iter_mut().zip(&stream.views) {
            let img = stream_image(sv);
            v.images = (0..v.cams.len() as u32)
                .map(|l| {
                    (l >= l1).then(|| {
                        PhotoImage::from_image(&crate::scene::image::downsample(&img, 1 << l))
                    })
                })
                .collect();
        }
        let mut term = PhotoTerm {
            total: stream.len(),
            views,
            cfg: cfg.clone(),
            span,
        };
        term.choose(tracer);
        Ok(term)
    }

    /// Choose every view's neighbours on the mesh of `tracer` (module docs).
    pub fn choose(&mut self, tracer: &Tracer) {
        let (views, cfg) = (&self.views, &self.cfg);
        let lists: Vec<Vec<usize>> = (0..views.len())
            .into_par_iter()
            .map_init(
                || tracer.scratch(),
                |sc, i| choose_neighbours(tracer, sc, views, i, cfg),
            )
            .collect();
        for (v, l) in self.views.iter_mut().zip(lists) {
            v.neighbours = l;
        }
    }

    /// Image level of view `slot` at step k (module docs): `top` for the first of
    /// `n = top − photo_levels[1] + 1` equal spans of the moving steps, down to
    /// `photo_levels[1]` for the last.
    pub fn level(&self, slot: usize, k: u64) -> u32 {
        level_at(self.views[slot].top, self.cfg.photo_levels[1], self.span, k)
    }

    /// Draw and cast the patches of step k at image level l against `tracer` (module docs);
    /// `None` for a dropped slot.
    pub fn draw(
        &self,
        stream: &RayStream,
        tracer: &Tracer,
        seed: u64,
        k: u64,
    ) -> Vec<Option<Patch>> {
        let n = self.cfg.photo_pixels as usize;
        let draw = StepDraw {
            stream,
            tracer,
            seed,
            k,
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
        let level = self.level(slot, k);
        let cam = &view.cams[level as usize];
        let img = view.images.get(level as usize)?.as_ref()?;
        // The neighbour's photo at that level (a view of the same band may stop a level short).
        self.views[j].images.get(level as usize)?.as_ref()?;
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
        let base = self.cfg.photo / self.cfg.photo_pixels as f64;
        patches
            .par_iter()
            .with_min_len(PHOTO_CHUNK)
            .map(|p| {
                let p = p.as_ref()?;
                let scoring = Scoring {
                    measure: self.cfg.photo_measure,
                    min_cos: self.cfg.min_cos,
                    weight: base * self.views[p.view].weight,
                };
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
    let pts = probe(tracer, sc, cam);
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

/// The hits (local point, triangle) of the probe grid's pixel-centre rays of a view's level-0
/// camera (module docs).
fn probe(tracer: &Tracer, sc: &mut Scratch, cam: &PhotoCamera) -> Vec<(DVec3, u32)> {
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
    trace_from(tracer, sc, cam.origin, &dirs)
        .into_iter()
        .zip(&dirs)
        .filter_map(|(h, d)| h.map(|(tri, t)| (cam.origin + *d * t, tri)))
        .collect()
}

/// The deepest level a view's photo can be used at: the largest `l ≥ l0` (at most
/// [`PHOTO_MAX_LEVEL`](crate::model::refine::PHOTO_MAX_LEVEL)) whose image holds a patch and its pull-in on either side
/// (`photo_patch + 2·⌈PHOTO_PULL⌉` pixels high and wide), else `l0` (which `PhotoTerm::new`
/// checks holds one patch).
pub fn level_cap(cam: &PhotoCamera, l0: u32, patch: u32) -> u32 {
    photo_level_cap(cam.width, cam.height, l0, patch)
}

/// Each view's deepest level `top` and weight (module docs) from the footprints.
pub fn plan_views(views: &mut [PhotoView], cfg: &RefineConfig) {
    let l0 = cfg.photo_levels[0];
    let fps: Vec<f64> = views
        .iter()
        .filter(|v| v.active && v.footprint.is_finite() && v.footprint > 0.0)
        .map(|v| v.footprint)
        .collect();
    let coarsest = fps.iter().copied().fold(f64::NAN, f64::max);
    for v in views.iter_mut() {
        let cap = (v.cams.len() - 1) as u32;
        v.top = l0;
        if cfg.photo_reach > 0.0 && v.footprint > 0.0 && coarsest.is_finite() {
            // Displacement in the view's pixels: reach · coarsest / footprint; level l divides
            // it by 2^l, down to PHOTO_PULL.
            let px = cfg.photo_reach * coarsest / v.footprint;
            let need = (px / PHOTO_PULL).log2().ceil();
            if need.is_finite() && need > l0 as f64 {
                v.top = (need.min(cap as f64) as u32).max(l0);
            }
        }
        v.weight = 1.0;
    }
    if !cfg.photo_balance || fps.is_empty() {
        return;
    }
    // Views in a view's band (itself included), and their mean over the active views.
    let band = |f: f64| {
        fps.iter()
            .filter(|&&g| g <= f * cfg.photo_scale && g * cfg.photo_scale >= f)
            .count() as f64
    };
    let counts: Vec<Option<f64>> = views
        .iter()
        .map(|v| {
            (v.active && v.footprint.is_finite() && v.footprint > 0.0).then(|| band(v.footprint))
        })
        .collect();
    let n = counts.iter().flatten().count() as f64;
    let mean = counts.iter().flatten().sum::<f64>() / n;
    for (v, c) in views.iter_mut().zip(counts) {
        if let Some(c) = c {
            v.weight = mean / c;
        }
    }
}

/// Image level at step k of a view whose deepest level is `top` (module docs).
pub fn level_at(top: u32, finest: u32, (k0, k1): (u64, u64), k: u64) -> u32 {
    let n = (top - finest + 1) as u64;
    let span = k1.saturating_sub(k0).max(1);
    let i = (k.saturating_sub(k0) * n / span).min(n - 1);
    top - i as u32
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::scene::{Camera, Distortion};
    use glam::DMat3;

    /// A view of `w × h` pixels whose probe footprint is `footprint`, with cameras up to its cap.
    fn view(w: u32, h: u32, footprint: f64, cfg: &RefineConfig) -> PhotoView {
        let cam = PhotoCamera::new(
            &Camera {
                width: w,
                height: h,
                fx: w as f64,
                fy: w as f64,
                cx: w as f64 / 2.0,
                cy: h as f64 / 2.0,
                distortion: Distortion::None,
                rotation: DMat3::IDENTITY,
                translation: DVec3::ZERO,
            },
            DVec3::ZERO,
        );
        let cap = level_cap(&cam, cfg.photo_levels[0], cfg.photo_patch);
        PhotoView {
            row: 0,
            cams: (0..=cap).map(|l| cam.level(l)).collect(),
            images: Vec::new(),
            neighbours: Vec::new(),
            active: true,
            footprint,
            top: 0,
            weight: 0.0,
            probe_triangles: Vec::new(),
        }
    }

    #[test]
    fn levels_follow_the_footprints_and_bands_weigh_alike() {
        let cfg = RefineConfig {
            photo_reach: 2.0,
            photo_balance: true,
            ..RefineConfig::default()
        };
        assert_eq!(cfg.photo_levels, [2, 0]);
        // 200 × 150 with 5 × 5 patches: level 4 is 12 × 9, the last that holds 5 + 2·2 pixels.
        let mut views = vec![
            view(200, 150, 0.7, &cfg),
            view(200, 150, 0.5, &cfg),
            view(200, 150, 0.6, &cfg),
            view(200, 150, 0.03, &cfg),
            view(200, 150, 0.3, &cfg),
        ];
        assert_eq!(views[0].cams.len(), 5);
        plan_views(&mut views, &cfg);
        // Displacement 2 · 0.7 / f pixels, over PHOTO_PULL = 2: the far views 1 – 1.4 (level 2,
        // photo_levels[0]), 0.3 → ⌈log2 2.33⌉ = 2, the close-up 23.3 → 5, capped at 4.
        let tops: Vec<u32> = views.iter().map(|v| v.top).collect();
        assert_eq!(tops, [2, 2, 2, 4, 2]);
        // Each view counts the views within a factor photo_scale = 2 of its footprint, itself
        // included: 0.7 {0.7, 0.5, 0.6}, 0.5 and 0.6 also 0.3, 0.3 {0.5, 0.6, 0.3}, 0.03 alone.
        let counts = [3.0, 4.0, 4.0, 1.0, 3.0];
        let mean = counts.iter().sum::<f64>() / 5.0;
        for (v, c) in views.iter().zip(counts) {
            assert_eq!(v.weight, mean / c);
        }
        // Off: photo_levels for every view, weights 1.
        let off = RefineConfig {
            photo_reach: 0.0,
            photo_balance: false,
            ..cfg.clone()
        };
        plan_views(&mut views, &off);
        assert!(views.iter().all(|v| v.top == 2 && v.weight == 1.0));
    }

    #[test]
    fn a_view_descends_from_its_top_level_in_equal_spans() {
        // top 2 → the global schedule of photo_levels [2, 0] over steps [10, 40).
        let lv: Vec<u32> = (10..40).map(|k| level_at(2, 0, (10, 40), k)).collect();
        assert_eq!(&lv[..10], &[2; 10]);
        assert_eq!(&lv[10..20], &[1; 10]);
        assert_eq!(&lv[20..], &[0; 10]);
        // top 4: five spans of 6 steps.
        let lv: Vec<u32> = (10..40).map(|k| level_at(4, 0, (10, 40), k)).collect();
        assert_eq!(lv[0], 4);
        assert_eq!(lv[6], 3);
        assert_eq!(lv[29], 0);
        assert_eq!(level_at(4, 0, (10, 40), 100), 0);
    }
}
