//! instant-ngp / nerfstudio `transforms.json` (SPEC §3).
//!
//! Intrinsics `fl_x, fl_y, cx, cy, w, h` are read per frame, falling back to the top level;
//! when `fl_x` is absent, `camera_angle_x` gives `fl_x = w / (2 tan(angle_x / 2))` (likewise
//! `fl_y` from `camera_angle_y`, else `fl_y = fl_x`); `cx, cy` default to `w/2, h/2`; `w, h`
//! default to the image header. `camera_model` (per frame, else top level, default OPENCV):
//! OPENCV / PINHOLE / SIMPLE_PINHOLE read `k1, k2, p1, p2` (non-zero: OpenCV distortion; a
//! non-zero `k3`/`k4` is an error), OPENCV_FISHEYE (nerfstudio) reads `k1 … k4`; any other model
//! (EQUIRECTANGULAR, …) is an error naming it.
//!
//! Poses: `transform_matrix` is camera→world in OpenGL axes (x right, y up, z backward). We
//! convert to OpenCV world→camera: `R_c2w_cv = R_c2w_gl · diag(1,-1,-1)`, `R = R_c2w_cvᵀ`,
//! `t = -R c`. The rotation block must be orthonormal to 1e-3 (files written in f32 are fine;
//! scaled matrices are rejected).
//!
//! `file_path` is relative to the JSON file; instant-ngp often omits the extension, so if the
//! path is not a file, `.png`, `.jpg`, `.jpeg`, `.exr` (and upper-case) are tried. The view
//! name is `file_path` without a leading `./`, plus the extension found. Views keep the file's
//! frame order.
//!
//! A top-level `applied_transform` (nerfstudio: the rigid map it applied to the reconstruction's
//! poses) is undone by default, so the cameras stand where the reconstruction's meshes are
//! ([`AppliedTransform`]; `applied_transform = "keep"` in `scene.toml` keeps the file's frame).
//!
//! A frame's `mask_path` (nerfstudio), relative to the JSON file like `file_path`, is that view's
//! object mask (`scene/mask.rs`); nerfstudio's rule holds: every frame has one or none does.

use super::{Camera, Distortion, View};
use anyhow::{anyhow, bail, Context, Result};
use glam::{DMat3, DVec3};
use serde_json::{json, Map, Value};
use std::fs;
use std::path::{Path, PathBuf};

/// Parse a JSON file with an error naming the file, line and column.
fn read_json(path: &Path) -> Result<Value> {
    let text = crate::io::text::read(path)?;
    serde_json::from_str(&text).map_err(|e| {
        anyhow!(
            "{}: line {} column {}: malformed JSON: {e}",
            path.display(),
            e.line(),
            e.column()
        )
    })
}

/// A numeric field from the frame, else the top level.
fn num(
    p: &str,
    frame: &Map<String, Value>,
    top: &Map<String, Value>,
    key: &str,
) -> Result<Option<f64>> {
    let v = frame.get(key).or_else(|| top.get(key));
    match v {
        None | Some(Value::Null) => Ok(None),
        Some(Value::Number(n)) => {
            let x = n.as_f64().unwrap_or(f64::NAN);
            if !x.is_finite() {
                bail!("{p}: '{key}' is not finite");
            }
            Ok(Some(x))
        }
        Some(other) => bail!("{p}: '{key}' must be a number, found {other}"),
    }
}

/// A field of view in radians (`camera_angle_x` / `_y`), which must lie in (0, π).
fn field_of_view(
    p: &str,
    frame: &Map<String, Value>,
    top: &Map<String, Value>,
    key: &str,
) -> Result<Option<f64>> {
    match num(p, frame, top, key)? {
        Some(a) if !(a > 0.0 && a < std::f64::consts::PI) => bail!(
            "{p}: '{key}' = {a} must be an angle in (0, π) radians{}",
            if (std::f64::consts::PI..360.0).contains(&a) {
                " (given in degrees?)"
            } else {
                ""
            }
        ),
        a => Ok(a),
    }
}

/// Resolve a frame's image path relative to `base`; returns (path, view name).
fn resolve_image(base: &Path, file_path: &str) -> Option<(PathBuf, String)> {
    let rel = file_path.strip_prefix("./").unwrap_or(file_path);
    let direct = base.join(rel);
    if direct.is_file() {
        return Some((direct, rel.to_string()));
    }
    for e in super::mvsnet::IMAGE_EXTS {
        let name = format!("{rel}.{e}");
        let p = base.join(&name);
        if p.is_file() {
            return Some((p, name));
        }
    }
    None
}

/// Load all frames of a transforms file; a frame whose photo is not on disk is an error.
pub fn load(path: &Path) -> Result<Vec<View>> {
    let loaded = load_full(path, AppliedTransform::Undo)?;
    if let Some(m) = loaded.missing.first() {
        bail!("{m}");
    }
    Ok(loaded.views)
}

/// What to do with a file's top-level `applied_transform` (nerfstudio): the map its writer
/// applied to the poses of the reconstruction it read (`ns-process-data` from COLMAP: world
/// `(x, y, z) → (x, z, −y)`; also written by its Metashape converter), and to the point cloud it
/// exported with them — not to a mesh the user made from the same reconstruction.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum AppliedTransform {
    /// Take the poses back to the reconstruction's frame, where its multi-view-stereo meshes
    /// are (COLMAP's dense `meshed-*.ply`, Metashape's export). The default.
    Undo,
    /// Keep the file's frame (a mesh made in it).
    Keep,
}

/// A transforms file's contents ([`load_full`]).
pub struct Loaded {
    pub views: Vec<View>,
    /// Each frame's `mask_path` (nerfstudio's per-frame object mask; `scene/mask.rs`), resolved
    /// against the file's folder like `file_path`; `None` for a frame without one.
    pub masks: Vec<Option<PathBuf>>,
    /// The frames whose photo is not on disk, left out of `views` and `masks`: what was tried
    /// for each (`FILE: frame i ('path'): image not found: tried …`). [`Scene::load`] refuses
    /// the scene when there are any, unless its `scene.toml` says `skip_missing = true`.
    ///
    /// [`Scene::load`]: crate::scene::Scene::load
    pub missing: Vec<String>,
    /// Whether the file has an `applied_transform` that was undone.
    pub undone: bool,
    /// Whether the file looks written by instant-ngp's `colmap2nerf.py` without
    /// `--keep_colmap_coords` ([`NGP_MEAN_DISTANCE`]).
    pub ngp_rescaled: bool,
}

/// instant-ngp's `colmap2nerf.py`, unless run with `--keep_colmap_coords`, turns the COLMAP
/// poses up to +z, moves the point the cameras look at to the origin and scales the poses so that
/// the cameras stand a mean of exactly this far from it — without recording the map. Its frames
/// also carry a `sharpness` key. A file with both is taken to be its output.
pub const NGP_MEAN_DISTANCE: f64 = 4.0;

/// [`load`], with the frames' mask files (a `mask_path` naming no file is an error) and the
/// file's `applied_transform` undone or kept.
pub fn load_full(path: &Path, applied: AppliedTransform) -> Result<Loaded> {
    let pd = path.display().to_string();
    let root = read_json(path)?;
    let top = root
        .as_object()
        .ok_or_else(|| anyhow!("{pd}: expected a JSON object at the top level"))?;
    let undo = match top.get("applied_transform") {
        Some(m) if applied == AppliedTransform::Undo => Some(world_map(&pd, m)?),
        _ => None,
    };
    let base = path.parent().unwrap_or(Path::new("."));
    let top_model = camera_model(&pd, top, None)?;
    let frames = top
        .get("frames")
        .and_then(|f| f.as_array())
        .ok_or_else(|| anyhow!("{pd}: no 'frames' array"))?;
    if frames.is_empty() {
        bail!("{pd}: 'frames' is empty");
    }
    let mut views = Vec::with_capacity(frames.len());
    let mut masks = Vec::with_capacity(frames.len());
    let mut missing = Vec::new();
    for (i, f) in frames.iter().enumerate() {
        let wh = format!("{pd}: frame {i}");
        let fr = f
            .as_object()
            .ok_or_else(|| anyhow!("{wh}: expected an object"))?;
        let file_path = fr
            .get("file_path")
            .and_then(|v| v.as_str())
            .ok_or_else(|| anyhow!("{wh}: missing string 'file_path'"))?;
        let wh = format!("{wh} ('{file_path}')");
        let model = camera_model(&wh, fr, top_model)?.unwrap_or("OPENCV");
        let Some((image_path, name)) = resolve_image(base, file_path) else {
            missing.push(format!(
                "{wh}: image not found: tried {} and with extensions {}",
                base.join(file_path.strip_prefix("./").unwrap_or(file_path))
                    .display(),
                super::mvsnet::IMAGE_EXTS.join(",")
            ));
            continue;
        };
        let (mut rotation, mut translation) = pose(&wh, fr)?;
        if let Some((r, t)) = undo {
            // The file's world point is x' = r·x + t of the reconstruction's x, and its camera
            // maps x' to rotation·x' + translation.
            translation += rotation * t;
            rotation *= r;
        }
        let camera = intrinsics(&wh, fr, top, model, &image_path, rotation, translation)?;
        masks.push(mask_path(&wh, base, fr)?);
        views.push(View {
            name,
            camera,
            image_path,
        });
    }
    let ngp_rescaled = undo.is_none()
        && views.len() >= 2
        && frames.iter().all(|f| f.get("sharpness").is_some())
        && {
            let mean = views
                .iter()
                .map(|v| v.camera.center().length())
                .sum::<f64>()
                / views.len() as f64;
            (mean - NGP_MEAN_DISTANCE).abs() <= 1e-5 * NGP_MEAN_DISTANCE
        };
    Ok(Loaded {
        views,
        masks,
        missing,
        undone: undo.is_some(),
        ngp_rescaled,
    })
}

/// The file a transforms file's `ply_file_path` names (relative to the file), if any.
fn ply_path(path: &Path, root: &Value) -> Result<Option<PathBuf>> {
    let Some(rel) = root.get("ply_file_path") else {
        return Ok(None);
    };
    let rel = rel.as_str().ok_or_else(|| {
        anyhow!(
            "{}: 'ply_file_path' must be a string, got {rel}",
            path.display()
        )
    })?;
    let base = path.parent().unwrap_or(Path::new("."));
    Ok(Some(base.join(rel.strip_prefix("./").unwrap_or(rel))))
}

/// The point cloud `dir/transforms.json` declares (`ply_file_path`), if the file reads and names
/// one: not a mesh candidate.
pub fn declared_point_cloud(dir: &Path) -> Option<PathBuf> {
    let path = dir.join("transforms.json");
    let root = read_json(&path).ok()?;
    ply_path(&path, &root).ok().flatten()
}

/// The point cloud a transforms file names (nerfstudio's top-level `ply_file_path`, relative to
/// the file: the reconstruction's sparse points, which its writer moved by `applied_transform`
/// with the poses), in the frame [`load_full`] gives the cameras; `None` without the key.
pub fn sparse_points(
    path: &Path,
    applied: AppliedTransform,
) -> Result<Option<(PathBuf, Vec<DVec3>)>> {
    let pd = path.display().to_string();
    let root = read_json(path)?;
    let Some(ply) = ply_path(path, &root)? else {
        return Ok(None);
    };
    let mut xyz = super::mesh::load_ply_points(&ply)?;
    if let (AppliedTransform::Undo, Some(m)) = (applied, root.get("applied_transform")) {
        // x' = r·x + t, so x = rᵀ·(x' − t).
        let (r, t) = world_map(&pd, m)?;
        let rt = r.transpose();
        for p in &mut xyz {
            *p = rt * (*p - t);
        }
    }
    Ok(Some((ply, xyz)))
}

/// `applied_transform` (3×4, or 4×4 with last row [0, 0, 0, 1]) as the rigid world map
/// `x' = r·x + t`; its 3×3 part must be a rotation to 1e-6 (nerfstudio's are axis permutations).
fn world_map(pd: &str, m: &Value) -> Result<(DMat3, DVec3)> {
    let wh = format!("{pd}: 'applied_transform'");
    let (r, t) = affine_map(&affine_rows(&wh, m)?);
    if let Some(why) = not_a_rotation(&r, 1e-6) {
        bail!("{wh}: its 3x3 part {why}; set applied_transform = \"keep\" in scene.toml to use the poses as written");
    }
    Ok((r, t))
}

/// Rows `[A | a]` as the matrix `A` and the vector `a`.
fn affine_map(a: &[[f64; 4]; 3]) -> (DMat3, DVec3) {
    let m = DMat3::from_cols_array_2d(&[
        [a[0][0], a[1][0], a[2][0]],
        [a[0][1], a[1][1], a[2][1]],
        [a[0][2], a[1][2], a[2][2]],
    ]);
    (m, DVec3::new(a[0][3], a[1][3], a[2][3]))
}

/// A frame's `mask_path`, if it has one: relative to the JSON file's folder, and an existing file.
fn mask_path(wh: &str, base: &Path, fr: &Map<String, Value>) -> Result<Option<PathBuf>> {
    let Some(v) = fr.get("mask_path") else {
        return Ok(None);
    };
    let rel = v
        .as_str()
        .ok_or_else(|| anyhow!("{wh}: 'mask_path' must be a string, got {v}"))?;
    let p = base.join(rel.strip_prefix("./").unwrap_or(rel));
    if !p.is_file() {
        bail!("{wh}: mask_path '{rel}': {} not found", p.display());
    }
    Ok(Some(p))
}

/// The lens model an object (a frame, or the top level) names, else `inherited` (the top
/// level's, for a frame): its `camera_model` string, or instant-ngp's `is_fisheye: true`
/// (`colmap2nerf.py`: its `k1 … k4` are OpenCV fisheye terms), which means OPENCV_FISHEYE.
fn camera_model<'a>(
    wh: &str,
    obj: &'a Map<String, Value>,
    inherited: Option<&'a str>,
) -> Result<Option<&'a str>> {
    let named = match obj.get("camera_model") {
        None | Some(Value::Null) => None,
        Some(Value::String(m)) if MODELS.contains(&m.as_str()) => Some(m.as_str()),
        Some(Value::String(m)) => bail!(
            "{wh}: camera_model '{m}' is not supported ({})",
            MODELS.join(", ")
        ),
        Some(other) => bail!("{wh}: 'camera_model' must be a string, found {other}"),
    };
    let fisheye = match obj.get("is_fisheye") {
        None | Some(Value::Null) => None,
        Some(Value::Bool(b)) => Some(*b),
        Some(other) => bail!("{wh}: 'is_fisheye' must be true or false, found {other}"),
    };
    match (named, fisheye) {
        (Some(m), Some(true)) if m != "OPENCV_FISHEYE" => {
            bail!("{wh}: camera_model '{m}' contradicts 'is_fisheye: true'")
        }
        (Some(m), _) => Ok(Some(m)),
        (None, Some(true)) => Ok(Some("OPENCV_FISHEYE")),
        (None, Some(false)) => Ok(inherited
            .filter(|m| *m != "OPENCV_FISHEYE")
            .or(Some("OPENCV"))),
        (None, None) => Ok(inherited),
    }
}

/// A frame's `transform_matrix` (4x4, or 3x4; camera→world, OpenGL axes) as the world→camera
/// rotation and translation in OpenCV axes.
fn pose(wh: &str, fr: &Map<String, Value>) -> Result<(DMat3, DVec3)> {
    let m = fr
        .get("transform_matrix")
        .ok_or_else(|| anyhow!("{wh}: missing 'transform_matrix' (4x4 array)"))?;
    let a = affine_rows(&format!("{wh}: 'transform_matrix'"), m)?;
    // Columns of the camera→world rotation in OpenCV axes: x, -y, -z of the GL one.
    let col = |c: usize, s: f64| DVec3::new(s * a[0][c], s * a[1][c], s * a[2][c]);
    let c2w = DMat3::from_cols(col(0, 1.0), col(1, -1.0), col(2, -1.0));
    if let Some(why) = not_a_rotation(&c2w, 1e-3) {
        bail!("{wh}: the rotation part of 'transform_matrix' {why}");
    }
    let center = DVec3::new(a[0][3], a[1][3], a[2][3]);
    let rotation = c2w.transpose();
    Ok((rotation, -(rotation * center)))
}

/// The top three rows of a 3×4, or 4×4 with last row [0, 0, 0, 1], matrix of finite numbers;
/// errors start with `wh` (the file, frame and key).
fn affine_rows(wh: &str, m: &Value) -> Result<[[f64; 4]; 3]> {
    let rows = m
        .as_array()
        .filter(|r| r.len() == 3 || r.len() == 4)
        .ok_or_else(|| anyhow!("{wh} must be a 4x4 (or 3x4) array"))?;
    let mut a = [[0f64; 4]; 4];
    for (r, row) in rows.iter().enumerate() {
        let row = row
            .as_array()
            .filter(|row| row.len() == 4)
            .ok_or_else(|| anyhow!("{wh} row {r} must have 4 numbers"))?;
        for (c, v) in row.iter().enumerate() {
            a[r][c] = v
                .as_f64()
                .filter(|x| x.is_finite())
                .ok_or_else(|| anyhow!("{wh}[{r}][{c}] is not a finite number"))?;
        }
    }
    if rows.len() == 4 && a[3] != [0.0, 0.0, 0.0, 1.0] {
        bail!("{wh}: last row must be [0,0,0,1], found {:?}", a[3]);
    }
    Ok([a[0], a[1], a[2]])
}

/// max |RᵀR − I|: how far a matrix is from orthonormal.
/// Why `r` is not a rotation (orthonormal to `tol`, determinant +1), or `None` if it is one.
pub(crate) fn not_a_rotation(r: &DMat3, tol: f64) -> Option<String> {
    let ortho = non_orthonormality(r);
    let det = r.determinant();
    if ortho > tol {
        Some(format!("is not a rotation (|RᵀR − I| = {ortho:.2e})"))
    } else if det <= 0.0 {
        Some(format!(
            "has determinant {det:.3}: a reflection (a left-handed frame), not a rotation"
        ))
    } else {
        None
    }
}

fn non_orthonormality(r: &DMat3) -> f64 {
    (r.transpose() * *r - DMat3::IDENTITY)
        .to_cols_array()
        .iter()
        .fold(0f64, |mx, v| mx.max(v.abs()))
}

/// A frame's camera: size (or the image's), focal lengths (or field of view), principal point
/// and distortion, each from the frame or else the top level.
fn intrinsics(
    wh: &str,
    fr: &Map<String, Value>,
    top: &Map<String, Value>,
    model: &str,
    image_path: &Path,
    rotation: DMat3,
    translation: DVec3,
) -> Result<Camera> {
    let mut w = num(wh, fr, top, "w")?;
    let mut h = num(wh, fr, top, "h")?;
    if w.is_none() || h.is_none() {
        let (iw, ih) = super::image::dimensions(image_path)?;
        w = w.or(Some(iw as f64));
        h = h.or(Some(ih as f64));
    }
    let (w, h) = (w.unwrap(), h.unwrap());
    if !(w >= 1.0
        && h >= 1.0
        && w.fract() == 0.0
        && h.fract() == 0.0
        && w <= u32::MAX as f64
        && h <= u32::MAX as f64)
    {
        bail!("{wh}: image size w={w}, h={h} must be positive integers");
    }
    let fx = match num(wh, fr, top, "fl_x")? {
        Some(f) => f,
        None => match field_of_view(wh, fr, top, "camera_angle_x")? {
            Some(ax) => 0.5 * w / (0.5 * ax).tan(),
            None => bail!("{wh}: no focal length: neither 'fl_x' nor 'camera_angle_x' given"),
        },
    };
    let fy = match num(wh, fr, top, "fl_y")? {
        Some(f) => f,
        None => match field_of_view(wh, fr, top, "camera_angle_y")? {
            Some(ay) => 0.5 * h / (0.5 * ay).tan(),
            None => fx,
        },
    };
    if !(fx > 0.0 && fy > 0.0 && fx.is_finite() && fy.is_finite()) {
        bail!("{wh}: focal lengths must be positive (fl_x={fx}, fl_y={fy})");
    }
    let cx = num(wh, fr, top, "cx")?.unwrap_or(0.5 * w);
    let cy = num(wh, fr, top, "cy")?.unwrap_or(0.5 * h);
    let mut k = [0.0; 4];
    for (i, key) in ["k1", "k2", "k3", "k4"].iter().enumerate() {
        k[i] = num(wh, fr, top, key)?.unwrap_or(0.0);
    }
    let p1 = num(wh, fr, top, "p1")?.unwrap_or(0.0);
    let p2 = num(wh, fr, top, "p2")?.unwrap_or(0.0);
    let distortion = if model == "OPENCV_FISHEYE" {
        if p1 != 0.0 || p2 != 0.0 {
            bail!("{wh}: OPENCV_FISHEYE has no tangential terms, but p1/p2 are given");
        }
        Distortion::Fisheye { k }
    } else {
        for key in ["k3", "k4"] {
            if num(wh, fr, top, key)?.unwrap_or(0.0) != 0.0 {
                bail!("{wh}: distortion term '{key}' needs camera_model OPENCV_FISHEYE (OPENCV has k1, k2, p1, p2)");
            }
        }
        let [k1, k2, ..] = k;
        if k1 == 0.0 && k2 == 0.0 && p1 == 0.0 && p2 == 0.0 {
            Distortion::None
        } else {
            Distortion::OpenCv { k1, k2, p1, p2 }
        }
    };
    Ok(Camera {
        width: w as u32,
        height: h as u32,
        fx,
        fy,
        cx,
        cy,
        distortion,
        rotation,
        translation,
    })
}

/// Intrinsics as JSON fields (`camera_model`, `fl_x`, …, `k1, k2, p1, p2` or OPENCV_FISHEYE's
/// `k1 … k4`); a distortion transforms.json cannot express is an error.
fn intrinsics_json(c: &Camera) -> Result<Map<String, Value>> {
    let mut v = json!({
        "camera_model": "OPENCV",
        "fl_x": c.fx, "fl_y": c.fy, "cx": c.cx, "cy": c.cy,
        "w": c.width, "h": c.height,
    });
    let o = v.as_object_mut().unwrap();
    let (k1, k2, p1, p2) = match c.distortion {
        Distortion::None => (0.0, 0.0, 0.0, 0.0),
        Distortion::SimpleRadial { k } => (k, 0.0, 0.0, 0.0),
        Distortion::Radial { k1, k2 } => (k1, k2, 0.0, 0.0),
        Distortion::OpenCv { k1, k2, p1, p2 } => (k1, k2, p1, p2),
        Distortion::Fisheye { k } => {
            o.insert("camera_model".into(), json!("OPENCV_FISHEYE"));
            for (i, key) in ["k1", "k2", "k3", "k4"].iter().enumerate() {
                o.insert((*key).into(), json!(k[i]));
            }
            return Ok(o.clone());
        }
        other => bail!(
            "transforms.json cannot express the lens distortion {other:?} (OPENCV and OPENCV_FISHEYE only); write COLMAP instead"
        ),
    };
    for (key, val) in [("k1", k1), ("k2", k2), ("p1", p1), ("p2", p2)] {
        o.insert(key.into(), json!(val));
    }
    Ok(o.clone())
}

/// `camera_model` values read: OpenCV's pinhole family and nerfstudio's fisheye.
const MODELS: [&str; 4] = ["OPENCV", "PINHOLE", "SIMPLE_PINHOLE", "OPENCV_FISHEYE"];

/// Write a transforms.json: intrinsics at the top level when all views share them, else per
/// frame; `file_path = image_prefix + view.name`; camera→world OpenGL `transform_matrix`.
/// Numbers are written by serde_json (shortest round-trip f64). Distortion is written as
/// OpenCV `k1, k2, p1, p2` (SIMPLE_RADIAL/RADIAL map onto it exactly; it reads back as
/// `Distortion::OpenCv`).
pub fn write(path: &Path, views: &[View], image_prefix: &str) -> Result<()> {
    let shared = views.windows(2).all(|w| {
        let (a, b) = (&w[0].camera, &w[1].camera);
        a.width == b.width
            && a.height == b.height
            && a.fx == b.fx
            && a.fy == b.fy
            && a.cx == b.cx
            && a.cy == b.cy
            && a.distortion == b.distortion
    });
    let mut top = Map::new();
    if shared {
        if let Some(v) = views.first() {
            top.extend(intrinsics_json(&v.camera)?);
        }
    }
    let frames: Vec<Value> = views
        .iter()
        .map(|v| -> Result<Value> {
            let c = &v.camera;
            let c2w = c.rotation.transpose(); // columns: camera axes in world (OpenCV)
            let center = c.center();
            let (x, y, z) = (c2w.x_axis, -c2w.y_axis, -c2w.z_axis); // OpenGL axes
            let m = json!([
                [x.x, y.x, z.x, center.x],
                [x.y, y.y, z.y, center.y],
                [x.z, y.z, z.z, center.z],
                [0.0, 0.0, 0.0, 1.0]
            ]);
            let mut f = Map::new();
            f.insert(
                "file_path".into(),
                json!(format!("{image_prefix}{}", v.name)),
            );
            f.insert("transform_matrix".into(), m);
            if !shared {
                f.extend(intrinsics_json(c)?);
            }
            Ok(Value::Object(f))
        })
        .collect::<Result<_>>()?;
    top.insert("frames".into(), Value::Array(frames));
    let text = serde_json::to_string_pretty(&Value::Object(top))?;
    if let Some(d) = path.parent().filter(|d| !d.as_os_str().is_empty()) {
        fs::create_dir_all(d).with_context(|| format!("{}: cannot create", d.display()))?;
    }
    fs::write(path, text).with_context(|| format!("{}: cannot write", path.display()))
}

/// `applied_transform` nerfstudio assumes for a transforms file without one when a COLMAP model
/// stands in `colmap/sparse/0` beside it: what `ns-process-data` applied before it wrote the key
/// (`nerfstudio_dataparser.py`).
pub const LEGACY_APPLIED: [[f64; 4]; 3] = [[0., 1., 0., 0.], [1., 0., 0., 0.], [0., 0., -1., 0.]];

/// [`LEGACY_APPLIED`] as the world map `x' = r·x + t`.
pub fn legacy_applied() -> (DMat3, DVec3) {
    affine_map(&LEGACY_APPLIED)
}

/// The top-level `applied_transform` of a transforms file as the world map `x' = r·x + t`, or
/// `None` without one.
pub fn applied_map(path: &Path) -> Result<Option<(DMat3, DVec3)>> {
    let root = read_json(path)?;
    match root.get("applied_transform") {
        Some(m) => Ok(Some(world_map(&path.display().to_string(), m)?)),
        None => Ok(None),
    }
}

/// nerfstudio's `dataparser_transforms.json`, written beside a trained model's `config.yml`: the
/// map its dataparser applied to the reconstruction before training, `x_ns = scale · (M·x + t)`
/// (`"transform"`: `[M | t]`, 3×4 or 4×4; `"scale"`). Its dataparsers fold the transforms file's
/// `applied_transform` into `M` and `t`, so `x` is the reconstruction's own frame (COLMAP's). A
/// mesh from `ns-export` (`tsdf`, `poisson`) stands in the dataparser's frame `x_ns`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct DataparserTransform {
    pub matrix: DMat3,
    pub translation: DVec3,
    pub scale: f64,
}

impl DataparserTransform {
    /// Read one, with errors naming the file and the key.
    pub fn read(path: &Path) -> Result<DataparserTransform> {
        let pd = path.display().to_string();
        let root = read_json(path)?;
        let (Some(m), Some(s)) = (root.get("transform"), root.get("scale")) else {
            bail!("{pd}: expected nerfstudio's dataparser_transforms.json, an object with 'transform' (3x4) and 'scale'");
        };
        let (matrix, translation) = affine_map(&affine_rows(&format!("{pd}: 'transform'"), m)?);
        // nerfstudio's orientations are rotations (written in f32); anything far from one is
        // not a dataparser transform. Inverted in full, as nerfstudio's own
        // `transform_poses_to_original_space` does.
        if let Some(why) = not_a_rotation(&matrix, 1e-4) {
            bail!("{pd}: 'transform': its 3x3 part {why}");
        }
        let scale = s
            .as_f64()
            .filter(|x| x.is_finite() && *x > 0.0)
            .ok_or_else(|| anyhow!("{pd}: 'scale' must be a positive number, got {s}"))?;
        Ok(DataparserTransform {
            matrix,
            translation,
            scale,
        })
    }

    /// Points of the dataparser's frame moved to the reconstruction's: `M⁻¹·(x_ns / scale − t)`.
    pub fn to_original(&self, pts: &mut [DVec3]) {
        let inv = self.matrix.inverse();
        for p in pts {
            *p = inv * (*p / self.scale - self.translation);
        }
    }
}
