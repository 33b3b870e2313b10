//! Deterministic 2-D value noise for the synthetic scenes (terrain heights, albedo octaves,
//! proxy displacement). Every lattice value is `rng::uniform_f64(seed, Purpose::Synth, stream,
//! key(ix, iy))`, a pure function of its inputs (SPEC §5): no tables, no state, any evaluation
//! order gives the same bits.
//!
//! Interpolation is bilinear in the quintic fade `6t⁵ − 15t⁴ + 10t³` (C² across cells), so the
//! noise has energy around its wavelength and little above it. Its expectation is exactly 0.5
//! (lattice values are U[0,1) and the interpolation weights sum to 1): the albedo uses that as
//! the value an octave fades to when it is finer than the pixel footprint (see `shade.rs`).

use crate::rng::{self, Purpose};

/// Sub-purposes (`a` of `Purpose::Synth`). Distinct streams never share lattice values.
pub mod stream {
    pub const TERRAIN: u64 = 0x100; // + octave
    pub const BUILDINGS: u64 = 0x200;
    pub const CAMERAS: u64 = 0x300;
    pub const PROXY: u64 = 0x400; // + component
    pub const REGION: u64 = 0x500;
    pub const TINT: u64 = 0x510;
    pub const MID_A: u64 = 0x520;
    pub const MID_B: u64 = 0x530;
    pub const FINE: u64 = 0x540;
    pub const TILE: u64 = 0x550;
    pub const BRICK: u64 = 0x560;
    pub const WEATHER: u64 = 0x570;
    pub const ROOF: u64 = 0x580;
}

/// Pack a lattice point into the `b` counter (low 32 bits of each coordinate; the scenes use
/// |ix|, |iy| < 2^31).
#[inline]
fn key(ix: i64, iy: i64) -> u64 {
    ((ix as u64) << 32) ^ (iy as u32 as u64)
}

/// Lattice value in [0, 1).
#[inline]
pub fn lattice(seed: u64, stream: u64, ix: i64, iy: i64) -> f64 {
    rng::uniform_f64(seed, Purpose::Synth, stream, key(ix, iy))
}

#[inline]
fn fade(t: f64) -> f64 {
    t * t * t * (t * (t * 6.0 - 15.0) + 10.0)
}

/// Value noise in [0, 1) with unit lattice spacing at (x, y); mean 0.5.
pub fn value(seed: u64, stream: u64, x: f64, y: f64) -> f64 {
    let (fx, fy) = (x.floor(), y.floor());
    let (ix, iy) = (fx as i64, fy as i64);
    let (tx, ty) = (fade(x - fx), fade(y - fy));
    let v00 = lattice(seed, stream, ix, iy);
    let v10 = lattice(seed, stream, ix + 1, iy);
    let v01 = lattice(seed, stream, ix, iy + 1);
    let v11 = lattice(seed, stream, ix + 1, iy + 1);
    let a = v00 + (v10 - v00) * tx;
    let b = v01 + (v11 - v01) * tx;
    a + (b - a) * ty
}

/// Value noise with the given wavelength (lattice spacing, metres), centred: in [-0.5, 0.5),
/// mean 0.
#[inline]
pub fn centred(seed: u64, stream: u64, x: f64, y: f64, wavelength: f64) -> f64 {
    value(seed, stream, x / wavelength, y / wavelength) - 0.5
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn continuous_and_in_range() {
        for i in 0..2000 {
            let x = -7.3 + i as f64 * 0.0137;
            let y = 3.1 - i as f64 * 0.0071;
            let v = value(5, stream::TINT, x, y);
            assert!((0.0..1.0).contains(&v));
            let w = value(5, stream::TINT, x + 1e-9, y);
            assert!((v - w).abs() < 1e-7, "discontinuity at {x} {y}");
        }
        // Lattice points reproduce the lattice values.
        assert_eq!(value(5, 1, 3.0, -2.0), lattice(5, 1, 3, -2));
    }
}
