//! The fine "true" surface of a synthetic scene and its exact ray intersection.
//!
//! The surface is a terrain heightfield (a regular grid of `n × n` cells, each split into two
//! triangles along its (0,0)–(1,1) diagonal) plus axis-aligned box buildings standing on it.
//! Ground truth is rendered by intersecting rays with *this* description directly — a 2-D DDA
//! over the grid (two levels: blocks of [`BLOCK`]² cells with their height range, then cells)
//! and a slab test per box — so it shares no code with the BVH under test in `raycast`.
//! [`TrueSurface::to_mesh`] emits exactly the triangles that are intersected (terrain triangles
//! plus five faces per box; box bottoms are buried in the terrain and omitted).
//!
//! Numerics: everything is f64. The triangle test is Möller–Trumbore with a barycentric
//! tolerance of 1e-10 (relative) so that rays through shared edges and vertices cannot slip
//! between neighbouring triangles; the cell/block culling uses a height margin of 1e-9·extent.
//! World frame: z up, metres; cameras use OpenCV axes (see `cameras.rs`).

use crate::scene::Mesh;
use glam::{DVec2, DVec3};

/// Cells per block side in the two-level DDA (a constant of the code).
pub const BLOCK: usize = 8;

/// Barycentric slack of the triangle test (see the file comment).
const BARY_EPS: f64 = 1e-10;

/// Terrain heightfield over `[origin, origin + n·cell]²`.
#[derive(Clone, Debug)]
pub struct Heightfield {
    pub origin: DVec2,
    pub cell: f64,
    /// Cells per side (a multiple of [`BLOCK`]).
    pub n: usize,
    /// `(n+1)²` vertex heights, row-major: index `j·(n+1) + i` is the vertex at
    /// `origin + (i·cell, j·cell)`.
    pub heights: Vec<f64>,
    /// Per block `(min, max)` height of its vertices, row-major over `(n/BLOCK)²` blocks.
    block_range: Vec<(f64, f64)>,
    pub min_height: f64,
    pub max_height: f64,
}

impl Heightfield {
    pub fn new(origin: DVec2, cell: f64, n: usize, heights: Vec<f64>) -> Heightfield {
        assert!(n % BLOCK == 0 && heights.len() == (n + 1) * (n + 1));
        let nb = n / BLOCK;
        let mut block_range = vec![(f64::INFINITY, f64::NEG_INFINITY); nb * nb];
        for bj in 0..nb {
            for bi in 0..nb {
                let r = &mut block_range[bj * nb + bi];
                for j in bj * BLOCK..=(bj + 1) * BLOCK {
                    for i in bi * BLOCK..=(bi + 1) * BLOCK {
                        let h = heights[j * (n + 1) + i];
                        r.0 = r.0.min(h);
                        r.1 = r.1.max(h);
                    }
                }
            }
        }
        let min_height = heights.iter().cloned().fold(f64::INFINITY, f64::min);
        let max_height = heights.iter().cloned().fold(f64::NEG_INFINITY, f64::max);
        Heightfield {
            origin,
            cell,
            n,
            heights,
            block_range,
            min_height,
            max_height,
        }
    }

    #[inline]
    pub fn vertex(&self, i: usize, j: usize) -> DVec3 {
        DVec3::new(
            self.origin.x + i as f64 * self.cell,
            self.origin.y + j as f64 * self.cell,
            self.heights[j * (self.n + 1) + i],
        )
    }

    /// Side length of the covered square.
    pub fn size(&self) -> f64 {
        self.n as f64 * self.cell
    }

    /// The two triangles of cell (i, j): (00, 10, 11) and (00, 11, 01).
    #[inline]
    fn cell_triangles(&self, i: usize, j: usize) -> [[DVec3; 3]; 2] {
        let v00 = self.vertex(i, j);
        let v10 = self.vertex(i + 1, j);
        let v01 = self.vertex(i, j + 1);
        let v11 = self.vertex(i + 1, j + 1);
        [[v00, v10, v11], [v00, v11, v01]]
    }

    /// Height of the triangulated surface at (x, y) (clamped to the covered square).
    pub fn height_at(&self, x: f64, y: f64) -> f64 {
        let gx = ((x - self.origin.x) / self.cell).clamp(0.0, self.n as f64);
        let gy = ((y - self.origin.y) / self.cell).clamp(0.0, self.n as f64);
        let i = (gx.floor() as usize).min(self.n - 1);
        let j = (gy.floor() as usize).min(self.n - 1);
        let (fx, fy) = (gx - i as f64, gy - j as f64);
        let h = |a: usize, b: usize| self.heights[(j + b) * (self.n + 1) + i + a];
        if fx >= fy {
            h(0, 0) + fx * (h(1, 0) - h(0, 0)) + fy * (h(1, 1) - h(1, 0))
        } else {
            h(0, 0) + fy * (h(0, 1) - h(0, 0)) + fx * (h(1, 1) - h(0, 1))
        }
    }

    /// Closest terrain hit with `t ∈ [tmin, tmax]`: `(t, unit geometric normal facing up)`.
    pub fn trace(&self, o: DVec3, d: DVec3, tmin: f64, tmax: f64) -> Option<(f64, DVec3)> {
        let margin = 1e-9 * self.size().max(1.0);
        let lo = DVec3::new(self.origin.x, self.origin.y, self.min_height - margin);
        let hi = DVec3::new(
            self.origin.x + self.size(),
            self.origin.y + self.size(),
            self.max_height + margin,
        );
        let (t0, t1) = slab(o, d, lo, hi)?;
        let (t0, t1) = (t0.max(tmin), t1.min(tmax));
        if t0 > t1 {
            return None;
        }
        let nb = self.n / BLOCK;
        let o2 = DVec2::new(o.x, o.y);
        let d2 = DVec2::new(d.x, d.y);
        let z_range = |ta: f64, tb: f64| {
            let (za, zb) = (o.z + d.z * ta, o.z + d.z * tb);
            (za.min(zb) - margin, za.max(zb) + margin)
        };
        let blocks = SquareGrid {
            origin: self.origin,
            cell: self.cell * BLOCK as f64,
            n: nb,
        };
        dda(blocks, o2, d2, t0, t1, |bi, bj, ta, tb| {
            let (bmin, bmax) = self.block_range[bj * nb + bi];
            let (zlo, zhi) = z_range(ta, tb);
            if zhi < bmin || zlo > bmax {
                return None;
            }
            let borig = self.origin + DVec2::new(bi as f64, bj as f64) * self.cell * BLOCK as f64;
            let cells = SquareGrid {
                origin: borig,
                cell: self.cell,
                n: BLOCK,
            };
            dda(cells, o2, d2, ta, tb, |ci, cj, _, _| {
                let (i, j) = (bi * BLOCK + ci, bj * BLOCK + cj);
                let mut best: Option<(f64, DVec3)> = None;
                for tri in self.cell_triangles(i, j) {
                    if let Some(t) = intersect_triangle(o, d, &tri) {
                        if t >= tmin && t <= tmax && best.is_none_or(|b| t < b.0) {
                            let n = (tri[1] - tri[0]).cross(tri[2] - tri[0]).normalize();
                            best = Some((t, n));
                        }
                    }
                }
                best
            })
        })
    }
}

/// A box building `[lo, hi]`; `lo.z` is below the terrain under its footprint.
#[derive(Clone, Debug, PartialEq, serde::Serialize)]
pub struct Building {
    pub lo: [f64; 3],
    pub hi: [f64; 3],
    /// Base colour (linear-ish RGB in `[0,1]`) of walls and roof.
    pub wall_colour: [f64; 3],
    pub roof_colour: [f64; 3],
}

impl Building {
    pub fn lo(&self) -> DVec3 {
        DVec3::from_array(self.lo)
    }
    pub fn hi(&self) -> DVec3 {
        DVec3::from_array(self.hi)
    }
    /// Is `p` inside the box (with a margin)?
    pub fn contains(&self, p: DVec3, margin: f64) -> bool {
        let (lo, hi) = (self.lo() - margin, self.hi() + margin);
        p.cmpge(lo).all() && p.cmple(hi).all()
    }
}

/// What a ray hit (selects the material in `shade.rs`).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum SurfaceKind {
    Terrain,
    /// A wall of building `b`, facing along axis 0 (x) or 1 (y).
    Wall {
        building: u32,
        axis: u8,
    },
    Roof {
        building: u32,
    },
}

#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Hit {
    pub t: f64,
    pub pos: DVec3,
    /// Unit geometric normal, facing the ray origin.
    pub normal: DVec3,
    pub kind: SurfaceKind,
}

/// Terrain + buildings.
#[derive(Clone, Debug)]
pub struct TrueSurface {
    pub terrain: Heightfield,
    pub buildings: Vec<Building>,
}

impl TrueSurface {
    /// Closest hit along `o + t·d` (d unit) with `t ∈ (tmin, tmax]`.
    pub fn trace(&self, o: DVec3, d: DVec3, tmin: f64, tmax: f64) -> Option<Hit> {
        let mut best: Option<Hit> = None;
        let mut limit = tmax;
        for (b, bd) in self.buildings.iter().enumerate() {
            if let Some((t, axis)) = box_entry(o, d, bd.lo(), bd.hi()) {
                if t > tmin && t <= limit {
                    let mut normal = DVec3::ZERO;
                    normal[axis] = -d[axis].signum();
                    let kind = if axis == 2 {
                        SurfaceKind::Roof { building: b as u32 }
                    } else {
                        SurfaceKind::Wall {
                            building: b as u32,
                            axis: axis as u8,
                        }
                    };
                    limit = t;
                    best = Some(Hit {
                        t,
                        pos: o + d * t,
                        normal,
                        kind,
                    });
                }
            }
        }
        if let Some((t, n)) = self.terrain.trace(o, d, tmin, limit) {
            if best.is_none_or(|h| t < h.t) {
                let n = if n.dot(d) > 0.0 { -n } else { n };
                best = Some(Hit {
                    t,
                    pos: o + d * t,
                    normal: n,
                    kind: SurfaceKind::Terrain,
                });
            }
        }
        best
    }

    /// Does any building block the ray `o + t·d`, t > 0? (Shadow rays; terrain self-shadowing
    /// is not modelled: the hills are gentle and the sun high, so `n·l` carries their shading.)
    pub fn blocked_by_building(&self, o: DVec3, d: DVec3) -> bool {
        self.buildings
            .iter()
            .any(|b| slab(o, d, b.lo(), b.hi()).is_some_and(|(t0, t1)| t1 > 0.0 && t0 <= t1))
    }

    /// The triangles [`TrueSurface::trace`] intersects: terrain (2 per cell) then 5 faces
    /// (2 triangles each) per building.
    pub fn to_mesh(&self) -> Mesh {
        let hf = &self.terrain;
        let n = hf.n;
        let mut vertices = Vec::with_capacity((n + 1) * (n + 1) + 8 * self.buildings.len());
        for j in 0..=n {
            for i in 0..=n {
                vertices.push(hf.vertex(i, j));
            }
        }
        let mut triangles = Vec::with_capacity(2 * n * n + 10 * self.buildings.len());
        let idx = |i: usize, j: usize| (j * (n + 1) + i) as u32;
        for j in 0..n {
            for i in 0..n {
                triangles.push([idx(i, j), idx(i + 1, j), idx(i + 1, j + 1)]);
                triangles.push([idx(i, j), idx(i + 1, j + 1), idx(i, j + 1)]);
            }
        }
        for b in &self.buildings {
            push_box(&mut vertices, &mut triangles, b.lo(), b.hi());
        }
        Mesh {
            vertices,
            triangles,
        }
    }
}

/// Append an open-bottomed box (4 walls + top, outward counter-clockwise) to a mesh.
pub fn push_box(vertices: &mut Vec<DVec3>, triangles: &mut Vec<[u32; 3]>, lo: DVec3, hi: DVec3) {
    let base = vertices.len() as u32;
    for k in 0..8u32 {
        vertices.push(DVec3::new(
            if k & 1 != 0 { hi.x } else { lo.x },
            if k & 2 != 0 { hi.y } else { lo.y },
            if k & 4 != 0 { hi.z } else { lo.z },
        ));
    }
    // Corner k: bit0 = x, bit1 = y, bit2 = z.
    let quads: [[u32; 4]; 5] = [
        [0, 1, 5, 4], // y = lo (normal -y)
        [1, 3, 7, 5], // x = hi (+x)
        [3, 2, 6, 7], // y = hi (+y)
        [2, 0, 4, 6], // x = lo (-x)
        [4, 5, 7, 6], // top (+z)
    ];
    for q in quads {
        triangles.push([base + q[0], base + q[1], base + q[2]]);
        triangles.push([base + q[0], base + q[2], base + q[3]]);
    }
}

/// Möller–Trumbore, two-sided; returns t (may be negative: the caller filters).
#[inline]
pub fn intersect_triangle(o: DVec3, d: DVec3, tri: &[DVec3; 3]) -> Option<f64> {
    let e1 = tri[1] - tri[0];
    let e2 = tri[2] - tri[0];
    let p = d.cross(e2);
    let det = e1.dot(p);
    if det.abs() < 1e-300 {
        return None;
    }
    let inv = 1.0 / det;
    let s = o - tri[0];
    let u = s.dot(p) * inv;
    if !(-BARY_EPS..=1.0 + BARY_EPS).contains(&u) {
        return None;
    }
    let q = s.cross(e1);
    let v = d.dot(q) * inv;
    if v < -BARY_EPS || u + v > 1.0 + BARY_EPS {
        return None;
    }
    Some(e2.dot(q) * inv)
}

/// Ray–AABB slab test: the parameter interval `[t0, t1]` inside the box (t may be negative).
pub fn slab(o: DVec3, d: DVec3, lo: DVec3, hi: DVec3) -> Option<(f64, f64)> {
    let (mut t0, mut t1) = (f64::NEG_INFINITY, f64::INFINITY);
    for a in 0..3 {
        if d[a] == 0.0 {
            if o[a] < lo[a] || o[a] > hi[a] {
                return None;
            }
        } else {
            let (ta, tb) = ((lo[a] - o[a]) / d[a], (hi[a] - o[a]) / d[a]);
            t0 = t0.max(ta.min(tb));
            t1 = t1.min(ta.max(tb));
        }
    }
    (t0 <= t1).then_some((t0, t1))
}

/// Entry of a ray into a box from outside: `(t, axis of the entered face)`; `None` if it misses
/// or starts inside.
fn box_entry(o: DVec3, d: DVec3, lo: DVec3, hi: DVec3) -> Option<(f64, usize)> {
    let (mut t0, mut t1, mut axis) = (f64::NEG_INFINITY, f64::INFINITY, 0usize);
    for a in 0..3 {
        if d[a] == 0.0 {
            if o[a] < lo[a] || o[a] > hi[a] {
                return None;
            }
        } else {
            let (ta, tb) = ((lo[a] - o[a]) / d[a], (hi[a] - o[a]) / d[a]);
            let (near, far) = (ta.min(tb), ta.max(tb));
            if near > t0 {
                t0 = near;
                axis = a;
            }
            t1 = t1.min(far);
        }
    }
    (t0 <= t1 && t0 > 0.0).then_some((t0, axis))
}

/// An `n × n` grid of square cells of side `cell`, corner `origin` (the xy plane).
#[derive(Clone, Copy)]
struct SquareGrid {
    origin: DVec2,
    cell: f64,
    n: usize,
}

/// 2-D DDA over the square cells of `grid`, visiting in ray
/// order the cells the ray `o + t·d` crosses for `t ∈ [t0, t1]`; `f(i, j, t_enter, t_exit)`
/// stops the walk by returning `Some`. Indices are clamped at the start (the entry point may
/// round just outside the grid).
fn dda<R>(
    grid: SquareGrid,
    o: DVec2,
    d: DVec2,
    t0: f64,
    t1: f64,
    mut f: impl FnMut(usize, usize, f64, f64) -> Option<R>,
) -> Option<R> {
    let SquareGrid { origin, cell, n } = grid;
    let p = o + d * t0;
    let last = n as i64 - 1;
    let mut ix = (((p.x - origin.x) / cell).floor() as i64).clamp(0, last);
    let mut iy = (((p.y - origin.y) / cell).floor() as i64).clamp(0, last);
    let axis = |o: f64, d: f64, org: f64, i: i64| -> (i64, f64, f64) {
        if d > 0.0 {
            (1, (org + (i + 1) as f64 * cell - o) / d, cell / d)
        } else if d < 0.0 {
            (-1, (org + i as f64 * cell - o) / d, -cell / d)
        } else {
            (0, f64::INFINITY, f64::INFINITY)
        }
    };
    let (sx, mut tx, dx) = axis(o.x, d.x, origin.x, ix);
    let (sy, mut ty, dy) = axis(o.y, d.y, origin.y, iy);
    let mut t = t0;
    loop {
        let t_next = tx.min(ty).min(t1);
        if let Some(r) = f(ix as usize, iy as usize, t, t_next) {
            return Some(r);
        }
        if t_next >= t1 {
            return None;
        }
        if tx < ty {
            ix += sx;
            t = tx;
            tx += dx;
        } else {
            iy += sy;
            t = ty;
            ty += dy;
        }
        if ix < 0 || iy < 0 || ix > last || iy > last {
            return None;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn bumpy(n: usize) -> Heightfield {
        let mut h = Vec::new();
        for j in 0..=n {
            for i in 0..=n {
                let (x, y) = (i as f64, j as f64);
                h.push(
                    (x * 0.37).sin() * 2.0
                        + (y * 0.23).cos() * 1.5
                        + ((i * 7 + j * 13) % 5) as f64 * 0.1,
                );
            }
        }
        Heightfield::new(DVec2::new(-8.0, -8.0), 16.0 / n as f64, n, h)
    }

    /// The DDA traversal agrees with testing every triangle of the mesh (an independent brute
    /// force), including on rays aimed exactly at grid vertices and edges.
    #[test]
    fn dda_matches_brute_force() {
        let hf = bumpy(16);
        let surf = TrueSurface {
            terrain: hf.clone(),
            buildings: vec![],
        };
        let mesh = surf.to_mesh();
        let mut n_hit = 0;
        for k in 0..400u64 {
            let r = |b| crate::rng::uniform_f64(3, crate::rng::Purpose::Test, k, b);
            let o = DVec3::new(-12.0 + 24.0 * r(0), -12.0 + 24.0 * r(1), 6.0 + 10.0 * r(2));
            // Aim at a vertex, an edge midpoint or a random point.
            let (i, j) = ((r(3) * 16.0) as usize, (r(4) * 16.0) as usize);
            let target = match k % 3 {
                0 => hf.vertex(i, j),
                1 => (hf.vertex(i, j) + hf.vertex(i + 1, j + 1)) * 0.5,
                _ => DVec3::new(-8.0 + 16.0 * r(5), -8.0 + 16.0 * r(6), -1.0),
            };
            let d = (target - o).normalize();
            let fast = hf.trace(o, d, 0.0, f64::INFINITY);
            let mut slow: Option<f64> = None;
            for t in &mesh.triangles {
                let tri = t.map(|v| mesh.vertices[v as usize]);
                if let Some(t) = intersect_triangle(o, d, &tri) {
                    if t >= 0.0 && slow.is_none_or(|s| t < s) {
                        slow = Some(t);
                    }
                }
            }
            match (fast, slow) {
                (Some((a, _)), Some(b)) => {
                    n_hit += 1;
                    assert!((a - b).abs() < 1e-9, "ray {k}: {a} vs {b}")
                }
                (None, None) => {}
                other => panic!("ray {k}: {other:?}"),
            }
        }
        assert!(n_hit > 300);
        // Vertical rays.
        let p = hf.trace(DVec3::new(0.3, 0.7, 50.0), DVec3::NEG_Z, 0.0, f64::INFINITY);
        assert!((50.0 - p.unwrap().0 - hf.height_at(0.3, 0.7)).abs() < 1e-9);
    }

    #[test]
    fn boxes_hit_and_shadow() {
        let hf = bumpy(8);
        let b = Building {
            lo: [-1.0, -1.0, -5.0],
            hi: [1.0, 2.0, 10.0],
            wall_colour: [0.5; 3],
            roof_colour: [0.5; 3],
        };
        let s = TrueSurface {
            terrain: hf,
            buildings: vec![b],
        };
        let h = s
            .trace(DVec3::new(0.0, 0.0, 20.0), DVec3::NEG_Z, 0.0, f64::INFINITY)
            .unwrap();
        assert_eq!(h.kind, SurfaceKind::Roof { building: 0 });
        assert!((h.t - 10.0).abs() < 1e-12 && h.normal == DVec3::Z);
        let h = s
            .trace(DVec3::new(-5.0, 0.5, 5.0), DVec3::X, 0.0, f64::INFINITY)
            .unwrap();
        assert_eq!(
            h.kind,
            SurfaceKind::Wall {
                building: 0,
                axis: 0
            }
        );
        assert!((h.t - 4.0).abs() < 1e-12 && h.normal == DVec3::NEG_X);
        assert!(s.blocked_by_building(DVec3::new(-5.0, 0.5, 5.0), DVec3::X));
        assert!(!s.blocked_by_building(DVec3::new(-5.0, 0.5, 5.0), DVec3::NEG_X));
    }
}
