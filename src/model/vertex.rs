//! The vertex-feature featurization: the 3D-surface-based baseline the paper argues against
//! (Fig. 2b; "learnable Z-dimensional feature descriptors are assigned to each surface
//! primitive … mesh vertex \[45\]", Sec. 3.1). One learnable vector of Z features per mesh vertex;
//! a sub-sample that hit triangle `(i0, i1, i2)` with barycentrics `(u, v)` of vertices 1 and 2
//! gets
//! ```text
//! F_V(x_j) = w0·T[i0] + w1·T[i1] + w2·T[i2],   (w0, w1, w2) = (1 − u − v, u, v)     (Fig. 2b)
//! ```
//! It replaces F_H(x_j) of Eq. 2 in the pipeline; everything after it (pooling over valid
//! sub-samples, Eq. 4; SH(d); appearance code; shader, Eq. 3) is the hash model's. So its
//! featuremetric resolution is the mesh's vertex spacing — exactly the limitation Fig. 2b
//! illustrates.
//!
//! Numerics: weights are computed in f64 from the f64 barycentrics and rounded once to the
//! model's float; the sum is `((w0·T0) + w1·T1) + w2·T2` in that order, unfused (no FMA), in the
//! model's float. Backward scatters `w_k · d_out` into the three rows, sub-samples in batch
//! order, corners k = 0, 1, 2: deterministic (sequential; the cost is 3·Z multiply-adds per
//! valid sub-sample, negligible next to the shader). Barycentrics are data (the ray cast), so
//! there is no gradient with respect to them or to the hit position.
//!
//! Table: `vertex.features` [V, Z] (parameter, sparse Adam group `vertex`: rows whose gradient is
//! exactly zero are skipped, SPEC §4.8), `vertex.faces` [T, 3] u32 (structure: the mesh's
//! triangles, saved with the model so triangle ids from a ray cast can be checked against it).
//! Initialisation U(±1e-4) like the hash tables.

use crate::model::hashgrid::Touched;
use crate::model::Real;

use anyhow::{ensure, Result};

use std::sync::Arc;

/// The structure of a vertex-feature table (the numbers live in the flat parameter buffer).
#[derive(Clone, Debug, PartialEq)]
pub struct VertexTable {
    /// V: rows of the table.
    pub n_vertices: usize,
    /// Z: features per vertex.
    pub features: usize,
    /// `[T]` the mesh triangles (vertex indices < V), shared.
    pub faces: Arc<[[u32; 3]]>,
}

impl VertexTable {
    /// Checks Z > 0, V > 0 and every face index < V (errors name the face).
    pub fn new(n_vertices: usize, features: usize, faces: Arc<[[u32; 3]]>) -> Result<VertexTable> {
        ensure!(
            features > 0,
            "vertex featurization: vertex_features must be > 0"
        );
        ensure!(
            n_vertices > 0,
            "vertex featurization: the mesh has no vertices"
        );
        ensure!(
            n_vertices <= u32::MAX as usize,
            "vertex featurization: too many vertices"
        );
        if let Some((i, f)) = faces
            .iter()
            .enumerate()
            .find(|(_, f)| f.iter().any(|&k| k as usize >= n_vertices))
        {
            anyhow::bail!(
                "vertex featurization: face {i} {f:?} refers to a vertex beyond the {n_vertices} vertices"
            );
        }
        Ok(VertexTable {
            n_vertices,
            features,
            faces,
        })
    }

    /// V·Z.
    pub fn n_params(&self) -> usize {
        self.n_vertices * self.features
    }

    /// U(−1e-4, 1e-4) per element from `rng` (InitTable, `tensor_id`, element index).
    pub fn init_table(&self, seed: u64, tensor_id: u64) -> Vec<f32> {
        crate::model::hashgrid::init_uniform_table(self.n_params(), seed, tensor_id)
    }

    /// Every triangle id below T (for batch checks); returns the first offending position.
    pub fn first_bad_triangle(&self, tris: &[u32]) -> Option<usize> {
        tris.iter().position(|&t| t as usize >= self.faces.len())
    }
}

/// Barycentric weights `(1 − u − v, u, v)` in f64, rounded once to `R`.
#[inline]
fn weights<R: Real>(b: [f64; 2]) -> [R; 3] {
    [
        R::from_f64(1.0 - b[0] - b[1]),
        R::from_f64(b[0]),
        R::from_f64(b[1]),
    ]
}

/// Fig. 2b forward: `out[r, :] = Σ_k w_k · table[faces[tri[r]][k], :]` for each of the `M`
/// sub-samples (OVERWRITES `out [M, Z]`). `table [V, Z]`, `tri [M]`, `bary [M]`.
pub fn vertex_forward<R: Real>(
    vt: &VertexTable,
    table: &[R],
    tri: &[u32],
    bary: &[[f64; 2]],
    out: &mut [R],
) {
    let z = vt.features;
    assert_eq!(table.len(), vt.n_params(), "vertex_forward: table length");
    assert_eq!(tri.len(), bary.len(), "vertex_forward: tri / bary lengths");
    assert_eq!(out.len(), tri.len() * z, "vertex_forward: out length");
    for (r, (&t, &b)) in tri.iter().zip(bary).enumerate() {
        let f = vt.faces[t as usize];
        let w: [R; 3] = weights(b);
        let o = &mut out[r * z..(r + 1) * z];
        let t0 = &table[f[0] as usize * z..][..z];
        for (o, &v) in o.iter_mut().zip(t0) {
            *o = w[0] * v;
        }
        for k in 1..3 {
            let tk = &table[f[k] as usize * z..][..z];
            for (o, &v) in o.iter_mut().zip(tk) {
                *o += w[k] * v;
            }
        }
    }
}

/// Fig. 2b backward: ACCUMULATES `d_table[faces[tri[r]][k], :] += w_k · d_out[r, :]`
/// (sub-samples in order, corners k = 0, 1, 2) and merges the rows written into `touched`
/// (sorted ascending, unique; entries are vertex ids, each `Z` floats).
pub fn vertex_backward<R: Real>(
    vt: &VertexTable,
    tri: &[u32],
    bary: &[[f64; 2]],
    d_out: &[R],
    d_table: &mut [R],
    touched: &mut Touched,
) {
    let z = vt.features;
    assert_eq!(
        d_table.len(),
        vt.n_params(),
        "vertex_backward: d_table length"
    );
    assert_eq!(tri.len(), bary.len(), "vertex_backward: tri / bary lengths");
    assert_eq!(d_out.len(), tri.len() * z, "vertex_backward: d_out length");
    touched.entries.reserve(tri.len() * 3);
    for (r, (&t, &b)) in tri.iter().zip(bary).enumerate() {
        let f = vt.faces[t as usize];
        let w: [R; 3] = weights(b);
        let g = &d_out[r * z..(r + 1) * z];
        for k in 0..3 {
            let row = &mut d_table[f[k] as usize * z..][..z];
            for (d, &gv) in row.iter_mut().zip(g) {
                *d += w[k] * gv;
            }
            touched.entries.push(f[k]);
        }
    }
    touched.entries.sort_unstable();
    touched.entries.dedup();
}

#[cfg(test)]
mod tests {
    use super::*;

    fn table() -> VertexTable {
        VertexTable::new(5, 2, Arc::from(vec![[0u32, 1, 2], [2, 3, 4]])).unwrap()
    }

    #[test]
    fn corners_reproduce_vertex_rows_and_touch_them() {
        let vt = table();
        let t: Vec<f64> = (0..10).map(|i| i as f64 * 0.5 - 1.0).collect();
        let mut out = vec![0.0; 6];
        // Vertex 0, vertex 1 of face 0; vertex 2 of face 1 (= mesh vertex 4).
        vertex_forward(
            &vt,
            &t,
            &[0, 0, 1],
            &[[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]],
            &mut out,
        );
        assert_eq!(out, [t[0], t[1], t[2], t[3], t[8], t[9]]);
        // Centroid = mean of the rows.
        let mut c = vec![0.0; 2];
        vertex_forward(&vt, &t, &[1], &[[1.0 / 3.0, 1.0 / 3.0]], &mut c);
        for f in 0..2 {
            let m = (t[4 + f] + t[6 + f] + t[8 + f]) / 3.0;
            assert!((c[f] - m).abs() < 1e-15);
        }
        let mut d = vec![0.0; 10];
        let mut touched = Touched {
            entries: vec![4, 0],
        };
        vertex_backward(
            &vt,
            &[1],
            &[[0.25, 0.5]],
            &[1.0, -2.0],
            &mut d,
            &mut touched,
        );
        assert_eq!(touched.entries, [0, 2, 3, 4]);
        assert_eq!(&d[4..10], &[0.25, -0.5, 0.25, -0.5, 0.5, -1.0]);
        assert!(d[..4].iter().all(|&v| v == 0.0));
    }

    #[test]
    fn bad_faces_are_errors() {
        let e = VertexTable::new(3, 2, Arc::from(vec![[0u32, 1, 2], [1, 2, 3]]))
            .unwrap_err()
            .to_string();
        assert!(e.contains("face 1"), "{e}");
        assert!(VertexTable::new(3, 0, Arc::from(vec![[0u32, 1, 2]])).is_err());
        assert_eq!(table().first_bad_triangle(&[0, 1, 2]), Some(2));
    }
}
