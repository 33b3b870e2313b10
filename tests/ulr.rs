//! The ULR baseline (`src/render/ulr.rs`): a training view rendered from the training photos is
//! its own photo (angle 0 dominates the blend), held-out views score finite, the result does not
//! depend on the thread count, and its hit pixels and footprints are the model's.

use std::path::Path;
use xscale::eval::protocol::score_rendered;
use xscale::raycast::{cast_rows, Tracer};
use xscale::render::ulr::{render_ulr, Source};
use xscale::scene::{LoadOptions, Scene};

#[path = "common/pool.rs"]
mod pool;
use pool::in_pool;

#[test]
fn ulr_reproduces_training_photos_and_scores_held_out_views() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("fixtures/tiny");
    let scene = Scene::load(&root, &LoadOptions::default()).unwrap();
    let tracer = Tracer::new(&scene.mesh, &scene.normalization).unwrap();
    let train = scene.train();
    let sources: Vec<Source> = train
        .iter()
        .map(|&j| Source::new(scene.views[j].camera.clone(), &scene.load_image(j).unwrap()))
        .collect();
    let bg = scene.background;
    // A training view: its own photo at angle 0 takes (nearly) all the weight.
    let j = train[1];
    let r = render_ulr(&tracer, &sources, &scene.views[j].camera, 2, bg).unwrap();
    let own = score_rendered(&scene, j, r, bg).unwrap().scored.score;
    assert!(
        own.psnr_masked > 40.0,
        "training view {j}: {} dB",
        own.psnr_masked
    );
    // A held-out view: finite, sensible scores; the same bits with 1 and 2 threads.
    let t = scene.test[1];
    let a = in_pool(1, || {
        render_ulr(&tracer, &sources, &scene.views[t].camera, 2, bg).unwrap()
    });
    let b = in_pool(2, || {
        render_ulr(&tracer, &sources, &scene.views[t].camera, 2, bg).unwrap()
    });
    assert!(a
        .image
        .data
        .iter()
        .zip(&b.image.data)
        .all(|(x, y)| x.to_bits() == y.to_bits()));
    let s = score_rendered(&scene, t, a, bg).unwrap().scored.score;
    assert!(
        s.psnr_masked.is_finite() && s.psnr_masked > 10.0,
        "{}",
        s.psnr_masked
    );
    assert!(s.footprint.is_some());
    // Its pixels are the model's: a pixel is a hit when any of its γ² rays hits (the mesh ends
    // inside some of this view's pixels), with the cast's footprint — for γ = 1 and 2.
    let cam = &scene.views[t].camera;
    for gamma in [1, 2] {
        let r = render_ulr(&tracer, &sources, cam, gamma, bg).unwrap();
        let cast = cast_rows(&tracer, cam, gamma, 0, cam.height).unwrap();
        let hits: Vec<bool> = cast.pixels.iter().map(|p| p.valid != 0).collect();
        assert_eq!(r.hit, hits, "γ = {gamma}");
        let fp: Vec<f32> = cast.pixels.iter().map(|p| p.footprint as f32).collect();
        assert_eq!(r.footprint, fp, "γ = {gamma}");
    }
}

/// `xscale eval --method ulr --scene DIR` needs no trained model; `--method model` without one
/// says what to give.
#[test]
fn ulr_eval_needs_only_a_scene() {
    let exe = env!("CARGO_BIN_EXE_xscale");
    let scene = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("fixtures/tiny");
    let json =
        std::env::temp_dir().join(format!("xscale-ulr-scene-only-{}.json", std::process::id()));
    let out = std::process::Command::new(exe)
        .args(["eval", "--method", "ulr", "--scene"])
        .arg(&scene)
        .arg("--json")
        .arg(&json)
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let v: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&json).unwrap()).unwrap();
    assert!(!v["views"].as_array().unwrap().is_empty());
    assert!(v["mean"]["psnr_masked"].as_f64().unwrap() > 10.0, "{v}");
    // The JSON says what rendered, and names no checkpoint (none was used).
    assert_eq!(v["method"], "ulr", "{v}");
    assert!(v.get("checkpoint").is_none(), "{v}");
    let _ = std::fs::remove_file(&json);
    let out = std::process::Command::new(exe)
        .args(["eval", "--scene"])
        .arg(&scene)
        .output()
        .unwrap();
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("--run"));
}

/// With a run, ULR uses its scene, split, mesh and γ but not its checkpoint: the `--json` file
/// says `"method": "ulr"` and names no checkpoint (it named the run's, as the model's does);
/// the model's names its checkpoint and `"method": "model"`. A view named twice is refused
/// (`--views 0,0` scored it twice and counted it twice in the mean).
#[test]
fn eval_json_records_the_method_and_only_a_used_checkpoint() {
    let exe = env!("CARGO_BIN_EXE_xscale");
    let scene = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("fixtures/tiny");
    let dir = std::env::temp_dir().join(format!("xscale-ulr-json-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    let run = dir.join("run");
    let xs = |args: &[&str]| {
        let o = std::process::Command::new(exe).args(args).output().unwrap();
        (
            o.status.code(),
            String::from_utf8_lossy(&o.stderr).into_owned(),
        )
    };
    // A 3-step run of the tiny preset (the scores do not matter here).
    let mut cfg = xscale::train::config::RunConfig::preset("tiny").unwrap();
    cfg.train.steps = 3;
    let opts = xscale::run::trainer::TrainOptions {
        no_final_eval: true,
        quiet: true,
        ..Default::default()
    };
    xscale::run::trainer::train(&scene, &run, cfg, &opts).unwrap();
    let r = run.to_str().unwrap();
    let json = dir.join("e.json");
    let j = json.to_str().unwrap();
    let read = || -> serde_json::Value {
        serde_json::from_str(&std::fs::read_to_string(&json).unwrap()).unwrap()
    };
    let (code, err) = xs(&["eval", "--run", r, "--method", "ulr", "--json", j, "-q"]);
    assert_eq!(code, Some(0), "{err}");
    let v = read();
    assert_eq!(v["method"], "ulr", "{v}");
    assert!(v.get("checkpoint").is_none(), "{v}");
    let (code, err) = xs(&["eval", "--run", r, "--json", j, "-q"]);
    assert_eq!(code, Some(0), "{err}");
    let v = read();
    assert_eq!(v["method"], "model", "{v}");
    assert!(
        v["checkpoint"]
            .as_str()
            .unwrap()
            .ends_with("checkpoint.safetensors"),
        "{v}"
    );
    let (code, err) = xs(&["eval", "--run", r, "--views", "0,0", "-q"]);
    assert!(
        code == Some(2) && err.contains("--views: view 0000.png is named twice"),
        "{code:?} {err}"
    );
    let _ = std::fs::remove_dir_all(&dir);
}
