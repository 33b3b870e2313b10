//! Every COLMAP camera model xscale reads, against COLMAP itself: `fixtures/camera_models/
//! cases.json` holds pycolmap's projections of camera-frame points and its lifted rays of
//! pixels (written by `make_cases.py`). Each model is read from a `cameras.txt` line, as COLMAP
//! writes it; `Camera::project` must land on COLMAP's pixel and `Camera::dir_camera` on COLMAP's
//! ray. Models xscale does not read are an error naming the model and the supported ones.

use glam::{DMat3, DVec3};
use std::path::PathBuf;
use xscale::scene::colmap;

fn tmp(name: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("xscale-test-cams-{}-{name}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).unwrap();
    d
}

/// A one-camera, one-image COLMAP text model (identity pose) in a fresh directory.
fn model_dir(name: &str, line: &str) -> PathBuf {
    let d = tmp(name);
    std::fs::write(d.join("cameras.txt"), format!("{line}\n")).unwrap();
    std::fs::write(d.join("images.txt"), "1 1 0 0 0 0 0 0 1 a.png\n\n").unwrap();
    d
}

#[test]
fn every_model_matches_colmap() {
    let root = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("fixtures/camera_models");
    let data: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(root.join("cases.json")).unwrap()).unwrap();
    let mut failures = Vec::new();
    let mut models = 0;
    for c in data["cases"].as_array().unwrap() {
        let name = c["model"].as_str().unwrap();
        let params: Vec<String> = c["params"]
            .as_array()
            .unwrap()
            .iter()
            .map(|p| format!("{:?}", p.as_f64().unwrap()))
            .collect();
        let line = format!(
            "1 {name} {} {} {}",
            c["width"],
            c["height"],
            params.join(" ")
        );
        let dir = model_dir(name, &line);
        let views = match colmap::load(&dir, &dir) {
            Ok(v) => v,
            Err(e) => {
                failures.push(format!("{name}: {e:#}"));
                continue;
            }
        };
        let _ = std::fs::remove_dir_all(&dir);
        let cam = &views[0].camera;
        assert_eq!(cam.rotation, DMat3::IDENTITY);
        models += 1;
        let pts = c["points"].as_array().unwrap();
        let proj = c["projected"].as_array().unwrap();
        for (p, want) in pts.iter().zip(proj) {
            let p: Vec<f64> = p
                .as_array()
                .unwrap()
                .iter()
                .map(|x| x.as_f64().unwrap())
                .collect();
            let w: Vec<f64> = want
                .as_array()
                .unwrap()
                .iter()
                .map(|x| x.as_f64().unwrap())
                .collect();
            match cam.project(DVec3::new(p[0], p[1], p[2])) {
                Some((x, y)) if (x - w[0]).abs() < 1e-8 && (y - w[1]).abs() < 1e-8 => {}
                got => failures.push(format!("{name}: project {p:?} = {got:?}, COLMAP {w:?}")),
            }
        }
        let px = c["pixels"].as_array().unwrap();
        let norm = c["normalized"].as_array().unwrap();
        for (q, want) in px.iter().zip(norm) {
            let q: Vec<f64> = q
                .as_array()
                .unwrap()
                .iter()
                .map(|x| x.as_f64().unwrap())
                .collect();
            let w: Vec<f64> = want
                .as_array()
                .unwrap()
                .iter()
                .map(|x| x.as_f64().unwrap())
                .collect();
            let d = cam.dir_camera(q[0], q[1]);
            let (x, y) = (d.x / d.z, d.y / d.z);
            // COLMAP's own inversion stops at a step of 1e-5 (squared 1e-10): compare at 1e-7
            // relative to the ray's size, far below a pixel (the focal lengths are ~300–500).
            let tol = 1e-7 * (1.0 + w[0].abs().max(w[1].abs()));
            if !((x - w[0]).abs() < tol && (y - w[1]).abs() < tol) {
                failures.push(format!(
                    "{name}: ray of pixel {q:?} = ({x}, {y}), COLMAP {w:?}"
                ));
            }
        }
    }
    assert!(
        failures.is_empty(),
        "{} mismatches:\n{}",
        failures.len(),
        failures.join("\n")
    );
    assert_eq!(models, 16);
}

/// A fisheye ray more than 90° off the optical axis points backwards (z < 0) at the right angle.
#[test]
fn fisheye_rays_beyond_ninety_degrees() {
    let dir = model_dir("wide", "1 OPENCV_FISHEYE 640 480 150 150 320 240 0 0 0 0");
    let cam = colmap::load(&dir, &dir).unwrap().remove(0).camera;
    let _ = std::fs::remove_dir_all(&dir);
    // Equidistant: θ = r / f. A pixel 300 px right of the centre is θ = 2 rad ≈ 115°.
    let d = cam.dir_camera(320.0 + 300.0, 240.0).normalize();
    assert!((d.z - 2.0f64.cos()).abs() < 1e-12 && d.z < 0.0, "{d}");
    assert!((d.x - 2.0f64.sin()).abs() < 1e-12, "{d}");
}

/// Models xscale cannot represent are an error that names the model and lists those it reads.
#[test]
fn unsupported_models_are_named() {
    for (name, params) in [
        ("EUCM", "300 300 320 240 0.5 1.0"),
        ("EQUIRECTANGULAR", "640 480"),
    ] {
        let dir = model_dir(name, &format!("1 {name} 640 480 {params}"));
        let e = format!("{:#}", colmap::load(&dir, &dir).unwrap_err());
        let _ = std::fs::remove_dir_all(&dir);
        assert!(
            e.contains(name) && e.contains("supported") && e.contains("OPENCV_FISHEYE"),
            "{e}"
        );
    }
}
