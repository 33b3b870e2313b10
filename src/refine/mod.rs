//! Mesh refinement (beyond the paper; SPEC §4.11, docs/geometry.md): the vertices of the training
//! mesh move along their normals while the features train, driven by the loss's gradient through
//! the ray–triangle hit point and by the multi-view photo-consistency of the training photos. Its
//! configuration and saved parameters are part of the model (`model/refine.rs`); everything else
//! is here, one file per concept:
//!
//! | file | owns |
//! |---|---|
//! | `field.rs` | the offset field: what the training mesh fixes, θ per vertex from grids and residual, its backward, smoothness |
//! | `hit.rs` | a ray's hit on the moved triangle's plane and the gradient of a batch's loss with respect to θ |
//! | `photo.rs` | the photo-consistency energy of one patch and its derivative |
//! | `photo_term.rs` | which patches: views' photos by level, neighbour views, drawing a step's patches |
//! | `trust.rs` | the trust region: acceptance batches and their paired error |
//! | `refiner.rs` | the step driver: schedule, re-intersection, pending sums, updates, BVH rebuilds |
//! | `diagnostics.rs` | `XSCALE_REFINE_LOG`: update-by-update diagnostics |
//! | `mesh.rs` | the refined mesh a model renders, its BVH, `RUN/refined.ply` |

pub mod diagnostics;
pub mod field;
pub mod hit;
pub mod mesh;
pub mod photo;
pub mod photo_term;
pub mod refiner;
pub mod trust;

pub use field::RefineGeom;
pub use refiner::Refiner;
