//! Scene input (SPEC §3): a mesh, posed views with their images, the train/test split, and the
//! f64 normalisation of SPEC §4.1. Everything downstream (ray casting, training, rendering) takes
//! a [`Scene`].
//!
//! This file only declares and re-exports. Files: `view.rs` ([`Scene`], [`View`]), `load.rs`
//! (loading a scene directory: layout detection, one loader per layout, image checks, split,
//! mesh), `normalize.rs` ([`Normalization`]), `mesh.rs` ([`Mesh`]; OBJ/PLY load and write),
//! `image.rs` ([`Image`]; PNG/JPEG/EXR load, downsample, write), `camera.rs` (pinhole +
//! distortion), `colmap.rs`, `mvsnet.rs`, `transforms.rs` (camera layouts, load and write),
//! `metashape.rs` (Agisoft Metashape's camera export, load only), `mask.rs` (object masks), `remesh.rs` (decimation and subdivision), `points.rs` (the
//! reconstruction's 3-D points against the mesh: are they in one frame?), `distance.rs`
//! (point-to-surface distance).
//!
//! Errors: every loader returns `anyhow::Result` whose message names the file, the line or
//! element, and what was expected. No loader panics on bad input.

pub mod camera;
pub mod colmap;
pub mod distance;
pub mod dual;
pub mod image;
pub mod load;
pub mod mask;
pub mod mesh;
pub mod metashape;
pub mod mvsnet;
pub mod normalize;
pub mod points;
pub mod remesh;
pub mod transforms;
pub mod view;

pub use camera::{Camera, Distortion};
pub use image::Image;
pub use load::{detect_formats, find_mesh, CameraFormat, LoadOptions, LoadReport, HOLDOUT_EVERY};
pub use mask::MaskSource;
pub use mesh::Mesh;
pub use normalize::{Normalization, NormalizeMode};
pub use view::{Scene, View};
