//! Camera placement for synthetic scenes: `look_at`, an aerial ring looking down obliquely at
//! the scene, and close-ups a few metres from surface points (walls, roofs, ground).
//!
//! All cameras are pinhole (`Distortion::None`) with the same K; close-ups stand at
//! `close_distance ≤ aerial_distance / 20` from their target point, so their pixel footprints
//! are ≥ 20× finer. A candidate camera is kept only if it stands outside every building, above
//! the terrain, and at least `min_hit_fraction` of a coarse grid of its pixel rays hits the
//! surface; otherwise the next deterministic candidate is tried.

use super::noise::stream;
use super::surface::TrueSurface;
use crate::rng::{self, Purpose};
use crate::scene::{Camera, Distortion};
use glam::{DMat3, DVec3};

/// World→camera `(rotation, translation)` in OpenCV axes (x right, y down, z forward) for a
/// camera at `eye` looking at `target`, with `up` (world) pointing up in the image.
/// Panics if `target == eye` or `up` is parallel to the viewing direction (programming errors).
pub fn look_at(eye: DVec3, target: DVec3, up: DVec3) -> (DMat3, DVec3) {
    let f = (target - eye).normalize();
    let r = f.cross(up);
    assert!(
        r.length() > 1e-12,
        "look_at: up is parallel to the view direction"
    );
    let r = r.normalize();
    let down = f.cross(r);
    // Rows of the world→camera rotation are the camera axes in world coordinates.
    let rotation = DMat3::from_cols(r, down, f).transpose();
    (rotation, -(rotation * eye))
}

/// What a view is.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "lowercase")]
pub enum ViewKind {
    Aerial,
    Close,
}

/// A placed camera and why it is there.
#[derive(Clone, Debug)]
pub struct Placed {
    pub kind: ViewKind,
    pub camera: Camera,
    pub target: DVec3,
    /// Distance from the eye to the target (m).
    pub distance: f64,
}

/// Intrinsics shared by all views: width, height and horizontal field of view.
pub fn intrinsics(width: u32, height: u32, hfov_deg: f64) -> (f64, f64, f64, f64) {
    let f = 0.5 * width as f64 / (0.5 * hfov_deg.to_radians()).tan();
    (f, f, 0.5 * width as f64, 0.5 * height as f64)
}

/// Camera parameters of a preset (recorded in `synth.toml`).
#[derive(Clone, Debug, PartialEq, serde::Serialize)]
pub struct CameraParams {
    pub width: u32,
    pub height: u32,
    pub hfov_deg: f64,
    pub n_aerial: usize,
    pub n_close: usize,
    /// Eye–target distance of aerial views (m).
    pub aerial_distance: f64,
    /// Elevation range of aerial views above the horizon (degrees).
    pub aerial_elevation_deg: [f64; 2],
    /// Aerial targets are jittered by up to this much around the scene centre (m).
    pub aerial_target_jitter: f64,
    /// Eye–target distance of close-ups (m).
    pub close_distance: f64,
    /// Close-up targets lie within this half-width of the centre (m).
    pub close_region: f64,
    /// Close-ups come in clusters of this many views of one target from nearby positions, so a
    /// held-out close-up has training views of the same surface at the same scale (1 = every
    /// close-up has its own target; omitted from `synth.toml` then).
    #[serde(skip_serializing_if = "is_one")]
    pub close_cluster: usize,
    pub min_hit_fraction: f64,
    /// Close-up cluster `k` looks at `CLOSE_MATERIALS[k % 7]` (so the held-out close-ups cover
    /// every material), instead of cycling target types with each placement attempt.
    #[serde(skip_serializing_if = "std::ops::Not::not")]
    pub close_by_material: bool,
}

/// What a close-up cluster looks at.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Target {
    Wall,
    Roof,
    /// The ground where the terrain is paved (`true`) or grass (`false`).
    Ground(bool),
}

/// The cycle of close-up targets with `close_by_material`: with 7 clusters of 4 interleaved
/// among as many aerial views, the every-7th held-out views are close-ups of clusters 0, 2, 4, 6:
/// a wall, a roof, grass and pavement.
pub const CLOSE_MATERIALS: [Target; 7] = [
    Target::Wall,
    Target::Ground(true),
    Target::Roof,
    Target::Wall,
    Target::Ground(false),
    Target::Roof,
    Target::Ground(true),
];

fn camera(p: &CameraParams, eye: DVec3, target: DVec3) -> Camera {
    let (fx, fy, cx, cy) = intrinsics(p.width, p.height, p.hfov_deg);
    let (rotation, translation) = look_at(eye, target, DVec3::Z);
    Camera {
        width: p.width,
        height: p.height,
        fx,
        fy,
        cx,
        cy,
        distortion: Distortion::None,
        rotation,
        translation,
    }
}

/// Fraction of a 16×12 grid of pixel-centre rays that hit the surface.
pub fn hit_fraction(surface: &TrueSurface, cam: &Camera) -> f64 {
    let (nx, ny) = (16u32, 12u32);
    let o = cam.center();
    let mut hits = 0;
    for j in 0..ny {
        for i in 0..nx {
            let x = (i as f64 + 0.5) * cam.width as f64 / nx as f64;
            let y = (j as f64 + 0.5) * cam.height as f64 / ny as f64;
            if surface
                .trace(o, cam.dir_world(x, y), 0.0, f64::INFINITY)
                .is_some()
            {
                hits += 1;
            }
        }
    }
    hits as f64 / (nx * ny) as f64
}

fn eye_ok(surface: &TrueSurface, eye: DVec3) -> bool {
    // `height_at` clamps to the terrain's square, so outside it the border height applies.
    !surface.buildings.iter().any(|b| b.contains(eye, 0.5))
        && eye.z > surface.terrain.height_at(eye.x, eye.y) + 0.5
}

fn is_one(n: &usize) -> bool {
    *n == 1
}

/// Place every camera. `close[i]` says whether view i is a close-up (interleaved by the caller).
/// Close-up `c` belongs to cluster `c / close_cluster`: the first of a cluster picks a target,
/// the others look at the same target from nearby eyes (`place_near`).
/// `paved(x, y)` says whether the terrain at (x, y) is pavement (used with `close_by_material`).
pub fn place(
    seed: u64,
    p: &CameraParams,
    surface: &TrueSurface,
    close: &[bool],
    paved: &dyn Fn(f64, f64) -> bool,
) -> Vec<Placed> {
    let mut out = Vec::with_capacity(close.len());
    let (mut ia, mut ic) = (0usize, 0usize);
    let cluster = p.close_cluster.max(1);
    let mut anchor: Option<Placed> = None;
    for &is_close in close {
        let placed = if is_close {
            ic += 1;
            let c = ic - 1;
            let placed = match &anchor {
                Some(a) if c % cluster != 0 => place_near(seed, p, surface, a, c),
                _ => place_close(seed, p, surface, c / cluster, paved),
            };
            if c % cluster == 0 {
                anchor = Some(placed.clone());
            }
            placed
        } else {
            ia += 1;
            place_aerial(seed, p, surface, ia - 1)
        };
        out.push(placed);
    }
    out
}

const MAX_ATTEMPTS: u64 = 256;

fn place_aerial(seed: u64, p: &CameraParams, s: &TrueSurface, k: usize) -> Placed {
    let r = |attempt: u64, c: u64| {
        rng::uniform_f64(
            seed,
            Purpose::Synth,
            stream::CAMERAS + 1,
            (k as u64) << 16 | attempt << 4 | c,
        )
    };
    let mut fallback = None;
    for attempt in 0..MAX_ATTEMPTS {
        let az = std::f64::consts::TAU * (k as f64 + 0.3 * r(attempt, 0)) / p.n_aerial as f64;
        let [e0, e1] = p.aerial_elevation_deg;
        let el = (e0 + (e1 - e0) * r(attempt, 1)).to_radians();
        let j = p.aerial_target_jitter;
        let tx = j * (2.0 * r(attempt, 2) - 1.0);
        let ty = j * (2.0 * r(attempt, 3) - 1.0);
        let target = DVec3::new(tx, ty, s.terrain.height_at(tx, ty));
        let eye = target
            + p.aerial_distance * DVec3::new(el.cos() * az.cos(), el.cos() * az.sin(), el.sin());
        if !eye_ok(s, eye) {
            continue;
        }
        let cam = camera(p, eye, target);
        let placed = Placed {
            kind: ViewKind::Aerial,
            camera: cam,
            target,
            distance: p.aerial_distance,
        };
        if hit_fraction(s, &placed.camera) >= p.min_hit_fraction {
            return placed;
        }
        fallback.get_or_insert(placed);
    }
    fallback.expect("no admissible aerial camera")
}

fn place_close(
    seed: u64,
    p: &CameraParams,
    s: &TrueSurface,
    k: usize,
    paved: &dyn Fn(f64, f64) -> bool,
) -> Placed {
    let r = |attempt: u64, c: u64| {
        rng::uniform_f64(
            seed,
            Purpose::Synth,
            stream::CAMERAS + 2,
            (k as u64) << 16 | attempt << 4 | c,
        )
    };
    let mut fallback = None;
    let d = p.close_distance;
    for attempt in 0..MAX_ATTEMPTS {
        // Cycle through target types: wall, ground, roof, wall, ground, … (with each attempt,
        // unless `close_by_material` fixes the cluster's target).
        let want = p
            .close_by_material
            .then(|| CLOSE_MATERIALS[k % CLOSE_MATERIALS.len()]);
        let kind = match want {
            Some(Target::Wall) => 0,
            Some(Target::Roof) => 2,
            Some(Target::Ground(_)) => 1,
            None => (k + attempt as usize) % 5,
        };
        let (target, eye) = if (kind == 0 || kind == 3) && !s.buildings.is_empty() {
            // A wall: a point on one face, the camera in front of it, tilted down 15–30°.
            let b = &s.buildings[(r(attempt, 0) * s.buildings.len() as f64) as usize];
            let face = (r(attempt, 1) * 4.0) as usize;
            let (axis, side) = (face % 2, face / 2);
            let other = 1 - axis;
            let u = 0.2 + 0.6 * r(attempt, 2);
            let mut t = DVec3::ZERO;
            t[axis] = if side == 0 { b.lo[axis] } else { b.hi[axis] };
            t[other] = b.lo[other] + u * (b.hi[other] - b.lo[other]);
            let ground = s.terrain.height_at(t.x, t.y);
            let top = b.hi[2];
            t.z = (ground + 2.0 + (top - ground - 5.0).max(0.0) * r(attempt, 3)).min(top - 1.5);
            let mut n = DVec3::ZERO;
            n[axis] = if side == 0 { -1.0 } else { 1.0 };
            let tilt = (15.0 + 15.0 * r(attempt, 4)).to_radians();
            let yaw = (-20.0 + 40.0 * r(attempt, 5)).to_radians();
            let side_dir = DVec3::Z.cross(n);
            let horiz = n * yaw.cos() + side_dir * yaw.sin();
            (t, t + d * (horiz * tilt.cos() + DVec3::Z * tilt.sin()))
        } else if kind == 2 && !s.buildings.is_empty() {
            // A roof: look down steeply.
            let b = &s.buildings[(r(attempt, 0) * s.buildings.len() as f64) as usize];
            let tx = b.lo[0] + (0.25 + 0.5 * r(attempt, 1)) * (b.hi[0] - b.lo[0]);
            let ty = b.lo[1] + (0.25 + 0.5 * r(attempt, 2)) * (b.hi[1] - b.lo[1]);
            let t = DVec3::new(tx, ty, b.hi[2]);
            let az = std::f64::consts::TAU * r(attempt, 3);
            let el = (55.0 + 30.0 * r(attempt, 4)).to_radians();
            (
                t,
                t + d * DVec3::new(el.cos() * az.cos(), el.cos() * az.sin(), el.sin()),
            )
        } else {
            // The ground (terrain or whatever stands there), looked at from 45–80° elevation.
            let h = p.close_region;
            let tx = h * (2.0 * r(attempt, 0) - 1.0);
            let ty = h * (2.0 * r(attempt, 1) - 1.0);
            let o = DVec3::new(tx, ty, s.terrain.max_height + 100.0);
            let Some(hit) = s.trace(o, DVec3::NEG_Z, 0.0, f64::INFINITY) else {
                continue;
            };
            if let Some(Target::Ground(pave)) = want {
                // The wanted material, and open ground (not a roof) around the target.
                let open = s.buildings.iter().all(|b| !b.contains(hit.pos, 2.0 * d));
                if paved(tx, ty) != pave || !open {
                    continue;
                }
            }
            let t = hit.pos;
            let az = std::f64::consts::TAU * r(attempt, 3);
            let el = (45.0 + 35.0 * r(attempt, 4)).to_radians();
            (
                t,
                t + d * DVec3::new(el.cos() * az.cos(), el.cos() * az.sin(), el.sin()),
            )
        };
        let Some((placed, enough)) = close_candidate(p, s, eye, target, d) else {
            continue;
        };
        if enough {
            return placed;
        }
        fallback.get_or_insert(placed);
    }
    fallback.expect("no admissible close-up camera")
}

/// A close-up of `anchor`'s target from a nearby eye: azimuth within ±25°, elevation within
/// ±12° (kept in 10°..85°), distance 0.8–1.2 × the close-up distance; the same admissibility
/// checks as [`place_close`]. Falls back to the anchor's own camera.
fn place_near(seed: u64, p: &CameraParams, s: &TrueSurface, anchor: &Placed, k: usize) -> Placed {
    let r = |attempt: u64, c: u64| {
        rng::uniform_f64(
            seed,
            Purpose::Synth,
            stream::CAMERAS + 3,
            (k as u64) << 16 | attempt << 4 | c,
        )
    };
    let target = anchor.target;
    let off = anchor.camera.center() - target;
    let (az0, el0) = (off.y.atan2(off.x), (off.z / off.length()).asin());
    for attempt in 0..MAX_ATTEMPTS {
        let az = az0 + (50.0 * r(attempt, 0) - 25.0).to_radians();
        let el = (el0 + (24.0 * r(attempt, 1) - 12.0).to_radians())
            .clamp(10f64.to_radians(), 85f64.to_radians());
        let d = p.close_distance * (0.8 + 0.4 * r(attempt, 2));
        let eye = target + d * DVec3::new(el.cos() * az.cos(), el.cos() * az.sin(), el.sin());
        if let Some((placed, true)) = close_candidate(p, s, eye, target, d) {
            return placed;
        }
    }
    anchor.clone()
}

/// A close-up from `eye` at `target` (distance `d`): `None` if the eye is inside something or
/// the target is hidden from it; else the camera and whether enough of its pixels see surface.
fn close_candidate(
    p: &CameraParams,
    s: &TrueSurface,
    eye: DVec3,
    target: DVec3,
    d: f64,
) -> Option<(Placed, bool)> {
    if !eye_ok(s, eye) {
        return None;
    }
    // The target must be visible from the eye (nothing in between).
    let dir = (target - eye).normalize();
    match s.trace(eye, dir, 0.0, f64::INFINITY) {
        Some(h) if (h.t - d).abs() < 1e-6 * d.max(1.0) + 1e-6 => {}
        _ => return None,
    }
    let placed = Placed {
        kind: ViewKind::Close,
        camera: camera(p, eye, target),
        target,
        distance: d,
    };
    let enough = hit_fraction(s, &placed.camera) >= p.min_hit_fraction;
    Some((placed, enough))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn look_at_axes() {
        let eye = DVec3::new(1.0, -2.0, 3.0);
        let target = DVec3::new(4.0, 2.0, -1.0);
        let (r, t) = look_at(eye, target, DVec3::Z);
        // Orthonormal, right-handed.
        assert!((r * r.transpose() - DMat3::IDENTITY)
            .to_cols_array()
            .iter()
            .all(|v| v.abs() < 1e-12));
        assert!((r.determinant() - 1.0).abs() < 1e-12);
        // Eye maps to the origin, target onto +z.
        assert!((r * eye + t).length() < 1e-12);
        let c = r * target + t;
        assert!(c.x.abs() < 1e-12 && c.y.abs() < 1e-12 && c.z > 0.0);
        // World up appears as image up (negative y) for a point above the target.
        let above = r * (target + DVec3::Z) + t;
        assert!(above.y < 0.0);
        // A point to the right of the viewing direction (f × up) has positive x.
        let f = (target - eye).normalize();
        let right = r * (target + f.cross(DVec3::Z)) + t;
        assert!(right.x > 0.0);
    }
}
