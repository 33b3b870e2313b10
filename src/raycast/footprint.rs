//! Per-view statistics of pixel footprints (SPEC §1.1, §8): a log-scale histogram of the kept
//! pixels' footprints, from which the level range of the hash grid is chosen.
//!
//! Bins are 1/[`BINS_PER_OCTAVE`] of an octave wide over `[2^MIN_LOG2, 2^MAX_LOG2)` normalised
//! units (values outside land in the end bins). Counting is exact and order-free, so the histogram
//! of a view is the same however its strips are split among threads, and the same whether the
//! ray stream or the sample cache built it. A percentile is the lower edge of the bin where the
//! cumulative count first reaches it: quantised to 1/32 octave (2.2 %), and never above the true
//! percentile by more than one bin.

/// Bins per octave.
pub const BINS_PER_OCTAVE: usize = 32;
/// log2 of the lower edge of the first bin (2⁻⁴⁰ ≈ 1e-12 of the scene: far below any f32 hit).
pub const MIN_LOG2: i32 = -40;
/// log2 of the upper edge of the last bin.
pub const MAX_LOG2: i32 = 2;
const NBINS: usize = (MAX_LOG2 - MIN_LOG2) as usize * BINS_PER_OCTAVE;

/// A log-scale histogram of footprints (module docs).
#[derive(Clone, Debug, PartialEq)]
pub struct FootprintHist {
    counts: Vec<u32>,
}

impl Default for FootprintHist {
    fn default() -> Self {
        FootprintHist {
            counts: vec![0; NBINS],
        }
    }
}

fn bin(fp: f64) -> usize {
    if fp.is_nan() || fp <= 0.0 {
        return 0;
    }
    let x = (fp.log2() - MIN_LOG2 as f64) * BINS_PER_OCTAVE as f64;
    (x.max(0.0) as usize).min(NBINS - 1)
}

impl FootprintHist {
    /// Count one footprint (normalised units; zero, negative and NaN go to the first bin).
    #[inline]
    pub fn add(&mut self, fp: f64) {
        self.counts[bin(fp)] += 1;
    }

    /// Add another histogram's counts.
    pub fn merge(&mut self, o: &FootprintHist) {
        for (a, b) in self.counts.iter_mut().zip(&o.counts) {
            *a += b;
        }
    }

    /// Number of footprints counted.
    pub fn len(&self) -> u64 {
        self.counts.iter().map(|&c| c as u64).sum()
    }
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// The `p`-quantile (0 ≤ p ≤ 1): the lower edge of the bin where the cumulative count first
    /// reaches `ceil(p · n)` (at least 1); `None` when empty.
    pub fn quantile(&self, p: f64) -> Option<f64> {
        let n = self.len();
        if n == 0 {
            return None;
        }
        let want = ((p.clamp(0.0, 1.0) * n as f64).ceil() as u64).max(1);
        let mut acc = 0u64;
        for (i, &c) in self.counts.iter().enumerate() {
            acc += c as u64;
            if acc >= want {
                return Some((MIN_LOG2 as f64 + i as f64 / BINS_PER_OCTAVE as f64).exp2());
            }
        }
        unreachable!("the cumulative count reaches n")
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn quantiles_within_one_bin() {
        let mut h = FootprintHist::default();
        // 1000 footprints spread log-uniformly over [1e-5, 1e-2].
        let v: Vec<f64> = (0..1000)
            .map(|i| 10f64.powf(-5.0 + 3.0 * (i as f64 + 0.5) / 1000.0))
            .collect();
        for &x in &v {
            h.add(x);
        }
        assert_eq!(h.len(), 1000);
        for p in [0.0, 0.1, 0.5, 0.9, 1.0] {
            let q = h.quantile(p).unwrap();
            let exact = v[((p * 1000.0).ceil() as usize).max(1) - 1];
            let bin = (1.0f64 / BINS_PER_OCTAVE as f64).exp2();
            assert!(
                q <= exact && q * bin > exact * 0.999_999,
                "p {p}: {q} vs {exact}"
            );
        }
        let mut a = FootprintHist::default();
        let mut b = FootprintHist::default();
        for (i, &x) in v.iter().enumerate() {
            if i % 3 == 0 {
                a.add(x)
            } else {
                b.add(x)
            }
        }
        a.merge(&b);
        assert_eq!(a, h, "merging is order-free");
        assert_eq!(FootprintHist::default().quantile(0.5), None);
    }
}
