//! COLMAP sparse models (SPEC §3): read `cameras` + `images` in text (`.txt`) or binary
//! (`.bin`) form, write both forms. `points3D` is written empty, and read only by
//! [`read_points`] for the check that the mesh stands in the cameras' frame
//! (`scene/points.rs`). Newer COLMAP layouts (3.12+) add `rigs.*` and `frames.*`; `images.*`
//! keeps each image's world→camera pose, so those extra files are simply ignored.
//!
//! Camera models: every perspective and fisheye model of COLMAP 3.13 (mapped to [`Distortion`]:
//! SIMPLE_PINHOLE, PINHOLE, SIMPLE_RADIAL, RADIAL, OPENCV, OPENCV_FISHEYE, FULL_OPENCV, FOV,
//! SIMPLE_RADIAL_FISHEYE, RADIAL_FISHEYE, THIN_PRISM_FISHEYE, RAD_TAN_THIN_PRISM_FISHEYE,
//! SIMPLE_DIVISION, DIVISION, SIMPLE_FISHEYE, FISHEYE); EUCM and EQUIRECTANGULAR are an error
//! that names the model and lists the supported ones. COLMAP's pixel convention
//! (centre of the top-left pixel at (0.5, 0.5)) is ours, so K is taken as is.
//!
//! Pose: `QW QX QY QZ TX TY TZ` is world→camera (`x_cam = R(q) x_world + t`), OpenCV axes; the
//! quaternion is normalised before use.
//!
//! Order: views are sorted by image name (COLMAP image ids are arbitrary and not contiguous;
//! sorting by name makes the scene order, and so the train/test split, deterministic).
//!
//! If both text and binary files are present, the text files are read.

use super::camera::Intrinsics;
use super::{Distortion, View};
use anyhow::{anyhow, bail, Context, Result};
use glam::{DMat3, DQuat, DVec3};
use std::collections::HashMap;
use std::fmt::Write as _;
use std::fs;
use std::path::{Path, PathBuf};

const SUPPORTED: &str = "SIMPLE_PINHOLE, PINHOLE, SIMPLE_RADIAL, RADIAL, OPENCV, OPENCV_FISHEYE, FULL_OPENCV, FOV, SIMPLE_RADIAL_FISHEYE, RADIAL_FISHEYE, THIN_PRISM_FISHEYE, RAD_TAN_THIN_PRISM_FISHEYE, SIMPLE_DIVISION, DIVISION, SIMPLE_FISHEYE, FISHEYE";

/// COLMAP's camera model names by id (`src/colmap/sensor/models.h`), and their parameter
/// counts.
pub(crate) const MODELS: [(&str, usize); 18] = [
    ("SIMPLE_PINHOLE", 3),
    ("PINHOLE", 4),
    ("SIMPLE_RADIAL", 4),
    ("RADIAL", 5),
    ("OPENCV", 8),
    ("OPENCV_FISHEYE", 8),
    ("FULL_OPENCV", 12),
    ("FOV", 5),
    ("SIMPLE_RADIAL_FISHEYE", 4),
    ("RADIAL_FISHEYE", 5),
    ("THIN_PRISM_FISHEYE", 12),
    ("RAD_TAN_THIN_PRISM_FISHEYE", 16),
    ("SIMPLE_DIVISION", 4),
    ("DIVISION", 5),
    ("SIMPLE_FISHEYE", 3),
    ("FISHEYE", 4),
    ("EUCM", 6),
    ("EQUIRECTANGULAR", 2),
];

/// Build intrinsics from a model id and its parameters (count already checked). `where_` is
/// prefixed to errors.
fn intrinsics(where_: &str, model: usize, w: u64, h: u64, p: &[f64]) -> Result<Intrinsics> {
    if p.iter().any(|v| !v.is_finite()) {
        bail!("{where_}: non-finite camera parameter");
    }
    if w == 0 || h == 0 || w > u32::MAX as u64 || h > u32::MAX as u64 {
        bail!("{where_}: bad image size {w}x{h}");
    }
    // (fx, fy, cx, cy, distortion) from each model's parameter order.
    let f1 = |d| (p[0], p[0], p[1], p[2], d);
    let f2 = |d| (p[0], p[1], p[2], p[3], d);
    let arr = |a: &[f64]| -> [f64; 4] { [a[0], a[1], a[2], a[3]] };
    let (fx, fy, cx, cy, distortion) = match model {
        0 => f1(Distortion::None),
        1 => f2(Distortion::None),
        2 => f1(Distortion::SimpleRadial { k: p[3] }),
        3 => f1(Distortion::Radial { k1: p[3], k2: p[4] }),
        4 => f2(Distortion::OpenCv {
            k1: p[4],
            k2: p[5],
            p1: p[6],
            p2: p[7],
        }),
        5 => f2(Distortion::Fisheye { k: arr(&p[4..8]) }),
        6 => f2(Distortion::FullOpenCv {
            k: [p[4], p[5], p[8], p[9], p[10], p[11]],
            p1: p[6],
            p2: p[7],
        }),
        7 => f2(Distortion::Fov { omega: p[4] }),
        8 => f1(Distortion::Fisheye {
            k: [p[3], 0.0, 0.0, 0.0],
        }),
        9 => f1(Distortion::Fisheye {
            k: [p[3], p[4], 0.0, 0.0],
        }),
        10 => f2(Distortion::ThinPrismFisheye {
            k: [p[4], p[5], p[8], p[9]],
            p1: p[6],
            p2: p[7],
            sx1: p[10],
            sy1: p[11],
        }),
        11 => f2(Distortion::RadTanThinPrismFisheye {
            k: [p[4], p[5], p[6], p[7], p[8], p[9]],
            p: [p[10], p[11]],
            s: [p[12], p[13], p[14], p[15]],
        }),
        12 => f1(Distortion::Division { k: p[3] }),
        13 => f2(Distortion::Division { k: p[4] }),
        14 => f1(Distortion::Fisheye { k: [0.0; 4] }),
        15 => f2(Distortion::Fisheye { k: [0.0; 4] }),
        _ => {
            let name = MODELS.get(model).map(|m| m.0).unwrap_or("(unknown id)");
            bail!(
                "{where_}: camera model {name} is not supported (supported: {SUPPORTED}); \
                 undistort the images first, e.g. with `colmap image_undistorter`"
            )
        }
    };
    if !(fx > 0.0 && fy > 0.0) {
        bail!("{where_}: focal length must be positive (fx={fx}, fy={fy})");
    }
    Ok(Intrinsics {
        width: w as u32,
        height: h as u32,
        fx,
        fy,
        cx,
        cy,
        distortion,
    })
}

/// COLMAP model id and parameters representing a camera exactly (SIMPLE_RADIAL/RADIAL need
/// fx == fy; otherwise the equivalent OPENCV with zero extra terms is used). A distortion no
/// COLMAP model has (Metashape's r⁸ term or skew) is an error naming the view.
pub(crate) fn model_of(view: &View) -> Result<(usize, Vec<f64>)> {
    let cam = &view.camera;
    let same_f = cam.fx == cam.fy;
    let k4 = [cam.fx, cam.fy, cam.cx, cam.cy];
    let with = |extra: &[f64]| [&k4[..], extra].concat();
    Ok(match cam.distortion {
        Distortion::None => (1, k4.to_vec()),
        Distortion::SimpleRadial { k } if same_f => (2, vec![cam.fx, cam.cx, cam.cy, k]),
        Distortion::SimpleRadial { k } => (4, with(&[k, 0.0, 0.0, 0.0])),
        Distortion::Radial { k1, k2 } if same_f => (3, vec![cam.fx, cam.cx, cam.cy, k1, k2]),
        Distortion::Radial { k1, k2 } => (4, with(&[k1, k2, 0.0, 0.0])),
        Distortion::OpenCv { k1, k2, p1, p2 } => (4, with(&[k1, k2, p1, p2])),
        Distortion::Fisheye { k } => (5, with(&k)),
        Distortion::FullOpenCv { k, p1, p2 } => {
            (6, with(&[k[0], k[1], p1, p2, k[2], k[3], k[4], k[5]]))
        }
        Distortion::Fov { omega } => (7, with(&[omega])),
        Distortion::ThinPrismFisheye {
            k,
            p1,
            p2,
            sx1,
            sy1,
        } => (10, with(&[k[0], k[1], p1, p2, k[2], k[3], sx1, sy1])),
        Distortion::RadTanThinPrismFisheye { k, p, s } => (11, with(&[&k[..], &p, &s].concat())),
        Distortion::Division { k } => (13, with(&[k])),
        Distortion::Brown { k, p1, p2, skew } if k[3] == 0.0 && skew == 0.0 => {
            (6, with(&[k[0], k[1], p1, p2, k[2], 0.0, 0.0, 0.0]))
        }
        Distortion::Brown { k, skew, .. } => bail!(
            "view '{}': no COLMAP camera model has Metashape's k4 = {} or skew = {skew}; undistort the images first",
            view.name,
            k[3]
        ),
    })
}

/// World→camera rotation from a COLMAP quaternion (normalised first).
fn rotation_from_q(where_: &str, q: [f64; 4]) -> Result<DMat3> {
    let n = (q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]).sqrt();
    if !(n.is_finite() && n > 1e-12) {
        bail!("{where_}: quaternion {q:?} is zero or not finite");
    }
    let (w, x, y, z) = (q[0] / n, q[1] / n, q[2] / n, q[3] / n);
    Ok(DMat3::from_quat(DQuat::from_xyzw(x, y, z, w)))
}

/// COLMAP quaternion (qw, qx, qy, qz) with qw >= 0 for a rotation matrix.
fn q_from_rotation(r: &DMat3) -> [f64; 4] {
    let q = DQuat::from_mat3(r).normalize();
    let s = if q.w < 0.0 { -1.0 } else { 1.0 };
    [s * q.w, s * q.x, s * q.y, s * q.z]
}

struct RawImage {
    name: String,
    q: [f64; 4],
    t: [f64; 3],
    camera_id: u64,
    /// For error messages ("images.txt: line 7").
    origin: String,
}

fn assemble(
    dir: &Path,
    cams: HashMap<u64, Intrinsics>,
    imgs: Vec<RawImage>,
    images_dir: &Path,
) -> Result<Vec<View>> {
    let mut views = Vec::with_capacity(imgs.len());
    let mut seen = HashMap::new();
    for im in imgs {
        let k = cams.get(&im.camera_id).ok_or_else(|| {
            anyhow!(
                "{}: image '{}' refers to camera {} which is not in the cameras file of {}",
                im.origin,
                im.name,
                im.camera_id,
                dir.display()
            )
        })?;
        if let Some(prev) = seen.insert(im.name.clone(), im.origin.clone()) {
            bail!(
                "{}: image name '{}' appears twice (also at {prev})",
                im.origin,
                im.name
            );
        }
        if im.t.iter().any(|v| !v.is_finite()) {
            bail!("{}: translation is not finite", im.origin);
        }
        let rotation = rotation_from_q(&im.origin, im.q)?;
        views.push(View {
            image_path: images_dir.join(&im.name),
            name: im.name,
            camera: k.posed(rotation, DVec3::from_array(im.t)),
        });
    }
    views.sort_by(|a, b| a.name.cmp(&b.name));
    Ok(views)
}

/// True if `dir` holds a COLMAP model (cameras + images, text or binary).
pub fn is_model_dir(dir: &Path) -> bool {
    (dir.join("cameras.txt").is_file() && dir.join("images.txt").is_file())
        || (dir.join("cameras.bin").is_file() && dir.join("images.bin").is_file())
}

/// A model directory among the places [`find_layout`] looks that holds part of a model but not
/// a whole one (`cameras` and `images` both .txt or both .bin): what is there and what is missing.
pub fn incomplete_model(scene: &Path) -> Option<String> {
    model_places(scene).iter().map(|(d, _)| d).find_map(|d| {
        let has = |f: &str| d.join(f).is_file();
        let found: Vec<&str> = ["cameras.txt", "images.txt", "cameras.bin", "images.bin"]
            .into_iter()
            .filter(|f| has(f))
            .collect();
        if found.is_empty() || is_model_dir(d) {
            return None;
        }
        let missing = if has("cameras.txt") || has("images.txt") {
            if has("cameras.txt") {
                "images.txt"
            } else {
                "cameras.txt"
            }
        } else if has("cameras.bin") {
            "images.bin"
        } else {
            "cameras.bin"
        };
        let mixed = if (has("cameras.txt") || has("images.txt"))
            && (has("cameras.bin") || has("images.bin"))
        {
            " (a model is read whole from .txt or whole from .bin, not mixed)"
        } else {
            ""
        };
        Some(format!(
            "{} holds {} but no {missing}{mixed}",
            d.display(),
            found.join(", ")
        ))
    })
}

/// Find the model in a scene dir: `sparse/0/`, `sparse/`, or the dir itself.
pub fn find_model_dir(scene: &Path) -> Option<PathBuf> {
    find_layout(scene).map(|l| l.model)
}

/// Where a COLMAP model and its images are in a scene dir.
#[derive(Clone, Debug, PartialEq)]
pub struct Layout {
    pub model: PathBuf,
    pub images: PathBuf,
    /// The model is the undistorted one of a dense workspace (`colmap image_undistorter`).
    pub dense: bool,
}

/// The COLMAP model of a scene dir, first found of:
/// 1. a dense workspace as `colmap image_undistorter` leaves it, the scene dir being the
///    workspace root (`dense/0/sparse` + `dense/0/images`), its `dense/` folder (`0/sparse` +
///    `0/images`) or the undistorted folder itself (`sparse/` + `images/` + `stereo/`), or an
///    undistorter output without the `0/` level (`dense/sparse` + `dense/images`) — the
///    undistorted (PINHOLE) model is preferred to a workspace root's original `sparse/0`, as
///    COLMAP's meshes (`meshed-poisson.ply`, `meshed-delaunay.ply`) live beside it;
/// 2. `sparse/0/`, `sparse/` or the dir itself, with images in `images/`.
pub fn find_layout(scene: &Path) -> Option<Layout> {
    let undistorted_here = scene.join("stereo").is_dir();
    model_places(scene)
        .into_iter()
        .find(|(model, ws)| {
            is_model_dir(model) && ws.as_ref().is_none_or(|w| w.join("images").is_dir())
        })
        .map(|(model, ws)| Layout {
            model,
            images: ws.as_deref().unwrap_or(scene).join("images"),
            dense: ws.is_some() || undistorted_here,
        })
}

/// The folders of a scene dir that may hold a COLMAP model, in the order they are looked in, each
/// with its dense workspace when it is one's `sparse/` (its images beside it): `dense/0/sparse/`,
/// `dense/sparse/`, `0/sparse/`, then `sparse/0/`, `sparse/` and the dir itself.
fn model_places(scene: &Path) -> Vec<(PathBuf, Option<PathBuf>)> {
    let dense = [
        scene.join("dense").join("0"),
        scene.join("dense"),
        scene.join("0"),
    ];
    let plain = [
        scene.join("sparse").join("0"),
        scene.join("sparse"),
        scene.to_path_buf(),
    ];
    (dense.into_iter().map(|w| (w.join("sparse"), Some(w))))
        .chain(plain.into_iter().map(|d| (d, None)))
        .collect()
}

/// Read a model directory (text preferred over binary); image paths are `images_dir/NAME`.
pub fn load(dir: &Path, images_dir: &Path) -> Result<Vec<View>> {
    if dir.join("cameras.txt").is_file() && dir.join("images.txt").is_file() {
        read_text(dir, images_dir)
    } else if dir.join("cameras.bin").is_file() && dir.join("images.bin").is_file() {
        read_binary(dir, images_dir)
    } else {
        bail!(
            "{}: no COLMAP model (expected cameras.txt + images.txt or cameras.bin + images.bin)",
            dir.display()
        )
    }
}

// ---------------------------------------------------------------------------------------------
// Text
// ---------------------------------------------------------------------------------------------

fn parse_num<T: std::str::FromStr>(s: &str, where_: &str, what: &str) -> Result<T> {
    s.parse()
        .map_err(|_| anyhow!("{where_}: {what} '{s}' is not a valid number"))
}

/// Read `cameras.txt` + `images.txt`.
pub fn read_text(dir: &Path, images_dir: &Path) -> Result<Vec<View>> {
    let cpath = dir.join("cameras.txt");
    let ctext = crate::io::text::read(&cpath)?;
    let mut cams = HashMap::new();
    for (ln, line) in ctext.lines().enumerate() {
        let line = line.trim();
        if line.is_empty() || line.starts_with('#') {
            continue;
        }
        let wh = format!("{}: line {}", cpath.display(), ln + 1);
        let tok: Vec<&str> = line.split_whitespace().collect();
        if tok.len() < 4 {
            bail!("{wh}: expected 'CAMERA_ID MODEL WIDTH HEIGHT PARAMS...', found '{line}'");
        }
        let id: u64 = parse_num(tok[0], &wh, "camera id")?;
        let model = MODELS.iter().position(|m| m.0 == tok[1]).ok_or_else(|| {
            anyhow!(
                "{wh}: camera {id}: unknown camera model '{}' (supported: {SUPPORTED})",
                tok[1]
            )
        })?;
        let w: u64 = parse_num(tok[2], &wh, "width")?;
        let h: u64 = parse_num(tok[3], &wh, "height")?;
        let params = tok[4..]
            .iter()
            .map(|s| parse_num::<f64>(s, &wh, "parameter"))
            .collect::<Result<Vec<_>>>()?;
        let wh = format!("{wh}: camera {id}");
        if params.len() != MODELS[model].1 {
            bail!(
                "{wh}: model {} takes {} parameters, found {}",
                MODELS[model].0,
                MODELS[model].1,
                params.len()
            );
        }
        let k = intrinsics(&wh, model, w, h, &params)?;
        if cams.insert(id, k).is_some() {
            bail!("{wh}: camera id {id} defined twice");
        }
    }

    let ipath = dir.join("images.txt");
    let itext = crate::io::text::read(&ipath)?;
    let mut imgs = Vec::new();
    // Two lines per image; the second (2D points) may be empty, so blank lines are significant
    // there. A header line is never blank, so blank lines are skipped while looking for one. If
    // the expected points line is not one (numbers in threes), it is taken as the next header
    // (some tools drop empty points lines); a header always ends in a name, which is not a
    // number.
    let lines: Vec<(usize, &str)> = itext
        .lines()
        .enumerate()
        .filter(|(_, l)| !l.trim_start().starts_with('#'))
        .map(|(i, l)| (i + 1, l.trim()))
        .collect();
    let mut ids = HashMap::new();
    let mut i = 0;
    while i < lines.len() {
        let (ln, line) = lines[i];
        i += 1;
        if line.is_empty() {
            continue;
        }
        let wh = format!("{}: line {ln}", ipath.display());
        let tok: Vec<&str> = line.split_whitespace().collect();
        if tok.len() < 10 {
            bail!(
                "{wh}: expected 'IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME', found {} fields",
                tok.len()
            );
        }
        let id: u64 = parse_num(tok[0], &wh, "image id")?;
        if let Some(first) = ids.insert(id, ln) {
            bail!("{wh}: image id {id} is used twice (first on line {first})");
        }
        let mut v = [0f64; 7];
        for k in 0..7 {
            v[k] = parse_num(tok[1 + k], &wh, "pose value")?;
        }
        let camera_id: u64 = parse_num(tok[8], &wh, "camera id")?;
        imgs.push(RawImage {
            name: name_after(line, 9).to_string(),
            q: [v[0], v[1], v[2], v[3]],
            t: [v[4], v[5], v[6]],
            camera_id,
            origin: wh,
        });
        // The points line.
        if i < lines.len() && is_points_line(lines[i].1) {
            i += 1;
        }
    }
    if imgs.is_empty() {
        bail!("{}: lists no images", ipath.display());
    }
    assemble(dir, cams, imgs, images_dir)
}

/// A 2D-points line: `X Y POINT3D_ID` triples, every token a number (an empty line included).
fn is_points_line(line: &str) -> bool {
    let tok: Vec<&str> = line.split_whitespace().collect();
    tok.len() % 3 == 0 && tok.iter().all(|t| t.parse::<f64>().is_ok())
}

/// The rest of `line` after its first `n` whitespace-separated fields, exactly as written (an
/// image name may hold spaces, runs of them included).
fn name_after(line: &str, n: usize) -> &str {
    let mut rest = line.trim_start();
    for _ in 0..n {
        let end = rest.find(char::is_whitespace).unwrap_or(rest.len());
        rest = rest[end..].trim_start();
    }
    rest
}

fn fmt_params(p: &[f64]) -> String {
    p.iter()
        .map(|v| format!("{v}"))
        .collect::<Vec<_>>()
        .join(" ")
}

/// Write `cameras.txt`, `images.txt` and an empty `points3D.txt` into `dir` (created if
/// needed): one camera per view (ids 1..=n in the given order), numbers with Rust's `{}`
/// (shortest round-trip), an empty 2D-points line per image.
pub fn write_text(dir: &Path, views: &[View]) -> Result<()> {
    fs::create_dir_all(dir).with_context(|| format!("{}: cannot create", dir.display()))?;
    check_names(views)?;
    let mut cams = String::new();
    writeln!(cams, "# Camera list with one line of data per camera:").unwrap();
    writeln!(cams, "#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]").unwrap();
    writeln!(cams, "# Number of cameras: {}", views.len()).unwrap();
    let mut imgs = String::new();
    writeln!(imgs, "# Image list with two lines of data per image:").unwrap();
    writeln!(
        imgs,
        "#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME"
    )
    .unwrap();
    writeln!(imgs, "#   POINTS2D[] as (X, Y, POINT3D_ID)").unwrap();
    writeln!(
        imgs,
        "# Number of images: {}, mean observations per image: 0",
        views.len()
    )
    .unwrap();
    for (i, v) in views.iter().enumerate() {
        let c = &v.camera;
        let (model, params) = model_of(v)?;
        writeln!(
            cams,
            "{} {} {} {} {}",
            i + 1,
            MODELS[model].0,
            c.width,
            c.height,
            fmt_params(&params)
        )
        .unwrap();
        let q = q_from_rotation(&c.rotation);
        let t = c.translation;
        writeln!(
            imgs,
            "{} {} {} {} {} {} {} {} {} {}\n",
            i + 1,
            q[0],
            q[1],
            q[2],
            q[3],
            t.x,
            t.y,
            t.z,
            i + 1,
            v.name
        )
        .unwrap();
    }
    let pts = "# 3D point list with one line of data per point:\n\
               #   POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[] as (IMAGE_ID, POINT2D_IDX)\n\
               # Number of points: 0, mean track length: 0\n";
    for (name, text) in [
        ("cameras.txt", cams.as_str()),
        ("images.txt", imgs.as_str()),
        ("points3D.txt", pts),
    ] {
        let p = dir.join(name);
        fs::write(&p, text).with_context(|| format!("{}: cannot write", p.display()))?;
    }
    Ok(())
}

fn check_names(views: &[View]) -> Result<()> {
    for v in views {
        if v.name.is_empty() || v.name.contains(['\n', '\r', '\0']) {
            bail!(
                "cannot write COLMAP model: image name {:?} is empty or has a line break/NUL",
                v.name
            );
        }
    }
    Ok(())
}

/// A model's 3-D point and its track length.
pub type Point = (DVec3, u32);

/// A model's 3-D points (`points3D.txt`, else `points3D.bin`: text preferred, as for the
/// model): each point's position and track length (the number of image observations). `None`
/// when the model has no points file.
pub fn read_points(dir: &Path) -> Result<Option<(PathBuf, Vec<Point>)>> {
    let text = dir.join("points3D.txt");
    let binary = dir.join("points3D.bin");
    if text.is_file() {
        return Ok(Some((text.clone(), read_points_text(&text)?)));
    }
    if binary.is_file() {
        return Ok(Some((binary.clone(), read_points_binary(&binary)?)));
    }
    Ok(None)
}

/// `points3D.txt`: `POINT3D_ID X Y Z R G B ERROR` then the track's `IMAGE_ID POINT2D_IDX` pairs.
fn read_points_text(path: &Path) -> Result<Vec<Point>> {
    let text = crate::io::text::read(path)?;
    let mut out = Vec::new();
    for (i, line) in text.lines().enumerate() {
        let line = line.trim();
        if line.is_empty() || line.starts_with('#') {
            continue;
        }
        let wh = format!("{}: line {}", path.display(), i + 1);
        let f: Vec<&str> = line.split_whitespace().collect();
        if f.len() < 8 || (f.len() - 8) % 2 != 0 {
            bail!(
                "{wh}: expected POINT3D_ID X Y Z R G B ERROR and (IMAGE_ID, POINT2D_IDX) pairs, got {} fields",
                f.len()
            );
        }
        let mut x = [0f64; 3];
        for (k, v) in x.iter_mut().enumerate() {
            *v = parse_num(f[1 + k], &wh, "coordinate")?;
        }
        let p = DVec3::from(x);
        if !p.is_finite() {
            bail!("{wh}: non-finite point {p}");
        }
        out.push((p, ((f.len() - 8) / 2) as u32));
    }
    Ok(out)
}

/// `points3D.bin`: a u64 count, then per point a u64 id, 3 f64, 3 u8 colours, an f64 error, a
/// u64 track length and that many (u32 image id, u32 point index) pairs.
fn read_points_binary(path: &Path) -> Result<Vec<Point>> {
    let data = fs::read(path).with_context(|| format!("{}: cannot read", path.display()))?;
    let mut r = Reader {
        data: &data,
        pos: 0,
        path,
    };
    let n = r.u64("the point count")?;
    // A point takes at least 51 bytes: a count beyond the file's size is not allocated.
    let mut out = Vec::with_capacity((n as usize).min(data.len() / 51));
    for k in 0..n {
        let what = format!("point {k} of {n}");
        let id = r.u64(&what)?;
        let p = DVec3::new(r.f64(&what)?, r.f64(&what)?, r.f64(&what)?);
        r.take(3 + 8, &what)?;
        let track = r.u64(&what)?;
        let bytes = track.checked_mul(8).filter(|b| *b <= usize::MAX as u64);
        match bytes {
            Some(b) => {
                r.take(
                    b as usize,
                    &format!("{what}: a track of {track} observations"),
                )?;
            }
            None => bail!("{}: {what}: absurd track length {track}", path.display()),
        }
        if !p.is_finite() {
            bail!("{}: {what} (id {id}): non-finite point {p}", path.display());
        }
        out.push((p, track.min(u32::MAX as u64) as u32));
    }
    if r.pos != data.len() {
        bail!(
            "{}: {} bytes after the {n} declared points (wrong count?)",
            path.display(),
            data.len() - r.pos
        );
    }
    Ok(out)
}

// ---------------------------------------------------------------------------------------------
// Binary
// ---------------------------------------------------------------------------------------------

/// Little-endian reads of a COLMAP binary file, with errors naming the file (also
/// `prepare::sparse`'s reader of whole sparse models).
pub(crate) struct Reader<'a> {
    data: &'a [u8],
    pos: usize,
    path: &'a Path,
}

impl<'a> Reader<'a> {
    pub(crate) fn new(data: &'a [u8], path: &'a Path) -> Self {
        Reader { data, pos: 0, path }
    }
    /// Bytes not read yet.
    pub(crate) fn remaining(&self) -> usize {
        self.data.len() - self.pos
    }
}

impl Reader<'_> {
    pub(crate) fn take(&mut self, n: usize, what: &str) -> Result<&[u8]> {
        // `pos + n` can overflow: a count read from the file times its record size may be as
        // large as usize::MAX (cargo-fuzz, `colmap_points_binary`).
        if self
            .pos
            .checked_add(n)
            .is_none_or(|end| end > self.data.len())
        {
            bail!(
                "{}: truncated: file ends at byte {} while reading {what}",
                self.path.display(),
                self.data.len()
            );
        }
        let s = &self.data[self.pos..self.pos + n];
        self.pos += n;
        Ok(s)
    }
    pub(crate) fn u64(&mut self, what: &str) -> Result<u64> {
        Ok(u64::from_le_bytes(self.take(8, what)?.try_into().unwrap()))
    }
    pub(crate) fn u32(&mut self, what: &str) -> Result<u32> {
        Ok(u32::from_le_bytes(self.take(4, what)?.try_into().unwrap()))
    }
    pub(crate) fn i32(&mut self, what: &str) -> Result<i32> {
        Ok(i32::from_le_bytes(self.take(4, what)?.try_into().unwrap()))
    }
    pub(crate) fn f64(&mut self, what: &str) -> Result<f64> {
        Ok(f64::from_le_bytes(self.take(8, what)?.try_into().unwrap()))
    }
    pub(crate) fn cstr(&mut self, what: &str) -> Result<String> {
        let rest = &self.data[self.pos..];
        let n = rest.iter().position(|&c| c == 0).ok_or_else(|| {
            anyhow!(
                "{}: truncated: no NUL terminator for {what}",
                self.path.display()
            )
        })?;
        let s = String::from_utf8(rest[..n].to_vec())
            .map_err(|_| anyhow!("{}: {what}: name is not UTF-8", self.path.display()))?;
        self.pos += n + 1;
        Ok(s)
    }
    /// A count of records of at least `size` bytes each: more than the file holds is an error
    /// before anything is allocated.
    pub(crate) fn count(&mut self, size: usize, what: &str) -> Result<usize> {
        let n = self.u64(what)?;
        if n.checked_mul(size as u64)
            .is_none_or(|b| b > (self.data.len() - self.pos) as u64)
        {
            bail!(
                "{}: {what}: {n} records do not fit in the file",
                self.path.display()
            );
        }
        Ok(n as usize)
    }
}

/// Read `cameras.bin` + `images.bin`.
pub fn read_binary(dir: &Path, images_dir: &Path) -> Result<Vec<View>> {
    let cpath = dir.join("cameras.bin");
    let cdata = fs::read(&cpath).with_context(|| format!("{}: cannot read", cpath.display()))?;
    let mut r = Reader {
        data: &cdata,
        pos: 0,
        path: &cpath,
    };
    let n = r.u64("the camera count")?;
    let mut cams = HashMap::new();
    for k in 0..n {
        let what = format!("camera {k} of {n}");
        let id = r.u32(&what)? as u64;
        let model = r.i32(&what)?;
        let w = r.u64(&what)?;
        let h = r.u64(&what)?;
        let wh = format!("{}: camera {k} (id {id})", cpath.display());
        if model < 0 || model as usize >= MODELS.len() {
            bail!("{wh}: unknown camera model id {model} (supported: {SUPPORTED})");
        }
        let model = model as usize;
        let mut p = Vec::with_capacity(MODELS[model].1);
        for _ in 0..MODELS[model].1 {
            p.push(r.f64(&what)?);
        }
        let k = intrinsics(&wh, model, w, h, &p)?;
        if cams.insert(id, k).is_some() {
            bail!("{wh}: camera id {id} defined twice");
        }
    }
    if r.pos != cdata.len() {
        bail!(
            "{}: {} bytes after the {n} declared cameras (wrong count?)",
            cpath.display(),
            cdata.len() - r.pos
        );
    }

    let ipath = dir.join("images.bin");
    let idata = fs::read(&ipath).with_context(|| format!("{}: cannot read", ipath.display()))?;
    let mut r = Reader {
        data: &idata,
        pos: 0,
        path: &ipath,
    };
    let n = r.u64("the image count")?;
    let mut imgs = Vec::new();
    let mut ids = HashMap::new();
    for k in 0..n {
        let what = format!("image {k} of {n}");
        let id = r.u32(&what)?;
        if let Some(first) = ids.insert(id, k) {
            bail!(
                "{}: {what}: image id {id} is used twice (first by image {first})",
                ipath.display()
            );
        }
        let mut v = [0f64; 7];
        for x in v.iter_mut() {
            *x = r.f64(&what)?;
        }
        let camera_id = r.u32(&what)? as u64;
        let name = r.cstr(&what)?;
        let np = r.u64(&what)?;
        // Each 2D point: x, y (f64) and a u64 point3D id.
        let bytes = np.checked_mul(24).filter(|b| *b <= usize::MAX as u64);
        match bytes {
            Some(b) => {
                r.take(b as usize, &format!("{what}: {np} 2D points"))?;
            }
            None => bail!("{}: {what}: absurd 2D point count {np}", ipath.display()),
        }
        imgs.push(RawImage {
            name,
            q: [v[0], v[1], v[2], v[3]],
            t: [v[4], v[5], v[6]],
            camera_id,
            origin: format!("{}: image {k} (id {id})", ipath.display()),
        });
    }
    if r.pos != idata.len() {
        bail!(
            "{}: {} bytes after the {n} declared images (wrong count?)",
            ipath.display(),
            idata.len() - r.pos
        );
    }
    if imgs.is_empty() {
        bail!("{}: lists no images", ipath.display());
    }
    assemble(dir, cams, imgs, images_dir)
}

/// Write `cameras.bin`, `images.bin` and an empty `points3D.bin` (same content as
/// [`write_text`]).
pub fn write_binary(dir: &Path, views: &[View]) -> Result<()> {
    fs::create_dir_all(dir).with_context(|| format!("{}: cannot create", dir.display()))?;
    check_names(views)?;
    let mut cams = Vec::new();
    let mut imgs = Vec::new();
    cams.extend((views.len() as u64).to_le_bytes());
    imgs.extend((views.len() as u64).to_le_bytes());
    for (i, v) in views.iter().enumerate() {
        let c = &v.camera;
        let (model, params) = model_of(v)?;
        let id = (i + 1) as u32;
        cams.extend(id.to_le_bytes());
        cams.extend((model as i32).to_le_bytes());
        cams.extend((c.width as u64).to_le_bytes());
        cams.extend((c.height as u64).to_le_bytes());
        for p in params {
            cams.extend(p.to_le_bytes());
        }
        imgs.extend(id.to_le_bytes());
        let q = q_from_rotation(&c.rotation);
        for x in q.into_iter().chain(c.translation.to_array()) {
            imgs.extend(x.to_le_bytes());
        }
        imgs.extend(id.to_le_bytes());
        imgs.extend(v.name.as_bytes());
        imgs.push(0);
        imgs.extend(0u64.to_le_bytes());
    }
    for (name, data) in [
        ("cameras.bin", cams),
        ("images.bin", imgs),
        ("points3D.bin", 0u64.to_le_bytes().to_vec()),
    ] {
        let p = dir.join(name);
        fs::write(&p, data).with_context(|| format!("{}: cannot write", p.display()))?;
    }
    Ok(())
}
