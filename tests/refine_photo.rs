//! The mesh refinement's photo-consistency term (`[model.refine] photo`, src/refine/photo_term.rs) and its
//! Gauss–Newton step (`optimizer = "gauss-newton"`): bit-identical on 1 and 2 threads, exact
//! resume between two updates and right after one, patches that actually take part, and clear
//! errors for values it cannot run. Its own test binary: it sets `XSCALE_REFINE_LOG`
//! (process-wide) to read each update's photo statistics.

use std::path::Path;
use xscale::model::refine::PhotoMeasure;
use xscale::model::refine::RefineOptimizer;
use xscale::run::trainer::train;
use xscale::train::config::RunConfig;
use xscale::train::state::TrainState;

#[path = "common/pool.rs"]
mod pool;
use pool::in_pool;
#[path = "common/refine_run.rs"]
mod refine_run;
use refine_run::{cfg, fixture, opts, tmp};

/// The shared refinement run (`common/refine_run.rs`: steps 40 to 144 of 160, updates every 17
/// steps, so the resume point 100 falls between two) with the photo term at image levels 1 → 0,
/// half the feature gradient, and the given step rule and measure.
fn photo_cfg(opt: RefineOptimizer, measure: PhotoMeasure) -> RunConfig {
    let mut c = cfg();
    let r = &mut c.model.refine;
    r.photo = 1.0;
    r.features = 0.5;
    r.photo_pixels = 48;
    r.photo_patch = 3;
    r.photo_measure = measure;
    r.photo_levels = [1, 0];
    r.photo_angle = [2.0, 80.0];
    r.photo_scale = 4.0;
    // The cross-scale levels, weights and neighbours chosen again (configs/refine-cross.toml).
    r.photo_reach = 2.0;
    r.photo_balance = true;
    r.photo_rechoose = true;
    r.optimizer = opt;
    if opt == RefineOptimizer::GaussNewton {
        r.lr = 0.5;
        r.lr_end = 0.25;
    }
    c.validate().unwrap();
    c
}

/// Run `f` with the refinement log at `log` (removed first); the log's update lines.
fn logged<T>(log: &Path, f: impl FnOnce() -> T) -> (T, Vec<serde_json::Value>) {
    let _ = std::fs::remove_file(log);
    std::env::set_var("XSCALE_REFINE_LOG", log);
    let out = f();
    std::env::remove_var("XSCALE_REFINE_LOG");
    let text = std::fs::read_to_string(log).unwrap_or_default();
    let lines = text
        .lines()
        .map(|l| serde_json::from_str::<serde_json::Value>(l).unwrap())
        .collect();
    let _ = std::fs::remove_file(log);
    (out, lines)
}

/// The tests of this binary run one at a time (the log variable is process-wide).
static SERIAL: std::sync::Mutex<()> = std::sync::Mutex::new(());

fn moved(run: &Path) -> usize {
    let st = TrainState::load(&run.join("checkpoint.safetensors")).unwrap();
    let r = st.ckpt.refine.unwrap();
    r.offsets.iter().filter(|&&t| t != 0.0).count()
}

#[test]
fn photo_refinement_is_thread_independent_and_resumes_exactly() {
    let _serial = SERIAL.lock().unwrap_or_else(|e| e.into_inner());
    let c = photo_cfg(RefineOptimizer::GaussNewton, PhotoMeasure::Zncc);
    let mut finals = Vec::new();
    let mut logs = Vec::new();
    for threads in [1, 2] {
        let run = tmp(&format!("photo{threads}"));
        let (r, log) = logged(&tmp(&format!("photo-log{threads}")), || {
            in_pool(threads, || {
                train(&fixture(), &run, c.clone(), &opts(false, None))
            })
        });
        r.unwrap();
        finals.push(std::fs::read(run.join("checkpoint.safetensors")).unwrap());
        if threads == 1 {
            assert!(moved(&run) > 0, "the photo term moved no vertex");
        }
        logs.push(log);
        let _ = std::fs::remove_dir_all(&run);
    }
    assert!(finals[0] == finals[1], "1 and 2 threads differ");
    assert_eq!(logs[0], logs[1]);
    // The neighbours chosen, then an update line with the photo statistics after each update.
    let pairs = &logs[0][0]["photo_pairs"];
    assert!(
        pairs
            .as_array()
            .unwrap()
            .iter()
            .any(|p| !p[1].as_array().unwrap().is_empty()),
        "no view has a neighbour: {pairs}"
    );
    let updates: Vec<&serde_json::Value> = logs[0]
        .iter()
        .filter(|l| l.get("photo").is_some())
        .collect();
    assert_eq!(updates.len(), 7, "{:?}", logs[0]);
    for u in &updates {
        let p = &u["photo"];
        assert!(
            p["valid"].as_u64().unwrap() > 0,
            "no patch took part in the update after step {}: {p}",
            u["step"]
        );
    }
    // The cross-scale levels (photo_reach): the close-ups (footprints ~30× finer)
    // start at level 2, the last a 48-row photo holds a 3 × 3 patch and its pull-in at, the
    // aerial views at photo_levels[0] = 1, each view's first span at its top; every view
    // descends to 0 by the last update; the weights are positive.
    let views: Vec<&serde_json::Value> = logs[0].iter().filter_map(|l| l.get("views")).collect();
    assert_eq!(views.len(), 7, "{:?}", logs[0]);
    let tops: Vec<u64> = views[0]
        .as_array()
        .unwrap()
        .iter()
        .map(|v| v["top"].as_u64().unwrap())
        .collect();
    assert!(tops.contains(&2) && tops.contains(&1), "tops {tops:?}");
    for v in views[0].as_array().unwrap() {
        assert!(v["weight"].as_f64().unwrap() > 0.0, "{v}");
        assert_eq!(
            v["level"], v["top"],
            "the first update is at each view's top: {v}"
        );
    }
    for v in views[6].as_array().unwrap() {
        assert_eq!(v["level"], 0, "{v}");
    }
    // Stopped at 100 (between the updates after steps 91 and 108, gradient and curvature
    // pending) and resumed: the same bytes.
    let split = tmp("photo-split");
    in_pool(2, || {
        let s = train(&fixture(), &split, c.clone(), &opts(false, Some(100))).unwrap();
        assert!(s.interrupted && s.steps == 100);
        train(&fixture(), &split, c.clone(), &opts(true, None)).unwrap();
    });
    assert!(
        std::fs::read(split.join("checkpoint.safetensors")).unwrap() == finals[1],
        "a resumed photo refinement run differs from the uninterrupted one"
    );
    let _ = std::fs::remove_dir_all(&split);
    // Stopped right after the update of step 74 (before its BVH rebuild) and resumed.
    let cut = tmp("photo-cut");
    in_pool(2, || {
        train(&fixture(), &cut, c.clone(), &opts(false, Some(74))).unwrap();
        train(&fixture(), &cut, c.clone(), &opts(true, None)).unwrap();
    });
    assert!(
        std::fs::read(cut.join("checkpoint.safetensors")).unwrap() == finals[1],
        "a photo refinement run resumed right after an update differs"
    );
    let _ = std::fs::remove_dir_all(&cut);
}

/// The other measure with Adam, and the photo term alone (features = 0): thread-independent,
/// and the mesh moves.
#[test]
fn photo_refinement_with_adam_and_huber_is_thread_independent() {
    let _serial = SERIAL.lock().unwrap_or_else(|e| e.into_inner());
    let mut c = photo_cfg(RefineOptimizer::Adam, PhotoMeasure::Huber);
    c.model.refine.features = 0.0;
    c.model.refine.photo_patch = 1;
    c.validate().unwrap();
    let mut finals = Vec::new();
    for threads in [1, 2] {
        let run = tmp(&format!("huber{threads}"));
        in_pool(threads, || {
            train(&fixture(), &run, c.clone(), &opts(false, None))
        })
        .unwrap();
        finals.push(std::fs::read(run.join("checkpoint.safetensors")).unwrap());
        assert!(moved(&run) > 0, "the photo term moved no vertex");
        let _ = std::fs::remove_dir_all(&run);
    }
    assert!(finals[0] == finals[1], "1 and 2 threads differ");
}

/// Values the photo term cannot run are refused with the key and the value named.
#[test]
fn bad_photo_settings_are_named() {
    type Setter = Box<dyn Fn(&mut RunConfig)>;
    let bad: Vec<(&str, Setter)> = vec![
        ("photo = -1", Box::new(|c| c.model.refine.photo = -1.0)),
        (
            "features = NaN",
            Box::new(|c| c.model.refine.features = f64::NAN),
        ),
        (
            "features = 0 and photo = 0",
            Box::new(|c| c.model.refine.features = 0.0),
        ),
        (
            "photo_patch = 4",
            Box::new(|c| c.model.refine.photo_patch = 4),
        ),
        (
            "photo_patch = 1 with photo_measure = \"zncc\"",
            Box::new(|c| {
                c.model.refine.photo = 1.0;
                c.model.refine.photo_patch = 1;
            }),
        ),
        (
            "photo_levels = [0, 1]",
            Box::new(|c| c.model.refine.photo_levels = [0, 1]),
        ),
        (
            "photo_pixels = 0",
            Box::new(|c| c.model.refine.photo_pixels = 0),
        ),
        (
            "photo_neighbours = 0",
            Box::new(|c| c.model.refine.photo_neighbours = 0),
        ),
        (
            "photo_angle = [30, 10]",
            Box::new(|c| c.model.refine.photo_angle = [30.0, 10.0]),
        ),
        (
            "photo_scale = 0.5",
            Box::new(|c| c.model.refine.photo_scale = 0.5),
        ),
        (
            "photo_reach = -1",
            Box::new(|c| c.model.refine.photo_reach = -1.0),
        ),
        ("damping = -1", Box::new(|c| c.model.refine.damping = -1.0)),
        (
            "optimizer = \"gauss-newton\" needs",
            Box::new(|c| c.model.refine.optimizer = RefineOptimizer::GaussNewton),
        ),
    ];
    for (want, set) in bad {
        let mut c = cfg();
        set(&mut c);
        let e = format!("{:#}", c.validate().unwrap_err());
        assert!(e.contains(want), "want {want:?} in: {e}");
        assert!(e.contains("model.refine"), "{e}");
    }
    // From TOML, an unknown measure or step rule names the key.
    for (text, key) in [
        ("[model.refine]\nphoto_measure = \"ssd\"\n", "photo_measure"),
        ("[model.refine]\noptimizer = \"lbfgs\"\n", "optimizer"),
    ] {
        let e = RunConfig::from_toml_str(text, "tiny", "test.toml").unwrap_err();
        let e = format!("{e:#}");
        assert!(e.contains(key), "{e}");
    }
    // A level so coarse that a view is smaller than a patch is refused when the run starts.
    let mut c = photo_cfg(RefineOptimizer::GaussNewton, PhotoMeasure::Zncc);
    c.model.refine.photo_levels = [5, 0];
    c.model.refine.photo_patch = 3;
    c.validate().unwrap();
    let run = tmp("too-coarse");
    let Err(e) = train(&fixture(), &run, c, &opts(false, None)) else {
        panic!("a photo level coarser than the views ran");
    };
    let e = format!("{e:#}");
    assert!(
        e.contains("photo_levels[0] = 5") && e.contains("view 0001.png"),
        "{e}"
    );
    let _ = std::fs::remove_dir_all(&run);
}

/// Through real lenses: the tiny scene rendered through an OPENCV lens (`xscale synth --lens
/// opencv`, the same views as the fixture) runs the photo term bit-identically on 1 and 2
/// threads, its patches take part and the mesh moves. (The distortion's derivative is checked
/// by tests/gradcheck.rs.)
#[test]
fn photo_refinement_through_a_distorted_lens_is_thread_independent() {
    let _serial = SERIAL.lock().unwrap_or_else(|e| e.into_inner());
    let scene = tmp("opencv-scene");
    xscale::synth::generate(
        xscale::synth::Preset::Tiny,
        1,
        xscale::synth::Lens::Opencv,
        &scene,
        false,
        &mut |_, _| Ok(()),
    )
    .unwrap();
    let cams = std::fs::read_to_string(scene.join("sparse/0/cameras.txt")).unwrap();
    assert!(cams.contains("OPENCV"), "{cams}");
    let c = photo_cfg(RefineOptimizer::GaussNewton, PhotoMeasure::Zncc);
    let mut finals = Vec::new();
    for threads in [1, 2] {
        let run = tmp(&format!("opencv-run{threads}"));
        let (r, log) = logged(&tmp(&format!("opencv-log{threads}")), || {
            in_pool(threads, || {
                train(&scene, &run, c.clone(), &opts(false, None))
            })
        });
        r.unwrap();
        finals.push(std::fs::read(run.join("checkpoint.safetensors")).unwrap());
        assert!(moved(&run) > 0, "the photo term moved no vertex");
        let valid: u64 = log
            .iter()
            .filter_map(|l| l.get("photo"))
            .map(|p| p["valid"].as_u64().unwrap())
            .sum();
        assert!(valid > 0, "no patch took part: {log:?}");
        let _ = std::fs::remove_dir_all(&run);
    }
    assert!(finals[0] == finals[1], "1 and 2 threads differ");
    let _ = std::fs::remove_dir_all(&scene);
}
