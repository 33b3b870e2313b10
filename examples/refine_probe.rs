//! Does the vertex gradient through the hit point point at the true surface? (docs/geometry.md)
//!
//! Loads a run trained on a displaced proxy of a synthetic scene (`xscale bench-geometry`), and
//! accumulates ∂L/∂θ (`model::refine::hits_backward`) over a number of training batches with the
//! mesh unmoved, for several cut-offs of the grid levels the position gradient goes through
//! (`Grads::position_max_scale`). The proxy's true error is known vertex by vertex (the proxy is
//! the exact mesh with every vertex moved along its normal), so the cosine between the gradient
//! and the error (per vertex, and gathered on each grid level of the offset field as the
//! refinement's Adam sees it) says whether gradient descent moves the mesh towards the truth
//! (cosine > 0) and how consistently.
//!
//! ```text
//! cargo run --release --example refine_probe -- RUN_DIR EXACT_MESH [BATCHES] [SCALES,...]
//! ```
//! `SCALES`: cells per unit of the finest level used (0 = every level).

use glam::DVec3;
use xscale::model::params::Grads;
use xscale::refine::field::{field_backward, Active, RefineGeom};
use xscale::refine::hit::{hits_backward, reintersect_batch};
use xscale::train::sampler::sample_batch;
use xscale::train::setup::prepare;
use xscale::train::state::TrainState;

fn cosine(a: &[f64], b: &[f64]) -> f64 {
    let (mut ab, mut aa, mut bb) = (0.0, 0.0, 0.0);
    for (x, y) in a.iter().zip(b) {
        ab += x * y;
        aa += x * x;
        bb += y * y;
    }
    ab / (aa.sqrt() * bb.sqrt()).max(1e-300)
}

fn main() -> anyhow::Result<()> {
    let args: Vec<String> = std::env::args().collect();
    anyhow::ensure!(
        args.len() >= 3,
        "usage: refine_probe RUN_DIR EXACT_MESH [BATCHES] [SCALES,...]"
    );
    let run = std::path::PathBuf::from(&args[1]);
    let exact = xscale::scene::mesh::load_mesh(std::path::Path::new(&args[2]))?.0;
    let batches: u64 = args.get(3).map_or(Ok(16), |s| s.parse())?;
    let scales: Vec<f32> = args
        .get(4)
        .map_or("0,64,256,1024,4096".into(), |s| s.clone())
        .split(',')
        .map(|s| s.parse())
        .collect::<Result<_, _>>()?;
    let st = TrainState::load(&run.join("checkpoint.safetensors"))?;
    let scene = xscale::run::run_dir::SceneFingerprint::read(&run)?
        .ok_or_else(|| anyhow::anyhow!("{}: no scene.json", run.display()))?
        .scene;
    let mut cfg = st.cfg.clone();
    cfg.model.refine.enabled = true;
    let prepared = prepare(&scene, &cfg, true, &mut |_| {})?;
    let norm = st.ckpt.normalization;
    let mesh = &prepared.scene.mesh;
    anyhow::ensure!(
        exact.vertices.len() == mesh.vertices.len(),
        "the exact mesh must have the proxy's vertices"
    );
    let geom = RefineGeom::new(mesh, &norm);
    // The correction gradient descent should make: θ* = −(proxy − exact)·m / s, so a helpful
    // gradient is ∝ (proxy − exact)·m.
    let err: Vec<f64> = (0..mesh.vertices.len())
        .map(|i| (mesh.vertices[i] - exact.vertices[i]).dot(geom.normals[i]) / geom.scale)
        .collect();
    let origins: Vec<DVec3> = prepared
        .train_views
        .iter()
        .map(|&i| prepared.scene.views[i].camera.center() - norm.center)
        .collect();
    let rcfg = xscale::model::refine::RefineConfig {
        levels: 6,
        base_resolution: 4,
        ..Default::default()
    };
    let nv = mesh.vertices.len();
    let all: Vec<u32> = (0..nv as u32).collect();
    let zeros = vec![0.0; nv];
    println!(
        "{} batches of {} pixels; cosine of dL/dθ with the true error (> 0: descent moves towards the truth)",
        batches, cfg.train.batch_pixels
    );
    print!("{:>10} {:>9}", "max scale", "vertices");
    for l in 0..rcfg.levels {
        print!(" {:>8}", format!("grid{}", rcfg.resolution(l)));
    }
    println!();
    for &sc in &scales {
        let mut d_theta = vec![0.0; nv];
        let mut touched = vec![false; nv];
        for b in 0..batches {
            let mut batch = sample_batch(
                &prepared.samples,
                &prepared.tracer,
                cfg.train.seed,
                1_000_000 + b,
                cfg.train.batch_pixels,
            );
            let views = batch.view.clone();
            let origin = |p: usize| origins[views[p] as usize];
            let hits = reintersect_batch(&geom, &zeros, &mut batch, &origin, 0.1);
            for h in &hits {
                for &k in &h.tri {
                    touched[k as usize] = true;
                }
            }
            let model = &st.ckpt.model;
            let fwd = model.forward(&st.ckpt.params, &batch)?;
            let mut grads = Grads::<f32>::new(&model.layout);
            grads.position_max_scale = (sc > 0.0).then_some(sc);
            model.backward(&st.ckpt.params, &batch, &fwd, &mut grads);
            hits_backward(&geom, &hits, &grads.positions, &mut d_theta);
        }
        let err_t: Vec<f64> = err
            .iter()
            .zip(&touched)
            .map(|(e, &t)| if t { *e } else { 0.0 })
            .collect();
        print!(
            "{:>10} {:>9.3}",
            if sc > 0.0 {
                format!("{sc}")
            } else {
                "all".into()
            },
            cosine(&d_theta, &err_t)
        );
        for l in 0..rcfg.levels as usize {
            let mut ga: Vec<Vec<f64>> = (0..rcfg.levels)
                .map(|k| vec![0.0; (rcfg.resolution(k) + 1).pow(3)])
                .collect();
            let mut gb = ga.clone();
            let mut dr = Vec::new();
            field_backward(
                &rcfg,
                &geom,
                &all,
                &d_theta,
                Active {
                    grids: l + 1,
                    residual: false,
                },
                &mut ga,
                &mut dr,
            );
            field_backward(
                &rcfg,
                &geom,
                &all,
                &err_t,
                Active {
                    grids: l + 1,
                    residual: false,
                },
                &mut gb,
                &mut dr,
            );
            print!(" {:>8.3}", cosine(&ga[l], &gb[l]));
        }
        println!();
    }
    Ok(())
}
