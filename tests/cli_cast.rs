//! `xscale cast` end to end on the COLMAP fixture scene (a cube seen by three cameras).

use std::process::Command;

fn xscale(args: &[&str]) -> (i32, String, String) {
    let out = Command::new(env!("CARGO_BIN_EXE_xscale"))
        .args(args)
        .output()
        .unwrap();
    (
        out.status.code().unwrap_or(-1),
        String::from_utf8_lossy(&out.stdout).into_owned(),
        String::from_utf8_lossy(&out.stderr).into_owned(),
    )
}

fn field(stdout: &str, name: &str) -> String {
    stdout
        .lines()
        .find(|l| l.starts_with(name))
        .unwrap_or_else(|| panic!("no '{name}' in:\n{stdout}"))[name.len()..]
        .trim()
        .to_string()
}

#[test]
fn cast_reports_the_cache() {
    let scene = concat!(env!("CARGO_MANIFEST_DIR"), "/fixtures/formats/colmap");
    let (code, out, err) = xscale(&["cast", "--scene", scene, "--views", "all", "--gamma", "2"]);
    assert_eq!(code, 0, "{err}");
    assert_eq!(field(&out, "views cast:"), "3");
    assert_eq!(field(&out, "views kept:"), "3");
    // 3 views of 8×6 pixels, 4 rays each.
    assert_eq!(field(&out, "rays cast:"), "576");
    let kept: usize = field(&out, "pixels kept:")
        .split(' ')
        .next()
        .unwrap()
        .parse()
        .unwrap();
    assert!(kept > 0 && kept < 144, "{out}");
    assert!(err.contains("see the mesh"), "{err}");
    // The photos are read, so they are checked against the mesh (`raycast/consistency.rs`).
    assert!(err.contains("photo check: "), "{err}");
    // γ = 1 casts a quarter of the rays; the training split drops the held-out view 0.
    let (code, out, err) = xscale(&["cast", "--scene", scene, "--gamma", "1", "--no-images"]);
    assert_eq!(code, 0);
    assert!(!err.contains("photo check"), "no photos read: {err}");
    assert_eq!(field(&out, "views cast:"), "2");
    assert_eq!(field(&out, "rays cast:"), "96");
}

#[test]
fn cast_rejects_bad_arguments() {
    let scene = concat!(env!("CARGO_MANIFEST_DIR"), "/fixtures/formats/colmap");
    let (code, _, err) = xscale(&["cast", "--scene", scene, "--gamma", "7"]);
    assert_eq!(code, 64, "a value --gamma does not take: a usage error");
    assert!(
        err.contains("'7' for '--gamma") && err.contains("1 to 4"),
        "{err}"
    );
    let (code, _, err) = xscale(&["cast", "--scene", "/nonexistent/scene"]);
    assert_eq!(code, 2);
    assert!(err.contains("/nonexistent/scene"), "{err}");
}

/// A `--format` the flag does not take is a usage error (64) naming the flag, like every other
/// flag value (it was a load error, exit 2).
#[test]
fn an_unknown_format_is_a_usage_error() {
    let scene = concat!(env!("CARGO_MANIFEST_DIR"), "/fixtures/formats/colmap");
    let (code, _, err) = xscale(&["cast", "--scene", scene, "--format", "foo"]);
    assert_eq!(code, 64, "{err}");
    assert!(
        err.contains("'--format <FORMAT>'") && err.contains("unknown camera format 'foo'"),
        "{err}"
    );
    let (code, _, err) = xscale(&["cast", "--scene", scene, "--format", "colmap"]);
    assert_eq!(code, 0, "{err}");
}

/// `--no-images` reads no photo's pixels but still checks every photo's size against its camera
/// from the header, as without it (it cast at the camera's size and reported success).
#[test]
fn no_images_still_checks_the_image_sizes() {
    let fixture = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("fixtures/formats/colmap");
    let scene = std::path::Path::new(env!("CARGO_TARGET_TMPDIR")).join("cli_cast_size");
    let _ = std::fs::remove_dir_all(&scene);
    copy_dir(&fixture, &scene);
    // The camera of c.png says 8x6.
    let wrong = xscale::scene::Image {
        width: 9,
        height: 6,
        data: vec![0.0; 3 * 9 * 6],
    };
    xscale::scene::image::write_png8(&scene.join("images/c.png"), &wrong).unwrap();
    let s = scene.to_str().unwrap();
    for extra in [&[][..], &["--no-images"]] {
        let args = [&["cast", "--scene", s, "--views", "all"][..], extra].concat();
        let (code, _, err) = xscale(&args);
        assert_eq!(code, 2, "{extra:?}: {err}");
        assert!(
            err.contains("c.png: image is 9x6 but the camera of view 'c.png' says 8x6"),
            "{extra:?}: {err}"
        );
    }
    let _ = std::fs::remove_dir_all(&scene);
}

fn copy_dir(from: &std::path::Path, to: &std::path::Path) {
    std::fs::create_dir_all(to).unwrap();
    for e in std::fs::read_dir(from).unwrap() {
        let e = e.unwrap();
        let t = to.join(e.file_name());
        if e.path().is_dir() {
            copy_dir(&e.path(), &t);
        } else {
            std::fs::copy(e.path(), t).unwrap();
        }
    }
}
