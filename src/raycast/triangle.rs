//! Watertight ray–triangle intersection (Woop, Benthin, Wald 2013, "Watertight Ray/Triangle
//! Intersection", JCGT 2(1); the formulation of pbrt-v4 §6.5.3), on f32 vertices in the local
//! frame of SPEC §4.1. Two-sided.
//!
//! Algorithm: translate the vertices by the ray origin, permute the axes so that the ray's largest
//! direction component becomes z (`kz`; `kx = kz+1 mod 3`, `ky = kx+1 mod 3`), shear x and y so the
//! ray becomes the +z axis, and evaluate the three 2-D edge functions
//! `e0 = p1×p2`, `e1 = p2×p0`, `e2 = p0×p1` (z component of the cross products). The ray hits when
//! no two edge functions have opposite signs. An edge shared by two triangles evaluates to exactly
//! the negated value in both (IEEE products commute and `a-b = -(b-a)` exactly), so a ray can
//! never pass between two triangles that share the edge: this is what "watertight" means. When an
//! edge function is exactly 0 in f32 the three are recomputed in f64 from the same f32 sheared
//! coordinates (products of two f32 are exact in f64, so the sign is exact).
//!
//! Numerics: the accepted region deviates from the exact triangle by the rounding of the
//! translated/sheared coordinates, ≈ a few f32 ulps of the distance `|p - o|` (≈ 8·2⁻²⁴·D
//! laterally). The BVH pads its boxes to cover this (see `bvh.rs`). The returned `t` is the f32
//! distance `t_scaled / det` along the (unit) direction; the tracer refines it in f64.
//!
//! Both the scalar [`intersect`] and the lane-wise [`intersect_lanes`] compute identical f32
//! values per lane (same operations, no FMA), so packet and single-ray traversal agree bit for
//! bit.

// Index loops over lanes read best; `!(t > 0)` also rejects NaN on purpose.
#![allow(clippy::needless_range_loop, clippy::neg_cmp_op_on_partial_ord)]

use super::packet::{Packet, MAX_LANES};
use super::simd::{Lanes, Mask};

/// Index of the largest |component| (first one on ties), pbrt's `MaxComponentIndex(Abs(d))`.
#[inline]
pub fn dominant_axis(d: [f32; 3]) -> usize {
    let a = d.map(f32::abs);
    if a[0] >= a[1] && a[0] >= a[2] {
        0
    } else if a[1] >= a[2] {
        1
    } else {
        2
    }
}

/// The axis permutation `[kx, ky, kz]` for a dominant axis `kz`.
#[inline]
pub fn permutation(kz: usize) -> [usize; 3] {
    let kx = (kz + 1) % 3;
    let ky = (kx + 1) % 3;
    [kx, ky, kz]
}

/// A ray prepared for the watertight test.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct WatertightRay {
    /// Origin in the local frame (f32).
    pub origin: [f32; 3],
    /// `[kx, ky, kz]`.
    pub k: [usize; 3],
    /// Shear `[Sx, Sy, Sz] = [-d_kx/d_kz, -d_ky/d_kz, 1/d_kz]`.
    pub shear: [f32; 3],
}

/// The dominant axis `kz` of a ray the watertight test accepts: `None` when the direction is
/// zero or a coordinate is not finite.
#[inline]
pub fn ray_axis(origin: [f32; 3], dir: [f32; 3]) -> Option<usize> {
    if !dir.iter().chain(origin.iter()).all(|x| x.is_finite()) {
        return None;
    }
    let kz = dominant_axis(dir);
    (dir[kz] != 0.0).then_some(kz)
}

impl WatertightRay {
    /// `None` when the direction is zero or not finite.
    pub fn new(origin: [f32; 3], dir: [f32; 3]) -> Option<WatertightRay> {
        let k = permutation(ray_axis(origin, dir)?);
        let dz = dir[k[2]];
        Some(WatertightRay {
            origin,
            k,
            shear: [-dir[k[0]] / dz, -dir[k[1]] / dz, 1.0 / dz],
        })
    }
}

/// A hit of the f32 test: distance and barycentrics `[b0, b1, b2]` (weights of v0, v1, v2).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TriHit {
    pub t: f32,
    pub b: [f32; 3],
}

/// Scalar watertight test. Returns every hit with `t > 0` (no `t_max`: the caller keeps the
/// lexicographically smallest `(t, triangle id)`, which makes the closest hit independent of the
/// order triangles are visited in).
#[inline]
pub fn intersect(r: &WatertightRay, v: &[[f32; 3]; 3]) -> Option<TriHit> {
    let [kx, ky, kz] = r.k;
    let [sx, sy, sz] = r.shear;
    let o = r.origin;
    // Translate, permute, shear (x and y only; z is scaled later, pbrt order).
    let p = |i: usize| {
        let x = v[i][kx] - o[kx];
        let y = v[i][ky] - o[ky];
        let z = v[i][kz] - o[kz];
        (x + sx * z, y + sy * z, z)
    };
    let (p0x, p0y, p0z) = p(0);
    let (p1x, p1y, p1z) = p(1);
    let (p2x, p2y, p2z) = p(2);
    // Edge functions.
    let e0 = p1x * p2y - p1y * p2x;
    let e1 = p2x * p0y - p2y * p0x;
    let e2 = p0x * p1y - p0y * p1x;
    let (z0, z1, z2) = (p0z * sz, p1z * sz, p2z * sz);
    if e0 == 0.0 || e1 == 0.0 || e2 == 0.0 {
        return intersect_f64_edges([p0x, p0y, p1x, p1y, p2x, p2y], [z0, z1, z2]);
    }
    if (e0 < 0.0 || e1 < 0.0 || e2 < 0.0) && (e0 > 0.0 || e1 > 0.0 || e2 > 0.0) {
        return None;
    }
    let det = e0 + e1 + e2;
    if det == 0.0 {
        return None;
    }
    let ts = e0 * z0 + e1 * z1 + e2 * z2;
    if (det < 0.0 && ts >= 0.0) || (det > 0.0 && ts <= 0.0) {
        return None;
    }
    let t = ts / det;
    if !(t > 0.0) {
        return None;
    }
    Some(TriHit {
        t,
        b: [e0 / det, e1 / det, e2 / det],
    })
}

/// The f64 fallback: edge functions, determinant and scaled distance in f64 from the f32 sheared
/// coordinates `[p0x, p0y, p1x, p1y, p2x, p2y]` and scaled z values.
#[cold]
#[inline(never)]
fn intersect_f64_edges(p: [f32; 6], z: [f32; 3]) -> Option<TriHit> {
    let [p0x, p0y, p1x, p1y, p2x, p2y] = p.map(|x| x as f64);
    let e0 = p1x * p2y - p1y * p2x;
    let e1 = p2x * p0y - p2y * p0x;
    let e2 = p0x * p1y - p0y * p1x;
    if (e0 < 0.0 || e1 < 0.0 || e2 < 0.0) && (e0 > 0.0 || e1 > 0.0 || e2 > 0.0) {
        return None;
    }
    let det = e0 + e1 + e2;
    if det == 0.0 {
        return None;
    }
    let [z0, z1, z2] = z.map(|x| x as f64);
    let ts = e0 * z0 + e1 * z1 + e2 * z2;
    if (det < 0.0 && ts >= 0.0) || (det > 0.0 && ts <= 0.0) {
        return None;
    }
    let t = (ts / det) as f32;
    if !(t > 0.0) {
        return None;
    }
    Some(TriHit {
        t,
        b: [(e0 / det) as f32, (e1 / det) as f32, (e2 / det) as f32],
    })
}

/// `L::N` rays of a packet sharing the permutation `k`, in SIMD lanes.
#[derive(Clone, Copy)]
pub struct RayLanes<'a, L: Lanes> {
    pub k: [usize; 3],
    /// Origin, permuted: `[o_kx, o_ky, o_kz]` per lane.
    pub o: [L; 3],
    /// Shear `[Sx, Sy, Sz]` per lane (computed exactly as [`WatertightRay::new`] does).
    pub s: [L; 3],
    /// The packet and the first lane (for the rare f64 fallback, which rebuilds the scalar ray).
    pub packet: &'a Packet,
    pub base: usize,
    /// The permuted origin when every lane has the same one (camera rays): the vertex
    /// translation is then one scalar subtraction instead of one per lane (same IEEE result).
    pub shared: [f32; 3],
}

impl<'a, L: Lanes> RayLanes<'a, L> {
    /// Lanes `base .. base + L::N` of `p`; all must be valid rays ([`WatertightRay::new`] is
    /// `Some`) with the permutation `k`.
    #[inline(always)]
    pub fn new(p: &'a Packet, base: usize, k: [usize; 3]) -> RayLanes<'a, L> {
        let lanes = |x: &[f32; MAX_LANES]| L::load(&x[base..]);
        let o = [
            lanes(&p.origin[k[0]]),
            lanes(&p.origin[k[1]]),
            lanes(&p.origin[k[2]]),
        ];
        // [-d_kx/d_kz, -d_ky/d_kz, 1/d_kz]: negation is exact, so (-1·d)/dz is -d/dz bit for bit.
        let dz = lanes(&p.dir[k[2]]);
        let m1 = L::splat(-1.0);
        let s = [
            (m1 * lanes(&p.dir[k[0]])) / dz,
            (m1 * lanes(&p.dir[k[1]])) / dz,
            L::splat(1.0) / dz,
        ];
        let shared = [
            p.origin[k[0]][base],
            p.origin[k[1]][base],
            p.origin[k[2]][base],
        ];
        RayLanes {
            k,
            o,
            s,
            packet: p,
            base,
            shared,
        }
    }
}

/// A vertex translated, permuted and sheared into each lane's ray space. `SHARED`: all lanes
/// have the origin `r.shared`.
#[inline(always)]
fn vertex_lanes<L: Lanes, const SHARED: bool>(r: &RayLanes<'_, L>, v: [f32; 3]) -> (L, L, L) {
    let [kx, ky, kz] = r.k;
    let (x, y, z) = if SHARED {
        (
            L::splat(v[kx] - r.shared[0]),
            L::splat(v[ky] - r.shared[1]),
            L::splat(v[kz] - r.shared[2]),
        )
    } else {
        (
            L::splat(v[kx]) - r.o[0],
            L::splat(v[ky]) - r.o[1],
            L::splat(v[kz]) - r.o[2],
        )
    };
    (x + r.s[0] * z, y + r.s[1] * z, z)
}

/// SIMD watertight test of one triangle against `L::N` rays: returns the lanes that hit (among
/// `active`) and their distances. Lane `i` equals `intersect` of its `WatertightRay` exactly.
#[inline(always)]
pub fn intersect_lanes<L: Lanes, const SHARED: bool>(
    r: &RayLanes<'_, L>,
    v: &[[f32; 3]; 3],
    active: u32,
) -> (u32, L) {
    let (p0x, p0y, p0z) = vertex_lanes::<L, SHARED>(r, v[0]);
    let (p1x, p1y, p1z) = vertex_lanes::<L, SHARED>(r, v[1]);
    let (p2x, p2y, p2z) = vertex_lanes::<L, SHARED>(r, v[2]);
    let sz = r.s[2];
    let e0 = p1x * p2y - p1y * p2x;
    let e1 = p2x * p0y - p2y * p0x;
    let e2 = p0x * p1y - p0y * p1x;
    let zero = L::splat(0.0);
    let neg = e0.lt(zero).or(e1.lt(zero)).or(e2.lt(zero)).bits();
    let pos = e0.gt(zero).or(e1.gt(zero)).or(e2.gt(zero)).bits();
    // An f32 edge function has the exact sign or is 0 (rounding is monotonic), so mixed
    // nonzero signs are a certain miss even when another edge function is 0.
    let mut cand = active & !(neg & pos);
    if cand == 0 {
        return (0, zero);
    }
    // Lanes with an edge function exactly 0 are redone in the scalar path (f64 edges).
    let redo = e0.eq(zero).or(e1.eq(zero)).or(e2.eq(zero)).bits() & cand;
    let det = e0 + e1 + e2;
    let z0 = p0z * sz;
    let z1 = p1z * sz;
    let z2 = p2z * sz;
    let ts = e0 * z0 + e1 * z1 + e2 * z2;
    // Same sign and both nonzero (ts·det > 0 could overflow, so compare signs).
    let dpos = det.gt(zero).bits();
    let dneg = det.lt(zero).bits();
    let tpos = ts.gt(zero).bits();
    let tneg = ts.lt(zero).bits();
    cand &= (dpos & tpos) | (dneg & tneg);
    if cand | redo == 0 {
        return (0, zero);
    }
    let t = ts / det;
    cand &= t.gt(zero).bits();
    if redo != 0 {
        return fallback(r, v, cand & !redo, t, redo);
    }
    (cand, t)
}

#[cold]
#[inline(never)]
fn fallback<L: Lanes>(
    r: &RayLanes<'_, L>,
    v: &[[f32; 3]; 3],
    cand: u32,
    t: L,
    redo: u32,
) -> (u32, L) {
    let mut ta = [0.0f32; MAX_LANES];
    t.store(&mut ta);
    let mut hits = cand;
    for i in 0..L::N {
        if redo >> i & 1 != 0 {
            let (o, d) = (r.packet.origin(r.base + i), r.packet.dir(r.base + i));
            let ray = WatertightRay::new(o, d).expect("lanes hold valid rays");
            if let Some(h) = intersect(&ray, v) {
                hits |= 1 << i;
                ta[i] = h.t;
            }
        }
    }
    (hits, L::load(&ta))
}
