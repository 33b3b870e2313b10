//! The MVSNet camera layout used by the official XScale-NVS code (SPEC §3):
//! `images_<dsp>/NAME.ext` beside `cams_<dsp>/NAME_cam.txt`, where a cam file is
//!
//! ```text
//! extrinsic
//! r11 r12 r13 t1
//! r21 r22 r23 t2
//! r31 r32 r33 t3
//! 0 0 0 1
//!
//! intrinsic
//! fx 0 cx
//! 0 fy cy
//! 0 0 1
//!
//! depth_min depth_interval ...      (optional; ignored)
//! ```
//!
//! The extrinsic is world→camera in OpenCV axes. NAME is the image file stem; the image size
//! comes from the image header. Views are in cam-file name order (byte-wise sort). A `cams/` +
//! `images/` pair (no `_<dsp>` suffix) is accepted as well. K is used in full (the official
//! code ignores cx, cy and the skew; a non-zero skew is rejected here rather than ignored).

use super::{Camera, Distortion, View};
use anyhow::{anyhow, bail, Context, Result};
use glam::{DMat3, DVec3};
use std::fmt::Write as _;
use std::fs;
use std::path::{Path, PathBuf};

/// Image file extensions tried for `NAME`, in order.
pub const IMAGE_EXTS: [&str; 8] = ["png", "jpg", "jpeg", "exr", "PNG", "JPG", "JPEG", "EXR"];

/// A `cams_<dsp>` / `images_<dsp>` pair found in a scene dir.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Layout {
    /// `None` for plain `cams/` + `images/`.
    pub dsp: Option<u32>,
    pub cams: PathBuf,
    pub images: PathBuf,
}

fn has_cam_files(dir: &Path) -> bool {
    fs::read_dir(dir)
        .map(|rd| {
            rd.flatten()
                .any(|e| e.file_name().to_string_lossy().ends_with("_cam.txt"))
        })
        .unwrap_or(false)
}

/// All camera/image dir pairs in `scene` that hold at least one `*_cam.txt`, sorted by dsp
/// (plain `cams/` first).
pub fn find_layouts(scene: &Path) -> Vec<Layout> {
    let mut out = Vec::new();
    let Ok(rd) = fs::read_dir(scene) else {
        return out;
    };
    for e in rd.flatten() {
        let name = e.file_name().to_string_lossy().to_string();
        let dsp = if name == "cams" {
            None
        } else if let Some(s) = name.strip_prefix("cams_") {
            match s.parse::<u32>() {
                Ok(d) => Some(d),
                Err(_) => continue,
            }
        } else {
            continue;
        };
        let cams = e.path();
        if !cams.is_dir() || !has_cam_files(&cams) {
            continue;
        }
        let images = match dsp {
            None => scene.join("images"),
            Some(d) => scene.join(format!("images_{d}")),
        };
        out.push(Layout { dsp, cams, images });
    }
    out.sort_by_key(|l| l.dsp.map(|d| d as i64).unwrap_or(-1));
    out
}

/// Parse one cam file into (rotation, translation, K = (fx, fy, cx, cy)).
pub fn parse_cam(path: &Path) -> Result<(DMat3, DVec3, [f64; 4])> {
    let p = path.display();
    let text = crate::io::text::read(path)?;
    // Non-blank lines with their numbers.
    let lines: Vec<(usize, &str)> = text
        .lines()
        .enumerate()
        .map(|(i, l)| (i + 1, l.trim()))
        .filter(|(_, l)| !l.is_empty())
        .collect();
    let find = |kw: &str| -> Result<usize> {
        lines
            .iter()
            .position(|(_, l)| l.eq_ignore_ascii_case(kw))
            .ok_or_else(|| anyhow!("{p}: no '{kw}' line"))
    };
    let rows = |start: usize, n: usize, cols: usize, what: &str| -> Result<Vec<Vec<f64>>> {
        let mut out = Vec::new();
        for r in 0..n {
            let (ln, l) = *lines.get(start + r).ok_or_else(|| {
                anyhow!("{p}: truncated: {what} needs {n} rows of {cols} numbers, found {r}")
            })?;
            let v: Vec<f64> = l
                .split_whitespace()
                .map(|s| {
                    s.parse::<f64>()
                        .map_err(|_| anyhow!("{p}: line {ln}: {what}: '{s}' is not a number"))
                })
                .collect::<Result<_>>()?;
            if v.len() != cols {
                bail!(
                    "{p}: line {ln}: {what} row {r}: expected {cols} numbers, found {}",
                    v.len()
                );
            }
            if v.iter().any(|x| !x.is_finite()) {
                bail!("{p}: line {ln}: {what} row {r}: non-finite value");
            }
            out.push(v);
        }
        Ok(out)
    };
    let e = find("extrinsic")?;
    let ext = rows(e + 1, 4, 4, "extrinsic")?;
    let i = find("intrinsic")?;
    let k = rows(i + 1, 3, 3, "intrinsic")?;
    let ln_k = lines[i].0;
    let rot = DMat3::from_cols_array_2d(&[
        [ext[0][0], ext[1][0], ext[2][0]],
        [ext[0][1], ext[1][1], ext[2][1]],
        [ext[0][2], ext[1][2], ext[2][2]],
    ]);
    let t = DVec3::new(ext[0][3], ext[1][3], ext[2][3]);
    let last = &ext[3];
    if last[0] != 0.0 || last[1] != 0.0 || last[2] != 0.0 || last[3] != 1.0 {
        bail!("{p}: extrinsic last row must be '0 0 0 1', found {last:?}");
    }
    let ortho = (rot.transpose() * rot - DMat3::IDENTITY)
        .to_cols_array()
        .iter()
        .fold(0f64, |m, v| m.max(v.abs()));
    if ortho > 1e-4 || rot.determinant() <= 0.0 {
        bail!(
            "{p}: extrinsic rotation is not a rotation (|RᵀR − I| = {ortho:.2e}, det = {})",
            rot.determinant()
        );
    }
    if k[0][1] != 0.0 || k[1][0] != 0.0 || k[2] != [0.0, 0.0, 1.0] {
        bail!(
            "{p}: line {ln_k}: intrinsic must be [[fx,0,cx],[0,fy,cy],[0,0,1]] (no skew), found {k:?}"
        );
    }
    if !(k[0][0] > 0.0 && k[1][1] > 0.0) {
        bail!("{p}: line {ln_k}: focal lengths must be positive");
    }
    Ok((rot, t, [k[0][0], k[1][1], k[0][2], k[1][2]]))
}

/// Find `images/NAME.<ext>` for the extensions in [`IMAGE_EXTS`] (also Metashape's labels).
pub(super) fn find_image(images: &Path, stem: &str) -> Option<PathBuf> {
    IMAGE_EXTS
        .iter()
        .map(|e| images.join(format!("{stem}.{e}")))
        .find(|p| p.is_file())
}

/// Load all views of a layout (sorted by cam file name). Missing images are an error naming
/// the cam file and the paths tried.
pub fn load(layout: &Layout) -> Result<Vec<View>> {
    if !layout.images.is_dir() {
        bail!(
            "{}: image directory not found (beside {})",
            layout.images.display(),
            layout.cams.display()
        );
    }
    let mut files: Vec<(String, PathBuf)> = fs::read_dir(&layout.cams)
        .with_context(|| format!("{}: cannot list", layout.cams.display()))?
        .flatten()
        .filter_map(|e| {
            let n = e.file_name().to_string_lossy().to_string();
            n.strip_suffix("_cam.txt")
                .map(|s| (s.to_string(), e.path()))
        })
        .collect();
    files.sort();
    let mut views = Vec::with_capacity(files.len());
    for (stem, cam_path) in files {
        let (rotation, translation, k) = parse_cam(&cam_path)?;
        let img = find_image(&layout.images, &stem).ok_or_else(|| {
            anyhow!(
                "{}: image for this camera not found: tried {}/{stem}.{{{}}}",
                cam_path.display(),
                layout.images.display(),
                IMAGE_EXTS.join(",")
            )
        })?;
        let (width, height) = super::image::dimensions(&img)?;
        views.push(View {
            name: img.file_name().unwrap().to_string_lossy().to_string(),
            camera: Camera {
                width,
                height,
                fx: k[0],
                fy: k[1],
                cx: k[2],
                cy: k[3],
                distortion: Distortion::None,
                rotation,
                translation,
            },
            image_path: img,
        });
    }
    Ok(views)
}

/// Format one cam file (full-precision numbers, `{}` of f64).
pub fn format_cam(cam: &Camera) -> String {
    let r = cam.rotation;
    let t = cam.translation;
    let mut s = String::from("extrinsic\n");
    for i in 0..3 {
        let row = r.row(i);
        writeln!(s, "{} {} {} {}", row.x, row.y, row.z, t[i]).unwrap();
    }
    s.push_str("0 0 0 1\n\nintrinsic\n");
    writeln!(s, "{} 0 {}", cam.fx, cam.cx).unwrap();
    writeln!(s, "0 {} {}", cam.fy, cam.cy).unwrap();
    s.push_str("0 0 1\n");
    s
}

/// Write `dir/cams_<dsp>/NAME_cam.txt` for every view (NAME = the stem of `view.name`) and
/// create `dir/images_<dsp>/` (the caller writes the images there). Distorted cameras cannot be
/// represented in this format and are an error.
pub fn write(dir: &Path, views: &[View], dsp: u32) -> Result<()> {
    let cams = dir.join(format!("cams_{dsp}"));
    let images = dir.join(format!("images_{dsp}"));
    for d in [&cams, &images] {
        fs::create_dir_all(d).with_context(|| format!("{}: cannot create", d.display()))?;
    }
    let mut seen = std::collections::HashSet::new();
    for v in views {
        if v.camera.distortion != Distortion::None {
            bail!(
                "view '{}': the MVSNet layout has no lens distortion; undistort first",
                v.name
            );
        }
        let stem = Path::new(&v.name)
            .file_stem()
            .map(|s| s.to_string_lossy().to_string())
            .ok_or_else(|| anyhow!("view '{}': name has no file stem", v.name))?;
        if !seen.insert(stem.clone()) {
            bail!(
                "view '{}': another view has the same file stem '{stem}'",
                v.name
            );
        }
        let p = cams.join(format!("{stem}_cam.txt"));
        fs::write(&p, format_cam(&v.camera))
            .with_context(|| format!("{}: cannot write", p.display()))?;
    }
    Ok(())
}
