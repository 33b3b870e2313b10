//! Does the mesh stand in the cameras' frame? The reconstruction the cameras come from has its
//! own 3-D points (COLMAP's `points3D`, nerfstudio's `sparse_pc.ply`), which lie on the
//! surfaces the photos see; a mesh in the same frame passes through them. A mesh from another
//! tool's coordinate system, a rotated or rescaled export, or a transforms file read in the wrong
//! frame does not — and nothing else catches it when the mesh still fills the views (the tiny
//! fixture's mesh turned a quarter turn about x still meets 70 % of the training rays).
//!
//! [`check`] measures both ways, and [`Agreement::disagrees`] needs both to fail:
//! * points → mesh: of the points inside the bounding box of the mesh's triangles (grown by
//!   [`BOX_MARGIN`] of its diagonal, so a mesh cropped to an object is judged on that object's
//!   points), the share within [`NEAR`] of the size of the region the cameras see
//!   ([`seen_size`], not the mesh's diagonal, which background inflates) (`distance::SurfaceIndex`,
//!   exact, stopped at the threshold) is below [`MIN_NEAR_SHARE`], or fewer than [`MIN_POINTS`]
//!   lie inside the box;
//! * mesh → points: of [`MESH_SAMPLES`] area samples of the mesh, the share with a point within
//!   [`COVER`] of that size is below [`MIN_COVER_SHARE`].
//!
//! One way alone is not enough. A real COLMAP workspace (5 photos, `meshed-poisson.ply` trimmed
//! to a floor by `--trim 10`) has only 9 % of its in-box points on the mesh — the trimmed-away
//! objects' points stand above it — but 65 % of its surface has a point within 5 %; turned a
//! quarter about any axis through its centre, 7–22 %. The tiny fixture: 99 % of its surface in
//! place whether 100 or 3,000 points, 9–20 % turned about x. A loader's warning, not an error.

use super::distance::SurfaceIndex;
use super::{colmap, transforms, Camera, CameraFormat, Mesh};
use anyhow::Result;
use glam::DVec3;
use rayon::prelude::*;
use std::path::{Path, PathBuf};

/// Observations a COLMAP point needs to be used (fewer are the model's least reliable points);
/// all are used when fewer than [`MIN_POINTS`] have that many.
pub const MIN_TRACK: u32 = 3;
/// Points measured at most (an even stride through the file's order).
pub const MAX_POINTS: usize = 20_000;
/// Fewer points than this in all: no verdict; fewer inside the box: the points miss the mesh.
pub const MIN_POINTS: usize = 50;
/// A point is on the mesh within this fraction of the size of the region the cameras see
/// ([`seen_size`]; the mesh's bounding-box diagonal when no camera sees it).
pub const NEAR: f64 = 0.01;
/// The mesh's bounding box is grown by this fraction of its diagonal on every side.
pub const BOX_MARGIN: f64 = 0.05;
/// Below this share of the in-box points on the mesh, the points disagree with the mesh.
pub const MIN_NEAR_SHARE: f64 = 0.3;
/// Area samples of the mesh measured against the points.
pub const MESH_SAMPLES: usize = 4000;
/// A mesh sample is covered by a point within this fraction of the seen region's size (sparse
/// points are far apart where the photos have little texture: a looser bound than [`NEAR`]).
pub const COVER: f64 = 0.05;
/// Below this share of covered mesh samples, the mesh disagrees with the points.
pub const MIN_COVER_SHARE: f64 = 0.4;

/// A reconstruction's points, in the frame the scene's cameras were loaded in.
#[derive(Clone, Debug)]
pub struct SparsePoints {
    /// The file they were read from.
    pub source: PathBuf,
    pub xyz: Vec<DVec3>,
}

/// The points of the scene's camera file, if it has any: COLMAP's `points3D` (the model
/// [`colmap::find_layout`] picks; points seen by at least [`MIN_TRACK`] images), a transforms
/// file's `ply_file_path` (moved like its cameras); MVSNet cameras have none.
pub fn find(
    dir: &Path,
    format: CameraFormat,
    applied: transforms::AppliedTransform,
) -> Result<Option<SparsePoints>> {
    let found = match format {
        CameraFormat::Colmap => match colmap::find_layout(dir) {
            Some(layout) => colmap::read_points(&layout.model)?.map(|(source, pts)| {
                let reliable = pts.iter().filter(|p| p.1 >= MIN_TRACK).count();
                let keep = if reliable >= MIN_POINTS { MIN_TRACK } else { 0 };
                let xyz = pts.iter().filter(|p| p.1 >= keep).map(|p| p.0).collect();
                (source, xyz)
            }),
            None => None,
        },
        CameraFormat::Transforms => {
            let file = dir.join("transforms.json");
            if file.is_file() {
                transforms::sparse_points(&file, applied)?
            } else {
                None
            }
        }
        CameraFormat::MvsNet | CameraFormat::Metashape => None,
    };
    Ok(found.map(|(source, xyz)| SparsePoints { source, xyz }))
}

/// What [`check`] measured.
#[derive(Clone, Debug, PartialEq)]
pub struct Agreement {
    /// Points measured (after the track filter and the [`MAX_POINTS`] stride).
    pub measured: usize,
    /// Of those, inside the grown bounding box.
    pub inside: usize,
    /// Of those inside, within `tolerance` of the mesh.
    pub near: usize,
    /// The distance that counts as on the mesh ([`NEAR`] × `size`).
    pub tolerance: f64,
    /// The size tolerances are measured in: the seen region's ([`seen_size`]), else the mesh's
    /// diagonal.
    pub size: f64,
    /// Area samples of the mesh measured, and of those, with a point within [`COVER`] ×
    /// `size`.
    pub samples: usize,
    pub covered: usize,
}

impl Agreement {
    /// Share of the in-box points on the mesh (0 with none inside).
    pub fn share(&self) -> f64 {
        self.near as f64 / self.inside.max(1) as f64
    }

    /// Share of the mesh's samples with a point near them.
    pub fn cover(&self) -> f64 {
        self.covered as f64 / self.samples.max(1) as f64
    }

    /// Whether the frames disagree, both ways (module docs); `false` when there is too little
    /// to judge.
    pub fn disagrees(&self) -> bool {
        self.judged() && !self.agrees_somehow()
    }

    /// Whether the mesh and the points were found in one frame (`false` when there is too little
    /// to judge).
    pub fn agrees(&self) -> bool {
        self.judged() && self.agrees_somehow()
    }

    /// Enough points to judge.
    fn judged(&self) -> bool {
        self.measured >= MIN_POINTS
    }

    /// One of the two ways passes.
    fn agrees_somehow(&self) -> bool {
        (self.inside >= MIN_POINTS && self.share() >= MIN_NEAR_SHARE)
            || self.cover() >= MIN_COVER_SHARE
    }
}

/// Area samples of the mesh [`seen_size`] measures.
pub const SEEN_SAMPLES: usize = 2000;

/// The size of the region of `mesh` the cameras see: of [`SEEN_SAMPLES`] area samples, those
/// in front of and inside the image of at least half of the cameras (at least two; of at least
/// two when fewer than a tenth of the samples are), twice their RMS distance from their centroid.
/// The object a capture circles, not the background a few views see past it, which inflates the
/// mesh's bounding box (instant-ngp's fox: the room). No occlusion test. `None` when fewer than
/// two samples are seen so.
pub fn seen_size(mesh: &Mesh, cameras: &[&Camera]) -> Option<f64> {
    let samples = super::distance::area_samples(mesh, SEEN_SAMPLES);
    let count: Vec<usize> = samples
        .par_iter()
        .map(|&p| {
            (cameras.iter())
                .filter(|c| {
                    c.project(p).is_some_and(|(x, y)| {
                        x >= 0.0 && y >= 0.0 && x < c.width as f64 && y < c.height as f64
                    })
                })
                .count()
        })
        .collect();
    let pick = |least: usize| -> Vec<DVec3> {
        (samples.iter().zip(&count))
            .filter(|(_, &c)| c >= least)
            .map(|(&p, _)| p)
            .collect()
    };
    let mut seen = pick((cameras.len() / 2).max(2));
    if seen.len() * 10 < samples.len() {
        seen = pick(2);
    }
    if seen.len() < 2 {
        return None;
    }
    let centre = seen.iter().sum::<DVec3>() / seen.len() as f64;
    let ms = seen
        .iter()
        .map(|p| (*p - centre).length_squared())
        .sum::<f64>()
        / seen.len() as f64;
    let size = 2.0 * ms.sqrt();
    (size > 0.0 && size.is_finite()).then_some(size)
}

/// Measure how many of `points` lie on `mesh` (module docs), with tolerances in units of
/// `seen` (the size of the region the cameras see, [`seen_size`]; the mesh's diagonal when
/// `None`). Each point is measured on its own and the counts are sums, so the result does not
/// depend on the thread count.
pub fn check(mesh: &Mesh, points: &[DVec3], seen: Option<f64>) -> Agreement {
    // The bounds of the surface: vertices no triangle uses (a cropped export often keeps them)
    // do not count.
    let (lo, hi) = (mesh.triangles.iter().flatten()).fold(
        (DVec3::splat(f64::INFINITY), DVec3::splat(f64::NEG_INFINITY)),
        |(lo, hi), &i| {
            let v = mesh.vertices[i as usize];
            (lo.min(v), hi.max(v))
        },
    );
    let diag = (hi - lo).length();
    // A mesh of one point or a non-finite one: nothing to measure against.
    let sized = diag > 0.0 && diag.is_finite();
    let size = seen.unwrap_or(diag);
    let tolerance = NEAR * size;
    let step = points.len().div_ceil(MAX_POINTS).max(1);
    let measured: Vec<DVec3> = points.iter().step_by(step).copied().collect();
    let grow = DVec3::splat(BOX_MARGIN * diag);
    let (blo, bhi) = (lo - grow, hi + grow);
    let inside: Vec<DVec3> = measured
        .iter()
        .copied()
        .filter(|p| p.cmpge(blo).all() && p.cmple(bhi).all())
        .collect();
    let near = if inside.len() < MIN_POINTS || !sized {
        0
    } else {
        let index = SurfaceIndex::new(mesh);
        inside
            .par_iter()
            .filter(|&&p| index.distance_within(p, tolerance) <= tolerance)
            .count()
    };
    let samples = if sized {
        super::distance::area_samples(mesh, MESH_SAMPLES)
    } else {
        Vec::new()
    };
    let covered = covered(&samples, &measured, COVER * size);
    Agreement {
        size,
        measured: measured.len(),
        inside: inside.len(),
        near,
        tolerance,
        samples: samples.len(),
        covered,
    }
}

/// How many of `samples` have one of `points` within `reach` (points binned in cubes of side
/// `reach`, so the 27 cubes around a sample hold every candidate).
fn covered(samples: &[DVec3], points: &[DVec3], reach: f64) -> usize {
    if !(reach > 0.0 && reach.is_finite()) || points.is_empty() {
        return 0;
    }
    let cube = |p: DVec3| (p / reach).floor().as_i64vec3();
    let mut bins: std::collections::HashMap<glam::I64Vec3, Vec<DVec3>> = Default::default();
    for &p in points {
        bins.entry(cube(p)).or_default().push(p);
    }
    let r2 = reach * reach;
    samples
        .par_iter()
        .filter(|&&s| {
            let c = cube(s);
            (-1..=1).any(|z| {
                (-1..=1).any(|y| {
                    (-1..=1).any(|x| {
                        bins.get(&(c + glam::I64Vec3::new(x, y, z)))
                            .is_some_and(|b| b.iter().any(|p| p.distance_squared(s) <= r2))
                    })
                })
            })
        })
        .count()
}

/// The warning for a mesh whose frame disagrees with the reconstruction's points (read from
/// `source`, measured by [`check`]), else `None`.
pub fn frame_disagreement(mesh_path: &Path, source: &Path, a: &Agreement) -> Option<String> {
    if !a.disagrees() {
        return None;
    }
    let src = source.display();
    let onto = if a.inside < MIN_POINTS {
        format!(
            "only {} of {} points of {src} lie inside its bounds",
            a.inside, a.measured
        )
    } else {
        format!(
            "only {} of the {} points of {src} inside its bounds ({:.0} %) lie on it (within {:.3e}, {} % of the size of the region the cameras see)",
            a.near,
            a.inside,
            100.0 * a.share(),
            a.tolerance,
            100.0 * NEAR
        )
    };
    let what = format!(
        "{onto}, and only {:.0} % of its surface has one of them within {} % of that size",
        100.0 * a.cover(),
        100.0 * COVER
    );
    Some(format!(
        "{}: {what}: the mesh probably stands in another frame than the cameras (another tool's \
         coordinate system, a rotated or rescaled export, a transforms.json read in the wrong frame: \
         see applied_transform in docs/spec.md §3); training will run but learn little where they disagree",
        mesh_path.display()
    ))
}
