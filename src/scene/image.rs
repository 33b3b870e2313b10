//! Images: load PNG (8/16-bit; gray, gray+alpha, RGB, RGBA → RGB, alpha dropped), JPEG and EXR
//! as f32 RGB; integer block-average downsampling; PNG (8/16-bit) and EXR writers. SPEC §2, §3.
//!
//! Values: 8-bit / 255, 16-bit / 65535 (sRGB-encoded values, no colour conversion), EXR as
//! stored (f32; half channels widen exactly). Writers quantise with `round(clamp(v,0,1)·max)`,
//! so `load(write_png8(img))` reproduces an 8-bit image exactly.

use anyhow::{anyhow, bail, Context, Result};
use std::path::Path;

/// An RGB image with f32 values (sRGB-encoded values in `[0,1]` for PNG/JPEG; EXR as stored).
#[derive(Clone, Debug, PartialEq)]
pub struct Image {
    pub width: u32,
    pub height: u32,
    /// Row-major, row 0 at the top, 3 values per pixel.
    pub data: Vec<f32>,
}

fn is_exr(path: &Path) -> bool {
    path.extension()
        .and_then(|e| e.to_str())
        .is_some_and(|e| e.eq_ignore_ascii_case("exr"))
}

/// Image size (width, height) from the file header only (cheap).
pub fn dimensions(path: &Path) -> Result<(u32, u32)> {
    if is_exr(path) {
        let meta = exr::meta::MetaData::read_from_file(path, false)
            .map_err(|e| anyhow!("{}: cannot read EXR header: {e}", path.display()))?;
        let h = meta
            .headers
            .first()
            .ok_or_else(|| anyhow!("{}: EXR file has no layers", path.display()))?;
        Ok((h.layer_size.0 as u32, h.layer_size.1 as u32))
    } else {
        // Format from the content, not the extension (a mislabelled JPEG still works).
        ::image::ImageReader::open(path)
            .with_context(|| format!("{}: cannot open image", path.display()))?
            .with_guessed_format()
            .with_context(|| format!("{}: cannot read image", path.display()))?
            .into_dimensions()
            .map_err(|e| anyhow!("{}: cannot read image header: {e}", path.display()))
    }
}

/// The EXIF orientation of an image file when it is not the identity (header only; EXR: none).
pub fn exif_orientation(path: &Path) -> Result<Option<::image::metadata::Orientation>> {
    use ::image::ImageDecoder;
    if is_exr(path) {
        return Ok(None);
    }
    let mut dec = ::image::ImageReader::open(path)
        .with_context(|| format!("{}: cannot open image", path.display()))?
        .with_guessed_format()
        .with_context(|| format!("{}: cannot read image", path.display()))?
        .into_decoder()
        .map_err(|e| anyhow!("{}: cannot read image header: {e}", path.display()))?;
    let o = dec
        .orientation()
        .unwrap_or(::image::metadata::Orientation::NoTransforms);
    Ok((o != ::image::metadata::Orientation::NoTransforms).then_some(o))
}

/// Whether an EXIF orientation swaps the image's width and height (a quarter turn).
pub fn swaps_axes(o: ::image::metadata::Orientation) -> bool {
    use ::image::metadata::Orientation as O;
    matches!(
        o,
        O::Rotate90 | O::Rotate270 | O::Rotate90FlipH | O::Rotate270FlipH
    )
}

/// Load an image as RGB f32 (see the module doc for the value conventions), pixels as stored
/// (an EXIF orientation tag is not applied, as COLMAP does not).
pub fn load_rgb(path: &Path) -> Result<Image> {
    load_rgb_oriented(path, false)
}

/// [`load_rgb`], with the file's EXIF orientation applied when `orient` is true (for photos whose
/// cameras were made from the turned image: their size is the stored one with width and height
/// swapped).
pub fn load_rgb_oriented(path: &Path, orient: bool) -> Result<Image> {
    if !path.exists() {
        bail!("{}: image file not found", path.display());
    }
    if is_exr(path) {
        return load_exr(path);
    }
    let mut img = ::image::ImageReader::open(path)
        .with_context(|| format!("{}: cannot open image", path.display()))?
        .with_guessed_format()
        .with_context(|| format!("{}: cannot read image", path.display()))?
        .decode()
        .map_err(|e| anyhow!("{}: cannot decode image: {e}", path.display()))?;
    if orient {
        if let Some(o) = exif_orientation(path)? {
            img.apply_orientation(o);
        }
    }
    let (width, height) = (img.width(), img.height());
    use ::image::DynamicImage as D;
    let data: Vec<f32> = match img {
        D::ImageLuma8(b) => b
            .as_raw()
            .iter()
            .flat_map(|&g| [g as f32 / 255.0; 3])
            .collect(),
        D::ImageLumaA8(b) => b
            .as_raw()
            .chunks_exact(2)
            .flat_map(|c| [c[0] as f32 / 255.0; 3])
            .collect(),
        D::ImageRgb8(b) => b.as_raw().iter().map(|&v| v as f32 / 255.0).collect(),
        D::ImageRgba8(b) => b
            .as_raw()
            .chunks_exact(4)
            .flat_map(|c| [c[0], c[1], c[2]].map(|v| v as f32 / 255.0))
            .collect(),
        D::ImageLuma16(b) => b
            .as_raw()
            .iter()
            .flat_map(|&g| [g as f32 / 65535.0; 3])
            .collect(),
        D::ImageLumaA16(b) => b
            .as_raw()
            .chunks_exact(2)
            .flat_map(|c| [c[0] as f32 / 65535.0; 3])
            .collect(),
        D::ImageRgb16(b) => b.as_raw().iter().map(|&v| v as f32 / 65535.0).collect(),
        D::ImageRgba16(b) => b
            .as_raw()
            .chunks_exact(4)
            .flat_map(|c| [c[0], c[1], c[2]].map(|v| v as f32 / 65535.0))
            .collect(),
        D::ImageRgb32F(b) => b.into_raw(),
        D::ImageRgba32F(b) => b
            .as_raw()
            .chunks_exact(4)
            .flat_map(|c| [c[0], c[1], c[2]])
            .collect(),
        other => bail!(
            "{}: unsupported pixel format {:?}",
            path.display(),
            other.color()
        ),
    };
    debug_assert_eq!(data.len(), 3 * width as usize * height as usize);
    Ok(Image {
        width,
        height,
        data,
    })
}

fn load_exr(path: &Path) -> Result<Image> {
    use exr::prelude::{read_first_rgba_layer_from_file, Vec2};
    let img = read_first_rgba_layer_from_file(
        path,
        |size, _channels| (size.0, size.1, vec![0f32; 3 * size.0 * size.1]),
        |px: &mut (usize, usize, Vec<f32>),
         pos: Vec2<usize>,
         (r, g, b, _a): (f32, f32, f32, f32)| {
            let i = 3 * (pos.1 * px.0 + pos.0);
            px.2[i] = r;
            px.2[i + 1] = g;
            px.2[i + 2] = b;
        },
    )
    .map_err(|e| anyhow!("{}: cannot read EXR: {e}", path.display()))?;
    let (w, h, data) = img.layer_data.channel_data.pixels;
    Ok(super::Image {
        width: w as u32,
        height: h as u32,
        data,
    })
}

/// Block-average downsampling by an integer factor `s`: output size `(w/s, h/s)` (floor, the
/// trailing partial blocks are discarded — consistent with [`super::Camera::downsampled`]).
/// Each output value is the mean of its s×s block, accumulated in f64 in row-major order and
/// rounded once to f32. `s = 1` returns a copy. Panics if `s == 0` (callers validate it).
pub fn downsample(img: &Image, s: u32) -> Image {
    assert!(s >= 1, "downsample factor must be >= 1");
    if s == 1 {
        return img.clone();
    }
    let (w, h) = (img.width / s, img.height / s);
    let (s, iw) = (s as usize, img.width as usize);
    let inv = 1.0 / (s * s) as f64;
    let mut data = vec![0f32; 3 * w as usize * h as usize]; // [h][w][3]
    for y in 0..h as usize {
        for x in 0..w as usize {
            let mut acc = [0f64; 3];
            for by in 0..s {
                let row = (y * s + by) * iw;
                for bx in 0..s {
                    let i = 3 * (row + x * s + bx);
                    for (c, a) in acc.iter_mut().enumerate() {
                        *a += img.data[i + c] as f64;
                    }
                }
            }
            let o = 3 * (y * w as usize + x);
            for c in 0..3 {
                data[o + c] = (acc[c] * inv) as f32;
            }
        }
    }
    Image {
        width: w,
        height: h,
        data,
    }
}

fn check(img: &Image, path: &Path) -> Result<()> {
    if img.data.len() != 3 * img.width as usize * img.height as usize {
        bail!(
            "{}: image buffer has {} values, expected 3·{}·{}",
            path.display(),
            img.data.len(),
            img.width,
            img.height
        );
    }
    Ok(())
}

/// Quantise one value to `0..=max`: `round(clamp(v, 0, 1) · max)`; NaN → 0.
#[inline]
fn quantize(v: f32, max: f32) -> f32 {
    let v = if v.is_nan() { 0.0 } else { v.clamp(0.0, 1.0) };
    (v * max).round()
}

/// Write an 8-bit RGB PNG (values are written as they are: sRGB-encoded, no conversion), whole or
/// not at all.
pub fn write_png8(path: &Path, img: &Image) -> Result<()> {
    check(img, path)?;
    // In parallel (a 1-MP frame's 3 M values were a render's last serial step but the encoder).
    use rayon::prelude::*;
    let buf: Vec<u8> = (img.data.par_iter())
        .map(|&v| quantize(v, 255.0) as u8)
        .collect();
    save_png(path, img, &buf, ::image::ExtendedColorType::Rgb8)
}

/// Encode `buf` as a PNG at `path`, whole or not at all (a killed render leaves no truncated
/// file: [`crate::io::atomic::write_atomic`]).
fn save_png(path: &Path, img: &Image, buf: &[u8], color: ::image::ExtendedColorType) -> Result<()> {
    crate::io::atomic::write_atomic(path, false, |tmp| {
        ::image::save_buffer_with_format(
            tmp,
            buf,
            img.width,
            img.height,
            color,
            ::image::ImageFormat::Png,
        )
        .map_err(|e| anyhow!("{}: cannot write PNG: {e}", path.display()))
    })
}

/// Write a 16-bit RGB PNG.
pub fn write_png16(path: &Path, img: &Image) -> Result<()> {
    check(img, path)?;
    let buf: Vec<u8> = img
        .data
        .iter()
        .flat_map(|&v| (quantize(v, 65535.0) as u16).to_ne_bytes())
        .collect();
    save_png(path, img, &buf, ::image::ExtendedColorType::Rgb16)
}

/// Write a 32-bit float RGB EXR (values exactly as stored).
pub fn write_exr(path: &Path, img: &Image) -> Result<()> {
    check(img, path)?;
    let w = img.width as usize;
    crate::io::atomic::write_atomic(path, false, |tmp| {
        exr::prelude::write_rgb_file(tmp, w, img.height as usize, |x, y| {
            let i = 3 * (y * w + x);
            (img.data[i], img.data[i + 1], img.data[i + 2])
        })
        .map_err(|e| anyhow!("{}: cannot write EXR: {e}", path.display()))
    })
}
