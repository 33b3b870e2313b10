//! Bench: a training step with the `cpu` preset's table sizes from the scene
//! (`log2_table_size = "auto"`) against fixed 2^19 tables (grid D at the preset's 2^17), on the
//! `small` and `cross` synthetic scenes (seed 1), 2 threads, at 4,096- and 16,384-pixel batches. Both models take
//! their warm-up steps (the loss must fall in each: a broken loop is not timed), then rounds of
//! `STEPS` steps alternate between them so the ratio holds on a machine whose speed drifts;
//! the best round of each is reported, with the parameters of each model.
//!
//! Run: `cargo bench --bench sizing` (`XSCALE_BENCH_STEPS`, `XSCALE_BENCH_ROUNDS`,
//! `XSCALE_BENCH_SCENES`: a comma-separated subset of `small,cross`).

mod common;
use common::{emit_json, env_count, synth_scene, warm_up};
use std::time::Instant;
use xscale::model::params::Grads;
use xscale::synth::Preset;
use xscale::train::config::{RunConfig, TableSize};
use xscale::train::sampler::sample_batch;
use xscale::train::setup::{prepare, Prepared};
use xscale::train::state::TrainState;

const WARMUP: u64 = 10;

/// A run of the `cpu` preset at `batch` pixels, its tables `auto` or fixed at 2^19.
fn state(prepared: &Prepared, batch: usize, auto: bool) -> (TrainState, Grads<f32>) {
    let mut cfg = RunConfig::preset("cpu").unwrap();
    cfg.train.batch_pixels = batch;
    if !auto {
        cfg.train.table_size = TableSize::Fixed;
        cfg.model.grid_h.log2_table_size = 19;
    }
    let mut st = TrainState::init(cfg, prepared, &mut |_| {}).unwrap();
    let mut g = Grads::new(&st.ckpt.model.layout);
    g.inputs = false;
    warm_up(&mut st, &mut g, prepared, batch, WARMUP);
    (st, g)
}

fn main() {
    let steps = env_count("XSCALE_BENCH_STEPS", 30) as u64;
    let rounds = env_count("XSCALE_BENCH_ROUNDS", 3);
    let scenes = std::env::var("XSCALE_BENCH_SCENES").unwrap_or_else(|_| "small,cross".into());
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(2)
        .build()
        .unwrap();
    let mut rows = Vec::new();
    for name in scenes.split(',').map(str::trim).filter(|n| !n.is_empty()) {
        let preset = match name {
            "small" => Preset::Small,
            "cross" => Preset::Cross,
            _ => panic!("XSCALE_BENCH_SCENES: {name}: expected small or cross"),
        };
        let dir = synth_scene(preset, name);
        let cfg = RunConfig::preset("cpu").unwrap();
        let prepared = prepare(&dir, &cfg, true, &mut |m| eprintln!("{m}")).unwrap();
        for batch in [4096usize, 16384] {
            let mut runs = pool.install(|| {
                [
                    state(&prepared, batch, false),
                    state(&prepared, batch, true),
                ]
            });
            let mut best = [f64::INFINITY; 2];
            for round in 0..rounds {
                for (i, (st, g)) in runs.iter_mut().enumerate() {
                    let t = pool.install(|| {
                        let t0 = Instant::now();
                        for _ in 0..steps {
                            let b = sample_batch(
                                &prepared.samples,
                                &prepared.tracer,
                                0,
                                st.step,
                                batch,
                            );
                            assert!(st.step(&b, g).unwrap().loss.is_finite());
                        }
                        t0.elapsed().as_secs_f64()
                    });
                    let ms = 1e3 * t / steps as f64;
                    eprintln!(
                        "{name}, batch {batch}, round {round}, {}: {ms:.1} ms/step",
                        ["fixed 2^19", "auto"][i]
                    );
                    best[i] = best[i].min(ms);
                }
            }
            let params = runs.each_ref().map(|(s, _)| s.ckpt.model.layout.total);
            println!(
                "{name}, batch {batch}: fixed 2^19 {:.1} ms/step ({} parameters), auto {:.1} ms/step ({} parameters), fixed / auto {:.2}x",
                best[0], params[0], best[1], params[1], best[0] / best[1]
            );
            rows.push(serde_json::json!({
                "scene": name, "batch": batch,
                "fixed_ms": best[0], "auto_ms": best[1], "fixed_over_auto": best[0] / best[1],
                "fixed_params": params[0], "auto_params": params[1],
            }));
        }
    }
    emit_json(serde_json::json!({ "steps": steps, "rounds": rounds, "threads": 2, "rows": rows }));
}
