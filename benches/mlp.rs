//! ns per pixel of (1) the shader MLP forward+backward at the `cpu` preset (52 → 64 → 64 → 3,
//! f32, no bias) and (2) the whole pipeline forward+backward at the `cpu` preset (γ = 2, 20 %
//! invalid sub-samples, ξ and appearance codes on), with 1 and 2 threads. Outputs are validated
//! before timing. Run: `cargo bench --bench mlp` (XSCALE_BENCH_PIXELS overrides the 16,384 pixels).

// Index loops mirror the formulas (i over entries, c over channels).
#![allow(clippy::needless_range_loop)]

mod common;
use common::env_count;
use rayon::prelude::*;
use std::time::Instant;
use xscale::model::mlp::{Mlp, MlpActs};
use xscale::model::params::{Grads, Group};
use xscale::model::{Batch, Hfm, ModelConfig};
use xscale::rng::{uniform_f32, Purpose};

const CHUNK: usize = 128;

fn shader_pass(mlp: &Mlp, p: &[f32], x: &[f32], n: usize) -> Vec<f32> {
    let din = mlp.in_dim();
    let wt = mlp.transpose_weights(p);
    let parts: Vec<Vec<f32>> = (0..n.div_ceil(CHUNK))
        .into_par_iter()
        .map(|c| {
            let rows = CHUNK.min(n - c * CHUNK);
            let xs = &x[c * CHUNK * din..(c * CHUNK + rows) * din];
            let mut acts = MlpActs::default();
            mlp.forward(p, &wt, xs, rows, &mut acts);
            let d_out = acts.out.iter().map(|v| v * 1e-3).collect();
            let mut dp = vec![0.0f32; mlp.n_params];
            let mut dx = vec![0.0f32; rows * din];
            mlp.backward(p, xs, rows, &acts, d_out, &mut dp, Some(&mut dx));
            dp
        })
        .collect();
    let mut g = vec![0.0f32; mlp.n_params];
    for part in &parts {
        for (a, b) in g.iter_mut().zip(part) {
            *a += b;
        }
    }
    g
}

/// Process CPU time (user + system) in seconds, from /proc/self/stat (Linux; 0 elsewhere).
/// Reported next to wall time because the machines this runs on are often shared.
fn cpu_seconds() -> f64 {
    let Ok(s) = std::fs::read_to_string("/proc/self/stat") else {
        return 0.0;
    };
    let rest = &s[s.rfind(')').map_or(0, |i| i + 2)..];
    let f: Vec<&str> = rest.split_whitespace().collect();
    let ticks: f64 = f[11].parse::<f64>().unwrap_or(0.0) + f[12].parse::<f64>().unwrap_or(0.0);
    ticks / 100.0 // USER_HZ is 100 on Linux
}

/// (wall seconds, CPU seconds) per repetition.
fn time<F: FnMut()>(reps: usize, mut f: F) -> (f64, f64) {
    f(); // warm-up
    let c = cpu_seconds();
    let t = Instant::now();
    for _ in 0..reps {
        f();
    }
    (
        t.elapsed().as_secs_f64() / reps as f64,
        (cpu_seconds() - c) / reps as f64,
    )
}

fn main() {
    let n = env_count("XSCALE_BENCH_PIXELS", 16_384);
    let cfg = {
        let mut c = ModelConfig::cpu();
        c.appearance_views = 8;
        // Every level of every pixel (random batches carry no footprints; SPEC §4.10).
        c.level_weight = xscale::model::config::LevelWeight::None;
        c
    };
    // (1) Shader MLP.
    let din = (cfg.grid_h.levels * cfg.grid_h.features) as usize + 16 + cfg.appearance_dim as usize;
    let mlp = Mlp::new(&[din, 64, 64, 3], false);
    assert_eq!(din, 52);
    let p: Vec<f32> = mlp.init(1, &[0, 1, 2], false);
    let x: Vec<f32> = (0..n * din)
        .map(|i| uniform_f32(2, Purpose::Test, 0, i as u64) - 0.5)
        .collect();
    // Validate: forward rows against an f64 naive evaluation, gradients finite and non-zero.
    {
        let mut acts = MlpActs::default();
        mlp.forward(&p, &mlp.transpose_weights(&p), &x[..4 * din], 4, &mut acts);
        for m in 0..4 {
            let mut h = x[m * din..(m + 1) * din]
                .iter()
                .map(|&v| v as f64)
                .collect::<Vec<_>>();
            for (k, l) in mlp.layers.iter().enumerate() {
                let mut y = vec![0.0f64; l.out_dim];
                for (o, yo) in y.iter_mut().enumerate() {
                    for (i, hi) in h.iter().enumerate() {
                        *yo += p[l.w_off + o * l.in_dim + i] as f64 * hi;
                    }
                    if k + 1 < mlp.layers.len() {
                        *yo = yo.max(0.0);
                    }
                }
                h = y;
            }
            for o in 0..3 {
                assert!(
                    (h[o] - acts.out[m * 3 + o] as f64).abs() < 1e-5,
                    "shader forward mismatch"
                );
            }
        }
        let g = shader_pass(&mlp, &p, &x, n);
        assert!(g.iter().all(|v| v.is_finite()) && g.iter().any(|&v| v != 0.0));
    }
    // (2) Whole pipeline.
    let model = Hfm::new(&cfg).unwrap();
    let mut params = model.init_params(3);
    let r = model.layout.group_range(Group::Appearance).unwrap();
    for (e, v) in params[r].iter_mut().enumerate() {
        *v = uniform_f32(5, Purpose::Test, 0, e as u64) - 0.5;
    }
    let batch = Batch::random(11, n, 4, 8, 0.2);
    let mut grads = Grads::<f32>::new(&model.layout);
    let loss = model.loss_and_grad(&params, &batch, &mut grads).unwrap();
    assert!(loss.is_finite() && loss > 0.0);
    assert!(grads.params.iter().all(|v| v.is_finite()));
    assert!(grads.positions.iter().any(|&v| v != 0.0));
    let (fh, fd) = model.grid_features();

    println!("cpu preset, {n} pixels, γ = 2 (20% invalid sub-samples), f32");
    let mut base = (0.0, 0.0);
    let load = std::fs::read_to_string("/proc/loadavg").unwrap_or_default();
    println!(
        "load average at start: {}",
        load.split_whitespace()
            .take(3)
            .collect::<Vec<_>>()
            .join(" ")
    );
    for threads in [1usize, 2] {
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .unwrap();
        let t_mlp = pool.install(|| {
            time(5, || {
                std::hint::black_box(shader_pass(&mlp, &p, &x, n));
            })
        });
        let t_pipe = pool.install(|| {
            time(3, || {
                grads.zero_sparse(&model.layout, fh, fd);
                std::hint::black_box(model.loss_and_grad(&params, &batch, &mut grads).unwrap());
            })
        });
        // As training runs it: no input-position / direction gradients.
        let mut train_grads = Grads::<f32>::new(&model.layout);
        train_grads.inputs = false;
        let t_train = pool.install(|| {
            time(3, || {
                train_grads.zero_sparse(&model.layout, fh, fd);
                std::hint::black_box(
                    model
                        .loss_and_grad(&params, &batch, &mut train_grads)
                        .unwrap(),
                );
            })
        });
        if threads == 1 {
            base = (t_mlp.0, t_pipe.0);
        }
        println!(
            "threads {threads}: training step fwd+bwd (no input gradients) {:8.1} ns/pixel wall ({:8.1} CPU-ns)",
            t_train.0 / n as f64 * 1e9,
            t_train.1 / n as f64 * 1e9
        );
        let ns = |t: f64| t / n as f64 * 1e9;
        println!(
            "threads {threads}: shader MLP fwd+bwd {:8.1} ns/pixel wall ({:8.1} CPU-ns, speed-up ×{:.2}) | \
             pipeline fwd+bwd {:8.1} ns/pixel wall ({:8.1} CPU-ns, speed-up ×{:.2})",
            ns(t_mlp.0),
            ns(t_mlp.1),
            base.0 / t_mlp.0,
            ns(t_pipe.0),
            ns(t_pipe.1),
            base.1 / t_pipe.0
        );
    }
}
