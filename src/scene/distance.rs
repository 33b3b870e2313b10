//! Point-to-surface distance between two triangle meshes (geometry error of a proxy against the
//! true surface, `xscale bench-geometry`, docs/geometry.md).
//!
//! [`SurfaceIndex`] bins a mesh's triangles in a uniform grid of cubic cells (each triangle in
//! every cell its bounding box overlaps) and answers "distance from p to the closest point of
//! the mesh" exactly: cells are visited in shells of growing Chebyshev radius around p's cell
//! and the search stops once the best distance found is not above the distance to the next
//! shell. The closest point on a triangle is Ericson's region test (Real-Time Collision
//! Detection, 5.1.5), in f64.
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

/// A mesh's triangles binned in a uniform grid (module docs).
pub struct SurfaceIndex<'a> {
    mesh: &'a Mesh,
    lo: DVec3,
    cell: f64,
    dims: [usize; 3],
    /// CSR: triangles of cell k are `items[start[k]..start[k+1]]`.
    start: Vec<u32>,
    items: Vec<u32>,
}

impl<'a> SurfaceIndex<'a> {
    /// Bin `mesh` with cells of about twice its mean edge length (at most ~2²² cells).
    pub fn new(mesh: &'a Mesh) -> SurfaceIndex<'a> {
        let (lo, hi) = mesh.bbox();
        let span = (hi - lo).max(DVec3::splat(1e-12));
        // Summed per fixed chunk, then in chunk order: the same bits on any thread count.
        let edge: f64 = mesh
            .triangles
            .par_chunks(1 << 14)
            .map(|ts| {
                ts.iter()
                    .map(|t| {
                        let [a, b, c] = t.map(|i| mesh.vertices[i as usize]);
                        (b - a).length() + (c - b).length() + (a - c).length()
                    })
                    .sum::<f64>()
            })
            .collect::<Vec<f64>>()
            .iter()
            .sum();
        let mean_edge = edge / (3 * mesh.triangles.len()).max(1) as f64;
        let mut cell = (2.0 * mean_edge).max(span.max_element() * 1e-6);
        // Keep the grid at most ~4M cells.
        while (span.x / cell + 1.0) * (span.y / cell + 1.0) * (span.z / cell + 1.0) > 4.2e6 {
            cell *= 1.25;
        }
        let dims = [
            (span.x / cell).floor() as usize + 1,
            (span.y / cell).floor() as usize + 1,
            (span.z / cell).floor() as usize + 1,
        ];
        let mut s = SurfaceIndex {
            mesh,
            lo,
            cell,
            dims,
            start: Vec::new(),
            items: Vec::new(),
        };
        let n_cells = dims[0] * dims[1] * dims[2];
        let mut count = vec![0u32; n_cells + 1];
        let ranges: Vec<([usize; 3], [usize; 3])> = mesh
            .triangles
            .par_iter()
            .map(|t| {
                let [a, b, c] = t.map(|i| mesh.vertices[i as usize]);
                (s.cell_of(a.min(b).min(c)), s.cell_of(a.max(b).max(c)))
            })
            .collect();
        for (c0, c1) in &ranges {
            for z in c0[2]..=c1[2] {
                for y in c0[1]..=c1[1] {
                    for x in c0[0]..=c1[0] {
                        count[s.index([x, y, z]) + 1] += 1;
                    }
                }
            }
        }
        for k in 0..n_cells {
            count[k + 1] += count[k];
        }
        let mut fill = count.clone();
        let mut items = vec![0u32; count[n_cells] as usize];
        for (t, (c0, c1)) in ranges.iter().enumerate() {
            for z in c0[2]..=c1[2] {
                for y in c0[1]..=c1[1] {
                    for x in c0[0]..=c1[0] {
                        let k = s.index([x, y, z]);
                        items[fill[k] as usize] = t as u32;
                        fill[k] += 1;
                    }
                }
            }
        }
        s.start = count;
        s.items = items;
        s
    }

    fn cell_of(&self, p: DVec3) -> [usize; 3] {
        let q = (p - self.lo) / self.cell;
        [0, 1, 2].map(|a| (q[a].floor().max(0.0) as usize).min(self.dims[a] - 1))
    }

    fn index(&self, c: [usize; 3]) -> usize {
        (c[2] * self.dims[1] + c[1]) * self.dims[0] + c[0]
    }

    /// Distance from `p` to the closest point of the mesh (+inf for a mesh without triangles).
    pub fn distance(&self, p: DVec3) -> f64 {
        self.distance_within(p, f64::INFINITY)
    }

    /// [`SurfaceIndex::distance`] when it is at most `cap`, else +inf: the search stops at
    /// `cap`, so a point far from the mesh costs a few cells instead of the whole grid.
    pub fn distance_within(&self, p: DVec3, cap: f64) -> f64 {
        if self.mesh.triangles.is_empty() {
            return f64::INFINITY;
        }
        let grid_hi = self.lo + DVec3::from(self.dims.map(|d| d as f64)) * self.cell;
        if (self.lo - p).max(p - grid_hi).max(DVec3::ZERO).length() > cap {
            return f64::INFINITY;
        }
        let c = self.cell_of(p);
        // Distance from p to the outside of its (clamped) cell's box: shell r's cells are at
        // least this far plus (r-1) cells away.
        let q = (p - self.lo) / self.cell;
        let inside = [0, 1, 2]
            .map(|a| (q[a] - c[a] as f64).min(c[a] as f64 + 1.0 - q[a]).max(0.0))
            .into_iter()
            .fold(f64::INFINITY, f64::min)
            * self.cell;
        let mut best2 = f64::INFINITY;
        let max_r = *self.dims.iter().max().unwrap_or(&1);
        for r in 0..=max_r {
            if r > 0 {
                let reach = inside + (r - 1) as f64 * self.cell;
                if best2 <= reach * reach || reach > cap {
                    break;
                }
            }
            let lo = c.map(|v| v.saturating_sub(r));
            let hi = [0, 1, 2].map(|a| (c[a] + r).min(self.dims[a] - 1));
            for z in lo[2]..=hi[2] {
                for y in lo[1]..=hi[1] {
                    for x in lo[0]..=hi[0] {
                        let on_shell = [x, y, z]
                            .iter()
                            .zip(&c)
                            .any(|(&v, &cv)| v.abs_diff(cv) == r);
                        if !on_shell {
                            continue;
                        }
                        let k = self.index([x, y, z]);
                        for &t in &self.items[self.start[k] as usize..self.start[k + 1] as usize] {
                            let [a, b, cc] = self.mesh.triangles[t as usize]
                                .map(|i| self.mesh.vertices[i as usize]);
                            let d2 = (closest_on_triangle(p, a, b, cc) - p).length_squared();
                            best2 = best2.min(d2);
                        }
                    }
                }
            }
        }
        let best = best2.sqrt();
        if best <= cap {
            best
        } else {
            f64::INFINITY
        }
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
    fn grid_search_equals_brute_force() {
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
            assert!(
                (a - b).abs() <= 1e-12 * (1.0 + b),
                "{p}: grid {a} brute {b}"
            );
            // Capped: the same distance up to the cap, +inf beyond it (also for points far
            // outside the grid).
            for cap in [0.05, 0.5, 2.0] {
                for q in [p, p * 40.0] {
                    let (got, b) = (idx.distance_within(q, cap), brute(&m, q));
                    let want = if b <= cap { b } else { f64::INFINITY };
                    assert!(
                        got == want || (got - want).abs() <= 1e-12 * (1.0 + b),
                        "{q} cap {cap}: grid {got} brute {b}"
                    );
                }
            }
        }
        // A mesh against itself: zero; shifted by 0.25 along z on a flat mesh: 0.25.
        let s = surface_distance(&m, &idx, 2000);
        assert!(s.rms < 1e-9, "{s:?}");
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
