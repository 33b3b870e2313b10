//! Mesh refinement during training (`[model.refine]`, src/refine/refiner.rs): bit-identical on 1, 2
//! and 4 threads, exact resume across a BVH rebuild, the refined mesh in the checkpoint, in
//! `refined.ply` and in what eval/render load, and clear errors for configurations it cannot run.

use std::path::Path;
use xscale::run::trainer::train;
use xscale::train::config::RunConfig;
use xscale::train::state::TrainState;

#[path = "common/pool.rs"]
mod pool;
use pool::in_pool;
#[path = "common/refine_run.rs"]
mod refine_run;
use refine_run::{cfg, fixture, opts, tmp};

/// The final checkpoint of run `c` stopped at step 100 (2 threads) and resumed.
fn resumed_at_100(c: &RunConfig, tag: &str) -> Vec<u8> {
    let split = tmp(tag);
    let s = in_pool(2, || {
        train(&fixture(), &split, c.clone(), &opts(false, Some(100)))
    })
    .unwrap();
    assert!(s.interrupted && s.steps == 100);
    in_pool(2, || {
        train(&fixture(), &split, c.clone(), &opts(true, None))
    })
    .unwrap();
    let bytes = std::fs::read(split.join("checkpoint.safetensors")).unwrap();
    let _ = std::fs::remove_dir_all(&split);
    bytes
}

/// More than half the vertices of the run's checkpoint have a nonzero offset.
fn assert_mesh_moved(run: &Path) {
    let st = TrainState::load(&run.join("checkpoint.safetensors")).unwrap();
    let r = st.ckpt.refine.as_ref().unwrap();
    let moved = r.offsets.iter().filter(|&&t| t != 0.0).count();
    assert!(
        moved * 2 > r.offsets.len(),
        "{moved} of {} vertices moved",
        r.offsets.len()
    );
}

#[test]
fn refinement_is_thread_independent_resumes_exactly_and_moves_the_mesh() {
    let mut finals = Vec::new();
    for threads in [1, 2, 4] {
        let run = tmp(&format!("straight{threads}"));
        in_pool(threads, || {
            train(&fixture(), &run, cfg(), &opts(false, None))
        })
        .unwrap();
        finals.push(std::fs::read(run.join("checkpoint.safetensors")).unwrap());
        if threads == 2 {
            // Stopped at 100 (between the rebuilds at 91 and 108) and resumed.
            let resumed = resumed_at_100(&cfg(), "split");
            assert!(
                resumed == finals[1],
                "a resumed refinement run differs from the uninterrupted one"
            );
        }
        if threads == 4 {
            // The mesh moved, the checkpoint and refined.ply agree, and eval/render load it.
            assert_mesh_moved(&run);
            let refined = xscale::scene::mesh::load_mesh(&run.join("refined.ply"))
                .unwrap()
                .0;
            let (base, _) = xscale::scene::mesh::load_mesh(&fixture().join("mesh.ply")).unwrap();
            assert_eq!(refined.triangles, base.triangles);
            assert!(refined.vertices != base.vertices);
            let (ck, rc) =
                xscale::run::model::load_model(&run.join("checkpoint.safetensors")).unwrap();
            let s = xscale::run::model::scene_for_model(&fixture(), &ck, rc.as_ref(), None, None)
                .unwrap();
            assert_eq!(s.scene.mesh.vertices, refined.vertices);
            // Loaded with the scene read while the tables are: the refined mesh too.
            let (_, _, _, s2) = xscale::run::model::load_model_and_scene(
                &run.join("checkpoint.safetensors"),
                || Ok(fixture()),
                None,
                None,
            )
            .unwrap();
            assert_eq!(s2.scene.mesh.vertices, refined.vertices);
        }
        let _ = std::fs::remove_dir_all(&run);
    }
    assert!(finals[0] == finals[1], "1 and 2 threads differ");
    assert!(finals[0] == finals[2], "1 and 4 threads differ");
}

#[test]
fn configurations_refinement_cannot_run_are_errors() {
    let check = |text: &str, want: &str| {
        let e = RunConfig::from_toml_str(text, "tiny", "r.toml").unwrap_err();
        let msg = format!("{e:#}");
        assert!(msg.contains("r.toml") && msg.contains(want), "{msg}");
    };
    check(
        "[model.refine]\nenabled = true\n[train]\nsamples = \"cache\"\n",
        "stream",
    );
    check(
        "[model.refine]\nenabled = true\n[train]\narithmetic = \"f64\"\n",
        "f32",
    );
    check(
        "[model]\nfeaturization = \"vertex\"\nvertex_features = 4\n[model.deform]\nenabled = false\n[model.refine]\nenabled = true\n",
        "hash",
    );
    check("[model.refine]\nenabled = true\nstart = 1.5\n", "start");
    check("[model.refine]\nupdate_every = 0\n", "update_every");
    check("[model.refine]\nlr_end = -1e-3\n", "lr_end");
    check("[model.refine]\nstart = 0.5\nstop = 0.4\n", "stop");
    check(
        "[model.refine]\ngradient_cells = [0, 64]\n",
        "gradient_cells",
    );
    check(
        "[model.refine]\nlevels = 0\nper_vertex = false\n",
        "nothing can move",
    );
    check("[model.refine]\nenabeld = true\n", "enabeld");
    // Defaults are absent from the saved config; a refinement config round-trips.
    let plain = RunConfig::preset("cpu").unwrap().to_toml();
    assert!(!plain.contains("refine"), "{plain}");
    let c = RunConfig::from_toml_str(
        "[model.refine]\nenabled = true\nlr = 3e-5\n",
        "cpu",
        "r.toml",
    )
    .unwrap();
    assert!(c.model.refine.enabled && c.model.refine.lr == 3e-5);
    // `enabled = true` alone is the section's defaults, the photo-consistency refinement
    // (configs/refine-photo.toml spells them out), under every preset.
    for preset in ["tiny", "cpu", "paper"] {
        let on = RunConfig::from_toml_str("[model.refine]\nenabled = true\n", preset, "on")
            .unwrap()
            .model
            .refine;
        let photo = RunConfig::resolve(
            preset,
            Some(
                &std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("configs/refine-photo.toml"),
            ),
        )
        .unwrap()
        .model
        .refine;
        assert_eq!(on, photo, "{preset}");
        assert!(
            on.photo == 1.0 && on.features == 0.0 && on.anchored,
            "{on:?}"
        );
    }
    // configs/refine-cross.toml: those defaults with the cross-scale levels, weights and
    // neighbours chosen again (docs/geometry.md §5), and nothing else changed.
    let cross = RunConfig::resolve(
        "cpu",
        Some(&std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("configs/refine-cross.toml")),
    )
    .unwrap()
    .model
    .refine;
    assert_eq!(
        cross,
        xscale::model::refine::RefineConfig {
            enabled: true,
            photo_reach: 2.0,
            photo_balance: true,
            photo_rechoose: true,
            ..Default::default()
        }
    );
    // A table written before that (which left out `features`, `photo` and `optimizer` at the
    // learned-features values) reads back as what it trained with.
    let mut old = RunConfig::preset("cpu").unwrap();
    old.model.refine = xscale::model::refine::RefineConfig::learned();
    old.model.refine.enabled = true;
    let text = old
        .to_toml()
        .replace("features = 1.0\n", "")
        .replace("photo = 0.0\n", "")
        .replace("optimizer = \"adam\"\n", "");
    assert!(!text.contains("photo ="), "{text}");
    assert_eq!(RunConfig::from_stored_toml(&text, "old").unwrap(), old);
    assert_eq!(
        RunConfig::from_toml_str(&c.to_toml(), "cpu", "again").unwrap(),
        c
    );
}

/// `[model.refine] anchored`: bit-identical on 1 and 2 threads, exact resume across a rebuild
/// (the rays of a batch are rebuilt from the `traced` offsets), the mesh moves, and a render
/// loaded with the run config reports the training mesh's points.
#[test]
fn anchored_refinement_is_thread_independent_resumes_exactly_and_moves_the_mesh() {
    let mut c = cfg();
    c.model.refine.anchored = true;
    c.validate().unwrap();
    let mut finals = Vec::new();
    for threads in [1, 2] {
        let run = tmp(&format!("anchored{threads}"));
        in_pool(threads, || {
            train(&fixture(), &run, c.clone(), &opts(false, None))
        })
        .unwrap();
        finals.push(std::fs::read(run.join("checkpoint.safetensors")).unwrap());
        if threads == 2 {
            assert_mesh_moved(&run);
            // The render's tracer runs on the refined mesh and reports the training mesh's point.
            let (ck, rc) =
                xscale::run::model::load_model(&run.join("checkpoint.safetensors")).unwrap();
            let s = xscale::run::model::scene_for_model(&fixture(), &ck, rc.as_ref(), None, None)
                .unwrap();
            let (base, _) = xscale::scene::mesh::load_mesh(&fixture().join("mesh.ply")).unwrap();
            let view = &s.scene.views[s.scene.test[0]];
            let cast = xscale::raycast::cast_view(&s.tracer, &view.camera, 1).unwrap();
            let norm = s.scene.normalization;
            let mut checked = 0;
            for ss in cast.subs.iter().filter(|ss| ss.hit()) {
                let t = base.triangles[ss.triangle as usize].map(|k| base.vertices[k as usize]);
                let x = t[0] * (1.0 - ss.u - ss.v) + t[1] * ss.u + t[2] * ss.v;
                let want = (x - norm.center) / norm.extent + glam::DVec3::splat(0.5);
                assert!((ss.position - want).abs().max_element() < 1e-9);
                checked += 1;
            }
            assert!(checked > 100, "{checked} hits");
            let resumed = resumed_at_100(&c, "anchored-split");
            assert!(resumed == finals[1], "a resumed anchored run differs");
        }
        let _ = std::fs::remove_dir_all(&run);
    }
    assert!(finals[0] == finals[1], "1 and 2 threads differ");
}

/// A run that refines its mesh says where the refined mesh is and how far it moved (it used to
/// write `refined.ply` without a word; a user found it only through `mesh-distance`).
#[test]
fn a_refining_run_names_its_refined_mesh_and_how_far_it_moved() {
    let run = tmp("cli-says");
    let _ = std::fs::remove_dir_all(&run);
    let cfg = Path::new(env!("CARGO_MANIFEST_DIR")).join("configs/refine.toml");
    let o = std::process::Command::new(env!("CARGO_BIN_EXE_xscale"))
        .args([
            "train",
            "--preset",
            "tiny",
            "--steps",
            "30",
            "--no-eval",
            "--scene",
        ])
        .arg(fixture())
        .arg("--config")
        .arg(&cfg)
        .arg("--out")
        .arg(&run)
        .output()
        .unwrap();
    let text = format!(
        "{}{}",
        String::from_utf8_lossy(&o.stdout),
        String::from_utf8_lossy(&o.stderr)
    );
    assert!(o.status.success(), "{text}");
    let line = text
        .lines()
        .find(|l| l.starts_with("refined mesh written to "))
        .unwrap_or_else(|| panic!("no refined-mesh line in:\n{text}"));
    assert!(
        line.contains(&run.join("refined.ply").display().to_string()),
        "{line}"
    );
    let rms: f64 = line
        .split("moved ")
        .nth(1)
        .and_then(|r| r.split(' ').next())
        .and_then(|v| v.parse().ok())
        .unwrap_or_else(|| panic!("no RMS in {line}"));
    assert!(rms > 0.0 && rms.is_finite(), "{line}");
    let _ = std::fs::remove_dir_all(&run);
}
