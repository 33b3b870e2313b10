//! Tensor exchange (SPEC §6): safetensors checkpoints, batches and dumps, and `compare`.
//!
//! - [`tensors`]: owned tensors and deterministic, atomic safetensors files.
//! - [`atomic`]: whole-or-absent file writes (temp file, rename) for checkpoints, dumps and images.
//! - [`compare`]: tensor-by-tensor comparison of two files with tolerance rules (`xscale compare`).
//! - [`text`]: reading other tools' text files (a Windows byte-order mark dropped).

pub mod atomic;
// `to_table` and `compare` run over 120 lines; their split is the Python-oracle branch's.
#[allow(clippy::too_many_lines)]
pub mod compare;
pub mod tensors;
pub mod text;

pub use tensors::{DType, Tensor, TensorFile};
