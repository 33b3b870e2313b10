//! The hit point of a ray on the moving mesh and its gradient with respect to the offsets
//! (SPEC §4.11): every valid sub-sample of a batch is re-intersected with the current plane of
//! the triangle its ray hit, and the loss's gradient with respect to the hit position
//! (`grad.batch.positions`) becomes one with respect to the vertex offsets.
//!
//! The paper's mesh is fixed. Here the vertices of the training mesh may move along their
//! normals, and the photometric loss moves them: a hit point moves along its ray when its
//! triangle moves along the triangle's normal (tangential motion only re-parametrises the
//! surface).
//!
//! ## Hit point and its gradient
//! For a valid sub-sample of a training batch: its triangle T = (k0, k1, k2) (from the ray cast),
//! the ray origin `o` (the camera centre, local frame) and the unit direction `d` from `o` to the
//! cast hit. With the current vertices a, b, c of T, Möller–Trumbore (f64, as `raycast/bvh.rs`)
//! gives `t` and barycentrics `β = (1 − u − v, u, v)`; the position is `x_n = (o + t·d) / extent + 0.5`.
//! With `n = (b − a) × (c − a)` and `g = ∂L/∂x_n ⊘ extent` (per axis: the normalisation's chain
//! rule, so ∂L/∂x in local units),
//! ```text
//! ∂L/∂v_k = (g·d) · β_k · n / (n·d)                 (k ∈ T)
//! ∂L/∂θ_k = s · (g·d) · β_k · (n·m_k) / (n·d)
//! ```
//! which is the exact derivative of the plane intersection (the hit moves along `d` by
//! `Σ_k β_k n·δv_k / (n·d)`). Held constant (data, as in the fixed-mesh model): the ray (`o`, `d`),
//! the triangle each sub-sample hits (chosen by the BVH of the last rebuild), which sub-samples
//! are valid, the pixel's view direction and its footprint (level weighting, SPEC §4.10). A
//! sub-sample is left at its cast position with no vertex gradient when the ray is within
//! `acos(min_cos)` of the triangle's plane (`|n·d| < min_cos·|n|`: the hit would run off along the
//! ray), when `t` is not finite and positive, or when a barycentric lies outside [−0.5, 1.5] (the
//! triangle moved far since the BVH was built).

use crate::model::batch::Batch;
use crate::model::Real;
use crate::refine::field::RefineGeom;
use glam::DVec3;

/// A valid sub-sample re-intersected with its triangle's current plane (module docs).
#[derive(Clone, Copy, Debug)]
pub struct RayHit {
    /// Index into the batch's `[N*S]` sub-samples.
    pub sample: usize,
    pub tri: [u32; 3],
    pub o: DVec3,
    pub d: DVec3,
    pub t: f64,
    /// Barycentrics of the triangle's three corners.
    pub beta: [f64; 3],
    /// `(b − a) × (c − a)`, unnormalised.
    pub n: DVec3,
    /// The moved triangle's edges `b − a`, `c − a` (for the anchored gradient).
    pub e: [DVec3; 2],
}

/// Möller–Trumbore of the ray `o + t·d` with triangle (a, b, c) (f64, as `raycast/bvh.rs`):
/// `(t, [1−u−v, u, v], n)`, or `None` when the ray is within `acos(min_cos)` of the plane, `t`
/// is not finite and positive, or a barycentric is outside [−0.5, 1.5].
pub fn intersect(
    o: DVec3,
    d: DVec3,
    [a, b, c]: [DVec3; 3],
    min_cos: f64,
) -> Option<(f64, [f64; 3], DVec3)> {
    let (e1, e2) = (b - a, c - a);
    let p = d.cross(e2);
    let det = e1.dot(p);
    let n = e1.cross(e2);
    let nn = n.length();
    // det = −n·d.
    if nn.is_nan() || nn <= 0.0 || det.abs() < min_cos * nn {
        return None;
    }
    let inv = 1.0 / det;
    let s = o - a;
    let q = s.cross(e1);
    let (t, u, v) = (e2.dot(q) * inv, s.dot(p) * inv, d.dot(q) * inv);
    let beta = [1.0 - u - v, u, v];
    if !(t.is_finite() && t > 0.0) || beta.iter().any(|&x| !(-0.5..=1.5).contains(&x)) {
        return None;
    }
    Some((t, beta, n))
}

/// Sub-samples per parallel work item of [`reintersect_batch`] (a constant, SPEC §5.2; every
/// sub-sample is independent, so it does not enter the results).
pub const HIT_CHUNK: usize = 1024;

/// Move every valid sub-sample of `batch` (which must carry triangle ids) to its triangle's plane
/// at offsets `theta` (indexed by vertex; only the batch's triangles' vertices are read) and
/// return the hits that carry a vertex gradient, in batch order (module docs). The ray of a
/// sub-sample runs from `origin(pixel)` (local frame) through its position in `batch`; a
/// sub-sample [`intersect`] rejects keeps its position.
pub fn reintersect_batch(
    geom: &RefineGeom,
    theta: &[f64],
    batch: &mut Batch,
    origin: &(dyn Fn(usize) -> DVec3 + Sync),
    min_cos: f64,
) -> Vec<RayHit> {
    reintersect_with(geom, theta, None, batch, origin, min_cos)
}

/// [`reintersect_batch`] for `[model.refine] anchored = true`: the batch's positions are on the
/// training mesh (an anchored tracer's), so the ray of a sub-sample runs from `origin(pixel)`
/// through the point with the batch's barycentrics (`bary`) on the mesh at offsets `traced` (the
/// mesh the rays were cast against); the position written is the *training* mesh's point with the
/// barycentrics of the hit on the mesh at `theta`.
pub fn reintersect_batch_anchored(
    geom: &RefineGeom,
    theta: &[f64],
    traced: &[f64],
    batch: &mut Batch,
    origin: &(dyn Fn(usize) -> DVec3 + Sync),
    min_cos: f64,
) -> Vec<RayHit> {
    reintersect_with(geom, theta, Some(traced), batch, origin, min_cos)
}

fn reintersect_with(
    geom: &RefineGeom,
    theta: &[f64],
    traced: Option<&[f64]>,
    batch: &mut Batch,
    origin: &(dyn Fn(usize) -> DVec3 + Sync),
    min_cos: f64,
) -> Vec<RayHit> {
    use rayon::prelude::*;
    let s = batch.samples_per_pixel();
    let extent = geom.norm.extent;
    let (valid, triangle, positions) = (&batch.valid, &batch.triangle, &batch.positions);
    let bary = &batch.bary;
    let out: Vec<Option<(DVec3, RayHit)>> = (0..positions.len())
        .into_par_iter()
        .with_min_len(HIT_CHUNK)
        .map(|j| {
            if valid[j] == 0 {
                return None;
            }
            let tri = geom.triangles[triangle[j] as usize];
            let o = origin(j / s);
            let x = match traced {
                None => (DVec3::from_array(positions[j]) - DVec3::splat(0.5)) * extent,
                Some(tr) => {
                    let [u, v] = bary[j];
                    let w = [1.0 - u - v, u, v];
                    (0..3).fold(DVec3::ZERO, |acc, c| {
                        let i = tri[c] as usize;
                        acc + geom.position(i, tr[i]) * w[c]
                    })
                }
            };
            let d = (x - o).normalize_or_zero();
            let v = tri.map(|i| geom.position(i as usize, theta[i as usize]));
            let (t, beta, n) = intersect(o, d, v, min_cos)?;
            let hit = match traced {
                None => o + d * t,
                // The training mesh's point with the moved hit's barycentrics.
                Some(_) => (0..3).fold(DVec3::ZERO, |acc, c| {
                    acc + geom.position(tri[c] as usize, 0.0) * beta[c]
                }),
            };
            let p = hit / extent + DVec3::splat(0.5);
            Some((
                p,
                RayHit {
                    sample: j,
                    tri,
                    o,
                    d,
                    t,
                    beta,
                    n,
                    e: [v[1] - v[0], v[2] - v[0]],
                },
            ))
        })
        .collect();
    let mut hits = Vec::with_capacity(out.len());
    for (p, h) in out.into_iter().flatten() {
        batch.positions[h.sample] = p.to_array();
        hits.push(h);
    }
    hits
}

/// ∂L/∂x in local units of sub-sample `j` from `grad.batch.positions` (x_n = x / extent + 0.5 per
/// axis).
#[inline]
fn local_gradient<R: Real>(d_positions: &[R], j: usize, inv_extent: DVec3) -> DVec3 {
    let k = j * 3;
    DVec3::new(
        d_positions[k].to_f64(),
        d_positions[k + 1].to_f64(),
        d_positions[k + 2].to_f64(),
    ) * inv_extent
}

/// `∂L/∂θ` of the hits (module docs), accumulated into `d_theta` in hit order. `d_positions` is
/// `grad.batch.positions` `[N*S*3]`; `inv_extent` the normalisation's `1/extent` per axis.
pub fn hits_backward<R: Real>(
    geom: &RefineGeom,
    hits: &[RayHit],
    d_positions: &[R],
    d_theta: &mut [f64],
) {
    let inv_extent = DVec3::ONE / geom.norm.extent;
    for h in hits {
        let g = local_gradient(d_positions, h.sample, inv_extent);
        for (i, v) in plane_hit_chain(geom, h.tri, h.beta, h.n, h.d, g) {
            d_theta[i as usize] += v;
        }
    }
}

/// `∂L/∂θ` of anchored hits ([`reintersect_batch_anchored`]; docs/geometry.md §3), accumulated
/// into `d_theta` in hit order. The query point is `x₀ = Σ β_k v⁰_k` (training mesh), so
/// `∂L/∂β` restricted to the plane is `c = J₀ᵀ g` (`J₀ = [b⁰−a⁰, c⁰−a⁰]`), pulled back to the
/// moved plane as `h = J G⁻¹ c` (`J` the moved edges, `G = JᵀJ`). Moving the material point of
/// the hit by `w = Σ β_k δv_k` moves the hit in the plane by `δt·d − w` with
/// `δt = n·w / n·d`, so `∂L/∂w = (h·d) n / (n·d) − h` and `∂L/∂θ_k = s β_k m_k · ∂L/∂w`.
pub fn hits_backward_anchored<R: Real>(
    geom: &RefineGeom,
    hits: &[RayHit],
    d_positions: &[R],
    d_theta: &mut [f64],
) {
    let inv_extent = DVec3::ONE / geom.norm.extent;
    for h in hits {
        let g = local_gradient(d_positions, h.sample, inv_extent);
        let base = h.tri.map(|i| geom.base[i as usize]);
        let c = [g.dot(base[1] - base[0]), g.dot(base[2] - base[0])];
        let [e1, e2] = h.e;
        let (g11, g12, g22) = (e1.dot(e1), e1.dot(e2), e2.dot(e2));
        let det = g11 * g22 - g12 * g12;
        if det.is_nan() || det <= 0.0 {
            continue;
        }
        // G⁻¹ c, then h = J (G⁻¹ c).
        let y = [
            (g22 * c[0] - g12 * c[1]) / det,
            (g11 * c[1] - g12 * c[0]) / det,
        ];
        let hv = e1 * y[0] + e2 * y[1];
        let dw = h.n * (hv.dot(h.d) / h.n.dot(h.d)) - hv;
        for c in 0..3 {
            let i = h.tri[c] as usize;
            d_theta[i] += geom.scale * h.beta[c] * dw.dot(geom.normals[i]);
        }
    }
}

/// `∂L/∂θ_k = s · (g·d) · β_k · (n·m_k) / (n·d)` for the three corners of a plane hit (SPEC §4.11):
/// `g` = ∂L/∂x (local units) of the hit `o + t·d` of triangle `tri` (barycentrics `beta`,
/// unnormalised normal `n`).
#[inline]
pub fn plane_hit_chain(
    geom: &RefineGeom,
    tri: [u32; 3],
    beta: [f64; 3],
    n: DVec3,
    d: DVec3,
    g: DVec3,
) -> [(u32, f64); 3] {
    let along = geom.scale * g.dot(d) / n.dot(d);
    std::array::from_fn(|c| {
        let i = tri[c];
        (i, along * beta[c] * n.dot(geom.normals[i as usize]))
    })
}
