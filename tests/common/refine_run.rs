//! The tiny fixture, run folders and the refinement configuration shared by the mesh refinement
//! tests (`tests/refine.rs`, `tests/refine_trust.rs`).

use std::path::{Path, PathBuf};
use xscale::run::trainer::TrainOptions;
use xscale::train::config::RunConfig;

pub fn fixture() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("fixtures/tiny")
}

pub fn tmp(name: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("xscale-test-refine-{}-{name}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    d
}

/// The tiny preset with refinement from step 40 to 144 of 160, updates (and BVH rebuilds) every
/// 17 steps (so the resume point, 100, falls between two, with gradient pending), every level on
/// by step 88, the per-vertex residual with its smoothness terms.
pub fn cfg() -> RunConfig {
    let mut c = RunConfig::preset("tiny").unwrap();
    c.train.steps = 160;
    c.train.batch_pixels = 512;
    c.train.eval_every = 0;
    c.train.checkpoint_every = 30;
    // The refinement through the learned features (the defaults before issue #39, whose
    // schedule these tests pin down; the photo term's own tests build on it).
    c.model.refine = xscale::model::refine::RefineConfig::learned();
    let r = &mut c.model.refine;
    r.enabled = true;
    r.start = 0.25;
    r.coarse_to_fine = 0.3;
    r.update_every = 17;
    r.stop = 0.9;
    r.per_vertex = true;
    r.laplacian = 1e-3;
    r.lr = 1e-3;
    // A decaying rate: the resume must land on the same rate schedule.
    r.lr_end = 2e-4;
    c.validate().unwrap();
    c
}

pub fn opts(resume: bool, stop_at: Option<u64>) -> TrainOptions {
    TrainOptions {
        resume,
        stop_at,
        no_final_eval: true,
        quiet: true,
        ..Default::default()
    }
}
