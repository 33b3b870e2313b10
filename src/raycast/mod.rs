//! Ray casting against the fixed mesh (SPEC §1, §2, §8): a BVH built once per scene in the
//! local frame of SPEC §4.1, a watertight ray–triangle test, γ×γ rays per pixel, and the
//! compacted per-view sample cache.
//!
//! Files: `triangle.rs` (watertight ray–triangle test), `bvh.rs` ([`Tracer`]: obvhs-built BVH,
//! packet traversal, f64 refinement), `cast.rs` (γ² rays per pixel, view direction, footprint),
//! `cache.rs` ([`SampleCache`]), `stream.rs` ([`RayStream`]: hit maps + photos, rays cast per
//! batch), `packet.rs` ([`Packet`]: rays traced together), `simd.rs` (4- and 8-lane f32 vectors: SSE,
//! AVX behind runtime detection).

pub mod bvh;
pub mod cache;
pub mod cast;
pub mod consistency;
pub mod footprint;
pub mod meshes;
pub mod packet;
mod simd;
pub mod stream;
pub mod triangle;

pub use bvh::{BuildPreset, Packet, Scratch, Tracer, MAX_LANES};
pub use cache::{CacheEvent, CachedView, SampleCache};
pub use cast::{
    cast_rows, cast_rows_into, cast_view, sub_offset, PixelSummary, SubSample, ViewCast,
};
pub use footprint::FootprintHist;
pub use stream::{HitMap, RayStream, StreamView, Targets};

use crate::scene::Mesh;
use glam::DVec3;

/// Closest hit of one ray.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Hit {
    /// Distance along the (unit) ray direction.
    pub t: f64,
    /// Index into `Mesh::triangles`.
    pub triangle: u32,
    /// Barycentrics of vertices 1 and 2 (vertex 0 has 1-u-v).
    pub u: f64,
    pub v: f64,
}

/// Reference closest-hit by testing every triangle (f64, Möller–Trumbore). For tests; O(triangles)
/// per ray. `Hit::t` is in units of `|dir|`.
pub fn brute_force_closest_hit(mesh: &Mesh, origin: DVec3, dir: DVec3) -> Option<Hit> {
    let mut best: Option<Hit> = None;
    for (i, tri) in mesh.triangles.iter().enumerate() {
        let [a, b, c] = tri.map(|k| mesh.vertices[k as usize]);
        let (e1, e2) = (b - a, c - a);
        let p = dir.cross(e2);
        let det = e1.dot(p);
        if det.abs() < 1e-300 {
            continue;
        }
        let inv = 1.0 / det;
        let s = origin - a;
        let u = s.dot(p) * inv;
        if !(0.0..=1.0).contains(&u) {
            continue;
        }
        let q = s.cross(e1);
        let v = dir.dot(q) * inv;
        if v < 0.0 || u + v > 1.0 {
            continue;
        }
        let t = e2.dot(q) * inv;
        if t > 0.0 && best.is_none_or(|h| t < h.t) {
            best = Some(Hit {
                t,
                triangle: i as u32,
                u,
                v,
            });
        }
    }
    best
}

pub(crate) use crate::memhint::advise as advise_huge_pages;
