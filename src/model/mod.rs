//! The differentiable model (SPEC §4): hash grids, SH direction encoding, MLPs, manifold
//! deformation ξ (Eq. 5), surface multisampling (Eq. 4), shader (Eq. 3), loss. Every op is a
//! `*_forward` / `*_backward` pair; backward passes accumulate.

pub mod batch;
pub mod checkpoint;
pub mod config;
pub mod hashgrid;
pub mod hfm;
pub mod kink;
pub mod level_weight;
pub mod loss;
pub mod manifest;
pub mod mlp;
pub mod params;
pub mod real;
pub mod refine;
pub mod sh;
pub mod ssim;
pub mod vertex;

pub use batch::Batch;
pub use config::ModelConfig;
pub use hfm::{Forward, Hfm};
pub use params::{Grads, Group, ParamLayout, TensorSpec};
pub use real::Real;
