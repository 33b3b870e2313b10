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
pub mod mask;
pub mod mesh;
pub mod mvsnet;
pub mod remesh;
pub mod transforms;

pub use camera::{Camera, Distortion};
pub use mask::MaskSource;

use glam::DVec3;
use std::path::{Path, PathBuf};

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

/// `x_n = (x - center) / extent + 0.5` (SPEC §4.1), all in f64. Serialised (checkpoint metadata
/// `normalization`) as JSON `{"center":[x,y,z],"extent":[x,y,z]}`.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Normalization {
    pub center: DVec3,
    pub extent: DVec3,
}

impl Normalization {
    /// The identity map of `[0,1]^3` (center 0.5, extent 1).
    pub fn unit() -> Normalization {
        Normalization {
            center: DVec3::splat(0.5),
            extent: DVec3::ONE,
        }
    }

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

// -------------------------------------------------------------------------------------------------
// Loading a scene directory
// -------------------------------------------------------------------------------------------------

/// Which camera layout a scene directory uses (SPEC §3).
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum CameraFormat {
    /// COLMAP sparse model in `sparse/0/`, `sparse/` or the dir itself; images in `images/`.
    Colmap,
    /// `cams_<dsp>/NAME_cam.txt` + `images_<dsp>/NAME.ext` (official XScale-NVS layout).
    MvsNet,
    /// `transforms.json` (instant-ngp / nerfstudio), or NeRF-synthetic style
    /// `transforms_train.json` + `transforms_test.json` (+ `transforms_val.json`, used for training).
    Transforms,
}

impl CameraFormat {
    pub fn name(self) -> &'static str {
        match self {
            CameraFormat::Colmap => "colmap",
            CameraFormat::MvsNet => "mvsnet",
            CameraFormat::Transforms => "transforms",
        }
    }
}

impl std::str::FromStr for CameraFormat {
    type Err = anyhow::Error;
    fn from_str(s: &str) -> anyhow::Result<Self> {
        match s.to_ascii_lowercase().as_str() {
            "colmap" => Ok(CameraFormat::Colmap),
            "mvsnet" | "xscale" => Ok(CameraFormat::MvsNet),
            "transforms" | "nerf" | "instant-ngp" | "nerfstudio" => Ok(CameraFormat::Transforms),
            _ => anyhow::bail!("unknown camera format '{s}' (colmap, mvsnet, transforms)"),
        }
    }
}

/// Options for [`Scene::load`].
#[derive(Clone, Debug)]
pub struct LoadOptions {
    /// Camera layout; `None` = auto-detect (an error if several are present).
    pub format: Option<CameraFormat>,
    /// Integer image downsample factor (≥ 1); cameras are scaled to match.
    pub downsample: u32,
    pub normalize: NormalizeMode,
    /// Mesh file; `None` = look in the scene dir (see [`find_mesh`]). A relative path that does
    /// not exist as given is tried relative to the scene dir.
    pub mesh: Option<PathBuf>,
    /// Also read every image's header at load time and check its size against the camera
    /// (cheap: headers only). Existence of every image is always checked.
    pub load_images_check: bool,
    /// MVSNet layout: which `cams_<dsp>` to use when several exist (`None` = the smallest dsp).
    pub mvsnet_dsp: Option<u32>,
}

impl Default for LoadOptions {
    fn default() -> Self {
        LoadOptions {
            format: None,
            downsample: 1,
            normalize: NormalizeMode::PerAxis,
            mesh: None,
            load_images_check: true,
            mvsnet_dsp: None,
        }
    }
}

/// Optional `scene.toml` in a scene dir: the train/test split.
#[derive(Clone, Debug, Default, serde::Deserialize)]
#[serde(deny_unknown_fields)]
struct SceneToml {
    /// Camera layout to use when the dir holds several (`colmap`, `mvsnet`, `transforms`).
    format: Option<String>,
    /// Names of the held-out views (as in [`View::name`]).
    test_views: Option<Vec<String>>,
    /// Hold out indices 0, N, 2N, … (0 = no test views).
    holdout_every: Option<usize>,
    /// Colour of misses in renders, `[r, g, b]` in [0, 1] (default white).
    background: Option<[f32; 3]>,
}

/// What [`Scene::load_report`] found.
#[derive(Clone, Debug)]
pub struct LoadReport {
    pub format: CameraFormat,
    pub mesh_path: PathBuf,
    pub mesh_stats: mesh::MeshStats,
}

/// Default split: every 7th view held out (indices 0, 7, 14, …), the official protocol.
pub const HOLDOUT_EVERY: usize = 7;

/// Which camera formats are present in `dir`.
pub fn detect_formats(dir: &Path) -> Vec<CameraFormat> {
    let mut out = Vec::new();
    if dir.join("transforms.json").is_file() || dir.join("transforms_train.json").is_file() {
        out.push(CameraFormat::Transforms);
    }
    if colmap::find_model_dir(dir).is_some() {
        out.push(CameraFormat::Colmap);
    }
    if !mvsnet::find_layouts(dir).is_empty() {
        out.push(CameraFormat::MvsNet);
    }
    out
}

/// The mesh of a scene dir: `mesh.ply`, `mesh.obj`, COLMAP's `meshed-poisson.ply` then
/// `meshed-delaunay.ply` (in the dir, `dense/0/`, `dense/` or `0/`), else the single `*.ply` /
/// `*.obj` in the dir; an error lists the candidates otherwise.
pub fn find_mesh(dir: &Path) -> anyhow::Result<PathBuf> {
    let mut named = vec![dir.join("mesh.ply"), dir.join("mesh.obj")];
    // COLMAP's meshers: Poisson first (watertight, what most pipelines use), then Delaunay; in
    // the dir itself, a dense workspace's `dense/0/` and `dense/`, or a `dense/` folder's `0/`.
    for sub in [&[][..], &["dense", "0"], &["dense"], &["0"]] {
        for m in ["meshed-poisson.ply", "meshed-delaunay.ply"] {
            named.push(sub.iter().fold(dir.to_path_buf(), |p, s| p.join(s)).join(m));
        }
    }
    if let Some(p) = named.iter().find(|p| p.is_file()) {
        return Ok(p.clone());
    }
    let mut cands: Vec<PathBuf> = std::fs::read_dir(dir)
        .map_err(|e| anyhow::anyhow!("{}: cannot list scene directory: {e}", dir.display()))?
        .flatten()
        .map(|e| e.path())
        .filter(|p| {
            p.is_file()
                && p.extension()
                    .and_then(|e| e.to_str())
                    .is_some_and(|e| e.eq_ignore_ascii_case("ply") || e.eq_ignore_ascii_case("obj"))
        })
        .collect();
    cands.sort();
    match cands.len() {
        1 => Ok(cands.pop().unwrap()),
        0 => anyhow::bail!(
            "{}: no mesh found (looked for mesh.ply, mesh.obj, meshed-poisson.ply / meshed-delaunay.ply here or in dense/0/, or a single *.ply/*.obj); pass the mesh explicitly",
            dir.display()
        ),
        _ => anyhow::bail!(
            "{}: several mesh candidates, pass one explicitly: {}",
            dir.display(),
            cands
                .iter()
                .map(|p| p.file_name().unwrap().to_string_lossy().to_string())
                .collect::<Vec<_>>()
                .join(", ")
        ),
    }
}

/// Each view's mask source (`scene/mask.rs`): files in `dir/masks/` when that folder exists
/// (every view must have one), else the photo's alpha channel when `check_alpha` finds one.
fn find_masks(dir: &Path, views: &[View], check_alpha: bool) -> anyhow::Result<Vec<MaskSource>> {
    let masks_dir = dir.join("masks");
    if masks_dir.is_dir() {
        return views
            .iter()
            .map(|v| mask::find_mask(&masks_dir, &v.name).map(MaskSource::File))
            .collect();
    }
    views
        .iter()
        .map(|v| {
            Ok(if check_alpha && mask::has_alpha(&v.image_path)? {
                MaskSource::Alpha
            } else {
                MaskSource::None
            })
        })
        .collect()
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
    /// Load a scene directory: cameras (auto-detected or `opts.format`), the mesh, the split
    /// (`scene.toml` or every 7th view), the normalisation, and check the images (existence,
    /// and sizes if `opts.load_images_check`). Views keep the camera file's order (COLMAP: sorted
    /// by image name; MVSNet: by cam file name; transforms: frame order).
    pub fn load(dir: &Path, opts: &LoadOptions) -> anyhow::Result<Scene> {
        Ok(Scene::load_report(dir, opts)?.0)
    }

    /// [`Scene::load`], also returning what was found (format, mesh file, mesh statistics such as
    /// the number of degenerate triangles dropped) for the CLI to report.
    pub fn load_report(dir: &Path, opts: &LoadOptions) -> anyhow::Result<(Scene, LoadReport)> {
        use anyhow::{anyhow, bail};
        if !dir.is_dir() {
            bail!("{}: scene directory not found", dir.display());
        }
        if opts.downsample == 0 {
            bail!("downsample factor must be >= 1");
        }
        // Optional scene.toml: camera layout and split.
        let toml_path = dir.join("scene.toml");
        let cfg: SceneToml = if toml_path.is_file() {
            let text = std::fs::read_to_string(&toml_path)
                .map_err(|e| anyhow!("{}: cannot read: {e}", toml_path.display()))?;
            toml::from_str(&text).map_err(|e| anyhow!("{}: {e}", toml_path.display()))?
        } else {
            SceneToml::default()
        };
        let toml_format = match &cfg.format {
            Some(name) => Some(
                name.parse::<CameraFormat>()
                    .map_err(|e| anyhow!("{}: format: {e}", toml_path.display()))?,
            ),
            None => None,
        };
        let format = match opts.format.or(toml_format) {
            Some(f) => f,
            None => {
                let found = detect_formats(dir);
                match found.as_slice() {
                    [f] => *f,
                    [] => bail!(
                        "{}: no cameras found (looked for transforms.json, a COLMAP model in sparse/0/, sparse/ or the dir itself, and MVSNet cams_<dsp>/*_cam.txt)",
                        dir.display()
                    ),
                    many => bail!(
                        "{}: several camera formats present ({}); choose one explicitly",
                        dir.display(),
                        many.iter().map(|f| f.name()).collect::<Vec<_>>().join(", ")
                    ),
                }
            }
        };
        // (views, test view names given by the format itself)
        let (mut views, format_test): (Vec<View>, Option<Vec<String>>) = match format {
            CameraFormat::Colmap => {
                let layout = colmap::find_layout(dir).ok_or_else(|| {
                    anyhow!(
                        "{}: no COLMAP model (cameras + images .txt/.bin) in dense/0/sparse/, sparse/0/, sparse/ or the dir itself",
                        dir.display()
                    )
                })?;
                if !layout.images.is_dir() {
                    bail!(
                        "{}: COLMAP image directory not found (the model is in {})",
                        layout.images.display(),
                        layout.model.display()
                    );
                }
                (colmap::load(&layout.model, &layout.images)?, None)
            }
            CameraFormat::MvsNet => {
                let layouts = mvsnet::find_layouts(dir);
                let layout = match opts.mvsnet_dsp {
                    Some(d) => layouts
                        .into_iter()
                        .find(|l| l.dsp == Some(d))
                        .ok_or_else(|| {
                            anyhow!("{}: no cams_{d}/ with *_cam.txt files", dir.display())
                        })?,
                    None => layouts.into_iter().next().ok_or_else(|| {
                        anyhow!("{}: no cams_<dsp>/ with *_cam.txt files", dir.display())
                    })?,
                };
                (mvsnet::load(&layout)?, None)
            }
            CameraFormat::Transforms => {
                let single = dir.join("transforms.json");
                if single.is_file() {
                    (transforms::load(&single)?, None)
                } else {
                    let train = dir.join("transforms_train.json");
                    let test = dir.join("transforms_test.json");
                    if !train.is_file() {
                        bail!("{}: transforms.json not found", dir.display());
                    }
                    let mut v = transforms::load(&train)?;
                    let val = dir.join("transforms_val.json");
                    if val.is_file() {
                        v.extend(transforms::load(&val)?);
                    }
                    let t = if test.is_file() {
                        transforms::load(&test)?
                    } else {
                        Vec::new()
                    };
                    let names = t.iter().map(|x| x.name.clone()).collect();
                    v.extend(t);
                    (v, Some(names))
                }
            }
        };
        if views.is_empty() {
            bail!("{}: the camera file has no views", dir.display());
        }
        {
            let mut seen = std::collections::HashSet::new();
            for v in &views {
                if !seen.insert(v.name.as_str()) {
                    bail!("{}: view name '{}' appears twice", dir.display(), v.name);
                }
            }
        }

        // Images: existence always; header sizes optionally.
        for v in &views {
            if !v.image_path.is_file() {
                bail!(
                    "{}: image of view '{}' not found",
                    v.image_path.display(),
                    v.name
                );
            }
            if opts.load_images_check {
                let (w, h) = image::dimensions(&v.image_path)?;
                if (w, h) != (v.camera.width, v.camera.height) && !v.needs_orientation(1)? {
                    let tag = match image::exif_orientation(&v.image_path)? {
                        Some(o) => {
                            format!(" (its EXIF orientation {o:?} does not explain it either)")
                        }
                        None => String::new(),
                    };
                    bail!(
                        "{}: image is {w}x{h} but the camera of view '{}' says {}x{}{tag}",
                        v.image_path.display(),
                        v.name,
                        v.camera.width,
                        v.camera.height
                    );
                }
            }
        }
        let s = opts.downsample;
        if s > 1 {
            for v in &mut views {
                if v.camera.width / s == 0 || v.camera.height / s == 0 {
                    bail!(
                        "view '{}': image {}x{} is smaller than the downsample factor {s}",
                        v.name,
                        v.camera.width,
                        v.camera.height
                    );
                }
                v.camera = v.camera.downsampled(s);
            }
        }

        // Split (scene.toml was read above).
        let test: Vec<usize> = if let Some(names) = &cfg.test_views {
            if cfg.holdout_every.is_some() {
                bail!(
                    "{}: give either test_views or holdout_every, not both",
                    toml_path.display()
                );
            }
            let mut t = Vec::with_capacity(names.len());
            for n in names {
                let i = views.iter().position(|v| &v.name == n).ok_or_else(|| {
                    anyhow!(
                        "{}: test view '{n}' is not a view of the scene",
                        toml_path.display()
                    )
                })?;
                t.push(i);
            }
            t.sort_unstable();
            t.dedup();
            t
        } else if let Some(k) = cfg.holdout_every {
            if k == 0 {
                Vec::new()
            } else {
                (0..views.len()).step_by(k).collect()
            }
        } else if let Some(names) = format_test {
            let mut t: Vec<usize> = names
                .iter()
                .filter_map(|n| views.iter().position(|v| &v.name == n))
                .collect();
            t.sort_unstable();
            t
        } else {
            (0..views.len()).step_by(HOLDOUT_EVERY).collect()
        };

        // Mesh.
        let mesh_path = match &opts.mesh {
            Some(p) if p.exists() || p.is_absolute() => p.clone(),
            Some(p) => dir.join(p),
            None => find_mesh(dir)?,
        };
        let (mesh, mesh_stats) = mesh::load_mesh(&mesh_path)?;
        let normalization = Normalization::from_mesh(&mesh, opts.normalize);
        let background = cfg.background.unwrap_or([1.0; 3]);
        if background.iter().any(|c| !(0.0..=1.0).contains(c)) {
            bail!(
                "{}: background {background:?}: expected three values in [0, 1]",
                toml_path.display()
            );
        }
        let masks = find_masks(dir, &views, opts.load_images_check)?;
        let scene = Scene {
            root: dir.to_path_buf(),
            mesh,
            views,
            test,
            normalization,
            downsample: s,
            masks,
            background,
        };
        Ok((
            scene,
            LoadReport {
                format,
                mesh_path,
                mesh_stats,
            },
        ))
    }

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
