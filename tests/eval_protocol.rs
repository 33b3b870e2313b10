//! The held-out protocol (`eval/protocol.rs`): honest full-image scores against scikit-image on a
//! committed case, the same figures end to end through `train` → render PNG, object masks
//! (a `masks/` folder and an alpha channel) limiting training and scoring, and outputs named
//! after views that live in folders.

use std::path::PathBuf;
use std::process::Command;
use xscale::eval::protocol::{mean_score, score_view, table};
use xscale::render::WHITE;
use xscale::scene::image::load_rgb;
use xscale::scene::{Image, LoadOptions, MaskSource, Scene};
use xscale::train::config::RunConfig;
use xscale::train::sampler::SampleMode;
use xscale::train::setup::prepare;

fn root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}

fn tmp(name: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("xscale-test-eval-{}-{name}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    d
}

fn xscale(args: &[&str]) -> std::process::Output {
    let out = Command::new(env!("CARGO_BIN_EXE_xscale"))
        .args(args)
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "xscale {args:?} failed: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    out
}

/// The masked fixture's mesh with the triangles within `r` (a fraction of the mesh's x extent)
/// of the middle removed, written to `out`.
fn write_holed_mesh(r: f64, out: &std::path::Path) {
    let scene = root().join("fixtures/masked");
    let (mut mesh, _) = xscale::scene::mesh::load_mesh(&scene.join("mesh.ply")).unwrap();
    let (lo, hi) = mesh.bbox();
    let c = (lo + hi) * 0.5;
    let r = r * (hi - lo).x;
    let v = mesh.vertices.clone();
    let before = mesh.triangles.len();
    mesh.triangles.retain(|t| {
        let m = (v[t[0] as usize] + v[t[1] as usize] + v[t[2] as usize]) / 3.0;
        (m.x - c.x).hypot(m.y - c.y) > r
    });
    assert!(mesh.triangles.len() < before);
    xscale::scene::mesh::write_ply(out, &mesh).unwrap();
}

/// The masked fixture without its masks folder (so every pixel counts), copied to `dir`.
fn copy_without_masks(dir: &std::path::Path) {
    let scene = root().join("fixtures/masked");
    std::fs::create_dir_all(dir.join("images")).unwrap();
    for f in ["transforms.json", "mesh.ply"] {
        std::fs::copy(scene.join(f), dir.join(f)).unwrap();
    }
    for e in std::fs::read_dir(scene.join("images")).unwrap() {
        let p = e.unwrap().path();
        std::fs::copy(&p, dir.join("images").join(p.file_name().unwrap())).unwrap();
    }
}

/// The committed case (`fixtures/scores/`): a render with a hole where the mesh misses, against
/// its untouched photo. xscale's full-image PSNR and SSIM equal scikit-image's (the numbers in
/// `expected.json` are scikit-image's, written by `reference/scores_case.py`).
#[test]
fn full_image_scores_match_scikit_image() {
    let dir = root().join("fixtures/scores");
    let expected: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(dir.join("expected.json")).unwrap()).unwrap();
    let render = load_rgb(&dir.join("render.png")).unwrap();
    let gt = load_rgb(&dir.join("gt.png")).unwrap();
    // Misses are the white pixels of the render (the background it was rendered with).
    let hit: Vec<bool> = render
        .data
        .chunks_exact(3)
        .map(|p| p != [1.0, 1.0, 1.0])
        .collect();
    let s = score_view("0000.png", &render, &gt, &hit, None, WHITE).score;
    let psnr = expected["psnr"].as_f64().unwrap();
    let ssim = expected["ssim"].as_f64().unwrap();
    assert!(
        (s.psnr - psnr).abs() <= 0.01,
        "PSNR {} vs scikit-image {psnr}",
        s.psnr
    );
    assert!(
        (s.ssim - ssim).abs() <= 1e-4,
        "SSIM {} vs scikit-image {ssim}",
        s.ssim
    );
    // ꟻLIP against NVIDIA's flip-evaluator (the same C++ behind nv-flip: this checks how xscale
    // calls it — 8-bit quantisation, 67 pixels per degree, channel order). Measured: < 1e-12 apart.
    let flip = expected["flip"].as_f64().unwrap();
    assert!(
        (s.flip - flip).abs() <= 1e-6,
        "FLIP {} vs flip-evaluator {flip}",
        s.flip
    );
    // The hole shows: the full-image score is far below the hit pixels' score, and below what
    // painting the photo white where the render missed would report.
    let painted = expected["psnr_gt_painted_white"].as_f64().unwrap();
    assert!(s.psnr < painted - 5.0, "{} vs painted {painted}", s.psnr);
    assert!(s.psnr < s.psnr_masked - 5.0, "{s:?}");
    assert!(s.flip > s.flip_masked, "{s:?}");
}

/// A mesh with a hole, trained and evaluated through the CLI: `eval.json`'s full-image PSNR is
/// the PSNR of the written render PNG against the untouched photo (≤ 0.01 dB: only the PNG's
/// 8-bit rounding differs), and renders keep the view names' folders (`render/images/…`).
#[test]
fn eval_json_full_psnr_is_the_render_against_the_photo() {
    // The tiny mesh with the triangles around the middle of the scene removed.
    let holed = tmp("holed.ply");
    write_holed_mesh(0.2, &holed);
    let run = tmp("run");
    let empty = tmp("nomasks");
    copy_without_masks(&empty);
    let (e, h, r_) = (
        empty.to_str().unwrap(),
        holed.to_str().unwrap(),
        run.to_str().unwrap(),
    );
    xscale(&[
        "train", "--scene", e, "--mesh", h, "--out", r_, "--preset", "tiny", "--steps", "60",
        "--quiet",
    ]);
    let json: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(run.join("eval.json")).unwrap()).unwrap();
    let views = json["views"].as_array().unwrap();
    assert!(!views.is_empty());
    let mut some_hole = false;
    for v in views {
        let name = v["view"].as_str().unwrap();
        assert!(name.starts_with("images/"), "{name}");
        let png = run.join("render").join(name);
        assert!(png.is_file(), "{} missing", png.display());
        assert!(run.join("eval").join(name).is_file());
        let render = load_rgb(&png).unwrap();
        let gt = load_rgb(&empty.join(name)).unwrap();
        let psnr = xscale::eval::metrics::psnr(&render.data, &gt.data);
        let got = v["psnr"].as_f64().unwrap();
        assert!(
            (got - psnr).abs() <= 0.01,
            "{name}: eval.json {got} vs PNG {psnr}"
        );
        // ꟻLIP in eval.json and as the side-by-side's fourth panel: render | photo | error |
        // ꟻLIP map of the written render against the untouched photo (to the PNGs' 8 bits). The
        // side-by-side shows what the full scores score: the photo as it is, the errors over
        // every pixel, and the region the mesh misses outlined (cyan) on every panel.
        let flip = v["flip"].as_f64().unwrap();
        assert!(flip > 0.0 && flip < 1.0, "{v}");
        let side = load_rgb(&run.join("eval").join(name)).unwrap();
        let (w, hh) = (render.width as usize, render.height as usize);
        assert_eq!((side.width as usize, side.height as usize), (4 * w, hh));
        let fmap = xscale::eval::metrics::flip_map(&gt.data, &render.data, w, hh);
        assert!(
            (xscale::eval::metrics::masked_mean(&fmap, None) - flip).abs() < 1e-6,
            "{name}: ꟻLIP {flip} in eval.json"
        );
        let want = xscale::render::flip_image(&fmap, w as u32, hh as u32);
        let heat = xscale::render::heat_map(&render, &gt);
        // Misses are the render's white (background) pixels.
        let hit: Vec<bool> = (render.data.chunks_exact(3))
            .map(|p| p != [1.0, 1.0, 1.0])
            .collect();
        let outline = xscale::render::miss_outline(&hit, w as u32, hh as u32, 2);
        let (mut outlined, mut miss_error) = (0, 0.0f32);
        for y in 0..hh {
            for x in 0..w {
                let p = y * w + x;
                // The heat map scales the error by 12 (0.25 saturates the 3-colour ramp): the
                // render PNG's 8-bit rounding moves it by up to 12/255.
                for (panel, img, tol) in [(1, &gt, 1.0), (2, &heat, 12.5), (3, &want, 1.0)] {
                    for c in 0..3 {
                        let a = side.data[(y * 4 * w + panel * w + x) * 3 + c];
                        let b = if outline[p] {
                            xscale::render::MISS_OUTLINE[c]
                        } else {
                            img.data[p * 3 + c]
                        };
                        assert!(
                            (a - b).abs() <= tol / 255.0 + 1e-6,
                            "{name} ({x},{y}) panel {panel}: {a} vs {b}"
                        );
                    }
                }
                outlined += outline[p] as usize;
                if !hit[p] && !outline[p] {
                    miss_error += side.data[(y * 4 * w + 2 * w + x) * 3];
                }
            }
        }
        if hit.contains(&false) {
            assert!(outlined > 0, "{name}: the misses are not outlined");
            // The photo is not white where the mesh misses: the heat map shows that error.
            assert!(
                miss_error > 0.0,
                "{name}: no error shown where the mesh misses"
            );
        }
        if v["hit_fraction"].as_f64().unwrap() < 0.99 {
            some_hole = true;
            assert!(got < v["psnr_masked"].as_f64().unwrap(), "{v}");
        }
    }
    assert!(some_hole, "the hole is seen by no held-out view");
    for d in [holed, run, empty] {
        let _ = std::fs::remove_dir_all(&d);
        let _ = std::fs::remove_file(&d);
    }
}

fn count_inside(scene: &Scene, i: usize) -> usize {
    scene
        .load_mask(i)
        .unwrap()
        .map_or(0, |m| m.iter().filter(|&&x| x).count())
}

/// `fixtures/masked`: every view finds its mask in `masks/`; training draws only pixels inside
/// the masks (same count streamed or cached); eval scores inside the mask and reports the mask
/// pixels the mesh misses. A photo's alpha channel works as a mask the same way.
#[test]
fn masks_limit_training_and_scoring() {
    let dir = root().join("fixtures/masked");
    let scene = Scene::load(&dir, &LoadOptions::default()).unwrap();
    assert!(scene.has_masks());
    assert!(scene
        .masks
        .iter()
        .all(|m| matches!(m, MaskSource::File(p) if p.starts_with(dir.join("masks")))));
    let train = scene.train();
    let inside: usize = train.iter().map(|&i| count_inside(&scene, i)).sum();
    let all: usize = train
        .iter()
        .map(|&i| (scene.views[i].camera.width * scene.views[i].camera.height) as usize)
        .sum();
    assert!(inside > 0 && inside < all / 2 * 2 && inside < all);
    let mut lens = Vec::new();
    for mode in [SampleMode::Stream, SampleMode::Cache] {
        let mut cfg = RunConfig::preset("tiny").unwrap();
        cfg.train.samples = mode;
        let p = prepare(&dir, &cfg, true, &mut |_| {}).unwrap();
        lens.push(p.samples.len());
    }
    // The tiny mesh covers every pixel, so the kept pixels are exactly the mask pixels.
    assert_eq!(lens, vec![inside, inside]);

    // Alpha as the mask: the same photos as RGBA with alpha = the mask.
    let alpha = tmp("alpha");
    std::fs::create_dir_all(alpha.join("images")).unwrap();
    for f in ["transforms.json", "mesh.ply"] {
        std::fs::copy(dir.join(f), alpha.join(f)).unwrap();
    }
    for (i, v) in scene.views.iter().enumerate() {
        let img = image::open(&v.image_path).unwrap().to_rgb8();
        let m = scene.load_mask(i).unwrap().unwrap();
        let mut rgba = image::RgbaImage::new(img.width(), img.height());
        for (k, (p, q)) in img.pixels().zip(rgba.pixels_mut()).enumerate() {
            *q = image::Rgba([p[0], p[1], p[2], if m[k] { 255 } else { 0 }]);
        }
        rgba.save(alpha.join(&v.name)).unwrap();
    }
    let sa = Scene::load(&alpha, &LoadOptions::default()).unwrap();
    assert!(sa.masks.iter().all(|m| *m == MaskSource::Alpha));
    for i in 0..sa.views.len() {
        assert_eq!(sa.load_mask(i).unwrap(), scene.load_mask(i).unwrap());
    }
    // Photos transparent everywhere: the setup says their masks are empty (it blamed the mesh).
    for v in &sa.views {
        let mut rgba = image::open(&v.image_path).unwrap().to_rgba8();
        rgba.pixels_mut().for_each(|p| p[3] = 0);
        rgba.save(&v.image_path).unwrap();
    }
    let mut log = Vec::new();
    let cfg = RunConfig::preset("tiny").unwrap();
    let e = format!(
        "{:#}",
        prepare(&alpha, &cfg, true, &mut |m| log.push(m))
            .err()
            .expect("empty masks must be refused")
    );
    assert!(
        e.contains("no training pixel is inside its view's object mask"),
        "{e}"
    );
    let n = sa.views.len();
    assert!(
        log.iter()
            .any(|m| m.contains(&format!("object masks: {n} of {n} views"))),
        "{log:?}"
    );
    assert!(
        log.iter()
            .any(|m| m.contains("has an object mask that excludes every pixel")),
        "{log:?}"
    );

    // A masks folder missing one view's mask is an error naming the view.
    let partial = tmp("partial");
    std::fs::create_dir_all(partial.join("masks")).unwrap();
    std::fs::create_dir_all(partial.join("images")).unwrap();
    for f in ["transforms.json", "mesh.ply"] {
        std::fs::copy(dir.join(f), partial.join(f)).unwrap();
    }
    for v in &scene.views {
        std::fs::copy(&v.image_path, partial.join(&v.name)).unwrap();
    }
    for k in 1..8 {
        let f = format!("{k:04}.png");
        std::fs::copy(dir.join("masks").join(&f), partial.join("masks").join(&f)).unwrap();
    }
    let e = format!(
        "{:#}",
        Scene::load(&partial, &LoadOptions::default()).unwrap_err()
    );
    assert!(e.contains("images/0000.png") && e.contains("masks"), "{e}");
    let _ = std::fs::remove_dir_all(&alpha);
    let _ = std::fs::remove_dir_all(&partial);
}

/// Eval through the CLI on the masked fixture: every score has `mask_miss`, full-image scores
/// are computed inside the mask only.
#[test]
fn eval_reports_mask_coverage() {
    let dir = root().join("fixtures/masked");
    let run = tmp("maskrun");
    let (d, r) = (dir.to_str().unwrap(), run.to_str().unwrap());
    xscale(&[
        "train", "--scene", d, "--out", r, "--preset", "tiny", "--steps", "40", "--quiet",
    ]);
    let json: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(run.join("eval.json")).unwrap()).unwrap();
    let views = json["views"].as_array().unwrap();
    assert!(!views.is_empty());
    for v in views {
        assert_eq!(
            v["mask_miss"].as_f64(),
            Some(0.0),
            "the tiny mesh covers every mask pixel: {v}"
        );
        // Inside the mask every pixel hits: full and masked PSNR agree.
        let (f, m) = (
            v["psnr"].as_f64().unwrap(),
            v["psnr_masked"].as_f64().unwrap(),
        );
        assert!((f - m).abs() < 1e-9, "{v}");
    }
    assert!(json["mean"]["mask_miss"].as_f64().is_some());
    let _ = std::fs::remove_dir_all(&run);
}

/// Scores grouped by scale: factor-2 bins of the views' median footprints, and a near/far split
/// at the geometric mean of the finest and coarsest; a mean over all views would hide the
/// close-ups' failure.
#[test]
fn scores_are_grouped_by_footprint() {
    use xscale::eval::protocol::{mean_score, scale_summary, scale_table, ViewScore};
    let v = |name: &str, fp: f64, psnr: f64| ViewScore {
        view: name.into(),
        psnr,
        ssim: 0.9,
        flip: 0.1,
        psnr_masked: psnr,
        ssim_masked: 0.9,
        flip_masked: 0.1,
        hit_fraction: 1.0,
        mask_miss: None,
        footprint: Some(fp),
    };
    let scores = vec![
        v("far1", 0.70, 36.0),
        v("close1", 0.024, 27.0),
        v("far2", 0.60, 36.0),
        v("close2", 0.021, 28.0),
    ];
    let s = scale_summary(&scores);
    assert_eq!(s.bins.len(), 2);
    assert_eq!((s.bins[0].lo, s.bins[0].hi), (2f64.powi(-6), 2f64.powi(-5)));
    assert_eq!(s.bins[0].views, vec!["close1", "close2"]);
    assert_eq!(s.bins[0].mean.psnr_masked, 27.5);
    assert_eq!(s.bins[1].views, vec!["far1", "far2"]);
    let (split, near, far) = s.near_far.expect("scales 28x apart");
    assert!((split - (0.021f64 * 0.70).sqrt()).abs() < 1e-12);
    assert_eq!((near.mean.psnr_masked, far.mean.psnr_masked), (27.5, 36.0));
    assert_eq!(mean_score(&scores).psnr_masked, 31.75);
    assert!(scale_table(&scores).contains("near"));
    // One scale only: no split, no table.
    let one = vec![v("a", 0.5, 30.0), v("b", 0.7, 31.0)];
    assert!(scale_summary(&one).near_far.is_none());
    assert!(scale_table(&one).is_empty());
}

/// Silhouette coverage counted: the masked fixture evaluated on its mesh with a hole cut in the
/// middle. Each held-out view's `mask_miss` is the mask pixels whose rays miss the mesh (read
/// from `render --mask`) over the mask pixels, and the hole shows in it.
#[test]
fn mask_miss_is_the_fraction_of_mask_pixels_the_mesh_misses() {
    let dir = root().join("fixtures/masked");
    let work = tmp("maskmiss");
    std::fs::create_dir_all(&work).unwrap();
    let holed_path = work.join("holed.ply");
    write_holed_mesh(0.1, &holed_path);
    let (d, run, h) = (
        dir.to_str().unwrap(),
        work.join("run"),
        holed_path.to_str().unwrap(),
    );
    let r = run.to_str().unwrap();
    xscale(&[
        "train",
        "--scene",
        d,
        "--out",
        r,
        "--preset",
        "tiny",
        "--steps",
        "10",
        "--no-eval",
        "-q",
    ]);
    let json = work.join("eval.json");
    let frames = work.join("frames");
    xscale(&[
        "eval",
        "--run",
        r,
        "--mesh",
        h,
        "--json",
        json.to_str().unwrap(),
    ]);
    xscale(&[
        "render",
        "--run",
        r,
        "--mesh",
        h,
        "--mask",
        "--out",
        frames.to_str().unwrap(),
    ]);
    let scene = Scene::load(&dir, &LoadOptions::default()).unwrap();
    let json: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&json).unwrap()).unwrap();
    let views = json["views"].as_array().unwrap();
    assert_eq!(views.len(), scene.test.len());
    let mut largest = 0.0f64;
    for (v, &i) in views.iter().zip(&scene.test) {
        assert_eq!(v["view"].as_str(), Some(scene.views[i].name.as_str()));
        let mask = scene.load_mask(i).unwrap().unwrap();
        let stem = scene.views[i].name.trim_end_matches(".png");
        let hit = image::open(frames.join(format!("{stem}_mask.png")))
            .unwrap()
            .to_luma8();
        let inside = mask.iter().filter(|&&m| m).count();
        let missed = mask
            .iter()
            .zip(hit.pixels())
            .filter(|&(&m, p)| m && p[0] < 128)
            .count();
        let want = missed as f64 / inside as f64;
        let got = v["mask_miss"].as_f64().unwrap();
        assert!((got - want).abs() < 1e-12, "{}: {got} vs {want}", v["view"]);
        largest = largest.max(got);
    }
    // Measured: 0.197 and 0.055 of the two views' mask pixels fall in the hole.
    assert!(largest > 0.1, "the hole does not show: mask_miss {largest}");
    let _ = std::fs::remove_dir_all(&work);
}

/// The background colour (`scene.toml` `background`, `--background` on eval and render): misses
/// are painted with it in the renders, and the full-image scores compare that colour with the
/// photo. A scene saying black, on a mesh with a hole: renders are black exactly where the rays
/// miss, `eval.json`'s full PSNR is the written render's against the photo, `--background white`
/// overrides the scene and scores differently; a bad colour is a usage error.
#[test]
fn the_background_colour_paints_misses_and_counts_in_full_scores() {
    let work = tmp("background");
    let scene = work.join("scene");
    copy_without_masks(&scene);
    std::fs::write(scene.join("scene.toml"), "background = [0.0, 0.0, 0.0]\n").unwrap();
    let holed = work.join("holed.ply");
    write_holed_mesh(0.2, &holed);
    let (s, h, run) = (
        scene.to_str().unwrap(),
        holed.to_str().unwrap(),
        work.join("run"),
    );
    let r = run.to_str().unwrap();
    xscale(&[
        "train",
        "--scene",
        s,
        "--mesh",
        h,
        "--out",
        r,
        "--preset",
        "tiny",
        "--steps",
        "30",
        "--no-eval",
        "-q",
    ]);
    let psnrs = |json: &std::path::Path| -> Vec<f64> {
        let v: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(json).unwrap()).unwrap();
        v["views"]
            .as_array()
            .unwrap()
            .iter()
            .map(|v| v["psnr"].as_f64().unwrap())
            .collect()
    };
    let (black_json, white_json) = (work.join("black.json"), work.join("white.json"));
    xscale(&["eval", "--run", r, "--json", black_json.to_str().unwrap()]);
    xscale(&[
        "eval",
        "--run",
        r,
        "--json",
        white_json.to_str().unwrap(),
        "--background",
        "white",
    ]);
    let frames = work.join("frames");
    let f = frames.to_str().unwrap();
    xscale(&["render", "--run", r, "--out", f, "--mask"]);
    let loaded = Scene::load(&scene, &LoadOptions::default()).unwrap();
    assert_eq!(loaded.background, [0.0; 3]);
    let (black, white) = (psnrs(&black_json), psnrs(&white_json));
    let mut misses = 0;
    for (k, &i) in loaded.test.iter().enumerate() {
        let name = &loaded.views[i].name;
        let render = load_rgb(&frames.join(name)).unwrap();
        let hit = image::open(frames.join(name.replace(".png", "_mask.png")))
            .unwrap()
            .to_luma8();
        for (p, m) in render.data.chunks_exact(3).zip(hit.pixels()) {
            if m[0] < 128 {
                misses += 1;
                assert_eq!(p, [0.0; 3], "{name}: a miss is not black");
            }
        }
        let photo = load_rgb(&loaded.views[i].image_path).unwrap();
        let psnr = xscale::eval::metrics::psnr(&render.data, &photo.data);
        assert!(
            (black[k] - psnr).abs() <= 0.01,
            "{name}: eval.json {} vs the black render {psnr}",
            black[k]
        );
    }
    assert!(misses > 0, "the hole is seen by no held-out view");
    assert!(
        black.iter().zip(&white).any(|(b, w)| (b - w).abs() > 0.1),
        "--background white scored as the scene's black: {black:?} {white:?}"
    );
    for bad in ["2,0,0", "red", "1,1"] {
        let o = Command::new(env!("CARGO_BIN_EXE_xscale"))
            .args(["eval", "--run", r, "--background", bad])
            .output()
            .unwrap();
        let err = String::from_utf8_lossy(&o.stderr);
        assert_eq!(o.status.code(), Some(64), "--background {bad}: {err}");
        assert!(
            err.contains("--background") && err.contains("R,G,B"),
            "{err}"
        );
    }
    let _ = std::fs::remove_dir_all(&work);
}

/// A `w × h` image of a smooth pattern (`k` shifts it), values in (0, 1).
fn pattern(w: u32, h: u32, k: f32) -> Image {
    let data = (0..w * h * 3)
        .map(|i| 0.5 + 0.4 * ((i as f32) * 0.37 + k).sin())
        .collect();
    Image {
        width: w,
        height: h,
        data,
    }
}

/// `pred` scored against `gt` with every ray hitting (`hit`) or missing, no object mask.
fn scored(name: &str, pred: &Image, gt: &Image, hit: bool) -> xscale::eval::protocol::ViewScore {
    let n = (gt.width * gt.height) as usize;
    score_view(name, pred, gt, &vec![hit; n], None, WHITE).score
}

/// Views the mesh misses entirely have no masked score: they used to score PSNR ∞ / SSIM 1 and
/// enter the means. Now their masked scores are n/a, the means are those of the other views, and
/// the table says which views were left out.
#[test]
fn views_the_mesh_misses_are_left_out_of_the_masked_means_with_a_word() {
    let (w, h) = (24, 20);
    let gt = pattern(w, h, 0.0);
    let pred = pattern(w, h, 0.3);
    let seen = scored("seen", &pred, &gt, true);
    // Every ray misses: the render is all background.
    let blank = Image {
        width: w,
        height: h,
        data: vec![1.0; (w * h * 3) as usize],
    };
    let missed = scored("missed", &blank, &gt, false);
    assert!(
        missed.psnr_masked.is_nan() && missed.ssim_masked.is_nan(),
        "{missed:?}"
    );
    // The full-image scores count the misses as the error they are.
    assert!(missed.psnr.is_finite() && missed.ssim < 1.0, "{missed:?}");
    let m = mean_score(&[seen.clone(), missed.clone()]);
    assert_eq!(m.psnr_masked, seen.psnr_masked);
    assert_eq!(m.ssim_masked, seen.ssim_masked);
    assert_eq!(m.psnr, (seen.psnr + missed.psnr) / 2.0);
    let t = table(&[seen, missed]);
    assert!(
        t.contains("no pixel of missed sees the mesh: left out of the masked means"),
        "{t}"
    );
}

/// SSIM needs an 11×11 window: a smaller image has none, so its SSIM is n/a (not a number that
/// means something), it stays out of the mean, and the table says why (it used to print NaN).
#[test]
fn ssim_of_images_smaller_than_its_window_is_na_and_says_why() {
    let (w, h) = (10, 40);
    let gt = pattern(w, h, 0.0);
    let pred = pattern(w, h, 0.3);
    let s = scored("narrow", &pred, &gt, true);
    assert!(
        s.psnr.is_finite() && s.ssim.is_nan() && s.ssim_masked.is_nan(),
        "{s:?}"
    );
    let big = scored("big", &pattern(12, 12, 0.3), &pattern(12, 12, 0.0), true);
    assert!(big.ssim.is_finite());
    assert_eq!(mean_score(&[s.clone(), big.clone()]).ssim, big.ssim);
    let t = table(&[s, big]);
    assert!(t.contains("n/a"), "{t}");
    assert!(
        t.contains("SSIM of narrow is n/a") && t.contains("11×11"),
        "the table does not say why: {t}"
    );
}
