//! Mesh resolution changes for the paper's ablations: quadric-error decimation (Table 5, "mesh
//! decimation \[11\]", Garland & Heckbert) through the maintained `meshopt` crate
//! (meshoptimizer's `meshopt_simplify`), and 1→4 midpoint subdivision (used to give the
//! vertex-feature baseline of Fig. 2b a parameter budget comparable to the hash grid's).
//!
//! Both keep the mesh in f64 world coordinates. Decimation hands meshoptimizer f32 positions in
//! the LOCAL frame of SPEC §4.1 (vertices minus the bounding-box centre), so georeferenced scenes
//! (UTM, ~1e6 m) lose no precision in the error metric; the output reuses the ORIGINAL f64
//! vertices (meshoptimizer's simplifier only collapses edges onto existing vertices), so every
//! output vertex is exactly an input vertex.
//!
//! Normalisation note: a scene loaded with a decimated mesh normalises by THAT mesh's bounding
//! box (SPEC §4.1). meshoptimizer keeps the topological border (border vertices only collapse
//! along the border), so the bounding box barely changes (tested), and a model trained on the
//! decimated mesh is evaluated with its own saved normalisation anyway.

use super::Mesh;
use anyhow::{bail, ensure, Result};
use glam::DVec3;
use std::collections::HashMap;

/// What [`decimate_report`] did.
#[derive(Clone, Debug, PartialEq)]
pub struct DecimateReport {
    pub faces_in: usize,
    pub faces_target: usize,
    pub faces_out: usize,
    pub vertices_out: usize,
    /// meshoptimizer's resulting error, relative to the mesh extent.
    pub relative_error: f32,
}

/// Decimate to about `ratio` of the faces (0 < ratio ≤ 1) with quadric error metrics
/// (`meshopt::simplify`, no error limit, border kept). Unreferenced vertices are removed; the
/// kept vertices stay in their original order. See the module doc.
pub fn decimate(mesh: &Mesh, ratio: f64) -> Result<Mesh> {
    Ok(decimate_report(mesh, ratio)?.0)
}

/// [`decimate`] with a report of the face counts and the error.
pub fn decimate_report(mesh: &Mesh, ratio: f64) -> Result<(Mesh, DecimateReport)> {
    ensure!(
        ratio.is_finite() && ratio > 0.0 && ratio <= 1.0,
        "decimate: ratio {ratio} must be in (0, 1]"
    );
    ensure!(
        !mesh.triangles.is_empty(),
        "decimate: the mesh has no triangles"
    );
    let nv = mesh.vertices.len();
    if let Some((i, t)) = mesh
        .triangles
        .iter()
        .enumerate()
        .find(|(_, t)| t.iter().any(|&k| k as usize >= nv))
    {
        bail!("decimate: triangle {i} {t:?} refers to a vertex beyond the {nv} vertices");
    }
    let (lo, hi) = mesh.bbox();
    let center = (lo + hi) * 0.5;
    // Local frame, then f32 (SPEC §4.1).
    let local: Vec<[f32; 3]> = mesh
        .vertices
        .iter()
        .map(|v| (*v - center).as_vec3().to_array())
        .collect();
    let indices: Vec<u32> = mesh.triangles.iter().flatten().copied().collect();
    let faces_in = mesh.triangles.len();
    let faces_target = ((faces_in as f64 * ratio).round() as usize).max(1);
    let mut err = 0.0f32;
    // target_error = 1.0: up to the whole mesh extent, i.e. no error limit — the face count is
    // the only target (as a decimation to a face budget is).
    let out = meshopt::simplify_decoder(
        &indices,
        &local,
        faces_target * 3,
        1.0,
        meshopt::SimplifyOptions::None,
        Some(&mut err),
    );
    let mut m = compact(&mesh.vertices, &out);
    // meshoptimizer never emits repeated indices; drop any zero-area triangle defensively.
    m.triangles
        .retain(|t| t[0] != t[1] && t[1] != t[2] && t[0] != t[2]);
    let report = DecimateReport {
        faces_in,
        faces_target,
        faces_out: m.triangles.len(),
        vertices_out: m.vertices.len(),
        relative_error: err,
    };
    Ok((m, report))
}

/// Keep the vertices `indices` refer to (original order) and renumber.
fn compact(vertices: &[DVec3], indices: &[u32]) -> Mesh {
    let mut used = vec![false; vertices.len()];
    for &i in indices {
        used[i as usize] = true;
    }
    let mut remap = vec![u32::MAX; vertices.len()];
    let mut out = Mesh::default();
    for (i, v) in vertices.iter().enumerate() {
        if used[i] {
            remap[i] = out.vertices.len() as u32;
            out.vertices.push(*v);
        }
    }
    out.triangles = indices
        .chunks_exact(3)
        .map(|t| {
            [
                remap[t[0] as usize],
                remap[t[1] as usize],
                remap[t[2] as usize],
            ]
        })
        .collect();
    out
}

/// `levels` rounds of 1→4 midpoint subdivision: every triangle (a, b, c) becomes (a, ab, ca),
/// (ab, b, bc), (ca, bc, c), (ab, bc, ca) with one shared midpoint per edge (so the surface and
/// its bounding box are unchanged and the mesh stays watertight where it was). Faces × 4^levels,
/// vertices ≈ × 4^levels / 2 for a closed or large mesh. Midpoints are `(a + b) / 2` in f64.
pub fn subdivide(mesh: &Mesh, levels: u32) -> Result<Mesh> {
    ensure!(
        levels <= 6,
        "subdivide: {levels} levels is more than 6 (× 4096 faces)"
    );
    let faces = mesh.triangles.len() as u128 * 4u128.pow(levels);
    ensure!(
        faces <= u32::MAX as u128 / 2,
        "subdivide: {faces} faces would not fit 32-bit indices"
    );
    let mut m = mesh.clone();
    for _ in 0..levels {
        let mut mid: HashMap<(u32, u32), u32> = HashMap::with_capacity(m.triangles.len() * 2);
        let mut verts = m.vertices.clone();
        let mut tris = Vec::with_capacity(m.triangles.len() * 4);
        let mut midpoint = |a: u32, b: u32, verts: &mut Vec<DVec3>| -> u32 {
            let key = (a.min(b), a.max(b));
            *mid.entry(key).or_insert_with(|| {
                verts.push((verts[a as usize] + verts[b as usize]) * 0.5);
                (verts.len() - 1) as u32
            })
        };
        for &[a, b, c] in &m.triangles {
            let ab = midpoint(a, b, &mut verts);
            let bc = midpoint(b, c, &mut verts);
            let ca = midpoint(c, a, &mut verts);
            tris.extend_from_slice(&[[a, ab, ca], [ab, b, bc], [ca, bc, c], [ab, bc, ca]]);
        }
        m = Mesh {
            vertices: verts,
            triangles: tris,
        };
    }
    Ok(m)
}

/// The most memory [`subdivide`] holds at once for `levels` rounds (bytes): during the last
/// round, the previous mesh, the new vertex array as it grows (its last reallocation holds the
/// old and the new buffer), the new triangles and the midpoint map (`HashMap` buckets of 13
/// bytes, doubled — old and new — when the edges outgrow it). Exact counts, not bounds: the
/// input's distinct edges E, then per round V += E, E = 2E + 3T, T ×= 4. An upper bound of the
/// peak when the allocator adds nothing; the input mesh, which the caller keeps, is not counted.
pub fn subdivide_bytes(mesh: &Mesh, levels: u32) -> u64 {
    if levels == 0 {
        return 0;
    }
    let mut edges: Vec<u64> = (mesh.triangles.iter())
        .flat_map(|&[a, b, c]| [(a, b), (b, c), (c, a)])
        .map(|(a, b)| (a.min(b) as u64) << 32 | a.max(b) as u64)
        .collect();
    edges.sort_unstable();
    edges.dedup();
    let (mut v, mut e, mut t) = (
        mesh.vertices.len() as u64,
        edges.len() as u64,
        mesh.triangles.len() as u64,
    );
    let (vert, tri) = (
        std::mem::size_of::<DVec3>() as u64,
        std::mem::size_of::<[u32; 3]>() as u64,
    );
    let mut peak = 0u64;
    for _ in 0..levels {
        // The vertex array: cloned at capacity v, doubled until it holds v + e.
        let (mut cap, mut verts) = (v, v);
        while cap < v + e {
            verts = verts.max(cap + 2 * cap);
            cap *= 2;
        }
        verts = verts.max(cap);
        // hashbrown's buckets for a capacity: the next power of two of 8/7 of it (≥ 4).
        let mut buckets = (2 * t * 8 / 7).next_power_of_two().max(4);
        let mut map = buckets;
        while buckets * 7 / 8 < e {
            map = map.max(buckets + 2 * buckets);
            buckets *= 2;
        }
        map = map.max(buckets);
        let round = v * vert + t * tri + verts * vert + 4 * t * tri + map * 13;
        peak = peak.max(round);
        (v, e, t) = (v + e, 2 * e + 3 * t, 4 * t);
    }
    peak
}

/// [`crate::sysmem::check_fits`] for `levels` rounds of midpoint subdivision of `mesh`
/// ([`subdivide`], which holds [`subdivide_bytes`] at its peak): `what` names the request (`subdivide --levels 6`), `fix` what to change.
pub fn check_subdivide(mesh: &Mesh, levels: u32, what: &str, fix: &str) -> Result<()> {
    crate::sysmem::check_fits(
        subdivide_bytes(mesh, levels) as f64,
        &format!(
            "{what}: {} faces",
            mesh.triangles.len() as u64 * 4u64.pow(levels)
        ),
        fix,
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A bumpy height-field grid of `n × n` quads (2 triangles each) over [0, 10]², offset far
    /// from the origin (georeferenced-like coordinates).
    fn terrain(n: u32) -> Mesh {
        let off = DVec3::new(5.0e5, 4.0e6, 100.0);
        let mut m = Mesh::default();
        for j in 0..=n {
            for i in 0..=n {
                let (x, y) = (10.0 * i as f64 / n as f64, 10.0 * j as f64 / n as f64);
                let z = 0.8 * (0.7 * x).sin() * (0.5 * y).cos() + 0.1 * (3.1 * x + 1.7 * y).sin();
                m.vertices.push(off + DVec3::new(x, y, z));
            }
        }
        let w = n + 1;
        for j in 0..n {
            for i in 0..n {
                let (a, b, c, d) = (
                    j * w + i,
                    j * w + i + 1,
                    (j + 1) * w + i,
                    (j + 1) * w + i + 1,
                );
                m.triangles.push([a, b, d]);
                m.triangles.push([a, d, c]);
            }
        }
        m
    }

    #[test]
    fn decimation_hits_the_face_budget_and_keeps_the_surface() {
        let m = terrain(60); // 7200 triangles
        let (d, r) = decimate_report(&m, 0.1).unwrap();
        assert_eq!(r.faces_in, 7200);
        assert_eq!(r.faces_target, 720);
        // Within 10% of the target (meshoptimizer stops at or just below it).
        let f = d.triangles.len() as f64;
        assert!((f - 720.0).abs() <= 72.0, "{r:?}");
        assert_eq!(r.faces_out, d.triangles.len());
        // Every output vertex is an input vertex (exactly), all are referenced, indices valid.
        let set: std::collections::HashSet<[u64; 3]> = m
            .vertices
            .iter()
            .map(|v| v.to_array().map(f64::to_bits))
            .collect();
        assert!(d
            .vertices
            .iter()
            .all(|v| set.contains(&v.to_array().map(f64::to_bits))));
        let mut used = vec![false; d.vertices.len()];
        for t in &d.triangles {
            for &k in t {
                used[k as usize] = true;
            }
        }
        assert!(used.iter().all(|&u| u));
        assert!(d.vertices.len() < m.vertices.len() / 5);
        // Bounding box nearly unchanged (border kept): within 1% of the extent per axis.
        let ((lo0, hi0), (lo1, hi1)) = (m.bbox(), d.bbox());
        let ext = hi0 - lo0;
        for a in 0..3 {
            assert!(
                (lo0[a] - lo1[a]).abs() <= 0.01 * ext[a],
                "axis {a}: {lo0} vs {lo1}"
            );
            assert!(
                (hi0[a] - hi1[a]).abs() <= 0.01 * ext[a],
                "axis {a}: {hi0} vs {hi1}"
            );
        }
        // The decimated surface stays close to the original: every original vertex is within
        // 0.1 (1% of the 10-unit extent) of the decimated mesh's height at its (x, y).
        let dist = max_height_error(&m, &d);
        assert!(dist < 0.1, "max height error {dist}");
        // Deterministic.
        assert_eq!(decimate(&m, 0.1).unwrap(), d);
    }

    /// Max |z_original − z_decimated(x, y)| over the original vertices (height fields only).
    fn max_height_error(orig: &Mesh, dec: &Mesh) -> f64 {
        let mut worst: f64 = 0.0;
        for p in &orig.vertices {
            let mut best = f64::INFINITY;
            for t in &dec.triangles {
                let [a, b, c] = t.map(|k| dec.vertices[k as usize]);
                // Barycentrics of (p.x, p.y) in the projected triangle.
                let det = (b.y - c.y) * (a.x - c.x) + (c.x - b.x) * (a.y - c.y);
                if det.abs() < 1e-18 {
                    continue;
                }
                let l0 = ((b.y - c.y) * (p.x - c.x) + (c.x - b.x) * (p.y - c.y)) / det;
                let l1 = ((c.y - a.y) * (p.x - c.x) + (a.x - c.x) * (p.y - c.y)) / det;
                let l2 = 1.0 - l0 - l1;
                if l0 >= -1e-9 && l1 >= -1e-9 && l2 >= -1e-9 {
                    best = best.min((l0 * a.z + l1 * b.z + l2 * c.z - p.z).abs());
                }
            }
            worst = worst.max(best);
        }
        worst
    }

    #[test]
    fn ratio_one_keeps_every_face_and_bad_input_is_an_error() {
        let m = terrain(8);
        assert_eq!(
            decimate(&m, 1.0).unwrap().triangles.len(),
            m.triangles.len()
        );
        assert!(decimate(&m, 0.0).is_err());
        assert!(decimate(&m, 1.5).is_err());
        assert!(decimate(&m, f64::NAN).is_err());
        assert!(decimate(&Mesh::default(), 0.5).is_err());
        let mut bad = m.clone();
        bad.triangles[3][1] = 10_000;
        let e = decimate(&bad, 0.5).unwrap_err().to_string();
        assert!(e.contains("triangle 3"), "{e}");
    }

    #[test]
    fn subdivision_quadruples_faces_and_keeps_the_surface() {
        let m = terrain(4); // 32 triangles, 25 vertices, 56 edges (20 + 20 + 16 diagonals)
        let s = subdivide(&m, 2).unwrap();
        assert_eq!(s.triangles.len(), 32 * 16);
        // One level: V + E new vertices (shared edges deduplicated).
        let s1 = subdivide(&m, 1).unwrap();
        assert_eq!(s1.vertices.len(), 25 + 56);
        assert_eq!(s.bbox(), m.bbox());
        // The original vertices come first, unchanged.
        assert_eq!(&s.vertices[..25], &m.vertices[..]);
        assert_eq!(subdivide(&m, 0).unwrap(), m);
        // Area is preserved.
        let area = |m: &Mesh| -> f64 {
            m.triangles
                .iter()
                .map(|t| {
                    let [a, b, c] = t.map(|k| m.vertices[k as usize]);
                    0.5 * (b - a).cross(c - a).length()
                })
                .sum()
        };
        assert!((area(&s) - area(&m)).abs() < 1e-9 * area(&m));
        assert!(subdivide(&m, 7).is_err());
    }

    /// [`subdivide_bytes`] covers what the subdivided mesh holds, without being far above it.
    #[test]
    fn subdivide_bytes_bounds_the_result() {
        let m = terrain(20);
        assert_eq!(subdivide_bytes(&m, 0), 0);
        for levels in 1..=3 {
            let s = subdivide(&m, levels).unwrap();
            let held = (s.vertices.capacity() * 24 + s.triangles.capacity() * 12) as u64;
            let est = subdivide_bytes(&m, levels);
            assert!(est > held && est < 4 * held, "{levels}: {est} for {held}");
        }
    }
}
