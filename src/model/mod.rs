//! The differentiable model (SPEC §4): hash grids, SH direction encoding, MLPs, manifold
//! deformation ξ (Eq. 5), surface multisampling (Eq. 4), shader (Eq. 3), loss. Every op is a
//! `*_forward` / `*_backward` pair; backward passes accumulate.

pub mod config;
pub mod hashgrid;
pub mod real;

pub use config::ModelConfig;
pub use real::Real;
