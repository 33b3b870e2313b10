//! A whole COLMAP sparse model: the posed views (read by `scene::colmap`), and what the scene
//! loader skips — the 3-D points with their tracks and each image's 2-D keypoints — which the
//! mesher and the reprojection error need. Text (`.txt`) and binary (`.bin`) models, the text
//! files preferred when both are there (as `scene::colmap` does).

use crate::io::text;
use crate::scene::{colmap, Camera, View};
use anyhow::{anyhow, bail, Context, Result};
use glam::DVec3;
use std::collections::HashMap;
use std::path::Path;

/// A 3-D point of the model.
#[derive(Clone, Debug, PartialEq)]
pub struct Point {
    pub xyz: DVec3,
    /// COLMAP's mean reprojection error of the point (pixels).
    pub error: f64,
    /// Observations: (view index into [`Model::views`], keypoint index in that image).
    pub track: Vec<(u32, u32)>,
}

/// A sparse model.
#[derive(Clone, Debug)]
pub struct Model {
    /// Views sorted by image name (as `scene::colmap::load` gives them).
    pub views: Vec<View>,
    /// Per view: its keypoints' pixel coordinates (COLMAP's convention: pixel centres at +0.5,
    /// which is ours).
    pub keypoints: Vec<Vec<[f64; 2]>>,
    pub points: Vec<Point>,
}

/// Reprojection error of a model's observations through xscale's cameras.
#[derive(Clone, Copy, Debug, Default, PartialEq, serde::Serialize)]
pub struct Reprojection {
    pub observations: usize,
    pub mean: f64,
    pub rms: f64,
    /// Observations behind their camera or without a keypoint.
    pub invalid: usize,
}

impl Model {
    /// Read the model in `dir`, with image paths `images_dir/NAME`.
    pub fn read(dir: &Path, images_dir: &Path) -> Result<Model> {
        let views = colmap::load(dir, images_dir)?;
        let index: HashMap<&str, u32> = views
            .iter()
            .enumerate()
            .map(|(i, v)| (v.name.as_str(), i as u32))
            .collect();
        let text = dir.join("images.txt").is_file() && dir.join("cameras.txt").is_file();
        let images = if text {
            read_images_text(&dir.join("images.txt"))?
        } else {
            read_images_binary(&dir.join("images.bin"))?
        };
        let mut keypoints = vec![Vec::new(); views.len()];
        let mut by_id = HashMap::new();
        for (id, name, kp) in images {
            let v = *index.get(name.as_str()).ok_or_else(|| {
                anyhow!(
                    "{}: image '{name}' is not among the model's views",
                    dir.display()
                )
            })?;
            by_id.insert(id, v);
            keypoints[v as usize] = kp;
        }
        let (ptxt, pbin) = (dir.join("points3D.txt"), dir.join("points3D.bin"));
        let raw = if text && ptxt.is_file() {
            read_points_text(&ptxt)?
        } else if pbin.is_file() {
            read_points_binary(&pbin)?
        } else if ptxt.is_file() {
            read_points_text(&ptxt)?
        } else {
            bail!(
                "{}: the model has no points3D.txt or points3D.bin",
                dir.display()
            )
        };
        let mut points = Vec::with_capacity(raw.len());
        for (origin, xyz, error, track) in raw {
            let mut t = Vec::with_capacity(track.len());
            for (img, k) in track {
                let v = *by_id
                    .get(&img)
                    .ok_or_else(|| anyhow!("{origin}: the track names image id {img}, which the images file does not have"))?;
                if k as usize >= keypoints[v as usize].len() {
                    bail!(
                        "{origin}: keypoint {k} of image '{}', which has {}",
                        views[v as usize].name,
                        keypoints[v as usize].len()
                    );
                }
                t.push((v, k));
            }
            points.push(Point {
                xyz,
                error,
                track: t,
            });
        }
        Ok(Model {
            views,
            keypoints,
            points,
        })
    }

    /// Reprojection error of every observation through the views' cameras (with distortion).
    pub fn reprojection(&self) -> Reprojection {
        let mut r = Reprojection::default();
        let (mut s, mut s2) = (0.0, 0.0);
        for p in &self.points {
            for &(v, k) in &p.track {
                let cam: &Camera = &self.views[v as usize].camera;
                let [x, y] = self.keypoints[v as usize][k as usize];
                match cam.project(p.xyz) {
                    Some((u, w)) => {
                        let e = ((u - x).powi(2) + (w - y).powi(2)).sqrt();
                        s += e;
                        s2 += e * e;
                        r.observations += 1;
                    }
                    None => r.invalid += 1,
                }
            }
        }
        if r.observations > 0 {
            r.mean = s / r.observations as f64;
            r.rms = (s2 / r.observations as f64).sqrt();
        }
        r
    }
}

type RawImage = (u32, String, Vec<[f64; 2]>);
type RawPoint = (String, DVec3, f64, Vec<(u32, u32)>);

fn num<T: std::str::FromStr>(s: &str, wh: &str, what: &str) -> Result<T> {
    s.parse()
        .map_err(|_| anyhow!("{wh}: {what} '{s}' is not a valid number"))
}

/// `images.txt`: per image a pose line `IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME` and a
/// keypoint line `X Y POINT3D_ID …`.
fn read_images_text(path: &Path) -> Result<Vec<RawImage>> {
    let content = text::read(path)?;
    let mut out = Vec::new();
    let mut lines = content
        .lines()
        .enumerate()
        .filter(|(_, l)| !l.trim_start().starts_with('#'));
    while let Some((i, line)) = lines.next() {
        if line.trim().is_empty() {
            continue;
        }
        let wh = format!("{}: line {}", path.display(), i + 1);
        let f: Vec<&str> = line.split_whitespace().collect();
        if f.len() < 10 {
            bail!("{wh}: expected IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME");
        }
        let id: u32 = num(f[0], &wh, "image id")?;
        // The name may hold spaces: everything after the 9th field.
        let name = line
            .split_whitespace()
            .skip(9)
            .collect::<Vec<_>>()
            .join(" ");
        let (j, kp_line) = lines.next().unwrap_or((i + 1, ""));
        let wh = format!("{}: line {}", path.display(), j + 1);
        let g: Vec<&str> = kp_line.split_whitespace().collect();
        if g.len() % 3 != 0 {
            bail!(
                "{wh}: expected X Y POINT3D_ID triples, got {} fields",
                g.len()
            );
        }
        let kp = g
            .chunks(3)
            .map(|c| Ok([num(c[0], &wh, "x")?, num(c[1], &wh, "y")?]))
            .collect::<Result<Vec<[f64; 2]>>>()?;
        out.push((id, name, kp));
    }
    Ok(out)
}

/// `points3D.txt`: `POINT3D_ID X Y Z R G B ERROR (IMAGE_ID POINT2D_IDX)…`.
fn read_points_text(path: &Path) -> Result<Vec<RawPoint>> {
    let content = text::read(path)?;
    let mut out = Vec::new();
    for (i, line) in content.lines().enumerate() {
        let line = line.trim();
        if line.is_empty() || line.starts_with('#') {
            continue;
        }
        let wh = format!("{}: line {}", path.display(), i + 1);
        let f: Vec<&str> = line.split_whitespace().collect();
        if f.len() < 8 || (f.len() - 8) % 2 != 0 {
            bail!("{wh}: expected POINT3D_ID X Y Z R G B ERROR and (IMAGE_ID, POINT2D_IDX) pairs");
        }
        let xyz = DVec3::new(
            num(f[1], &wh, "x")?,
            num(f[2], &wh, "y")?,
            num(f[3], &wh, "z")?,
        );
        if !xyz.is_finite() {
            bail!("{wh}: non-finite point {xyz}");
        }
        let error = num(f[7], &wh, "error")?;
        let track = f[8..]
            .chunks(2)
            .map(|c| {
                Ok((
                    num(c[0], &wh, "image id")?,
                    num(c[1], &wh, "keypoint index")?,
                ))
            })
            .collect::<Result<Vec<_>>>()?;
        out.push((wh, xyz, error, track));
    }
    Ok(out)
}

/// Little-endian reads with errors naming the file.
struct Bytes<'a> {
    data: &'a [u8],
    pos: usize,
    path: &'a Path,
}

impl Bytes<'_> {
    fn take(&mut self, n: usize, what: &str) -> Result<&[u8]> {
        if self.pos.checked_add(n).is_none_or(|e| e > self.data.len()) {
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
    fn u64(&mut self, what: &str) -> Result<u64> {
        Ok(u64::from_le_bytes(self.take(8, what)?.try_into().unwrap()))
    }
    fn u32(&mut self, what: &str) -> Result<u32> {
        Ok(u32::from_le_bytes(self.take(4, what)?.try_into().unwrap()))
    }
    fn f64(&mut self, what: &str) -> Result<f64> {
        Ok(f64::from_le_bytes(self.take(8, what)?.try_into().unwrap()))
    }
    /// A count of records of at least `size` bytes each: more than the file holds is an error
    /// before anything is allocated.
    fn count(&mut self, size: usize, what: &str) -> Result<usize> {
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

/// `images.bin`: count, then per image id (u32), pose (7 f64), camera id (u32), a NUL-ended
/// name, a keypoint count and per keypoint x, y (f64) and a point id (u64).
fn read_images_binary(path: &Path) -> Result<Vec<RawImage>> {
    let data = std::fs::read(path).with_context(|| format!("{}: cannot read", path.display()))?;
    let mut r = Bytes {
        data: &data,
        pos: 0,
        path,
    };
    let n = r.count(4 + 56 + 4 + 1 + 8, "the image count")?;
    let mut out = Vec::with_capacity(n);
    for k in 0..n {
        let what = format!("image {k} of {n}");
        let id = r.u32(&what)?;
        r.take(56 + 4, &what)?;
        let rest = &r.data[r.pos..];
        let end = rest
            .iter()
            .position(|&c| c == 0)
            .ok_or_else(|| anyhow!("{}: {what}: the name has no end", path.display()))?;
        let name = String::from_utf8(rest[..end].to_vec())
            .map_err(|_| anyhow!("{}: {what}: name is not UTF-8", path.display()))?;
        r.pos += end + 1;
        let m = r.count(24, &format!("{what}: the keypoint count"))?;
        let mut kp = Vec::with_capacity(m);
        for _ in 0..m {
            let x = r.f64(&what)?;
            let y = r.f64(&what)?;
            r.u64(&what)?;
            kp.push([x, y]);
        }
        out.push((id, name, kp));
    }
    Ok(out)
}

/// `points3D.bin`: count, then per point id (u64), xyz (3 f64), rgb (3 u8), error (f64), a
/// track length (u64) and (image id, keypoint index) u32 pairs.
fn read_points_binary(path: &Path) -> Result<Vec<RawPoint>> {
    let data = std::fs::read(path).with_context(|| format!("{}: cannot read", path.display()))?;
    let mut r = Bytes {
        data: &data,
        pos: 0,
        path,
    };
    let n = r.count(8 + 24 + 3 + 8 + 8, "the point count")?;
    let mut out = Vec::with_capacity(n);
    for k in 0..n {
        let what = format!("point {k} of {n}");
        let id = r.u64(&what)?;
        let xyz = DVec3::new(r.f64(&what)?, r.f64(&what)?, r.f64(&what)?);
        r.take(3, &what)?;
        let error = r.f64(&what)?;
        let m = r.count(8, &format!("{what}: the track length"))?;
        let mut track = Vec::with_capacity(m);
        for _ in 0..m {
            track.push((r.u32(&what)?, r.u32(&what)?));
        }
        let origin = format!("{}: point id {id}", path.display());
        if !xyz.is_finite() {
            bail!("{origin}: non-finite point {xyz}");
        }
        out.push((origin, xyz, error, track));
    }
    if r.pos != data.len() {
        bail!(
            "{}: {} bytes after the {n} declared points",
            path.display(),
            data.len() - r.pos
        );
    }
    Ok(out)
}
