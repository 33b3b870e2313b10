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
//! photos do not — and averages it weighted by the samples shared.
//!
//! Measured (`raycast::photo_check_flags_a_mesh_where_the_photos_disagree`, and with `xscale
//! batch`'s setup log on `synth` scenes and a real COLMAP workspace of 5 photos at downsample 4):
//! in place 0.93 (the `tiny` fixture), 0.97 (`synth --preset small` and `cross`), 0.99 (`large`),
//! 0.95 (the real workspace);
//! the mesh turned a quarter about a horizontal axis 0.02–0.35, about the vertical 0.23 on the
//! real scene; moved up by 5 % of its diagonal 0.21–0.49. A terrain turned within its own plane
//! keeps 0.75–0.78 (its points still lie on the photographed surface but for its relief), turned
//! by 10° or moved sideways by 3 % of its size 0.78–0.91: training learns from such a mesh,
//! worse; below [`MIN_CORRELATION`] it learns little.

use super::Tracer;
use crate::scene::{distance::area_samples, Camera, Image, Mesh};
use rayon::prelude::*;

/// Area samples of the mesh.
pub const SAMPLES: usize = 2000;
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

/// The plan and the luminances read so far ([module docs](self)).
pub struct PhotoCheck {
    /// Caller's view index → planned slot.
    slot: Vec<Option<usize>>,
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
}

impl Consistency {
    /// Whether the photos disagree where the mesh is (`false` without a pair to judge by).
    pub fn disagrees(&self) -> bool {
        self.pairs > 0 && self.correlation < MIN_CORRELATION
    }
}

impl PhotoCheck {
    /// Plan the check for `cameras` (the training views, in the caller's order).
    pub fn plan(mesh: &Mesh, tracer: &Tracer, cameras: &[&Camera]) -> PhotoCheck {
        let (lo, hi) = mesh.bbox();
        let tol = VISIBLE * (hi - lo).length();
        let points = area_samples(mesh, SAMPLES);
        let n = cameras.len();
        let planned: Vec<usize> = (0..n.min(MAX_VIEWS))
            .map(|k| k * n / n.min(MAX_VIEWS))
            .collect();
        let mut slot = vec![None; n];
        for (s, &k) in planned.iter().enumerate() {
            slot[k] = Some(s);
        }
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
            slot,
            lum: vec![None; planned.len()],
            seen,
            samples: points.len(),
        }
    }

    /// Read the luminances of the samples view `k` sees from its photo (`img`: the camera's size).
    pub fn add_view(&mut self, k: usize, img: &Image) {
        let Some(s) = self.slot.get(k).copied().flatten() else {
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
        let pairs: Vec<(usize, usize)> = (read.iter().enumerate())
            .flat_map(|(i, &a)| read[i + 1..].iter().map(move |&b| (a, b)))
            .collect();
        let (mut count, mut shared, mut sum) = (0usize, 0usize, 0f64);
        for &(a, b) in &pairs {
            let (la, lb) = (self.lum[a].as_ref().unwrap(), self.lum[b].as_ref().unwrap());
            let xy: Vec<(f64, f64)> = (0..self.samples)
                .filter_map(|j| Some((la[pos[a][j]? as usize], lb[pos[b][j]? as usize])))
                .collect();
            if xy.len() < MIN_SHARED {
                continue;
            }
            if let Some(r) = pearson(&xy) {
                count += 1;
                shared += xy.len();
                sum += xy.len() as f64 * r;
            }
        }
        Consistency {
            pairs: count,
            shared,
            correlation: if shared > 0 { sum / shared as f64 } else { 0.0 },
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
