//! Loading a scene directory (SPEC §3): which camera layout it uses, one small loader per layout,
//! the image checks, the train/test split from `scene.toml`, and the mesh.
//!
//! [`Scene::load_report`] composes them in that order; each step names the file and what was
//! expected when it fails.

use super::{
    colmap, image, mask, mesh, metashape, mvsnet, points, transforms, MaskSource, Normalization,
    NormalizeMode, Scene, View,
};
use anyhow::{anyhow, bail, Result};
use glam::{DMat3, DVec3};
use std::path::{Path, PathBuf};

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
    /// Agisoft Metashape's camera export: `cameras.xml` (or a single other Agisoft `*.xml`) with
    /// the photos in `images/` ([`metashape`]).
    Metashape,
}

impl CameraFormat {
    pub fn name(self) -> &'static str {
        match self {
            CameraFormat::Colmap => "colmap",
            CameraFormat::MvsNet => "mvsnet",
            CameraFormat::Transforms => "transforms",
            CameraFormat::Metashape => "metashape",
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
            "metashape" | "agisoft" => Ok(CameraFormat::Metashape),
            _ => {
                anyhow::bail!("unknown camera format '{s}' (colmap, mvsnet, transforms, metashape)")
            }
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
    /// `transforms.json`'s `applied_transform`: `"undo"` (default) or `"keep"`
    /// ([`transforms::AppliedTransform`]).
    applied_transform: Option<transforms::AppliedTransform>,
    /// Leave out the views whose photo is not on disk (a trimmed copy of a public dataset)
    /// instead of refusing the scene ([`skip_missing_photos`]). Default false.
    skip_missing: Option<bool>,
}

/// What [`Scene::load_report`] found.
#[derive(Clone, Debug)]
pub struct LoadReport {
    pub format: CameraFormat,
    pub mesh_path: PathBuf,
    pub mesh_stats: mesh::MeshStats,
    /// What loading did that the user should know of (printed by the callers as they are).
    pub notes: Vec<String>,
    /// Things that load but are probably wrong (printed by the callers as `warning: …`).
    pub warnings: Vec<String>,
    /// The mesh against the reconstruction's points (`points.rs`): the points' file and what
    /// was measured; `None` without points (or when they could not be read).
    pub frame_check: Option<(PathBuf, points::Agreement)>,
    /// Views left out because their photo is not on disk (`skip_missing = true`; the note in
    /// `notes` names them).
    pub left_out: usize,
}

/// How far apart the mesh's size and the cameras' layout may be before the scene is flagged as a
/// probable unit or frame mismatch. Real scenes stay well inside: the mesh's bounding-box
/// diagonal is about 0.1–10 times the spread of the camera centres (object scans, aerial
/// surveys, indoor scans), and the cameras stand within a few diagonals of the mesh; a mesh in
/// millimetres with cameras in metres is off by 1000, the mismatches seen in practice by more.
pub const SCALE_MISMATCH: f64 = 1000.0;

/// A warning when the mesh is [`SCALE_MISMATCH`] times larger than the spread of the camera
/// centres (their bounding-box diagonal), or the cameras stand a median [`SCALE_MISMATCH`] mesh
/// diagonals away from its centre. (A ratio of the mesh's size to the cameras' distance from
/// its centre alone misses a mesh scaled about an origin far from it.)
pub fn scale_mismatch(mesh: &mesh::Mesh, views: &[View], mesh_path: &Path) -> Option<String> {
    let (lo, hi) = mesh.bbox();
    let diag = (hi - lo).length();
    if views.is_empty() || !(diag > 0.0 && diag.is_finite()) {
        return None;
    }
    let centres: Vec<DVec3> = views.iter().map(|v| v.camera.center()).collect();
    let (clo, chi) = centres.iter().fold(
        (DVec3::splat(f64::INFINITY), DVec3::splat(f64::NEG_INFINITY)),
        |(a, b), c| (a.min(*c), b.max(*c)),
    );
    let spread = (chi - clo).length();
    let mid = 0.5 * (lo + hi);
    let mut d: Vec<f64> = centres.iter().map(|c| (*c - mid).length()).collect();
    d.sort_by(f64::total_cmp);
    let away = d[d.len() / 2] / diag;
    let mesh_vs_rig = if spread > 0.0 { diag / spread } else { 1.0 };
    let what = if mesh_vs_rig > SCALE_MISMATCH {
        format!("the mesh is {diag:.3e} across, {mesh_vs_rig:.3e}× the spread of the camera centres ({spread:.3e})")
    } else if away > SCALE_MISMATCH {
        format!("the mesh is {diag:.3e} across and the cameras stand a median {away:.3e} of that from its centre")
    } else {
        return None;
    };
    Some(format!(
        "{}: {what}: mesh and cameras are probably in different units or frames (a mesh in \
         millimetres with cameras in metres, an unaligned reconstruction); training will run but \
         learn little",
        mesh_path.display()
    ))
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
    if metashape::find(dir).is_some() {
        out.push(CameraFormat::Metashape);
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
    // nerfstudio's sparse points (`ply_file_path`, e.g. sparse_pc.ply) are not a mesh.
    let points = transforms::declared_point_cloud(dir).and_then(|p| p.canonicalize().ok());
    let mut cands: Vec<PathBuf> = std::fs::read_dir(dir)
        .map_err(|e| anyhow::anyhow!("{}: cannot list scene directory: {e}", dir.display()))?
        .flatten()
        .map(|e| e.path())
        .filter(|p| {
            p.is_file()
                && p.extension()
                    .and_then(|e| e.to_str())
                    .is_some_and(|e| e.eq_ignore_ascii_case("ply") || e.eq_ignore_ascii_case("obj"))
                && (points.is_none() || p.canonicalize().ok() != points)
        })
        .collect();
    cands.sort();
    match cands.len() {
        1 => Ok(cands.pop().unwrap()),
        0 => anyhow::bail!(
            "{}: no mesh found (looked for mesh.ply, mesh.obj, meshed-poisson.ply / meshed-delaunay.ply here or in dense/0/, or a single *.ply/*.obj); name it with --mesh FILE, or put it in the folder as mesh.ply",
            dir.display()
        ),
        _ => anyhow::bail!(
            "{}: several mesh candidates ({}); choose one with --mesh (e.g. --mesh {}) or rename it mesh.ply",
            dir.display(),
            cands
                .iter()
                .map(|p| p.file_name().unwrap().to_string_lossy().to_string())
                .collect::<Vec<_>>()
                .join(", "),
            cands[0].display()
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

impl Scene {
    /// Load a scene directory: cameras (auto-detected or `opts.format`), the mesh, the split
    /// (`scene.toml` or every 7th view), the normalisation, and check the images (existence,
    /// and sizes if `opts.load_images_check`). Views keep the camera file's order (COLMAP: sorted
    /// by image name; MVSNet: by cam file name; transforms: frame order).
    pub fn load(dir: &Path, opts: &LoadOptions) -> Result<Scene> {
        Ok(Scene::load_report(dir, opts)?.0)
    }

    /// [`Scene::load`], also returning what was found (format, mesh file, mesh statistics such as
    /// the number of degenerate triangles dropped) for the CLI to report.
    pub fn load_report(dir: &Path, opts: &LoadOptions) -> Result<(Scene, LoadReport)> {
        if !dir.is_dir() {
            if dir.exists() {
                bail!(
                    "{}: is a file; --scene takes the scene's folder (the one holding the cameras, images and mesh)",
                    dir.display()
                );
            }
            bail!("{}: scene directory not found", dir.display());
        }
        if opts.downsample == 0 {
            bail!("downsample factor must be >= 1");
        }
        let toml_path = dir.join("scene.toml");
        let cfg = read_scene_toml(&toml_path)?;
        let format = choose_format(dir, opts, &cfg, &toml_path)?;
        let mut notes = Vec::new();
        let applied = cfg
            .applied_transform
            .unwrap_or(transforms::AppliedTransform::Undo);
        // Views whose photo is not on disk (`skip_missing_photos`).
        let mut missing = Vec::new();
        let (mut views, format_test, given_masks) = match format {
            CameraFormat::Colmap => (load_colmap(dir)?, None, None),
            CameraFormat::MvsNet => (load_mvsnet(dir, opts.mvsnet_dsp)?, None, None),
            CameraFormat::Metashape => {
                let xml = metashape::find(dir).ok_or_else(|| {
                    anyhow!(
                        "{}: no Metashape camera export ({} or a single Agisoft *.xml)",
                        dir.display(),
                        metashape::FILE
                    )
                })?;
                let loaded = metashape::load(&xml, &dir.join("images"))?;
                notes.extend(loaded.notes);
                (loaded.views, None, None)
            }
            CameraFormat::Transforms => {
                let (loaded, undone) = load_transforms(dir, applied, &mut notes, &mut missing)?;
                if let Some(file) = undone {
                    notes.push(format!(
                        "{}: its applied_transform is undone, so the cameras stand in the frame of the reconstruction it was written from (COLMAP's, Metashape's), where that reconstruction's meshes are; for a mesh in the file's own frame set applied_transform = \"keep\" in {}; a mesh from nerfstudio's ns-export stands in neither: `xscale align-mesh` brings it here",
                        file.display(),
                        toml_path.display()
                    ));
                }
                loaded
            }
        };
        // The other layouts name a photo whatever is on disk: a view whose file does not exist
        // is missing as a transforms frame whose photo was not found.
        if given_masks.is_none() {
            views.retain(|v| photo_on_disk(v, &mut missing));
        }
        skip_missing_photos(
            &missing,
            views.len(),
            cfg.skip_missing.unwrap_or(false),
            &toml_path,
            &mut notes,
        )?;
        check_views(dir, &views)?;
        check_images(&views, opts.load_images_check)?;
        downsample_cameras(&mut views, opts.downsample)?;
        let test = split(&views, &cfg, format_test, &toml_path)?;
        let mesh_path = match &opts.mesh {
            Some(p) if p.exists() || p.is_absolute() => p.clone(),
            Some(p) => dir.join(p),
            None => find_mesh(dir)?,
        };
        let (mesh, mesh_stats) = mesh::load_mesh(&mesh_path)?;
        let normalization = Normalization::from_mesh(&mesh, opts.normalize);
        let mut warnings: Vec<String> = scale_mismatch(&mesh, &views, &mesh_path)
            .into_iter()
            .collect();
        // The reconstruction's own points against the mesh (`points.rs`): an auxiliary file, so
        // one that cannot be read skips the check with a note rather than failing the scene.
        let frame_check = points_check(
            points::find(dir, format, applied),
            format,
            &views,
            &mesh,
            &mesh_path,
            &mut warnings,
            &mut notes,
        );
        let background = cfg.background.unwrap_or([1.0; 3]);
        if background.iter().any(|c| !(0.0..=1.0).contains(c)) {
            bail!(
                "{}: background {background:?}: expected three values in [0, 1]",
                toml_path.display()
            );
        }
        let masks = match given_masks {
            Some(files) => files.into_iter().map(MaskSource::File).collect(),
            None => find_masks(dir, &views, opts.load_images_check)?,
        };
        let scene = Scene {
            root: dir.to_path_buf(),
            mesh,
            views,
            test,
            normalization,
            downsample: opts.downsample,
            masks,
            background,
        };
        let report = LoadReport {
            format,
            mesh_path,
            mesh_stats,
            notes,
            warnings,
            frame_check,
            left_out: missing.len(),
        };
        Ok((scene, report))
    }
}

/// The map from the frame nerfstudio's `dataparser_transforms.json` leads back to (the
/// reconstruction's: [`transforms::DataparserTransform`]) to the frame `dir`'s cameras are read
/// in, `x' = r·x + t`; `None` when they are one frame. They differ for a transforms layout that
/// keeps its `applied_transform` (`scene.toml`), and for one without the key while a COLMAP
/// model in `colmap/sparse/0` beside it makes nerfstudio assume [`transforms::LEGACY_APPLIED`].
pub fn nerfstudio_original_to_cameras(dir: &Path) -> Result<Option<(DMat3, DVec3)>> {
    if !dir.is_dir() {
        bail!("{}: scene directory not found", dir.display());
    }
    let toml_path = dir.join("scene.toml");
    let cfg = read_scene_toml(&toml_path)?;
    if choose_format(dir, &LoadOptions::default(), &cfg, &toml_path)? != CameraFormat::Transforms {
        return Ok(None);
    }
    let file = &transforms_files(dir)?[0];
    let keep = cfg.applied_transform == Some(transforms::AppliedTransform::Keep);
    Ok(match transforms::applied_map(file)? {
        Some(m) if keep => Some(m),
        Some(_) => None,
        None if dir.join("colmap/sparse/0").is_dir() => Some(transforms::legacy_applied()),
        None => None,
    })
}

/// The optional `scene.toml` (an empty one when the file is absent).
fn read_scene_toml(path: &Path) -> Result<SceneToml> {
    if !path.is_file() {
        return Ok(SceneToml::default());
    }
    let text = crate::io::text::read(path)?;
    toml::from_str(&text).map_err(|e| anyhow!("{}: {e}", path.display()))
}

/// What the "no cameras found" error says about photos without poses.
pub const POSES_HINT: &str = "photos without poses get them from COLMAP (`colmap feature_extractor`, `exhaustive_matcher` and `mapper` write a sparse model that --scene can point at; the README's \"Your own data\" has the commands) or from Metashape (align the photos, then export the cameras as cameras.xml beside an images/ folder)";

/// The camera layout: the option, else `scene.toml`'s `format`, else the single one detected.
fn choose_format(
    dir: &Path,
    opts: &LoadOptions,
    cfg: &SceneToml,
    toml_path: &Path,
) -> Result<CameraFormat> {
    let toml_format = match &cfg.format {
        Some(name) => Some(
            name.parse::<CameraFormat>()
                .map_err(|e| anyhow!("{}: format: {e}", toml_path.display()))?,
        ),
        None => None,
    };
    if let Some(f) = opts.format.or(toml_format) {
        return Ok(f);
    }
    match detect_formats(dir).as_slice() {
        [f] => Ok(*f),
        [] => {
            // A COLMAP project's root keeps its undistorted workspace (cameras, images, mesh)
            // in dense/N/: name it rather than leave the user to guess.
            let inner: Vec<PathBuf> = ["dense/0", "dense"]
                .iter()
                .map(|d| dir.join(d))
                .filter(|d| d.is_dir() && !detect_formats(d).is_empty())
                .collect();
            let hint = match (inner.first(), colmap::incomplete_model(dir)) {
                (Some(d), _) => format!(
                    "; {} holds a scene (a COLMAP dense workspace?): use --scene {}",
                    d.display(),
                    d.display()
                ),
                (None, Some(part)) => format!("; {part}"),
                (None, None) => String::new(),
            };
            bail!(
                "{}: no cameras found (looked for the four layouts xscale reads: transforms.json (instant-ngp / nerfstudio), a COLMAP model (cameras and images, .txt or .bin) in sparse/0/, sparse/ or the folder itself, MVSNet cams_<dsp>/*_cam.txt, and Metashape's cameras.xml){hint}; {POSES_HINT}",
                dir.display()
            )
        }
        many => bail!(
            "{}: several camera formats present ({}); choose one by writing `format = \"{}\"` (or another of them) into {}",
            dir.display(),
            many.iter().map(|f| f.name()).collect::<Vec<_>>().join(", "),
            many[0].name(),
            dir.join("scene.toml").display()
        ),
    }
}

/// COLMAP: the model in `dense/0/sparse/`, `sparse/0/`, `sparse/` or the dir itself.
fn load_colmap(dir: &Path) -> Result<Vec<View>> {
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
    colmap::load(&layout.model, &layout.images)
}

/// MVSNet: `cams_<dsp>/`, the requested dsp or the smallest.
fn load_mvsnet(dir: &Path, dsp: Option<u32>) -> Result<Vec<View>> {
    let layouts = mvsnet::find_layouts(dir);
    let layout = match dsp {
        Some(d) => layouts
            .into_iter()
            .find(|l| l.dsp == Some(d))
            .ok_or_else(|| anyhow!("{}: no cams_{d}/ with *_cam.txt files", dir.display()))?,
        None => layouts
            .into_iter()
            .next()
            .ok_or_else(|| anyhow!("{}: no cams_<dsp>/ with *_cam.txt files", dir.display()))?,
    };
    mvsnet::load(&layout)
}

/// The views of a layout, the layout's own test split (view names) and the mask files its
/// frames name (one per view).
type LoadedViews = (Vec<View>, Option<Vec<String>>, Option<Vec<PathBuf>>);

/// The camera files of a transforms layout: `transforms.json`, else NeRF-synthetic
/// `transforms_train.json` with the `_val` and `_test` files that exist (train first).
fn transforms_files(dir: &Path) -> Result<Vec<PathBuf>> {
    let single = dir.join("transforms.json");
    if single.is_file() {
        return Ok(vec![single]);
    }
    if !dir.join("transforms_train.json").is_file() {
        bail!("{}: transforms.json not found", dir.display());
    }
    Ok(["train", "val", "test"]
        .iter()
        .map(|s| dir.join(format!("transforms_{s}.json")))
        .filter(|p| p.is_file())
        .collect())
}

/// `transforms.json`, or NeRF-synthetic `transforms_{train,val,test}.json` (the test file's
/// views are returned as the format's own test split), with the frames' `mask_path` files when
/// every frame gives one, and the first file whose `applied_transform` was undone; a file that
/// looks written by instant-ngp's `colmap2nerf.py` is named in `notes`.
/// Frames whose photo is not on disk are left out and described in `missing`.
fn load_transforms(
    dir: &Path,
    applied: transforms::AppliedTransform,
    notes: &mut Vec<String>,
    missing: &mut Vec<String>,
) -> Result<(LoadedViews, Option<PathBuf>)> {
    let files = transforms_files(dir)?;
    let nerf_synthetic = !files[0].ends_with("transforms.json");
    let split_files: Vec<String> = ["train", "val", "test"]
        .iter()
        .map(|s| format!("transforms_{s}.json"))
        .filter(|f| dir.join(f).is_file())
        .collect();
    if !nerf_synthetic && !split_files.is_empty() {
        notes.push(format!(
            "{}: read alone; {} beside it are not read (their split neither): to use them, move transforms.json away",
            files[0].display(),
            split_files.join(", ")
        ));
    }
    // NeRF-synthetic: the test file's views are the split (none without a test file).
    let mut test = nerf_synthetic.then(Vec::new);
    let (mut views, mut masks, mut undone) = (Vec::new(), Vec::new(), None);
    for f in &files {
        let loaded = transforms::load_full(f, applied)?;
        if f.ends_with("transforms_test.json") {
            test = Some(loaded.views.iter().map(|x| x.name.clone()).collect());
        }
        if loaded.undone && undone.is_none() {
            undone = Some(f.clone());
        }
        if loaded.ngp_rescaled {
            notes.push(format!(
                "{}: written by instant-ngp's colmap2nerf.py, it seems (its frames have 'sharpness' and the cameras stand a mean {} from the origin): that script turns, moves and scales COLMAP's poses without recording how, so a mesh of the COLMAP reconstruction does not stand in this frame; run it with --keep_colmap_coords, or give xscale the COLMAP model itself (sparse/0 with images/)",
                f.display(),
                transforms::NGP_MEAN_DISTANCE
            ));
        }
        views.extend(loaded.views);
        masks.extend(loaded.masks.into_iter().map(|m| (f, m)));
        missing.extend(loaded.missing);
    }
    let given = masks.iter().filter(|(_, m)| m.is_some()).count();
    if given == 0 {
        return Ok(((views, test, None), undone));
    }
    if let Some(k) = masks.iter().position(|(_, m)| m.is_none()) {
        bail!(
            "{}: {given} of {} frames give a mask_path, but view '{}' has none: give every frame one or none (nerfstudio's rule)",
            masks[k].0.display(),
            masks.len(),
            views[k].name
        );
    }
    let files = masks.into_iter().filter_map(|(_, m)| m).collect();
    Ok(((views, test, Some(files)), undone))
}

/// Views whose photo is not on disk (`missing`, one description each; `kept` views remain):
/// an error naming them and the way to leave them out, or, with `skip_missing = true` in the
/// scene's `scene.toml` (`toml_path`), a note naming them. A `scene.toml` key rather than a
/// command-line flag: every command that reads the scene (train, cast, eval, render) must see the
/// same views, or the held-out split (every 7th view) would differ between training and scoring.
/// Whether view `v`'s photo exists; when not, the reason is added to `missing`.
fn photo_on_disk(v: &View, missing: &mut Vec<String>) -> bool {
    let on_disk = v.image_path.exists();
    if !on_disk {
        missing.push(format!(
            "{}: image of view '{}' not found",
            v.image_path.display(),
            v.name
        ));
    }
    on_disk
}

/// The reconstruction's own points against the mesh (`points.rs`): an auxiliary file, so one
/// that cannot be read skips the check with a note rather than failing the scene.
fn points_check(
    found: Result<Option<points::SparsePoints>>,
    format: CameraFormat,
    views: &[View],
    mesh: &super::Mesh,
    mesh_path: &Path,
    warnings: &mut Vec<String>,
    notes: &mut Vec<String>,
) -> Option<(PathBuf, points::Agreement)> {
    match found {
        Ok(Some(p)) => {
            let cameras: Vec<&super::Camera> = views.iter().map(|v| &v.camera).collect();
            let seen = points::seen_size(mesh, &cameras);
            let agreement = points::check(mesh, &p.xyz, seen);
            warnings.extend(
                points::frame_disagreement(mesh_path, &p.source, &agreement).map(|w| {
                    if format == CameraFormat::Transforms {
                        format!("{w}. A mesh from nerfstudio's ns-export stands in its dataparser's frame: bring it back with `xscale align-mesh`")
                    } else {
                        w
                    }
                }),
            );
            Some((p.source, agreement))
        }
        Ok(None) => None,
        Err(e) => {
            notes.push(format!(
                "the check of the mesh against the reconstruction's points is skipped: {e:#}"
            ));
            None
        }
    }
}

fn skip_missing_photos(
    missing: &[String],
    kept: usize,
    skip: bool,
    toml_path: &Path,
    notes: &mut Vec<String>,
) -> Result<()> {
    if missing.is_empty() {
        return Ok(());
    }
    const SHOWN: usize = 8;
    let mut list = missing[..missing.len().min(SHOWN)].join("\n  ");
    if missing.len() > SHOWN {
        list += &format!("\n  … and {} more", missing.len() - SHOWN);
    }
    let total = missing.len() + kept;
    if !skip {
        bail!(
            "{} of {total} views have no photo on disk:\n  {list}\nput the photos in place, or add `skip_missing = true` to {} to leave these views out (train, cast, eval and render then all use the {kept} that remain)",
            missing.len(),
            toml_path.display()
        );
    }
    if kept == 0 {
        bail!(
            "none of the {total} views has a photo on disk ({} says skip_missing = true):\n  {list}",
            toml_path.display()
        );
    }
    notes.push(format!(
        "{} of {total} views have no photo on disk and are left out (skip_missing = true in {}); the held-out split is taken over the {kept} that remain:\n  {list}",
        missing.len(),
        toml_path.display()
    ));
    Ok(())
}

/// At least one view, and unique names.
fn check_views(dir: &Path, views: &[View]) -> Result<()> {
    if views.is_empty() {
        bail!("{}: the camera file has no views", dir.display());
    }
    let mut seen = std::collections::HashSet::new();
    for v in views {
        if !seen.insert(v.name.as_str()) {
            bail!("{}: view name '{}' appears twice", dir.display(), v.name);
        }
    }
    Ok(())
}

/// Every image exists; with `check_sizes`, its header size matches the camera (or does after
/// its EXIF orientation).
fn check_images(views: &[View], check_sizes: bool) -> Result<()> {
    for v in views {
        if !v.image_path.is_file() {
            bail!(
                "{}: image of view '{}' {}",
                v.image_path.display(),
                v.name,
                if v.image_path.is_dir() {
                    "is a directory, not a file"
                } else {
                    "not found"
                }
            );
        }
        if !check_sizes {
            continue;
        }
        let (w, h) = image::dimensions(&v.image_path)?;
        if (w, h) != (v.camera.width, v.camera.height) && !v.needs_orientation(1)? {
            let tag = match image::exif_orientation(&v.image_path)? {
                Some(o) => format!(" (its EXIF orientation {o:?} does not explain it either)"),
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
    Ok(())
}

/// Scale every camera to the downsampled image size.
fn downsample_cameras(views: &mut [View], s: u32) -> Result<()> {
    if s <= 1 {
        return Ok(());
    }
    for v in views {
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
    Ok(())
}

/// The held-out views: `scene.toml`'s `test_views` or `holdout_every`, else the format's own
/// test split, else every [`HOLDOUT_EVERY`]th view.
fn split(
    views: &[View],
    cfg: &SceneToml,
    format_test: Option<Vec<String>>,
    toml_path: &Path,
) -> Result<Vec<usize>> {
    if let Some(names) = &cfg.test_views {
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
        return Ok(t);
    }
    Ok(match (cfg.holdout_every, format_test) {
        (Some(0), _) => Vec::new(),
        (Some(k), _) => (0..views.len()).step_by(k).collect(),
        (None, Some(names)) => {
            let mut t: Vec<usize> = names
                .iter()
                .filter_map(|n| views.iter().position(|v| &v.name == n))
                .collect();
            t.sort_unstable();
            t
        }
        (None, None) => (0..views.len()).step_by(HOLDOUT_EVERY).collect(),
    })
}
