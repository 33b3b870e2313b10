//! The held-out protocol (SPEC §7): render each test view (misses in the scene's background
//! colour) and score it against its photo with PSNR, SSIM and ꟻLIP, over two pixel sets:
//!
//! - **full**: every pixel (inside the object mask when the scene has masks), the render against
//!   the photo *as it is* — misses of the mesh count as the error they are, so silhouette errors
//!   of the mesh show;
//! - **masked**: the pixels whose rays hit the mesh (and inside the object mask), the photo's
//!   misses painted with the background colour like the render's (so SSIM windows that straddle
//!   the silhouette compare background with background, as in the official protocol where both
//!   are painted white).
//!
//! A view whose every ray misses (or whose mask holds no hit) has no masked score (NaN); means
//! skip NaN values metric by metric, and `mean_score` says which views had none. SSIM needs an
//! image of at least 11×11 pixels (its window); smaller views have no SSIM (NaN, "n/a").
//! With masks, `mask_miss` is the fraction of mask pixels the mesh misses (silhouette coverage).

use crate::eval::metrics::{flip_map, masked_mean, psnr_masked, ssim, ssim_masked};
use crate::render::{comparison, Appearance, ModelRenderer, Rendered};
use crate::scene::image::write_png8;
use crate::scene::{Image, Scene};
use anyhow::{Context, Result};
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};

#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
pub struct ViewScore {
    pub view: String,
    /// Full image (inside the object mask, if any): render vs the untouched photo.
    pub psnr: f64,
    pub ssim: f64,
    /// Mean ꟻLIP error over the same pixels (lower is better).
    pub flip: f64,
    /// Hit pixels only (inside the object mask, if any).
    pub psnr_masked: f64,
    pub ssim_masked: f64,
    pub flip_masked: f64,
    /// Fraction of pixels whose rays hit the mesh.
    pub hit_fraction: f64,
    /// Fraction of object-mask pixels the mesh misses (scenes with masks only).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub mask_miss: Option<f64>,
    /// Median pixel footprint on the surface over the view's hit pixels, in scene units (the
    /// scale the view sees; `None` when no pixel hits or for a mean).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub footprint: Option<f64>,
}

/// A scored view: the scores, the photo as it is (for the side-by-side) and the per-pixel ꟻLIP
/// error of the full image.
pub struct Scored {
    pub score: ViewScore,
    pub photo: Image,
    pub flip_map: Vec<f32>,
}

/// The photo with the pixels whose rays all miss painted `background`.
pub fn paint_misses(gt: &Image, hit: &[bool], background: [f32; 3]) -> Image {
    let mut g = gt.clone();
    for (i, &h) in hit.iter().enumerate() {
        if !h {
            g.data[i * 3..i * 3 + 3].copy_from_slice(&background);
        }
    }
    g
}

/// Score a render (misses already `background`) against its untouched photo (module docs).
pub fn score_view(
    name: &str,
    pred: &Image,
    gt: &Image,
    hit: &[bool],
    mask: Option<&[bool]>,
    background: [f32; 3],
) -> Scored {
    let (w, h) = (pred.width as usize, pred.height as usize);
    let painted = paint_misses(gt, hit, background);
    let all = vec![true; hit.len()];
    let full: &[bool] = mask.unwrap_or(&all);
    let hit_in: Vec<bool> = hit.iter().zip(full).map(|(&a, &b)| a && b).collect();
    let fmap = flip_map(&gt.data, &pred.data, w, h);
    let fmap_masked = flip_map(&painted.data, &pred.data, w, h);
    let mask_miss = mask.map(|m| {
        let inside = m.iter().filter(|&&x| x).count();
        let missed = m.iter().zip(hit).filter(|&(&x, &h)| x && !h).count();
        missed as f64 / inside.max(1) as f64
    });
    let score = ViewScore {
        view: name.to_string(),
        psnr: psnr_masked(&pred.data, &gt.data, full),
        ssim: match mask {
            None => ssim(&pred.data, &gt.data, w, h),
            Some(m) => ssim_masked(&pred.data, &gt.data, w, h, m),
        },
        flip: masked_mean(&fmap, Some(full)),
        psnr_masked: psnr_masked(&pred.data, &painted.data, &hit_in),
        ssim_masked: ssim_masked(&pred.data, &painted.data, w, h, &hit_in),
        flip_masked: masked_mean(&fmap_masked, Some(&hit_in)),
        hit_fraction: hit.iter().filter(|&&x| x).count() as f64 / hit.len().max(1) as f64,
        mask_miss,
        footprint: None,
    };
    Scored {
        score,
        photo: gt.clone(),
        flip_map: fmap,
    }
}

/// Mean of each metric over views; a view whose value is not finite (no hit pixel, an image
/// smaller than SSIM's window, a perfect PSNR) is left out of that metric's mean.
pub fn mean_score(scores: &[ViewScore]) -> ViewScore {
    let mean = |f: &dyn Fn(&ViewScore) -> f64| {
        let v: Vec<f64> = scores.iter().map(f).filter(|x| x.is_finite()).collect();
        if v.is_empty() {
            f64::NAN
        } else {
            v.iter().sum::<f64>() / v.len() as f64
        }
    };
    let any_mask = scores.iter().any(|s| s.mask_miss.is_some());
    ViewScore {
        view: "mean".into(),
        psnr: mean(&|s| s.psnr),
        ssim: mean(&|s| s.ssim),
        flip: mean(&|s| s.flip),
        psnr_masked: mean(&|s| s.psnr_masked),
        ssim_masked: mean(&|s| s.ssim_masked),
        flip_masked: mean(&|s| s.flip_masked),
        hit_fraction: mean(&|s| s.hit_fraction),
        mask_miss: any_mask.then(|| mean(&|s| s.mask_miss.unwrap_or(f64::NAN))),
        footprint: None,
    }
}

/// Scores of the views whose median footprint lies in `[lo, hi)` (scene units).
#[derive(Clone, Debug, Serialize)]
pub struct ScaleGroup {
    pub lo: f64,
    pub hi: f64,
    pub views: Vec<String>,
    pub mean: ViewScore,
}

/// Held-out scores grouped by the scale each view sees: factor-2 bins of the views' median
/// footprints (`[2^k, 2^(k+1))` scene units), finest first, and a near/far split at the geometric
/// mean of the finest and coarsest view footprints (`None` when all views see one scale, i.e.
/// they lie within a factor 2). A mean over all views hides a close-up failure; these do not.
#[derive(Clone, Debug, Serialize)]
pub struct ScaleSummary {
    pub bins: Vec<ScaleGroup>,
    /// `(split, near, far)`: near = footprint below `split`.
    pub near_far: Option<(f64, ScaleGroup, ScaleGroup)>,
}

pub fn scale_summary(scores: &[ViewScore]) -> ScaleSummary {
    let with: Vec<(&ViewScore, f64)> = scores
        .iter()
        .filter_map(|s| {
            s.footprint
                .filter(|f| *f > 0.0 && f.is_finite())
                .map(|f| (s, f))
        })
        .collect();
    let group = |lo: f64, hi: f64| {
        let members: Vec<ViewScore> = with
            .iter()
            .filter(|(_, f)| *f >= lo && *f < hi)
            .map(|(s, _)| (*s).clone())
            .collect();
        ScaleGroup {
            lo,
            hi,
            views: members.iter().map(|s| s.view.clone()).collect(),
            mean: mean_score(&members),
        }
    };
    let mut ks: Vec<i32> = with.iter().map(|(_, f)| f.log2().floor() as i32).collect();
    ks.sort_unstable();
    ks.dedup();
    let bins = ks
        .iter()
        .map(|&k| group(2f64.powi(k), 2f64.powi(k + 1)))
        .collect();
    let (fmin, fmax) = with.iter().fold((f64::INFINITY, 0.0f64), |(a, b), (_, f)| {
        (a.min(*f), b.max(*f))
    });
    let near_far = (with.len() >= 2 && fmax >= 2.0 * fmin).then(|| {
        let split = (fmin * fmax).sqrt();
        (split, group(0.0, split), group(split, f64::INFINITY))
    });
    ScaleSummary { bins, near_far }
}

/// The per-scale lines printed under the score table.
pub fn scale_table(scores: &[ViewScore]) -> String {
    let s = scale_summary(scores);
    if s.bins.len() < 2 {
        return String::new();
    }
    let line = |label: String, g: &ScaleGroup| {
        format!(
            "{label:<34} {:>3} views  PSNR(mask) {}  SSIM(mask) {}\n",
            g.views.len(),
            cell(g.mean.psnr_masked, 7, 3),
            cell(g.mean.ssim_masked, 6, 4)
        )
    };
    let mut out = String::from("by scale (median pixel footprint of each view, scene units):\n");
    for g in &s.bins {
        out += &line(format!("  footprint {:.3e} .. {:.3e}", g.lo, g.hi), g);
    }
    if let Some((split, near, far)) = &s.near_far {
        out += &line(format!("  near (footprint < {split:.3e})"), near);
        out += &line(format!("  far  (footprint >= {split:.3e})"), far);
    }
    out
}

/// Names of the views left out of the masked means (no pixel hits the mesh).
pub fn views_without_hits(scores: &[ViewScore]) -> Vec<String> {
    scores
        .iter()
        .filter(|s| !s.psnr_masked.is_finite())
        .map(|s| s.view.clone())
        .collect()
}

fn cell(v: f64, width: usize, prec: usize) -> String {
    if v.is_nan() {
        format!("{:>width$}", "n/a")
    } else {
        format!("{v:>width$.prec$}")
    }
}

/// A printed table of scores (n/a where a metric has no value; see the module doc).
pub fn table(scores: &[ViewScore]) -> String {
    let masks = scores.iter().any(|s| s.mask_miss.is_some());
    let mut out = format!(
        "{:<24} {:>8} {:>7} {:>6} {:>11} {:>10} {:>10} {:>6}{}\n",
        "view",
        "PSNR",
        "SSIM",
        "FLIP",
        "PSNR(mask)",
        "SSIM(mask)",
        "FLIP(mask)",
        "hit%",
        if masks { "  miss%" } else { "" }
    );
    for s in scores.iter().chain(std::iter::once(&mean_score(scores))) {
        out += &format!(
            "{:<24} {} {} {} {} {} {} {}{}\n",
            s.view,
            cell(s.psnr, 8, 3),
            cell(s.ssim, 7, 4),
            cell(s.flip, 6, 4),
            cell(s.psnr_masked, 11, 3),
            cell(s.ssim_masked, 10, 4),
            cell(s.flip_masked, 10, 4),
            cell(100.0 * s.hit_fraction, 6, 1),
            s.mask_miss
                .map_or(String::new(), |m| format!(" {}", cell(100.0 * m, 6, 2)))
        );
    }
    let none = views_without_hits(scores);
    if !none.is_empty() {
        out += &format!(
            "(no pixel of {} sees the mesh: left out of the masked means)\n",
            none.join(", ")
        );
    }
    // A full-image SSIM of n/a with a PSNR: no pixel has SSIM's whole window (see the module doc).
    let no_ssim: Vec<&str> = scores
        .iter()
        .filter(|s| s.ssim.is_nan() && !s.psnr.is_nan())
        .map(|s| s.view.as_str())
        .collect();
    if !no_ssim.is_empty() {
        out += &format!(
            "(SSIM of {} is n/a: SSIM averages 11×11 windows, and the image is smaller than 11×11 or its mask lies within 5 pixels of the border; left out of the SSIM means)\n",
            no_ssim.join(", ")
        );
    }
    out
}

/// A held-out view rendered and scored.
pub struct Evaluated {
    pub rendered: Rendered,
    pub scored: Scored,
}

/// Render scene view `i` with `renderer` in `appearance` (`render::appearance`: a row, −1 for
/// the mean code, or a code of its own) and score it against its photo inside its mask
/// (module docs).
pub fn evaluate_view(
    renderer: &ModelRenderer,
    scene: &Scene,
    i: usize,
    appearance: &Appearance,
) -> Result<Evaluated> {
    let rendered = renderer.render(&scene.views[i].camera, appearance)?;
    score_rendered(scene, i, rendered, renderer.background)
}

/// Score a render of view `i` (by the model or any other method, e.g. `render::ulr`) against its
/// photo, with the view's median footprint.
pub fn score_rendered(
    scene: &Scene,
    i: usize,
    rendered: Rendered,
    background: [f32; 3],
) -> Result<Evaluated> {
    let view = &scene.views[i];
    let gt = scene.load_image(i)?;
    let mask = scene.load_mask(i)?;
    let mut scored = score_view(
        &view.name,
        &rendered.image,
        &gt,
        &rendered.hit,
        mask.as_deref(),
        background,
    );
    // Median footprint of the hit pixels, normalised units → scene units (largest extent).
    let mut fp: Vec<f32> = rendered
        .footprint
        .iter()
        .zip(&rendered.hit)
        .filter(|(f, &h)| h && **f > 0.0)
        .map(|(f, _)| *f)
        .collect();
    if !fp.is_empty() {
        let mid = fp.len() / 2;
        let (_, m, _) = fp.select_nth_unstable_by(mid, f32::total_cmp);
        scored.score.footprint = Some(*m as f64 * scene.normalization.extent.max_element());
    }
    Ok(Evaluated { rendered, scored })
}

/// The relative output path of a view named `name` (its folders kept, so `a/0000.png` and
/// `b/0000.png` do not collide; `..`, root and prefix components dropped) with its extension
/// replaced by `ext` (`""` removes it).
pub fn output_name(name: &str, ext: &str) -> PathBuf {
    let p: PathBuf = Path::new(name)
        .components()
        .filter_map(|c| match c {
            std::path::Component::Normal(s) => Some(s),
            _ => None,
        })
        .collect();
    let p = if p.as_os_str().is_empty() {
        PathBuf::from("view")
    } else {
        p
    };
    p.with_extension(ext)
}

/// Write `img` as an 8-bit PNG at `dir/<output_name(name)>`, creating its folders.
pub fn write_view_png(dir: &Path, name: &str, img: &Image) -> Result<PathBuf> {
    let path = dir.join(output_name(name, "png"));
    if let Some(parent) = path.parent() {
        std::fs::create_dir_all(parent)
            .with_context(|| format!("{}: cannot create", parent.display()))?;
    }
    write_png8(&path, img)?;
    Ok(path)
}

/// Write an evaluated view's render into `render_dir` and its side-by-side (render | photo as it
/// is | error | ꟻLIP, the mesh's misses outlined: `render::comparison`) into `compare_dir`, each
/// under the view's own name.
pub fn write_evaluated(
    e: &Evaluated,
    name: &str,
    render_dir: Option<&Path>,
    compare_dir: Option<&Path>,
) -> Result<()> {
    if let Some(d) = render_dir {
        write_view_png(d, name, &e.rendered.image)?;
    }
    if let Some(d) = compare_dir {
        let cmp = comparison(
            &e.rendered.image,
            &e.scored.photo,
            &e.rendered.hit,
            &e.scored.flip_map,
        );
        write_view_png(d, name, &cmp)?;
    }
    Ok(())
}
