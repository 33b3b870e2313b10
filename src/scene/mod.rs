//! Scene input (SPEC §3): a mesh, posed views with their images, the train/test split, and the
//! f64 normalisation of SPEC §4.1. Everything downstream (ray casting, training, rendering) takes
//! a [`Scene`].
//!
//! Files: `camera.rs` (pinhole + distortion), `mesh.rs` (OBJ/PLY load and write), `colmap.rs`,
//! `mvsnet.rs`, `transforms.rs` (the three camera layouts, load and write), `image.rs`
//! (PNG/JPEG/EXR load, downsample, write).
//!
//! Errors: every loader returns `anyhow::Result` whose message names the file, the line or
//! element, and what was expected. No loader panics on bad input.

pub mod camera;
pub mod colmap;
pub mod image;
pub mod mesh;
pub mod mvsnet;
pub mod transforms;

pub use camera::{Camera, Distortion};

use glam::DVec3;
use std::path::PathBuf;

/// A triangle mesh in world coordinates (f64, so georeferenced scenes keep their precision).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Mesh {
    pub vertices: Vec<DVec3>,
    /// Counter-clockwise or not: ray casting is two-sided.
    pub triangles: Vec<[u32; 3]>,
}

impl Mesh {
    /// Axis-aligned bounding box (min, max) of the vertices.
    pub fn bbox(&self) -> (DVec3, DVec3) {
        self.vertices.iter().fold(
            (DVec3::splat(f64::INFINITY), DVec3::splat(f64::NEG_INFINITY)),
            |(lo, hi), v| (lo.min(*v), hi.max(*v)),
        )
    }
}

/// How the bounding box maps to [0,1]^3 (SPEC §4.1).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum NormalizeMode {
    /// Per-axis extent, as the official code.
    #[default]
    PerAxis,
    /// The largest axis extent for all three axes.
    Isotropic,
}

/// `x_n = (x - center) / extent + 0.5` (SPEC §4.1), all in f64.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Normalization {
    pub center: DVec3,
    pub extent: DVec3,
}

impl Normalization {
    /// `center = (min+max)/2`, `extent = max-min+1e-6` per axis (or the largest for all).
    pub fn from_mesh(mesh: &Mesh, mode: NormalizeMode) -> Normalization {
        let (lo, hi) = mesh.bbox();
        let center = (lo + hi) * 0.5;
        let e = hi - lo + DVec3::splat(1e-6);
        let extent = match mode {
            NormalizeMode::PerAxis => e,
            NormalizeMode::Isotropic => DVec3::splat(e.max_element()),
        };
        Normalization { center, extent }
    }

    #[inline]
    pub fn to_normalized(&self, x: DVec3) -> DVec3 {
        (x - self.center) / self.extent + DVec3::splat(0.5)
    }

    #[inline]
    pub fn from_normalized(&self, x: DVec3) -> DVec3 {
        (x - DVec3::splat(0.5)) * self.extent + self.center
    }
}

/// One posed photo.
#[derive(Clone, Debug, PartialEq)]
pub struct View {
    /// Image name as the camera file gives it (e.g. `"0003.png"`), unique within a scene.
    pub name: String,
    /// Camera for the image *after* downsampling.
    pub camera: Camera,
    /// Where the image is; loaded on demand.
    pub image_path: PathBuf,
}

/// An RGB image with f32 values (sRGB-encoded values in [0,1] for PNG/JPEG; EXR as stored).
#[derive(Clone, Debug, PartialEq)]
pub struct Image {
    pub width: u32,
    pub height: u32,
    /// Row-major, row 0 at the top, 3 values per pixel.
    pub data: Vec<f32>,
}

/// A loaded scene.
#[derive(Clone, Debug)]
pub struct Scene {
    pub root: PathBuf,
    pub mesh: Mesh,
    /// All views in scene order (the order of the camera file).
    pub views: Vec<View>,
    /// Indices into `views` held out for testing (default every 7th: 0, 7, 14, …).
    pub test: Vec<usize>,
    pub normalization: Normalization,
    /// Integer downsample factor applied to every image (1 = none).
    pub downsample: u32,
}

impl Scene {
    /// Indices of the training views, in scene order.
    pub fn train(&self) -> Vec<usize> {
        (0..self.views.len())
            .filter(|i| !self.test.contains(i))
            .collect()
    }
}
