//! Determinism of the full pipeline (SPEC §5): the loss and every gradient (parameters,
//! positions, directions, touched sets) of a 16,384-pixel batch at the `cpu` preset (γ = 2 with
//! invalid sub-samples, deformation and appearance codes on, views −1 and ≥ 0) are bit-identical
//! with 1, 2 and 4 threads (rayon pools built here) and across two runs.

use xscale::model::batch::Batch;
use xscale::model::config::LevelWeight;
use xscale::model::params::{Grads, Group};
use xscale::model::{Hfm, ModelConfig};
use xscale::rng::{uniform_f32, Purpose};

fn bits(v: &[f32]) -> Vec<u32> {
    v.iter().map(|x| x.to_bits()).collect()
}

struct Result1 {
    loss: u64,
    params: Vec<u32>,
    positions: Vec<u32>,
    dirs: Vec<u32>,
    touched: (Vec<u32>, Vec<u32>),
}

fn run(model: &Hfm, params: &[f32], batch: &Batch, threads: usize) -> Result1 {
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()
        .unwrap();
    pool.install(|| {
        let mut g = Grads::<f32>::new(&model.layout);
        let loss = model.loss_and_grad(params, batch, &mut g).unwrap();
        Result1 {
            loss: loss.to_bits(),
            params: bits(&g.params),
            positions: bits(&g.positions),
            dirs: bits(&g.dirs),
            touched: (g.touched_h.entries, g.touched_d.entries),
        }
    })
}

#[test]
fn gradients_bit_identical_across_threads_and_runs() {
    bit_identical(LevelWeight::None);
}

/// The same with the footprint level weighting (SPEC §4.10): footprints spread over the cpu
/// preset's cell sizes, so every level is fully, partly and not evaluated by some pixels.
#[test]
fn level_weighted_gradients_bit_identical_across_threads_and_runs() {
    bit_identical(LevelWeight::Footprint);
}

fn bit_identical(level_weight: LevelWeight) {
    let mut cfg = ModelConfig::cpu();
    cfg.appearance_views = 8;
    cfg.level_weight = level_weight;
    assert_eq!(cfg.gamma, 2);
    let model = Hfm::new(&cfg).unwrap();
    let mut params = model.init_params(3);
    // ξ's last layer and the codes start at zero; give them values so every path carries
    // gradient (otherwise grid D's gradient would be exactly zero).
    let r = model.layout.group_range(Group::Appearance).unwrap();
    for (e, v) in params[r].iter_mut().enumerate() {
        *v = uniform_f32(5, Purpose::Test, 0, e as u64) - 0.5;
    }
    let last = format!(
        "deform.layers.{}.weight",
        model.deform.as_ref().unwrap().layers.len() - 1
    );
    for (e, v) in model
        .layout
        .view_mut(&mut params, &last)
        .iter_mut()
        .enumerate()
    {
        *v = 0.1 * (uniform_f32(5, Purpose::Test, 1, e as u64) - 0.5);
    }
    let mut batch = Batch::random(11, 16_384, 4, 8, 0.2);
    assert!(batch.valid.contains(&0) && batch.view.contains(&-1));
    if level_weight == LevelWeight::Footprint {
        // log-uniform over [1e-4, 1e-1]: from finer than the finest cell to coarser than level 0's.
        batch.footprint = (0..16_384)
            .map(|i| 10f32.powf(-4.0 + 3.0 * uniform_f32(13, Purpose::Test, 0, i)))
            .collect();
    }

    let reference = run(&model, &params, &batch, 1);
    assert!(reference.params.iter().any(|&b| f32::from_bits(b) != 0.0));
    let gd = model.layout.range("grid_d.table");
    assert!(reference.params[gd]
        .iter()
        .any(|&b| f32::from_bits(b) != 0.0));
    for (label, threads) in [
        ("2 threads", 2),
        ("4 threads", 4),
        ("1 thread, second run", 1),
        ("2 threads, second run", 2),
    ] {
        let r = run(&model, &params, &batch, threads);
        assert_eq!(r.loss, reference.loss, "{label}: loss differs");
        let diff = r
            .params
            .iter()
            .zip(&reference.params)
            .filter(|(a, b)| a != b)
            .count();
        assert_eq!(diff, 0, "{label}: {diff} parameter gradients differ");
        assert!(
            r.positions == reference.positions,
            "{label}: position gradients differ"
        );
        assert!(
            r.dirs == reference.dirs,
            "{label}: direction gradients differ"
        );
        assert!(
            r.touched == reference.touched,
            "{label}: touched sets differ"
        );
    }
}

/// Turning the input gradients off (as training does) leaves the parameter gradients and the
/// touched sets bit-identical, and computes no input gradients.
#[test]
fn parameter_gradients_do_not_depend_on_input_gradients() {
    let mut cfg = ModelConfig::tiny();
    cfg.appearance_views = 3;
    let model = Hfm::new(&cfg).unwrap();
    let mut params = model.init_params(5);
    // Non-zero ξ output layer so every path carries gradient.
    for (i, p) in params.iter_mut().enumerate() {
        *p += 0.05 * (uniform_f32(9, Purpose::Test, 0, i as u64) - 0.5);
    }
    let batch = Batch::random(11, 700, 4, 3, 0.2);
    let mut with = Grads::<f32>::new(&model.layout);
    let mut without = Grads::<f32>::new(&model.layout);
    without.inputs = false;
    let l1 = model.loss_and_grad(&params, &batch, &mut with).unwrap();
    let l2 = model.loss_and_grad(&params, &batch, &mut without).unwrap();
    assert_eq!(l1.to_bits(), l2.to_bits());
    assert_eq!(bits(&with.params), bits(&without.params));
    assert_eq!(with.touched_h.entries, without.touched_h.entries);
    assert_eq!(with.touched_d.entries, without.touched_d.entries);
    assert!(without.positions.is_empty() && without.dirs.is_empty());
    assert!(with.positions.iter().any(|&x| x != 0.0));
}
