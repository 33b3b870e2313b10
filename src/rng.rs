//! Counter-based random numbers (SPEC §5).
//!
//! Every random number in xscale is a pure function of `(seed, purpose, a, b)`: there is no shared
//! stateful generator, so a value never depends on what was drawn before it, on thread scheduling,
//! or on whether a run was resumed. `a` and `b` are free counters (e.g. step and index, or
//! tensor id and element).
//!
//! The mixer is the SplitMix64 finaliser applied after each key word (a well-studied 64-bit
//! avalanche); the exact definition is part of the format, so a backend can reproduce draws:
//! ```text
//! h = fmix(seed ^ 0x9E3779B97F4A7C15)
//! h = fmix(h ^ purpose * 0xBF58476D1CE4E5B9)
//! h = fmix(h ^ a       * 0x94D049BB133111EB)
//! h = fmix(h ^ b       * 0xD6E8FEB86659FD93)
//! fmix(z) = z ^= z>>30; z *= 0xBF58476D1CE4E5B9; z ^= z>>27; z *= 0x94D049BB133111EB; z ^ z>>31
//! ```

/// What a random number is for. Distinct purposes never share a stream.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[repr(u64)]
pub enum Purpose {
    /// Hash-table initialisation; `a` = tensor id, `b` = element index.
    InitTable = 1,
    /// MLP weight initialisation; `a` = tensor id, `b` = element index.
    InitWeights = 2,
    /// Training batch selection; `a` = step, `b` = slot in the batch.
    Batch = 3,
    /// Synthetic scene generation; `a` = sub-purpose, `b` = index.
    Synth = 4,
    /// Ray jitter / sampling inside a pixel; `a` = pixel id, `b` = sample.
    PixelSample = 5,
    /// Acceptance batches of the mesh refinement's trust region; `a` = step, `b` = slot.
    RefineTrust = 6,
    /// Patches and neighbour views of the refinement's photo-consistency term; `a` = step,
    /// `b` = 2·slot (pixel) or 2·slot + 1 (neighbour).
    RefinePhoto = 7,
    /// `xscale case`'s batch edit; `a` = 0 (sub-sample invalidated), `b` = sub-sample index.
    Case = 8,
    /// Patch origins of a patch batch (`train/sampler.rs`); `a` = step, `b` = patch·tries + try.
    Patch = 9,
    /// Anything a test needs.
    Test = 99,
}

/// SplitMix64's finaliser (`fmix` in the module docs).
#[inline]
pub(crate) fn fmix(mut z: u64) -> u64 {
    z ^= z >> 30;
    z = z.wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z ^= z >> 27;
    z = z.wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

/// 64 random bits for `(seed, purpose, a, b)`.
#[inline]
pub fn bits(seed: u64, purpose: Purpose, a: u64, b: u64) -> u64 {
    Keyed::new(seed, purpose, a).bits(b)
}

/// The draws of one `(seed, purpose, a)`: the first three rounds of [`bits`] done once, then one
/// per `b` (a loader drawing millions of a table's initial values, `model/checkpoint.rs`).
#[derive(Clone, Copy, Debug)]
pub struct Keyed(u64);

impl Keyed {
    #[inline]
    pub fn new(seed: u64, purpose: Purpose, a: u64) -> Keyed {
        let mut h = fmix(seed ^ 0x9E37_79B9_7F4A_7C15);
        h = fmix(h ^ (purpose as u64).wrapping_mul(0xBF58_476D_1CE4_E5B9));
        Keyed(fmix(h ^ a.wrapping_mul(0x94D0_49BB_1331_11EB)))
    }

    /// `bits(seed, purpose, a, b)`.
    #[inline]
    pub fn bits(self, b: u64) -> u64 {
        fmix(self.0 ^ b.wrapping_mul(0xD6E8_FEB8_6659_FD93))
    }

    /// `uniform_f64(seed, purpose, a, b)`.
    #[inline]
    pub fn uniform_f64(self, b: u64) -> f64 {
        // Below 2^53: exact through i64, one instruction where u64 → f64 takes several.
        ((self.bits(b) >> 11) as i64) as f64 * (1.0 / (1u64 << 53) as f64)
    }
}

/// Uniform f64 in [0, 1) with 53 random bits.
#[inline]
pub fn uniform_f64(seed: u64, purpose: Purpose, a: u64, b: u64) -> f64 {
    Keyed::new(seed, purpose, a).uniform_f64(b)
}

/// Uniform f32 in [0, 1) with 24 random bits.
#[inline]
pub fn uniform_f32(seed: u64, purpose: Purpose, a: u64, b: u64) -> f32 {
    (bits(seed, purpose, a, b) >> 40) as f32 * (1.0 / (1u32 << 24) as f32)
}

/// Uniform integer in `0..n` (n > 0), by 128-bit multiply (Lemire, no modulo bias worth noting
/// for n << 2^64).
#[inline]
pub fn below(seed: u64, purpose: Purpose, a: u64, b: u64, n: u64) -> u64 {
    ((bits(seed, purpose, a, b) as u128 * n as u128) >> 64) as u64
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn pure_and_distinct() {
        assert_eq!(bits(1, Purpose::Batch, 2, 3), bits(1, Purpose::Batch, 2, 3));
        assert_ne!(bits(1, Purpose::Batch, 2, 3), bits(1, Purpose::Batch, 3, 2));
        assert_ne!(
            bits(1, Purpose::Batch, 2, 3),
            bits(1, Purpose::InitTable, 2, 3)
        );
        assert_ne!(bits(1, Purpose::Batch, 2, 3), bits(2, Purpose::Batch, 2, 3));
    }

    #[test]
    fn uniform_moments() {
        let n = 100_000u64;
        let (mut s, mut s2) = (0.0f64, 0.0f64);
        for i in 0..n {
            let x = uniform_f64(7, Purpose::Test, 0, i);
            assert!((0.0..1.0).contains(&x));
            s += x;
            s2 += x * x;
        }
        let mean = s / n as f64;
        let var = s2 / n as f64 - mean * mean;
        assert!((mean - 0.5).abs() < 0.005, "mean {mean}");
        assert!((var - 1.0 / 12.0).abs() < 0.002, "var {var}");
        let mut counts = [0u32; 10];
        for i in 0..n {
            counts[below(7, Purpose::Test, 1, i, 10) as usize] += 1;
        }
        for c in counts {
            assert!((c as i64 - 10_000).abs() < 500, "{counts:?}");
        }
    }
}
