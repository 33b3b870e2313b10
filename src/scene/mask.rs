//! Object masks: which pixels of a photo belong to the object (SPEC §3). Training only draws
//! pixels inside the mask and the held-out scores are computed inside it (SPEC §7).
//!
//! ## Where a view's mask comes from
//! 0. With `transforms.json` layouts, the frames' `mask_path` (nerfstudio: relative to the JSON
//!    file, given for every frame or none; a mix is an error naming the first view without one).
//! 1. A `masks/` folder in the scene directory (as object datasets ship them): for a view named
//!    `NAME` (its name in the camera file, e.g. `images/0003.png`, `cam1/0003.jpg`), the first of
//!    `masks/NAME`, `masks/NAME.png` (COLMAP's convention for `NAME.jpg`), `masks/<NAME with its
//!    extension replaced by .png>` and the same three with only the file name of `NAME` that
//!    exists. When `masks/` exists, every view must have one (an error names the first that
//!    does not and the paths tried).
//! 2. Else the photo's own alpha channel, when it has one (RGBA / grey+alpha PNG), as the
//!    NeRF-synthetic datasets store their objects.
//! 3. Else no mask: every pixel counts.
//!
//! ## Values
//! A mask file's coverage is its alpha channel when it has one, else its grey value (the mean
//! of R, G, B for a colour file), scaled to [0, 1]. A pixel is inside the mask when its coverage
//! is ≥ 0.5 (nerfstudio keeps every non-zero pixel; the two agree on the usual 0/255 masks). With
//! `--downsample s`, coverage is averaged over each s×s block first, as photos
//! are.

use anyhow::{anyhow, bail, Context, Result};
use std::path::{Path, PathBuf};

/// Where a view's mask comes from (module docs).
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum MaskSource {
    /// No mask: every pixel counts.
    None,
    /// A file in `masks/`.
    File(PathBuf),
    /// The photo's alpha channel.
    Alpha,
}

/// Whether a view's mask (`None`: no mask) leaves no pixel inside it.
pub fn excludes_all(mask: Option<&[bool]>) -> bool {
    mask.is_some_and(|m| !m.contains(&true))
}

/// Why a view none of whose pixels the cast kept was dropped, for its warning: its mask
/// ([`excludes_all`]), else the mesh.
pub fn drop_reason(mask: Option<&[bool]>) -> &'static str {
    if excludes_all(mask) {
        "has an object mask that excludes every pixel"
    } else {
        "sees no part of the mesh"
    }
}

/// The candidates for the mask of a view named `name` under `masks_dir` (module docs), in order.
pub fn mask_candidates(masks_dir: &Path, name: &str) -> Vec<PathBuf> {
    let mut names = vec![name.to_string()];
    if let Some(file) = Path::new(name).file_name().and_then(|f| f.to_str()) {
        if file != name {
            names.push(file.to_string());
        }
    }
    let mut out = Vec::new();
    for n in names {
        out.push(masks_dir.join(&n));
        out.push(masks_dir.join(format!("{n}.png")));
        out.push(masks_dir.join(Path::new(&n).with_extension("png")));
    }
    out.dedup();
    out
}

/// The mask file of view `name`, or an error listing what was tried.
pub fn find_mask(masks_dir: &Path, name: &str) -> Result<PathBuf> {
    let c = mask_candidates(masks_dir, name);
    c.iter().find(|p| p.is_file()).cloned().ok_or_else(|| {
        anyhow!(
            "{}: the scene has a masks folder but no mask for view '{name}' (tried {})",
            masks_dir.display(),
            c.iter()
                .map(|p| p.display().to_string())
                .collect::<Vec<_>>()
                .join(", ")
        )
    })
}

/// Whether an image file has an alpha channel (header only; EXR and JPEG: no).
pub fn has_alpha(path: &Path) -> Result<bool> {
    if path
        .extension()
        .and_then(|e| e.to_str())
        .is_some_and(|e| e.eq_ignore_ascii_case("exr"))
    {
        return Ok(false);
    }
    use ::image::ImageDecoder;
    let dec = ::image::ImageReader::open(path)
        .with_context(|| format!("{}: cannot open image", path.display()))?
        .with_guessed_format()
        .with_context(|| format!("{}: cannot read image", path.display()))?
        .into_decoder()
        .map_err(|e| anyhow!("{}: cannot read image header: {e}", path.display()))?;
    Ok(dec.color_type().has_alpha())
}

/// Coverage in [0, 1] of every pixel of `path` (module docs): the alpha channel if the file has
/// one; else, when `grey` is true, its grey value; else an error. Returns (width, height, values).
pub fn load_coverage(path: &Path, grey: bool) -> Result<(u32, u32, Vec<f32>)> {
    let img = ::image::ImageReader::open(path)
        .with_context(|| format!("{}: cannot open mask", path.display()))?
        .with_guessed_format()
        .with_context(|| format!("{}: cannot read mask", path.display()))?
        .decode()
        .map_err(|e| anyhow!("{}: cannot decode mask: {e}", path.display()))?;
    let (w, h) = (img.width(), img.height());
    let cov: Vec<f32> = if img.color().has_alpha() {
        img.to_rgba32f().pixels().map(|p| p.0[3]).collect()
    } else if grey {
        img.to_rgb32f()
            .pixels()
            .map(|p| (p.0[0] + p.0[1] + p.0[2]) / 3.0)
            .collect()
    } else {
        bail!("{}: has no alpha channel to use as a mask", path.display())
    };
    Ok((w, h, cov))
}

/// The mask at the camera's resolution: coverage averaged over s×s blocks (s = `downsample`,
/// trailing partial blocks dropped as for photos), inside where ≥ 0.5. `(w, h)` is the size
/// expected after downsampling; a mismatch is an error naming the file.
pub fn load_mask(
    source: &MaskSource,
    image_path: &Path,
    downsample: u32,
    (w, h): (u32, u32),
) -> Result<Option<Vec<bool>>> {
    let (path, grey) = match source {
        MaskSource::None => return Ok(None),
        MaskSource::File(p) => (p.as_path(), true),
        MaskSource::Alpha => (image_path, false),
    };
    let (fw, fh, cov) = load_coverage(path, grey)?;
    let s = downsample.max(1);
    if (fw / s, fh / s) != (w, h) {
        bail!(
            "{}: mask is {fw}x{fh}{} but the view's camera is {w}x{h}",
            path.display(),
            if s > 1 {
                format!(" ({}x{} after downsampling by {s})", fw / s, fh / s)
            } else {
                String::new()
            }
        );
    }
    let (s, fw) = (s as usize, fw as usize);
    let mut out = Vec::with_capacity(w as usize * h as usize);
    for y in 0..h as usize {
        for x in 0..w as usize {
            let mut acc = 0.0f64;
            for by in 0..s {
                for bx in 0..s {
                    acc += cov[(y * s + by) * fw + x * s + bx] as f64;
                }
            }
            out.push(acc / (s * s) as f64 >= 0.5);
        }
    }
    Ok(Some(out))
}
