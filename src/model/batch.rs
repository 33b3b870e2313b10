//! A training/evaluation batch (SPEC §6 "a batch"): N pixels × S sub-samples (S = γ²).
//!
//! `positions [N*S]` are normalised (f64), `valid [N*S]` is 0/1, `dirs [N]` are the pixels' unit
//! view directions (f32), `view [N]` the appearance-code row (−1: mean code), `target [N]` RGB.
//! A batch never holds a pixel without a valid sub-sample; invalid sub-samples are never
//! evaluated (their position is ignored).
//!
//! Optional (only for the vertex-feature featurization, `src/model/vertex.rs`; empty otherwise,
//! so the hash model's batch tensors are exactly SPEC §6's): `triangle [N*S]` the mesh triangle
//! each sub-sample hit and `bary [N*S]` its barycentrics `(u, v)` of vertices 1 and 2 (f64).
//! Invalid sub-samples hold `u32::MAX` and `(0, 0)`.

use anyhow::{bail, ensure, Result};

#[derive(Clone, Debug, Default, PartialEq)]
pub struct Batch {
    /// `[N*S]` normalised positions (pixel-major, then sub-sample).
    pub positions: Vec<[f64; 3]>,
    /// `[N*S]` 1 = the sub-sample's ray hit the mesh.
    pub valid: Vec<u8>,
    /// `[N]` unit view direction per pixel.
    pub dirs: Vec<[f32; 3]>,
    /// `[N]` appearance-code row, or −1 for the mean of all rows.
    pub view: Vec<i32>,
    /// `[N]` target RGB.
    pub target: Vec<[f32; 3]>,
    /// `[N]` pixel footprint on the surface, normalised units (SPEC §1.1), or empty when unknown:
    /// read only by the footprint level weighting (SPEC §4.10).
    pub footprint: Vec<f32>,
    /// `[N*S]` triangle hit by each sub-sample (optional, see the module doc).
    pub triangle: Vec<u32>,
    /// `[N*S]` barycentrics `(u, v)` of each sub-sample (optional, with `triangle`).
    pub bary: Vec<[f64; 2]>,
    /// Side k of the batch's square patches (`train/sampler.rs` patch mode; 0 = independent
    /// pixels): rows `j·k²..(j+1)·k²` are patch j, row-major (rows after the last whole block,
    /// and blocks of rows marked 0 in `patch_mask`, are in no window). Read only by the D-SSIM
    /// term (`model/ssim.rs`).
    pub patch: usize,
    /// `[N]` or empty (= all 1): 0 marks a row that fills a patch slot whose pixel does not see
    /// the mesh (the D-SSIM term leaves out every window that covers it; the L1 term counts it).
    pub patch_mask: Vec<u8>,
}

impl Batch {
    /// `n` pixels of `s` sub-samples to be filled in: positions, directions, targets and
    /// footprints zero, every sub-sample invalid, views 0; with `triangles`, triangle ids
    /// `u32::MAX` (none) and barycentrics zero.
    pub fn zeros(n: usize, s: usize, triangles: bool) -> Batch {
        let mut b = Batch {
            positions: vec![[0.0; 3]; n * s],
            valid: vec![0; n * s],
            dirs: vec![[0.0; 3]; n],
            view: vec![0; n],
            target: vec![[0.0; 3]; n],
            footprint: vec![0.0; n],
            ..Batch::default()
        };
        if triangles {
            b.triangle = vec![u32::MAX; n * s];
            b.bary = vec![[0.0; 2]; n * s];
        }
        b
    }

    pub fn n_pixels(&self) -> usize {
        self.dirs.len()
    }

    /// Sub-samples per pixel S (0 for an empty batch).
    pub fn samples_per_pixel(&self) -> usize {
        self.positions
            .len()
            .checked_div(self.dirs.len())
            .unwrap_or(0)
    }

    /// Remove the pixels none of whose sub-samples is valid (possible once the mesh refinement
    /// has moved the mesh the batch was cast against).
    pub fn drop_empty_pixels(&mut self) {
        let s = self.samples_per_pixel();
        let n = self.n_pixels();
        if s == 0 {
            return;
        }
        let keep: Vec<bool> = (0..n)
            .map(|i| self.valid[i * s..(i + 1) * s].iter().any(|&v| v != 0))
            .collect();
        if keep.iter().all(|&k| k) {
            return;
        }
        // Rows move: the patch layout no longer holds, the batch is independent pixels.
        self.patch = 0;
        self.patch_mask.clear();
        let mut w = 0;
        for (i, &k) in keep.iter().enumerate() {
            if !k {
                continue;
            }
            if w != i {
                for j in 0..s {
                    self.positions[w * s + j] = self.positions[i * s + j];
                    self.valid[w * s + j] = self.valid[i * s + j];
                    if !self.triangle.is_empty() {
                        self.triangle[w * s + j] = self.triangle[i * s + j];
                        self.bary[w * s + j] = self.bary[i * s + j];
                    }
                }
                self.dirs[w] = self.dirs[i];
                self.view[w] = self.view[i];
                self.target[w] = self.target[i];
                if !self.footprint.is_empty() {
                    self.footprint[w] = self.footprint[i];
                }
            }
            w += 1;
        }
        self.positions.truncate(w * s);
        self.valid.truncate(w * s);
        if !self.triangle.is_empty() {
            self.triangle.truncate(w * s);
            self.bary.truncate(w * s);
        }
        self.dirs.truncate(w);
        self.view.truncate(w);
        self.target.truncate(w);
        if !self.footprint.is_empty() {
            self.footprint.truncate(w);
        }
    }

    /// Shapes agree, every pixel has ≥ 1 valid sub-sample, valid flags are 0/1, positions of
    /// valid sub-samples and all directions/targets are finite, views are ≥ −1. Messages name the
    /// element.
    pub fn validate(&self) -> Result<()> {
        let n = self.dirs.len();
        ensure!(n > 0, "batch: no pixels");
        ensure!(
            self.positions.len() % n == 0 && !self.positions.is_empty(),
            "batch: {} positions is not a positive multiple of {n} pixels",
            self.positions.len()
        );
        let s = self.positions.len() / n;
        ensure!(
            self.valid.len() == n * s,
            "batch: valid has {} entries, expected N*S = {}",
            self.valid.len(),
            n * s
        );
        ensure!(
            self.view.len() == n,
            "batch: view has {} entries, expected N = {n}",
            self.view.len()
        );
        ensure!(
            self.target.len() == n,
            "batch: target has {} entries, expected N = {n}",
            self.target.len()
        );
        ensure!(
            self.footprint.is_empty() || self.footprint.len() == n,
            "batch: footprint has {} entries, expected N = {n} (or none)",
            self.footprint.len()
        );
        if let Some(i) = self
            .footprint
            .iter()
            .position(|f| !(f.is_finite() && *f >= 0.0))
        {
            bail!(
                "batch: pixel {i}: footprint {} is not a finite number ≥ 0",
                self.footprint[i]
            );
        }
        ensure!(
            self.patch_mask.is_empty() || (self.patch > 0 && self.patch_mask.len() == n),
            "batch: patch_mask has {} entries, expected N = {n} with patches (or none)",
            self.patch_mask.len()
        );
        ensure!(
            self.triangle.len() == self.bary.len(),
            "batch: triangle has {} entries but bary has {}",
            self.triangle.len(),
            self.bary.len()
        );
        ensure!(
            self.triangle.is_empty() || self.triangle.len() == n * s,
            "batch: triangle has {} entries, expected N*S = {}",
            self.triangle.len(),
            n * s
        );
        for i in 0..n {
            let mut any = false;
            for j in 0..s {
                match self.valid[i * s + j] {
                    0 => {}
                    1 => {
                        any = true;
                        let p = self.positions[i * s + j];
                        if !p.iter().all(|v| v.is_finite()) {
                            bail!("batch: pixel {i} sub-sample {j}: position {p:?} is not finite");
                        }
                        if let Some(b) = self.bary.get(i * s + j) {
                            if !b.iter().all(|v| v.is_finite()) {
                                bail!("batch: pixel {i} sub-sample {j}: barycentrics {b:?} are not finite");
                            }
                        }
                    }
                    v => {
                        bail!("batch: pixel {i} sub-sample {j}: valid flag is {v}, expected 0 or 1")
                    }
                }
            }
            ensure!(any, "batch: pixel {i} has no valid sub-sample");
            let d = self.dirs[i];
            ensure!(
                d.iter().all(|v| v.is_finite()),
                "batch: pixel {i}: direction {d:?} is not finite"
            );
            let t = self.target[i];
            ensure!(
                t.iter().all(|v| v.is_finite()),
                "batch: pixel {i}: target {t:?} is not finite"
            );
            ensure!(
                self.view[i] >= -1,
                "batch: pixel {i}: view {} is below -1",
                self.view[i]
            );
        }
        Ok(())
    }

    /// A seeded random batch for tests and benches: positions uniform in `[lo, 1-lo]^3`,
    /// sub-samples invalid with probability `p_invalid` (sub-sample 0 of a pixel is made valid
    /// if all others missed), unit directions, views uniform in `-1..n_views`, targets in [0,1).
    pub fn random(seed: u64, n: usize, s: usize, n_views: usize, p_invalid: f64) -> Batch {
        use crate::rng::{uniform_f64, Purpose::Test};
        let lo = 0.02;
        let u = |a: u64, b: usize| uniform_f64(seed, Test, a, b as u64);
        let mut b = Batch::default();
        for i in 0..n {
            let mut any = false;
            for j in 0..s {
                let k = i * s + j;
                b.positions.push([
                    lo + (1.0 - 2.0 * lo) * u(1, k),
                    lo + (1.0 - 2.0 * lo) * u(2, k),
                    lo + (1.0 - 2.0 * lo) * u(3, k),
                ]);
                let v = u(4, k) >= p_invalid;
                any |= v;
                b.valid.push(v as u8);
            }
            if !any {
                b.valid[i * s] = 1;
            }
            // Uniform direction on the sphere.
            let z = 2.0 * u(5, i) - 1.0;
            let phi = std::f64::consts::TAU * u(6, i);
            let r = (1.0 - z * z).sqrt();
            b.dirs
                .push([(r * phi.cos()) as f32, (r * phi.sin()) as f32, z as f32]);
            b.view
                .push((u(7, i) * (n_views as f64 + 1.0)).floor() as i32 - 1);
            b.target
                .push([u(8, i) as f32, u(9, i) as f32, u(10, i) as f32]);
        }
        b
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn random_batch_is_valid_and_bad_ones_are_named() {
        let b = Batch::random(1, 50, 4, 3, 0.5);
        b.validate().unwrap();
        assert!(b.valid.contains(&0));
        assert!(b.view.contains(&-1) && b.view.contains(&2));

        let mut bad = b.clone();
        for j in 0..4 {
            bad.valid[7 * 4 + j] = 0;
        }
        let e = bad.validate().unwrap_err().to_string();
        assert!(e.contains("pixel 7 has no valid"), "{e}");

        let mut bad = b.clone();
        bad.dirs[3][1] = f32::NAN;
        assert!(bad.validate().unwrap_err().to_string().contains("pixel 3"));

        let mut bad = b.clone();
        bad.valid.pop();
        assert!(bad.validate().is_err());

        let mut bad = b.clone();
        bad.valid[0] = 1;
        bad.positions[0][2] = f64::INFINITY;
        assert!(bad
            .validate()
            .unwrap_err()
            .to_string()
            .contains("sub-sample 0"));
    }

    #[test]
    fn empty_pixels_are_dropped_with_their_rows() {
        let mut b = Batch::random(3, 6, 4, 2, 0.0);
        b.triangle = (0..24).collect();
        b.bary = vec![[0.25, 0.5]; 24];
        b.footprint = (0..6).map(|i| i as f32).collect();
        let orig = b.clone();
        for j in 0..4 {
            b.valid[4 + j] = 0; // pixel 1
            b.valid[16 + j] = 0; // pixel 4
        }
        b.drop_empty_pixels();
        b.validate().unwrap();
        assert_eq!(b.n_pixels(), 4);
        let kept = [0usize, 2, 3, 5];
        for (w, &i) in kept.iter().enumerate() {
            assert_eq!(b.dirs[w], orig.dirs[i]);
            assert_eq!(b.target[w], orig.target[i]);
            assert_eq!(b.view[w], orig.view[i]);
            assert_eq!(b.footprint[w], orig.footprint[i]);
            assert_eq!(
                b.positions[w * 4..w * 4 + 4],
                orig.positions[i * 4..i * 4 + 4]
            );
            assert_eq!(
                b.triangle[w * 4..w * 4 + 4],
                orig.triangle[i * 4..i * 4 + 4]
            );
        }
        let before = b.clone();
        b.drop_empty_pixels();
        assert_eq!(b, before, "nothing to drop: unchanged");
    }
}
