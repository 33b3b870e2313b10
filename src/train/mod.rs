//! Training, one step at a time: the run configuration, the scene prepared for training, the
//! deterministic batches, the optimizer (Adam with tiny-cuda-nn's rules, SPEC §4.8) and the state
//! of a run with its optimisation step. The loop that drives it is `run/`; the mesh refinement's
//! step, an extension of it, is `refine/`.
//!
//! | file | owns |
//! |---|---|
//! | `config.rs` | presets + TOML overrides → [`RunConfig`] |
//! | `setup.rs` | scene → BVH → sample cache; dropping unresolved hash levels (SPEC §8) |
//! | `sampler.rs` | batch k as a pure function of (seed, k); streamed or cached samples |
//! | `memory.rs` | a run's memory estimate and budget (what the machine has: `sysmem.rs`) |
//! | `adam.rs` | the optimizer |
//! | `state.rs` | the state of a run at a step ([`state::TrainState`]) and one optimisation step |
//! | `precision.rs` | the step with the model in f64 |

pub mod adam;
pub mod config;
pub mod memory;
pub mod precision;
pub mod sampler;
pub mod setup;
pub mod state;

pub use config::{RunConfig, TrainConfig};
