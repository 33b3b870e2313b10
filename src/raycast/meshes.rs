//! Procedural meshes for the ray-casting tests and benches: an icosphere (optionally displaced),
//! a closed cube with gridded faces, a height-field terrain and a random triangle soup. Closed
//! meshes share vertices by index, so shared edges are bit-identical (needed by the watertight
//! tests). Randomness comes from `rng` (seeded, pure).

use crate::rng::{self, Purpose};
use crate::scene::Mesh;
use glam::DVec3;
use std::collections::HashMap;

/// Unit icosphere subdivided `level` times: 20·4^level triangles, consistently wound.
pub fn icosphere(level: u32) -> Mesh {
    let t = (1.0 + 5f64.sqrt()) / 2.0;
    let mut vertices: Vec<DVec3> = [
        (-1.0, t, 0.0),
        (1.0, t, 0.0),
        (-1.0, -t, 0.0),
        (1.0, -t, 0.0),
        (0.0, -1.0, t),
        (0.0, 1.0, t),
        (0.0, -1.0, -t),
        (0.0, 1.0, -t),
        (t, 0.0, -1.0),
        (t, 0.0, 1.0),
        (-t, 0.0, -1.0),
        (-t, 0.0, 1.0),
    ]
    .iter()
    .map(|&(x, y, z)| DVec3::new(x, y, z).normalize())
    .collect();
    let mut triangles: Vec<[u32; 3]> = vec![
        [0, 11, 5],
        [0, 5, 1],
        [0, 1, 7],
        [0, 7, 10],
        [0, 10, 11],
        [1, 5, 9],
        [5, 11, 4],
        [11, 10, 2],
        [10, 7, 6],
        [7, 1, 8],
        [3, 9, 4],
        [3, 4, 2],
        [3, 2, 6],
        [3, 6, 8],
        [3, 8, 9],
        [4, 9, 5],
        [2, 4, 11],
        [6, 2, 10],
        [8, 6, 7],
        [9, 8, 1],
    ];
    for _ in 0..level {
        let mut mid: HashMap<(u32, u32), u32> = HashMap::new();
        let mut next = Vec::with_capacity(triangles.len() * 4);
        let mut midpoint = |a: u32, b: u32, vs: &mut Vec<DVec3>| {
            let key = (a.min(b), a.max(b));
            *mid.entry(key).or_insert_with(|| {
                vs.push(((vs[a as usize] + vs[b as usize]) * 0.5).normalize());
                vs.len() as u32 - 1
            })
        };
        for [a, b, c] in triangles {
            let ab = midpoint(a, b, &mut vertices);
            let bc = midpoint(b, c, &mut vertices);
            let ca = midpoint(c, a, &mut vertices);
            next.extend_from_slice(&[[a, ab, ca], [b, bc, ab], [c, ca, bc], [ab, bc, ca]]);
        }
        triangles = next;
    }
    Mesh {
        vertices,
        triangles,
    }
}

/// An icosphere whose vertices are pushed radially by a smooth bumpy function of relative
/// amplitude `amp` (a ≥1M-triangle test object at level 8).
pub fn displaced_icosphere(level: u32, amp: f64) -> Mesh {
    let mut m = icosphere(level);
    for v in &mut m.vertices {
        let bump = (7.0 * v.x).sin() * (5.0 * v.y).cos()
            + 0.5 * (19.0 * v.z + 3.0 * v.x).sin()
            + 0.25 * (41.0 * v.y - 29.0 * v.z).sin();
        *v *= 1.0 + amp * bump;
    }
    m
}

/// Closed axis-aligned cube [-1,1]³, every face an n×n grid of quads (2 triangles each),
/// 12·n² triangles, vertices shared along the cube's edges.
pub fn cube_grid(n: u32) -> Mesh {
    let mut index: HashMap<[u32; 3], u32> = HashMap::new();
    let mut vertices = Vec::new();
    let mut id = |p: [u32; 3], vs: &mut Vec<DVec3>| {
        *index.entry(p).or_insert_with(|| {
            let c = |i: u32| -1.0 + 2.0 * i as f64 / n as f64;
            vs.push(DVec3::new(c(p[0]), c(p[1]), c(p[2])));
            vs.len() as u32 - 1
        })
    };
    let mut triangles = Vec::new();
    for axis in 0..3 {
        for side in [0, n] {
            for i in 0..n {
                for j in 0..n {
                    let lattice = |a: u32, b: u32| {
                        let mut p = [0u32; 3];
                        p[axis] = side;
                        p[(axis + 1) % 3] = a;
                        p[(axis + 2) % 3] = b;
                        p
                    };
                    let q = [
                        id(lattice(i, j), &mut vertices),
                        id(lattice(i + 1, j), &mut vertices),
                        id(lattice(i + 1, j + 1), &mut vertices),
                        id(lattice(i, j + 1), &mut vertices),
                    ];
                    // Alternate the diagonal so both orientations are exercised.
                    if (i + j) % 2 == 0 {
                        triangles.push([q[0], q[1], q[2]]);
                        triangles.push([q[0], q[2], q[3]]);
                    } else {
                        triangles.push([q[0], q[1], q[3]]);
                        triangles.push([q[1], q[2], q[3]]);
                    }
                }
            }
        }
    }
    Mesh {
        vertices,
        triangles,
    }
}

/// Height-field terrain over [-1,1]² (z = smooth bumps of amplitude `amp`), n×n quads.
pub fn terrain(n: u32, amp: f64) -> Mesh {
    let mut vertices = Vec::with_capacity(((n + 1) * (n + 1)) as usize);
    for j in 0..=n {
        for i in 0..=n {
            let x = -1.0 + 2.0 * i as f64 / n as f64;
            let y = -1.0 + 2.0 * j as f64 / n as f64;
            let z = amp * ((3.0 * x).sin() * (2.0 * y).cos() + 0.3 * (11.0 * x + 7.0 * y).sin());
            vertices.push(DVec3::new(x, y, z));
        }
    }
    let mut triangles = Vec::with_capacity((2 * n * n) as usize);
    let at = |i: u32, j: u32| j * (n + 1) + i;
    for j in 0..n {
        for i in 0..n {
            triangles.push([at(i, j), at(i + 1, j), at(i + 1, j + 1)]);
            triangles.push([at(i, j), at(i + 1, j + 1), at(i, j + 1)]);
        }
    }
    Mesh {
        vertices,
        triangles,
    }
}

/// `n` random triangles with vertices in [-1,1]³ near a random centre (edge ≲ `size`).
pub fn random_soup(seed: u64, n: u32, size: f64) -> Mesh {
    let u = |a: u64, b: u64| 2.0 * rng::uniform_f64(seed, Purpose::Test, a, b) - 1.0;
    let mut vertices = Vec::with_capacity(3 * n as usize);
    let mut triangles = Vec::with_capacity(n as usize);
    for t in 0..n as u64 {
        let c = DVec3::new(u(t, 0), u(t, 1), u(t, 2));
        for k in 0..3u64 {
            let o = DVec3::new(u(t, 3 + 3 * k), u(t, 4 + 3 * k), u(t, 5 + 3 * k));
            vertices.push(c + size * o);
        }
        let b = 3 * t as u32;
        triangles.push([b, b + 1, b + 2]);
    }
    Mesh {
        vertices,
        triangles,
    }
}
