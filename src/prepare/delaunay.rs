//! 3-D Delaunay tetrahedralisation (Bowyer–Watson), with Shewchuk's exact `orient3d` and
//! `insphere` predicates from the `robust` crate: every geometric decision is exact, so the
//! result is a valid triangulation whatever the input's rounding (a predicate that only
//! approximates can make the walk cycle or the cavity non-star-shaped).
//!
//! Why our own: the pure-Rust `delaunay` crate measured 5.4 s for 1,000 and 80 s for 5,000
//! random points here (it validates topology as it goes); a sparse model has 10–100k points.
//! `tritet` wraps TetGen, whose licence (AGPL) the project cannot take; `qhull` needs libclang
//! at build time (bindgen). This file is the textbook algorithm, about 10⁵ points per second.
//!
//! The algorithm:
//! 1. the points are inserted in Morton (Z-curve) order, so each lies near the previous one;
//! 2. four far vertices make a tetrahedron holding every point (and the cameras, so rays
//!    from them start inside): [`Tetrahedralization::is_finite`] tells a cell without them;
//! 3. a point is located by a visibility walk from the last cell made (each step crosses a face
//!    the point is beyond, the first such face from a rotating start, so the walk cannot cycle);
//! 4. the cavity is every cell whose circumsphere holds the point strictly (`insphere > 0`),
//!    grown from the cell that holds it; should a boundary face of the cavity be coplanar with
//!    the point (only for cospherical inputs), the cell beyond it joins the cavity too;
//! 5. the cavity is replaced by cells joining the point to its boundary faces.
//!
//! A point equal to an earlier one (exactly) is not inserted: [`Tetrahedralization::vertex_of`]
//! maps it to the earlier one.
//!
//! Conventions: cell `t` has vertices `cells[t]` in positive orientation (`orient3d > 0` in
//! `robust`'s sign, i.e. the fourth vertex is below the plane of the first three seen
//! counter-clockwise), and `neighbors[t][i]` is the cell across the face opposite vertex `i`
//! ([`NONE`] on the far tetrahedron's outer faces).

use glam::DVec3;

/// No cell (the outside of the far tetrahedron).
pub const NONE: u32 = u32::MAX;

/// How far the four far vertices stand, in multiples of the extent of the points (and the
/// extra points the box must hold): far enough that the hull of the points is not changed by
/// them in practice, near enough that their coordinates keep ~10 significant digits of the
/// points' own spacing in the predicates' fast (filtered) path.
const FAR: f64 = 50.0;

/// A 3-D Delaunay tetrahedralisation of points (plus the four far vertices).
#[derive(Clone, Debug)]
pub struct Tetrahedralization {
    /// The input points, then the four far vertices (indices `n..n+4`).
    pub points: Vec<DVec3>,
    /// Cells: four vertex indices each, positively oriented.
    pub cells: Vec<[u32; 4]>,
    /// `neighbors[t][i]`: the cell across the face opposite `cells[t][i]`, or [`NONE`].
    pub neighbors: Vec<[u32; 4]>,
    /// Per input point: the point it was merged into (itself unless it repeats an earlier one).
    pub vertex_of: Vec<u32>,
    /// Per vertex (input points and far vertices): one cell that has it (NONE for a merged point).
    pub vertex_cell: Vec<u32>,
    n: usize,
}

fn c3(p: DVec3) -> robust::Coord3D<f64> {
    robust::Coord3D {
        x: p.x,
        y: p.y,
        z: p.z,
    }
}

/// `robust::orient3d(a, b, c, d)`: positive when `d` is below the plane of `a, b, c`.
#[inline]
pub fn orient(a: DVec3, b: DVec3, c: DVec3, d: DVec3) -> f64 {
    robust::orient3d(c3(a), c3(b), c3(c), c3(d))
}

/// `robust::insphere`: positive when `e` is strictly inside the sphere through the positively
/// oriented `a, b, c, d`.
#[inline]
fn insphere(a: DVec3, b: DVec3, c: DVec3, d: DVec3, e: DVec3) -> f64 {
    robust::insphere(c3(a), c3(b), c3(c), c3(d), c3(e))
}

/// Spread the low 21 bits of `v` three apart (Morton code helper).
fn spread(mut v: u64) -> u64 {
    v &= 0x1f_ffff;
    v = (v | v << 32) & 0x1f00000000ffff;
    v = (v | v << 16) & 0x1f0000ff0000ff;
    v = (v | v << 8) & 0x100f00f00f00f00f;
    v = (v | v << 4) & 0x10c30c30c30c30c3;
    v = (v | v << 2) & 0x1249249249249249;
    v
}

/// The order points are inserted in: along the Morton curve of their bounding box (ties by
/// index, so the order is a pure function of the points).
fn morton_order(points: &[DVec3], lo: DVec3, hi: DVec3) -> Vec<u32> {
    let ext = (hi - lo).max(DVec3::splat(f64::MIN_POSITIVE));
    let scale = ((1u64 << 21) - 1) as f64;
    let mut keyed: Vec<(u64, u32)> = points
        .iter()
        .enumerate()
        .map(|(i, p)| {
            let q = ((*p - lo) / ext * scale).clamp(DVec3::ZERO, DVec3::splat(scale));
            let code = spread(q.x as u64) | spread(q.y as u64) << 1 | spread(q.z as u64) << 2;
            (code, i as u32)
        })
        .collect();
    keyed.sort_unstable();
    keyed.into_iter().map(|(_, i)| i).collect()
}

/// The three vertices of face `i` of a cell (the face opposite vertex `i`), ordered so that
/// `orient(face, vertex i) > 0` for a positively oriented cell.
#[inline]
pub fn face(c: &[u32; 4], i: usize) -> [u32; 3] {
    // Replacing vertex i by a point q keeps the orientation sign; these orders realise
    // orient(f0, f1, f2, v_i) = orient(cell) for each i.
    match i {
        0 => [c[1], c[3], c[2]],
        1 => [c[0], c[2], c[3]],
        2 => [c[0], c[3], c[1]],
        _ => [c[0], c[1], c[2]],
    }
}

impl Tetrahedralization {
    /// Tetrahedralise `points`. `also_inside` are points the far tetrahedron must also hold
    /// (cameras), not inserted. Errors: non-finite coordinates, fewer than 4 distinct points,
    /// or all points on one plane.
    pub fn new(points: &[DVec3], also_inside: &[DVec3]) -> anyhow::Result<Tetrahedralization> {
        Self::with_progress(points, also_inside, &mut |_| {})
    }

    /// [`new`](Self::new), calling `progress(points inserted)` every 4096 points.
    pub fn with_progress(
        points: &[DVec3],
        also_inside: &[DVec3],
        progress: &mut dyn FnMut(usize),
    ) -> anyhow::Result<Tetrahedralization> {
        let n = points.len();
        if let Some(k) = points.iter().position(|p| !p.is_finite()) {
            anyhow::bail!("point {k} is not finite ({})", points[k]);
        }
        if n < 4 {
            anyhow::bail!("{n} points: a tetrahedralisation needs at least 4");
        }
        if n >= (u32::MAX / 8) as usize {
            anyhow::bail!("{n} points: more than this tetrahedralisation indexes");
        }
        let (lo, hi) = points
            .iter()
            .chain(also_inside.iter().filter(|p| p.is_finite()))
            .fold(
                (DVec3::splat(f64::INFINITY), DVec3::splat(f64::NEG_INFINITY)),
                |(a, b), p| (a.min(*p), b.max(*p)),
            );
        let centre = 0.5 * (lo + hi);
        let r = (hi - lo).max_element().max(1e-300) * FAR;
        // A regular tetrahedron around the box, its vertices ~FAR extents away.
        let far = [
            centre + DVec3::new(r, r, r),
            centre + DVec3::new(r, -r, -r),
            centre + DVec3::new(-r, r, -r),
            centre + DVec3::new(-r, -r, r),
        ];
        let mut all = points.to_vec();
        all.extend_from_slice(&far);
        let f = n as u32;
        let mut first = [f, f + 1, f + 2, f + 3];
        if orient(
            all[first[0] as usize],
            all[first[1] as usize],
            all[first[2] as usize],
            all[first[3] as usize],
        ) < 0.0
        {
            first.swap(0, 1);
        }
        let mut t = Tetrahedralization {
            points: all,
            cells: vec![first],
            neighbors: vec![[NONE; 4]],
            vertex_of: (0..n as u32).collect(),
            vertex_cell: vec![NONE; n + 4],
            n,
        };
        let mut st = Insert::default();
        let mut last = 0u32;
        for (k, &i) in morton_order(points, lo, hi).iter().enumerate() {
            last = t.insert(i, last, &mut st);
            if k % 4096 == 4095 {
                progress(k + 1);
            }
        }
        t.compact(&st.free);
        let distinct = t
            .vertex_of
            .iter()
            .enumerate()
            .filter(|(i, v)| **v == *i as u32)
            .count();
        if distinct < 4 {
            anyhow::bail!("only {distinct} distinct points: a tetrahedralisation needs 4");
        }
        if t.cells.iter().all(|c| !t.is_finite_cell(c)) {
            anyhow::bail!("all {n} points lie on one plane (or line): nothing has volume");
        }
        Ok(t)
    }

    /// Number of input points (the far vertices are `n..n+4`).
    pub fn input_len(&self) -> usize {
        self.n
    }

    /// Whether vertex `v` is an input point (not a far vertex).
    #[inline]
    pub fn is_input(&self, v: u32) -> bool {
        (v as usize) < self.n
    }

    /// Whether a cell has only input points as vertices.
    #[inline]
    pub fn is_finite_cell(&self, c: &[u32; 4]) -> bool {
        c.iter().all(|&v| self.is_input(v))
    }

    /// Whether cell `t` has only input points as vertices.
    #[inline]
    pub fn is_finite(&self, t: u32) -> bool {
        self.is_finite_cell(&self.cells[t as usize])
    }

    #[inline]
    fn p(&self, v: u32) -> DVec3 {
        self.points[v as usize]
    }

    /// `orient` of cell `t` with its vertex `i` replaced by `q`: positive when `q` is on the
    /// same side of face `i` as vertex `i`.
    #[inline]
    pub fn side(&self, t: u32, i: usize, q: DVec3) -> f64 {
        let f = face(&self.cells[t as usize], i);
        orient(self.p(f[0]), self.p(f[1]), self.p(f[2]), q)
    }

    /// The cell holding `q` (on its boundary counts), by a visibility walk from `start`.
    fn locate(&self, q: DVec3, start: u32, salt: &mut u32) -> u32 {
        let mut t = start;
        // A walk visits far fewer cells than exist; the bound only guards against a bug.
        for _ in 0..self.cells.len() * 4 + 16 {
            *salt = salt.wrapping_add(1);
            let s = (*salt % 4) as usize;
            let mut moved = false;
            for k in 0..4 {
                let i = (s + k) % 4;
                if self.side(t, i, q) < 0.0 {
                    let nb = self.neighbors[t as usize][i];
                    if nb != NONE {
                        t = nb;
                        moved = true;
                        break;
                    }
                }
            }
            if !moved {
                return t;
            }
        }
        unreachable!("point location did not end (a bug in the tetrahedralisation)")
    }

    /// Insert input point `i`, starting the walk at `hint`; returns a cell made (or `hint`).
    fn insert(&mut self, i: u32, hint: u32, st: &mut Insert) -> u32 {
        let q = self.p(i);
        let t0 = self.locate(q, hint, &mut st.salt);
        if let Some(&v) = self.cells[t0 as usize].iter().find(|&&v| self.p(v) == q) {
            self.vertex_of[i as usize] = v;
            return t0;
        }
        // The cavity: cells whose circumsphere holds q strictly, grown from t0 (which holds q,
        // so its sphere does, unless q is on it — then t0 is taken anyway: q is in its closure).
        st.stamp = st.stamp.wrapping_add(1);
        if st.mark.len() < self.cells.len() {
            st.mark.resize(self.cells.len(), 0);
        }
        st.cavity.clear();
        st.stack.clear();
        st.stack.push(t0);
        st.mark[t0 as usize] = st.stamp;
        while let Some(t) = st.stack.pop() {
            st.cavity.push(t);
            for k in 0..4 {
                let nb = self.neighbors[t as usize][k];
                if nb == NONE || st.mark[nb as usize] == st.stamp {
                    continue;
                }
                let c = self.cells[nb as usize];
                if insphere(self.p(c[0]), self.p(c[1]), self.p(c[2]), self.p(c[3]), q) > 0.0 {
                    st.mark[nb as usize] = st.stamp;
                    st.stack.push(nb);
                }
            }
        }
        // Boundary faces; a face q is not strictly on the inner side of pulls its outer cell in.
        loop {
            st.boundary.clear();
            let mut grown = false;
            for ci in 0..st.cavity.len() {
                let t = st.cavity[ci];
                for k in 0..4 {
                    let nb = self.neighbors[t as usize][k];
                    if nb != NONE && st.mark[nb as usize] == st.stamp {
                        continue;
                    }
                    if self.side(t, k, q) <= 0.0 {
                        if nb != NONE {
                            st.mark[nb as usize] = st.stamp;
                            st.cavity.push(nb);
                            grown = true;
                        }
                        continue;
                    }
                    st.boundary.push((t, k as u8, nb));
                }
            }
            if !grown {
                break;
            }
        }
        // New cells: each boundary face joined to q (q takes the place of the cavity cell's
        // vertex k, which keeps the orientation positive). They take slots freed by earlier
        // insertions only: the cavity's own cells are still read (and linked from outside)
        // until every new cell is made.
        st.edges.clear();
        let mut made = hint;
        for bi in 0..st.boundary.len() {
            let (t, k, nb) = st.boundary[bi];
            let mut c = self.cells[t as usize];
            c[k as usize] = i;
            let nt = match st.free.pop() {
                Some(s) => {
                    self.cells[s as usize] = c;
                    self.neighbors[s as usize] = [NONE; 4];
                    s
                }
                None => {
                    self.cells.push(c);
                    self.neighbors.push([NONE; 4]);
                    st.mark.push(0);
                    (self.cells.len() - 1) as u32
                }
            };
            // The outer cell's back link.
            self.neighbors[nt as usize][k as usize] = nb;
            if nb != NONE {
                let back = self.neighbors[nb as usize]
                    .iter()
                    .position(|&x| x == t)
                    .expect("neighbour links are symmetric");
                self.neighbors[nb as usize][back] = nt;
            }
            for &v in &c {
                self.vertex_cell[v as usize] = nt;
            }
            // Faces through q: opposite each other vertex j; the neighbour across shares the
            // edge made of the two remaining vertices.
            for j in 0..4 {
                if j == k as usize {
                    continue;
                }
                let mut e = [NONE; 2];
                let mut m = 0;
                for (l, &v) in c.iter().enumerate() {
                    if l != j && l != k as usize {
                        e[m] = v;
                        m += 1;
                    }
                }
                let key = (e[0].min(e[1]), e[0].max(e[1]));
                if let Some(pos) = st.edges.iter().position(|x| x.0 == key) {
                    let (_, ot, oj) = st.edges.swap_remove(pos);
                    self.neighbors[nt as usize][j] = ot;
                    self.neighbors[ot as usize][oj as usize] = nt;
                } else {
                    st.edges.push((key, nt, j as u8));
                }
            }
            made = nt;
        }
        debug_assert!(st.edges.is_empty(), "cavity boundary is not closed");
        st.free.extend_from_slice(&st.cavity);
        made
    }

    /// Drop the cells on the free list and renumber the rest (keeping their order).
    fn compact(&mut self, free: &[u32]) {
        let mut dead = vec![false; self.cells.len()];
        for &t in free {
            dead[t as usize] = true;
        }
        let mut new_id = vec![NONE; self.cells.len()];
        let mut k = 0u32;
        for (t, d) in dead.iter().enumerate() {
            if !d {
                new_id[t] = k;
                k += 1;
            }
        }
        let keep = |t: usize| !dead[t];
        let cells: Vec<[u32; 4]> = (0..self.cells.len())
            .filter(|&t| keep(t))
            .map(|t| self.cells[t])
            .collect();
        let neighbors: Vec<[u32; 4]> = (0..self.neighbors.len())
            .filter(|&t| keep(t))
            .map(|t| self.neighbors[t].map(|x| if x == NONE { NONE } else { new_id[x as usize] }))
            .collect();
        self.cells = cells;
        self.neighbors = neighbors;
        self.vertex_cell.iter_mut().for_each(|x| *x = NONE);
        for (t, c) in self.cells.iter().enumerate() {
            for &v in c {
                self.vertex_cell[v as usize] = t as u32;
            }
        }
    }

    /// The cells around vertex `v` (its star), found from `vertex_cell[v]` across faces through
    /// `v`; empty for a merged point.
    pub fn star(&self, v: u32, out: &mut Vec<u32>) {
        out.clear();
        let t0 = self.vertex_cell[v as usize];
        if t0 == NONE {
            return;
        }
        out.push(t0);
        let mut k = 0;
        while k < out.len() {
            let t = out[k];
            k += 1;
            let c = &self.cells[t as usize];
            for (i, &nb) in self.neighbors[t as usize].iter().enumerate() {
                if c[i] == v {
                    continue;
                }
                if nb != NONE && !out.contains(&nb) {
                    out.push(nb);
                }
            }
        }
    }
}

/// Scratch space of [`Tetrahedralization::insert`], reused across points.
#[derive(Default)]
struct Insert {
    mark: Vec<u32>,
    stamp: u32,
    cavity: Vec<u32>,
    stack: Vec<u32>,
    boundary: Vec<(u32, u8, u32)>,
    /// Edges of the boundary awaiting their second cell: (edge, cell, local face).
    edges: Vec<((u32, u32), u32, u8)>,
    free: Vec<u32>,
    salt: u32,
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::rng::{uniform_f64, Purpose};

    fn random_points(n: usize, seed: u64) -> Vec<DVec3> {
        (0..n as u64)
            .map(|k| {
                let r = |b| uniform_f64(seed, Purpose::Test, k, b);
                DVec3::new(r(0), r(1), r(2))
            })
            .collect()
    }

    /// Links are symmetric, cells are positively oriented, and no input point is strictly
    /// inside any cell's circumsphere (the Delaunay property, checked exactly).
    fn check(t: &Tetrahedralization) {
        for (i, c) in t.cells.iter().enumerate() {
            let p = c.map(|v| t.points[v as usize]);
            assert!(
                orient(p[0], p[1], p[2], p[3]) > 0.0,
                "cell {i} not positive"
            );
            for k in 0..4 {
                let nb = t.neighbors[i][k];
                if nb == NONE {
                    continue;
                }
                assert!(
                    t.neighbors[nb as usize].contains(&(i as u32)),
                    "link {i}->{nb}"
                );
                // The shared face has the same three vertices.
                let mut a = face(c, k).to_vec();
                let back = t.neighbors[nb as usize]
                    .iter()
                    .position(|&x| x == i as u32)
                    .unwrap();
                let mut b = face(&t.cells[nb as usize], back).to_vec();
                a.sort();
                b.sort();
                assert_eq!(a, b);
            }
        }
        for (i, c) in t.cells.iter().enumerate() {
            let p = c.map(|v| t.points[v as usize]);
            for (v, q) in t.points[..t.input_len()].iter().enumerate() {
                if c.contains(&(v as u32)) || t.vertex_of[v] != v as u32 {
                    continue;
                }
                assert!(
                    insphere(p[0], p[1], p[2], p[3], *q) <= 0.0,
                    "point {v} inside cell {i}'s sphere"
                );
            }
        }
    }

    #[test]
    fn random_points_are_delaunay() {
        let pts = random_points(300, 1);
        let t = Tetrahedralization::new(&pts, &[]).unwrap();
        check(&t);
        // Every input point is a vertex of some cell.
        for v in 0..pts.len() {
            assert_ne!(t.vertex_cell[v], NONE);
        }
        // Volumes of the cells add up to the far tetrahedron's.
        let vol = |c: &[u32; 4]| {
            let p = c.map(|v| t.points[v as usize]);
            (p[1] - p[0]).dot((p[2] - p[0]).cross(p[3] - p[0])).abs() / 6.0
        };
        let total: f64 = t.cells.iter().map(vol).sum();
        let n = t.input_len() as u32;
        let far = vol(&[n, n + 1, n + 2, n + 3]);
        assert!((total - far).abs() <= 1e-9 * far, "{total} vs {far}");
    }

    /// A regular grid (every cell cospherical with many points, coplanar faces everywhere) and
    /// repeated points: still a valid Delaunay tetrahedralisation.
    #[test]
    fn degenerate_grid_and_duplicates() {
        let mut pts = Vec::new();
        for i in 0..5 {
            for j in 0..5 {
                for k in 0..5 {
                    pts.push(DVec3::new(i as f64, j as f64, k as f64));
                }
            }
        }
        pts.push(DVec3::new(2.0, 2.0, 2.0));
        pts.push(DVec3::new(0.0, 0.0, 0.0));
        let t = Tetrahedralization::new(&pts, &[]).unwrap();
        check(&t);
        assert_eq!(t.vertex_of[125], t.vertex_of[62]);
        assert_eq!(t.vertex_of[126], 0);
        // The finite cells fill the cube exactly (volume 64).
        let vol: f64 = t
            .cells
            .iter()
            .filter(|c| t.is_finite_cell(c))
            .map(|c| {
                let p = c.map(|v| t.points[v as usize]);
                (p[1] - p[0]).dot((p[2] - p[0]).cross(p[3] - p[0])).abs() / 6.0
            })
            .sum();
        assert!((vol - 64.0).abs() < 1e-9, "{vol}");
    }

    /// Points on a sphere (cospherical in exact arithmetic, nearly so after rounding).
    #[test]
    fn sphere_points() {
        let pts: Vec<DVec3> = random_points(400, 2)
            .into_iter()
            .map(|p| (p - DVec3::splat(0.5)).normalize())
            .collect();
        let t = Tetrahedralization::new(&pts, &[DVec3::new(10.0, 0.0, 0.0)]).unwrap();
        check(&t);
        // The far tetrahedron holds the extra point.
        let q = DVec3::new(10.0, 0.0, 0.0);
        let mut salt = 0;
        let c = t.locate(q, 0, &mut salt);
        for i in 0..4 {
            assert!(t.side(c, i, q) >= 0.0);
        }
    }

    #[test]
    fn bad_inputs_are_errors() {
        let flat: Vec<DVec3> = (0..20)
            .map(|k| DVec3::new(k as f64, (k * k % 7) as f64, 0.0))
            .collect();
        let e = Tetrahedralization::new(&flat, &[]).unwrap_err().to_string();
        assert!(e.contains("one plane"), "{e}");
        let e = Tetrahedralization::new(&flat[..3], &[])
            .unwrap_err()
            .to_string();
        assert!(e.contains("at least 4"), "{e}");
        let mut nan = random_points(10, 3);
        nan[4].y = f64::NAN;
        let e = Tetrahedralization::new(&nan, &[]).unwrap_err().to_string();
        assert!(e.contains("point 4 is not finite"), "{e}");
    }

    #[test]
    fn star_of_a_vertex() {
        let pts = random_points(200, 4);
        let t = Tetrahedralization::new(&pts, &[]).unwrap();
        let mut star = Vec::new();
        for v in [0u32, 17, 199] {
            t.star(v, &mut star);
            let want: Vec<u32> = (0..t.cells.len() as u32)
                .filter(|&c| t.cells[c as usize].contains(&v))
                .collect();
            let mut got = star.clone();
            got.sort();
            assert_eq!(got, want);
        }
    }
}
