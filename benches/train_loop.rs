//! Bench: the whole training loop at the `cpu` preset on the `small` synthetic scene (setup
//! excluded): pixels per second with 1 and 2 threads, and where each step's time goes (batch
//! drawing with its ray casting, forward, backward, Adam, gradient zeroing).
//!
//! The scene is generated into `target/bench-scenes/small` on first use (`xscale synth --preset
//! small --seed 1`, ~5 s). The run is configured exactly as `xscale train --preset cpu` would run
//! it (automatic level range and level dropping resolved from the scene), then `WARMUP` steps are
//! taken and discarded, then `STEPS` steps are timed, alternating 1 and 2 threads in rounds so the
//! ratio holds on a machine whose speed drifts. Before timing, the bench checks that the loss is
//! finite and falls over the warm-up (a broken loop is not timed).
//!
//! Run: `cargo bench --bench train_loop` (`XSCALE_BENCH_BATCH=16384` for larger batches,
//! `XSCALE_BENCH_STEPS`, `XSCALE_BENCH_ROUNDS`, `XSCALE_BENCH_SAMPLES=stream|cache` instead of the
//! default `auto`, which takes the sample cache on `small`).

mod common;
use common::{emit_json, env_count, small_scene as scene, warm_up};
use std::time::Instant;
use xscale::model::params::Grads;
use xscale::train::config::RunConfig;
use xscale::train::sampler::{sample_batch, SampleMode};
use xscale::train::setup::prepare;
use xscale::train::state::TrainState;

#[derive(Default, Clone, Copy)]
struct Phases {
    batch: f64,
    forward: f64,
    backward: f64,
    adam: f64,
    zero: f64,
    total: f64,
}

fn main() {
    let batch = env_count("XSCALE_BENCH_BATCH", 4096);
    let steps = env_count("XSCALE_BENCH_STEPS", 60) as u64;
    let rounds = env_count("XSCALE_BENCH_ROUNDS", 3);
    const WARMUP: u64 = 20;
    let dir = scene();
    let mut cfg = RunConfig::preset("cpu").unwrap();
    cfg.train.batch_pixels = batch;
    // `train.samples` as a run has it (`auto`: the cache on `small`), or as the variable says.
    match std::env::var("XSCALE_BENCH_SAMPLES").as_deref() {
        Ok("stream") => cfg.train.samples = SampleMode::Stream,
        Ok("cache") => cfg.train.samples = SampleMode::Cache,
        Ok(v) => panic!("XSCALE_BENCH_SAMPLES={v}: expected stream or cache"),
        Err(_) => {}
    }
    let prepared = prepare(&dir, &cfg, true, &mut |m| eprintln!("{m}")).unwrap();
    let mut state = TrainState::init(cfg, &prepared, &mut |m| eprintln!("{m}")).unwrap();
    let mut grads = Grads::new(&state.ckpt.model.layout);
    grads.inputs = false;
    // Warm-up, and the check that the loop learns.
    warm_up(&mut state, &mut grads, &prepared, batch, WARMUP);
    {
        // What a step touches (for reading the Adam column).
        let b = sample_batch(&prepared.samples, &prepared.tracer, 0, 999_999, batch);
        let mut g = Grads::new(&state.ckpt.model.layout);
        g.inputs = false;
        state
            .ckpt
            .model
            .loss_and_grad(&state.ckpt.params, &b, &mut g)
            .unwrap();
        eprintln!(
            "one step touches {} grid-H entries ({} features) and {} grid-D entries; {} parameters in all",
            g.touched_h.entries.len(),
            state.cfg.model.grid_h.features,
            g.touched_d.entries.len(),
            state.ckpt.model.layout.total
        );
    }
    let pools: Vec<(usize, rayon::ThreadPool)> = [1usize, 2]
        .iter()
        .map(|&t| {
            (
                t,
                rayon::ThreadPoolBuilder::new()
                    .num_threads(t)
                    .build()
                    .unwrap(),
            )
        })
        .collect();
    let mut best = [Phases::default(); 2];
    for round in 0..rounds {
        for (pi, (threads, pool)) in pools.iter().enumerate() {
            let mut ph = Phases::default();
            pool.install(|| {
                let t0 = Instant::now();
                for _ in 0..steps {
                    let tb = Instant::now();
                    let b = sample_batch(&prepared.samples, &prepared.tracer, 0, state.step, batch);
                    ph.batch += tb.elapsed().as_secs_f64();
                    let st = state.step(&b, &mut grads).unwrap();
                    assert!(st.loss.is_finite());
                    ph.forward += st.timing.forward;
                    ph.backward += st.timing.backward;
                    ph.adam += st.timing.adam;
                    ph.zero += st.timing.zero;
                }
                ph.total = t0.elapsed().as_secs_f64();
            });
            let px = (steps as usize * batch) as f64 / ph.total;
            eprintln!(
                "round {round}, {threads} thread(s): {px:.0} px/s ({:.1} ms/step)",
                1e3 * ph.total / steps as f64
            );
            if best[pi].total == 0.0 || ph.total < best[pi].total {
                best[pi] = ph;
            }
        }
    }
    println!(
        "train loop, cpu preset, small scene, batch {batch} px (γ=2), best of {rounds} rounds of {steps} steps"
    );
    println!(
        "{:>8} {:>10} {:>9} {:>8} {:>8} {:>8} {:>8} {:>8}",
        "threads", "px/s", "ms/step", "batch", "forward", "backward", "adam", "zero"
    );
    for (pi, (threads, _)) in pools.iter().enumerate() {
        let p = best[pi];
        let ms = |x: f64| 1e3 * x / steps as f64;
        println!(
            "{:>8} {:>10.0} {:>9.2} {:>8.2} {:>8.2} {:>8.2} {:>8.2} {:>8.2}",
            threads,
            (steps as usize * batch) as f64 / p.total,
            ms(p.total),
            ms(p.batch),
            ms(p.forward),
            ms(p.backward),
            ms(p.adam),
            ms(p.zero)
        );
    }
    println!(
        "2 threads / 1 thread: {:.2}x",
        best[0].total / best[1].total
    );
    let ms = |x: f64| 1e3 * x / steps as f64;
    emit_json(serde_json::json!({
        "batch": batch, "rounds": rounds, "steps": steps,
        "levels": state.cfg.model.grid_h.levels,
        "rows": pools.iter().enumerate().map(|(pi, (threads, _))| {
            let p = best[pi];
            serde_json::json!({
                "threads": threads,
                "pixels_per_s": (steps as usize * batch) as f64 / p.total,
                "ms_per_step": ms(p.total), "batch_ms": ms(p.batch), "forward_ms": ms(p.forward),
                "backward_ms": ms(p.backward), "adam_ms": ms(p.adam), "zero_ms": ms(p.zero),
            })
        }).collect::<Vec<_>>(),
        "two_over_one": best[0].total / best[1].total,
    }));
}
