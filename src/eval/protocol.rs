//! The held-out protocol (SPEC §7): render each test view, paint pixels whose rays all miss white
//! in both the prediction and the ground truth, and report PSNR / SSIM over the full image and
//! over the hit pixels only.

use crate::eval::metrics::{psnr, psnr_masked, ssim, ssim_masked};
use crate::scene::Image;
use serde::Serialize;

#[derive(Clone, Debug, Serialize)]
pub struct ViewScore {
    pub view: String,
    pub psnr: f64,
    pub ssim: f64,
    pub psnr_masked: f64,
    pub ssim_masked: f64,
    /// Fraction of pixels whose rays hit the mesh.
    pub hit_fraction: f64,
}

/// Ground truth with misses painted white (the prediction already has them white).
pub fn mask_ground_truth(gt: &Image, hit: &[bool]) -> Image {
    let mut g = gt.clone();
    for (i, &h) in hit.iter().enumerate() {
        if !h {
            g.data[i * 3..i * 3 + 3].fill(1.0);
        }
    }
    g
}

/// Score a prediction (misses white) against a ground truth (misses painted white here).
pub fn score_view(name: &str, pred: &Image, gt: &Image, hit: &[bool]) -> (ViewScore, Image) {
    let g = mask_ground_truth(gt, hit);
    let (w, h) = (pred.width as usize, pred.height as usize);
    let s = ViewScore {
        view: name.to_string(),
        psnr: psnr(&pred.data, &g.data),
        ssim: ssim(&pred.data, &g.data, w, h),
        psnr_masked: psnr_masked(&pred.data, &g.data, hit),
        ssim_masked: ssim_masked(&pred.data, &g.data, w, h, hit),
        hit_fraction: hit.iter().filter(|&&x| x).count() as f64 / hit.len().max(1) as f64,
    };
    (s, g)
}

/// Mean of each metric over views (NaN-free views only for each metric).
pub fn mean_score(scores: &[ViewScore]) -> ViewScore {
    let mean = |f: &dyn Fn(&ViewScore) -> f64| {
        let v: Vec<f64> = scores.iter().map(f).filter(|x| x.is_finite()).collect();
        if v.is_empty() {
            f64::NAN
        } else {
            v.iter().sum::<f64>() / v.len() as f64
        }
    };
    ViewScore {
        view: "mean".into(),
        psnr: mean(&|s| s.psnr),
        ssim: mean(&|s| s.ssim),
        psnr_masked: mean(&|s| s.psnr_masked),
        ssim_masked: mean(&|s| s.ssim_masked),
        hit_fraction: mean(&|s| s.hit_fraction),
    }
}

/// A printed table of scores.
pub fn table(scores: &[ViewScore]) -> String {
    let mut out = format!(
        "{:<24} {:>8} {:>7} {:>11} {:>10} {:>6}\n",
        "view", "PSNR", "SSIM", "PSNR(mask)", "SSIM(mask)", "hit%"
    );
    for s in scores.iter().chain(std::iter::once(&mean_score(scores))) {
        out += &format!(
            "{:<24} {:>8.3} {:>7.4} {:>11.3} {:>10.4} {:>6.1}\n",
            s.view,
            s.psnr,
            s.ssim,
            s.psnr_masked,
            s.ssim_masked,
            100.0 * s.hit_fraction
        );
    }
    out
}
