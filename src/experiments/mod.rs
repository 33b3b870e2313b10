//! Experiments over many training runs, each a command that trains variants on one scene with one
//! budget and writes a comparison (tables, CSV, plots): above the run (`run/`), which each variant
//! is.
//!
//! | file | owns |
//! |---|---|
//! | `ablate.rs` | the paper's ablations and the vertex baseline (`xscale ablate`) |
//! | `bench_geometry.rs` | what an imperfect mesh costs, and what refining it wins back (`xscale bench-geometry`) |
//! | `bench_quality.rs` | run time against error (`xscale bench-quality`) |
//! | `variant.rs` | what they share: training a variant's run, the ULR baseline's scores |

pub mod ablate;
pub mod bench_geometry;
pub mod bench_quality;
pub mod variant;
