//! xscale — a pure-CPU, deterministic Rust implementation of XScale-NVS, the hash featurized
//! manifold for cross-scale novel view synthesis (CVPR 2024).
//!
//! The modules follow the data flow of SPEC §1:
//!
//! | stage | module |
//! |---|---|
//! | scene dir → mesh, cameras, images, split, normalisation | [`scene`] |
//! | BVH, γ² rays per pixel, sample cache | [`raycast`] |
//! | synthetic cross-scale scenes with independent ground truth | [`synth`] |
//! | hash grids, SH, MLPs, deformation ξ, pooling, shader, loss (forward + backward) | [`model`] |
//! | Adam, batches, training loop, checkpoints | [`train`] |
//! | rendering any camera, camera paths, error images | [`render`] |
//! | PSNR / SSIM, the held-out protocol | [`eval`] |
//! | safetensors checkpoints, batches, dumps, `compare` | [`io`] |
//! | counter-based random numbers (SPEC §5) | [`rng`] |
//! | command-line front end | [`cli`] |

pub mod cli;
pub mod eval;
pub mod io;
pub mod memhint;
pub mod model;
pub mod raycast;
pub mod render;
pub mod rng;
pub mod scene;
pub mod synth;
pub mod train;
