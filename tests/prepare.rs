//! `xscale prepare` as a user runs it: on the committed real COLMAP model (fixtures/prepare_skull:
//! 10 photos of a skull, CC BY 4.0), without COLMAP (the install hint and the commands), as a dry
//! run, through every stage with a stand-in `colmap` (a shell script that leaves the fixture's
//! model where COLMAP's mapper would), twice, and stopped by SIGTERM mid-stage.

use std::path::{Path, PathBuf};
use std::process::{Command, Output, Stdio};
use std::time::{Duration, Instant};

fn fixture() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("fixtures/prepare_skull")
}

fn tmp(name: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("xscale-test-prepare-{}-{name}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    d
}

fn xscale(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_xscale"))
        .args(args)
        // No real COLMAP: the tests name their stand-in explicitly.
        .env("PATH", "/nonexistent")
        .stdin(Stdio::null())
        .output()
        .unwrap()
}

fn text(o: &Output) -> String {
    format!(
        "{}{}",
        String::from_utf8_lossy(&o.stdout),
        String::from_utf8_lossy(&o.stderr)
    )
}

fn report(out: &Path) -> serde_json::Value {
    serde_json::from_str(&std::fs::read_to_string(out.join("prepare.json")).unwrap()).unwrap()
}

/// The real model meshes into a scene xscale loads, whose mesh covers the object in every photo;
/// the same command again only reports.
#[test]
fn real_colmap_model_to_a_scene() {
    let out = tmp("real");
    let o = xscale(&[
        "prepare",
        "--sparse",
        fixture().to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
    ]);
    assert!(o.status.success(), "{}", text(&o));
    let r = report(&out);
    assert_eq!(r["views"], 10);
    assert!(r["points"].as_u64().unwrap() > 500, "{r}");
    // COLMAP's keypoints reproject through xscale's cameras as COLMAP says they do.
    let (mean, colmap) = (
        r["reprojection"]["mean"].as_f64().unwrap(),
        r["colmap_mean_error"].as_f64().unwrap(),
    );
    assert!(
        mean < 1.5 && (mean - colmap).abs() < 0.5,
        "{mean} vs COLMAP's {colmap}"
    );
    // The skull fills about a fifth of each photo (black background): the mesh covers it.
    for v in r["per_view"].as_array().unwrap() {
        assert!(v["hit"].as_f64().unwrap() > 0.08, "{v}");
    }
    assert!(r["mean_hit"].as_f64().unwrap() > 0.15, "{r}");
    let scene = xscale::scene::Scene::load(&out, &Default::default()).unwrap();
    assert_eq!(scene.views.len(), 10);
    assert!(scene.mesh.triangles.len() > 300);
    // Again: nothing redone.
    let mesh_time = std::fs::metadata(out.join("mesh.ply"))
        .unwrap()
        .modified()
        .unwrap();
    let o = xscale(&[
        "prepare",
        "--sparse",
        fixture().to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
    ]);
    assert!(
        o.status.success() && text(&o).contains("already prepared"),
        "{}",
        text(&o)
    );
    assert_eq!(
        std::fs::metadata(out.join("mesh.ply"))
            .unwrap()
            .modified()
            .unwrap(),
        mesh_time
    );
    // Other photos into the same folder: refused, naming what changed.
    let other = tmp("other-photos");
    std::fs::create_dir_all(&other).unwrap();
    std::fs::copy(fixture().join("images/22.JPG"), other.join("22.JPG")).unwrap();
    let o = xscale(&[
        "prepare",
        "--photos",
        other.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
        "--dry-run",
    ]);
    assert_eq!(o.status.code(), Some(2), "{}", text(&o));
    assert!(
        text(&o).contains("prepared from other photos or settings"),
        "{}",
        text(&o)
    );
    let _ = std::fs::remove_dir_all(&out);
    let _ = std::fs::remove_dir_all(&other);
}

/// Without COLMAP: what to install, and the commands it would have run; nothing written.
#[test]
fn without_colmap_says_what_to_install() {
    let out = tmp("nocolmap");
    let photos = fixture().join("images");
    let o = xscale(&[
        "prepare",
        "--photos",
        photos.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
    ]);
    assert_eq!(o.status.code(), Some(2));
    let t = text(&o);
    assert!(
        t.contains("apt-get install colmap") && t.contains("--sparse"),
        "{t}"
    );
    for cmd in [
        "colmap feature_extractor",
        "colmap exhaustive_matcher",
        "colmap mapper",
    ] {
        assert!(
            String::from_utf8_lossy(&o.stdout).contains(cmd),
            "{cmd}: {t}"
        );
    }
    assert!(!out.join("mesh.ply").exists());
    // A dry run prints the same and succeeds; known poses give the triangulator and pairs.
    let o = xscale(&[
        "prepare",
        "--photos",
        photos.to_str().unwrap(),
        "--poses",
        fixture().to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
        "--dry-run",
    ]);
    assert!(o.status.success(), "{}", text(&o));
    let s = String::from_utf8_lossy(&o.stdout);
    assert!(
        s.contains("colmap point_triangulator")
            && s.contains("matches_importer")
            && s.contains("--clear_points 1"),
        "{s}"
    );
    assert!(!out.join(".prepare").exists());
}

/// A stand-in `colmap`: the database is a file, matching sleeps when `FAKE_COLMAP_SLOW` is
/// set, the mapper leaves the fixture's model in `output_path/0`.
fn fake_colmap(dir: &Path) -> PathBuf {
    let p = dir.join("colmap");
    let model = fixture().join("sparse/0");
    std::fs::write(
        &p,
        format!(
            "#!/bin/sh\nPATH=/usr/bin:/bin\ncmd=$1; shift\nout=''; db=''\nwhile [ $# -gt 0 ]; do case $1 in --output_path) out=$2;; --database_path) db=$2;; esac; shift; done\n\
             case $cmd in\n  help) echo 'COLMAP 0.0 (stand-in)';;\n  feature_extractor) echo 'Processed file [1/10]'; touch \"$db\";;\n  \
             exhaustive_matcher) [ -n \"$FAKE_COLMAP_SLOW\" ] && sleep 30; echo 'Matching block [1/1, 1/1]';;\n  \
             mapper) mkdir -p \"$out/0\" && cp {}/* \"$out/0/\";;\n  *) echo \"unexpected $cmd\" >&2; exit 1;;\nesac\n",
            model.display()
        ),
    )
    .unwrap();
    use std::os::unix::fs::PermissionsExt;
    std::fs::set_permissions(&p, std::fs::Permissions::from_mode(0o755)).unwrap();
    p
}

/// Every stage through the stand-in; SIGTERM during matching leaves no mesh and exits 3; the same
/// command then resumes from matching and finishes.
#[test]
fn stages_resume_after_sigterm() {
    let dir = tmp("stages");
    std::fs::create_dir_all(&dir).unwrap();
    let colmap = fake_colmap(&dir);
    let out = dir.join("scene");
    let photos = fixture().join("images");
    let args = [
        "prepare",
        "--photos",
        photos.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
        "--colmap",
        colmap.to_str().unwrap(),
    ];
    let child = Command::new(env!("CARGO_BIN_EXE_xscale"))
        .args(args)
        .env("FAKE_COLMAP_SLOW", "1")
        .stdin(Stdio::null())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    // Wait for matching to start.
    let t = Instant::now();
    let state = out.join(".prepare/state.json");
    while !std::fs::read_to_string(&state).is_ok_and(|s| s.contains("features")) {
        assert!(
            t.elapsed() < Duration::from_secs(60),
            "features never finished"
        );
        std::thread::sleep(Duration::from_millis(50));
    }
    std::thread::sleep(Duration::from_millis(300));
    let st = Command::new("kill")
        .args(["-TERM", &child.id().to_string()])
        .status()
        .unwrap();
    assert!(st.success());
    let o = child.wait_with_output().unwrap();
    assert_eq!(o.status.code(), Some(3), "{}", text(&o));
    assert!(
        t.elapsed() < Duration::from_secs(25),
        "the stand-in's sleep was not cut short"
    );
    assert!(!out.join("mesh.ply").exists() && !out.join("sparse").exists());
    // Resumed: features are not extracted again.
    let o = xscale(&args);
    assert!(o.status.success(), "{}", text(&o));
    let t = text(&o);
    assert!(
        t.contains("features: done before")
            && t.contains("[3/5] matches: colmap exhaustive_matcher"),
        "{t}"
    );
    assert!(out.join("mesh.ply").is_file() && out.join("sparse/0").is_dir());
    assert_eq!(report(&out)["views"], 10);
    xscale::scene::Scene::load(&out, &Default::default()).unwrap();
    let _ = std::fs::remove_dir_all(&dir);
}

/// Bad input: a typo in the photo folder, an --out that holds something else.
#[test]
fn clear_errors() {
    let o = xscale(&[
        "prepare",
        "--photos",
        "/nonexistent/photos",
        "--out",
        "/tmp/x",
    ]);
    assert_eq!(o.status.code(), Some(2));
    assert!(
        text(&o).contains("/nonexistent/photos: photo folder not found"),
        "{}",
        text(&o)
    );
    let busy = tmp("busy");
    std::fs::create_dir_all(&busy).unwrap();
    std::fs::write(busy.join("notes.txt"), "mine").unwrap();
    let o = xscale(&[
        "prepare",
        "--sparse",
        fixture().to_str().unwrap(),
        "--out",
        busy.to_str().unwrap(),
    ]);
    assert_eq!(o.status.code(), Some(2));
    assert!(
        text(&o).contains("was not made by `xscale prepare`"),
        "{}",
        text(&o)
    );
    assert_eq!(
        std::fs::read_to_string(busy.join("notes.txt")).unwrap(),
        "mine"
    );
    let _ = std::fs::remove_dir_all(&busy);
}

/// A model given as COLMAP's `WS/sparse/0` (as docs/prepare.md shows it) finds its photos in
/// `WS/images`; known poses in a transforms.json named by a relative path (with relative
/// `mask_path`s) load, though prepare reads them from a copy in another folder.
#[test]
fn model_folder_and_relative_poses() {
    let out = tmp("model-folder");
    let model = fixture().join("sparse").join("0");
    let o = xscale(&[
        "prepare",
        "--sparse",
        model.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
    ]);
    assert!(o.status.success(), "{}", text(&o));
    assert_eq!(report(&out)["views"], 10);
    let _ = std::fs::remove_dir_all(&out);

    // A transforms.json scene (the tiny synthetic one) with a mask per frame, named relatively.
    let work = tmp("relative-poses");
    let scene = work.join("scene");
    let o = xscale(&["synth", "--out", scene.to_str().unwrap()]);
    assert!(o.status.success(), "{}", text(&o));
    let poses = work.join("poses");
    std::fs::create_dir_all(poses.join("masks")).unwrap();
    let mut t: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(scene.join("transforms.json")).unwrap())
            .unwrap();
    for f in t["frames"].as_array_mut().unwrap() {
        let name = Path::new(f["file_path"].as_str().unwrap())
            .file_name()
            .unwrap()
            .to_string_lossy()
            .to_string();
        std::fs::copy(
            scene.join("images").join(&name),
            poses.join("masks").join(&name),
        )
        .unwrap();
        f["mask_path"] = format!("./masks/{name}").into();
    }
    std::fs::write(poses.join("transforms.json"), t.to_string()).unwrap();
    // A dry run reads the copy from the temporary folder; a run from OUT/.prepare (the stand-in
    // COLMAP then fails at the triangulator, which it does not stand in for).
    let colmap = fake_colmap(&work);
    for dry in [true, false] {
        let mut args = vec![
            "prepare",
            "--photos",
            "scene/images",
            "--poses",
            "poses",
            "--out",
            "out",
            "--matcher",
            "exhaustive",
            "--colmap",
            colmap.to_str().unwrap(),
        ];
        if dry {
            args.push("--dry-run");
        }
        let o = Command::new(env!("CARGO_BIN_EXE_xscale"))
            .args(&args)
            .current_dir(&work)
            .stdin(Stdio::null())
            .output()
            .unwrap();
        let t = text(&o);
        assert!(
            t.contains("point_triangulator") && !t.contains("not found"),
            "dry run {dry}: {t}"
        );
        if dry {
            assert!(o.status.success(), "{t}");
        } else {
            assert!(
                t.contains("[4/5] sparse: colmap point_triangulator")
                    && t.contains("unexpected point_triangulator"),
                "{t}"
            );
            assert!(work.join("out/.prepare/poses-transforms.json").is_file());
        }
    }
    let _ = std::fs::remove_dir_all(&work);
}
