//! Does the photo-consistency gradient point at the true surface, and how large is it on the exact
//! mesh? (docs/geometry.md §4)
//!
//! Sums the photo term's ∂E/∂θ (`src/refine/photo_term.rs`) over `STEPS` steps with the mesh unmoved, at one
//! image level, on a displaced proxy of a synthetic scene whose true error is known vertex by
//! vertex (as `refine_probe`), and prints per grid level of the offset field: the cosine between
//! the summed gradient and the true error (> 0: descent moves towards the truth), the RMS of the
//! summed gradient over the nodes it touches, and what a diagonal Gauss–Newton step −G/H would do
//! (its least-squares slope against the node's true error: 1 = the step removes the error; and
//! the correlation). No model is needed.
//!
//! ```text
//! cargo run --release --example photo_probe -- SCENE MESH EXACT_MESH STEPS LEVEL ['key = value' ...]
//! ```
//! The optional arguments are `[model.refine]` keys (`photo_patch = 3`, `photo_measure = "huber"` …).

use xscale::refine::field::{field_backward, Active, RefineGeom};

use xscale::model::refine::RefineConfig;
use xscale::refine::photo_term::{accumulate, PhotoTerm};
use xscale::train::config::RunConfig;
use xscale::train::sampler::Samples;
use xscale::train::setup::prepare;

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
    let a: Vec<String> = std::env::args().collect();
    anyhow::ensure!(
        a.len() >= 6,
        "usage: photo_probe SCENE MESH EXACT_MESH STEPS LEVEL ['key = value' ...]"
    );
    let scene = std::path::PathBuf::from(&a[1]);
    let mesh_path = std::path::PathBuf::from(&a[2]);
    let exact = xscale::scene::mesh::load_mesh(std::path::Path::new(&a[3]))?.0;
    let steps: u64 = a[4].parse()?;
    let level: u32 = a[5].parse()?;
    let mut text = String::from("enabled = true\nphoto = 1.0\nfeatures = 0.0\n");
    text.push_str(&format!(
        "photo_levels = [{level}, {level}]\nphoto_reach = 0\n"
    ));
    for kv in &a[6..] {
        text.push_str(kv);
        text.push('\n');
    }
    let rcfg: RefineConfig = toml::from_str(&text)?;
    rcfg.validate()?;
    let mut cfg = RunConfig::preset("cpu")?;
    cfg.train.mesh = Some(mesh_path);
    cfg.model.refine = rcfg.clone();
    cfg.validate()?;
    let prepared = prepare(&scene, &cfg, true, &mut |m| eprintln!("{m}"))?;
    let Samples::Stream(stream) = &prepared.samples else {
        anyhow::bail!("streamed samples expected");
    };
    let norm = prepared.scene.normalization;
    let mesh = &prepared.scene.mesh;
    anyhow::ensure!(exact.vertices.len() == mesh.vertices.len());
    let geom = RefineGeom::new(mesh, &norm);
    let t0 = std::time::Instant::now();
    let term = PhotoTerm::new(
        stream,
        &prepared.tracer,
        norm.center,
        &rcfg,
        &prepared.train_names(),
        (0, 1),
    )?;
    eprintln!("photo term set up in {:.2} s", t0.elapsed().as_secs_f64());
    for v in &term.views {
        let nb: Vec<usize> = v.neighbours.iter().map(|&j| term.views[j].row).collect();
        eprintln!("view row {}: neighbours {:?}", v.row, nb);
    }
    // θ* = −(proxy − exact)·m / s.
    let err: Vec<f64> = (0..mesh.vertices.len())
        .map(|i| (mesh.vertices[i] - exact.vertices[i]).dot(geom.normals[i]) / geom.scale)
        .collect();
    let nv = mesh.vertices.len();
    let theta = vec![0.0; nv];
    let levels = 6u32;
    let fcfg = RefineConfig {
        levels,
        base_resolution: 4,
        ..rcfg.clone()
    };
    let mut d_theta = vec![0.0; nv];
    let mut touched = vec![false; nv];
    let mut curv = vec![0.0; nv];
    let (mut drawn, mut valid, mut energy) = (0u64, 0u64, 0.0);
    let t1 = std::time::Instant::now();
    for k in 0..steps {
        let patches = term.draw(stream, &prepared.tracer, cfg.train.seed, k);
        let evals = term.evaluate(&geom, &theta, &patches);
        for e in evals.iter().flatten() {
            for &(v, _) in &e.grad {
                touched[v as usize] = true;
            }
        }
        let st = accumulate(&evals, &mut d_theta, Some(&mut curv));
        drawn += st.drawn;
        valid += st.valid;
        energy += st.energy;
    }
    let w = rcfg.photo / rcfg.photo_pixels as f64;
    println!(
        "{steps} steps at level {level}: {valid} of {drawn} patches valid, mean rho {:.4}, {:.2} s",
        energy / valid.max(1) as f64 / w,
        t1.elapsed().as_secs_f64()
    );
    let all: Vec<u32> = (0..nv as u32).collect();
    let err_t: Vec<f64> = err
        .iter()
        .zip(&touched)
        .map(|(e, &t)| if t { *e } else { 0.0 })
        .collect();
    let ones: Vec<f64> = touched.iter().map(|&t| t as u8 as f64).collect();
    println!(
        "per vertex: cosine {:.3}, touched {}",
        cosine(&d_theta, &err_t),
        touched.iter().filter(|&&t| t).count()
    );
    println!(
        "{:>6} {:>8} {:>10} {:>8} | GN over nodes with H >= 1e-2, 1e-3, 1e-4 max: nodes, slope, corr, RMS step (m)",
        "cells", "cosine", "grad RMS", "nodes"
    );
    for l in 0..levels as usize {
        let mk = || -> Vec<Vec<f64>> {
            (0..levels)
                .map(|k| vec![0.0; (fcfg.resolution(k) + 1).pow(3)])
                .collect()
        };
        let (mut ga, mut gb, mut gw, mut gh) = (mk(), mk(), mk(), mk());
        let mut dr = Vec::new();
        field_backward(
            &fcfg,
            &geom,
            &all,
            &curv,
            Active {
                grids: l + 1,
                residual: false,
            },
            &mut gh,
            &mut dr,
        );
        let hess = &gh;
        field_backward(
            &fcfg,
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
            &fcfg,
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
        field_backward(
            &fcfg,
            &geom,
            &all,
            &ones,
            Active {
                grids: l + 1,
                residual: false,
            },
            &mut gw,
            &mut dr,
        );
        let nodes: Vec<usize> = (0..ga[l].len()).filter(|&i| ga[l][i] != 0.0).collect();
        let rms = (nodes.iter().map(|&i| ga[l][i].powi(2)).sum::<f64>()
            / nodes.len().max(1) as f64)
            .sqrt();
        // GN step per node against the node's mean true error (θ units), for nodes whose
        // curvature is at least 1e-2, 1e-3, 1e-4 of the largest.
        let hmax = hess[l].iter().cloned().fold(0.0, f64::max);
        let mut gn = String::new();
        for frac in [1e-2, 1e-3, 1e-4] {
            let (mut sxy, mut sxx, mut syy, mut n) = (0.0, 0.0, 0.0, 0usize);
            for &i in &nodes {
                let h = hess[l][i];
                if h < frac * hmax || gw[l][i] <= 0.0 {
                    continue;
                }
                let step = -ga[l][i] / h;
                let e = -gb[l][i] / gw[l][i];
                sxy += step * e;
                sxx += e * e;
                syy += step * step;
                n += 1;
            }
            gn.push_str(&format!(
                " {:>6} {:>7.3} {:>7.3} {:>9.2e} |",
                n,
                sxy / sxx.max(1e-300),
                sxy / (sxx * syy).sqrt().max(1e-300),
                (syy / n.max(1) as f64).sqrt() * geom.scale
            ));
        }
        println!(
            "{:>6} {:>8.3} {:>10.3e} {:>8} |{gn}",
            fcfg.resolution(l as u32),
            cosine(&ga[l], &gb[l]),
            rms,
            nodes.len(),
        );
    }
    Ok(())
}
