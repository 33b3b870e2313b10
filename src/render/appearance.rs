//! The appearance code a rendered view is given (SPEC §4.6).
//!
//! A training view has its own row of `appearance.codes`. A view without one (held out, a new
//! camera, a frame of a flight) is given, by default, the codes of the training views whose
//! cameras are nearest to it, blended with the weights of unstructured lumigraph rendering
//! (Buehler et al. 2001; `render::ulr` uses the same rule per pixel):
//!
//! ```text
//! p_j = ∠(z, z_j) + |c − c_j| / s        z: optical axis, c: centre; s: the median distance of the
//!                                        training centres from their mean (the capture's radius)
//! w_j = (1 − p_j / p_(K+1)) / p_j        over the K smallest p_j (p_(K+1): the next one, or
//!                                        2·max when there are only K), normalised to sum 1
//! code = Σ_j w_j · code_j                (rows in ascending order, f64, rounded once to f32)
//! ```
//!
//! K is the model's own, chosen by leave one out ([`leave_one_out_k`]): the count whose blend
//! best predicts each training view's code from the other training views'.
//!
//! A camera at a training camera's pose (p_j = 0) takes that view's code. Nothing about the
//! rendered view's photo is used, only its camera: a phone's exposure and white balance drift
//! along a capture, and a view's neighbours in pose were taken under the light, exposure and
//! white balance closest to its own (on the real `fox` capture the mean code cost 0.3 dB of
//! masked PSNR; docs/results.md `real`). `appearance = "mean"` (`[model]`) gives every such
//! view the mean of all rows instead, as the official code's mean exposure code.

use crate::model::hfm::Hfm;
use crate::scene::Camera;
use glam::DVec3;
use serde::{Deserialize, Serialize};

/// Training views blended for a view without a code when [`leave_one_out_k`] has too few
/// views to choose (and [`neighbour_weights`]' count).
pub const K: usize = 4;

/// What a view without its own row is given (`[model] appearance`).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "lowercase")]
pub enum NewViewCode {
    /// The mean of all rows (the official code's mean exposure code; docs/spec.md §4.6's `code(−1)`).
    Mean,
    /// The codes of the nearest training cameras, blended (module docs).
    #[default]
    Neighbours,
}

/// The appearance of one rendered view.
#[derive(Clone, Debug, PartialEq)]
pub enum Appearance {
    /// An appearance row, or −1 for the mean code (SPEC §4.6).
    Row(i32),
    /// A code of its own (`[A]`), used for every pixel (as view −1 with this code).
    Code(Vec<f32>),
}

impl Appearance {
    /// The batch row (−1 for a code of its own) and the code that replaces the mean.
    pub fn row_and_code(&self) -> (i32, Option<&[f32]>) {
        match self {
            Appearance::Row(r) => (*r, None),
            Appearance::Code(c) => (-1, Some(c)),
        }
    }
}

/// The camera's optical axis (world).
fn axis(c: &Camera) -> DVec3 {
    c.rotation.transpose() * DVec3::Z
}

/// The median distance of `centres` from their mean (the capture's radius; 1 when it is 0).
fn spread(centres: &[DVec3]) -> f64 {
    if centres.is_empty() {
        return 1.0;
    }
    let mean = centres.iter().fold(DVec3::ZERO, |a, &c| a + c) / centres.len() as f64;
    let mut d: Vec<f64> = centres.iter().map(|&c| (c - mean).length()).collect();
    d.sort_by(f64::total_cmp);
    let m = d[d.len() / 2];
    if m > 0.0 && m.is_finite() {
        m
    } else {
        1.0
    }
}

/// ULR weights of the training cameras `train` (by row) for `camera` (module docs): at most
/// [`K`] `(row, weight)` pairs, weights summing to 1, rows ascending. Empty when `train` is.
pub fn neighbour_weights(camera: &Camera, train: &[&Camera]) -> Vec<(usize, f64)> {
    neighbour_weights_k(camera, train, K)
}

/// [`neighbour_weights`] over the `k` nearest (k ≥ 1).
pub fn neighbour_weights_k(camera: &Camera, train: &[&Camera], k: usize) -> Vec<(usize, f64)> {
    if train.is_empty() {
        return Vec::new();
    }
    let centres: Vec<DVec3> = train.iter().map(|c| c.center()).collect();
    let s = spread(&centres);
    let (z, c) = (axis(camera), camera.center());
    let mut p: Vec<(f64, usize)> = train
        .iter()
        .zip(&centres)
        .enumerate()
        .map(|(j, (t, &cj))| {
            let angle = z.dot(axis(t)).clamp(-1.0, 1.0).acos();
            (angle + (c - cj).length() / s, j)
        })
        .collect();
    p.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
    if p[0].0 <= 1e-12 {
        return vec![(p[0].1, 1.0)];
    }
    let k = k.max(1).min(p.len());
    let next = if p.len() > k {
        p[k].0
    } else {
        2.0 * p[k - 1].0
    };
    let mut w: Vec<(usize, f64)> = p[..k]
        .iter()
        .map(|&(pj, j)| (j, ((1.0 - pj / next) / pj).max(0.0)))
        .collect();
    let total: f64 = w.iter().map(|x| x.1).sum();
    if !(total > 0.0 && total.is_finite()) {
        // Every one of the K as far as the next: equal weights.
        w.iter_mut().for_each(|x| x.1 = 1.0 / k as f64);
    } else {
        w.iter_mut().for_each(|x| x.1 /= total);
    }
    w.sort_by_key(|x| x.0);
    w
}

/// The appearances of the views rendered with one model and fixed parameters: a view's own
/// `row` if it has one (≥ 0), else by `rule` — the mean code, or the blend of its neighbours'
/// codes (`train`: the training cameras, by row) over the K that [`leave_one_out_k`] chooses,
/// found once here rather than for every view. Models without codes (A = 0), or whose rows do
/// not match `train`, take `Row(row)` as it is.
pub struct NewViewCodes<'a> {
    model: &'a Hfm,
    params: &'a [f32],
    train: Vec<&'a Camera>,
    /// The neighbours blended; `None` when no view is blended (the mean-code rule, or the
    /// conditions above).
    k: Option<usize>,
}

impl<'a> NewViewCodes<'a> {
    pub fn new(
        model: &'a Hfm,
        params: &'a [f32],
        rule: NewViewCode,
        train: Vec<&'a Camera>,
    ) -> NewViewCodes<'a> {
        let a = model.appearance_dim();
        let blends =
            a > 0 && rule == NewViewCode::Neighbours && train.len() == model.appearance_views();
        let k = blends.then(|| leave_one_out_k(model.codes(params), a, &train));
        NewViewCodes {
            model,
            params,
            train,
            k,
        }
    }

    /// The appearance of a view with appearance row `row` (−1: none) and camera `camera`.
    pub fn appearance(&self, row: i32, camera: &Camera) -> Appearance {
        let Some(k) = self.k.filter(|_| row < 0) else {
            return Appearance::Row(row);
        };
        let a = self.model.appearance_dim();
        let codes = self.model.codes(self.params);
        let mut code = vec![0.0f64; a];
        for (j, w) in neighbour_weights_k(camera, &self.train, k) {
            for (c, &v) in code.iter_mut().zip(&codes[j * a..(j + 1) * a]) {
                *c += w * v as f64;
            }
        }
        Appearance::Code(code.into_iter().map(|v| v as f32).collect())
    }
}

/// The neighbour counts [`leave_one_out_k`] tries (those below the number of training views,
/// and all of them when there are at most 16).
pub const K_CANDIDATES: [usize; 5] = [1, 2, 4, 8, 16];

/// The neighbour count a view without a code blends (`[model] appearance = "neighbours"`):
/// the K whose blend best predicts each training view's own code from the other training
/// views' (leave one out) — the least sum over views of the squared code error (f64, views in
/// row order; the smaller K on a tie) over [`K_CANDIDATES`] below the number of training views
/// `n`, and `n` itself when n ≤ 16 (all views: the n − 1 others of a view left out).
/// [`K`] with fewer than 3 training views or no codes.
///
/// Why: how far a code carries depends on the capture. A phone's exposure and white balance
/// drift slowly along a capture, so the codes of many neighbours predict a view's best (K = 8
/// on the real `fox` and the skull); a synthetic scene's codes hold only what training left in
/// them, and its nearest few predict them best (K = 4 on `synth small`, `cross`). Scored on
/// held-out views, the rule's choice was the best or tied-best K on each of them
/// (docs/changelog.md).
pub fn leave_one_out_k(codes: &[f32], a: usize, train: &[&Camera]) -> usize {
    let n = train.len();
    if n < 3 || a == 0 || codes.len() != n * a {
        return K;
    }
    let mut candidates: Vec<usize> = K_CANDIDATES.iter().copied().filter(|&k| k < n).collect();
    if n <= K_CANDIDATES[K_CANDIDATES.len() - 1] {
        // All of them: the n − 1 others when a view is left out, all n for a new view.
        candidates.push(n);
    }
    let mut best = (f64::INFINITY, K);
    for k in candidates {
        let mut err = 0.0f64;
        for j in 0..n {
            let others: Vec<&Camera> = (0..n).filter(|&i| i != j).map(|i| train[i]).collect();
            let mut pred = vec![0.0f64; a];
            for (r, w) in neighbour_weights_k(train[j], &others, k) {
                let row = if r < j { r } else { r + 1 };
                for (p, &v) in pred.iter_mut().zip(&codes[row * a..(row + 1) * a]) {
                    *p += w * v as f64;
                }
            }
            err += pred
                .iter()
                .zip(&codes[j * a..(j + 1) * a])
                .map(|(p, &c)| (p - c as f64).powi(2))
                .sum::<f64>();
        }
        if err < best.0 {
            best = (err, k);
        }
    }
    best.1
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::DMat3;

    fn cam_at(angle: f64) -> Camera {
        // On a ring of radius 2 about the origin, looking at it.
        let c = DVec3::new(2.0 * angle.cos(), 2.0 * angle.sin(), 0.0);
        let z = -c.normalize();
        let x = z.cross(DVec3::Z).normalize();
        let y = z.cross(x);
        let rotation = DMat3::from_cols(x, y, z).transpose();
        crate::scene::camera::Intrinsics {
            width: 8,
            height: 8,
            fx: 8.0,
            fy: 8.0,
            cx: 4.0,
            cy: 4.0,
            distortion: Default::default(),
        }
        .posed(rotation, -(rotation * c))
    }

    #[test]
    fn weights_favour_the_nearest_cameras_and_sum_to_one() {
        let train: Vec<Camera> = (0..12).map(|k| cam_at(k as f64 * 0.5)).collect();
        let refs: Vec<&Camera> = train.iter().collect();
        let w = neighbour_weights(&cam_at(1.1), &refs);
        assert_eq!(w.len(), K);
        let total: f64 = w.iter().map(|x| x.1).sum();
        assert!((total - 1.0).abs() < 1e-12, "{w:?}");
        // 1.1 lies between rows 2 (1.0) and 3 (1.5), nearer 2.
        let get = |r: usize| w.iter().find(|x| x.0 == r).map_or(0.0, |x| x.1);
        assert!(get(2) > get(3) && get(3) > 0.0, "{w:?}");
        assert!(w.iter().all(|x| x.0 <= 5), "{w:?}");
        // At a training pose: that view alone.
        assert_eq!(neighbour_weights(&cam_at(1.5), &refs), vec![(3, 1.0)]);
        assert!(neighbour_weights(&cam_at(0.0), &[]).is_empty());
    }

    #[test]
    fn leave_one_out_picks_few_neighbours_for_a_drift_and_many_for_noise() {
        let train: Vec<Camera> = (0..24).map(|k| cam_at(k as f64 * 0.26)).collect();
        let refs: Vec<&Camera> = train.iter().collect();
        // A code that drifts fast around the ring (an exposure ramp): the nearest views know it.
        let drift: Vec<f32> = (0..24)
            .flat_map(|k| {
                let t = k as f32 * 0.26;
                [(3.0 * t).sin(), (3.0 * t).cos()]
            })
            .collect();
        assert!(leave_one_out_k(&drift, 2, &refs) <= 2);
        // The same constant code plus independent noise per view: the more views, the better.
        let noise: Vec<f32> = (0..48)
            .map(|i| {
                0.5 + ((crate::rng::fmix(i as u64 + 1) >> 40) as f32 / (1u64 << 24) as f32 - 0.5)
            })
            .collect();
        assert!(leave_one_out_k(&noise, 2, &refs) >= 8);
        // Too few views to choose, or no codes: the constant.
        assert_eq!(leave_one_out_k(&noise[..4], 2, &refs[..2]), K);
        assert_eq!(leave_one_out_k(&[], 0, &refs), K);
        // A small capture may blend all the others.
        let few: Vec<f32> = noise[..12].to_vec();
        assert!(leave_one_out_k(&few, 2, &refs[..6]) >= 4);
    }
}
