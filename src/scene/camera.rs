//! Pinhole camera with optional lens distortion (SPEC §2, §3).
//!
//! Conventions: world→camera pose in OpenCV axes (x right, y down, z forward); pixel (u, v)
//! covers [u, u+1)×[v, v+1), centre at (u+0.5, v+0.5), row 0 at the top. Distorted models
//! (COLMAP SIMPLE_RADIAL, RADIAL, OPENCV) are handled by undistorting each ray direction with an
//! iterative inversion, so the rest of the pipeline only sees ideal pinhole rays.

use glam::{DMat3, DVec3};

/// Lens distortion in COLMAP's parameterisation, applied to normalised image coordinates.
#[derive(Clone, Copy, Debug, PartialEq, Default)]
pub enum Distortion {
    #[default]
    None,
    /// COLMAP SIMPLE_RADIAL: `x_d = x (1 + k r²)`.
    SimpleRadial { k: f64 },
    /// COLMAP RADIAL: `x_d = x (1 + k1 r² + k2 r⁴)`.
    Radial { k1: f64, k2: f64 },
    /// COLMAP OPENCV: radial k1, k2 and tangential p1, p2.
    OpenCv { k1: f64, k2: f64, p1: f64, p2: f64 },
}

impl Distortion {
    /// Distort normalised coordinates (x, y) → (x_d, y_d), exactly as COLMAP's camera models.
    pub fn distort(&self, x: f64, y: f64) -> (f64, f64) {
        match *self {
            Distortion::None => (x, y),
            Distortion::SimpleRadial { k } => {
                let r2 = x * x + y * y;
                let f = 1.0 + k * r2;
                (x * f, y * f)
            }
            Distortion::Radial { k1, k2 } => {
                let r2 = x * x + y * y;
                let f = 1.0 + k1 * r2 + k2 * r2 * r2;
                (x * f, y * f)
            }
            Distortion::OpenCv { k1, k2, p1, p2 } => {
                let (x2, y2, xy) = (x * x, y * y, x * y);
                let r2 = x2 + y2;
                let radial = k1 * r2 + k2 * r2 * r2;
                (
                    x + x * radial + 2.0 * p1 * xy + p2 * (r2 + 2.0 * x2),
                    y + y * radial + 2.0 * p2 * xy + p1 * (r2 + 2.0 * y2),
                )
            }
        }
    }

    /// Invert [`Distortion::distort`] by Newton's method with a central-difference Jacobian
    /// (as COLMAP's `IterativeUndistortion`); converges to ~1e-15 for the distortions real
    /// cameras have. Returns undistorted normalised coordinates.
    pub fn undistort(&self, xd: f64, yd: f64) -> (f64, f64) {
        if matches!(self, Distortion::None) {
            return (xd, yd);
        }
        let (mut x, mut y) = (xd, yd);
        for _ in 0..100 {
            let (fx, fy) = self.distort(x, y);
            let (rx, ry) = (fx - xd, fy - yd);
            if rx.abs() < 1e-15 && ry.abs() < 1e-15 {
                break;
            }
            let h = 1e-7 * (1.0 + x.abs().max(y.abs()));
            let (ax, ay) = self.distort(x + h, y);
            let (bx, by) = self.distort(x - h, y);
            let (cx, cy) = self.distort(x, y + h);
            let (dx, dy) = self.distort(x, y - h);
            let (j00, j10) = ((ax - bx) / (2.0 * h), (ay - by) / (2.0 * h));
            let (j01, j11) = ((cx - dx) / (2.0 * h), (cy - dy) / (2.0 * h));
            let det = j00 * j11 - j01 * j10;
            if det.abs() < 1e-300 {
                break;
            }
            x -= (j11 * rx - j01 * ry) / det;
            y -= (-j10 * rx + j00 * ry) / det;
        }
        (x, y)
    }
}

/// A posed camera: intrinsics K, distortion, world→camera rotation and translation.
#[derive(Clone, Debug, PartialEq)]
pub struct Camera {
    /// Image size in pixels.
    pub width: u32,
    pub height: u32,
    /// K = [[fx,0,cx],[0,fy,cy],[0,0,1]] in pixels (pixel centres at +0.5).
    pub fx: f64,
    pub fy: f64,
    pub cx: f64,
    pub cy: f64,
    pub distortion: Distortion,
    /// World→camera: `x_cam = rotation * x_world + translation` (OpenCV axes).
    pub rotation: DMat3,
    pub translation: DVec3,
}

impl Camera {
    /// Camera centre in world coordinates, `-Rᵀ t`.
    pub fn center(&self) -> DVec3 {
        -(self.rotation.transpose() * self.translation)
    }

    /// Camera-frame direction (z = 1, not normalised) through image point (x, y) in pixels
    /// (continuous coordinates: the centre of pixel (u, v) is (u+0.5, v+0.5)), undistorted.
    pub fn dir_camera(&self, x: f64, y: f64) -> DVec3 {
        let (xn, yn) = ((x - self.cx) / self.fx, (y - self.cy) / self.fy);
        let (xu, yu) = self.distortion.undistort(xn, yn);
        DVec3::new(xu, yu, 1.0)
    }

    /// World-space unit direction of the ray through image point (x, y).
    pub fn dir_world(&self, x: f64, y: f64) -> DVec3 {
        (self.rotation.transpose() * self.dir_camera(x, y)).normalize()
    }

    /// Project a world point to continuous pixel coordinates (with distortion); `None` if it is
    /// behind the camera.
    pub fn project(&self, p: DVec3) -> Option<(f64, f64)> {
        let c = self.rotation * p + self.translation;
        if c.z <= 0.0 {
            return None;
        }
        let (xd, yd) = self.distortion.distort(c.x / c.z, c.y / c.z);
        Some((self.fx * xd + self.cx, self.fy * yd + self.cy))
    }

    /// The camera for an image downsampled by an integer factor `s` (block average): the image
    /// size is divided (floor), K scales by 1/s (pixel-edge convention, so cx' = cx / s).
    pub fn downsampled(&self, s: u32) -> Camera {
        let f = s as f64;
        Camera {
            width: self.width / s,
            height: self.height / s,
            fx: self.fx / f,
            fy: self.fy / f,
            cx: self.cx / f,
            cy: self.cy / f,
            ..self.clone()
        }
    }

    /// Largest absolute difference to another camera over K and pose (for cross-format checks).
    pub fn max_abs_diff(&self, o: &Camera) -> f64 {
        let mut d = [
            self.fx - o.fx,
            self.fy - o.fy,
            self.cx - o.cx,
            self.cy - o.cy,
            (self.width as f64) - (o.width as f64),
            (self.height as f64) - (o.height as f64),
        ]
        .iter()
        .fold(0.0f64, |m, v| m.max(v.abs()));
        let (a, b) = (self.rotation.to_cols_array(), o.rotation.to_cols_array());
        for i in 0..9 {
            d = d.max((a[i] - b[i]).abs());
        }
        d.max((self.translation - o.translation).abs().max_element())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn undistort_inverts_distort() {
        let models = [
            Distortion::SimpleRadial { k: -0.12 },
            Distortion::Radial {
                k1: 0.08,
                k2: -0.02,
            },
            Distortion::OpenCv {
                k1: -0.2,
                k2: 0.05,
                p1: 0.001,
                p2: -0.002,
            },
        ];
        for m in models {
            for i in 0..21 {
                for j in 0..21 {
                    let (x, y) = (-0.6 + 0.06 * i as f64, -0.45 + 0.045 * j as f64);
                    let (xd, yd) = m.distort(x, y);
                    let (xu, yu) = m.undistort(xd, yd);
                    assert!(
                        (xu - x).abs() < 1e-12 && (yu - y).abs() < 1e-12,
                        "{m:?} {x} {y}"
                    );
                }
            }
        }
    }

    #[test]
    fn project_roundtrip() {
        let rot = DMat3::from_euler(glam::EulerRot::XYZ, 0.3, -0.2, 0.9);
        let cam = Camera {
            width: 64,
            height: 48,
            fx: 50.0,
            fy: 52.0,
            cx: 32.5,
            cy: 23.0,
            distortion: Distortion::OpenCv {
                k1: -0.1,
                k2: 0.01,
                p1: 0.001,
                p2: 0.0005,
            },
            rotation: rot,
            translation: DVec3::new(0.1, -2.0, 5.0),
        };
        let d = cam.dir_world(10.5, 40.5);
        let p = cam.center() + 3.7 * d;
        let (x, y) = cam.project(p).unwrap();
        assert!((x - 10.5).abs() < 1e-9 && (y - 40.5).abs() < 1e-9);
    }
}
