//! Bench: what each skip of SPEC §8 (and each switch that removes work) saves per training step,
//! on the `small` synthetic scene at the `cpu` preset (2 threads, 4,096-pixel batches).
//!
//! Every line is the default `cpu` run with one thing changed:
//! - `no level dropping`: hash levels finer than any training footprint kept (`drop_fine_levels = false`);
//! - `no level weighting`: every pixel reads and writes every level (`level_weight = "none"`; with
//!   the weighting, levels whose weight is 0 for a pixel are skipped in forward and backward);
//! - `fixed level range`: the preset's 16 levels up to 2048 cells instead of the automatic range;
//! - `no deformation`, `γ = 1`: the model without ξ, without multisampling;
//! - `invalid sub-samples evaluated`: not a switch of the model (invalid sub-samples are compacted
//!   away before the grids run); measured as the cost of evaluating that many more sub-samples,
//!   i.e. the same batch with every sub-sample marked valid at its pixel's first valid position;
//! - `rays cast per batch`: `samples = "stream"` instead of the sample cache `auto` takes on
//!   `small` (the batch's γ² rays per pixel cast when it is drawn; same batches).
//!
//! Steps are timed in alternating rounds (each configuration once per round, best of rounds) after
//! a warm-up that must lower the loss (a broken configuration is not timed).
//!
//! Run: `cargo bench --bench skips` (`XSCALE_BENCH_STEPS`, `XSCALE_BENCH_ROUNDS`).

mod common;
use common::{emit_json, env_count, small_scene as scene};
use std::time::Instant;
use xscale::model::config::LevelWeight;
use xscale::model::params::Grads;
use xscale::model::Batch;
use xscale::train::config::{LevelRange, RunConfig};
use xscale::train::sampler::sample_batch;
use xscale::train::setup::{prepare, Prepared};
use xscale::train::state::TrainState;

struct Variant {
    name: &'static str,
    state: TrainState,
    prepared: Prepared,
    grads: Grads<f32>,
    fill_invalid: bool,
    best: f64,
    samples: usize,
}

/// Every sub-sample valid: an invalid one takes its pixel's first valid position (so it is
/// evaluated like a real one, at a place the grids know; the footprint is per pixel).
fn fill_invalid(b: &mut Batch) {
    let s = b.samples_per_pixel();
    for p in 0..b.n_pixels() {
        let Some(first) = (0..s).find(|&k| b.valid[p * s + k] != 0) else {
            continue;
        };
        for k in 0..s {
            if b.valid[p * s + k] == 0 {
                b.positions[p * s + k] = b.positions[p * s + first];
                b.valid[p * s + k] = 1;
            }
        }
    }
}

fn main() {
    let steps = env_count("XSCALE_BENCH_STEPS", 40) as u64;
    let rounds = env_count("XSCALE_BENCH_ROUNDS", 3);
    const WARMUP: u64 = 15;
    let dir = scene();
    type Edit = fn(&mut RunConfig);
    let edits: [(&str, Edit, bool); 8] = [
        ("cpu (default)", |_| {}, false),
        (
            "no level dropping",
            |c| c.train.drop_fine_levels = false,
            false,
        ),
        (
            "no level weighting",
            |c| c.model.level_weight = LevelWeight::None,
            false,
        ),
        (
            "fixed level range",
            |c| c.train.level_range = LevelRange::Fixed,
            false,
        ),
        ("no deformation", |c| c.model.deform.enabled = false, false),
        ("gamma = 1", |c| c.model.gamma = 1, false),
        ("invalid sub-samples evaluated", |_| {}, true),
        (
            "rays cast per batch",
            |c| c.train.samples = xscale::train::sampler::SampleMode::Stream,
            false,
        ),
    ];
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(2)
        .build()
        .unwrap();
    let mut vs: Vec<Variant> = pool.install(|| {
        edits
            .iter()
            .map(|(name, edit, fill)| {
                let mut cfg = RunConfig::preset("cpu").unwrap();
                edit(&mut cfg);
                let prepared = prepare(&dir, &cfg, true, &mut |_| {}).unwrap();
                let mut state = TrainState::init(cfg, &prepared, &mut |_| {}).unwrap();
                let mut grads = Grads::new(&state.ckpt.model.layout);
                grads.inputs = false;
                let (mut first, mut last) = (None, 0.0);
                for _ in 0..WARMUP {
                    let mut b =
                        sample_batch(&prepared.samples, &prepared.tracer, 0, state.step, 4096);
                    if *fill {
                        fill_invalid(&mut b);
                    }
                    let st = state.step(&b, &mut grads).unwrap();
                    assert!(st.loss.is_finite(), "{name}: loss {}", st.loss);
                    first.get_or_insert(st.loss);
                    last = st.loss;
                }
                assert!(
                    last < first.unwrap(),
                    "{name}: the loss did not fall in the warm-up"
                );
                Variant {
                    name,
                    state,
                    prepared,
                    grads,
                    fill_invalid: *fill,
                    best: f64::INFINITY,
                    samples: 0,
                }
            })
            .collect()
    });
    for round in 0..rounds {
        for v in vs.iter_mut() {
            let (t, n) = pool.install(|| {
                let mut n = 0usize;
                let t0 = Instant::now();
                for _ in 0..steps {
                    let mut b = sample_batch(
                        &v.prepared.samples,
                        &v.prepared.tracer,
                        0,
                        v.state.step,
                        4096,
                    );
                    if v.fill_invalid {
                        fill_invalid(&mut b);
                    }
                    let st = v.state.step(&b, &mut v.grads).unwrap();
                    assert!(st.loss.is_finite());
                    n += st.samples;
                }
                (t0.elapsed().as_secs_f64(), n)
            });
            eprintln!(
                "round {round}: {:<30} {:.1} ms/step",
                v.name,
                1e3 * t / steps as f64
            );
            if t < v.best {
                v.best = t;
                v.samples = n / steps as usize;
            }
        }
    }
    let base = vs[0].best;
    println!(
        "skips on the small scene, cpu preset, 4096-pixel batches, 2 threads, best of {rounds} rounds of {steps} steps (batch drawing included)"
    );
    println!(
        "{:<30} {:>9} {:>10} {:>12} {:>8}",
        "configuration", "ms/step", "vs cpu", "sub-samples", "levels"
    );
    for v in &vs {
        println!(
            "{:<30} {:>9.2} {:>9.2}x {:>12} {:>8}",
            v.name,
            1e3 * v.best / steps as f64,
            v.best / base,
            v.samples,
            v.state.cfg.model.grid_h.levels
        );
    }
    emit_json(serde_json::json!({
        "rounds": rounds, "steps": steps, "batch": 4096, "threads": 2,
        "rows": vs.iter().map(|v| serde_json::json!({
            "configuration": v.name,
            "ms_per_step": 1e3 * v.best / steps as f64,
            "vs_default": v.best / base,
            "sub_samples": v.samples,
            "levels": v.state.cfg.model.grid_h.levels,
        })).collect::<Vec<_>>(),
    }));
}
