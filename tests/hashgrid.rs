//! Hash grid (SPEC §4.2): geometry, hand-computed corners, agreement with plain scalar
//! references, finite-difference gradient checks, determinism across thread counts, and the
//! touched-entry set.

use xscale::model::config::{GridConfig, Interpolation, PositionMode};
use xscale::model::hashgrid::{HashGrid, Touched, BWD_TABLE_CHUNK, CHUNK_POINTS};
use xscale::model::ModelConfig;
use xscale::rng::{uniform_f64, Purpose};

fn cfg(levels: u32, features: u32, t: u32, n0: f32, b: f64, interp: Interpolation) -> GridConfig {
    GridConfig {
        levels,
        features,
        log2_table_size: t,
        base_resolution: n0,
        per_level_scale: b,
        interpolation: interp,
        finest_resolution: None,
        log2_table_sizes: None,
    }
}

/// Uniform points in [lo, hi)^3 from the test stream `a`.
fn points(n: usize, a: u64, lo: f64, hi: f64) -> Vec<[f64; 3]> {
    (0..n)
        .map(|i| {
            let u = |d: u64| lo + (hi - lo) * uniform_f64(7, Purpose::Test, a, 3 * i as u64 + d);
            [u(0), u(1), u(2)]
        })
        .collect()
}

fn values(n: usize, a: u64, amp: f64) -> Vec<f64> {
    (0..n)
        .map(|i| amp * (2.0 * uniform_f64(9, Purpose::Test, a, i as u64) - 1.0))
        .collect()
}

// ------------------------------------------------------------------------------------------
// Geometry
// ------------------------------------------------------------------------------------------

#[test]
fn cpu_preset_geometry() {
    let g = HashGrid::new(&ModelConfig::cpu().grid_h);
    // b = 128^(1/15) = 2^(7/15); scale_l = 16 * 2^(7l/15) - 1:
    //   l=0: 15      → res 16, 16^3 = 4096                       → 4096 entries, dense
    //   l=1: 21.11   → res 23, 12167 → next multiple of 8 12168  → dense
    //   l=2: 29.55   → res 31, 29791 → 29792                     → dense
    //   l=3: 41.22   → res 43, 79507 → 79512                     → dense
    //   l=4: 57.35   → res 59, 205379 → 205384                   → dense
    //   l=5: 79.63   → res 81, 531441 > 2^19                     → hashed, 2^19 entries
    // levels 5..15 are hashed: 11 * 524288. Parameters = 2 * total entries.
    assert_eq!(&g.resolutions[..6], &[16, 23, 31, 43, 59, 81]);
    assert_eq!(g.dense, [[true; 5].as_slice(), &[false; 11]].concat());
    let dense_entries = 4096 + 12168 + 29792 + 79512 + 205384;
    assert_eq!(g.n_entries(), dense_entries + 11 * 524288);
    assert_eq!(g.n_params(), 12_196_240);
    assert_eq!(g.offsets.len(), 17);
    assert_eq!(g.offsets[5], dense_entries as u32);
    // log2(b) in f32 as tcnn's host code, then exp2f(l*log2b)*N0 - 1 in f32.
    let log2b = (ModelConfig::cpu().grid_h.per_level_scale as f32).log2();
    for l in 0..16 {
        assert_eq!(g.scales[l], (l as f32 * log2b).exp2() * 16.0 - 1.0);
    }
    // The finest level lands on 2047 (to within the f32 rounding of log2b).
    assert!((g.scales[15] - 2047.0).abs() < 2e-3, "{}", g.scales[15]);
    // A loader rebuilds the same grid from the saved scale table.
    let back = HashGrid::with_scales(&g.cfg, g.scales.clone()).unwrap();
    assert_eq!(back, g);
    assert_eq!(g.out_dim(), 32);
}

/// `HashGrid::corners` is the documented scalar reference: an fma chain over its corners in
/// corner order reproduces `forward` bit for bit, for dense and hashed levels, both position
/// modes, both interpolations and both precisions.
#[test]
fn corners_is_the_scalar_reference_of_the_passes() {
    fn check<R: xscale::model::real::Real + PartialEq + std::fmt::Debug>(
        g: &HashGrid,
        table: &[R],
        pts: &[[f64; 3]],
        mode: PositionMode,
    ) -> usize {
        let f = g.cfg.features as usize;
        let lf = g.out_dim();
        let mut out = vec![R::ZERO; pts.len() * lf];
        g.forward(table, pts, mode, &mut out);
        let mut bad = 0;
        for (i, x) in pts.iter().enumerate() {
            for l in 0..g.cfg.levels as usize {
                let (idx, w) = g.corners::<R>(l, x, mode);
                for c in 0..f {
                    let mut acc = R::ZERO;
                    for k in 0..8 {
                        acc = w[k].mul_add(table[idx[k] as usize * f + c], acc);
                    }
                    if acc != out[i * lf + l * f + c] {
                        bad += 1;
                    }
                }
            }
        }
        bad
    }
    let mut failures = Vec::new();
    for interp in [Interpolation::Linear, Interpolation::Smoothstep] {
        // Levels 0-2 dense, 3-4 hashed (2^10 entries).
        let g = HashGrid::new(&cfg(5, 2, 10, 4.0, 2.0, interp));
        assert!(g.dense.contains(&true) && g.dense.contains(&false));
        let t64 = values(g.n_params(), 3, 1.0);
        let t32: Vec<f32> = t64.iter().map(|&v| v as f32).collect();
        let pts = points(300, 11, -0.2, 1.2);
        for mode in [PositionMode::F64, PositionMode::Tcnn] {
            let b64 = check::<f64>(&g, &t64, &pts, mode);
            let b32 = check::<f32>(&g, &t32, &pts, mode);
            if b64 + b32 > 0 {
                failures.push(format!(
                    "{interp:?} {mode:?}: f64 {b64}, f32 {b32} outputs differ"
                ));
            }
        }
    }
    assert!(failures.is_empty(), "{failures:#?}");
}

#[test]
fn tiny_preset_geometry() {
    // N0 = 4, b = 2: scales 3, 7, 15, 31 exactly; res 4, 8, 16, 32; sizes 64, 512, 4096 (dense),
    // 32^3 = 32768 > 2^12 → hashed with 4096 entries.
    let g = HashGrid::new(&ModelConfig::tiny().grid_h);
    assert_eq!(g.scales, vec![3.0, 7.0, 15.0, 31.0]);
    assert_eq!(g.resolutions, vec![4, 8, 16, 32]);
    assert_eq!(g.offsets, vec![0, 64, 576, 4672, 8768]);
    assert_eq!(g.dense, vec![true, true, true, false]);
    assert_eq!(g.n_params(), 8768 * 2);
}

/// Scales up to 1e9 are valid, but res³ overflows u64 from res ≈ 2^21.3: the wrapped cube made
/// the level of scale 2^22 − 1 (res 2^22, res³ = 2^66 ≡ 0) zero entries long, so queries indexed
/// outside it (found by `cargo fuzz run checkpoint`, a panic with overflow checks). Every huge
/// level is a full hashed table.
#[test]
fn huge_resolutions_do_not_overflow_level_sizes() {
    let t = 12;
    let c = cfg(1, 2, t, 16.0, 2.0, Interpolation::Linear);
    for s in [2_642_245.0f32, 4_194_303.0, 8_388_607.0, 1.0e8, 1.0e9] {
        let g = HashGrid::with_scales(&c, vec![s]).unwrap();
        assert_eq!(g.offsets, vec![0, 1 << t], "scale {s}");
        assert_eq!(g.dense, vec![false], "scale {s}");
        // A query reads inside the table (the table holds 1.0 everywhere: the output is the sum
        // of the corner weights, 1).
        let mut out = [0.0f64; 2];
        g.forward(
            &vec![1.0f64; (1 << t) * 2],
            &[[0.25, 0.5, 0.75]],
            PositionMode::F64,
            &mut out,
        );
        assert!(
            out.iter().all(|v| (v - 1.0).abs() < 1e-9),
            "scale {s}: {out:?}"
        );
    }
}

#[test]
fn init_table_range_and_determinism() {
    let g = HashGrid::new(&ModelConfig::tiny().grid_h);
    let a = g.init_table(5, 1);
    assert_eq!(a.len(), g.n_params());
    assert!(a.iter().all(|&v| (-1e-4..1e-4).contains(&v)));
    let mean = a.iter().map(|&v| v as f64).sum::<f64>() / a.len() as f64;
    assert!(mean.abs() < 3e-6, "mean {mean}");
    assert_eq!(a, g.init_table(5, 1));
    assert_ne!(a, g.init_table(5, 2));
    assert_ne!(a, g.init_table(6, 1));
}

// ------------------------------------------------------------------------------------------
// Hand-computed corners
// ------------------------------------------------------------------------------------------

fn assert_weights(got: [f64; 8], want: [f64; 8], what: &str) {
    for k in 0..8 {
        assert!(
            (got[k] - want[k]).abs() < 1e-12,
            "{what}: corner {k}: {} vs {}",
            got[k],
            want[k]
        );
    }
}

#[test]
fn hand_computed_dense_corners() {
    let g = HashGrid::new(&ModelConfig::tiny().grid_h);
    // Level 0: scale 3, res 4, 64 entries. x = (0.1, 0.2, 0.3):
    // p = 3x + 0.5 = (0.8, 1.1, 1.4) → c = (0, 1, 1), t = (0.8, 0.1, 0.4).
    // index = cx + 4 cy + 16 cz: k=0 (0,1,1) → 20, k=1 (1,1,1) → 21, k=2 (0,2,1) → 24,
    // k=3 → 25, k=4 (0,1,2) → 36, k=5 → 37, k=6 (0,2,2) → 40, k=7 → 41.
    // weights (1-t or t per axis): k=0 .2*.9*.6 = .108, k=1 .8*.9*.6 = .432, k=2 .2*.1*.6 = .012,
    // k=3 .8*.1*.6 = .048, k=4 .2*.9*.4 = .072, k=5 .8*.9*.4 = .288, k=6 .2*.1*.4 = .008,
    // k=7 .8*.1*.4 = .032.
    let (idx, w) = g.corners::<f64>(0, &[0.1, 0.2, 0.3], PositionMode::F64);
    assert_eq!(idx, [20, 21, 24, 25, 36, 37, 40, 41]);
    assert_weights(
        w,
        [0.108, 0.432, 0.012, 0.048, 0.072, 0.288, 0.008, 0.032],
        "dense l0",
    );

    // Level 1: scale 7, res 8, offset 64. x = (0.25, 0.5, 0.75):
    // p = (2.25, 4.0, 5.75) → c = (2, 4, 5), t = (0.25, 0, 0.75).
    // index = 64 + cx + 8 cy + 64 cz: (2,4,5) → 64+2+32+320 = 418; x+1 → 419; y+1 → 426, 427;
    // z+1 → 482, 483, 490, 491. t_y = 0 exactly: the y+1 corners have weight 0.
    let (idx, w) = g.corners::<f64>(1, &[0.25, 0.5, 0.75], PositionMode::F64);
    assert_eq!(idx, [418, 419, 426, 427, 482, 483, 490, 491]);
    let (a, b) = (0.75 * 0.25, 0.25 * 0.25); // (1-tx)(1-tz), tx(1-tz)
    let (c, d) = (0.75 * 0.75, 0.25 * 0.75); // (1-tx)tz, tx tz
    assert_weights(w, [a, b, 0.0, 0.0, c, d, 0.0, 0.0], "dense l1");
}

#[test]
fn hand_computed_hashed_corners() {
    let g = HashGrid::new(&ModelConfig::tiny().grid_h);
    // Level 3: scale 31, hashed, 4096 entries, offset 4672. x = (0.1, 0.2, 0.3):
    // p = 31x + 0.5 = (3.6, 6.7, 9.8) → c = (3, 6, 9), t = (0.6, 0.7, 0.8) (up to f64 rounding).
    // hash = cx*1 ^ cy*2654435761 ^ cz*805459861 (mod 2^32), then mod 4096:
    //   6*2654435761 = 15926614566 ≡ 3041712678,  7*2654435761 = 18581050327 ≡ 1401181143,
    //   9*805459861  =  7249138749 ≡ 2954171453, 10*805459861  =  8054598610 ≡ 3759631314.
    let ys = [3041712678u32, 1401181143];
    let zs = [2954171453u32, 3759631314];
    let mut want = [0u32; 8];
    for (k, w) in want.iter_mut().enumerate() {
        let x = 3 + (k as u32 & 1);
        *w = 4672 + (x ^ ys[(k >> 1) & 1] ^ zs[k >> 2]) % 4096;
    }
    // Worked out: k=0: 3 ^ 2598 ^ 1085 (the low 12 bits) = 3608.
    assert_eq!(want[0], 4672 + 3608);
    assert_eq!(want, [8280, 8287, 6697, 6702, 5175, 5168, 6726, 6721]);
    let (idx, w) = g.corners::<f64>(3, &[0.1, 0.2, 0.3], PositionMode::F64);
    assert_eq!(idx, want);
    let (tx, ty, tz) = (0.6, 0.7, 0.8);
    let mut ww = [0.0; 8];
    for (k, v) in ww.iter_mut().enumerate() {
        let f = |bit: usize, t: f64| if k >> bit & 1 == 1 { t } else { 1.0 - t };
        *v = f(0, tx) * f(1, ty) * f(2, tz);
    }
    // e.g. k=0: 0.4*0.3*0.2 = 0.024, k=7: 0.6*0.7*0.8 = 0.336.
    assert!((ww[0] - 0.024).abs() < 1e-15 && (ww[7] - 0.336).abs() < 1e-15);
    for k in 0..8 {
        assert!(
            (w[k] - ww[k]).abs() < 1e-9,
            "hashed corner {k}: {} vs {}",
            w[k],
            ww[k]
        );
    }
}

#[test]
fn upper_face_wraps_like_tcnn() {
    let g = HashGrid::new(&ModelConfig::tiny().grid_h);
    // Level 0 (scale 3, res 4, 64 entries). x = (1, 1, 1): p = 3.5 → c = (3,3,3), t = 0.5.
    // No clamping: the +1 corner has coordinate 4 = res, and index = cx + 4cy + 16cz mod 64:
    //   k=0 (3,3,3) → 63, k=1 (4,3,3) → 64 ≡ 0, k=2 (3,4,3) → 67 ≡ 3, k=3 (4,4,3) → 68 ≡ 4,
    //   k=4 (3,3,4) → 79 ≡ 15, k=5 (4,3,4) → 80 ≡ 16, k=6 (3,4,4) → 83 ≡ 19, k=7 → 84 ≡ 20.
    let want = [63, 0, 3, 4, 15, 16, 19, 20];
    for mode in [PositionMode::F64, PositionMode::Tcnn] {
        let (idx, w) = g.corners::<f64>(0, &[1.0, 1.0, 1.0], mode);
        assert_eq!(idx, want, "{mode:?}");
        assert_weights(w, [0.125; 8], "x = 1");
        // Just below the face: same cell, t just below 0.5 (x = 1 - 1e-7 is also distinct in f32).
        let (idx, _) = g.corners::<f64>(0, &[1.0 - 1e-7; 3], mode);
        assert_eq!(idx, want, "{mode:?} just below 1");
    }
    // x = (1, 0.1, 0.1): p = (3.5, 0.8, 0.8), c = (3, 0, 0): the x+1 corner (4,0,0) has index 4,
    // i.e. it wraps into the next row (grid vertex (0,1,0)).
    let (idx, _) = g.corners::<f64>(0, &[1.0, 0.1, 0.1], PositionMode::F64);
    assert_eq!(idx[0], 3);
    assert_eq!(idx[1], 4);
    // cpu preset level 0: scale 15, res 16, 4096 entries = 16^3 exactly; x = (1,1,1): p = 15.5,
    // corner 7 = (16,16,16) → 16 + 16*16 + 16*256 = 4368 ≡ 272 (mod 4096).
    let gc = HashGrid::new(&ModelConfig::cpu().grid_h);
    let (idx, _) = gc.corners::<f64>(0, &[1.0, 1.0, 1.0], PositionMode::F64);
    assert_eq!(idx[7], 272);
    assert_eq!(idx[0], 15 + 15 * 16 + 15 * 256);
    // Forward reads exactly those entries: a table that is 1 at entry 20 only gives 0.125.
    let mut table = vec![0.0f64; g.n_params()];
    table[20 * 2] = 1.0;
    let mut out = vec![0.0; 8];
    g.forward(&table, &[[1.0, 1.0, 1.0]], PositionMode::F64, &mut out);
    assert_eq!(out[0], 0.125);
}

// ------------------------------------------------------------------------------------------
// Plain scalar references
// ------------------------------------------------------------------------------------------

/// The SPEC §4.2 formula, written plainly in f64 (positions in f64, as PositionMode::F64).
fn reference_f64(grid: &HashGrid, table: &[f64], x: &[f64; 3]) -> Vec<f64> {
    let c = &grid.cfg;
    let nf = c.features as usize;
    let log2b = (c.per_level_scale as f32).log2();
    let mut out = vec![0.0; grid.out_dim()];
    for l in 0..c.levels as usize {
        let scale = (l as f32 * log2b).exp2() * c.base_resolution - 1.0;
        assert_eq!(scale, grid.scales[l]);
        let res = scale.ceil() as u32 + 1;
        let cube = (res as u64).pow(3);
        let size = (cube.min(2147483647).div_ceil(8) * 8).min(1 << c.log2_table_size) as u32;
        let dense = res <= 1625 && cube <= size as u64;
        let mut cell = [0u32; 3];
        let mut w = [0.0f64; 3];
        for d in 0..3 {
            let p = (scale as f64).mul_add(x[d], 0.5);
            cell[d] = p.floor() as i32 as u32;
            let t = p - p.floor();
            w[d] = match c.interpolation {
                Interpolation::Linear => t,
                Interpolation::Smoothstep => t * t * (3.0 - 2.0 * t),
            };
        }
        let mut acc = vec![0.0f64; nf];
        for k in 0..8 {
            let mut weight = 1.0;
            let mut v = [0u32; 3];
            for d in 0..3 {
                if k >> d & 1 == 1 {
                    weight *= w[d];
                    v[d] = cell[d].wrapping_add(1);
                } else {
                    weight *= 1.0 - w[d];
                    v[d] = cell[d];
                }
            }
            let index = if dense {
                v[0].wrapping_add(v[1].wrapping_mul(res))
                    .wrapping_add(v[2].wrapping_mul(res * res))
            } else {
                v[0] ^ v[1].wrapping_mul(2654435761) ^ v[2].wrapping_mul(805459861)
            } % size;
            let e = grid.offsets[l] as usize + index as usize;
            for f in 0..nf {
                acc[f] = f64::mul_add(weight, table[e * nf + f], acc[f]);
            }
        }
        out[l * nf..(l + 1) * nf].copy_from_slice(&acc);
    }
    out
}

/// The same in f32 with positions rounded to f32, as tiny-cuda-nn's fp32 build.
fn reference_tcnn_f32(grid: &HashGrid, table: &[f32], x: &[f64; 3]) -> Vec<f32> {
    let c = &grid.cfg;
    let nf = c.features as usize;
    let mut out = vec![0.0f32; grid.out_dim()];
    for l in 0..c.levels as usize {
        let scale = grid.scales[l];
        let res = grid.resolutions[l];
        let size = grid.offsets[l + 1] - grid.offsets[l];
        let mut cell = [0u32; 3];
        let mut w = [0.0f32; 3];
        for d in 0..3 {
            let p = f32::mul_add(scale, x[d] as f32, 0.5);
            let fl = p.floor();
            cell[d] = fl as i32 as u32;
            let t = p - fl;
            w[d] = match c.interpolation {
                Interpolation::Linear => t,
                Interpolation::Smoothstep => t * t * (3.0 - 2.0 * t),
            };
        }
        let mut acc = vec![0.0f32; nf];
        for k in 0..8 {
            let mut weight = 1.0f32;
            let mut v = [0u32; 3];
            for d in 0..3 {
                if k >> d & 1 == 1 {
                    weight *= w[d];
                    v[d] = cell[d] + 1;
                } else {
                    weight *= 1.0 - w[d];
                    v[d] = cell[d];
                }
            }
            let index = if grid.dense[l] {
                v[0] + v[1] * res + v[2] * res * res
            } else {
                v[0] ^ v[1].wrapping_mul(2654435761) ^ v[2].wrapping_mul(805459861)
            } % size;
            let e = grid.offsets[l] as usize + index as usize;
            for f in 0..nf {
                acc[f] = f32::mul_add(weight, table[e * nf + f], acc[f]);
            }
        }
        out[l * nf..(l + 1) * nf].copy_from_slice(&acc);
    }
    out
}

/// Configurations covering dense and hashed levels, F = 1, 2, 4, 8, both interpolations.
fn test_configs() -> Vec<GridConfig> {
    vec![
        ModelConfig::tiny().grid_h,
        cfg(8, 2, 12, 4.0, 1.5, Interpolation::Smoothstep),
        cfg(6, 1, 10, 3.0, 1.7, Interpolation::Linear),
        cfg(5, 4, 13, 16.0, 1.3819, Interpolation::Smoothstep),
        cfg(4, 8, 9, 2.0, 2.5, Interpolation::Linear),
    ]
}

#[test]
fn forward_matches_scalar_reference_f64_bitwise() {
    for (ci, c) in test_configs().into_iter().enumerate() {
        let g = HashGrid::new(&c);
        assert!(
            g.dense.iter().any(|&d| d) && g.dense.iter().any(|&d| !d),
            "config {ci}"
        );
        let table = values(g.n_params(), 100 + ci as u64, 1.0);
        // Include points outside [0,1] and on the faces: the index arithmetic wraps there too.
        let mut pts = points(CHUNK_POINTS + 37, ci as u64, -0.05, 1.05);
        pts.extend([[0.0; 3], [1.0; 3], [1.0, 0.0, 0.5]]);
        let mut out = vec![0.0; pts.len() * g.out_dim()];
        g.forward(&table, &pts, PositionMode::F64, &mut out);
        for (i, x) in pts.iter().enumerate() {
            let r = reference_f64(&g, &table, x);
            let o = &out[i * g.out_dim()..(i + 1) * g.out_dim()];
            assert_eq!(o, &r[..], "config {ci} point {i} {x:?}");
        }
    }
}

/// Points as a render casts them: clusters of four (a pixel's γ² sub-samples) a hair apart, a
/// cluster next to the one before it, so consecutive points share a cell at the coarse levels
/// and part them at the fine ones; the count leaves a ragged last block (not a multiple of 4).
fn clustered_points(n: usize, a: u64) -> Vec<[f64; 3]> {
    let base = points(n.div_ceil(4), a, 0.0, 1.0);
    (0..n)
        .map(|i| {
            let c = base[i / 4];
            let s = (i / 4) as f64 * 1e-3;
            let o = (i % 4) as f64 * 2e-4;
            [(0.3 + s + o) % 1.0, c[1] * 1e-2 + 0.5 + o, (c[2] + s) % 1.0]
        })
        .collect()
}

/// Levels evaluated per point for `forward_active`: runs (a pixel's sub-samples share a count)
/// from 0 to every level.
fn active_counts(n: usize, levels: u32) -> Vec<u8> {
    (0..n)
        .map(|i| ((i / 4 * 5 + i / 64) % (levels as usize + 1)) as u8)
        .collect()
}

/// `forward_active` (rendering and training's path: a point skips the levels past its count,
/// consecutive points in one cell share their corner rows, f32 with F = 2 takes the AVX2 pass
/// where the CPU has it) is the scalar reference on the levels a point evaluates and +0 on the
/// others, bit for bit, for F = 1, 2, 4 in f32 and f64.
#[test]
fn forward_active_is_the_scalar_reference() {
    fn check<R: xscale::model::real::Real + PartialEq + std::fmt::Debug>(
        g: &HashGrid,
        table: &[R],
        pts: &[[f64; 3]],
        active: &[u8],
        mode: PositionMode,
    ) -> (usize, usize) {
        let f = g.cfg.features as usize;
        let lf = g.out_dim();
        let mut out = vec![R::from_f64(7.0); pts.len() * lf];
        g.forward_active(table, pts, mode, &mut out, active);
        let (mut bad, mut shared) = (0, 0);
        for (i, x) in pts.iter().enumerate() {
            for l in 0..g.cfg.levels as usize {
                let (idx, w) = g.corners::<R>(l, x, mode);
                if i > 0 && g.corners::<R>(l, &pts[i - 1], mode).0 == idx {
                    shared += 1;
                }
                for c in 0..f {
                    let mut acc = R::ZERO;
                    if l < active[i] as usize {
                        for k in 0..8 {
                            acc = w[k].mul_add(table[idx[k] as usize * f + c], acc);
                        }
                    }
                    if acc.to_f64().to_bits() != out[i * lf + l * f + c].to_f64().to_bits() {
                        bad += 1;
                    }
                }
            }
        }
        (bad, shared)
    }
    let mut failures = Vec::new();
    for features in [1, 2, 4] {
        // Level 0 dense, 1-7 hashed; cells from 1/15 to 1/2047.
        let g = HashGrid::new(&cfg(8, features, 12, 16.0, 2.0, Interpolation::Linear));
        assert!(g.dense[0] && !g.dense[1]);
        let t64 = values(g.n_params(), 40 + features as u64, 1.0);
        let t32: Vec<f32> = t64.iter().map(|&v| v as f32).collect();
        let pts = clustered_points(CHUNK_POINTS + 70 + 3, features as u64);
        let active = active_counts(pts.len(), g.cfg.levels);
        for mode in [PositionMode::F64, PositionMode::Tcnn] {
            let (b32, shared) = check::<f32>(&g, &t32, &pts, &active, mode);
            let (b64, _) = check::<f64>(&g, &t64, &pts, &active, mode);
            assert!(
                shared > pts.len() && shared < pts.len() * (g.cfg.levels as usize - 1),
                "the points share cells at some levels only ({shared})"
            );
            if b32 + b64 > 0 {
                failures.push(format!(
                    "F = {features} {mode:?}: f32 {b32}, f64 {b64} differ"
                ));
            }
        }
    }
    assert!(failures.is_empty(), "{failures:#?}");
}

#[test]
fn tcnn_mode_f32_matches_scalar_fp32_bitwise() {
    for (ci, c) in test_configs().into_iter().enumerate() {
        let g = HashGrid::new(&c);
        let table: Vec<f32> = values(g.n_params(), 200 + ci as u64, 1.0)
            .iter()
            .map(|&v| v as f32)
            .collect();
        let mut pts = points(CHUNK_POINTS + 11, 50 + ci as u64, 0.0, 1.0);
        pts.extend([[0.0; 3], [1.0; 3], [0.999_999_99, 0.5, 1e-9]]);
        let mut out = vec![0.0f32; pts.len() * g.out_dim()];
        g.forward(&table, &pts, PositionMode::Tcnn, &mut out);
        for (i, x) in pts.iter().enumerate() {
            let r = reference_tcnn_f32(&g, &table, x);
            let o = &out[i * g.out_dim()..(i + 1) * g.out_dim()];
            let ob: Vec<u32> = o.iter().map(|v| v.to_bits()).collect();
            let rb: Vec<u32> = r.iter().map(|v| v.to_bits()).collect();
            assert_eq!(ob, rb, "config {ci} point {i} {x:?}");
        }
    }
}

#[test]
fn f32_model_with_f64_positions_tracks_f64() {
    // An f32 model in PositionMode::F64 differs from the f64 model only by f32 rounding of t,
    // of the weights, the table and the fma chain: |Δ| ≲ 8 corners · few ulp · |v| ≈ 1e-6.
    let c = cfg(8, 2, 12, 4.0, 1.5, Interpolation::Smoothstep);
    let g = HashGrid::new(&c);
    let t64: Vec<f64> = values(g.n_params(), 7, 1.0)
        .iter()
        .map(|&v| v as f32 as f64)
        .collect();
    let t32: Vec<f32> = t64.iter().map(|&v| v as f32).collect();
    let pts = points(300, 77, 0.0, 1.0);
    let mut o64 = vec![0.0f64; pts.len() * g.out_dim()];
    let mut o32 = vec![0.0f32; pts.len() * g.out_dim()];
    g.forward(&t64, &pts, PositionMode::F64, &mut o64);
    g.forward(&t32, &pts, PositionMode::F64, &mut o32);
    let worst = o64
        .iter()
        .zip(&o32)
        .map(|(a, &b)| (a - b as f64).abs())
        .fold(0.0, f64::max);
    assert!(worst < 2e-6, "worst {worst}");
}

/// tiny-cuda-nn's position gradient, written plainly (f64, PositionMode::F64): per level and
/// feature `dy_dx[d] = Σ_{4 edges along d} ((scale·w'_a)·w'_b)·(v_hi - v_lo)·dw_d/dt` (other
/// axes ascending, edge bits in that order), then `d_x[d] = fma-chain over (l, f) of
/// d_out·dy_dx[d]` starting from 0.
fn reference_points_f64(grid: &HashGrid, table: &[f64], x: &[f64; 3], d_out: &[f64]) -> [f64; 3] {
    let c = &grid.cfg;
    let nf = c.features as usize;
    let smooth = c.interpolation == Interpolation::Smoothstep;
    let mut res = [0.0f64; 3];
    for l in 0..c.levels as usize {
        let scale = grid.scales[l];
        let (mut w, mut dw) = ([0.0f64; 3], [1.0f64; 3]);
        for d in 0..3 {
            let p = (scale as f64).mul_add(x[d], 0.5);
            let t = p - p.floor();
            if smooth {
                w[d] = t * t * (3.0 - 2.0 * t);
                dw[d] = 6.0 * t * (1.0 - t);
            } else {
                w[d] = t;
            }
        }
        let (idx, _) = grid.corners::<f64>(l, x, PositionMode::F64);
        for f in 0..nf {
            let val = |k: usize| table[idx[k] as usize * nf + f];
            let mut dydx = [0.0f64; 3];
            for d in 0..3 {
                let others: Vec<usize> = (0..3).filter(|&o| o != d).collect();
                for e in 0..4usize {
                    let mut weight = scale as f64;
                    let mut lo = 0usize;
                    for (bit, &o) in others.iter().enumerate() {
                        if e >> bit & 1 == 1 {
                            weight *= w[o];
                            lo |= 1 << o;
                        } else {
                            weight *= 1.0 - w[o];
                        }
                    }
                    let hi = lo | 1 << d;
                    dydx[d] += weight * (val(hi) - val(lo)) * dw[d];
                }
            }
            for d in 0..3 {
                res[d] = d_out[l * nf + f].mul_add(dydx[d], res[d]);
            }
        }
    }
    res
}

#[test]
fn backward_points_matches_scalar_reference_f64_bitwise() {
    for (ci, c) in test_configs().into_iter().enumerate() {
        let g = HashGrid::new(&c);
        let table = values(g.n_params(), 900 + ci as u64, 1.0);
        let pts = points(CHUNK_POINTS + 70, 910 + ci as u64, 0.0, 1.0);
        let d_out = values(pts.len() * g.out_dim(), 920 + ci as u64, 1.0);
        let mut d_pts = vec![0.0; pts.len() * 3];
        g.backward_points(&table, &pts, PositionMode::F64, &d_out, &mut d_pts);
        let lf = g.out_dim();
        for (i, x) in pts.iter().enumerate() {
            let r = reference_points_f64(&g, &table, x, &d_out[i * lf..(i + 1) * lf]);
            assert_eq!(&d_pts[i * 3..i * 3 + 3], &r[..], "config {ci} point {i}");
        }
    }
}

// ------------------------------------------------------------------------------------------
// Finite differences (f64)
// ------------------------------------------------------------------------------------------

/// L = Σ d_out · out over the given points.
fn loss(g: &HashGrid, table: &[f64], pts: &[[f64; 3]], mode: PositionMode, d_out: &[f64]) -> f64 {
    let mut out = vec![0.0; pts.len() * g.out_dim()];
    g.forward(table, pts, mode, &mut out);
    out.iter().zip(d_out).map(|(a, b)| a * b).sum()
}

/// Points whose cell fraction t is at least `margin` away from 0 and 1 on every level and axis.
fn interior_points(g: &HashGrid, n: usize, a: u64, margin: f64) -> Vec<[f64; 3]> {
    let mut out = Vec::new();
    let mut i = 0u64;
    while out.len() < n {
        let x = points(1, a * 1_000_003 + i, 0.0, 1.0)[0];
        i += 1;
        let ok = g.scales.iter().all(|&s| {
            x.iter().all(|&xd| {
                let p = (s as f64).mul_add(xd, 0.5);
                let t = p - p.floor();
                t > margin && t < 1.0 - margin
            })
        });
        if ok {
            out.push(x);
        }
    }
    out
}

#[test]
fn table_gradient_matches_finite_differences() {
    // out is linear in the table, so the central difference is exact up to rounding:
    // |error| ≲ ε·Σ|d_out·out| / h ≈ 1e-16 · 1e2 / 1e-3 = 1e-11. Tolerance 1e-9 absolute plus
    // 1e-9 relative leaves margin and would still catch any wrong weight or index (O(1e-2)).
    let mut failures = Vec::new();
    for (ci, c) in test_configs().into_iter().enumerate() {
        let g = HashGrid::new(&c);
        let mut table = values(g.n_params(), 300 + ci as u64, 1.0);
        for mode in [PositionMode::F64, PositionMode::Tcnn] {
            let pts = points(40, 400 + ci as u64, 0.0, 1.0);
            let d_out = values(pts.len() * g.out_dim(), 500 + ci as u64, 1.0);
            let mut d_table = vec![0.0; g.n_params()];
            let mut touched = Touched::default();
            g.backward_table(&pts, mode, &d_out, &mut d_table, &mut touched);
            // Sample touched entries (every one with a gradient) and a few untouched ones.
            let nf = c.features as usize;
            let mut params: Vec<usize> = touched
                .entries
                .iter()
                .step_by((touched.entries.len() / 60).max(1))
                .flat_map(|&e| (0..nf).map(move |f| e as usize * nf + f))
                .collect();
            params.extend((0..10).map(|i| (i * 7919) % g.n_params()));
            let h = 1e-3;
            for &p in &params {
                let v = table[p];
                table[p] = v + h;
                let lp = loss(&g, &table, &pts, mode, &d_out);
                table[p] = v - h;
                let lm = loss(&g, &table, &pts, mode, &d_out);
                table[p] = v;
                let fd = (lp - lm) / (2.0 * h);
                if (fd - d_table[p]).abs() > 1e-9 + 1e-9 * fd.abs() {
                    failures.push(format!(
                        "config {ci} {mode:?} param {p}: analytic {} fd {fd}",
                        d_table[p]
                    ));
                }
            }
        }
    }
    assert!(
        failures.is_empty(),
        "{} failures:\n{}",
        failures.len(),
        failures.join("\n")
    );
}

#[test]
fn position_gradient_matches_finite_differences() {
    // Points are at least 1e-3 (in cell units) from every cell border on every level, and the
    // step moves p by at most 1e-5 cells on the finest level, so no corner changes.
    // Linear: out is linear along each axis inside a cell → the difference is exact up to
    // rounding, ε·|L|/h ≈ 1e-16·10/1e-7 ≈ 1e-8 at the finest steps.
    // Smoothstep: truncation error h_p²/6·|w'''|/|w'| = h_p²·2/(6t(1-t)) ≤ 1e-10/3e-3 ≈ 3e-8
    // relative. Tolerance 1e-6 absolute + 1e-6 relative (gradients are O(scale) ≈ 1..100).
    let mut failures = Vec::new();
    for (ci, c) in test_configs().into_iter().enumerate() {
        let g = HashGrid::new(&c);
        let table = values(g.n_params(), 600 + ci as u64, 1.0);
        let pts = interior_points(&g, 25, 700 + ci as u64, 1e-3);
        let d_out = values(pts.len() * g.out_dim(), 800 + ci as u64, 1.0);
        let mut d_pts = vec![0.0; pts.len() * 3];
        g.backward_points(&table, &pts, PositionMode::F64, &d_out, &mut d_pts);
        let smax = g.scales.iter().fold(0.0f32, |a, &b| a.max(b)) as f64;
        let h = 1e-5 / smax;
        let lf = g.out_dim();
        for (i, x) in pts.iter().enumerate() {
            let dd = &d_out[i * lf..(i + 1) * lf];
            for d in 0..3 {
                let mut xp = *x;
                xp[d] += h;
                let mut xm = *x;
                xm[d] -= h;
                let lp = loss(&g, &table, &[xp], PositionMode::F64, dd);
                let lm = loss(&g, &table, &[xm], PositionMode::F64, dd);
                let fd = (lp - lm) / (2.0 * h);
                let an = d_pts[i * 3 + d];
                if (fd - an).abs() > 1e-6 + 1e-6 * fd.abs() {
                    failures.push(format!(
                        "config {ci} point {i} axis {d}: analytic {an} fd {fd}"
                    ));
                }
            }
        }
    }
    assert!(
        failures.is_empty(),
        "{} failures:\n{}",
        failures.len(),
        failures.join("\n")
    );
}

#[test]
fn backward_accumulates() {
    let g = HashGrid::new(&ModelConfig::tiny().grid_h);
    let table = values(g.n_params(), 1, 1.0);
    let pts = points(50, 2, 0.0, 1.0);
    let d_out = values(pts.len() * g.out_dim(), 3, 1.0);
    let mut dp1 = vec![0.0; pts.len() * 3];
    g.backward_points(&table, &pts, PositionMode::F64, &d_out, &mut dp1);
    let mut dp2 = vec![1.0; pts.len() * 3];
    g.backward_points(&table, &pts, PositionMode::F64, &d_out, &mut dp2);
    for (a, b) in dp1.iter().zip(&dp2) {
        assert_eq!(a + 1.0, *b);
    }
    let mut dt1 = vec![0.0; g.n_params()];
    g.backward_table(
        &pts,
        PositionMode::F64,
        &d_out,
        &mut dt1,
        &mut Touched::default(),
    );
    let mut dt2 = vec![0.5; g.n_params()];
    g.backward_table(
        &pts,
        PositionMode::F64,
        &d_out,
        &mut dt2,
        &mut Touched::default(),
    );
    for (a, b) in dt1.iter().zip(&dt2) {
        assert!((a + 0.5 - b).abs() < 1e-12);
    }
}

// ------------------------------------------------------------------------------------------
// Determinism
// ------------------------------------------------------------------------------------------

#[test]
fn bit_identical_across_thread_counts() {
    // cpu-preset grid H, f32, enough points for several forward chunks and two sequential
    // backward_table chunks.
    let g = HashGrid::new(&ModelConfig::cpu().grid_h);
    let table = g.init_table(3, 0);
    let n = BWD_TABLE_CHUNK + 3 * CHUNK_POINTS + 5;
    let pts = points(n, 11, 0.0, 1.0);
    let d_out: Vec<f32> = values(n * g.out_dim(), 12, 1.0)
        .iter()
        .map(|&v| v as f32)
        .collect();
    let run = |threads: usize| {
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .unwrap();
        pool.install(|| {
            let mut out = vec![0.0f32; n * g.out_dim()];
            g.forward(&table, &pts, PositionMode::F64, &mut out);
            let mut d_table = vec![0.0f32; g.n_params()];
            let mut touched = Touched::default();
            g.backward_table(&pts, PositionMode::F64, &d_out, &mut d_table, &mut touched);
            let mut d_pts = vec![0.0f32; n * 3];
            g.backward_points(&table, &pts, PositionMode::F64, &d_out, &mut d_pts);
            let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<u32>>();
            (bits(&out), bits(&d_table), touched.entries, bits(&d_pts))
        })
    };
    let r1 = run(1);
    for t in [2, 4] {
        let r = run(t);
        assert!(r.0 == r1.0, "forward differs with {t} threads");
        assert!(r.1 == r1.1, "backward_table differs with {t} threads");
        assert!(r.2 == r1.2, "touched differs with {t} threads");
        assert!(r.3 == r1.3, "backward_points differs with {t} threads");
    }
}

#[test]
fn portable_and_fma_builds_agree_bitwise() {
    // The kernels are compiled for baseline x86-64 and for fma+avx2 and picked at run time; both
    // must compute the same bits (FMA is exactly rounded in hardware and in libm). This is the
    // only test that switches the process-wide flag, and it compares within itself.
    let c = cfg(8, 2, 12, 4.0, 1.5, Interpolation::Smoothstep);
    let g = HashGrid::new(&c);
    let table: Vec<f32> = values(g.n_params(), 31, 1.0)
        .iter()
        .map(|&v| v as f32)
        .collect();
    let pts = points(CHUNK_POINTS + 99, 32, -0.02, 1.02);
    let d_out: Vec<f32> = values(pts.len() * g.out_dim(), 33, 1.0)
        .iter()
        .map(|&v| v as f32)
        .collect();
    // Rendering's path too: skipped levels and consecutive points sharing cells.
    let clustered = clustered_points(CHUNK_POINTS + 70 + 3, 34);
    let active = active_counts(clustered.len(), g.cfg.levels);
    let run = |portable: bool, mode: PositionMode| {
        xscale::model::hashgrid::force_portable_kernels(portable);
        let mut out = vec![0.0f32; pts.len() * g.out_dim()];
        g.forward(&table, &pts, mode, &mut out);
        let mut out_active = vec![0.0f32; clustered.len() * g.out_dim()];
        g.forward_active(&table, &clustered, mode, &mut out_active, &active);
        out.extend(out_active);
        let mut d_table = vec![0.0f32; g.n_params()];
        let mut touched = Touched::default();
        g.backward_table(&pts, mode, &d_out, &mut d_table, &mut touched);
        let mut d_pts = vec![0.0f32; pts.len() * 3];
        g.backward_points(&table, &pts, mode, &d_out, &mut d_pts);
        xscale::model::hashgrid::force_portable_kernels(false);
        let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<u32>>();
        (bits(&out), bits(&d_table), touched.entries, bits(&d_pts))
    };
    for mode in [PositionMode::F64, PositionMode::Tcnn] {
        assert!(run(false, mode) == run(true, mode), "{mode:?}");
    }
}

// ------------------------------------------------------------------------------------------
// Touched entries
// ------------------------------------------------------------------------------------------

#[test]
fn touched_is_exactly_the_corners_written() {
    let g = HashGrid::new(&ModelConfig::tiny().grid_h);
    let lf = g.out_dim();
    let mut pts = points(60, 21, 0.0, 1.0);
    // x = 0.5 on level 0 gives p = 2.0 exactly: t = 0, so the upper corners get weight 0.
    pts.push([0.5, 0.5, 0.5]);
    let mut d_out = values(pts.len() * lf, 22, 1.0);
    // Points 0..10 have an all-zero d_out row on level 2 (they contribute nothing there).
    for i in 0..10 {
        for f in 0..2 {
            d_out[i * lf + 2 * 2 + f] = 0.0;
        }
    }
    let mut d_table = vec![0.0f64; g.n_params()];
    let mut touched = Touched::default();
    g.backward_table(&pts, PositionMode::F64, &d_out, &mut d_table, &mut touched);

    // Expected: all 8 corners of every (point, level) whose d_out slice is not all zero.
    let mut want = std::collections::BTreeSet::new();
    let mut zero_weight = std::collections::BTreeSet::new();
    for (i, x) in pts.iter().enumerate() {
        for l in 0..4 {
            if d_out[i * lf + l * 2] == 0.0 && d_out[i * lf + l * 2 + 1] == 0.0 {
                continue;
            }
            let (idx, w) = g.corners::<f64>(l, x, PositionMode::F64);
            for k in 0..8 {
                want.insert(idx[k]);
                if w[k] == 0.0 {
                    zero_weight.insert(idx[k]);
                }
            }
        }
    }
    let want: Vec<u32> = want.into_iter().collect();
    assert_eq!(touched.entries, want, "sorted, unique, exactly the corners");
    assert!(!zero_weight.is_empty());
    // Every entry with a non-zero gradient is listed; listed entries with a zero gradient are
    // only those reached through weight-0 corners.
    let listed: std::collections::BTreeSet<u32> = touched.entries.iter().copied().collect();
    for e in 0..g.n_entries() as u32 {
        let nz = d_table[e as usize * 2] != 0.0 || d_table[e as usize * 2 + 1] != 0.0;
        if nz {
            assert!(
                listed.contains(&e),
                "entry {e} has a gradient but is not listed"
            );
        } else if listed.contains(&e) {
            assert!(
                zero_weight.contains(&e),
                "entry {e} listed without a contribution"
            );
        }
    }

    // Two calls on the two halves give the union and the same gradient bits (point order).
    let half = pts.len() / 2;
    let mut d2 = vec![0.0f64; g.n_params()];
    let mut t2 = Touched::default();
    g.backward_table(
        &pts[..half],
        PositionMode::F64,
        &d_out[..half * lf],
        &mut d2,
        &mut t2,
    );
    g.backward_table(
        &pts[half..],
        PositionMode::F64,
        &d_out[half * lf..],
        &mut d2,
        &mut t2,
    );
    assert_eq!(t2.entries, touched.entries);
    assert!(d2
        .iter()
        .zip(&d_table)
        .all(|(a, b)| a.to_bits() == b.to_bits()));

    // Zeroing only the touched entries zeroes the whole gradient.
    for &e in &touched.entries {
        d_table[e as usize * 2] = 0.0;
        d_table[e as usize * 2 + 1] = 0.0;
    }
    assert!(d_table.iter().all(|&v| v == 0.0));
}
