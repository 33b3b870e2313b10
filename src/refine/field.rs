//! The offset field of the mesh refinement (SPEC §4.11; module docs of `refine/`): what the
//! training mesh fixes ([`RefineGeom`]: local-frame vertices, normals, unit coordinates, edges),
//! the field `θ_i = Σ_l trilinear(G_l, u_i) + r_i` and its backward, and the smoothness energy of
//! the per-vertex residual. Its parameters, as a checkpoint stores them, are
//! [`RefineParams`] (`model/refine.rs`).
//!
//! ## Parametrisation
//! Vertex i of the base mesh (the training mesh as loaded; local frame `v − center`, f64) moves to
//! ```text
//! v_i(θ) = v_i + (θ_i · s) · m_i          s = max(extent)  (the largest axis of the SPEC §4.1 normalisation)
//! θ_i    = Σ_l trilinear(G_l, u_i) + r_i  u_i = (v_i − center) / s + 0.5  (isotropic unit coordinates)
//! ```
//! `m_i` is the unit area-weighted vertex normal of the base mesh (`Mesh::vertex_normals`,
//! zero for an unused vertex), `G_l` (l = 0 … levels−1) are dense scalar grids of
//! `R_l = base_resolution · 2^l` cells per unit ((R_l + 1)³ nodes, node `x + y(R+1) + z(R+1)²`,
//! cell `c = clamp(floor(u·R), 0, R−1)`, fraction `u·R − c`), and `r_i` a per-vertex residual. The
//! grids are the coarse-to-fine part: a coarse node gathers the gradient of every vertex in its
//! cells, so an error that is smooth over the mesh is corrected even though a batch touches few
//! vertices; levels are switched on coarse first (`refine/refiner.rs`). Offsets are in units of
//! `s`, so learning rates do not depend on the scene's units. The normalisation (centre and
//! extent) stays the one of the base mesh throughout: refined vertices may leave the unit cube
//! (the hash grid wraps, SPEC §4.2).
//!
//! ## Smoothness
//! On the per-vertex residual (the grids are smooth by construction), with `N(i)` the vertices
//! sharing an edge with i, `E` the undirected edges and `(Lr)_i = r_i − mean_{j∈N(i)} r_j`:
//! ```text
//! E_smooth = laplacian · (1/|E|) Σ_{(i,j)∈E} (r_i − r_j)²  +  bilaplacian · (1/V) Σ_i (Lr)_i²
//! ```
//! (f64, sums in vertex / edge order, so deterministic).

use crate::model::refine::{RefineConfig, RefineParams};
use crate::model::Real;
use crate::scene::{Mesh, Normalization};
use glam::DVec3;
use rayon::prelude::*;

/// What the base mesh fixes (module docs): local-frame vertices, normals, unit coordinates,
/// edges. Built once per run from the training mesh and the model's normalisation.
#[derive(Clone, Debug)]
pub struct RefineGeom {
    /// The vertices as loaded (world frame).
    pub world: Vec<DVec3>,
    /// `v_i − center` (f64).
    pub base: Vec<DVec3>,
    /// Unit area-weighted vertex normals (zero for unused vertices).
    pub normals: Vec<DVec3>,
    /// `(v_i − center)/s + 0.5`, clamped to [0, 1].
    pub unit: Vec<DVec3>,
    pub triangles: Vec<[u32; 3]>,
    /// `s = max(extent)`.
    pub scale: f64,
    pub norm: Normalization,
    /// CSR neighbours: vertex i's are `nbr[nbr_start[i]..nbr_start[i+1]]` (ascending).
    pub nbr_start: Vec<u32>,
    pub nbr: Vec<u32>,
    /// Undirected edges (i < j), ascending.
    pub edges: Vec<[u32; 2]>,
}

impl RefineGeom {
    pub fn new(mesh: &Mesh, norm: &Normalization) -> RefineGeom {
        let scale = norm.extent.max_element();
        let base: Vec<DVec3> = mesh.vertices.iter().map(|&v| v - norm.center).collect();
        let normals = mesh.vertex_normals();
        let unit = base
            .iter()
            .map(|&v| (v / scale + DVec3::splat(0.5)).clamp(DVec3::ZERO, DVec3::ONE))
            .collect();
        let mut edges: Vec<[u32; 2]> = mesh
            .triangles
            .iter()
            .flat_map(|t| [[t[0], t[1]], [t[1], t[2]], [t[2], t[0]]])
            .filter(|e| e[0] != e[1])
            .map(|[a, b]| [a.min(b), a.max(b)])
            .collect();
        edges.sort_unstable();
        edges.dedup();
        let nv = mesh.vertices.len();
        let mut deg = vec![0u32; nv + 1];
        for e in &edges {
            deg[e[0] as usize + 1] += 1;
            deg[e[1] as usize + 1] += 1;
        }
        for i in 0..nv {
            deg[i + 1] += deg[i];
        }
        let mut fill = deg.clone();
        let mut nbr = vec![0u32; deg[nv] as usize];
        for e in &edges {
            for (a, b) in [(e[0], e[1]), (e[1], e[0])] {
                nbr[fill[a as usize] as usize] = b;
                fill[a as usize] += 1;
            }
        }
        for i in 0..nv {
            nbr[deg[i] as usize..deg[i + 1] as usize].sort_unstable();
        }
        RefineGeom {
            world: mesh.vertices.clone(),
            base,
            normals,
            unit,
            triangles: mesh.triangles.clone(),
            scale,
            norm: *norm,
            nbr_start: deg,
            nbr,
            edges,
        }
    }

    pub fn n_vertices(&self) -> usize {
        self.base.len()
    }

    /// Vertex i (local frame) at offset θ_i.
    #[inline]
    pub fn position(&self, i: usize, theta: f64) -> DVec3 {
        self.base[i] + self.normals[i] * (theta * self.scale)
    }

    /// The mesh (world frame) with offsets `theta`; a vertex whose offset is exactly 0 keeps its
    /// loaded coordinates bit for bit (so zero offsets give the training mesh itself).
    pub fn mesh_with(&self, theta: &[f64]) -> Mesh {
        Mesh {
            vertices: (0..self.n_vertices())
                .map(|i| {
                    if theta[i] == 0.0 {
                        self.world[i]
                    } else {
                        self.position(i, theta[i]) + self.norm.center
                    }
                })
                .collect(),
            triangles: self.triangles.clone(),
        }
    }

    pub fn neighbours(&self, i: usize) -> &[u32] {
        &self.nbr[self.nbr_start[i] as usize..self.nbr_start[i + 1] as usize]
    }
}

/// Node indices and trilinear weights of unit point `u` in a grid of `r` cells per axis.
#[inline]
pub fn trilinear(r: usize, u: DVec3) -> ([usize; 8], [f64; 8]) {
    let mut c = [0usize; 3];
    let mut f = [0f64; 3];
    for a in 0..3 {
        let p = u[a] * r as f64;
        let ci = (p.floor().max(0.0) as usize).min(r - 1);
        c[a] = ci;
        f[a] = p - ci as f64;
    }
    let n = r + 1;
    let mut idx = [0usize; 8];
    let mut w = [0f64; 8];
    for k in 0..8 {
        let (bx, by, bz) = (k & 1, (k >> 1) & 1, (k >> 2) & 1);
        idx[k] = (c[0] + bx) + (c[1] + by) * n + (c[2] + bz) * n * n;
        let wx = if bx == 1 { f[0] } else { 1.0 - f[0] };
        let wy = if by == 1 { f[1] } else { 1.0 - f[1] };
        let wz = if bz == 1 { f[2] } else { 1.0 - f[2] };
        w[k] = wx * wy * wz;
    }
    (idx, w)
}

/// `θ_i = Σ_l trilinear(G_l, u_i) + r_i` (module docs) from grids `[levels][(R_l+1)³]` and the
/// residual `r` (empty: none), in f64 whatever the parameters' type.
pub fn field_theta<R: Real>(
    cfg: &RefineConfig,
    geom: &RefineGeom,
    grids: &[Vec<R>],
    r: &[R],
    i: usize,
) -> f64 {
    let mut th = 0.0f64;
    for (l, g) in grids.iter().enumerate() {
        let (idx, w) = trilinear(cfg.resolution(l as u32), geom.unit[i]);
        for k in 0..8 {
            th += w[k] * g[idx[k]].to_f64();
        }
    }
    if !r.is_empty() {
        th += r[i].to_f64();
    }
    th
}

/// The levels of the offset field that take part (at a step of the schedule, `refiner.rs`): the
/// first `grids` grid levels, and the per-vertex residual when `residual`.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Active {
    pub grids: usize,
    pub residual: bool,
}

/// Accumulate `∂L/∂θ_i = d_theta[i]` of the listed vertices (in list order) into the gradients
/// of the `active` grid levels (`d_grids[l]`) and, when the residual is active, of the residual
/// (`d_r`).
pub fn field_backward(
    cfg: &RefineConfig,
    geom: &RefineGeom,
    vertices: &[u32],
    d_theta: &[f64],
    active: Active,
    d_grids: &mut [Vec<f64>],
    d_r: &mut [f64],
) {
    for &i in vertices {
        let (i, g) = (i as usize, d_theta[i as usize]);
        if g == 0.0 {
            continue;
        }
        for (l, dg) in d_grids.iter_mut().enumerate().take(active.grids) {
            let (idx, w) = trilinear(cfg.resolution(l as u32), geom.unit[i]);
            for k in 0..8 {
                dg[idx[k]] += w[k] * g;
            }
        }
        if active.residual && !d_r.is_empty() {
            d_r[i] += g;
        }
    }
}

/// θ_i from the parameters ([`field_theta`] with every level).
pub fn theta(p: &RefineParams, cfg: &RefineConfig, geom: &RefineGeom, i: usize) -> f64 {
    field_theta(cfg, geom, &p.grids, &p.vertex, i)
}

/// θ of every vertex (parallel, each vertex independent).
pub fn theta_all(p: &RefineParams, cfg: &RefineConfig, geom: &RefineGeom) -> Vec<f64> {
    (0..geom.n_vertices())
        .into_par_iter()
        .with_min_len(4096)
        .map(|i| theta(p, cfg, geom, i))
        .collect()
}

/// θ of the listed vertices written into `out` (indexed by vertex; parallel, each vertex
/// independent): what a step reads of the field (the vertices of a batch's or the photo term's
/// triangles).
pub fn theta_of(
    p: &RefineParams,
    cfg: &RefineConfig,
    geom: &RefineGeom,
    vertices: &[u32],
    out: &mut [f64],
) {
    let th: Vec<f64> = vertices
        .par_iter()
        .with_min_len(1024)
        .map(|&i| theta(p, cfg, geom, i as usize))
        .collect();
    for (&i, &t) in vertices.iter().zip(&th) {
        out[i as usize] = t;
    }
}

/// Recompute `p.offsets` from the parameters.
pub fn sync_offsets(p: &mut RefineParams, cfg: &RefineConfig, geom: &RefineGeom) {
    p.offsets = theta_all(p, cfg, geom)
        .into_iter()
        .map(|t| t as f32)
        .collect();
}

/// `E_smooth` of the residual `r` and its gradient added into `d_r` (module docs).
pub fn smoothness<R: Real>(cfg: &RefineConfig, geom: &RefineGeom, r: &[R], d_r: &mut [f64]) -> f64 {
    if r.is_empty() {
        return 0.0;
    }
    let mut e = 0.0f64;
    if cfg.laplacian > 0.0 && !geom.edges.is_empty() {
        let w = cfg.laplacian / geom.edges.len() as f64;
        for &[i, j] in &geom.edges {
            let (i, j) = (i as usize, j as usize);
            let diff = r[i].to_f64() - r[j].to_f64();
            e += w * diff * diff;
            d_r[i] += 2.0 * w * diff;
            d_r[j] -= 2.0 * w * diff;
        }
    }
    if cfg.bilaplacian > 0.0 {
        let nv = geom.n_vertices();
        let w = cfg.bilaplacian / nv as f64;
        // y = L r, then ∂/∂r of w·Σ y² = 2w·Lᵀy.
        let mut y = vec![0.0f64; nv];
        for (i, yi) in y.iter_mut().enumerate() {
            let nb = geom.neighbours(i);
            if nb.is_empty() {
                continue;
            }
            let m: f64 = nb.iter().map(|&j| r[j as usize].to_f64()).sum::<f64>() / nb.len() as f64;
            *yi = r[i].to_f64() - m;
            e += w * *yi * *yi;
        }
        for (i, &yi) in y.iter().enumerate() {
            let nb = geom.neighbours(i);
            if nb.is_empty() || yi == 0.0 {
                continue;
            }
            let g = 2.0 * w * yi;
            d_r[i] += g;
            let share = g / nb.len() as f64;
            for &j in nb {
                d_r[j as usize] -= share;
            }
        }
    }
    e
}
