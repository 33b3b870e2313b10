//! Tensor exchange (SPEC §6): safetensors checkpoints, batches and dumps, and `compare`.
//!
//! - [`tensors`]: owned tensors and deterministic, atomic safetensors files.
//! - [`compare`]: tensor-by-tensor comparison of two files with tolerance rules (`xscale compare`).

pub mod compare;
pub mod tensors;

pub use tensors::{DType, Tensor, TensorFile};
