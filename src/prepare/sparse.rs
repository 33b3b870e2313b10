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

/// `images.bin`: count, then per image id (u32), pose (7 f64), camera id (u32), a NUL-ended
/// name, a keypoint count and per keypoint x, y (f64) and a point id (u64).
fn read_images_binary(path: &Path) -> Result<Vec<RawImage>> {
    let data = std::fs::read(path).with_context(|| format!("{}: cannot read", path.display()))?;
    let mut r = colmap::Reader::new(&data, path);
    let n = r.count(4 + 56 + 4 + 1 + 8, "the image count")?;
    let mut out = Vec::with_capacity(n);
    for k in 0..n {
        let what = format!("image {k} of {n}");
        let id = r.u32(&what)?;
        r.take(56 + 4, &what)?;
        let name = r.cstr(&what)?;
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
    let mut r = colmap::Reader::new(&data, path);
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
    if r.remaining() != 0 {
        bail!(
            "{}: {} bytes after the {n} declared points",
            path.display(),
            r.remaining()
        );
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn point_record(id: u64, xyz: [f64; 3], track: &[(u32, u32)]) -> Vec<u8> {
        let mut b = id.to_le_bytes().to_vec();
        for c in xyz {
            b.extend(c.to_le_bytes());
        }
        b.extend([1u8, 2, 3]);
        b.extend(0.5f64.to_le_bytes());
        b.extend((track.len() as u64).to_le_bytes());
        for &(i, k) in track {
            b.extend(i.to_le_bytes());
            b.extend(k.to_le_bytes());
        }
        b
    }

    fn image_record(id: u32, name: &[u8], keypoints: usize) -> Vec<u8> {
        let mut b = id.to_le_bytes().to_vec();
        b.extend([0u8; 56 + 4]);
        b.extend(name);
        b.push(0);
        b.extend((keypoints as u64).to_le_bytes());
        for k in 0..keypoints {
            b.extend((k as f64).to_le_bytes());
            b.extend((2.0 * k as f64).to_le_bytes());
            b.extend(u64::MAX.to_le_bytes());
        }
        b
    }

    fn file(tag: &str, count: u64, records: &[u8]) -> std::path::PathBuf {
        let p = std::env::temp_dir().join(format!("xscale-sparse-{tag}-{}", std::process::id()));
        let mut b = count.to_le_bytes().to_vec();
        b.extend(records);
        std::fs::write(&p, b).unwrap();
        p
    }

    fn err<T>(r: Result<T>) -> String {
        match r {
            Ok(_) => panic!("bad input was read"),
            Err(e) => format!("{e:#}"),
        }
    }

    /// Well-formed records read back; every kind of damage is an error naming the file and
    /// what was being read, never a panic or an allocation of the declared size.
    #[test]
    fn binary_models_read_and_bad_ones_are_named() {
        let good = point_record(7, [1.0, 2.0, 3.0], &[(1, 0), (2, 5)]);
        let p = file("points-ok", 1, &good);
        let pts = read_points_binary(&p).unwrap();
        assert_eq!(pts.len(), 1);
        assert_eq!(pts[0].1, DVec3::new(1.0, 2.0, 3.0));
        assert_eq!(pts[0].3, vec![(1, 0), (2, 5)]);
        let p = file("points-short", 1, &good[..good.len() - 3]);
        let e = err(read_points_binary(&p));
        assert!(
            (e.contains("truncated") || e.contains("do not fit")) && e.contains("point 0 of 1"),
            "{e}"
        );
        let p = file("points-count", u64::MAX / 2, &good);
        let e = err(read_points_binary(&p));
        assert!(e.contains("do not fit in the file"), "{e}");
        let mut extra = good.clone();
        extra.extend([0u8; 5]);
        let p = file("points-extra", 1, &extra);
        assert!(err(read_points_binary(&p)).contains("5 bytes after the 1 declared points"));
        let p = file("points-nan", 1, &point_record(3, [f64::NAN, 0.0, 0.0], &[]));
        assert!(err(read_points_binary(&p)).contains("non-finite point"));

        let good = image_record(4, b"a.jpg", 2);
        let p = file("images-ok", 1, &good);
        let imgs = read_images_binary(&p).unwrap();
        assert_eq!((imgs[0].0, imgs[0].1.as_str()), (4, "a.jpg"));
        assert_eq!(imgs[0].2, vec![[0.0, 0.0], [1.0, 2.0]]);
        let p = file("images-name", 1, &image_record(4, b"\xff\xfe", 0));
        assert!(err(read_images_binary(&p)).contains("not UTF-8"));
        let p = file("images-short", 1, &good[..good.len() - 1]);
        assert!(err(read_images_binary(&p)).contains("do not fit in the file"));
        let p = file("images-count", 3, &good);
        let e = err(read_images_binary(&p));
        assert!(e.contains("do not fit") || e.contains("truncated"), "{e}");
    }
}
