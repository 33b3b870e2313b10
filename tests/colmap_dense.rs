//! Real dataset layouts: a COLMAP dense workspace as `colmap image_undistorter` +
//! `colmap poisson_mesher` leave it (`fixtures/colmap_dense`, made by pycolmap), and photos with
//! an EXIF orientation tag (`fixtures/exif`).

use std::path::{Path, PathBuf};
use xscale::scene::image::{load_rgb, load_rgb_oriented};
use xscale::scene::{Distortion, LoadOptions, Scene};
use xscale::train::config::RunConfig;

fn fixture(p: &str) -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("fixtures")
        .join(p)
}

fn tmp(name: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("xscale-test-dense-{}-{name}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).unwrap();
    d
}

fn copy_dir(from: &Path, to: &Path) {
    std::fs::create_dir_all(to).unwrap();
    for e in std::fs::read_dir(from).unwrap() {
        let p = e.unwrap().path();
        let q = to.join(p.file_name().unwrap());
        if p.is_dir() {
            copy_dir(&p, &q);
        } else {
            std::fs::copy(&p, &q).unwrap();
        }
    }
}

/// Pointed at the workspace root, at `dense/` or at `dense/0/`: the undistorted model (PINHOLE,
/// not the root's distorted OPENCV one), its images and `meshed-poisson.ply` — the same cameras
/// as the `tiny` fixture's own COLMAP model.
#[test]
fn dense_workspace_loads_from_any_level() {
    let root = fixture("colmap_dense");
    let tiny = Scene::load(&fixture("tiny"), &LoadOptions::default()).unwrap();
    for dir in [root.clone(), root.join("dense"), root.join("dense/0")] {
        let (s, rep) = Scene::load_report(&dir, &LoadOptions::default()).unwrap();
        assert_eq!(rep.format.name(), "colmap", "{}", dir.display());
        assert!(
            rep.mesh_path.ends_with("dense/0/meshed-poisson.ply"),
            "{}",
            rep.mesh_path.display()
        );
        assert_eq!(s.views.len(), tiny.views.len());
        for (a, b) in s.views.iter().zip(&tiny.views) {
            assert_eq!(a.name, b.name);
            assert_eq!(a.camera.distortion, Distortion::None, "{}", a.name);
            assert!(a.camera.max_abs_diff(&b.camera) < 1e-9, "{}", a.name);
            assert!(a.image_path.starts_with(root.join("dense/0/images")));
        }
    }
    // And it trains (setup casts every training view).
    let cfg = RunConfig::preset("tiny").unwrap();
    let p = xscale::train::setup::prepare(&root, &cfg, true, &mut |_| {}).unwrap();
    assert!(!p.samples.is_empty());
}

/// Poisson is preferred to Delaunay; Delaunay alone is found.
#[test]
fn colmap_meshes_are_found() {
    let d = tmp("meshes");
    copy_dir(&fixture("colmap_dense/dense/0"), &d);
    std::fs::rename(d.join("meshed-poisson.ply"), d.join("meshed-delaunay.ply")).unwrap();
    let (_, rep) = Scene::load_report(&d, &LoadOptions::default()).unwrap();
    assert!(rep.mesh_path.ends_with("meshed-delaunay.ply"));
    std::fs::copy(d.join("meshed-delaunay.ply"), d.join("meshed-poisson.ply")).unwrap();
    let (_, rep) = Scene::load_report(&d, &LoadOptions::default()).unwrap();
    assert!(rep.mesh_path.ends_with("meshed-poisson.ply"));
    let _ = std::fs::remove_dir_all(&d);
}

/// A photo stored turned with EXIF orientation 6 is turned upright when its camera expects the
/// upright size (PNG exactly, JPEG up to its compression), and used as stored when the camera
/// expects the stored size (as COLMAP, which ignores the tag); a size neither explains is an
/// error that says the tag does not explain it.
#[test]
fn exif_orientation_is_applied_when_the_camera_needs_it() {
    let dir = fixture("exif");
    let up = load_rgb(&dir.join("upright.png")).unwrap();
    let png = load_rgb_oriented(&dir.join("turned.png"), true).unwrap();
    assert_eq!((png.width, png.height), (64, 48));
    assert_eq!(
        png.data, up.data,
        "the turned PNG comes back upright exactly"
    );
    let jpg = load_rgb_oriented(&dir.join("turned.jpg"), true).unwrap();
    assert_eq!((jpg.width, jpg.height), (64, 48));
    let err = jpg
        .data
        .iter()
        .zip(&up.data)
        .map(|(a, b)| (a - b).abs())
        .fold(0.0f32, f32::max);
    assert!(err < 0.1, "JPEG differs by {err}");
    // Stored as is without the flag.
    let raw = load_rgb(&dir.join("turned.png")).unwrap();
    assert_eq!((raw.width, raw.height), (48, 64));

    // Through a scene: a transforms.json whose camera is 64×48 on the turned photos.
    let s = tmp("exif");
    for f in ["turned.png", "turned.jpg", "upright.png"] {
        std::fs::copy(dir.join(f), s.join(f)).unwrap();
    }
    std::fs::copy(fixture("tiny/mesh.ply"), s.join("mesh.ply")).unwrap();
    let tf = std::fs::read_to_string(fixture("tiny/transforms.json")).unwrap();
    let mut j: serde_json::Value = serde_json::from_str(&tf).unwrap();
    let frames = j["frames"].as_array_mut().unwrap();
    frames.truncate(3);
    for (f, name) in frames
        .iter_mut()
        .zip(["turned.png", "turned.jpg", "upright.png"])
    {
        f["file_path"] = serde_json::json!(name);
    }
    std::fs::write(s.join("transforms.json"), j.to_string()).unwrap();
    let scene = Scene::load(&s, &LoadOptions::default()).unwrap();
    let img = scene.load_image(0).unwrap();
    assert_eq!(img.data, up.data);
    assert_eq!(scene.load_image(2).unwrap().data, up.data);

    // A camera size that neither the stored nor the turned photo has.
    j["w"] = serde_json::json!(60);
    j["cx"] = serde_json::json!(30.0);
    std::fs::write(s.join("transforms.json"), j.to_string()).unwrap();
    let e = format!(
        "{:#}",
        Scene::load(&s, &LoadOptions::default()).unwrap_err()
    );
    assert!(
        e.contains("EXIF orientation") && e.contains("turned.png"),
        "{e}"
    );
    let _ = std::fs::remove_dir_all(&s);
}

/// A folder whose scene sits one level down in dense/0/ in a layout the root search does not
/// take (here the model one folder deeper, `dense/0/sparse/0/`): the error names the folder to
/// give instead, and that folder loads.
#[test]
fn a_scene_one_level_down_is_named_in_the_error() {
    let d = tmp("nested");
    let inner = d.join("dense/0");
    copy_dir(&fixture("tiny/images"), &inner.join("images"));
    copy_dir(&fixture("tiny/sparse"), &inner.join("sparse"));
    std::fs::copy(fixture("tiny/mesh.ply"), inner.join("meshed-poisson.ply")).unwrap();
    let err = format!(
        "{:#}",
        Scene::load(&d, &LoadOptions::default()).unwrap_err()
    );
    assert!(
        err.contains("no cameras found") && err.contains(&format!("--scene {}", inner.display())),
        "{err}"
    );
    assert!(Scene::load(&inner, &LoadOptions::default()).is_ok());
    // The mesh file given for the folder.
    let e = format!(
        "{:#}",
        Scene::load(&inner.join("meshed-poisson.ply"), &LoadOptions::default()).unwrap_err()
    );
    assert!(e.contains("is a file") && e.contains("folder"), "{e}");
    let _ = std::fs::remove_dir_all(&d);
}
