//! Sparse points of a synthetic scene (`synth`), as structure-from-motion would find them:
//! for the mesher's tests and its measured distance to the true surface (docs/prepare.md).
//!
//! Each camera finds points where random pixels' rays meet the true surface; a point's track
//! is every camera that sees it (in its image, in front, unoccluded by the true surface). Then
//! noise (a random offset of `noise` × the scene's diagonal, each axis uniform in ±1) and
//! outliers (a share `outliers` of the points are wrong matches: moved along the finding
//! camera's ray to between 0.5 and 1.5 times their depth, with a track of that camera and one
//! other — a point moved so with its whole track would fail COLMAP's reprojection-error filter).

use super::mesher::Track;
use crate::rng::{uniform_f64, Purpose};
use crate::synth::Synth;
use glam::DVec3;

/// Sub-purpose of this module's random numbers within `Purpose::Synth`.
const STREAM: u64 = 0x5052_4550; // "PREP"

/// Points of a synthetic scene with their tracks, the camera centres, and the true surface
/// normal at each point (before noise; facing the first camera).
pub struct SyntheticPoints {
    pub tracks: Vec<Track>,
    pub cameras: Vec<DVec3>,
    pub normals: Vec<DVec3>,
}

/// `per_view` points found by each camera of `s` (module docs for noise and outliers).
pub fn points(s: &Synth, per_view: usize, noise: f64, outliers: f64, seed: u64) -> SyntheticPoints {
    let mesh = s.truth.to_mesh();
    let (lo, hi) = mesh.bbox();
    let diag = (hi - lo).length();
    let cams: Vec<&crate::scene::Camera> = s.views.iter().map(|v| &v.camera).collect();
    let centres: Vec<DVec3> = cams.iter().map(|c| c.center()).collect();
    let r = |a: u64, b: u64| uniform_f64(seed, Purpose::Synth, STREAM ^ a, b);
    let mut out = SyntheticPoints {
        tracks: Vec::new(),
        cameras: centres.clone(),
        normals: Vec::new(),
    };
    for (ci, cam) in cams.iter().enumerate() {
        for k in 0..per_view as u64 {
            let id = (ci as u64) << 32 | k;
            let (x, y) = (r(id, 0) * cam.width as f64, r(id, 1) * cam.height as f64);
            let d = cam.dir_world(x, y);
            let Some(hit) = s.truth.trace(centres[ci], d, 0.0, f64::INFINITY) else {
                continue;
            };
            let p = hit.pos;
            // Every camera that sees p.
            let seen: Vec<u32> = cams
                .iter()
                .enumerate()
                .filter(|(j, c)| {
                    let Some((u, v)) = c.project(p) else {
                        return false;
                    };
                    if !(0.0..c.width as f64).contains(&u) || !(0.0..c.height as f64).contains(&v) {
                        return false;
                    }
                    let to = p - centres[*j];
                    let dist = to.length();
                    let h = s.truth.trace(centres[*j], to / dist, 0.0, f64::INFINITY);
                    h.is_some_and(|h| (h.t - dist).abs() <= 1e-6 * dist.max(1.0))
                })
                .map(|(j, _)| j as u32)
                .collect();
            if seen.len() < 2 {
                continue;
            }
            let mut q = p + DVec3::new(
                2.0 * r(id, 2) - 1.0,
                2.0 * r(id, 3) - 1.0,
                2.0 * r(id, 4) - 1.0,
            ) * noise
                * diag;
            let mut seen = seen;
            if r(id, 5) < outliers {
                // A wrong match: two cameras, the point anywhere along the finding camera's ray.
                let c = centres[ci];
                q = c + (p - c) * (0.5 + r(id, 6));
                let other = seen
                    .iter()
                    .copied()
                    .filter(|&j| j as usize != ci)
                    .nth((r(id, 7) * (seen.len() - 1) as f64) as usize);
                seen = vec![ci as u32, other.unwrap_or(seen[0])];
            }
            out.tracks.push(Track {
                xyz: q,
                cameras: seen,
            });
            out.normals.push(hit.normal);
        }
    }
    out
}

/// `n` area samples of the true surface that at least two cameras see (in their image, in
/// front, unoccluded): where a mesh of the points can be asked to be.
pub fn seen_samples(s: &Synth, n: usize) -> Vec<DVec3> {
    let truth = s.truth.to_mesh();
    let centres: Vec<DVec3> = s.views.iter().map(|v| v.camera.center()).collect();
    crate::scene::distance::area_samples(&truth, n)
        .into_iter()
        .filter(|&p| {
            s.views
                .iter()
                .zip(&centres)
                .filter(|(v, c)| {
                    let cam = &v.camera;
                    let Some((u, w)) = cam.project(p) else {
                        return false;
                    };
                    if !(0.0..cam.width as f64).contains(&u)
                        || !(0.0..cam.height as f64).contains(&w)
                    {
                        return false;
                    }
                    let to = p - **c;
                    let dist = to.length();
                    s.truth
                        .trace(**c, to / dist, 0.0, f64::INFINITY)
                        .is_some_and(|h| h.t >= dist * (1.0 - 1e-6))
                })
                .take(2)
                .count()
                == 2
        })
        .collect()
}

/// Distances are capped at this share of the true surface's diagonal (a far-off piece counts as
/// this far; the exact search is slow for points far from a surface).
pub const CAP: f64 = 0.1;

/// Accuracy (`n` area samples of `mesh` to the true surface) and completeness (the seen samples
/// of the true surface to `mesh`): (mean, RMS) each, in scene units, each distance capped at
/// [`CAP`] × the truth's diagonal.
pub fn distances(
    s: &Synth,
    mesh: &crate::scene::Mesh,
    seen: &[DVec3],
    n: usize,
) -> ((f64, f64), (f64, f64)) {
    use crate::scene::distance::{area_samples, SurfaceIndex};
    use rayon::prelude::*;
    let truth = s.truth.to_mesh();
    let cap = CAP * crate::synth::perturb::diagonal(&truth);
    let stats = |idx: &SurfaceIndex, pts: &[DVec3]| {
        let d: Vec<f64> = pts
            .par_iter()
            .map(|&p| idx.distance_within(p, cap).min(cap))
            .collect();
        let m = d.len().max(1) as f64;
        (
            d.iter().sum::<f64>() / m,
            (d.iter().map(|x| x * x).sum::<f64>() / m).sqrt(),
        )
    };
    let acc = stats(&SurfaceIndex::new(&truth), &area_samples(mesh, n));
    let comp = stats(&SurfaceIndex::new(mesh), seen);
    (acc, comp)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::prepare::mesher::{mesh, Options};

    /// The mesher on the tiny synthetic scene (terrain and buildings seen from an aerial ring
    /// and close-ups), with noise and 2 % outliers: its surface lies near the true one and
    /// covers most of it. Distances as a share of the true surface's diagonal.
    #[test]
    fn mesher_on_a_synthetic_scene() {
        let s = crate::synth::build(crate::synth::Preset::Tiny, 3);
        let pts = points(&s, 400, 0.001, 0.02, 1);
        assert!(pts.tracks.len() > 2500, "{}", pts.tracks.len());
        let (m, stats) = mesh(
            &pts.tracks,
            &pts.cameras,
            &Options::default(),
            &|_, _, _| {},
            &|| false,
        )
        .unwrap();
        assert_eq!(stats.rays_cut_short, 0);
        let truth = s.truth.to_mesh();
        let diag = crate::synth::perturb::diagonal(&truth);
        let seen = seen_samples(&s, 20000);
        assert!(seen.len() > 5000, "{}", seen.len());
        let (acc, comp) = distances(&s, &m, &seen, 20000);
        eprintln!(
            "accuracy RMS {:.4} %, completeness RMS {:.4} % of {diag}",
            100.0 * acc.1 / diag,
            100.0 * comp.1 / diag
        );
        assert!(
            acc.1 / diag < 0.01,
            "mesh → truth {acc:?} (diagonal {diag})"
        );
        assert!(
            comp.1 / diag < 0.01,
            "seen truth → mesh {comp:?} (diagonal {diag})"
        );
        // Outliers and noise cost little against clean points: within 2× the clean RMS + 0.5 %.
        let clean = points(&s, 400, 0.0, 0.0, 1);
        let (mc, _) = mesh(
            &clean.tracks,
            &clean.cameras,
            &Options::default(),
            &|_, _, _| {},
            &|| false,
        )
        .unwrap();
        let (acc_clean, _) = distances(&s, &mc, &seen, 20000);
        assert!(
            acc.1 <= 2.0 * acc_clean.1 + 0.005 * diag,
            "{acc:?} vs clean {acc_clean:?}"
        );
    }
}
