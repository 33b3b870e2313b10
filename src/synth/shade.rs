//! Procedural materials and shading of the true surface (the ground truth's appearance).
//!
//! Albedo octaves (all deterministic value noise / patterns from `noise.rs`, world units):
//! - coarse (`coarse_wavelength`, tens of metres): terrain regions (grass vs pavement) and
//!   tints, per-building wall and roof colours — what the aerial views resolve;
//! - mid (`mid_wavelength` and a quarter of it, metres): mottling, weathering, roof seams —
//!   resolved by the larger aerial images and by every close-up;
//! - fine (`fine_period`, set per preset: ~3× the close-up pixel footprint, at least 2.5 `cpu`-grid cells in `small`): pavement tiles
//!   and bricks with per-tile colour and mortar joints, plus grass grain at half that period —
//!   only the close-ups resolve it.
//!
//! Anti-aliasing: besides the 4×4 sub-pixel box filter of `render.rs`, every octave fades to
//! its mean (value noise: 0.5; tiles/bricks: the area-weighted mean of tile and mortar) as the
//! per-sub-sample footprint `fp` on the surface approaches its wavelength λ: weight
//! `clamp((λ/fp − 2)/2, 0, 1)` (full detail at ≥ 4 sub-samples per wavelength, none below the
//! Nyquist rate of 2). This is texture LOD; the result is an approximation of the box-filtered
//! pixel, free of the moiré that 16 point samples of a 0.1-m brick pattern seen from 150 m
//! would otherwise give.
//!
//! Shading: `albedo·(ambient + sun·max(n·l,0)·vis) + ks·sun·vis·max(n·h,0)^shininess`
//! (Blinn–Phong, per-material `ks` and shininess; `vis` = 0 in the shadow of a building), then
//! clamped to `[0,1]`. The values are written as they are, read as sRGB-encoded: no tone
//! mapping, no gamma (documented choice: the training target is "whatever the camera stored").

use super::noise::{self, stream};
use super::surface::{Hit, SurfaceKind, TrueSurface};
use glam::DVec3;

/// Appearance parameters (recorded in `synth.toml`).
#[derive(Clone, Debug, PartialEq, serde::Serialize)]
pub struct Look {
    /// Wavelength of terrain regions and tints (m).
    pub coarse_wavelength: f64,
    /// Wavelength of mid mottling (m); a second mid octave runs at a quarter of it.
    pub mid_wavelength: f64,
    /// Tile / brick period (m); fine grain runs at half of it.
    pub fine_period: f64,
    /// Unit direction towards the sun (world, z up).
    pub sun_dir: [f64; 3],
    pub sun: f64,
    pub ambient: f64,
}

/// Per-material reflectance.
#[derive(Clone, Copy, Debug)]
pub struct Material {
    pub albedo: DVec3,
    /// Specular weight and Blinn–Phong exponent (larger = smoother).
    pub ks: f64,
    pub shininess: f64,
}

#[inline]
fn lod(wavelength: f64, fp: f64) -> f64 {
    if fp <= 0.0 {
        1.0
    } else {
        ((wavelength / fp - 2.0) * 0.5).clamp(0.0, 1.0)
    }
}

/// A centred value-noise octave with its LOD weight applied (mean 0).
#[inline]
fn octave(seed: u64, s: u64, x: f64, y: f64, wavelength: f64, fp: f64) -> f64 {
    let w = lod(wavelength, fp);
    if w == 0.0 {
        0.0
    } else {
        w * noise::centred(seed, s, x, y, wavelength)
    }
}

/// A running-bond tile pattern: period `[px, py]`, rows offset by `offset·px`, mortar joints of
/// relative width `joint` at brightness `mortar`, per-tile jitter ±`jitter`.
#[derive(Clone, Copy, Debug)]
struct Tiles {
    period: [f64; 2],
    offset: f64,
    joint: f64,
    mortar: f64,
    jitter: f64,
}

/// The brightness factor of `pattern` at (x, y) (tiles drawn from stream `s` of `seed`), with
/// mean 1 over the area (normalised so the area mean is exactly 1), faded to 1 by LOD for a
/// footprint `fp`.
fn tiles(seed: u64, s: u64, x: f64, y: f64, pattern: &Tiles, fp: f64) -> f64 {
    let Tiles {
        period: [px, py],
        offset,
        joint,
        mortar,
        jitter,
    } = *pattern;
    let w = lod(py.min(px), fp);
    if w == 0.0 {
        return 1.0;
    }
    let row = (y / py).floor();
    let xs = x / px + offset * row;
    let col = xs.floor();
    let (fu, fv) = (xs - col, y / py - row);
    let in_joint = fu < joint || fv < joint;
    // Area fraction of tile interior: (1-joint)².
    let inner = (1.0 - joint) * (1.0 - joint);
    let mean = inner + (1.0 - inner) * mortar;
    let v = if in_joint {
        mortar
    } else {
        let r = noise::lattice(seed, s, col as i64, row as i64);
        1.0 + jitter * (2.0 * r - 1.0)
    };
    1.0 + w * (v / mean - 1.0)
}

/// Scene appearance: the surface, its look, and the seed of the procedural textures.
pub struct Shader<'a> {
    pub surface: &'a TrueSurface,
    pub look: &'a Look,
    pub seed: u64,
}

impl Shader<'_> {
    /// Whether the terrain at (x, y) is pavement (else grass / soil).
    pub fn paved(&self, x: f64, y: f64) -> bool {
        let l = self.look;
        let region = noise::value(
            self.seed,
            stream::REGION,
            x / l.coarse_wavelength,
            y / l.coarse_wavelength,
        );
        region > 0.56
    }

    /// Terrain albedo at (x, y) for a surface footprint `fp` (0 = full detail), and material.
    pub fn terrain_material(&self, x: f64, y: f64, fp: f64) -> Material {
        let (seed, l) = (self.seed, self.look);
        let tint = noise::centred(seed, stream::TINT, x, y, 0.5 * l.coarse_wavelength);
        let mid = octave(seed, stream::MID_A, x, y, l.mid_wavelength, fp)
            + 0.8 * octave(seed, stream::MID_B, x, y, 0.25 * l.mid_wavelength, fp);
        if self.paved(x, y) {
            // Pavement: warm grey, square tiles at the fine period.
            let base = DVec3::new(0.62, 0.58, 0.52) + DVec3::new(0.10, 0.06, 0.0) * tint * 2.0;
            let pattern = Tiles {
                period: [l.fine_period, l.fine_period],
                offset: 0.0,
                joint: 0.12,
                mortar: 0.45,
                jitter: 0.22,
            };
            let t = tiles(seed, stream::TILE, x, y, &pattern, fp);
            Material {
                albedo: base * (1.0 + 0.6 * mid) * t,
                ks: 0.10,
                shininess: 24.0,
            }
        } else {
            // Grass / soil: green to olive by tint, mottled, fine grain.
            let base = DVec3::new(0.26, 0.42, 0.16) + DVec3::new(0.22, 0.10, 0.02) * tint * 2.0;
            let grain = octave(seed, stream::FINE, x, y, 0.5 * l.fine_period, fp)
                + octave(seed, stream::FINE + 1, x, y, l.fine_period, fp);
            Material {
                albedo: base * (1.0 + mid) * (1.0 + 0.8 * grain),
                ks: 0.03,
                shininess: 6.0,
            }
        }
    }

    fn wall_material(&self, b: usize, s: f64, z: f64, fp: f64) -> Material {
        let (seed, l) = (self.seed, self.look);
        let base = DVec3::from_array(self.surface.buildings[b].wall_colour);
        let st = stream::BRICK + 16 * b as u64;
        let pattern = Tiles {
            period: [2.0 * l.fine_period, l.fine_period],
            offset: 0.5,
            joint: 0.10,
            mortar: 0.55,
            jitter: 0.25,
        };
        let bricks = tiles(seed, st, s, z, &pattern, fp);
        let weather = octave(
            seed,
            stream::WEATHER,
            s + 1000.0 * b as f64,
            z,
            l.mid_wavelength,
            fp,
        ) + 0.6
            * octave(seed, stream::WEATHER + 1, s, z, 0.25 * l.mid_wavelength, fp);
        // Darker towards the ground (coarse vertical gradient).
        let grime = 1.0 - 0.25 * (-(z - self.surface.buildings[b].lo[2]) / 6.0).exp();
        Material {
            albedo: base * bricks * (1.0 + 0.5 * weather) * grime,
            ks: 0.05,
            shininess: 10.0,
        }
    }

    fn roof_material(&self, b: usize, x: f64, y: f64, fp: f64) -> Material {
        let (seed, l) = (self.seed, self.look);
        let bd = &self.surface.buildings[b];
        let base = DVec3::from_array(bd.roof_colour);
        // Standing-seam panels along the longer side, period = a quarter of mid_wavelength.
        let along_x = bd.hi[0] - bd.lo[0] >= bd.hi[1] - bd.lo[1];
        let (u, v) = if along_x { (y, x) } else { (x, y) };
        let pattern = Tiles {
            period: [0.25 * l.mid_wavelength, 1e6],
            offset: 0.0,
            joint: 0.06,
            mortar: 0.6,
            jitter: 0.05,
        };
        let seams = tiles(seed, stream::ROOF + b as u64, u, v, &pattern, fp);
        let grain = octave(seed, stream::ROOF + 64, x, y, l.fine_period, fp);
        let stain = octave(seed, stream::ROOF + 65, x, y, l.mid_wavelength, fp);
        Material {
            albedo: base * seams * (1.0 + 0.4 * grain) * (1.0 + 0.5 * stain),
            ks: 0.35,
            shininess: 60.0,
        }
    }

    /// Material at a hit for surface footprint `fp`.
    pub fn material(&self, hit: &Hit, fp: f64) -> Material {
        let p = hit.pos;
        match hit.kind {
            SurfaceKind::Terrain => self.terrain_material(p.x, p.y, fp),
            SurfaceKind::Wall { building, axis } => {
                let s = if axis == 0 { p.y } else { p.x };
                self.wall_material(building as usize, s, p.z, fp)
            }
            SurfaceKind::Roof { building } => self.roof_material(building as usize, p.x, p.y, fp),
        }
    }

    /// Outgoing colour at `hit` seen along unit direction `d` (from the camera), clamped.
    pub fn shade(&self, hit: &Hit, d: DVec3, fp: f64) -> DVec3 {
        let m = self.material(hit, fp);
        let l = DVec3::from_array(self.look.sun_dir);
        let n = hit.normal;
        let ndl = n.dot(l);
        let lit = if ndl > 0.0 {
            let o = hit.pos + n * 1e-6 * (1.0 + hit.t);
            if self.surface.blocked_by_building(o, l) {
                0.0
            } else {
                1.0
            }
        } else {
            0.0
        };
        let h = (l - d).normalize();
        let spec = if lit > 0.0 {
            m.ks * n.dot(h).max(0.0).powf(m.shininess)
        } else {
            0.0
        };
        let c = m.albedo * (self.look.ambient + self.look.sun * ndl.max(0.0) * lit)
            + DVec3::splat(self.look.sun * spec);
        c.clamp(DVec3::ZERO, DVec3::ONE)
    }
}

/// Background seen by rays that miss: a sky gradient from horizon to zenith.
pub fn sky(d: DVec3) -> DVec3 {
    let s = d.z.clamp(0.0, 1.0);
    DVec3::new(0.86, 0.90, 0.95) * (1.0 - s) + DVec3::new(0.40, 0.58, 0.86) * s
}
