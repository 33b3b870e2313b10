//! Do the photos agree where the mesh is? A surface point of a mesh in the cameras' frame looks
//! alike in every training view that sees it; a mesh in another frame puts the "same" point on
//! unrelated pixels. The check needs no reconstruction points (`scene/points.rs`), so it also
//! covers the layouts that have none (MVSNet, instant-ngp and NeRF-synthetic transforms), and it
//! runs where the photos are read anyway: `train`'s setup, one photo at a time.
//!
//! [`PhotoCheck::plan`] takes [`SAMPLES`] area samples of the mesh and, for an even stride of at
//! most [`MAX_VIEWS`] training views, the samples each view sees: in front of it, inside its
//! image, and not hidden (the ray from its centre meets the mesh within [`VISIBLE`] of the mesh's
//! diagonal of the sample). [`PhotoCheck::add_view`] reads each seen sample's luminance from the
//! photo (the mean of R, G, B over the 3×3 pixels around its projection). [`PhotoCheck::result`]
//! takes, for every pair of views sharing at least [`MIN_SHARED`] samples with texture in both
//! (a standard deviation of at least [`MIN_STD`]), the Pearson correlation of the two views'
//! luminances of those samples — gain and offset do not count, so exposure changes between
//! photos do not — and averages it weighted by the samples shared. A view whose own pairs
//! correlate [`OUTLIER_GAP`] below the rest's is named: the mesh agrees with the other photos,
//! so that view's pose is wrong. A close-up that sees fewer than [`MIN_SHARED`] of the samples is
//! not judged (area samples rarely meet it; comparing it with a coarser view needs its photo
//! averaged to that view's footprint, which is not built).
//!
//! Measured (`raycast::photo_check_*`, and with `xscale cast` / `batch` on `synth` scenes and a
//! real COLMAP workspace of 5 photos): in place 0.92 (the `tiny` fixture), 0.97 (`synth --preset
//! small` and `cross`), 0.99 (`large`), 0.92 (the real workspace; 0.95 at downsample 4); the mesh
//! turned a quarter about a horizontal axis 0.06–0.35, about the vertical 0.25 on the real scene;
//! moved up by 5 % of its diagonal 0.18–0.48. A terrain turned within its own plane keeps
//! 0.72–0.77 (its points still lie on the photographed surface but for its relief), turned by 10°
//! or moved sideways by 3 % of its size 0.76–0.92: training learns from such a mesh, worse; below
//! [`MIN_CORRELATION`] it learns little.

use super::Tracer;
use crate::scene::{distance::area_samples, Camera, Image, Mesh};
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
/// pose is wrong. In place every judged view of the scenes measured correlates 0.91 or more
/// (within 0.06 of the rest); one `small` view turned about its axis by 5° drops to 0.72 against
/// 0.97 (by 3°: not flagged; by 180°: 0.04).
pub const OUTLIER_GAP: f64 = 0.2;
/// Views are named only when the others correlate at least this well (a mesh in place) and they
/// are at most a quarter of the judged views: a mesh out of place leaves some pairs of nearby
/// views agreeing and the rest not, which is not one view's pose (`small` with its mesh moved
/// sideways by 3 % of its size: 0.85 overall, three views 0.2 below).
pub const OUTLIER_REST: f64 = 0.9;

/// The plan and the luminances read so far ([module docs](self)).
pub struct PhotoCheck {
    /// Planned slot → caller's view index (increasing).
    planned: Vec<usize>,
    /// Per slot: (sample, pixel x, pixel y) of the samples the view sees, in sample order.
    seen: Vec<Vec<(u32, u32, u32)>>,
    /// Per slot: the seen samples' luminances, once [`PhotoCheck::add_view`] has read the photo.
    lum: Vec<Option<Vec<f64>>>,
    samples: usize,
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
    /// Mean correlation of the pairs without an outlier (`correlation` when there is none).
    pub rest: f64,
}

impl Consistency {
    /// Whether the photos disagree where the mesh is (`false` without a pair to judge by).
    pub fn disagrees(&self) -> bool {
        self.pairs > 0 && self.correlation < MIN_CORRELATION
    }

    /// What `train` and `cast` say of it: the correlation (a warning below [`MIN_CORRELATION`]),
    /// and a warning per view whose pose disagrees with the others' (`name(k)`: the name of the
    /// caller's view `k`).
    pub fn messages(&self, name: &dyn Fn(usize) -> String) -> Vec<String> {
        if self.pairs == 0 {
            return vec![
                "photo check: no two views share enough textured surface to compare".into(),
            ];
        }
        let what = format!(
            "the colours two photos see at the same surface points correlate {:.2} ({} view pairs, {} points; in place typically 0.9 or more, below {} the mesh stands elsewhere)",
            self.correlation, self.pairs, self.shared, MIN_CORRELATION
        );
        let mut out = vec![if self.disagrees() {
            format!(
                "warning: {what}: the photos disagree where the mesh is, which probably stands in another frame than the cameras (another tool's coordinate system, a turned or moved export, a transforms.json read in the wrong frame: docs/spec.md §3); training will run but learn little"
            )
        } else {
            format!("photo check: {what}")
        }];
        out.extend(self.outliers.iter().map(|&(k, c)| {
            format!(
                "warning: view {}: its photo disagrees with the others where the mesh is (correlation {c:.2} against {:.2} among the other views): its pose is probably wrong (a bad registration); hold it out with test_views in scene.toml, or fix it",
                name(k),
                self.rest
            )
        }));
        out
    }
}

impl PhotoCheck {
    /// Plan the check for `cameras` (the training views, in the caller's order).
    pub fn plan(mesh: &Mesh, tracer: &Tracer, cameras: &[&Camera]) -> PhotoCheck {
        let (lo, hi) = mesh.bbox();
        let tol = VISIBLE * (hi - lo).length();
        let n = cameras.len();
        let planned: Vec<usize> = (0..n.min(MAX_VIEWS))
            .map(|k| k * n / n.min(MAX_VIEWS))
            .collect();
        let points = area_samples(mesh, SAMPLES);
        let seen = planned
            .par_iter()
            .map(|&k| {
                let cam = cameras[k];
                let centre = cam.center();
                let (w, h) = (cam.width as f64, cam.height as f64);
                (points.iter().enumerate())
                    .filter_map(|(j, &p)| {
                        let (x, y) = cam.project(p)?;
                        if !(x >= 1.0 && y >= 1.0 && x < w - 1.0 && y < h - 1.0) {
                            return None;
                        }
                        let to = p - centre;
                        let hit = tracer.closest_hit(centre, to)?;
                        ((hit.t - to.length()).abs() <= tol)
                            .then_some((j as u32, x as u32, y as u32))
                    })
                    .collect()
            })
            .collect();
        PhotoCheck {
            lum: vec![None; planned.len()],
            planned,
            seen,
            samples: points.len(),
        }
    }

    /// Read the luminances of the samples view `k` sees from its photo (`img`: the camera's size).
    pub fn add_view(&mut self, k: usize, img: &Image) {
        let Ok(s) = self.planned.binary_search(&k) else {
            return;
        };
        let (w, h) = (img.width as usize, img.height as usize);
        let lum = self.seen[s]
            .iter()
            .map(|&(_, x, y)| {
                let (x, y) = (x as usize, y as usize);
                let (mut sum, mut count) = (0f64, 0usize);
                for yy in y.saturating_sub(1)..(y + 2).min(h) {
                    for xx in x.saturating_sub(1)..(x + 2).min(w) {
                        sum += img.data[(yy * w + xx) * 3..][..3]
                            .iter()
                            .map(|&v| v as f64)
                            .sum::<f64>();
                        count += 3;
                    }
                }
                sum / count.max(1) as f64
            })
            .collect();
        self.lum[s] = Some(lum);
    }

    /// Correlate the views read so far ([module docs](self)).
    pub fn result(&self) -> Consistency {
        // Per slot: sample → position in its list.
        let pos: Vec<Vec<Option<u32>>> = (self.seen.iter())
            .map(|list| {
                let mut p = vec![None; self.samples];
                for (k, &(j, _, _)) in list.iter().enumerate() {
                    p[j as usize] = Some(k as u32);
                }
                p
            })
            .collect();
        let read: Vec<usize> = (0..self.seen.len())
            .filter(|&s| self.lum[s].is_some())
            .collect();
        let pairs = (read.iter().enumerate())
            .flat_map(|(i, &a)| read[i + 1..].iter().map(move |&b| (a, b)));
        // Each correlated pair: (slot a, slot b, samples shared, correlation).
        let mut corr: Vec<(usize, usize, usize, f64)> = Vec::new();
        for (a, b) in pairs {
            let (la, lb) = (self.lum[a].as_ref().unwrap(), self.lum[b].as_ref().unwrap());
            let xy: Vec<(f64, f64)> = (0..self.samples)
                .filter_map(|j| Some((la[pos[a][j]? as usize], lb[pos[b][j]? as usize])))
                .collect();
            if xy.len() < MIN_SHARED {
                continue;
            }
            if let Some(r) = pearson(&xy) {
                corr.push((a, b, xy.len(), r));
            }
        }
        let mean = |keep: &dyn Fn(usize, usize) -> bool| {
            let (mut w, mut sum) = (0usize, 0f64);
            for &(_, _, n, r) in corr.iter().filter(|c| keep(c.0, c.1)) {
                w += n;
                sum += n as f64 * r;
            }
            (w, if w > 0 { sum / w as f64 } else { 0.0 })
        };
        let (shared, correlation) = mean(&|_, _| true);
        // A view whose own pairs correlate [`OUTLIER_GAP`] below the others': its pose, not the
        // mesh. Candidates against all pairs, confirmed against the pairs without them.
        let own: Vec<(usize, f64)> = (0..self.seen.len())
            .filter_map(|s| {
                let (w, m) = mean(&|a, b| a == s || b == s);
                (w > 0).then_some((s, m))
            })
            .collect();
        let low: Vec<(usize, f64)> = (own.iter().copied())
            .filter(|&(_, m)| m < correlation - OUTLIER_GAP)
            .collect();
        let (rest_w, rest) = mean(&|a, b| low.iter().all(|&(s, _)| s != a && s != b));
        let confirmed = !low.is_empty()
            && 4 * low.len() <= own.len()
            && rest_w > 0
            && rest >= OUTLIER_REST
            && low.iter().all(|&(_, m)| m < rest - OUTLIER_GAP);
        let outliers = if confirmed {
            low.iter().map(|&(s, m)| (self.planned[s], m)).collect()
        } else {
            Vec::new()
        };
        Consistency {
            pairs: corr.len(),
            shared,
            correlation,
            rest: if outliers.is_empty() {
                correlation
            } else {
                rest
            },
            outliers,
        }
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
