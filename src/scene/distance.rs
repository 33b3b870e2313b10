//! Point-to-surface distance between two triangle meshes (geometry error of a proxy against the
//! true surface, `xscale bench-geometry`, docs/geometry.md).
//!
//! [`SurfaceIndex`] answers "distance from p to the closest point of the mesh" exactly with a
//! bounding volume hierarchy (obvhs builds the tree; its boxes are recomputed in f64): a
//! depth-first search, nearer child first, that skips every box farther than the best triangle
//! found so far. Its cost follows the number of triangles near the answer, not the size of the
//! scene: a point far from every triangle, a mesh with huge triangles far outside the scene, or
//! a tiny patch in a large bounding box cost a few dozen boxes. (Until 2026-11 the index was a
//! uniform grid searched in shells of growing radius: a point whose closest triangle was many
//! cells away visited every cell between, and a huge triangle was stored in every cell its box
//! overlapped, so `mesh-distance` on COLMAP's Poisson mesh of `prepare_synth` — a 60 m patch of
//! 5 cm triangles against a 200 m scene — did not finish.) The closest point on a triangle is
//! Ericson's region test (Real-Time Collision Detection, 5.1.5), in f64.
//!
//! [`surface_distance`] samples points uniformly by area on mesh A (a counter-based RNG,
//! `Purpose::Test`-free: the stream is [`DIST_STREAM`] of `Purpose::Synth`, so the samples are a
//! pure function of the mesh and the count) and reports the mean and RMS of their distances to
//! mesh B. Points are measured in parallel, each independently, and summed in order (f64), so the
//! figures do not depend on the thread count.

use super::Mesh;
use crate::rng::{uniform_f64, Purpose};
use glam::DVec3;
use rayon::prelude::*;

/// `a` of the counter-based RNG for the area samples.
pub const DIST_STREAM: u64 = 0xD157;

/// Closest point to `p` on triangle (a, b, c) (Ericson 5.1.5; degenerate triangles work).
pub fn closest_on_triangle(p: DVec3, a: DVec3, b: DVec3, c: DVec3) -> DVec3 {
    let (ab, ac, ap) = (b - a, c - a, p - a);
    let (d1, d2) = (ab.dot(ap), ac.dot(ap));
    if d1 <= 0.0 && d2 <= 0.0 {
        return a;
    }
    let bp = p - b;
    let (d3, d4) = (ab.dot(bp), ac.dot(bp));
    if d3 >= 0.0 && d4 <= d3 {
        return b;
    }
    let vc = d1 * d4 - d3 * d2;
    if vc <= 0.0 && d1 >= 0.0 && d3 <= 0.0 {
        return a + ab * (d1 / (d1 - d3));
    }
    let cp = p - c;
    let (d5, d6) = (ab.dot(cp), ac.dot(cp));
    if d6 >= 0.0 && d5 <= d6 {
        return c;
    }
    let vb = d5 * d2 - d1 * d6;
    if vb <= 0.0 && d2 >= 0.0 && d6 <= 0.0 {
        return a + ac * (d2 / (d2 - d6));
    }
    let va = d3 * d6 - d5 * d4;
    if va <= 0.0 && (d4 - d3) >= 0.0 && (d5 - d6) >= 0.0 {
        return b + (c - b) * ((d4 - d3) / ((d4 - d3) + (d5 - d6)));
    }
    let denom = va + vb + vc;
    if denom == 0.0 || !denom.is_finite() {
        // Degenerate (collinear) triangle: the closest of its three edges.
        let seg = |s: DVec3, e: DVec3| {
            let d = e - s;
            let l = d.length_squared();
            let t = if l > 0.0 {
                ((p - s).dot(d) / l).clamp(0.0, 1.0)
            } else {
                0.0
            };
            s + d * t
        };
        return [seg(a, b), seg(b, c), seg(c, a)]
            .into_iter()
            .min_by(|x, y| {
                (p - *x)
                    .length_squared()
                    .total_cmp(&(p - *y).length_squared())
            })
            .unwrap_or(a);
    }
    let v = vb / denom;
    let w = vc / denom;
    a + ab * v + ac * w
}

/// Below this many triangles per leaf the BVH stops splitting (obvhs' `max_prims_per_leaf`).
const LEAF_TRIANGLES: u32 = 4;

/// A node of [`SurfaceIndex`]: the exact f64 box of its triangles, and either its two children
/// (`count == 0`: `nodes[first]`, `nodes[first + 1]`) or its triangles (`tris[first..first + count]`).
#[derive(Clone, Copy, Debug)]
struct Node {
    lo: DVec3,
    hi: DVec3,
    first: u32,
    count: u32,
}

/// A mesh's triangles in a bounding volume hierarchy for closest-point queries (module docs).
pub struct SurfaceIndex<'a> {
    mesh: &'a Mesh,
    nodes: Vec<Node>,
    /// Triangle ids in leaf order.
    tris: Vec<u32>,
    /// Largest |coordinate| of the mesh: the scale of the rounding slack in the pruning test.
    scale: f64,
}

/// Squared distance from `p` to the box `[lo, hi]` (0 inside).
fn box_distance2(p: DVec3, lo: DVec3, hi: DVec3) -> f64 {
    (lo - p).max(p - hi).max(DVec3::ZERO).length_squared()
}

impl<'a> SurfaceIndex<'a> {
    /// The BVH of `mesh`: obvhs builds the tree (its `fast_build` preset, leaves of at most
    /// [`LEAF_TRIANGLES`], on f32 vertices moved to the bounding box's centre); every box is
    /// then recomputed here in f64 from the mesh's own vertices, so the pruning below is exact
    /// whatever tree obvhs makes.
    pub fn new(mesh: &'a Mesh) -> SurfaceIndex<'a> {
        let mut s = SurfaceIndex {
            mesh,
            nodes: Vec::new(),
            tris: Vec::new(),
            scale: 0.0,
        };
        // Triangles with a non-finite vertex have no closest point (the mesh readers refuse
        // them; a NaN box would also break obvhs' build): they are left out.
        let kept: Vec<u32> = (0..mesh.triangles.len() as u32)
            .filter(|&t| {
                mesh.triangles[t as usize]
                    .iter()
                    .all(|&i| mesh.vertices[i as usize].is_finite())
            })
            .collect();
        if kept.is_empty() {
            return s;
        }
        let (lo, hi) = kept.iter().flat_map(|&t| mesh.triangles[t as usize]).fold(
            (DVec3::INFINITY, DVec3::NEG_INFINITY),
            |(a, b), i| {
                let v = mesh.vertices[i as usize];
                (a.min(v), b.max(v))
            },
        );
        s.scale = lo.abs().max(hi.abs()).max_element();
        let center = 0.5 * (lo + hi);
        // f32 only shapes the tree (clamped so no coordinate overflows); the boxes are f64.
        let local = |i: u32| {
            let v =
                (mesh.vertices[i as usize] - center).clamp(DVec3::splat(-1e30), DVec3::splat(1e30));
            glam::Vec3A::new(v.x as f32, v.y as f32, v.z as f32)
        };
        let otris: Vec<obvhs::triangle::Triangle> = kept
            .iter()
            .map(|&t| {
                let t = mesh.triangles[t as usize];
                obvhs::triangle::Triangle {
                    v0: local(t[0]),
                    v1: local(t[1]),
                    v2: local(t[2]),
                }
            })
            .collect();
        let params = obvhs::BvhBuildParams {
            max_prims_per_leaf: LEAF_TRIANGLES,
            ..obvhs::BvhBuildParams::fast_build()
        };
        let bvh = obvhs::bvh2::builder::build_bvh2_from_tris(
            &otris,
            params,
            &mut std::time::Duration::default(),
        );
        drop(otris);
        // Same layout as obvhs' nodes; boxes bottom-up (children before their parent).
        s.tris = bvh
            .primitive_indices
            .iter()
            .map(|&k| kept[k as usize])
            .collect();
        assert!(
            s.tris.len() == kept.len(),
            "BVH leaves hold {} triangles, the mesh has {}",
            s.tris.len(),
            kept.len()
        );
        s.nodes = bvh
            .nodes
            .iter()
            .map(|n| Node {
                lo: DVec3::INFINITY,
                hi: DVec3::NEG_INFINITY,
                first: n.first_index,
                count: n.prim_count,
            })
            .collect();
        let mut stack = vec![(0usize, false)];
        while let Some((k, children_done)) = stack.pop() {
            let n = s.nodes[k];
            if n.count > 0 {
                let (mut a, mut b) = (DVec3::INFINITY, DVec3::NEG_INFINITY);
                for &t in &s.tris[n.first as usize..(n.first + n.count) as usize] {
                    for i in mesh.triangles[t as usize] {
                        let v = mesh.vertices[i as usize];
                        (a, b) = (a.min(v), b.max(v));
                    }
                }
                (s.nodes[k].lo, s.nodes[k].hi) = (a, b);
            } else if children_done {
                let (l, r) = (s.nodes[n.first as usize], s.nodes[n.first as usize + 1]);
                (s.nodes[k].lo, s.nodes[k].hi) = (l.lo.min(r.lo), l.hi.max(r.hi));
            } else {
                stack.push((k, true));
                stack.push((n.first as usize, false));
                stack.push((n.first as usize + 1, false));
            }
        }
        s
    }

    /// Distance from `p` to the closest point of the mesh (+inf for a mesh without triangles,
    /// and for a non-finite `p`).
    pub fn distance(&self, p: DVec3) -> f64 {
        self.distance_within(p, f64::INFINITY)
    }

    /// [`SurfaceIndex::distance`] when it is at most `cap`, else +inf: boxes farther than `cap`
    /// are not opened, so a point far from the mesh costs a few boxes.
    pub fn distance_within(&self, p: DVec3, cap: f64) -> f64 {
        self.search(p, cap).0
    }

    /// The distance (as [`SurfaceIndex::distance_within`]) and the work it took: boxes measured
    /// plus triangles measured.
    fn search(&self, p: DVec3, cap: f64) -> (f64, usize) {
        if self.nodes.is_empty() || !p.is_finite() {
            return (f64::INFINITY, 0);
        }
        // Rounding slack of the box and triangle distances (both within a few ulps of the
        // coordinates): a box is skipped only when it is farther than the best triangle by more
        // than that, so no triangle whose computed distance could be the smallest is skipped and
        // the result is the brute-force minimum, whatever the tree.
        let slack = 1e-9 * (self.scale + p.abs().max_element());
        let reach = |best2: f64| {
            let b = best2.sqrt().min(cap) + slack;
            b * b
        };
        let mut best2 = f64::INFINITY;
        let mut work = 1;
        let root = &self.nodes[0];
        let d0 = box_distance2(p, root.lo, root.hi);
        let mut stack: Vec<(u32, f64)> = Vec::with_capacity(64);
        if d0 <= reach(best2) {
            stack.push((0, d0));
        }
        while let Some((k, d2)) = stack.pop() {
            if d2 > reach(best2) {
                continue;
            }
            let n = &self.nodes[k as usize];
            if n.count > 0 {
                for &t in &self.tris[n.first as usize..(n.first + n.count) as usize] {
                    let [a, b, c] =
                        self.mesh.triangles[t as usize].map(|i| self.mesh.vertices[i as usize]);
                    best2 = best2.min((closest_on_triangle(p, a, b, c) - p).length_squared());
                    work += 1;
                }
                continue;
            }
            let (l, r) = (n.first, n.first + 1);
            let dl = box_distance2(p, self.nodes[l as usize].lo, self.nodes[l as usize].hi);
            let dr = box_distance2(p, self.nodes[r as usize].lo, self.nodes[r as usize].hi);
            work += 2;
            // The nearer child is popped first.
            let (near, far) = if dl <= dr {
                ((l, dl), (r, dr))
            } else {
                ((r, dr), (l, dl))
            };
            let lim = reach(best2);
            if far.1 <= lim {
                stack.push(far);
            }
            if near.1 <= lim {
                stack.push(near);
            }
        }
        let best = best2.sqrt();
        (if best <= cap { best } else { f64::INFINITY }, work)
    }
}

/// Mean and RMS distance of area samples of one mesh to another.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize)]
pub struct DistanceStats {
    pub samples: usize,
    pub mean: f64,
    pub rms: f64,
    pub max: f64,
}

/// `n` points uniform by area on `mesh` (deterministic: a pure function of the mesh and `n`).
pub fn area_samples(mesh: &Mesh, n: usize) -> Vec<DVec3> {
    let mut cum = Vec::with_capacity(mesh.triangles.len());
    let mut total = 0.0;
    for t in &mesh.triangles {
        let [a, b, c] = t.map(|i| mesh.vertices[i as usize]);
        total += 0.5 * (b - a).cross(c - a).length();
        cum.push(total);
    }
    if total <= 0.0 || !total.is_finite() {
        return Vec::new();
    }
    (0..n as u64)
        .into_par_iter()
        .map(|k| {
            let r = |b: u64| uniform_f64(0, Purpose::Synth, DIST_STREAM, 3 * k + b);
            let x = r(0) * total;
            let t = cum.partition_point(|&c| c <= x).min(cum.len() - 1);
            let [a, b, c] = mesh.triangles[t].map(|i| mesh.vertices[i as usize]);
            let (mut u, mut v) = (r(1), r(2));
            if u + v > 1.0 {
                (u, v) = (1.0 - u, 1.0 - v);
            }
            a + (b - a) * u + (c - a) * v
        })
        .collect()
}

/// Distances from `n` area samples of `from` to the surface `to` (module docs).
pub fn surface_distance(from: &Mesh, to: &SurfaceIndex, n: usize) -> DistanceStats {
    let pts = area_samples(from, n);
    let d: Vec<f64> = pts.par_iter().map(|&p| to.distance(p)).collect();
    let (mut s, mut s2, mut mx) = (0.0f64, 0.0f64, 0.0f64);
    for &x in &d {
        s += x;
        s2 += x * x;
        mx = mx.max(x);
    }
    let m = d.len().max(1) as f64;
    DistanceStats {
        samples: d.len(),
        mean: s / m,
        rms: (s2 / m).sqrt(),
        max: mx,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn brute(mesh: &Mesh, p: DVec3) -> f64 {
        mesh.triangles
            .iter()
            .map(|t| {
                let [a, b, c] = t.map(|i| mesh.vertices[i as usize]);
                (closest_on_triangle(p, a, b, c) - p).length()
            })
            .fold(f64::INFINITY, f64::min)
    }

    #[test]
    fn index_equals_brute_force() {
        // A bumpy grid and a box, like a synthetic scene.
        let n = 12;
        let mut m = Mesh::default();
        for j in 0..=n {
            for i in 0..=n {
                let (x, y) = (i as f64, j as f64);
                m.vertices
                    .push(DVec3::new(x, y, (0.7 * x).sin() * 0.8 + (0.3 * y).cos()));
            }
        }
        for j in 0..n {
            for i in 0..n {
                let k = |a: usize, b: usize| (b * (n + 1) + a) as u32;
                m.triangles.push([k(i, j), k(i + 1, j), k(i + 1, j + 1)]);
                m.triangles.push([k(i, j), k(i + 1, j + 1), k(i, j + 1)]);
            }
        }
        crate::synth::surface::push_box(
            &mut m.vertices,
            &mut m.triangles,
            DVec3::new(3.0, 4.0, -1.0),
            DVec3::new(7.5, 6.0, 5.0),
        );
        let idx = SurfaceIndex::new(&m);
        for k in 0..500u64 {
            let r = |b| crate::rng::uniform_f64(9, Purpose::Test, k, b);
            let p = DVec3::new(-3.0 + 18.0 * r(0), -3.0 + 18.0 * r(1), -4.0 + 12.0 * r(2));
            let (a, b) = (idx.distance(p), brute(&m, p));
            assert_eq!(a, b, "{p}: index {a} brute {b}");
            // Capped: the same distance up to the cap, +inf beyond it (also for points far
            // outside the grid).
            for cap in [0.05, 0.5, 2.0] {
                for q in [p, p * 40.0] {
                    let (got, b) = (idx.distance_within(q, cap), brute(&m, q));
                    let want = if b <= cap { b } else { f64::INFINITY };
                    assert_eq!(got, want, "{q} cap {cap}: index {got} brute {b}");
                }
            }
        }
        // A mesh against itself: zero; shifted by 0.25 along z on a flat mesh: 0.25.
        let s = surface_distance(&m, &idx, 2000);
        assert!(s.rms < 1e-9, "{s:?}");
    }

    /// What made `mesh-distance` hang on COLMAP's Poisson mesh: points far from a fine patch,
    /// and huge triangles far outside the scene. The answer is the brute-force one and its cost
    /// (boxes and triangles measured) stays small; the uniform grid this index replaced visited
    /// every cell between a point and its closest triangle (millions here) and stored each huge
    /// triangle in every cell.
    #[test]
    fn far_points_and_huge_triangles_stay_cheap() {
        // A 1 × 1 patch of 0.01-sized triangles (20,000) ...
        let n = 100;
        let mut m = Mesh::default();
        for j in 0..=n {
            for i in 0..=n {
                let (x, y) = (i as f64 / n as f64, j as f64 / n as f64);
                m.vertices
                    .push(DVec3::new(x, y, 0.05 * (9.0 * x).sin() * y));
            }
        }
        for j in 0..n {
            for i in 0..n {
                let k = |a: usize, b: usize| (b * (n + 1) + a) as u32;
                m.triangles.push([k(i, j), k(i + 1, j), k(i + 1, j + 1)]);
                m.triangles.push([k(i, j), k(i + 1, j + 1), k(i, j + 1)]);
            }
        }
        // ... and three huge triangles 5,000 away (a Poisson surface's far-off sheet).
        for (k, z) in [5e3, -6e3, 7e3].into_iter().enumerate() {
            let b = m.vertices.len() as u32;
            let s = 2e4 * (k + 1) as f64;
            m.vertices.extend([
                DVec3::new(-s, -s, z),
                DVec3::new(s, -s, z + 10.0),
                DVec3::new(0.0, s, z),
            ]);
            m.triangles.push([b, b + 1, b + 2]);
        }
        let idx = SurfaceIndex::new(&m);
        let mut total = 0;
        let queries = 300u64;
        for k in 0..queries {
            let r = |b| crate::rng::uniform_f64(11, Purpose::Test, k, b);
            // Near the patch, 10-1000 patch sizes away, and near the huge triangles.
            let dir = DVec3::new(r(0) - 0.5, r(1) - 0.5, r(2) - 0.5).normalize_or_zero();
            let p = match k % 3 {
                0 => DVec3::new(r(3), r(4), 0.04 * r(5) - 0.02),
                1 => DVec3::splat(0.5) + dir * 10f64.powf(1.0 + 2.0 * r(3)),
                _ => DVec3::new(4e3 * r(3), 4e3 * r(4), 5e3 + 100.0 * (r(5) - 0.5)),
            };
            let (d, work) = idx.search(p, f64::INFINITY);
            assert_eq!(d, brute(&m, p), "{p}");
            assert!(work <= 1000, "{p}: {work} boxes and triangles measured");
            total += work;
        }
        assert!(
            total as f64 / (queries as f64) <= 150.0,
            "{} boxes and triangles per query",
            total as f64 / queries as f64
        );
    }

    /// Random triangle soups of every awkward kind, against the brute-force minimum (obvhs'
    /// own tests build random soups the same way): points, needles, repeated vertices, duplicate
    /// triangles, sizes from 1e-9 to 1e6, far from the origin (rounding), non-finite vertices
    /// (left out), and query points on vertices, edges, inside, far away and non-finite.
    #[test]
    fn degenerate_soups_equal_brute_force() {
        let brute_finite = |m: &Mesh, p: DVec3| {
            if !p.is_finite() {
                return f64::INFINITY;
            }
            m.triangles
                .iter()
                .filter(|t| t.iter().all(|&i| m.vertices[i as usize].is_finite()))
                .map(|t| {
                    let [a, b, c] = t.map(|i| m.vertices[i as usize]);
                    (closest_on_triangle(p, a, b, c) - p).length()
                })
                .fold(f64::INFINITY, f64::min)
        };
        // Empty meshes, and meshes whose every triangle has a non-finite vertex.
        let empty = Mesh::default();
        assert_eq!(
            SurfaceIndex::new(&empty).distance(DVec3::ONE),
            f64::INFINITY
        );
        let nan = Mesh {
            vertices: vec![DVec3::ZERO, DVec3::X, DVec3::new(f64::NAN, 0.0, 1.0)],
            triangles: vec![[0, 1, 2]],
        };
        assert_eq!(SurfaceIndex::new(&nan).distance(DVec3::ONE), f64::INFINITY);
        for soup in 0..24u64 {
            let r =
                |k: u64, b: u64| crate::rng::uniform_f64(13, Purpose::Test, soup * 100_000 + k, b);
            let origin = match soup % 4 {
                0 => DVec3::ZERO,
                1 => DVec3::new(1e5, -2e5, 3e4),
                2 => DVec3::splat(-7e6),
                _ => DVec3::new(0.0, 0.0, 1e8),
            };
            let size = [1e-9, 1e-3, 1.0, 1e3][(soup / 4 % 4) as usize];
            let n = [1usize, 2, 7, 40, 300, 1000][(soup % 6) as usize];
            let mut m = Mesh::default();
            for t in 0..n as u64 {
                let rv = |b: u64| DVec3::new(r(t, b) - 0.5, r(t, b + 1) - 0.5, r(t, b + 2) - 0.5);
                let c = origin + rv(0) * size * 10.0;
                let s = size * 10f64.powf(3.0 * r(t, 3) - 2.0);
                let (a, b, d) = (c + rv(4) * s, c + rv(7) * s, c + rv(10) * s);
                let tri = match t % 8 {
                    0 => [c, c, c],                    // a point
                    1 => [a, b, a + (b - a) * 0.3],    // collinear
                    2 => [a, a, b],                    // two equal vertices
                    3 => [a, b, d + rv(13) * 1e3 * s], // long sliver
                    _ => [a, b, d],
                };
                let base = m.vertices.len() as u32;
                m.vertices.extend(tri);
                m.triangles.push([base, base + 1, base + 2]);
                if t % 11 == 0 {
                    m.triangles.push([base, base + 1, base + 2]); // duplicate
                }
                if t % 97 == 5 {
                    // A vertex shared with a non-finite one: that triangle is left out.
                    m.vertices.push(DVec3::new(f64::INFINITY, 0.0, f64::NAN));
                    m.triangles.push([base, base + 1, base + 3]);
                }
            }
            let idx = SurfaceIndex::new(&m);
            for k in 0..200u64 {
                let rk = |b| r(1_000_000 + k, b);
                let v = m.vertices[(rk(0) * m.vertices.len() as f64) as usize % m.vertices.len()];
                let w = m.vertices[(rk(1) * m.vertices.len() as f64) as usize % m.vertices.len()];
                let jitter = DVec3::new(rk(2) - 0.5, rk(3) - 0.5, rk(4) - 0.5);
                let p = match k % 6 {
                    0 => v,                             // on a vertex
                    1 => v + (w - v) * rk(5),           // between two vertices
                    2 => origin + jitter * size * 20.0, // in the soup
                    3 => origin + jitter * size * 1e4,  // far
                    4 => v + jitter * size * 1e-6,      // just off a vertex
                    _ => [
                        DVec3::NAN,
                        DVec3::INFINITY,
                        DVec3::new(0.0, f64::NEG_INFINITY, 1.0),
                        v,
                    ][(k / 6 % 4) as usize],
                };
                let want = brute_finite(&m, p);
                assert_eq!(idx.distance(p), want, "soup {soup}, {p}");
                let cap = want * [0.5, 1.0, 2.0][(k % 3) as usize];
                let capped = if want <= cap { want } else { f64::INFINITY };
                assert_eq!(
                    idx.distance_within(p, cap),
                    capped,
                    "soup {soup}, {p}, cap {cap}"
                );
            }
        }
    }

    #[test]
    fn flat_offset_distance() {
        let plane = |z: f64| Mesh {
            vertices: vec![
                DVec3::new(0.0, 0.0, z),
                DVec3::new(4.0, 0.0, z),
                DVec3::new(4.0, 4.0, z),
                DVec3::new(0.0, 4.0, z),
            ],
            triangles: vec![[0, 1, 2], [0, 2, 3]],
        };
        let (a, b) = (plane(0.0), plane(0.25));
        let idx = SurfaceIndex::new(&a);
        let s = surface_distance(&b, &idx, 1000);
        assert_eq!(s.samples, 1000);
        assert!(
            (s.mean - 0.25).abs() < 1e-12 && (s.rms - 0.25).abs() < 1e-12,
            "{s:?}"
        );
    }
}
