//! Multi-view photo-consistency of the input photos: a source of vertex gradient for the mesh
//! refinement that does not depend on the learned features (`[model.refine] photo`; beyond the
//! paper; SPEC §4.11, docs/geometry.md §4). The sampling (which pixels, which neighbour view,
//! visibility, image levels) is in `refine/photo_term.rs`; this file is the energy of one patch and its
//! exact derivative with respect to the vertex offsets, in f64.
//!
//! ## One patch
//! A patch is `K = p²` pixels of a reference view i at image level l (the photo box-downsampled by
//! `2^l`, its camera's K divided by `2^l`): pixel q has the ray `o_i + t·d_q` through its centre,
//! the triangle that ray hit (from the BVH of the last rebuild: data) and the reference colour
//! `a_q` = the level-l photo of view i at q (data). The ray meets the triangle's *current* plane
//! at `x_q = o_i + t_q·d_q` (Möller–Trumbore, `hit::intersect`, as the hit point of the
//! feature gradient), which is projected into the neighbour view j at the same level
//! (`c = R_j (x_q − o_j)`, `π = (f_x x_d + c_x', f_y y_d + c_y')` with `(x_d, y_d) =
//! D_j(c_x/c_z, c_y/c_z)`, D_j the view's lens distortion — the identity for a pinhole — as
//! `Camera::project`) and sampled there
//! bilinearly between pixel centres: `b_q = I_j(π(x_q))`. The patch's energy is `w · ρ(a, b)`,
//! with `w` = `photo / photo_pixels` times the reference view's weight (`photo_balance`) and ρ
//! one of
//!
//! ```text
//! zncc:  a' = a − mean_q a (per channel), b' likewise (3K values each),
//!        ρ = 1 − a'·b' / sqrt((a'·a' + ε)(b'·b' + ε)),   ε = 3K · σ₀², σ₀ = 0.01
//! huber: ρ = (1/3K) Σ_{q,c} h(b_qc − a_qc),   h(r) = r²/(2δ) (|r| < δ), |r| − δ/2 (else), δ = 0.02
//! ```
//!
//! ## Derivative
//! `∂ρ/∂b` (zncc: `a'/D − ncc · b'/(b'·b' + ε)`, D the denominator — already zero-mean per
//! channel, so the mean subtraction adds nothing), times the bilinear image gradient
//! `(∂I/∂π_x, ∂I/∂π_y)` of the cell the sample lies in, times `∂π/∂x`
//! (pinhole: `(f_x/c_z)(R_j,0 − (c_x/c_z) R_j,2)` and likewise for y; through a distortion the
//! two rows of the pinhole derivative are mixed by D_j's exact 2×2 Jacobian, `PhotoCamera::project`) gives `g_q = ∂E/∂x_q` (local units);
//! then the hit-point chain of the feature gradient (SPEC §4.11):
//!
//! ```text
//! ∂E/∂θ_k = s · (g_q·d_q) · β_k · (n·m_k) / (n·d_q)        (k the corners of q's triangle)
//! ```
//!
//! Held constant (data): the rays, the triangle of each ray, the reference colours, the pair
//! (i, j), the image level, and visibility. The energy is piecewise smooth: the bilinear gradient
//! jumps where a sample crosses a pixel-centre line (the gradient check skips those steps).
//!
//! ## Curvature (for the Gauss–Newton step)
//! `curvature` is the Gauss–Newton curvature of the patch's energy along a common shift `θ_c` of
//! all its vertices (`∂x_q/∂θ_c = s·d_q·Σ_k β_k (n·m_k)/(n·d_q)`): with `J = ∂b/∂θ_c` (3K values),
//! `w·|∂b̂/∂θ_c|²` for zncc (`b̂ = b'/sqrt(b'·b' + ε)`, `1 − ncc ≈ ½|b̂ − â|²`) and
//! `w·(1/3K)Σ J²/max(|r|, δ)` for huber (iteratively reweighted least squares).

use crate::model::refine::PhotoMeasure;
use crate::refine::field::RefineGeom;
use crate::refine::hit::{intersect, plane_hit_chain};
use crate::scene::{Camera, Distortion, Image};
use glam::{DMat3, DVec3};

/// Noise floor of the zncc's variances (colour units): `ε = 3K·σ₀²`.
pub const ZNCC_SIGMA0: f64 = 0.01;
/// Huber threshold of the `huber` measure (colour units).
pub const HUBER_DELTA: f64 = 0.02;

/// A camera at one image level, in the refinement's local frame (world − normalisation
/// centre), with its lens distortion (any model the scene loaders read; SPEC §3.3).
#[derive(Clone, Debug, PartialEq)]
pub struct PhotoCamera {
    /// Camera centre, local frame.
    pub origin: DVec3,
    /// World→camera rotation (OpenCV axes).
    pub rot: DMat3,
    pub fx: f64,
    pub fy: f64,
    pub cx: f64,
    pub cy: f64,
    pub width: u32,
    pub height: u32,
    /// Applied to normalised coordinates, so the same at every level.
    pub distortion: Distortion,
}

impl PhotoCamera {
    /// The camera of a view at level 0; `center` is the normalisation centre.
    pub fn new(cam: &Camera, center: DVec3) -> PhotoCamera {
        PhotoCamera {
            origin: cam.center() - center,
            rot: cam.rotation,
            fx: cam.fx,
            fy: cam.fy,
            cx: cam.cx,
            cy: cam.cy,
            width: cam.width,
            height: cam.height,
            distortion: cam.distortion,
        }
    }

    /// The same camera for the photo box-downsampled by `2^l` (`Camera::downsampled`: sizes
    /// floored, K divided).
    pub fn level(&self, l: u32) -> PhotoCamera {
        let s = (1u32 << l) as f64;
        PhotoCamera {
            fx: self.fx / s,
            fy: self.fy / s,
            cx: self.cx / s,
            cy: self.cy / s,
            width: self.width >> l,
            height: self.height >> l,
            ..self.clone()
        }
    }

    /// Unit local-frame direction of the ray through continuous image point (x, y) (pixel (u, v)
    /// covers [u, u+1) × [v, v+1)), undistorted (`Distortion::undistort_dir`, as
    /// `Camera::dir_world`).
    #[inline]
    pub fn ray(&self, x: f64, y: f64) -> DVec3 {
        let c = self
            .distortion
            .undistort_dir((x - self.cx) / self.fx, (y - self.cy) / self.fy);
        (self.rot.transpose() * c).normalize()
    }

    /// Continuous image coordinates of local point `p` and their gradients with respect to `p`,
    /// or `None` behind (or nearly in the plane of) the camera. Through a lens distortion `D`
    /// the pinhole gradients `∂(x_n, y_n)/∂p` are chained through D's exact Jacobian
    /// (`Distortion::distort_jacobian`): `∂π_x/∂p = f_x (J₀₀ ∂x_n/∂p + J₀₁ ∂y_n/∂p)`, likewise y.
    #[inline]
    pub fn project(&self, p: DVec3) -> Option<([f64; 2], [DVec3; 2])> {
        let c = self.rot * (p - self.origin);
        if c.z.partial_cmp(&(1e-9 * c.length())) != Some(std::cmp::Ordering::Greater) {
            return None;
        }
        let iz = 1.0 / c.z;
        let (xn, yn) = (c.x * iz, c.y * iz);
        let (r0, r1, r2) = (self.rot.row(0), self.rot.row(1), self.rot.row(2));
        if self.distortion == Distortion::None {
            let gx = (r0 - r2 * xn) * (self.fx * iz);
            let gy = (r1 - r2 * yn) * (self.fy * iz);
            return Some(([self.fx * xn + self.cx, self.fy * yn + self.cy], [gx, gy]));
        }
        let ((xd, yd), j) = self.distortion.distort_jacobian(xn, yn);
        let (dxn, dyn_) = ((r0 - r2 * xn) * iz, (r1 - r2 * yn) * iz);
        let gx = (dxn * j[0][0] + dyn_ * j[0][1]) * self.fx;
        let gy = (dxn * j[1][0] + dyn_ * j[1][1]) * self.fy;
        Some(([self.fx * xd + self.cx, self.fy * yd + self.cy], [gx, gy]))
    }

    /// Distance-independent size of a pixel: `1/sqrt(fx·fy)` radians.
    pub fn pixel_angle(&self) -> f64 {
        1.0 / (self.fx * self.fy).abs().sqrt()
    }
}

/// An RGB photo at one level (f32, row-major, row 0 at the top).
#[derive(Clone, Debug, PartialEq)]
pub struct PhotoImage {
    pub width: u32,
    pub height: u32,
    pub data: Vec<f32>,
}

/// A bilinear sample: the colour, its derivatives along x and y, and the cell (the pixel-centre
/// lattice square the point lies in).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Sample {
    pub rgb: [f64; 3],
    pub dx: [f64; 3],
    pub dy: [f64; 3],
    pub cell: [i32; 2],
}

impl PhotoImage {
    pub fn from_image(img: &Image) -> PhotoImage {
        PhotoImage {
            width: img.width,
            height: img.height,
            data: img.data.clone(),
        }
    }

    /// Colour of pixel (u, v).
    #[inline]
    pub fn pixel(&self, u: u32, v: u32) -> [f32; 3] {
        let o = 3 * (v as usize * self.width as usize + u as usize);
        [self.data[o], self.data[o + 1], self.data[o + 2]]
    }

    /// Bilinear interpolation between pixel centres at continuous point (x, y), or `None` when the
    /// four pixels are not all inside the image (`0 ≤ x − ½ < w − 1`, likewise y).
    #[inline]
    pub fn sample(&self, x: f64, y: f64) -> Option<Sample> {
        let (px, py) = (x - 0.5, y - 0.5);
        let (w, h) = (self.width as f64, self.height as f64);
        if !(px >= 0.0 && py >= 0.0 && px < w - 1.0 && py < h - 1.0) {
            return None;
        }
        let (i, j) = (px.floor(), py.floor());
        let (fx, fy) = (px - i, py - j);
        let (i, j) = (i as u32, j as u32);
        let p00 = self.pixel(i, j);
        let p10 = self.pixel(i + 1, j);
        let p01 = self.pixel(i, j + 1);
        let p11 = self.pixel(i + 1, j + 1);
        let mut s = Sample {
            rgb: [0.0; 3],
            dx: [0.0; 3],
            dy: [0.0; 3],
            cell: [i as i32, j as i32],
        };
        for c in 0..3 {
            let (a, b, d, e) = (p00[c] as f64, p10[c] as f64, p01[c] as f64, p11[c] as f64);
            let top = a + fx * (b - a);
            let bottom = d + fx * (e - d);
            s.rgb[c] = top + fy * (bottom - top);
            s.dx[c] = (1.0 - fy) * (b - a) + fy * (e - d);
            s.dy[c] = bottom - top;
        }
        Some(s)
    }
}

/// One pixel of a reference patch: the mesh triangle its ray hit, the ray's unit direction (local
/// frame, from the reference camera's centre) and the reference colour.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PatchPoint {
    pub tri: u32,
    pub d: DVec3,
    pub reference: [f32; 3],
}

/// A patch's energy, its gradient per vertex (`(vertex, ∂E/∂θ)`, three per point in point order,
/// corners in triangle order), its Gauss–Newton curvature along a common shift (module docs), the
/// share of each gradient entry's vertex in the patch (`β_k / K`, summing to 1: how the curvature
/// is spread over the vertices), and the bilinear cells its samples fell in (a change of cell is a
/// kink).
#[derive(Clone, Debug, PartialEq)]
pub struct PatchEval {
    pub energy: f64,
    pub grad: Vec<(u32, f64)>,
    pub curvature: f64,
    pub share: Vec<f64>,
    pub cells: Vec<[i32; 2]>,
}

/// ρ(a, b) and `∂ρ/∂b` (written into `d_b`), and the curvature factor of the measure (module docs)
/// given `jb` = ∂b/∂θ_c.
pub fn measure(
    m: PhotoMeasure,
    a: &[[f64; 3]],
    b: &[[f64; 3]],
    jb: &[[f64; 3]],
    d_b: &mut [[f64; 3]],
) -> (f64, f64) {
    let k = a.len();
    let n = (3 * k) as f64;
    match m {
        PhotoMeasure::Zncc => {
            let mut ma = [0.0f64; 3];
            let mut mb = [0.0f64; 3];
            let mut mj = [0.0f64; 3];
            for q in 0..k {
                for c in 0..3 {
                    ma[c] += a[q][c];
                    mb[c] += b[q][c];
                    mj[c] += jb[q][c];
                }
            }
            for c in 0..3 {
                ma[c] /= k as f64;
                mb[c] /= k as f64;
                mj[c] /= k as f64;
            }
            let eps = n * ZNCC_SIGMA0 * ZNCC_SIGMA0;
            let (mut ab, mut aa, mut bb, mut bj) = (0.0, 0.0, 0.0, 0.0);
            for q in 0..k {
                for c in 0..3 {
                    let (x, y) = (a[q][c] - ma[c], b[q][c] - mb[c]);
                    ab += x * y;
                    aa += x * x;
                    bb += y * y;
                    bj += y * (jb[q][c] - mj[c]);
                }
            }
            let (sa, sb) = (aa + eps, bb + eps);
            let den = (sa * sb).sqrt();
            let ncc = ab / den;
            // ∂ncc/∂b' = a'/den − ncc·b'/sb (zero-mean per channel, so also ∂ncc/∂b).
            for q in 0..k {
                for c in 0..3 {
                    let (x, y) = (a[q][c] - ma[c], b[q][c] - mb[c]);
                    d_b[q][c] = -(x / den - ncc * y / sb);
                }
            }
            // |∂b̂/∂θ_c|² with b̂ = b'/sqrt(sb), j' = ∂b'/∂θ_c:
            // |j'|²/sb − (b'·j')² (2 sb − b'·b') / sb³.
            let mut jj = 0.0;
            for row in jb {
                for c in 0..3 {
                    let j = row[c] - mj[c];
                    jj += j * j;
                }
            }
            let curv = (jj / sb - bj * bj * (2.0 * sb - bb) / (sb * sb * sb)).max(0.0);
            (1.0 - ncc, curv)
        }
        PhotoMeasure::Huber => {
            let d = HUBER_DELTA;
            let (mut e, mut curv) = (0.0, 0.0);
            for q in 0..k {
                for c in 0..3 {
                    let r = b[q][c] - a[q][c];
                    let ar = r.abs();
                    let (v, g) = if ar < d {
                        (0.5 * r * r / d, r / d)
                    } else {
                        (ar - 0.5 * d, r.signum())
                    };
                    e += v;
                    d_b[q][c] = g / n;
                    curv += jb[q][c] * jb[q][c] / ar.max(d);
                }
            }
            (e / n, curv / n)
        }
    }
}

/// A neighbour view at a patch's level: its camera and its photo.
#[derive(Clone, Copy)]
pub struct Neighbour<'a> {
    pub cam: &'a PhotoCamera,
    pub img: &'a PhotoImage,
}

/// How a patch is scored: the measure ρ, the plane-hit cut-off (`hit::intersect`'s `min_cos`)
/// and the weight w of the energy `w · ρ`.
#[derive(Clone, Copy, Debug)]
pub struct Scoring {
    pub measure: PhotoMeasure,
    pub min_cos: f64,
    pub weight: f64,
}

/// The energy of one patch at offsets `theta` (module docs): `origin` is the reference camera's
/// centre (local frame), `neighbour` the other view at the patch's level. `None` when a ray
/// misses its triangle's current plane (`hit::intersect` with `min_cos`) or a sample falls
/// outside the neighbour's image or behind it. `theta` is read at the patch's triangles'
/// vertices only.
pub fn patch_eval(
    geom: &RefineGeom,
    theta: &[f64],
    origin: DVec3,
    points: &[PatchPoint],
    neighbour: Neighbour,
    scoring: Scoring,
) -> Option<PatchEval> {
    let (cam, img) = (neighbour.cam, neighbour.img);
    let Scoring {
        measure: m,
        min_cos,
        weight,
    } = scoring;
    let k = points.len();
    let mut a = Vec::with_capacity(k);
    let mut b = Vec::with_capacity(k);
    let mut jb = Vec::with_capacity(k);
    let mut cells = Vec::with_capacity(k);
    // Per point: triangle corners, barycentrics, normal, ∂π/∂x, the sample's derivatives.
    let mut geo = Vec::with_capacity(k);
    for p in points {
        let tri = geom.triangles[p.tri as usize];
        let v = tri.map(|i| geom.position(i as usize, theta[i as usize]));
        let (t, beta, n) = intersect(origin, p.d, v, min_cos)?;
        let x = origin + p.d * t;
        let (pi, dpi) = cam.project(x)?;
        let s = img.sample(pi[0], pi[1])?;
        // ∂x/∂θ_c: the hit's motion along the ray for a common shift of its three vertices.
        let nd = n.dot(p.d);
        let shift: f64 = (0..3)
            .map(|c| beta[c] * n.dot(geom.normals[tri[c] as usize]))
            .sum::<f64>()
            * geom.scale
            / nd;
        let dxc = p.d * shift;
        let (ux, uy) = (dpi[0].dot(dxc), dpi[1].dot(dxc));
        jb.push(std::array::from_fn(|c| s.dx[c] * ux + s.dy[c] * uy));
        a.push(p.reference.map(|v| v as f64));
        b.push(s.rgb);
        cells.push(s.cell);
        geo.push((tri, beta, n, dpi, s));
    }
    let mut d_b = vec![[0.0f64; 3]; k];
    let (rho, curv) = measure(m, &a, &b, &jb, &mut d_b);
    let mut grad = Vec::with_capacity(3 * k);
    let mut share = Vec::with_capacity(3 * k);
    for (q, p) in points.iter().enumerate() {
        let (tri, beta, n, dpi, s) = &geo[q];
        // ∂E/∂x_q = w Σ_c ∂ρ/∂b_qc (∂I_c/∂π_x ∂π_x/∂x + ∂I_c/∂π_y ∂π_y/∂x).
        let (mut gx, mut gy) = (0.0, 0.0);
        for (c, &db) in d_b[q].iter().enumerate() {
            gx += db * s.dx[c];
            gy += db * s.dy[c];
        }
        let g = (dpi[0] * gx + dpi[1] * gy) * weight;
        grad.extend(plane_hit_chain(geom, *tri, *beta, *n, p.d, g));
        share.extend(beta.map(|b| b / k as f64));
    }
    Some(PatchEval {
        energy: weight * rho,
        grad,
        curvature: weight * curv,
        share,
        cells,
    })
}
