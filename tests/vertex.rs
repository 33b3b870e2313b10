//! The vertex-feature baseline (Fig. 2b) end to end: the sample cache's triangle ids and
//! barycentrics agree with the cached positions, checkpoints and batches round-trip, training
//! (sparse Adam over the vertex table) learns and resumes exactly, and a model refuses a mesh it
//! was not trained on.

use std::path::{Path, PathBuf};
use xscale::io::tensors::TensorFile;
use xscale::model::batch::Batch;
use xscale::model::checkpoint::{
    batch_from_tensors, batch_to_tensors, dump, init_checkpoint, init_checkpoint_for_mesh,
    Checkpoint, Normalization,
};
use xscale::model::config::{Featurization, ModelConfig};
use xscale::raycast::{SampleCache, Tracer};
use xscale::run::trainer::{train, TrainOptions};
use xscale::scene::{LoadOptions, Scene};
use xscale::train::config::RunConfig;
use xscale::train::sampler::sample_batch;
use xscale::train::state::TrainState;

fn fixture() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("fixtures/tiny")
}

fn tmp(name: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("xscale-test-vertex-{}-{name}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    d
}

fn vertex_cfg() -> ModelConfig {
    let mut c = ModelConfig::tiny();
    c.featurization = Featurization::Vertex;
    c.vertex_features = 6;
    c.deform.enabled = false;
    c
}

#[test]
fn cached_barycentrics_reproduce_the_positions() {
    let scene = Scene::load(&fixture(), &LoadOptions::default()).unwrap();
    let tracer = Tracer::new(&scene.mesh, &scene.normalization).unwrap();
    let train = scene.train();
    let views: Vec<_> = train
        .iter()
        .take(3)
        .map(|&i| (&scene.views[i].camera, None))
        .collect();
    let plain = SampleCache::build(&tracer, &views, 2, false, &mut |_| {}).unwrap();
    let c = SampleCache::build(&tracer, &views, 2, true, &mut |_| {}).unwrap();
    assert!(c.has_triangles() && !plain.has_triangles());
    // Same pixels and positions as the plain cache; 12 more bytes per sub-sample slot.
    assert_eq!(c.len(), plain.len());
    assert_eq!(c.positions_fixed(), plain.positions_fixed());
    assert_eq!(c.bytes(), plain.bytes() + c.len() * 4 * 12);
    let n = &scene.normalization;
    let mut checked = 0;
    for i in (0..c.len()).step_by(7) {
        for j in 0..4 {
            let (t, [u, v]) = c.surface_id(i, j);
            if (c.valid(i) >> j) & 1 == 0 {
                assert_eq!(t, u32::MAX);
                continue;
            }
            assert!(u >= -1e-9 && v >= -1e-9 && u + v <= 1.0 + 1e-9, "{u} {v}");
            let f = scene.mesh.triangles[t as usize];
            let p = scene.mesh.vertices[f[0] as usize] * (1.0 - u - v)
                + scene.mesh.vertices[f[1] as usize] * u
                + scene.mesh.vertices[f[2] as usize] * v;
            let pn = n.to_normalized(p).to_array();
            let q = c.position(i, j);
            for a in 0..3 {
                assert!(
                    (pn[a] - q[a]).abs() < 1e-6,
                    "pixel {i} sub {j}: {pn:?} vs {q:?}"
                );
            }
            checked += 1;
        }
    }
    assert!(checked > 200, "{checked}");
}

#[test]
fn vertex_checkpoints_and_batches_roundtrip() {
    let scene = Scene::load(&fixture(), &LoadOptions::default()).unwrap();
    let cfg = vertex_cfg();
    assert!(init_checkpoint(&cfg, 1, Normalization::unit(), 3).is_err());
    let ck =
        init_checkpoint_for_mesh(&cfg, 1, Normalization::unit(), 3, Some(&scene.mesh)).unwrap();
    let vt = ck.model.vertex.as_ref().unwrap();
    assert_eq!(vt.n_vertices, scene.mesh.vertices.len());
    assert_eq!(
        ck.model.cfg.vertex_count as usize,
        scene.mesh.vertices.len()
    );
    let f = ck.to_tensor_file().unwrap();
    assert!(
        f.tensors.keys().all(|k| !k.starts_with("grid_")),
        "no grid tensors"
    );
    assert_eq!(
        f.tensors["vertex.faces"].shape,
        [scene.mesh.triangles.len(), 3]
    );
    assert_eq!(
        f.tensors["vertex.features"].shape,
        [scene.mesh.vertices.len(), 6]
    );
    let bytes = f.to_bytes().unwrap();
    let back =
        Checkpoint::from_tensor_file(&TensorFile::from_bytes(&bytes, "mem").unwrap()).unwrap();
    assert_eq!(back.params, ck.params);
    assert_eq!(back.model.vertex, ck.model.vertex);
    assert_eq!(back.model.cfg, ck.model.cfg);
    // A face pointing past the vertex table is a named error.
    let mut bad = f.clone();
    let mut faces = bad.tensors["vertex.faces"].to_u32().unwrap();
    faces[5] = 1_000_000;
    bad.insert(
        "vertex.faces",
        xscale::io::tensors::Tensor::u32(vec![faces.len() / 3, 3], &faces).unwrap(),
    );
    let e = format!("{:#}", Checkpoint::from_tensor_file(&bad).unwrap_err());
    assert!(e.contains("face 1"), "{e}");

    // A batch with triangle ids round-trips through tensors; a dump names the vertex stage.
    let mut rc = RunConfig::preset("tiny").unwrap();
    rc.model = cfg.clone();
    let p = xscale::train::setup::prepare(&fixture(), &rc, true, &mut |_| {}).unwrap();
    assert!(p.samples.has_triangles());
    let b = sample_batch(&p.samples, &p.tracer, 3, 0, 64);
    assert_eq!(b.triangle.len(), 64 * 4);
    let mut tf = TensorFile::new();
    batch_to_tensors(&mut tf, &b).unwrap();
    assert!(tf.tensors.contains_key("batch.triangle") && tf.tensors.contains_key("batch.bary"));
    let b2 = batch_from_tensors(&tf).unwrap();
    assert_eq!(b2, b);
    let ck = init_checkpoint_for_mesh(
        &cfg,
        1,
        Normalization::unit(),
        p.train_views.len(),
        Some(&p.scene.mesh),
    )
    .unwrap();
    let d = dump::<f64>(&ck, &b).unwrap();
    assert_eq!(d.get("fwd.vertex").unwrap().shape, [64, 4, 6]);
    assert!(!d.tensors.contains_key("fwd.grid_h"));
    assert!(d.tensors.contains_key("grad.vertex.features"));
    // A hash-model batch (no ids) keeps exactly SPEC §6's tensors.
    let hb = Batch::random(1, 5, 4, 2, 0.2);
    let mut tf = TensorFile::new();
    batch_to_tensors(&mut tf, &hb).unwrap();
    assert_eq!(tf.tensors.len(), 5);
}

#[test]
fn vertex_training_learns_and_resumes_exactly() {
    let mut rc = RunConfig::preset("tiny").unwrap();
    rc.model = vertex_cfg();
    rc.train.steps = 60;
    rc.train.batch_pixels = 512;
    rc.train.eval_every = 0;
    rc.train.checkpoint_every = 0;
    let opts = |resume, stop_at| TrainOptions {
        resume,
        stop_at,
        no_final_eval: true,
        quiet: true,
        ..Default::default()
    };
    let a = tmp("a");
    train(&fixture(), &a, rc.clone(), &opts(false, None)).unwrap();
    let b = tmp("b");
    train(&fixture(), &b, rc.clone(), &opts(false, Some(25))).unwrap();
    train(&fixture(), &b, rc.clone(), &opts(true, None)).unwrap();
    let (sa, sb) = (
        std::fs::read(a.join("checkpoint.safetensors")).unwrap(),
        std::fs::read(b.join("checkpoint.safetensors")).unwrap(),
    );
    assert!(
        sa == sb,
        "resumed vertex run differs from the uninterrupted one"
    );
    // Learning: the loss on a fixed batch fell, and only touched rows moved from their init.
    let st = TrainState::load(&a.join("checkpoint.safetensors")).unwrap();
    let p = xscale::train::setup::prepare(&fixture(), &st.cfg, true, &mut |_| {}).unwrap();
    let batch = sample_batch(&p.samples, &p.tracer, 99, 0, 2048);
    let init = init_checkpoint_for_mesh(
        &st.ckpt.model.cfg,
        rc.train.seed,
        st.ckpt.normalization,
        p.train_views.len(),
        Some(&p.scene.mesh),
    )
    .unwrap();
    let l0 = init.model.forward(&init.params, &batch).unwrap().loss;
    let l1 = st.ckpt.model.forward(&st.ckpt.params, &batch).unwrap().loss;
    assert!(l1 < 0.7 * l0, "loss {l0} → {l1}");
    let r = st.ckpt.model.layout.range("vertex.features");
    let moved = st.ckpt.params[r.clone()]
        .iter()
        .zip(&init.params[r])
        .filter(|(a, b)| a != b)
        .count();
    assert!(moved > 0);
    // The model refuses another mesh (a decimated one) at evaluation time.
    let scene = Scene::load(&fixture(), &LoadOptions::default()).unwrap();
    let dec = xscale::scene::mesh::decimate(&scene.mesh, 0.5).unwrap();
    let mp = a.join("dec.ply");
    xscale::scene::mesh::write_ply(&mp, &dec).unwrap();
    let out = std::process::Command::new(env!("CARGO_BIN_EXE_xscale"))
        .args(["eval", "--run"])
        .arg(&a)
        .arg("--scene")
        .arg(fixture())
        .arg("--mesh")
        .arg(&mp)
        .output()
        .unwrap();
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("--mesh"), "{err}");
    for d in [a, b] {
        let _ = std::fs::remove_dir_all(d);
    }
}
