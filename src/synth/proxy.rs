//! The proxy mesh handed to training: a coarser, slightly wrong copy of the true surface, like
//! an MVS reconstruction. The terrain keeps every `stride`-th vertex of the true heightfield
//! (so its triangles are `stride`× larger and miss the finer relief) and every vertex is moved
//! vertically by a low-frequency offset `displacement·2·(noise − 0.5)` (value noise of
//! wavelength `displacement_wavelength`, |offset| < displacement). Buildings stay boxes but
//! each is shifted by up to `building_shift` along x, y and z (its top), and its bottom is
//! pushed below the displaced terrain.

use super::noise::{self, stream};
use super::surface::{push_box, TrueSurface};
use super::ProxyParams;
use crate::rng::{self, Purpose};
use crate::scene::Mesh;
use glam::DVec3;

/// Low-frequency vertical displacement of the proxy terrain at (x, y).
pub fn displacement(seed: u64, p: &ProxyParams, x: f64, y: f64) -> f64 {
    2.0 * p.displacement * noise::centred(seed, stream::PROXY, x, y, p.displacement_wavelength)
}

pub fn proxy_mesh(seed: u64, p: &ProxyParams, truth: &TrueSurface) -> Mesh {
    let hf = &truth.terrain;
    assert!(
        hf.n % p.stride == 0,
        "terrain cells must be a multiple of the proxy stride"
    );
    let m = hf.n / p.stride;
    let mut vertices = Vec::with_capacity((m + 1) * (m + 1) + 8 * truth.buildings.len());
    for j in 0..=m {
        for i in 0..=m {
            let v = hf.vertex(i * p.stride, j * p.stride);
            vertices.push(v + DVec3::Z * displacement(seed, p, v.x, v.y));
        }
    }
    let idx = |i: usize, j: usize| (j * (m + 1) + i) as u32;
    let mut triangles = Vec::with_capacity(2 * m * m + 10 * truth.buildings.len());
    for j in 0..m {
        for i in 0..m {
            triangles.push([idx(i, j), idx(i + 1, j), idx(i + 1, j + 1)]);
            triangles.push([idx(i, j), idx(i + 1, j + 1), idx(i, j + 1)]);
        }
    }
    for (k, b) in truth.buildings.iter().enumerate() {
        let r = |c: u64| {
            2.0 * rng::uniform_f64(
                seed,
                Purpose::Synth,
                stream::PROXY + 16,
                (k as u64) << 4 | c,
            ) - 1.0
        };
        let s = p.building_shift;
        let shift = DVec3::new(s * r(0), s * r(1), 0.0);
        let lo = b.lo() + shift - DVec3::Z * (p.displacement + 1.0);
        let hi = b.hi() + shift + DVec3::Z * (s * r(2));
        push_box(&mut vertices, &mut triangles, lo, hi);
    }
    Mesh {
        vertices,
        triangles,
    }
}
