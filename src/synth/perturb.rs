//! MVS-like proxies of a mesh for the geometry sensitivity benchmark (`xscale bench-geometry`,
//! docs/geometry.md): every vertex moved along its vertex normal by a smooth noise field scaled
//! to a given RMS.
//!
//! - Vertex normal `m_i`: the normalised sum of the area-weighted normals `(b−a)×(c−a)` of the
//!   triangles using vertex i (`Mesh::vertex_normals`; zero for an unused vertex, which then does
//!   not move).
//! - Field `h(p) = c_xy(x, y) + c_yz(y, z) + c_zx(z, x)`, each `c` the synth module's 2-D value
//!   noise (`noise::centred`, C² quintic fade) of wavelength `λ` on its own stream: smooth in
//!   all three axes, energy around λ, zero mean.
//! - `v_i' = v_i + k · h(v_i) · m_i` with `k` chosen so that the RMS over vertices of the
//!   displacement `|k·h(v_i)|` (over vertices that have a normal) is exactly the requested value.
//!
//! Everything is f64 and a pure function of (mesh, seed, rms, λ).

use super::noise::{self, stream};
use crate::scene::Mesh;
use glam::DVec3;

/// Sub-stream of the proxy field (three components from here).
pub const FIELD_STREAM: u64 = stream::PROXY + 0x40;

/// The smooth field `h` at `p` (module docs), values in (−1.5, 1.5).
pub fn field(seed: u64, wavelength: f64, p: DVec3) -> f64 {
    noise::centred(seed, FIELD_STREAM, p.x, p.y, wavelength)
        + noise::centred(seed, FIELD_STREAM + 1, p.y, p.z, wavelength)
        + noise::centred(seed, FIELD_STREAM + 2, p.z, p.x, wavelength)
}

/// `mesh` with every vertex displaced along its normal by the field scaled to RMS `rms` (scene
/// units, module docs); `rms = 0` returns the mesh unchanged.
pub fn displace_along_normals(mesh: &Mesh, seed: u64, rms: f64, wavelength: f64) -> Mesh {
    if rms == 0.0 {
        return mesh.clone();
    }
    let normals = mesh.vertex_normals();
    let h: Vec<f64> = mesh
        .vertices
        .iter()
        .map(|&v| field(seed, wavelength, v))
        .collect();
    let (mut s2, mut n) = (0.0f64, 0usize);
    for (hi, m) in h.iter().zip(&normals) {
        if *m != DVec3::ZERO {
            s2 += hi * hi;
            n += 1;
        }
    }
    let k = if s2 > 0.0 {
        rms / (s2 / n as f64).sqrt()
    } else {
        0.0
    };
    let vertices = mesh
        .vertices
        .iter()
        .zip(&h)
        .zip(&normals)
        .map(|((&v, &hi), &m)| v + m * (k * hi))
        .collect();
    Mesh {
        vertices,
        triangles: mesh.triangles.clone(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn displacement_has_the_requested_rms_along_normals() {
        let mut m = Mesh::default();
        let n = 20;
        for j in 0..=n {
            for i in 0..=n {
                m.vertices
                    .push(DVec3::new(i as f64 * 5.0, j as f64 * 5.0, 0.1 * i as f64));
            }
        }
        for j in 0..n {
            for i in 0..n {
                let k = |a: usize, b: usize| (b * (n + 1) + a) as u32;
                m.triangles.push([k(i, j), k(i + 1, j), k(i + 1, j + 1)]);
                m.triangles.push([k(i, j), k(i + 1, j + 1), k(i, j + 1)]);
            }
        }
        let d = displace_along_normals(&m, 3, 0.4, 30.0);
        let normals = m.vertex_normals();
        let mut s2 = 0.0;
        for ((a, b), nrm) in m.vertices.iter().zip(&d.vertices).zip(&normals) {
            let delta = *b - *a;
            // Along the normal only.
            assert!(delta.cross(*nrm).length() < 1e-12, "{delta} vs {nrm}");
            s2 += delta.length_squared();
        }
        let rms = (s2 / m.vertices.len() as f64).sqrt();
        assert!((rms - 0.4).abs() < 1e-12, "{rms}");
        // Smooth: neighbouring vertices (5 apart, λ = 30) move by similar amounts.
        let dz = |i: usize| (d.vertices[i] - m.vertices[i]).length();
        assert!((dz(0) - dz(1)).abs() < 0.5);
        assert_eq!(displace_along_normals(&m, 3, 0.0, 30.0), m);
    }
}
