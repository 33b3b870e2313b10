//! Try mesh-refinement settings quickly: continue a finished run for `STEPS` more steps with
//! `[model.refine]` switched on from the first of them (moving for `MOVE` steps), then score the
//! held-out views. The run folder is not touched. With `XSCALE_REFINE_LOG=FILE` (and
//! `XSCALE_REFINE_TRUTH=MESH`) every offset update is logged (docs/geometry.md).
//!
//! ```text
//! cargo run --release --example refine_tune -- RUN_DIR REFINE.toml STEPS MOVE [OUT.ply]
//! ```
//! `REFINE.toml` holds `[model.refine]` keys at top level (`lr = 1e-4` …); `enabled`, `start` and
//! `stop` are set from STEPS and MOVE.

use xscale::model::params::Grads;
use xscale::model::refine::{RefineConfig, RefineParams};
use xscale::refine::refiner::Refiner;
use xscale::run::trainer::evaluate;
use xscale::train::adam::AdamState;
use xscale::train::setup::prepare;
use xscale::train::state::TrainState;

fn main() -> anyhow::Result<()> {
    let a: Vec<String> = std::env::args().collect();
    anyhow::ensure!(
        a.len() >= 5,
        "usage: refine_tune RUN_DIR REFINE.toml STEPS MOVE [OUT.ply]"
    );
    let run = std::path::PathBuf::from(&a[1]);
    let mut rcfg: RefineConfig = toml::from_str(&std::fs::read_to_string(&a[2])?)?;
    let (steps, moving): (u64, u64) = (a[3].parse()?, a[4].parse()?);
    let mut st = TrainState::load(&run.join("checkpoint.safetensors"))?;
    let scene = xscale::run::run_dir::SceneFingerprint::read(&run)?
        .ok_or_else(|| anyhow::anyhow!("{}: no scene.json", run.display()))?
        .scene;
    let k0 = st.step;
    let total = k0 + steps;
    rcfg.enabled = true;
    rcfg.start = k0 as f64 / total as f64;
    rcfg.stop = (k0 + moving) as f64 / total as f64;
    rcfg.validate()?;
    st.cfg.train.steps = total;
    st.cfg.train.eval_every = 0;
    st.cfg.train.checkpoint_every = 0;
    st.cfg.model.refine = rcfg.clone();
    st.ckpt.model.cfg.refine = rcfg.clone();
    let prepared = prepare(&scene, &st.cfg, true, &mut |m| eprintln!("{m}"))?;
    let params = RefineParams::zeros(&rcfg, prepared.scene.mesh.vertices.len());
    // Adam: the model's state as it was, then fresh state for the offset field.
    let mut specs = st.ckpt.model.layout.name_shapes();
    specs.extend(params.specs());
    let mut adam = AdamState::new(&specs);
    adam.state[..st.adam.len()].copy_from_slice(&st.adam.state);
    st.adam = adam;
    st.ckpt.refine = Some(params);
    let mut refiner = Refiner::for_run(&mut st, &prepared, None)?.expect("refinement is on");
    let mut grads = Grads::new(&st.ckpt.model.layout);
    grads.inputs = false;
    let t0 = std::time::Instant::now();
    let mut next = Some(refiner.draw(&prepared, st.step));
    let (mut loss_sum, mut n) = (0.0, 0);
    while let Some(mut batch) = next.take() {
        let k1 = st.step + 1;
        let (s, nb) = refiner.step_and_draw(
            &mut st,
            &prepared,
            &mut batch,
            &mut grads,
            (k1 < total).then_some(k1),
        );
        let s = s?;
        next = nb;
        loss_sum += s.loss;
        n += 1;
        if st.step % 25 == 0 {
            eprintln!(
                "step {} loss {:.5} ({:.0} s)",
                st.step,
                loss_sum / n as f64,
                t0.elapsed().as_secs_f64()
            );
            (loss_sum, n) = (0.0, 0);
        }
    }
    let scores = evaluate(&st, &prepared, 0, None)?;
    let (all, near, far) = xscale::experiments::bench_geometry::split_scores(&scores);
    println!(
        "masked PSNR {:.2} (close-up {:.2}, far {:.2}), SSIM {:.4}",
        all.psnr_masked, near.psnr_masked, far.psnr_masked, all.ssim_masked
    );
    if let Some(out) = a.get(5) {
        let dir = std::path::Path::new(out)
            .parent()
            .unwrap_or(std::path::Path::new("."));
        xscale::refine::mesh::write_refined(&st, &prepared, dir)?;
        std::fs::rename(dir.join("refined.ply"), out)?;
    }
    Ok(())
}
