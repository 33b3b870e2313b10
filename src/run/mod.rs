//! A training run (SPEC §1): the loop over the steps of `train/` (and of `refine/`), the run
//! folder, progress and `metrics.jsonl`, periodic evaluation, atomic checkpoints, exact resume,
//! Ctrl-C; and a run's model loaded with the scene to use it on (`eval`, `render`).
//!
//! | file | owns |
//! |---|---|
//! | `trainer.rs` | the loop, checkpoints, exact resume, evaluation of a state |
//! | `run_dir.rs` | the run folder's lock, its protection, the scene fingerprint |
//! | `divergence.rs` | stopping a run whose loss never falls or blows up |
//! | `report.rs` | what a run tells the user: progress, `metrics.jsonl`, `eval.json` |
//! | `model.rs` | a run's model and the scene to use it on (refined mesh, anchored BVH, appearance rows) |

pub mod divergence;
pub mod model;
pub mod report;
pub mod run_dir;
pub mod trainer;
