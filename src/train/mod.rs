//! Training: Adam with tiny-cuda-nn's rules (SPEC §4.8), deterministic batches, the loop,
//! checkpoints and resume.

pub mod adam;
