//! A surface from a sparse reconstruction's points and the cameras that saw them: the
//! visibility-based Delaunay graph cut of Labatut, Pons & Keriven ("Robust and efficient
//! surface reconstruction from range data", Computer Graphics Forum 2009) — what COLMAP's
//! `delaunay_mesher` computes, which Debian's COLMAP (built without CGAL) cannot run.
//!
//! 1. The points are tetrahedralised ([`super::delaunay`]).
//! 2. Every observation is a line of sight from the camera centre to the point; it says the
//!    space between them is empty. Walking the cells it crosses from the point to the camera,
//!    each face crossed gets one vote against a cut that puts the camera side outside and the
//!    point side inside (the arc camera-side → point-side of the graph); the cell holding the
//!    camera gets one vote for outside (a link from the source), and the cell just behind the
//!    point, along the line of sight, one vote for inside (a link to the sink).
//! 3. A surface-quality term (Labatut's, `1 − min(cos φ, cos ψ)` with φ, ψ the angles at which
//!    the circumspheres of the two cells beside a face meet its plane, times
//!    [`Options::quality`]) is added both ways on every face: cutting through big, round
//!    cells costs more than cutting along the thin ones that lie on a sampled surface.
//! 4. The minimum cut ([`super::maxflow`]) labels every cell outside (source side) or inside;
//!    the surface is the faces between an inside and an outside cell, wound so their normals
//!    face the outside cell. Faces that touch the far vertices are left out.
//! 5. Triangles whose longest side exceeds [`Options::max_side_factor`] times the
//!    [`SIDE_PERCENTILE`] percentile of all sides are dropped (long slivers spanning unseen
//!    space, as COLMAP's `max_side_length_factor`).
//!
//! Votes are integer counts (atomic adds, so the rays run in parallel and the result is the
//! same on any thread count); the cut itself is sequential.

use super::delaunay::{face, orient, Tetrahedralization, NONE};
use super::maxflow::Graph;
use crate::scene::Mesh;
use anyhow::{bail, Result};
use glam::DVec3;
use rayon::prelude::*;
use std::sync::atomic::{AtomicU32, Ordering::Relaxed};
use std::time::{Duration, Instant};

/// Percentile of the surface's side lengths [`Options::max_side_factor`] multiplies.
pub const SIDE_PERCENTILE: f64 = 0.95;

/// Lines of sight handed to one parallel work item (a constant: see SPEC §5).
const RAY_CHUNK: usize = 1024;

/// Settings of the mesher.
#[derive(Clone, Debug, PartialEq)]
pub struct Options {
    /// Weight of the surface-quality term per face, in lines of sight (Labatut's λ).
    pub quality: f64,
    /// Drop triangles with a side longer than this many times the [`SIDE_PERCENTILE`] side
    /// length (0: keep every triangle).
    pub max_side_factor: f64,
    /// Points seen by fewer cameras than this are left out (2 = every triangulated point).
    pub min_track: usize,
    /// Drop connected pieces of the surface with fewer triangles than this share of the
    /// largest piece's (the closed bubbles a wrong match leaves floating in free space).
    pub min_component: f64,
}

impl Default for Options {
    fn default() -> Self {
        Options {
            quality: 1.0,
            max_side_factor: 8.0,
            min_track: 2,
            min_component: 0.01,
        }
    }
}

/// What the mesher did.
#[derive(Clone, Debug, Default, PartialEq, serde::Serialize)]
pub struct Stats {
    /// Points given, used (track long enough) and merged into an equal earlier one.
    pub points: usize,
    pub points_used: usize,
    pub points_merged: usize,
    /// Cells of the tetrahedralisation (with those touching the far vertices).
    pub cells: usize,
    /// Lines of sight cast, and the faces they crossed in all.
    pub rays: usize,
    pub crossings: u64,
    /// Lines of sight stopped by the step bound (a bug if ever non-zero).
    pub rays_cut_short: usize,
    /// Cells labelled inside.
    pub inside_cells: usize,
    /// Value of the minimum cut, in lines of sight.
    pub cut: f64,
    /// Triangles of the surface, and those dropped as too long.
    pub triangles: usize,
    pub dropped_long: usize,
    /// Triangles dropped with pieces smaller than [`Options::min_component`].
    pub dropped_small: usize,
    /// Seconds per stage: tetrahedralisation, lines of sight, graph cut, surface.
    pub seconds: [f64; 4],
}

/// A point and the cameras (indices into the camera centres) that saw it.
#[derive(Clone, Debug, PartialEq)]
pub struct Track {
    pub xyz: DVec3,
    pub cameras: Vec<u32>,
}

/// Mesh `tracks` seen from `cameras` (camera centres). `progress(stage, done, total)` is called
/// during the long stages ("tetrahedralise", "rays"); `stop()` returning true ends the work with
/// an error (an interrupt).
pub fn mesh(
    tracks: &[Track],
    cameras: &[DVec3],
    opts: &Options,
    progress: &(dyn Fn(&str, usize, usize) + Sync),
    stop: &(dyn Fn() -> bool + Sync),
) -> Result<(Mesh, Stats)> {
    let mut stats = Stats {
        points: tracks.len(),
        ..Stats::default()
    };
    let used = used_tracks(tracks, cameras, opts)?;
    stats.points_used = used.len();
    let xyz: Vec<DVec3> = used.iter().map(|t| t.xyz).collect();

    // 1. The tetrahedralisation.
    let t0 = Instant::now();
    let n = xyz.len();
    let tet = Tetrahedralization::with_progress(&xyz, cameras, &mut |k| {
        progress("tetrahedralise", k, n)
    })?;
    progress("tetrahedralise", n, n);
    stats.points_merged = (0..n).filter(|&i| tet.vertex_of[i] != i as u32).count();
    stats.cells = tet.cells.len();
    stats.seconds[0] = t0.elapsed().as_secs_f64();
    if stop() {
        bail!("interrupted");
    }

    // 2. Lines of sight.
    let t1 = Instant::now();
    let votes = cast_votes(&tet, &used, cameras, progress, stop, &mut stats)?;
    stats.seconds[1] = t1.elapsed().as_secs_f64();

    // 3–4. The graph, one node per cell, and its minimum cut.
    let t2 = Instant::now();
    let outside = graph_cut(&tet, &votes, opts.quality, &mut stats);
    stats.seconds[2] = t2.elapsed().as_secs_f64();

    // 5. The surface.
    let t3 = Instant::now();
    let tris = surface(&tet, &outside, opts, &mut stats);
    let mesh = used_vertices(&xyz, &tris);
    stats.seconds[3] = t3.elapsed().as_secs_f64();
    Ok((mesh, stats))
}

/// The points seen by at least [`Options::min_track`] cameras (4 at least are needed); an
/// error for a non-finite camera or a track naming a camera that is not there.
fn used_tracks<'a>(
    tracks: &'a [Track],
    cameras: &[DVec3],
    opts: &Options,
) -> Result<Vec<&'a Track>> {
    if let Some(k) = cameras.iter().position(|c| !c.is_finite()) {
        bail!("camera {k} has a non-finite centre {}", cameras[k]);
    }
    let used: Vec<&Track> = tracks
        .iter()
        .filter(|t| t.cameras.len() >= opts.min_track.max(1))
        .collect();
    for t in &used {
        if let Some(&c) = t.cameras.iter().find(|&&c| c as usize >= cameras.len()) {
            bail!(
                "a point is seen by camera {c}, but there are only {} cameras",
                cameras.len()
            );
        }
    }
    if used.len() < 4 {
        bail!(
            "{} of {} points are seen by at least {} cameras: too few to mesh (4 at least)",
            used.len(),
            tracks.len(),
            opts.min_track
        );
    }
    Ok(used)
}

/// The lines of sight's votes (step 2 of the module's account), as counts.
struct Votes {
    /// `into[cell * 4 + face]`: lines of sight entering `cell` through its face `face`
    /// (the cell on the point's side).
    into: Vec<u32>,
    /// Per cell: lines of sight whose camera it holds (votes for outside).
    source: Vec<u32>,
    /// Per cell: lines of sight whose point it is just behind (votes for inside).
    sink: Vec<u32>,
}

/// Walk every line of sight (in parallel, [`RAY_CHUNK`] per work item) and count its votes;
/// fills `stats.rays`, `crossings` and `rays_cut_short`.
fn cast_votes(
    tet: &Tetrahedralization,
    used: &[&Track],
    cameras: &[DVec3],
    progress: &(dyn Fn(&str, usize, usize) + Sync),
    stop: &(dyn Fn() -> bool + Sync),
    stats: &mut Stats,
) -> Result<Votes> {
    let rays: Vec<(u32, u32)> = used
        .iter()
        .enumerate()
        .flat_map(|(i, t)| {
            let v = tet.vertex_of[i];
            t.cameras.iter().map(move |&c| (v, c))
        })
        .collect();
    stats.rays = rays.len();
    let cells = tet.cells.len();
    let counts = |n: usize| -> Vec<AtomicU32> { (0..n).map(|_| AtomicU32::new(0)).collect() };
    let (votes_in, source, sink) = (counts(cells * 4), counts(cells), counts(cells));
    let done = AtomicU32::new(0);
    let interrupted = std::sync::atomic::AtomicBool::new(false);
    let (crossings, short): (Vec<u64>, Vec<usize>) = rays
        .par_chunks(RAY_CHUNK)
        .map(|chunk| {
            let mut star = Vec::new();
            let (mut crossed, mut short) = (0u64, 0usize);
            if interrupted.load(Relaxed) {
                return (0, 0);
            }
            for &(v, c) in chunk {
                let sight =
                    line_of_sight(tet, v, cameras[c as usize], &mut star, &mut |into, face| {
                        votes_in[into as usize * 4 + face].fetch_add(1, Relaxed);
                    });
                crossed += sight.crossed;
                short += sight.cut_short as usize;
                source[sight.camera_cell as usize].fetch_add(1, Relaxed);
                if let Some(b) = sight.behind {
                    sink[b as usize].fetch_add(1, Relaxed);
                }
            }
            let k = done.fetch_add(chunk.len() as u32, Relaxed) as usize + chunk.len();
            progress("rays", k, rays.len());
            if stop() {
                interrupted.store(true, Relaxed);
            }
            (crossed, short)
        })
        .unzip();
    if interrupted.load(Relaxed) {
        bail!("interrupted");
    }
    stats.crossings = crossings.iter().sum();
    stats.rays_cut_short = short.iter().sum();
    let plain = |v: Vec<AtomicU32>| v.into_iter().map(AtomicU32::into_inner).collect();
    Ok(Votes {
        into: plain(votes_in),
        source: plain(source),
        sink: plain(sink),
    })
}

/// The graph of the cells (votes plus `quality` times the surface-quality term on every face)
/// and its minimum cut: per cell, whether it is outside (source side). Fills `stats.cut` and
/// `inside_cells`.
fn graph_cut(
    tet: &Tetrahedralization,
    votes: &Votes,
    quality_weight: f64,
    stats: &mut Stats,
) -> Vec<bool> {
    let cells = tet.cells.len();
    let quality: Vec<f64> = if quality_weight > 0.0 {
        face_quality(tet)
    } else {
        Vec::new()
    };
    let mut g = Graph::new(cells);
    for t in 0..cells {
        g.add_terminal(t, votes.source[t] as f64, votes.sink[t] as f64);
        for i in 0..4 {
            let nb = tet.neighbors[t][i];
            if nb == NONE || (nb as usize) < t {
                continue;
            }
            let back = tet.neighbors[nb as usize]
                .iter()
                .position(|&x| x == t as u32)
                .unwrap();
            let q = if quality.is_empty() {
                0.0
            } else {
                quality_weight * quality[t * 4 + i]
            };
            // into[nb, back]: lines of sight going t → nb (t on the camera side).
            let t_to_nb = votes.into[nb as usize * 4 + back] as f64 + q;
            let nb_to_t = votes.into[t * 4 + i] as f64 + q;
            g.add_edge(t, nb as usize, t_to_nb, nb_to_t);
        }
    }
    stats.cut = g.max_flow();
    let outside: Vec<bool> = (0..cells).map(|t| g.source_side(t)).collect();
    stats.inside_cells = outside.iter().filter(|o| !**o).count();
    outside
}

/// The faces between an inside and an outside cell (none touching the far vertices), without
/// the long ones and the small pieces. Fills `stats.dropped_long`, `dropped_small` and
/// `triangles`.
fn surface(
    tet: &Tetrahedralization,
    outside: &[bool],
    opts: &Options,
    stats: &mut Stats,
) -> Vec<[u32; 3]> {
    let mut tris: Vec<[u32; 3]> = Vec::new();
    for t in 0..tet.cells.len() {
        if outside[t] {
            continue;
        }
        for i in 0..4 {
            let nb = tet.neighbors[t][i];
            if nb != NONE && !outside[nb as usize] {
                continue;
            }
            let f = face(&tet.cells[t], i);
            if f.iter().all(|&v| tet.is_input(v)) {
                tris.push(f);
            }
        }
    }
    let before = tris.len();
    if opts.max_side_factor > 0.0 {
        tris = drop_long(&tet.points, tris, opts.max_side_factor);
    }
    stats.dropped_long = before - tris.len();
    let before = tris.len();
    if opts.min_component > 0.0 {
        tris = drop_small_components(tris, tet.points.len(), opts.min_component);
    }
    stats.dropped_small = before - tris.len();
    stats.triangles = tris.len();
    tris
}

/// The mesh of `tris` (indices into `xyz`), keeping the vertices they use, in point order.
fn used_vertices(xyz: &[DVec3], tris: &[[u32; 3]]) -> Mesh {
    let mut index = vec![u32::MAX; xyz.len()];
    let mut vertices = Vec::new();
    for tri in tris {
        for &v in tri {
            if index[v as usize] == u32::MAX {
                index[v as usize] = 0;
            }
        }
    }
    for (v, slot) in index.iter_mut().enumerate() {
        if *slot == 0 {
            *slot = vertices.len() as u32;
            vertices.push(xyz[v]);
        }
    }
    let triangles = tris.iter().map(|t| t.map(|v| index[v as usize])).collect();
    Mesh {
        vertices,
        triangles,
    }
}

/// What walking one line of sight found.
struct Sight {
    /// The cell holding the camera (or the last one reached).
    camera_cell: u32,
    /// The cell just behind the point, along the line of sight.
    behind: Option<u32>,
    crossed: u64,
    cut_short: bool,
}

/// A walk visits far fewer cells; the bound only guards against a bug looping forever.
const MAX_STEPS: usize = 1 << 20;

/// Walk from vertex `v` towards the camera centre `cam`, calling `cross(cell, face)` for each
/// face crossed, with the cell on the point's side and its face index.
fn line_of_sight(
    tet: &Tetrahedralization,
    v: u32,
    cam: DVec3,
    star: &mut Vec<u32>,
    cross: &mut dyn FnMut(u32, usize),
) -> Sight {
    let p = tet.points[v as usize];
    tet.star(v, star);
    // The cell around v that the ray towards q leaves v through.
    let cone = |q: DVec3| -> Option<u32> {
        star.iter().copied().find(|&t| {
            let c = &tet.cells[t as usize];
            (0..4).all(|j| c[j] == v || tet.side(t, j, q) >= 0.0)
        })
    };
    let behind = cone(p + (p - cam));
    let mut sight = Sight {
        camera_cell: star.first().copied().unwrap_or(0),
        behind,
        crossed: 0,
        cut_short: false,
    };
    let Some(mut t) = cone(cam) else {
        return sight;
    };
    // Leave the first cell through the face opposite v.
    let mut exit = tet.cells[t as usize].iter().position(|&x| x == v).unwrap();
    for _ in 0..MAX_STEPS {
        if tet.side(t, exit, cam) >= 0.0 {
            // The camera is in t (or on its exit face).
            sight.camera_cell = t;
            return sight;
        }
        let nb = tet.neighbors[t as usize][exit];
        if nb == NONE {
            sight.camera_cell = t;
            return sight;
        }
        cross(t, exit);
        sight.crossed += 1;
        let entry = tet.neighbors[nb as usize]
            .iter()
            .position(|&x| x == t)
            .unwrap();
        t = nb;
        exit = match next_exit(tet, t, entry, p, cam) {
            Some(e) => e,
            None => {
                sight.camera_cell = t;
                return sight;
            }
        };
    }
    sight.cut_short = true;
    sight.camera_cell = t;
    sight
}

/// The face of cell `t` (entered through `entry`) the segment `p → cam` leaves through; `None`
/// when `cam` is inside `t`.
fn next_exit(
    tet: &Tetrahedralization,
    t: u32,
    entry: usize,
    p: DVec3,
    cam: DVec3,
) -> Option<usize> {
    let c = &tet.cells[t as usize];
    let mut beyond = [0usize; 3];
    let mut m = 0;
    for j in 0..4 {
        if j != entry && tet.side(t, j, cam) < 0.0 {
            beyond[m] = j;
            m += 1;
        }
    }
    match m {
        0 => None,
        1 => Some(beyond[0]),
        _ => {
            // The line p → cam passes through the triangle of the exit face.
            let through = |j: usize| {
                let f = face(c, j).map(|x| tet.points[x as usize]);
                let s = [
                    orient(p, cam, f[0], f[1]),
                    orient(p, cam, f[1], f[2]),
                    orient(p, cam, f[2], f[0]),
                ];
                s.iter().all(|&x| x >= 0.0) || s.iter().all(|&x| x <= 0.0)
            };
            Some(
                beyond[..m]
                    .iter()
                    .copied()
                    .find(|&j| through(j))
                    .unwrap_or(beyond[0]),
            )
        }
    }
}

/// Circumcentre and radius of a tetrahedron (`None` when flat).
fn circumsphere(a: DVec3, b: DVec3, c: DVec3, d: DVec3) -> Option<(DVec3, f64)> {
    let (u, v, w) = (b - a, c - a, d - a);
    let det = 2.0 * u.dot(v.cross(w));
    if det.abs() <= f64::MIN_POSITIVE {
        return None;
    }
    let o = (v.cross(w) * u.length_squared()
        + w.cross(u) * v.length_squared()
        + u.cross(v) * w.length_squared())
        / det;
    o.is_finite().then(|| (a + o, o.length()))
}

/// Labatut's surface quality per face `t*4 + i`: `1 − min(cos φ, cos ψ)`, `cos φ = |d| / R` for
/// each neighbouring cell (its circumcentre at distance `d` from the face's plane, radius `R`).
/// Faces touching a far vertex get 0.
fn face_quality(tet: &Tetrahedralization) -> Vec<f64> {
    let spheres: Vec<Option<(DVec3, f64)>> = tet
        .cells
        .par_iter()
        .map(|c| {
            if tet.is_finite_cell(c) {
                let p = c.map(|v| tet.points[v as usize]);
                circumsphere(p[0], p[1], p[2], p[3])
            } else {
                None
            }
        })
        .collect();
    (0..tet.cells.len() * 4)
        .into_par_iter()
        .map(|k| {
            let (t, i) = (k / 4, k % 4);
            let nb = tet.neighbors[t][i];
            let f = face(&tet.cells[t], i);
            if nb == NONE || !f.iter().all(|&v| tet.is_input(v)) {
                return 0.0;
            }
            let q = f.map(|v| tet.points[v as usize]);
            let n = (q[1] - q[0]).cross(q[2] - q[0]);
            let len = n.length();
            if len <= 0.0 {
                return 0.0;
            }
            let n = n / len;
            let cosine = |s: Option<(DVec3, f64)>| match s {
                Some((o, r)) if r > 0.0 => ((o - q[0]).dot(n).abs() / r).min(1.0),
                // A cell with a far vertex: its sphere is huge and nearly flat on the face.
                _ => 1.0,
            };
            1.0 - cosine(spheres[t]).min(cosine(spheres[nb as usize]))
        })
        .collect()
}

/// Drop triangles with a side longer than `factor ×` the [`SIDE_PERCENTILE`] side length.
fn drop_long(points: &[DVec3], tris: Vec<[u32; 3]>, factor: f64) -> Vec<[u32; 3]> {
    let side =
        |t: &[u32; 3], k: usize| (points[t[k] as usize] - points[t[(k + 1) % 3] as usize]).length();
    let mut sides: Vec<f64> = tris
        .iter()
        .flat_map(|t| (0..3).map(move |k| side(t, k)))
        .collect();
    if sides.is_empty() {
        return tris;
    }
    let k = ((sides.len() - 1) as f64 * SIDE_PERCENTILE).round() as usize;
    let (_, &mut limit, _) = sides.select_nth_unstable_by(k, f64::total_cmp);
    let limit = limit * factor;
    tris.into_iter()
        .filter(|t| (0..3).all(|k| side(t, k) <= limit))
        .collect()
}

/// Keep the pieces (triangles connected through shared vertices) with at least `share` of the
/// largest piece's triangles.
fn drop_small_components(tris: Vec<[u32; 3]>, n_vertices: usize, share: f64) -> Vec<[u32; 3]> {
    let mut parent: Vec<u32> = (0..n_vertices as u32).collect();
    fn find(p: &mut [u32], mut x: u32) -> u32 {
        while p[x as usize] != x {
            p[x as usize] = p[p[x as usize] as usize];
            x = p[x as usize];
        }
        x
    }
    for t in &tris {
        for k in 1..3 {
            let (a, b) = (find(&mut parent, t[0]), find(&mut parent, t[k]));
            if a != b {
                parent[a.max(b) as usize] = a.min(b);
            }
        }
    }
    let mut size = vec![0usize; n_vertices];
    let roots: Vec<u32> = tris.iter().map(|t| find(&mut parent, t[0])).collect();
    for &r in &roots {
        size[r as usize] += 1;
    }
    let largest = size.iter().copied().max().unwrap_or(0);
    let keep = (share * largest as f64).ceil() as usize;
    tris.into_iter()
        .zip(roots)
        .filter(|(_, r)| size[*r as usize] >= keep)
        .map(|(t, _)| t)
        .collect()
}

/// Seconds as a short string for progress lines.
pub fn secs(d: Duration) -> String {
    format!("{:.1} s", d.as_secs_f64())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::rng::{uniform_f64, Purpose};
    use crate::scene::distance::{surface_distance, SurfaceIndex};

    /// Points on a unit sphere (with noise), each seen by the cameras on a ring around it that
    /// face its side: the mesh is a closed surface near the sphere.
    #[test]
    fn sphere_from_a_ring_of_cameras() {
        let cams: Vec<DVec3> = (0..12)
            .map(|k| {
                let a = k as f64 * std::f64::consts::TAU / 12.0;
                DVec3::new(
                    4.0 * a.cos(),
                    4.0 * a.sin(),
                    if k % 2 == 0 { 1.5 } else { -1.5 },
                )
            })
            .collect();
        let tracks: Vec<Track> = (0..3000u64)
            .map(|k| {
                let r = |b| uniform_f64(5, Purpose::Test, k, b);
                let z = 2.0 * r(0) - 1.0;
                let a = std::f64::consts::TAU * r(1);
                let s = (1.0 - z * z).sqrt();
                let n = DVec3::new(s * a.cos(), s * a.sin(), z);
                let p = n * (1.0 + 0.005 * (r(2) - 0.5));
                // Cameras in front of the point's tangent plane.
                let cameras = (0..12u32)
                    .filter(|&c| (cams[c as usize] - p).dot(n) > 0.3)
                    .collect();
                Track { xyz: p, cameras }
            })
            .collect();
        let (m, stats) = mesh(&tracks, &cams, &Options::default(), &|_, _, _| {}, &|| {
            false
        })
        .unwrap();
        assert_eq!(stats.rays_cut_short, 0);
        assert!(stats.triangles > 4000, "{stats:?}");
        // Every vertex is on the sphere; area samples are within the noise of it.
        let truth = crate::raycast::meshes::icosphere(5);
        let d = surface_distance(&m, &SurfaceIndex::new(&truth), 5000);
        assert!(d.rms < 0.02, "{d:?}");
        // And it covers the sphere (truth → mesh).
        let back = surface_distance(&truth, &SurfaceIndex::new(&m), 5000);
        assert!(back.rms < 0.03, "{back:?}");
        // The same on one thread and on several (votes are integer counts).
        let one = rayon::ThreadPoolBuilder::new()
            .num_threads(1)
            .build()
            .unwrap();
        let (m1, _) = one
            .install(|| {
                mesh(&tracks, &cams, &Options::default(), &|_, _, _| {}, &|| {
                    false
                })
            })
            .unwrap();
        assert_eq!(m1, m);
    }

    #[test]
    fn circumsphere_of_a_corner_tetrahedron() {
        let (o, r) = circumsphere(DVec3::ZERO, DVec3::X, DVec3::Y, DVec3::Z).unwrap();
        assert!((o - DVec3::splat(0.5)).length() < 1e-15);
        assert!((r - 0.75f64.sqrt()).abs() < 1e-15);
    }
}
