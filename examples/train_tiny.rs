//! The library without the CLI: load a scene, build the model, run the training loop by hand,
//! score the held-out views, and save a checkpoint that `xscale eval --checkpoint` reads.
//!
//!     cargo run --release --example train_tiny [SCENE_DIR] [STEPS]
//!
//! (default `fixtures/tiny`, 300 steps; about a second). `xscale train` does the same plus
//! progress, metrics, periodic evaluation, checkpoints and resume (`src/run/trainer.rs`).

use anyhow::Result;
use std::path::Path;
use xscale::eval::protocol::mean_score;
use xscale::model::params::Grads;
use xscale::run::trainer::evaluate;
use xscale::train::config::RunConfig;
use xscale::train::sampler::sample_batch;
use xscale::train::setup::prepare;
use xscale::train::state::TrainState;

/// What a run of the example reached.
#[allow(dead_code)] // the fields are read by tests/example_train_tiny.rs
pub struct Outcome {
    pub first_loss: f64,
    pub last_loss: f64,
    pub psnr_masked: f64,
    pub state: TrainState,
}

/// Train the `tiny` preset on `scene` for `steps` steps and score its held-out views.
pub fn run(scene: &Path, steps: u64, log: bool) -> Result<Outcome> {
    // 1. The configuration: a preset (docs/spec.md §9); any field can be changed here.
    let mut cfg = RunConfig::preset("tiny")?;
    cfg.train.steps = steps;
    // 2. The scene, the BVH and the training pixels that see the mesh (rays are cast per batch).
    let prepared = prepare(scene, &cfg, true, &mut |m| {
        if log {
            eprintln!("{m}")
        }
    })?;
    // 3. Settings that follow the scene (grid H's level range), then the initial parameters.
    let mut state = TrainState::init(cfg, &prepared, &mut |_| {})?;
    let mut grads = Grads::new(&state.ckpt.model.layout);
    grads.inputs = false; // positions and directions are data, not parameters
                          // 4. The loop: batch k is a pure function of (seed, k); one step = forward, backward, Adam.
    let tc = state.cfg.train.clone();
    let (mut first_loss, mut last_loss) = (f64::NAN, f64::NAN);
    while state.step < tc.steps {
        let batch = sample_batch(
            &prepared.samples,
            &prepared.tracer,
            tc.seed,
            state.step,
            tc.batch_pixels,
        );
        let st = state.step(&batch, &mut grads)?;
        anyhow::ensure!(st.loss.is_finite(), "step {}: loss {}", state.step, st.loss);
        if first_loss.is_nan() {
            first_loss = st.loss;
        }
        last_loss = st.loss;
    }
    // 5. Score the held-out views (docs/spec.md §7); `Some(dir)` would also write renders.
    let scores = evaluate(&state, &prepared, 0, None)?;
    let mean = mean_score(&scores);
    if log {
        eprintln!(
            "{} steps: loss {first_loss:.4} -> {last_loss:.4}; held-out masked PSNR {:.2} dB, SSIM {:.4} on {} views",
            state.step,
            mean.psnr_masked,
            mean.ssim_masked,
            scores.len()
        );
    }
    Ok(Outcome {
        first_loss,
        last_loss,
        psnr_masked: mean.psnr_masked,
        state,
    })
}

#[allow(dead_code)] // not called when the tests include this file
fn main() -> Result<()> {
    let args: Vec<String> = std::env::args().collect();
    let scene = args.get(1).map_or("fixtures/tiny", |s| s.as_str());
    let steps = args.get(2).map_or(Ok(300), |s| s.parse())?;
    let out = run(Path::new(scene), steps, true)?;
    // 6. A checkpoint like `xscale train`'s: the model (config, parameters, step) and, beside it
    //    in `xscale-example-tiny.optimizer.safetensors`, the Adam state a resume needs.
    let path = std::env::temp_dir().join("xscale-example-tiny.safetensors");
    out.state.save(&path)?;
    eprintln!("checkpoint: {}", path.display());
    Ok(())
}
