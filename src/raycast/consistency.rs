//! Do the photos agree where the mesh is? A surface point of a mesh in the cameras' frame looks
//! alike in every training view that sees it; a mesh in another frame puts the "same" point on
//! unrelated pixels. The check needs no reconstruction points (`scene/points.rs`), so it also
//! covers the layouts that have none (MVSNet, instant-ngp and NeRF-synthetic transforms), and it
//! runs where the photos are read anyway, one photo at a time: `train`'s setup (which reads the
//! held-out photos once more for it) and `cast`.
//!
//! [`PhotoCheck::plan`] takes [`SAMPLES`] area samples of the mesh and, for an even stride of at
//! most [`MAX_VIEWS`] training views, the samples each view sees: in front of it, inside its
//! image, not hidden (the ray from its centre meets the mesh within [`VISIBLE`] of the mesh's
//! diagonal of the sample) and not at a grazing angle ([`MIN_COS`]). A view that sees fewer than
//! [`LATTICE_BELOW`] of them (a close-up: area samples rarely meet its small patch) also casts a
//! [`LATTICE`]² lattice of rays through its image; those hits are samples too, compared only in
//! pairs with a view that cast them. Two views compare a sample at the same patch of surface:
//! the view with the finer footprint there (distance / focal length, stretched by the obliquity)
//! averages its photo over a window as much wider than 3 pixels as its footprint is finer, in
//! half-octave steps up to 4× ([`SCALES`]); further apart, or where the window leaves the image,
//! the sample is not compared. [`PhotoCheck::add_view`] reads each seen sample's luminance (the
//! mean of R, G, B over each window it needs) from the photo. [`PhotoCheck::result`] takes, for
//! every pair of views sharing at least [`MIN_SHARED`] samples with texture in both (a standard
//! deviation of at least [`MIN_STD`]), the Pearson correlation of the two views' luminances of
//! those samples — gain and offset do not count, so exposure changes between photos do not — and
//! averages it weighted by the samples shared.
//!
//! A view whose own pairs correlate [`OUTLIER_GAP`] below the others' is named: the mesh agrees
//! with the other photos, so that view's pose is wrong. Views are taken worst first, each judged
//! against the pairs without it and those named before (so a close-up's peers are not blamed for
//! their pairs with it); only views compared with two or more others that are themselves so
//! compared take part, and the views a named view is compared with must agree among themselves
//! ([`OUTLIER_REST`]): where the mesh is wrong, every view of that part disagrees, not one.
//!
//! The pairs with a close-up are also averaged apart from the others: a mesh that is off by more
//! than the close-ups' pixels but less than the other views' lowers the first and not the second,
//! and a note says so ([`CLOSE_UP_GAP`]; on `cross`, a smooth displacement of 1 % of the diagonal
//! or a shift of 0.5 % is noted, 0.3 % is not: 0.87 against 0.97).
//!
//! **Neighbours.** A mesh in place is a local maximum of photo-consistency; one correlation alone
//! misses a mesh a little off, or a real scene that correlates poorly anyway. So [`PhotoCheck::plan`]
//! also plans the mesh as given and 20 neighbours of it ([`neighbours`]: shifts by ±[`NB_SHIFT`]
//! of the seen region's size along x, y, z; turns by ±[`NB_TURN`]° and a quarter each way about x,
//! y, z; scales ×/÷ [`NB_SCALE`]; about the centroid of the area samples two or more views see, not
//! the mesh's bounding box, which background inflates), each with [`NB_SAMPLES`] samples over at
//! most [`NB_VIEWS`] views. Moving the mesh by T is moving every camera by T⁻¹
//! ([`Neighbour::camera`]), so the one BVH and the same samples serve all. Each is scored by its
//! *local* correlation ([`PhotoCheck::local_correlation`]): per pair of views, the luminances
//! correlated within cubes of [`NB_CELL`] of the seen region's size (each less its cube's mean),
//! so the layout at larger scales does not count. A neighbour that scores more than
//! [`NB_MARGIN`] above the mesh as given, and higher in [`NB_MOST`] of the view pairs (or more
//! than [`NB_MARGIN_ALONE`] above it), is named in a warning ([`Consistency::beaten`]).
//! With the pairs' whole correlation instead, the crude mesh of a real capture (the skull of
//! `xscale prepare`, 1,535 triangles from 808 sparse points, on a black backdrop) was beaten by
//! itself moved by 4 % (0.78 against 0.72), probably because more of its samples then fall on
//! the backdrop in every view, which correlates dark with dark (not measured apart). Within
//! cubes it gains less (0.69 against 0.67; 0.72 against 0.69 on the committed smaller photos)
//! and wins only 14–17 of 28 view pairs, while its turned, moved and scaled copies are beaten
//! by 0.04 to 0.45 in 21 to 27 (`docs/results.md`, section `meshcheck`).
//!
//! Measured (`raycast::photo_check_*`, the lines `xscale cast` prints, and a scratch probe that
//! turns each training view in turn about its axis): in place 0.93 (the `tiny` fixture), 0.98
//! (`synth --preset small`), 0.97 (`cross`), no view named; the mesh turned a quarter about a
//! horizontal axis 0.23–0.35, moved up by 5 % of its diagonal 0.17–0.40, turned 10° about the
//! vertical or moved sideways by 3 % 0.86–0.90, and no view named for any of them. One view
//! turned 5° about its axis: named, alone, for 34 of 34 views of `small` and 42 of 48 of `cross`
//! (the others: 3 aerial views that drop a little less than 0.2 below the rest, and 2 close-ups);
//! turned 3°, 14 of 34 (the close-ups of `small`, every one: their fine texture moves further)
//! and 24 of 48; never another view. A real COLMAP workspace (5 photos of 3 MP, 4 of them
//! training views, its `meshed-poisson.ply`): in place 0.92, no view named; each view turned 5°,
//! or 2°, named alone; the mesh turned or moved as above 0.17–0.87, no view named. Below
//! [`MIN_CORRELATION`] training learns little. (Before the lattices and the footprint windows,
//! close-ups were not judged at all and the in-place figures were 0.92 / 0.97 / 0.97.)

use super::Tracer;
use crate::scene::{distance::area_samples, Camera, Image, Mesh};
use glam::DVec3;
use rayon::prelude::*;

/// Area samples of the mesh.
pub const SAMPLES: usize = 4000;
/// Views planned at most (an even stride through the training views).
pub const MAX_VIEWS: usize = 48;
/// A sample is seen when the ray from the camera meets the mesh within this fraction of the
/// mesh's diagonal from it.
pub const VISIBLE: f64 = 1e-3;
/// Samples two views must share for their correlation to count.
pub const MIN_SHARED: usize = 30;
/// Luminance standard deviation (values in [0, 1]) below which a view's shared samples have too
/// little texture to correlate.
pub const MIN_STD: f64 = 1e-3;
/// Below this mean correlation the photos disagree where the mesh is.
pub const MIN_CORRELATION: f64 = 0.5;
/// A view whose pairs correlate this much below the other views' pairs disagrees with them: its
/// pose is wrong. In place every judged view of `small` and `cross` correlates within 0.1 of the
/// rest; one aerial view of `small` turned about its axis by 5° drops to 0.75 against 0.98, a
/// close-up to below 0.4.
pub const OUTLIER_GAP: f64 = 0.2;
/// Views are named only when the others, and the views each named one is compared with, correlate
/// at least this well (a mesh in place), and they are at most a quarter of the judged views: a
/// mesh out of place leaves some pairs of views agreeing and the rest not, which is not one
/// view's pose (`small` with its mesh turned 10° about the vertical: 0.90 overall, and without
/// the second condition three close-ups named).
pub const OUTLIER_REST: f64 = 0.9;

/// Close-ups whose pairs correlate this much below the other pairs see a mesh that is off at
/// their scale: a note says so. Measured on `synth --preset cross` (exact mesh): close-up pairs 0.955 in place against 0.975 for the others; the
/// mesh displaced smoothly along its normals by 0.3 % of its diagonal (RMS) 0.87 against 0.97, by
/// 1 % 0.74 against 0.90; moved sideways by 0.5 % 0.75 against 0.96. On `small` (coarser texture)
/// 0.945 against 0.977 in place, 0.65 against 0.97 moved by 0.5 %, 0.83 against 0.90 at 1 %.
pub const CLOSE_UP_GAP: f64 = 0.1;
/// The close-up note needs the other pairs to correlate at least this well (the mesh fits their
/// scale).
pub const CLOSE_UP_REST: f64 = 0.8;

/// Pixels across a view's lattice: a planned view that sees fewer than [`LATTICE_BELOW`] area
/// samples also casts LATTICE × LATTICE rays through its image, and their hits join the samples,
/// so a close-up (which few area samples meet) shares surface points with the views around it.
pub const LATTICE: usize = 12;
/// Footprint ratios are matched in steps of half an octave up to 2^((SCALES − 1)/2) = 4: a sample
/// two views see at footprints further apart than that is not compared between them. (At 28×,
/// the aerial/close-up gap of `small`, a close-up's photo averaged to the aerial footprint is a
/// few pixels across: such pairs correlated 0.39 in place, and the close-ups were named falsely.)
pub const SCALES: usize = 5;
/// Views that see fewer area samples than this cast their lattice.
pub const LATTICE_BELOW: usize = 4 * MIN_SHARED;
/// A view that sees the surface at a sample more obliquely than this (the cosine between its ray
/// and the surface normal) does not compare it: its pixels stretch along the surface there, and
/// a square window no longer covers the patch another view sees.
pub const MIN_COS: f64 = 0.5;

/// Area samples of the neighbour check's plans (the given mesh's and each neighbour's). At
/// 1,000 the pairs a neighbour of the real skull wins were noisier (in place 17 of 28, wrong 19
/// and more; [`NB_MOST`]).
pub const NB_SAMPLES: usize = 3000;
/// Views the neighbour check's plans take at most (an even stride).
pub const NB_VIEWS: usize = 16;
/// The neighbours' shifts along x, y and z, as a fraction of the seen region's size (twice the
/// RMS distance of the seen samples from their centroid).
pub const NB_SHIFT: f64 = 0.04;
/// The neighbours' small turns about x, y and z (through the seen samples' centroid), degrees.
pub const NB_TURN: f64 = 5.0;
/// The neighbours' scale changes about that centroid: × NB_SCALE and ÷ NB_SCALE.
pub const NB_SCALE: f64 = 1.1;
/// A neighbour whose local correlation beats the given mesh's by more than this, and does so in
/// at least [`NB_MOST`] of the view pairs, is warned of: the given mesh is not the local maximum
/// of photo-consistency a mesh in place is.
pub const NB_MARGIN: f64 = 0.03;
/// The share of view pairs a neighbour must win ([`NB_MARGIN`]). A frame error puts every view
/// off, so its fix wins nearly every pair; a crude mesh moved a little trades some pairs for
/// others. Measured (`docs/results.md` § meshcheck, and at 1,000 and 3,000 samples): the real
/// skull's crude mesh in place, its best neighbour wins 14–17 of 28 pairs; its turned, moved and
/// scaled copies 21–27 of 28 (19 at 1,000 samples); `tiny` and `small` wrong 44 of 45 and more
/// (3 of 3 on `tiny`), in place none.
pub const NB_MOST: f64 = 2.0 / 3.0;
/// A neighbour that beats the mesh as given by more than this in the mean is warned of whatever
/// the pairs say: the fox turned a quarter scores 0.12, its turned-back neighbour 0.30 but in
/// only 68 of 102 pairs (the rest correlate near zero either way). No correct mesh measured
/// gains more than 0.05 (the skull at 1,000 samples).
pub const NB_MARGIN_ALONE: f64 = 0.1;
/// The neighbour check correlates within cubes of this fraction of the seen region's size
/// ([`PhotoCheck::local_correlation`]). Measured with `raycast::photo_check_neighbours_table`
/// (the best neighbour's gain over the mesh as given): the real skull's crude mesh in place
/// +0.017 at a quarter, −0.022 at an eighth, +0.06 over whole pairs (the global correlation, which
/// warned falsely); its wrong meshes +0.075 to +0.43 at a quarter, but +0.001 scaled by 1.1 at an
/// eighth; `tiny` and `small` in place −0.014 and −0.062, wrong +0.044 to +0.70.
pub const NB_CELL: f64 = 0.25;

/// One sample as one view sees it.
#[derive(Clone, Copy)]
struct Seen {
    sample: u32,
    /// Continuous pixel position of its projection.
    x: f32,
    y: f32,
    /// log2 of its footprint: the surface width one pixel covers there, distance / focal length.
    log_fp: f32,
    /// The window scales (bit q: 2^(q/2) times the 3-pixel window) this view must read here.
    scales: u16,
    /// The largest window scale that fits inside the image here.
    fit: u8,
}

/// The plan and the luminances read so far ([module docs](self)).
pub struct PhotoCheck {
    /// Planned slot → caller's view index (increasing).
    planned: Vec<usize>,
    /// Per slot: the samples the view sees, in sample order.
    seen: Vec<Vec<Seen>>,
    /// Per slot: per seen sample, its luminance averaged over each window scale it needs (other
    /// scales 0), once [`PhotoCheck::add_view`] has read the photo.
    lum: Vec<Option<Vec<[f32; SCALES]>>>,
    /// Area samples (numbered first; the lattices' hits follow).
    area: usize,
    /// Every sample's position: the area samples, then the lattices' hits.
    points: Vec<DVec3>,
    /// Per slot: whether the view cast its lattice. The lattices' hits count only in pairs with
    /// such a view.
    cast: Vec<bool>,
    /// The neighbour check: the given mesh and its neighbours, each planned with [`NB_SAMPLES`]
    /// samples over at most [`NB_VIEWS`] views (empty in a neighbour's own plan).
    neighbours: Vec<(Neighbour, PhotoCheck)>,
    /// Seconds the neighbours' plans took.
    neighbour_seconds: f64,
    /// The seen region (centroid, size) the neighbours are built about ([`neighbours`]).
    seen_region: (DVec3, f64),
}

/// A neighbour of the given mesh: that mesh moved by a similarity (module docs, "neighbours").
#[derive(Clone, Debug, PartialEq)]
pub struct Neighbour {
    /// What it is, as the warning names it ("moved +x by 4% of the seen region", …); "as given"
    /// for the identity.
    pub name: String,
    /// Scale s, rotation R about `centre`, then a shift: p ↦ centre + s R (p − centre) + shift.
    pub scale: f64,
    pub rotation: glam::DMat3,
    pub centre: DVec3,
    pub shift: DVec3,
}

impl Neighbour {
    /// The identity: the mesh as given.
    fn given() -> Neighbour {
        Neighbour {
            name: "as given".into(),
            scale: 1.0,
            rotation: glam::DMat3::IDENTITY,
            centre: DVec3::ZERO,
            shift: DVec3::ZERO,
        }
    }

    /// The camera that sees the mesh as it is what `cam` sees of the mesh moved by this
    /// transform T: moving the mesh by T is moving the camera by T⁻¹. With T(p) = sRp + t,
    /// R_c (sRp + t) + t_c = s (R_c R p + (R_c t + t_c) / s), and a projection does not see the
    /// common factor s > 0.
    fn camera(&self, cam: &Camera) -> Camera {
        let r = self.rotation;
        let t = self.centre - self.scale * (r * self.centre) + self.shift;
        Camera {
            rotation: cam.rotation * r,
            translation: (cam.rotation * t + cam.translation) / self.scale,
            ..cam.clone()
        }
    }
}

/// The window scales at which views a and b compare a sample they see as `a` and `b`: the finer
/// view averages over 2^(q/2) times the coarser view's 3 pixels, so both
/// cover the same patch of surface (to within 2^(1/4)). `(q_a, q_b)`, one of them 0; `None`
/// beyond [`SCALES`].
fn scales(a: &Seen, b: &Seen) -> Option<(usize, usize)> {
    let q = (2.0 * (b.log_fp - a.log_fp).abs()).round() as usize;
    let (qa, qb) = if a.log_fp < b.log_fp { (q, 0) } else { (0, q) };
    (q < SCALES && qa <= a.fit as usize && qb <= b.fit as usize).then_some((qa, qb))
}

/// Half the width of the window at scale q, in pixels.
fn half_width(q: usize) -> f64 {
    1.5 * 2f64.powf(q as f64 / 2.0)
}

/// Shared samples of two views' sorted lists: (position in a, position in b).
fn shared(a: &[Seen], b: &[Seen], area: usize, lattice: bool) -> Vec<(usize, usize)> {
    let end = |s: &[Seen]| match lattice {
        true => s.len(),
        false => s.partition_point(|p| (p.sample as usize) < area),
    };
    let (ea, eb) = (end(a), end(b));
    let (mut i, mut j, mut out) = (0, 0, Vec::new());
    while i < ea && j < eb {
        match a[i].sample.cmp(&b[j].sample) {
            std::cmp::Ordering::Less => i += 1,
            std::cmp::Ordering::Greater => j += 1,
            std::cmp::Ordering::Equal => {
                out.push((i, j));
                i += 1;
                j += 1;
            }
        }
    }
    out
}

/// What [`PhotoCheck::result`] measured.
#[derive(Clone, Debug, PartialEq)]
pub struct Consistency {
    /// View pairs correlated.
    pub pairs: usize,
    /// Samples shared over those pairs (the weights).
    pub shared: usize,
    /// Mean correlation, weighted by the samples each pair shares (0 without pairs).
    pub correlation: f64,
    /// Views (the caller's indices) whose own pairs correlate [`OUTLIER_GAP`] below the pairs of
    /// the other views (which reach [`OUTLIER_REST`]), with their own mean correlation: the
    /// photos agree where the mesh is, except through these views' poses. At most a quarter of
    /// the judged views.
    pub outliers: Vec<(usize, f64)>,
    /// With outliers, the mean correlation of the pairs among the other judged views (those
    /// compared with two or more others); `correlation` when there is none.
    pub rest: f64,
    /// Of the pairs without an outlier, those with a close-up (a view that cast its lattice) and
    /// the others: (pairs, mean correlation) of each, `None` without such pairs.
    pub close_ups: Option<(usize, f64)>,
    pub others: Option<(usize, f64)>,
    /// The close-ups (the caller's indices) whose own pairs in `close_ups` correlate least, with
    /// their mean: at most three, lowest first. Where they look the mesh is off the most.
    pub worst_close_ups: Vec<(usize, f64)>,
    /// The neighbour check: the given mesh ("as given", first) and each neighbour, with its
    /// local correlation ([`PhotoCheck::local_correlation`], cells of [`NB_CELL`] of the seen
    /// region) at [`NB_SAMPLES`] samples over [`NB_VIEWS`] views (`None` without a pair).
    pub neighbours: Vec<(String, Option<f64>)>,
    /// Per entry of `neighbours`: its pairs' local correlations (slot a, slot b, samples shared,
    /// correlation).
    pub neighbour_pairs: Vec<Vec<(usize, usize, usize, f64)>>,
    /// Seconds the neighbours' plans took.
    pub neighbour_seconds: f64,
}

impl Consistency {
    /// Whether the photos disagree where the mesh is (`false` without a pair to judge by).
    pub fn disagrees(&self) -> bool {
        self.pairs > 0 && self.correlation < MIN_CORRELATION
    }

    /// The best neighbour (name, local correlation), with the given mesh's, when it beats the
    /// mesh as given: by more than [`NB_MARGIN`] in the mean and in at least [`NB_MOST`] of the
    /// view pairs, or by more than [`NB_MARGIN_ALONE`] in the mean. The mesh is then not where
    /// the photos agree most.
    pub fn beaten(&self) -> Option<(String, f64, f64)> {
        let (_, given) = self.neighbours.first()?;
        let given = (*given)?;
        let best = self.best_neighbour()?;
        let (won, all) = self.best_wins()?;
        let most = won as f64 >= NB_MOST * all as f64;
        let gain = best.1 - given;
        (gain > NB_MARGIN_ALONE || (gain > NB_MARGIN && most))
            .then(|| (best.0.clone(), best.1, given))
    }

    /// The neighbour that scores best (name, local correlation), if any scored.
    pub fn best_neighbour(&self) -> Option<(&String, f64)> {
        (self.neighbours.get(1..)?.iter())
            .filter_map(|(n, c)| Some((n, (*c)?)))
            .max_by(|a, b| a.1.total_cmp(&b.1))
    }

    /// Of the view pairs the best neighbour and the mesh as given both score, those where the
    /// neighbour scores higher, and all of them.
    pub fn best_wins(&self) -> Option<(usize, usize)> {
        let k = (1..self.neighbours.len())
            .filter_map(|k| Some((k, self.neighbours[k].1?)))
            .max_by(|a, b| a.1.total_cmp(&b.1))?
            .0;
        let (given, nb) = (self.neighbour_pairs.first()?, self.neighbour_pairs.get(k)?);
        let mut won = 0;
        let mut all = 0;
        for p in nb {
            if let Some(q) = given.iter().find(|q| (q.0, q.1) == (p.0, p.1)) {
                all += 1;
                won += usize::from(p.3 > q.3);
            }
        }
        Some((won, all))
    }

    /// Whether the close-ups agree [`CLOSE_UP_GAP`] less than the other views, which agree at
    /// least [`CLOSE_UP_REST`]: the mesh is off by more than the close-ups' pixels where they look.
    pub fn close_ups_disagree(&self) -> bool {
        match (self.close_ups, self.others) {
            (Some((_, c)), Some((_, o))) => {
                !self.disagrees() && o >= CLOSE_UP_REST && c < o - CLOSE_UP_GAP
            }
            _ => false,
        }
    }

    /// What `train` and `cast` say of it: the correlation (a warning below [`MIN_CORRELATION`]),
    /// a warning per view whose pose disagrees with the others' (`name(k)`: the name of the
    /// caller's view `k`), and a note when the close-ups disagree more than the other views.
    pub fn messages(&self, name: &dyn Fn(usize) -> String) -> Vec<String> {
        if self.pairs == 0 {
            return vec![
                "photo check: no two views share enough textured surface to compare".into(),
            ];
        }
        let close = match self.close_ups {
            Some((n, c)) => format!(", close-ups {c:.2} over {n} of them"),
            None => String::new(),
        };
        let what = format!(
            "the colours two photos see at the same surface points correlate {:.2} ({} view pairs{close}, {} points; in place typically 0.9 or more, below {} the mesh stands elsewhere)",
            self.correlation, self.pairs, self.shared, MIN_CORRELATION
        );
        let mut out = vec![if self.disagrees() {
            format!(
                "warning: {what}: the photos disagree where the mesh is, which probably stands in another frame than the cameras (another tool's coordinate system, a turned or moved export, a transforms.json read in the wrong frame: docs/spec.md §3); training will run but learn little"
            )
        } else {
            format!("photo check: {what}")
        }];
        let wins = self.best_wins().unwrap_or((0, 0));
        if let Some((name, best, given)) = self.beaten() {
            out.push(format!(
                "warning: the mesh {name} agrees better with the photos than the mesh as given (local correlation {best:.2} against {given:.2}, higher in {} of {} view pairs; {} neighbours scored in {:.2} s): the mesh is probably turned, moved or scaled against the cameras (another tool's frame or unit, a wrong alignment), or off the photographed surface by about that much (a crude mesh: docs/spec.md §3.9); training will run but learn less",
                wins.0,
                wins.1,
                self.neighbours.len() - 1,
                self.neighbour_seconds
            ));
        } else if self.neighbours.len() > 1 {
            let best = match (self.best_neighbour(), self.neighbours[0].1) {
                (Some((n, b)), Some(g)) => format!(
                    "the best, {n}: local correlation {b:.2} against {g:.2}, higher in {} of {} view pairs; ",
                    wins.0, wins.1
                ),
                _ => String::new(),
            };
            out.push(format!(
                "photo check: no neighbour of the mesh (moved, turned or scaled a little) agrees better with the photos ({best}{} scored in {:.2} s)",
                self.neighbours.len() - 1,
                self.neighbour_seconds
            ));
        }
        out.extend(self.outliers.iter().map(|&(k, c)| {
            format!(
                "warning: view {}: its photo disagrees with the others where the mesh is (correlation {c:.2} against {:.2} among the other views): its pose is probably wrong (a bad registration): fix it, or leave the view out (test_views in scene.toml holds a training view out)",
                name(k),
                self.rest
            )
        }));
        if let (true, Some((n, c)), Some((_, o))) =
            (self.close_ups_disagree(), self.close_ups, self.others)
        {
            let worst: Vec<String> = (self.worst_close_ups.iter())
                .map(|&(k, m)| format!("{} ({m:.2})", name(k)))
                .collect();
            out.push(format!(
                "note: the close-ups agree less ({c:.2} over {n} view pairs; least where {} look) than the other views ({o:.2}): the mesh is probably off by more than their pixels where they look, which costs most on the close-ups; mesh refinement by the photos, with image levels as deep as the close-ups need, moves it there (`xscale train --config configs/refine-cross.toml`, the repository's file; docs/geometry.md §5)",
                worst.join(", ")
            ));
        }
        out
    }
}

impl PhotoCheck {
    /// Plan the check for `cameras` (the views to check, in the caller's order; `train` gives its
    /// training views, then the held-out ones), with the neighbour check.
    pub fn plan(mesh: &Mesh, tracer: &Tracer, cameras: &[&Camera]) -> PhotoCheck {
        let mut check = PhotoCheck::plan_with(mesh, tracer, cameras, SAMPLES, MAX_VIEWS);
        let t0 = std::time::Instant::now();
        let given = PhotoCheck::plan_with(mesh, tracer, cameras, NB_SAMPLES, NB_VIEWS);
        let (nbs, region) = neighbours(&given).unwrap_or_default();
        check.seen_region = region;
        check.neighbours = (nbs.into_iter().map(|nb| {
            let cams: Vec<Camera> = cameras.iter().map(|c| nb.camera(c)).collect();
            let refs: Vec<&Camera> = cams.iter().collect();
            let c = PhotoCheck::plan_with(mesh, tracer, &refs, NB_SAMPLES, NB_VIEWS);
            (nb, c)
        }))
        .collect();
        check.neighbours.insert(0, (Neighbour::given(), given));
        check.neighbour_seconds = t0.elapsed().as_secs_f64();
        check
    }

    /// The plan of [`PhotoCheck::plan`] with `samples` area samples over at most `max_views`
    /// views, without neighbours.
    fn plan_with(
        mesh: &Mesh,
        tracer: &Tracer,
        cameras: &[&Camera],
        samples: usize,
        max_views: usize,
    ) -> PhotoCheck {
        let (lo, hi) = mesh.bbox();
        let tol = VISIBLE * (hi - lo).length();
        let n = cameras.len();
        let planned: Vec<usize> = (0..n.min(max_views))
            .map(|k| k * n / n.min(max_views))
            .collect();
        // Per planned view: the points of `pts` (numbered from `first`) it sees, in order.
        let see = |pts: &[DVec3], first: usize| -> Vec<Vec<Seen>> {
            planned
                .par_iter()
                .map(|&k| {
                    let cam = cameras[k];
                    let centre = cam.center();
                    let log_f = 0.5 * (cam.fx * cam.fy).abs().log2();
                    let (w, h) = (cam.width as f64, cam.height as f64);
                    (pts.iter().enumerate())
                        .filter_map(|(j, &p)| {
                            let (x, y) = cam.project(p)?;
                            if !(x >= 1.0 && y >= 1.0 && x < w - 1.0 && y < h - 1.0) {
                                return None;
                            }
                            let to = p - centre;
                            let hit = tracer.closest_hit(centre, to)?;
                            if (hit.t - to.length()).abs() > tol {
                                return None;
                            }
                            let cos =
                                tracer.triangle_normal(hit.triangle).dot(to).abs() / to.length();
                            if cos < MIN_COS {
                                return None;
                            }
                            let margin = x.min(y).min(w - x).min(h - y);
                            Some(Seen {
                                sample: (first + j) as u32,
                                x: x as f32,
                                y: y as f32,
                                log_fp: (to.length().log2() - log_f - 0.5 * cos.log2()) as f32,
                                scales: 0,
                                fit: (1..SCALES).take_while(|&q| half_width(q) <= margin).count()
                                    as u8,
                            })
                        })
                        .collect()
                })
                .collect()
        };
        let area = area_samples(mesh, samples);
        let mut seen = see(&area, 0);
        // The lattices of the views that see few area samples (close-ups).
        let cast: Vec<bool> = seen.iter().map(|s| s.len() < LATTICE_BELOW).collect();
        let lattice: Vec<DVec3> = (planned.par_iter().zip(&cast))
            .filter(|(_, &c)| c)
            .flat_map_iter(|(&k, _)| {
                let cam = cameras[k];
                let centre = cam.center();
                (0..LATTICE * LATTICE).filter_map(move |g| {
                    let x = (((g % LATTICE) as f64 + 0.5) / LATTICE as f64) * cam.width as f64;
                    let y = (((g / LATTICE) as f64 + 0.5) / LATTICE as f64) * cam.height as f64;
                    let d = cam.dir_world(x, y);
                    let hit = tracer.closest_hit(centre, d)?;
                    Some(centre + d * hit.t)
                })
            })
            .collect();
        let mut points = area.clone();
        points.extend(&lattice);
        for (s, more) in seen.iter_mut().zip(see(&lattice, area.len())) {
            s.extend(more);
        }
        // The window scales each view reads a sample at: one per view it shares it with.
        for a in 0..seen.len() {
            for b in a + 1..seen.len() {
                for (i, j) in shared(&seen[a], &seen[b], area.len(), cast[a] || cast[b]) {
                    if let Some((qa, qb)) = scales(&seen[a][i], &seen[b][j]) {
                        seen[a][i].scales |= 1 << qa;
                        seen[b][j].scales |= 1 << qb;
                    }
                }
            }
        }
        PhotoCheck {
            lum: vec![None; planned.len()],
            planned,
            seen,
            area: area.len(),
            cast,
            neighbours: Vec::new(),
            neighbour_seconds: 0.0,
            seen_region: (DVec3::ZERO, 0.0),
            points,
        }
    }

    /// Whether view `k` is planned (its photo is worth reading).
    pub fn wants(&self, k: usize) -> bool {
        self.planned.binary_search(&k).is_ok() || self.neighbours.iter().any(|(_, c)| c.wants(k))
    }

    /// Read the luminances of the samples view `k` sees from its photo (`img`: the camera's size):
    /// the mean of R, G, B over a square window around each sample's projection, 3 pixels wide
    /// times each scale the sample needs (pixels whose centres fall inside, clipped to the image).
    pub fn add_view(&mut self, k: usize, img: &Image) {
        for (_, c) in &mut self.neighbours {
            c.add_view(k, img);
        }
        let Ok(s) = self.planned.binary_search(&k) else {
            return;
        };
        let (w, h) = (img.width as i64, img.height as i64);
        let window = |x: f32, y: f32, half: f64| -> f32 {
            let span = |c: f32, n: i64| {
                let lo = ((c as f64 - half - 0.5).ceil() as i64).clamp(0, n - 1);
                let hi = ((c as f64 + half - 0.5).floor() as i64).clamp(lo, n - 1);
                (lo, hi)
            };
            let ((x0, x1), (y0, y1)) = (span(x, w), span(y, h));
            let mut sum = 0f64;
            for yy in y0..=y1 {
                let row = &img.data[((yy * w + x0) * 3) as usize..((yy * w + x1 + 1) * 3) as usize];
                sum += row.iter().map(|&v| v as f64).sum::<f64>();
            }
            (sum / (3 * (x1 - x0 + 1) * (y1 - y0 + 1)) as f64) as f32
        };
        let lum = self.seen[s]
            .par_iter()
            .map(|p| {
                let mut out = [0f32; SCALES];
                for (q, o) in out.iter_mut().enumerate() {
                    if p.scales & (1 << q) != 0 {
                        *o = window(p.x, p.y, half_width(q));
                    }
                }
                out
            })
            .collect();
        self.lum[s] = Some(lum);
    }

    /// Correlate the views read so far ([module docs](self)).
    pub fn result(&self) -> Consistency {
        let corr = self.pair_correlations();
        let (shared, correlation) = weighted_mean(&corr, &|_, _| true);
        let judged = (0..self.seen.len())
            .filter(|&s| corr.iter().any(|c| c.0 == s || c.1 == s))
            .count();
        let (low, rest) = low_views(&corr, self.seen.len(), correlation);
        let confirmed = !low.is_empty() && 4 * low.len() <= judged && rest >= OUTLIER_REST;
        let outliers = if confirmed {
            low.iter().map(|&(s, m)| (self.planned[s], m)).collect()
        } else {
            Vec::new()
        };
        let named = |s: usize| low.iter().any(|&(t, _)| t == s) && confirmed;
        let split = |close: bool| {
            let keep = |a: usize, b: usize| {
                !named(a) && !named(b) && (self.cast[a] || self.cast[b]) == close
            };
            let n = corr.iter().filter(|c| keep(c.0, c.1)).count();
            let (w, m) = weighted_mean(&corr, &keep);
            (w > 0).then_some((n, m))
        };
        let mut worst_close_ups: Vec<(usize, f64)> = (0..self.seen.len())
            .filter(|&s| self.cast[s] && !named(s))
            .filter_map(|s| {
                let (w, m) =
                    weighted_mean(&corr, &|a, b| (a == s || b == s) && !named(a) && !named(b));
                (w > 0).then_some((self.planned[s], m))
            })
            .collect();
        worst_close_ups.sort_by(|x, y| x.1.total_cmp(&y.1));
        worst_close_ups.truncate(3);
        let (centre, size) = self.seen_region;
        let neighbour_pairs: Vec<Vec<Pair>> = (self.neighbours.iter())
            .map(|(_, c)| c.local_correlation(centre, NB_CELL * size))
            .collect();
        let neighbours = (self.neighbours.iter().zip(&neighbour_pairs))
            .map(|((nb, _), pairs)| {
                let (w, m) = weighted_mean(pairs, &|_, _| true);
                (nb.name.clone(), (w > 0).then_some(m))
            })
            .collect();
        Consistency {
            neighbour_pairs,
            neighbours,
            neighbour_seconds: self.neighbour_seconds,
            pairs: corr.len(),
            shared,
            correlation,
            worst_close_ups,
            close_ups: split(true),
            others: split(false),
            rest: if outliers.is_empty() {
                correlation
            } else {
                rest
            },
            outliers,
        }
    }

    /// Each pair of views read that shares at least [`MIN_SHARED`] samples and whose samples'
    /// luminances spread: (slot a, slot b, samples shared, correlation), a < b.
    fn pair_correlations(&self) -> Vec<Pair> {
        (self.pair_samples().into_iter())
            .filter_map(|(a, b, _, xy)| Some((a, b, xy.len(), pearson(&xy)?)))
            .collect()
    }

    /// Each pair of views read that shares at least [`MIN_SHARED`] samples: (slot a, slot b,
    /// the samples, their luminances in a and b), a < b.
    fn pair_samples(&self) -> Vec<PairSamples> {
        let read: Vec<usize> = (0..self.seen.len())
            .filter(|&s| self.lum[s].is_some())
            .collect();
        let pairs = (read.iter().enumerate())
            .flat_map(|(i, &a)| read[i + 1..].iter().map(move |&b| (a, b)));
        let mut out = Vec::new();
        for (a, b) in pairs {
            let (la, lb) = (self.lum[a].as_ref().unwrap(), self.lum[b].as_ref().unwrap());
            let (sa, sb) = (&self.seen[a], &self.seen[b]);
            let lattice = self.cast[a] || self.cast[b];
            let (ids, xy): (Vec<u32>, Vec<(f64, f64)>) = (shared(sa, sb, self.area, lattice)
                .into_iter())
            .filter_map(|(i, j)| {
                let (qa, qb) = scales(&sa[i], &sb[j])?;
                Some((sa[i].sample, (la[i][qa] as f64, lb[j][qb] as f64)))
            })
            .unzip();
            if xy.len() >= MIN_SHARED {
                out.push((a, b, ids, xy));
            }
        }
        out
    }

    /// The neighbour check's score ([module docs](self), "neighbours"): per pair of views, the
    /// correlation of the two views' luminances *within cells* of side `cell` (cubes of the grid
    /// through `centre`): each sample's luminance less its cell's mean in that view, pooled
    /// over the cells with two or more of the pair's samples; averaged over the pairs weighted by
    /// the samples shared. The layout at larger scales (a bright object on a dark backdrop,
    /// shading across it), which a crude mesh moved a little can trade for the better, does not
    /// count; the texture within a cell, which only a mesh in place puts on the same pixels in
    /// every view, does. `None` without a pair.
    fn local_correlation(&self, centre: DVec3, cell: f64) -> Vec<Pair> {
        let mut out = Vec::new();
        for (a, b, ids, xy) in self.pair_samples() {
            let mut cells: Vec<(glam::I64Vec3, usize)> = (ids.iter().enumerate())
                .map(|(i, &id)| {
                    let c = ((self.points[id as usize] - centre) / cell).floor();
                    (c.as_i64vec3(), i)
                })
                .collect();
            cells.sort_by_key(|&(c, i)| (c.to_array(), i));
            let (mut sxy, mut sxx, mut syy) = (0f64, 0f64, 0f64);
            for group in cells.chunk_by(|a, b| a.0 == b.0).filter(|g| g.len() >= 2) {
                let m = group.len() as f64;
                let mx = group.iter().map(|&(_, i)| xy[i].0).sum::<f64>() / m;
                let my = group.iter().map(|&(_, i)| xy[i].1).sum::<f64>() / m;
                for &(_, i) in group {
                    let (dx, dy) = (xy[i].0 - mx, xy[i].1 - my);
                    sxy += dx * dy;
                    sxx += dx * dx;
                    syy += dy * dy;
                }
            }
            let n = xy.len() as f64;
            if (sxx / n).sqrt() >= MIN_STD && (syy / n).sqrt() >= MIN_STD {
                out.push((a, b, xy.len(), sxy / (sxx * syy).sqrt()));
            }
        }
        out
    }
}

/// The neighbours of the mesh `given` planned ([module docs](self)): shifts by ± [`NB_SHIFT`]
/// of the seen region's size along x, y, z, turns by ± [`NB_TURN`]° and a quarter turn each way
/// about x, y, z through the seen samples' centroid, and scales × and ÷ [`NB_SCALE`] about it.
/// The seen samples are the area samples two or more planned views see (the background a view
/// sees alone does not count). With the seen region (centroid, size: twice the samples' RMS
/// distance from it); `None` without two such samples.
fn neighbours(given: &PhotoCheck) -> Option<(Vec<Neighbour>, (DVec3, f64))> {
    let mut count = vec![0u32; given.area];
    for seen in &given.seen {
        for p in seen.iter().filter(|p| (p.sample as usize) < given.area) {
            count[p.sample as usize] += 1;
        }
    }
    let pts: Vec<DVec3> = (given.points.iter().zip(&count))
        .filter(|(_, &c)| c >= 2)
        .map(|(&p, _)| p)
        .collect();
    if pts.len() < 2 {
        return None;
    }
    let centre = pts.iter().sum::<DVec3>() / pts.len() as f64;
    let rms = (pts
        .iter()
        .map(|p| (*p - centre).length_squared())
        .sum::<f64>()
        / pts.len() as f64)
        .sqrt();
    let size = 2.0 * rms;
    let nb = |name: String, scale: f64, rotation: glam::DMat3, shift: DVec3| Neighbour {
        name,
        scale,
        rotation,
        centre,
        shift,
    };
    let id = glam::DMat3::IDENTITY;
    let axes = [("x", DVec3::X), ("y", DVec3::Y), ("z", DVec3::Z)];
    let mut out = Vec::new();
    for (a, v) in axes {
        for sign in [1.0, -1.0] {
            let pm = if sign > 0.0 { '+' } else { '-' };
            out.push(nb(
                format!(
                    "moved {pm}{a} by {:.0}% of the seen region",
                    100.0 * NB_SHIFT
                ),
                1.0,
                id,
                sign * NB_SHIFT * size * v,
            ));
        }
    }
    for (a, v) in axes {
        for (deg, what) in [(NB_TURN, "turned"), (90.0, "turned a quarter")] {
            for sign in [1.0, -1.0] {
                let pm = if sign > 0.0 { '+' } else { '-' };
                let r = glam::DMat3::from_axis_angle(v, sign * deg.to_radians());
                let name = match deg == 90.0 {
                    true => format!("{what} ({pm}90°) about {a}"),
                    false => format!("{what} {pm}{deg:.0}° about {a}"),
                };
                out.push(nb(name, 1.0, r, DVec3::ZERO));
            }
        }
    }
    for s in [NB_SCALE, 1.0 / NB_SCALE] {
        out.push(nb(format!("scaled {s:.2}×"), s, id, DVec3::ZERO));
    }
    Some((out, (centre, size)))
}

/// A correlated pair of views: (slot a, slot b, samples shared, correlation).
type Pair = (usize, usize, usize, f64);

/// A pair of views' shared samples: (slot a, slot b, the samples, their luminances in a and b).
type PairSamples = (usize, usize, Vec<u32>, Vec<(f64, f64)>);

/// The weight (samples shared) and the shared-weighted mean correlation of the pairs `keep`
/// takes (0 when it takes none).
fn weighted_mean(corr: &[Pair], keep: &dyn Fn(usize, usize) -> bool) -> (usize, f64) {
    let (mut w, mut sum) = (0usize, 0f64);
    for &(_, _, n, r) in corr.iter().filter(|c| keep(c.0, c.1)) {
        w += n;
        sum += n as f64 * r;
    }
    (w, if w > 0 { sum / w as f64 } else { 0.0 })
}

/// The views of `n` slots whose own pairs correlate [`OUTLIER_GAP`] below the others' (its pose,
/// not the mesh), with their mean correlation, worst first, and the correlation of the pairs
/// left (`correlation` when none). Taken worst first, each against the pairs of neither it nor
/// those taken before, so a close-up's peers are not blamed for their pairs with it. Only views
/// compared with at least two others that are themselves so compared take part (the graph's
/// 2-core): when two views disagree and nothing else judges one of them, which is wrong is
/// unknown.
fn low_views(corr: &[Pair], n: usize, correlation: f64) -> (Vec<(usize, f64)>, f64) {
    let mut low: Vec<(usize, f64)> = Vec::new();
    let mut rest = correlation;
    loop {
        let live = two_core(corr, n, &low);
        let worst = (0..live.len())
            .filter(|&s| live[s])
            .map(|s| {
                let m = weighted_mean(corr, &|a, b| live[a] && live[b] && (a == s || b == s));
                (s, m.1)
            })
            .min_by(|x, y| x.1.total_cmp(&y.1));
        let Some((s, m)) = worst else { break };
        let (w, r) = weighted_mean(corr, &|a, b| live[a] && live[b] && a != s && b != s);
        // The views that judge it must agree among themselves: where the mesh is wrong, every
        // view of that part disagrees with the others, not one.
        let judge: Vec<bool> = (0..live.len())
            .map(|t| {
                live[t]
                    && corr
                        .iter()
                        .any(|c| (c.0, c.1) == (s, t) || (c.0, c.1) == (t, s))
            })
            .collect();
        let (jw, local) = weighted_mean(corr, &|a, b| judge[a] && judge[b]);
        if w == 0
            || m >= r - OUTLIER_GAP
            || jw == 0
            || local < OUTLIER_REST
            || m >= local - OUTLIER_GAP
        {
            break;
        }
        low.push((s, m));
        rest = r;
    }
    (low, rest)
}

/// The views (of `n` slots) not in `low` that keep at least two partners among themselves: the
/// 2-core of the pair graph without them.
fn two_core(corr: &[Pair], n: usize, low: &[(usize, f64)]) -> Vec<bool> {
    let mut live: Vec<bool> = (0..n).map(|s| low.iter().all(|&(t, _)| t != s)).collect();
    loop {
        let partners = |s: usize| {
            let with = |c: &&Pair| (c.0 == s && live[c.1]) || (c.1 == s && live[c.0]);
            corr.iter().filter(with).count()
        };
        let drop: Vec<usize> = (0..live.len())
            .filter(|&s| live[s] && partners(s) < 2)
            .collect();
        if drop.is_empty() {
            return live;
        }
        drop.iter().for_each(|&s| live[s] = false);
    }
}

/// Pearson correlation of the pairs; `None` when either side has less than [`MIN_STD`] spread.
fn pearson(xy: &[(f64, f64)]) -> Option<f64> {
    let n = xy.len() as f64;
    let (mx, my) = xy
        .iter()
        .fold((0.0, 0.0), |(a, b), &(x, y)| (a + x / n, b + y / n));
    let (mut sxy, mut sxx, mut syy) = (0f64, 0f64, 0f64);
    for &(x, y) in xy {
        sxy += (x - mx) * (y - my);
        sxx += (x - mx) * (x - mx);
        syy += (y - my) * (y - my);
    }
    let (sx, sy) = ((sxx / n).sqrt(), (syy / n).sqrt());
    (sx >= MIN_STD && sy >= MIN_STD).then(|| sxy / (n * sx * sy))
}
