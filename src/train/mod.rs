//! Training: Adam with tiny-cuda-nn's rules (SPEC §4.8), deterministic batches, the loop,
//! checkpoints and resume.
//!
//! | file | owns |
//! |---|---|
//! | `config.rs` | presets + TOML overrides → [`RunConfig`] |
//! | `setup.rs` | scene → BVH → sample cache; dropping unresolved hash levels (SPEC §8) |
//! | `sampler.rs` | batch k as a pure function of (seed, k); streamed or cached samples |
//! | `memory.rs` | the memory estimate and budget, peak RSS |
//! | `adam.rs` | the optimizer |
//! | `state.rs` | the state of a run at a step ([`state::TrainState`]) and one optimisation step |
//! | `precision.rs` | the step with the model in f64 |
//! | `trainer.rs` | the loop, checkpoints, exact resume, Ctrl-C |
//! | `run_dir.rs` | the run folder's lock, its protection, the scene fingerprint |
//! | `divergence.rs` | stopping a run whose loss never falls or blows up |
//! | `report.rs` | what a run tells the user: progress, `metrics.jsonl`, `eval.json` |
//! | `ablate.rs` | the paper's ablations and the vertex baseline (`xscale ablate`) |

pub mod ablate;
pub mod adam;
pub mod bench_geometry;
pub mod bench_quality;
pub mod config;
pub mod divergence;
pub mod memory;
pub mod photo;
pub mod precision;
pub mod refine;
pub mod report;
pub mod run_dir;
pub mod sampler;
pub mod setup;
pub mod state;
pub mod trainer;
pub mod trust;

pub use config::{RunConfig, TrainConfig};
