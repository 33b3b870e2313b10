//! Pinhole camera with optional lens distortion (SPEC §2, §3).
//!
//! Conventions: world→camera pose in OpenCV axes (x right, y down, z forward); pixel (u, v)
//! covers [u, u+1)×[v, v+1), centre at (u+0.5, v+0.5), row 0 at the top. Distorted models (every
//! perspective and fisheye model COLMAP has, see [`Distortion`]) are handled by undistorting each
//! ray direction (an iterative inversion, or COLMAP's closed form where it has one), so the rest
//! of the pipeline only sees ideal rays from the camera centre.

use crate::scene::dual::{Dual2, Real};
use glam::{DMat3, DVec3};

/// Lens distortion in COLMAP's parameterisation, applied to normalised image coordinates.
///
/// Perspective models (`SimpleRadial` … `FullOpenCv`, `Division`, `Fov`) map a ray's normalised
/// pinhole coordinates `(x, y) = (X/Z, Y/Z)` to distorted ones. Fisheye models first take the ray
/// to the equidistant fisheye plane, `(u, v) = (x, y)·θ/r` with `r = |(x, y)|`, `θ = atan(r)`
/// (the angle to the optical axis), and distort there — COLMAP's `FisheyeFromNormal`. Formulas
/// are COLMAP's (`src/colmap/sensor/models.h`), model by model.
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
    /// COLMAP FULL_OPENCV: rational radial `(1 + k1 r² + k2 r⁴ + k3 r⁶) / (1 + k4 r² + k5 r⁴ +
    /// k6 r⁶)` (`k = [k1 … k6]`) and tangential p1, p2.
    FullOpenCv { k: [f64; 6], p1: f64, p2: f64 },
    /// Brown's model as Agisoft Metashape fits it for frame cameras (its manual, Appendix C):
    /// radial `1 + k1 r² + k2 r⁴ + k3 r⁶ + k4 r⁸`, tangential in OpenCV's order (Metashape's P1
    /// is `p2` here and its P2 is `p1`), then the skew `b2 / (f + b1)` added to x:
    /// `x_d = x' + skew·y'`. Not a COLMAP model; with `k4 = skew = 0` it is FULL_OPENCV.
    Brown {
        k: [f64; 4],
        p1: f64,
        p2: f64,
        skew: f64,
    },
    /// COLMAP FOV (Devernay & Faugeras 2001): `x_d = x · atan(2 r tan(ω/2)) / (r ω)`.
    Fov { omega: f64 },
    /// COLMAP SIMPLE_DIVISION / DIVISION (Fitzgibbon 2001): the undistorted point is
    /// `x_d / (1 + k r_d²)`.
    Division { k: f64 },
    /// Equidistant fisheye with radial terms (COLMAP OPENCV_FISHEYE: `k = [k1 … k4]`;
    /// RADIAL_FISHEYE, SIMPLE_RADIAL_FISHEYE, FISHEYE, SIMPLE_FISHEYE are the same with fewer
    /// or no terms): `θ_d = θ (1 + k1 θ² + k2 θ⁴ + k3 θ⁶ + k4 θ⁸)` in the fisheye plane.
    Fisheye { k: [f64; 4] },
    /// COLMAP THIN_PRISM_FISHEYE: in the fisheye plane, radial `k = [k1 … k4]` on
    /// `θ²…θ⁸`, tangential p1, p2 and thin-prism sx1, sy1.
    ThinPrismFisheye {
        k: [f64; 4],
        p1: f64,
        p2: f64,
        sx1: f64,
        sy1: f64,
    },
    /// COLMAP RAD_TAN_THIN_PRISM_FISHEYE (Project Aria's Fisheye624): radial `k = [k0 … k5]`
    /// on `θ²…θ¹²`, then tangential `p = [p0, p1]` and thin-prism `s = [s0 … s3]`.
    RadTanThinPrismFisheye {
        k: [f64; 6],
        p: [f64; 2],
        s: [f64; 4],
    },
}

/// `(x, y) · θ / r` with `θ = atan(r)`: pinhole → equidistant fisheye plane (COLMAP's
/// `FisheyeFromNormal`).
fn fisheye_from_normal<T: Real>(x: T, y: T) -> (T, T) {
    let r = (x * x + y * y).sqrt();
    if r.val() > f64::EPSILON {
        let t = r.atan() / r;
        (x * t, y * t)
    } else {
        (x, y)
    }
}

impl Distortion {
    /// Whether the model distorts in the equidistant fisheye plane.
    pub fn is_fisheye(&self) -> bool {
        matches!(
            self,
            Distortion::Fisheye { .. }
                | Distortion::ThinPrismFisheye { .. }
                | Distortion::RadTanThinPrismFisheye { .. }
        )
    }

    /// COLMAP's `Distortion` of a model: the distorted point `(u, v) + (du, dv)` in the model's
    /// own plane (pinhole for perspective models, fisheye for fisheye models). Not used for
    /// `Fov` and `Division`, whose maps are closed-form. Generic over [`Real`] so that
    /// [`Distortion::distort_jacobian`] differentiates this very code (constants are written on
    /// the right of each product and sum; IEEE `+` and `×` commute exactly, so the f64 values
    /// are COLMAP's expressions bit for bit).
    fn distort_plane<T: Real>(&self, u: T, v: T) -> (T, T) {
        match *self {
            Distortion::None | Distortion::Fov { .. } | Distortion::Division { .. } => (u, v),
            Distortion::SimpleRadial { k } => {
                let r2 = u * u + v * v;
                let f = r2 * k + 1.0;
                (u * f, v * f)
            }
            Distortion::Radial { k1, k2 } => {
                let r2 = u * u + v * v;
                let f = r2 * k1 + 1.0 + r2 * k2 * r2;
                (u * f, v * f)
            }
            Distortion::OpenCv { k1, k2, p1, p2 } => {
                let (x2, y2, xy) = (u * u, v * v, u * v);
                let r2 = x2 + y2;
                let radial = r2 * k1 + r2 * k2 * r2;
                (
                    u + u * radial + xy * (2.0 * p1) + (r2 + x2 * 2.0) * p2,
                    v + v * radial + xy * (2.0 * p2) + (r2 + y2 * 2.0) * p1,
                )
            }
            Distortion::FullOpenCv { k, p1, p2 } => {
                let (u2, v2, uv) = (u * u, v * v, u * v);
                let r2 = u2 + v2;
                let (r4, r6) = (r2 * r2, r2 * r2 * r2);
                let radial = (r2 * k[0] + 1.0 + r4 * k[1] + r6 * k[2])
                    / (r2 * k[3] + 1.0 + r4 * k[4] + r6 * k[5]);
                (
                    u * radial + uv * (2.0 * p1) + (r2 + u2 * 2.0) * p2,
                    v * radial + uv * (2.0 * p2) + (r2 + v2 * 2.0) * p1,
                )
            }
            Distortion::Brown { k, p1, p2, skew } => {
                let (u2, v2, uv) = (u * u, v * v, u * v);
                let r2 = u2 + v2;
                let radial = r2 * (r2 * (r2 * (r2 * k[3] + k[2]) + k[1]) + k[0]);
                let x = u + u * radial + uv * (2.0 * p1) + (r2 + u2 * 2.0) * p2;
                let y = v + v * radial + uv * (2.0 * p2) + (r2 + v2 * 2.0) * p1;
                (x + y * skew, y)
            }
            Distortion::Fisheye { k } => {
                let t2 = u * u + v * v;
                let radial = t2 * (t2 * (t2 * (t2 * k[3] + k[2]) + k[1]) + k[0]);
                (u + u * radial, v + v * radial)
            }
            Distortion::ThinPrismFisheye {
                k,
                p1,
                p2,
                sx1,
                sy1,
            } => {
                let (u2, v2, uv) = (u * u, v * v, u * v);
                let r2 = u2 + v2;
                let (r4, r6) = (r2 * r2, r2 * r2 * r2);
                let radial = r2 * k[0] + r4 * k[1] + r6 * k[2] + r6 * k[3] * r2;
                (
                    u + u * radial + uv * (2.0 * p1) + (r2 + u2 * 2.0) * p2 + r2 * sx1,
                    v + v * radial + uv * (2.0 * p2) + (r2 + v2 * 2.0) * p1 + r2 * sy1,
                )
            }
            Distortion::RadTanThinPrismFisheye { k, p, s } => {
                let t2 = u * u + v * v;
                let (mut radial, mut tp) = (T::cst(1.0), T::cst(1.0));
                for c in k {
                    tp = tp * t2;
                    radial = radial + tp * c;
                }
                let (x, y) = (radial * u, radial * v);
                let (x2, y2, xy) = (x * x, y * y, x * y);
                let r2 = x2 + y2;
                let r4 = r2 * r2;
                (
                    x + xy * (2.0 * p[1]) + (r2 + x2 * 2.0) * p[0] + r2 * s[0] + r4 * s[1],
                    y + xy * (2.0 * p[0]) + (r2 + y2 * 2.0) * p[1] + r2 * s[2] + r4 * s[3],
                )
            }
        }
    }

    /// Distort normalised pinhole coordinates (x, y) → distorted normalised image coordinates,
    /// exactly as COLMAP's camera models (fisheye models: in the fisheye plane).
    pub fn distort(&self, x: f64, y: f64) -> (f64, f64) {
        self.distort_t(x, y)
    }

    /// [`Distortion::distort`] and its exact Jacobian `[[∂x_d/∂x, ∂x_d/∂y], [∂y_d/∂x,
    /// ∂y_d/∂y]]` (forward-mode dual numbers through the same formulas, `scene/dual.rs`). The
    /// value is bit-identical to `distort`'s.
    pub fn distort_jacobian(&self, x: f64, y: f64) -> ((f64, f64), [[f64; 2]; 2]) {
        let (a, b) = self.distort_t(Dual2::var(x, 0), Dual2::var(y, 1));
        ((a.v, b.v), [a.d, b.d])
    }

    fn distort_t<T: Real>(&self, x: T, y: T) -> (T, T) {
        match *self {
            Distortion::Fov { omega } => {
                // COLMAP FOVCameraModel::Distortion (with its small-ω and small-r series).
                let (r2, o2) = (x * x + y * y, omega * omega);
                let f = if o2 < 1e-4 {
                    (r2 * o2) / 3.0 - o2 / 12.0 + 1.0
                } else if r2.val() < 1e-4 {
                    let t = (omega / 2.0).tan();
                    ((r2 * 4.0 * t * t - 3.0) * (-2.0 * t)) / (3.0 * omega)
                } else {
                    let r = r2.sqrt();
                    (r * 2.0 * (omega / 2.0).tan()).atan() / (r * omega)
                };
                (x * f, y * f)
            }
            Distortion::Division { k } => {
                // COLMAP DivisionCameraModel::ImgFromCam with w = 1: r = 2 / (1 + √(1 − 4ρ²k)).
                let rho2 = x * x + y * y;
                let disc = (T::cst(1.0) - rho2 * 4.0 * k).max0().sqrt();
                let r = T::cst(2.0) / (disc + 1.0);
                (x * r, y * r)
            }
            d if d.is_fisheye() => {
                let (u, v) = fisheye_from_normal(x, y);
                self.distort_plane(u, v)
            }
            _ => self.distort_plane(x, y),
        }
    }
    /// Invert [`Distortion::distort_plane`] by Newton's method with a central-difference
    /// Jacobian (as COLMAP's `IterativeUndistortion`); converges to ~1e-15 for the distortions
    /// real cameras have.
    fn undistort_plane(&self, xd: f64, yd: f64) -> (f64, f64) {
        let (mut x, mut y) = (xd, yd);
        for _ in 0..100 {
            let (fx, fy) = self.distort_plane(x, y);
            let (rx, ry) = (fx - xd, fy - yd);
            if rx.abs() < 1e-15 && ry.abs() < 1e-15 {
                break;
            }
            let h = 1e-7 * (1.0 + x.abs().max(y.abs()));
            let (ax, ay) = self.distort_plane(x + h, y);
            let (bx, by) = self.distort_plane(x - h, y);
            let (cx, cy) = self.distort_plane(x, y + h);
            let (dx, dy) = self.distort_plane(x, y - h);
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

    /// Camera-frame direction (not normalised) of the ray through distorted normalised image
    /// coordinates (xd, yd). Perspective models give `(x, y, 1)` with (x, y) the undistorted
    /// pinhole coordinates; fisheye models give `(u sin θ/θ, v sin θ/θ, cos θ)` from the
    /// undistorted fisheye point (u, v), `θ = |(u, v)|`, so rays at 90° and beyond the optical
    /// axis stay exact.
    pub fn undistort_dir(&self, xd: f64, yd: f64) -> DVec3 {
        match *self {
            Distortion::None => DVec3::new(xd, yd, 1.0),
            Distortion::Fov { omega } => {
                // COLMAP FOVCameraModel::Undistortion.
                let (r2, o2) = (xd * xd + yd * yd, omega * omega);
                let f = if o2 < 1e-4 {
                    (o2 * r2) / 3.0 - o2 / 12.0 + 1.0
                } else if r2 < 1e-4 {
                    (omega * (omega * omega * r2 + 3.0)) / (6.0 * (omega / 2.0).tan())
                } else {
                    let r = r2.sqrt();
                    (r * omega).tan() / (r * 2.0 * (omega / 2.0).tan())
                };
                DVec3::new(xd * f, yd * f, 1.0)
            }
            Distortion::Division { k } => {
                let d = 1.0 + k * (xd * xd + yd * yd);
                DVec3::new(xd / d, yd / d, 1.0)
            }
            d if d.is_fisheye() => {
                let (u, v) = self.undistort_plane(xd, yd);
                let t = (u * u + v * v).sqrt();
                if t > f64::EPSILON {
                    let s = t.sin() / t;
                    DVec3::new(u * s, v * s, t.cos())
                } else {
                    DVec3::new(u, v, 1.0)
                }
            }
            _ => {
                let (x, y) = self.undistort_plane(xd, yd);
                DVec3::new(x, y, 1.0)
            }
        }
    }

    /// Undistorted normalised pinhole coordinates `(X/Z, Y/Z)` of distorted (xd, yd) (see
    /// [`Distortion::undistort_dir`]; a fisheye ray at or beyond 90° has no such coordinates
    /// and gives non-finite values).
    pub fn undistort(&self, xd: f64, yd: f64) -> (f64, f64) {
        let d = self.undistort_dir(xd, yd);
        if d.z == 1.0 {
            (d.x, d.y)
        } else {
            (d.x / d.z, d.y / d.z)
        }
    }
}

/// A camera without its pose: what a camera file's camera or sensor entry holds (COLMAP's
/// `cameras.txt` rows, Metashape's `<sensor>`s) before an image's pose is attached.
#[derive(Clone, Debug)]
pub struct Intrinsics {
    pub width: u32,
    pub height: u32,
    pub fx: f64,
    pub fy: f64,
    pub cx: f64,
    pub cy: f64,
    pub distortion: Distortion,
}

impl Intrinsics {
    /// The camera with world→camera `rotation` and `translation`.
    pub fn posed(&self, rotation: DMat3, translation: DVec3) -> Camera {
        Camera {
            width: self.width,
            height: self.height,
            fx: self.fx,
            fy: self.fy,
            cx: self.cx,
            cy: self.cy,
            distortion: self.distortion,
            rotation,
            translation,
        }
    }
}

/// A posed camera: intrinsics K, distortion, world→camera rotation and translation.
#[derive(Clone, Debug, PartialEq)]
pub struct Camera {
    /// Image size in pixels.
    pub width: u32,
    pub height: u32,
    /// K = `[[fx,0,cx],[0,fy,cy],[0,0,1]]` in pixels (pixel centres at +0.5).
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
        self.distortion.undistort_dir(xn, yn)
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

    /// The camera for the same view at `f` times the resolution: size `round(w·f) × round(h·f)`,
    /// K scaled by the actual size ratios (pixel-edge convention: cx' = cx · w'/w), the same
    /// field of view and pose. `f = 1` returns the camera unchanged.
    pub fn scaled(&self, f: f64) -> Camera {
        if f == 1.0 {
            return self.clone();
        }
        let (w, h) = self.scaled_size(f);
        let (w, h) = (w as u32, h as u32);
        let (sx, sy) = (w as f64 / self.width as f64, h as f64 / self.height as f64);
        Camera {
            width: w,
            height: h,
            fx: self.fx * sx,
            fy: self.fy * sy,
            cx: self.cx * sx,
            cy: self.cy * sy,
            ..self.clone()
        }
    }

    /// The size of [`scaled`](Self::scaled)'s camera, `round(w·f) × round(h·f)`, in f64: what
    /// was asked for even when a side exceeds what a camera holds (`scaled` saturates it at
    /// `u32::MAX`), so callers can judge and report it first.
    pub fn scaled_size(&self, f: f64) -> (f64, f64) {
        let side = |n: u32| (n as f64 * f).round().max(0.0);
        (side(self.width), side(self.height))
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

    /// One of every model, with real lenses' coefficients.
    fn every_model() -> Vec<Distortion> {
        vec![
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
            Distortion::FullOpenCv {
                k: [-0.18, 0.05, -0.01, 0.02, -0.004, 0.001],
                p1: -0.002,
                p2: 0.0015,
            },
            Distortion::Brown {
                k: [-0.15, 0.04, -0.01, 0.002],
                p1: 0.0008,
                p2: -0.0011,
                skew: 0.0004,
            },
            Distortion::Fov { omega: 0.9 },
            Distortion::Fov { omega: 0.005 },
            Distortion::Division { k: -0.08 },
            Distortion::Fisheye {
                k: [0.03, -0.011, 0.002, -0.0003],
            },
            Distortion::ThinPrismFisheye {
                k: [0.02, -0.01, 0.001, 0.0002],
                p1: 0.001,
                p2: -0.0007,
                sx1: 0.0009,
                sy1: -0.0005,
            },
            Distortion::RadTanThinPrismFisheye {
                k: [0.02, -0.006, 0.001, 0.0001, 0.0, 0.0],
                p: [0.0008, -0.0006],
                s: [0.0004, -0.0002, 0.0003, 0.0001],
            },
        ]
    }

    /// `distort_jacobian`'s value is `distort`'s bit for bit, and its Jacobian matches central
    /// differences of `distort` (f64, step 1e-6) to 1e-8 for every model.
    #[test]
    fn distortion_jacobian_matches_finite_differences() {
        let h = 1e-6;
        for m in every_model() {
            let mut worst = 0.0f64;
            for i in 0..9 {
                for j in 0..9 {
                    let (x, y) = (-0.8 + 0.19 * i as f64, -0.6 + 0.143 * j as f64);
                    let ((xd, yd), jac) = m.distort_jacobian(x, y);
                    let (ex, ey) = m.distort(x, y);
                    assert!(xd.to_bits() == ex.to_bits() && yd.to_bits() == ey.to_bits());
                    let (ax, ay) = m.distort(x + h, y);
                    let (bx, by) = m.distort(x - h, y);
                    let (cx, cy) = m.distort(x, y + h);
                    let (dx, dy) = m.distort(x, y - h);
                    let fd = [
                        [(ax - bx) / (2.0 * h), (cx - dx) / (2.0 * h)],
                        [(ay - by) / (2.0 * h), (cy - dy) / (2.0 * h)],
                    ];
                    for r in 0..2 {
                        for c in 0..2 {
                            worst = worst.max((fd[r][c] - jac[r][c]).abs());
                        }
                    }
                }
            }
            assert!(worst < 1e-8, "{m:?}: worst |fd − analytic| = {worst:e}");
        }
        // The identity's Jacobian is the identity.
        let (_, j) = Distortion::None.distort_jacobian(0.3, -0.2);
        assert_eq!(j, [[1.0, 0.0], [0.0, 1.0]]);
    }

    #[test]
    fn undistort_inverts_distort() {
        // The four models this round trip has always checked, with `every_model`'s coefficients.
        let models = every_model().into_iter().filter(|m| {
            matches!(
                m,
                Distortion::SimpleRadial { .. }
                    | Distortion::Radial { .. }
                    | Distortion::OpenCv { .. }
                    | Distortion::Brown { .. }
            )
        });
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
