//! A loaded scene ([`Scene`]) and its posed photos ([`View`]): what every stage downstream of
//! loading takes. Loading itself is in `load.rs`.

use super::{image, mask, Camera, Image, MaskSource, Mesh, Normalization};
use std::path::PathBuf;

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
    /// Per view (same order as `views`): where its object mask comes from (`scene/mask.rs`).
    pub masks: Vec<MaskSource>,
    /// Colour of pixels whose rays all miss the mesh in renders (RGB in [0, 1]; `scene.toml`
    /// `background`, default white as the official protocol).
    pub background: [f32; 3],
}

impl Scene {
    /// Indices of the training views, in scene order.
    pub fn train(&self) -> Vec<usize> {
        (0..self.views.len())
            .filter(|i| !self.test.contains(i))
            .collect()
    }
}

impl View {
    /// Whether the photo must be turned by its EXIF orientation to fit the camera: its stored
    /// size does not match the camera (after `downsample`) but the turned size does. Photos whose
    /// stored size fits are used as stored (as COLMAP does) whatever their tag says.
    pub fn needs_orientation(&self, downsample: u32) -> anyhow::Result<bool> {
        let (w, h) = image::dimensions(&self.image_path)?;
        let s = downsample.max(1);
        if (w / s, h / s) == (self.camera.width, self.camera.height) {
            return Ok(false);
        }
        Ok(image::exif_orientation(&self.image_path)?.is_some_and(|o| {
            image::swaps_axes(o) && (h / s, w / s) == (self.camera.width, self.camera.height)
        }))
    }

    /// Load this view's image, downsample it by `downsample`, and check that the result has the
    /// camera's size (the camera is the downsampled one). Errors name the file and both sizes.
    pub fn load_image(&self, downsample: u32) -> anyhow::Result<Image> {
        anyhow::ensure!(downsample >= 1, "downsample factor must be >= 1");
        let img = image::load_rgb_oriented(&self.image_path, self.needs_orientation(downsample)?)?;
        let (w, h) = (img.width / downsample, img.height / downsample);
        if (w, h) != (self.camera.width, self.camera.height) {
            anyhow::bail!(
                "{}: image is {}x{}{} but the camera of view '{}' expects {}x{}",
                self.image_path.display(),
                img.width,
                img.height,
                if downsample > 1 {
                    format!(" ({w}x{h} after downsampling by {downsample})")
                } else {
                    String::new()
                },
                self.name,
                self.camera.width,
                self.camera.height
            );
        }
        Ok(image::downsample(&img, downsample))
    }
}

impl Scene {
    /// View `i`'s object mask at the camera's resolution (`scene/mask.rs`), `None` if it has none.
    pub fn load_mask(&self, i: usize) -> anyhow::Result<Option<Vec<bool>>> {
        let v = &self.views[i];
        mask::load_mask(
            &self.masks[i],
            &v.image_path,
            self.downsample,
            (v.camera.width, v.camera.height),
        )
    }

    /// Whether any view has an object mask.
    pub fn has_masks(&self) -> bool {
        self.masks.iter().any(|m| *m != MaskSource::None)
    }

    /// Load view `i`'s image, downsampled by the scene's factor (see [`View::load_image`]).
    pub fn load_image(&self, i: usize) -> anyhow::Result<Image> {
        let v = self.views.get(i).ok_or_else(|| {
            anyhow::anyhow!("view index {i} out of range ({} views)", self.views.len())
        })?;
        v.load_image(self.downsample)
    }
}
