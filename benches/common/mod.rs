//! Shared by the benches: environment knobs and the `small` synthetic scene (each bench uses
//! some of them).
#![allow(dead_code)]

use std::path::PathBuf;

/// `name` from the environment as a whole number, else `default` (unset or empty). A value that
/// is not a whole number stops the bench: a typo must not quietly measure the default.
pub fn env(name: &str, default: usize) -> usize {
    env_parse(name, default, "a whole number")
}

/// [`env`] for a count that must be at least 1 (steps, rounds, pixels, threads).
pub fn env_count(name: &str, default: usize) -> usize {
    let v = env_parse(name, default, "a whole number of at least 1");
    if v == 0 {
        panic!("{name}=0: expected a whole number of at least 1");
    }
    v
}

/// `name` parsed as `T`, else `default`; `what` names the expected form in the panic message.
pub fn env_parse<T: std::str::FromStr>(name: &str, default: T, what: &str) -> T {
    match std::env::var(name) {
        Ok(s) if !s.trim().is_empty() => s
            .trim()
            .parse()
            .unwrap_or_else(|_| panic!("{name}={s:?}: expected {what}")),
        Ok(_) | Err(std::env::VarError::NotPresent) => default,
        Err(e) => panic!("{name}: {e}"),
    }
}

/// `xscale synth --preset small --seed 1`, generated into `target/bench-scenes/small` on first use.
pub fn small_scene() -> PathBuf {
    synth_scene(xscale::synth::Preset::Small, "small")
}

/// `xscale synth --preset NAME --seed 1`, generated into `target/bench-scenes/NAME` on first use.
pub fn synth_scene(preset: xscale::synth::Preset, name: &str) -> PathBuf {
    let dir = PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("target/bench-scenes")
        .join(name);
    if !dir.join("scene.toml").is_file() {
        eprintln!("generating the {name} scene into {}", dir.display());
        let s = xscale::synth::build(preset, 1);
        let summary = s.summary();
        let images = s.render();
        xscale::synth::output::write(&s, &images, &summary, &dir, false).unwrap();
    }
    dir
}

/// When `XSCALE_BENCH_JSON` names a file, write `value` (the bench's results, validated before they
/// were timed) there as JSON: `cargo run --release --example results` reads it into
/// `docs/results/<section>.json`. Without the variable nothing is written.
pub fn emit_json(value: serde_json::Value) {
    if let Ok(path) = std::env::var("XSCALE_BENCH_JSON") {
        if !path.trim().is_empty() {
            std::fs::write(&path, serde_json::to_string_pretty(&value).unwrap())
                .unwrap_or_else(|e| panic!("XSCALE_BENCH_JSON={path}: {e}"));
        }
    }
}

/// `steps` training steps of `state` on `batch`-pixel batches of `prepared`, checking that the
/// loss stays finite and falls over them (a broken loop is not timed).
pub fn warm_up(
    state: &mut xscale::train::state::TrainState,
    grads: &mut xscale::model::params::Grads<f32>,
    prepared: &xscale::train::setup::Prepared,
    batch: usize,
    steps: u64,
) {
    let mut first = None;
    let mut last = 0.0;
    for _ in 0..steps {
        let b = xscale::train::sampler::sample_batch(
            &prepared.samples,
            &prepared.tracer,
            0,
            state.step,
            batch,
        );
        let st = state.step(&b, grads).unwrap();
        assert!(st.loss.is_finite(), "loss is not finite");
        first.get_or_insert(st.loss);
        last = st.loss;
    }
    assert!(
        last < first.unwrap(),
        "the loss did not fall over the warm-up ({} -> {last})",
        first.unwrap()
    );
}
