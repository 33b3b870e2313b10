//! Adam with tiny-cuda-nn's rules (SPEC §4.8): expected values are written out in f64 from the
//! formulas (m = β1 m + (1-β1) g, v = β2 v + (1-β2) g², lr_t = lr sqrt(1-β2^t)/(1-β1^t),
//! w -= lr_t m / (sqrt(v) + ε)) and compared with the f32 optimizer at f32-level tolerance.

// Index loops mirror the formulas (i over entries, c over channels).
#![allow(clippy::needless_range_loop)]

use xscale::io::TensorFile;
use xscale::train::adam::{AdamGroup, AdamState, LrSchedule, Moments, DENSE_CHUNK, SPARSE_CHUNK};

/// β1, β2 as the optimizer holds them (f32), widened exactly.
const B1: f64 = 0.9f32 as f64;
const B2: f64 = 0.999f32 as f64;

fn group(lr: f32, sparse: bool) -> AdamGroup {
    AdamGroup {
        lr,
        beta1: 0.9,
        beta2: 0.999,
        epsilon: 1e-8,
        l2: 0.0,
        sparse,
        schedule: LrSchedule::default(),
    }
}

/// |got - want| within a few f32 ulps (2^-24 ≈ 6e-8 relative) of the magnitudes involved: each
/// step rounds m, v, lr_t, the quotient and w once each in f32. Inputs of the expected values use
/// the f32 hyperparameters widened (B1, B2), as `1 - 0.999f32` differs from 0.001 by 1.3e-5.
const TOL_REL: f64 = 4e-7;

fn close(got: f32, want: f64, what: &str) {
    let tol = TOL_REL * want.abs().max(1e-3);
    assert!(
        (got as f64 - want).abs() <= tol,
        "{what}: got {got:e}, want {want:e} (diff {:e}, tol {tol:e})",
        (got as f64 - want).abs()
    );
}

#[test]
fn dense_three_steps_by_hand() {
    let mut st = AdamState::new(&[("w", vec![1])]);
    let cfg = group(0.1, false);
    let mut w = [0.5f32];
    let gs = [0.2f32, -0.4, 0.1];
    for (k, g) in gs.iter().enumerate() {
        st.step_dense(0..1, &mut w, &[*g], &cfg, k as u64);
    }
    // Step 1.
    let m1: f64 = (1.0 - B1) * 0.2;
    let v1: f64 = (1.0 - B2) * 0.2 * 0.2;
    let w1 = 0.5 - 0.1 * (1.0 - B2).sqrt() / (1.0 - B1) * m1 / (v1.sqrt() + 1e-8);
    // Step 2.
    let m2 = B1 * m1 + (1.0 - B1) * -0.4;
    let v2: f64 = B2 * v1 + (1.0 - B2) * 0.16;
    let w2 = w1 - 0.1 * (1.0 - B2 * B2).sqrt() / (1.0 - B1 * B1) * m2 / (v2.sqrt() + 1e-8);
    // Step 3.
    let m3 = B1 * m2 + (1.0 - B1) * 0.1;
    let v3: f64 = B2 * v2 + (1.0 - B2) * 0.01;
    let w3 = w2 - 0.1 * (1.0 - B2.powi(3)).sqrt() / (1.0 - B1.powi(3)) * m3 / (v3.sqrt() + 1e-8);
    close(st.state[0].m, m3, "m3");
    close(st.state[0].v, v3, "v3");
    assert_eq!(st.state[0].t, 3);
    close(w[0], w3, "w3");
    // Sanity of the hand arithmetic: Adam's first step moves by ~lr against the gradient.
    assert!((w1 - 0.4).abs() < 1e-6);
}

#[test]
fn dense_group_steps_zero_gradients_and_applies_l2() {
    let mut st = AdamState::new(&[("w", vec![2])]);
    let cfg = AdamGroup {
        l2: 0.5,
        ..group(0.01, false)
    };
    let mut w = [2.0f32, -1.0];
    st.step_dense(0..2, &mut w, &[0.1, 0.0], &cfg, 0);
    // g' = g + l2 * w: 0.1 + 1.0 = 1.1 and 0 + (-0.5) = -0.5; both step (dense never skips).
    assert_eq!(st.t(0..2), vec![1, 1]);
    close(st.state[0].m, (1.0 - B1) * 1.1, "m0");
    close(st.state[0].v, (1.0 - B2) * 1.21, "v0");
    close(st.state[1].m, (1.0 - B1) * -0.5, "m1");
    let step = |g: f64| {
        0.01 * (1.0 - B2).sqrt() / (1.0 - B1) * ((1.0 - B1) * g)
            / (((1.0 - B2) * g * g).sqrt() + 1e-8)
    };
    close(w[0], 2.0 - step(1.1), "w0");
    close(w[1], -1.0 - step(-0.5), "w1");
    // Even with l2 = 0 a dense group decays its moments on a zero gradient.
    let mut st = AdamState::with_len(1);
    let mut w = [1.0f32];
    st.step_dense(0..1, &mut w, &[1.0], &group(0.01, false), 0);
    let m_before = st.state[0].m;
    st.step_dense(0..1, &mut w, &[0.0], &group(0.01, false), 1);
    assert_eq!(st.state[0].t, 2);
    close(st.state[0].m, B1 * m_before as f64, "decayed m");
}

#[test]
fn sparse_skips_zero_gradients_and_uses_own_step_count() {
    // Table of 4 entries × 2 features.
    let mut st = AdamState::new(&[("grid_h.table", vec![4, 2])]);
    let cfg = group(0.1, true);
    let w0 = [0.1f32, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8];
    let mut w = w0;
    let all = [0u32, 1, 2, 3];
    // Step k = 0: entry 2 has an all-zero gradient; entry 1 feature 1 is exactly -0.0.
    let g0 = [0.2f32, 0.2, 0.2, -0.0, 0.0, 0.0, 0.2, 0.2];
    st.step_sparse(&mut w, &g0, &all, 2, 0, &cfg, 0);
    assert_eq!(st.t(0..st.len()), vec![1, 1, 1, 0, 0, 0, 1, 1]);
    for i in [3usize, 4, 5] {
        assert_eq!(
            w[i].to_bits(),
            w0[i].to_bits(),
            "skipped weight {i} unchanged"
        );
        assert_eq!(
            (st.state[i].m, st.state[i].v),
            (0.0, 0.0),
            "skipped moments {i} unchanged"
        );
    }
    // Step k = 1: every entry gets 0.3. Entry 2 takes its FIRST step (t = 1), the others their
    // second (t = 2).
    let g1 = [0.3f32; 8];
    st.step_sparse(&mut w, &g1, &all, 2, 0, &cfg, 1);
    assert_eq!(st.t(0..st.len()), vec![2, 2, 2, 1, 1, 1, 2, 2]);
    let first = |g: f64| {
        0.1 * (1.0 - B2).sqrt() / (1.0 - B1) * ((1.0 - B1) * g)
            / (((1.0 - B2) * g * g).sqrt() + 1e-8)
    };
    let m2 = B1 * ((1.0 - B1) * 0.2) + (1.0 - B1) * 0.3;
    let v2: f64 = B2 * ((1.0 - B2) * 0.04) + (1.0 - B2) * 0.09;
    let second = 0.1 * (1.0 - B2 * B2).sqrt() / (1.0 - B1 * B1) * m2 / (v2.sqrt() + 1e-8);
    close(w[4], 0.5 - first(0.3), "entry 2 first step with t = 1");
    close(w[5], 0.6 - first(0.3), "entry 2 first step with t = 1");
    close(w[3], 0.4 - first(0.3), "entry 1 feature 1: first step");
    close(
        w[0],
        0.1 - first(0.2) - second,
        "entry 0: second step with t = 2",
    );
    close(st.state[4].m, (1.0 - B1) * 0.3, "fresh m");
}

#[test]
fn sparse_touches_only_listed_entries() {
    let mut st = AdamState::with_len(10);
    let cfg = group(0.1, true);
    let mut w = [1.0f32; 10];
    let g = [0.5f32; 10];
    // Only entries 1 and 3 of 5 (entry_len 2), state based at 0.
    st.step_sparse(&mut w, &g, &[1, 3], 2, 0, &cfg, 0);
    for i in 0..10 {
        let listed = matches!(i / 2, 1 | 3);
        assert_eq!(st.state[i].t, listed as u32, "t[{i}]");
        assert_eq!(w[i] != 1.0, listed, "w[{i}]");
    }
    // base_offset: a table living at offset 4 of a larger state.
    let mut st = AdamState::with_len(10);
    let mut table = [1.0f32; 6];
    st.step_sparse(&mut table, &[0.5; 6], &[2], 2, 4, &cfg, 0);
    assert_eq!(st.t(0..st.len()), vec![0, 0, 0, 0, 0, 0, 0, 0, 1, 1]);
    assert_eq!(&table[..4], &[1.0; 4]);
    assert!(table[4] < 1.0 && table[5] < 1.0);
}

#[test]
#[should_panic(expected = "strictly increasing")]
fn sparse_rejects_unsorted_entries() {
    let mut st = AdamState::with_len(4);
    let mut w = [0.0f32; 4];
    st.step_sparse(&mut w, &[1.0; 4], &[1, 0], 2, 0, &group(0.1, true), 0);
}

/// The order is checked chunk by chunk (in parallel), so a repeat where two chunks meet and a
/// swap deep inside a later chunk must be caught as well as one in a single-chunk list.
#[test]
fn sparse_rejects_unsorted_entries_across_and_inside_chunks() {
    let n = 3 * SPARSE_CHUNK;
    let sorted: Vec<u32> = (0..n as u32).collect();
    let mut repeat_at_seam = sorted.clone();
    repeat_at_seam[SPARSE_CHUNK] = repeat_at_seam[SPARSE_CHUNK - 1];
    let mut swap_inside = sorted.clone();
    swap_inside.swap(SPARSE_CHUNK + 100, SPARSE_CHUNK + 101);
    let mut repeat_inside = sorted.clone();
    repeat_inside[2 * SPARSE_CHUNK + 7] = repeat_inside[2 * SPARSE_CHUNK + 6];
    for (what, entries) in [
        ("a repeat where chunks meet", repeat_at_seam),
        ("a swap inside a chunk", swap_inside),
        ("a repeat inside a chunk", repeat_inside),
    ] {
        let r = std::panic::catch_unwind(move || {
            let mut st = AdamState::with_len(n);
            let mut w = vec![0.0f32; n];
            st.step_sparse(&mut w, &vec![1.0; n], &entries, 1, 0, &group(0.1, true), 0);
        });
        let msg = r.expect_err(what);
        let msg = msg
            .downcast_ref::<String>()
            .cloned()
            .or_else(|| msg.downcast_ref::<&str>().map(|s| s.to_string()))
            .unwrap_or_default();
        assert!(msg.contains("strictly increasing"), "{what}: {msg}");
    }
    // And the sorted list steps every entry.
    let mut st = AdamState::with_len(n);
    let mut w = vec![0.0f32; n];
    st.step_sparse(&mut w, &vec![1.0; n], &sorted, 1, 0, &group(0.1, true), 0);
    assert!(st.t(0..n).iter().all(|&t| t == 1));
}

#[test]
fn per_group_learning_rates() {
    let mut st = AdamState::new(&[
        ("shader.layers.0.weight", vec![2, 2]),
        ("grid_h.table", vec![3, 2]),
    ]);
    let rs = st.range("shader.layers.0.weight").unwrap();
    let rg = st.range("grid_h.table").unwrap();
    assert_eq!((rs.clone(), rg.clone()), (0..4, 4..10));
    let mut shader = [0.5f32; 4];
    let mut grid = [0.5f32; 6];
    st.step_dense(rs, &mut shader, &[1.0; 4], &group(0.01, false), 0);
    st.step_sparse(
        &mut grid,
        &[1.0; 6],
        &[0, 1, 2],
        2,
        rg.start,
        &group(0.1, true),
        0,
    );
    // First step with g = 1: Δ = lr * sqrt(1-β2)/(1-β1) * (1-β1) / (sqrt(1-β2) + ε).
    let delta =
        |lr: f64| lr * (1.0 - B2).sqrt() / (1.0 - B1) * (1.0 - B1) / ((1.0 - B2).sqrt() + 1e-8);
    for w in shader {
        close(w, 0.5 - delta(0.01), "shader (lr 0.01)");
    }
    for w in grid {
        close(w, 0.5 - delta(0.1), "grid (lr 0.1)");
    }
}

#[test]
fn warmup_and_decay_schedule() {
    let warm = AdamGroup {
        schedule: LrSchedule {
            warmup_steps: 2,
            ..Default::default()
        },
        ..group(0.1, false)
    };
    assert_eq!(warm.lr_at(0), 0.1f32 as f64 * 0.5);
    assert_eq!(warm.lr_at(1), 0.1f32 as f64);
    let mut st = AdamState::with_len(1);
    let mut w = [0.0f32];
    st.step_dense(0..1, &mut w, &[1.0], &warm, 0);
    st.step_dense(0..1, &mut w, &[1.0], &warm, 1);
    // g = 1 twice: m_t/sqrt(v_t) with bias correction is exactly 1 each step (up to ε).
    let s1 = 0.05 * (1.0 - B2).sqrt() / (1.0 - B1) * (1.0 - B1) / ((1.0 - B2).sqrt() + 1e-8);
    let m2 = B1 * (1.0 - B1) + (1.0 - B1);
    let v2 = B2 * (1.0 - B2) + (1.0 - B2);
    let s2 = 0.1 * (1.0 - B2.powi(2)).sqrt() / (1.0 - B1.powi(2)) * m2 / (v2.sqrt() + 1e-8);
    close(w[0], -s1 - s2, "warm-up");
    assert!((s1 - 0.05).abs() < 1e-6 && (s2 - 0.1).abs() < 1e-6);

    let decay = AdamGroup {
        schedule: LrSchedule {
            decay_start: 1,
            decay_interval: 1,
            decay_base: 0.5,
            ..Default::default()
        },
        ..group(0.1, true)
    };
    let lrs: Vec<f64> = (0..4).map(|k| decay.lr_at(k) / 0.1f32 as f64).collect();
    assert_eq!(lrs, vec![1.0, 0.5, 0.25, 0.125]);
    let mut st = AdamState::with_len(1);
    let mut w = [0.0f32];
    st.step_sparse(&mut w, &[1.0], &[0], 1, 0, &decay, 0);
    st.step_sparse(&mut w, &[1.0], &[0], 1, 0, &decay, 1);
    let s1 = 0.1 * (1.0 - B2).sqrt() / (1.0 - B1) * (1.0 - B1) / ((1.0 - B2).sqrt() + 1e-8);
    let s2 = 0.05 * (1.0 - B2.powi(2)).sqrt() / (1.0 - B1.powi(2)) * m2 / (v2.sqrt() + 1e-8);
    close(w[0], -s1 - s2, "decay");
}

/// Deterministic pseudo-random values for the larger tests (no state, no crate RNG needed).
fn hashf(i: usize, salt: u32) -> f32 {
    let mut x = (i as u32).wrapping_mul(0x9E37_79B9) ^ salt.wrapping_mul(0x85EB_CA6B);
    x ^= x >> 16;
    x = x.wrapping_mul(0x7FEB_352D);
    x ^= x >> 15;
    (x as f32 / u32::MAX as f32) * 2.0 - 1.0
}

/// Gradient pattern with many exact zeros (whole entries and single features).
fn grads(n: usize, step: u32) -> Vec<f32> {
    (0..n)
        .map(|i| {
            let h = hashf(i, 1000 + step);
            if h.abs() < 0.4 {
                0.0
            } else {
                h * 1e-2
            }
        })
        .collect()
}

#[test]
fn sparse_equals_dense_with_skip_and_is_thread_count_invariant() {
    let entry_len = 2;
    let n_entries = 5 * SPARSE_CHUNK + 17;
    let n = n_entries * entry_len;
    assert!(n > DENSE_CHUNK, "exercise the parallel dense path");
    let cfg = group(1e-2, true);
    let w_init: Vec<f32> = (0..n).map(|i| hashf(i, 7) * 1e-4).collect();
    let run = |threads: usize, sparse: bool| {
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .unwrap();
        pool.install(|| {
            let mut st = AdamState::with_len(n);
            let mut w = w_init.clone();
            for k in 0..5u32 {
                let g = grads(n, k);
                if sparse {
                    // Touched entries: those with any non-zero feature (as the grid backward lists).
                    let entries: Vec<u32> = (0..n_entries as u32)
                        .filter(|&e| {
                            let b = e as usize * entry_len;
                            g[b..b + entry_len].iter().any(|&x| x != 0.0)
                        })
                        .collect();
                    st.step_sparse(&mut w, &g, &entries, entry_len, 0, &cfg, k as u64);
                } else {
                    st.step_dense(0..n, &mut w, &g, &cfg, k as u64);
                }
            }
            (w, st)
        })
    };
    let (w_ref, st_ref) = run(1, false);
    for (threads, sparse) in [(1, true), (2, true), (2, false), (4, true)] {
        let (w, st) = run(threads, sparse);
        let same = w
            .iter()
            .zip(&w_ref)
            .all(|(a, b)| a.to_bits() == b.to_bits())
            && st.state.iter().zip(&st_ref.state).all(|(a, b)| {
                a.m.to_bits() == b.m.to_bits() && a.v.to_bits() == b.v.to_bits() && a.t == b.t
            });
        assert!(
            same,
            "threads {threads}, sparse {sparse}: not bit-identical"
        );
    }
    // Some parameters were skipped on some steps, so step counts differ across parameters.
    let t = st_ref.t(0..st_ref.len());
    assert!(t.iter().any(|&t| t < 5) && t.contains(&5));
}

#[test]
fn save_and_load_state() {
    let params = [
        ("shader.layers.0.weight", vec![2, 3]),
        ("grid_h.table", vec![4, 2]),
    ];
    let mut st = AdamState::new(&params);
    let mut w = vec![0.5f32; 6];
    st.step_dense(
        0..6,
        &mut w,
        &[0.1, 0.0, -0.3, 0.2, 0.5, 0.1],
        &group(0.01, false),
        0,
    );
    let mut tab = vec![0.5f32; 8];
    st.step_sparse(&mut tab, &[0.1; 8], &[1, 3], 2, 6, &group(0.1, true), 0);
    let mut f = TensorFile::new();
    st.save(&mut f).unwrap();
    assert_eq!(f.get("adam.m.grid_h.table").unwrap().shape, vec![4, 2]);
    assert_eq!(
        f.get_u32("adam.t.grid_h.table").unwrap(),
        vec![0, 0, 1, 1, 0, 0, 1, 1]
    );
    let bytes = f.to_bytes().unwrap();
    let g = TensorFile::from_bytes(&bytes, "ck").unwrap();
    let back = AdamState::load(&g, &params).unwrap();
    assert_eq!(back, st);
    // A shape that does not match is an error naming the tensor.
    let wrong = [
        ("shader.layers.0.weight", vec![3, 2]),
        ("grid_h.table", vec![4, 2]),
    ];
    let e = format!("{:#}", AdamState::load(&g, &wrong).unwrap_err());
    assert!(e.contains("adam.m.shader.layers.0.weight"), "{e}");
    let e = format!(
        "{:#}",
        AdamState::load(&g, &[("appearance.codes", vec![2, 4])]).unwrap_err()
    );
    assert!(e.contains("missing tensor adam.m.appearance.codes"), "{e}");
}

#[test]
fn save_and_load_a_state_spanning_many_chunks() {
    // Saving and loading work on chunks of the state in parallel: every scalar must come back
    // in its place, across chunk borders and in a last partial chunk.
    let params = [("grid_h.table", vec![100_003, 2]), ("shader.w", vec![3])];
    let mut st = AdamState::new(&params);
    for (i, s) in st.state.iter_mut().enumerate() {
        *s = Moments {
            m: i as f32 * 0.25 - 7.0,
            v: i as f32 + 0.5,
            t: (i * 3) as u32,
        };
    }
    let mut f = TensorFile::new();
    st.save(&mut f).unwrap();
    let r = st.range("grid_h.table").unwrap();
    assert_eq!(f.get_f32("adam.m.grid_h.table").unwrap(), st.m(r.clone()));
    assert_eq!(f.get_f32("adam.v.grid_h.table").unwrap(), st.v(r.clone()));
    assert_eq!(f.get_u32("adam.t.grid_h.table").unwrap(), st.t(r));
    let g = TensorFile::from_bytes(&f.to_bytes().unwrap(), "ck").unwrap();
    assert_eq!(AdamState::load(&g, &params).unwrap().state, st.state);
}
