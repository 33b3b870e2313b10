//! Photos to a scene on a CPU (`xscale prepare`): COLMAP's CPU structure-from-motion when a
//! `colmap` binary is on the PATH, then a mesh of its sparse points made here.
//!
//! | file | what |
//! |---|---|
//! | `pipeline.rs` | the stages of `xscale prepare`, resumable, with the report |
//! | `colmap_run.rs` | running `colmap` (found on the PATH), logs, progress, interrupts |
//! | `delaunay.rs` | 3-D Delaunay tetrahedralisation (Bowyer–Watson, exact predicates) |
//! | `maxflow.rs` | minimum s–t cut (Boykov–Kolmogorov max flow) |
//! | `mesher.rs` | the visibility graph-cut surface of Labatut et al. 2009 from points and cameras |
//! | `sparse.rs` | a whole COLMAP sparse model: views, points with tracks, keypoints |
//! | `synthetic.rs` | sparse points and tracks of a synthetic scene (tests, measurements) |

pub mod colmap_run;
pub mod delaunay;
pub mod maxflow;
pub mod mesher;
pub mod pipeline;
pub mod sparse;
pub mod synthetic;
