//! Bench: a sparse Adam step costs O(entries touched), not O(table size) (SPEC §4.8, §8).
//!
//! For tables of 2^14, 2^19 and 2^22 entries (F = 2 features, the `cpu` preset's layout) the same
//! number of touched entries (4096, spread over the table) is stepped with `step_sparse_and_zero`
//! (the training loop's form; `step_sparse` would copy the whole gradient first); for
//! contrast, a dense pass over the whole table (`step_dense` with sparse semantics, i.e. what an
//! optimizer without a touched list must do) is timed too. Before timing, the bench checks that a
//! sparse step changed exactly the listed entries. Reports median times and ratios to the
//! smallest table from this one run. A last row steps the 2^22 table at the 2^14 run's entries,
//! isolating cache/TLB effects of spreading the same entries over a bigger table.
//!
//! Run: `cargo bench --bench adam` (add `-- --threads N` to fix the thread count).

use std::time::Instant;
use xscale::rng::{self, Purpose};
use xscale::train::adam::{AdamGroup, AdamState};

const F: usize = 2;
const TOUCHED: usize = 4096;

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(|a, b| a.partial_cmp(b).unwrap());
    v[v.len() / 2]
}

/// `TOUCHED` distinct entries spread over `n` entries, sorted (one random entry per stripe).
fn touched(n: usize) -> Vec<u32> {
    let stripe = n / TOUCHED;
    (0..TOUCHED)
        .map(|i| {
            (i * stripe) as u32 + rng::below(1, Purpose::Test, 7, i as u64, stripe as u64) as u32
        })
        .collect()
}

fn main() {
    let args: Vec<String> = std::env::args().collect();
    if let Some(i) = args.iter().position(|a| a == "--threads") {
        let n: usize = args[i + 1].parse().expect("--threads N");
        rayon::ThreadPoolBuilder::new()
            .num_threads(n)
            .build_global()
            .unwrap();
    }
    let cfg = AdamGroup {
        sparse: true,
        ..AdamGroup::default()
    };
    println!(
        "sparse Adam step, {TOUCHED} touched entries x F={F}, {} threads",
        rayon::current_num_threads()
    );
    println!(
        "{:>10} {:>14} {:>10} {:>16} {:>10}   (* = touched entries within the first 2^14)",
        "entries", "sparse step", "ratio", "dense pass", "ratio"
    );
    let mut base: Option<(f64, f64)> = None;
    // The last row: the 2^22 table with the touched entries of the 2^14 run (clustered in its
    // first 2^14 entries) separates the algorithmic cost (none per table entry) from cache and
    // TLB misses of entries spread over a large table.
    for (log2, spread_log2) in [(14u32, 14u32), (19, 19), (22, 22), (22, 14)] {
        let n = 1usize << log2;
        let entries = touched(1usize << spread_log2);
        let mut w: Vec<f32> = (0..n * F)
            .map(|i| rng::uniform_f32(1, Purpose::Test, 1, i as u64) * 2e-4 - 1e-4)
            .collect();
        let mut g = vec![0.0f32; n * F];
        for (k, &e) in entries.iter().enumerate() {
            for f in 0..F {
                g[e as usize * F + f] =
                    rng::uniform_f32(1, Purpose::Test, 2, (k * F + f) as u64) - 0.5;
            }
        }
        let mut st = AdamState::with_len(n * F);

        // Validate: one step changes exactly the listed entries (all their gradients are non-zero).
        let before = w.clone();
        st.step_sparse(&mut w, &g, &entries, F, 0, &cfg, 0);
        let mut listed = vec![false; n];
        for &e in &entries {
            listed[e as usize] = true;
        }
        for i in 0..n * F {
            let changed = w[i] != before[i];
            assert_eq!(changed, listed[i / F], "element {i}");
            assert_eq!(st.state[i].t, listed[i / F] as u32, "t[{i}]");
        }

        // Timed: the training loop's form, which zeroes the gradients it reads (`step_sparse`
        // copies the whole gradient first); the listed gradients are restored between steps.
        let reps = 200;
        let mut ts = Vec::with_capacity(reps);
        let mut gz = g.clone();
        for k in 0..reps {
            for &e in &entries {
                let r = e as usize * F..(e as usize + 1) * F;
                gz[r.clone()].copy_from_slice(&g[r]);
            }
            let t0 = Instant::now();
            st.step_sparse_and_zero(&mut w, &mut gz, &entries, F, 0, &cfg, 1 + k as u64);
            ts.push(t0.elapsed().as_secs_f64());
        }
        let sparse = median(ts);
        let dreps = 7;
        let mut ts = Vec::with_capacity(dreps);
        for k in 0..dreps {
            let t0 = Instant::now();
            st.step_dense(0..n * F, &mut w, &g, &cfg, (1 + reps + k) as u64);
            ts.push(t0.elapsed().as_secs_f64());
        }
        let dense = median(ts);
        let (bs, bd) = *base.get_or_insert((sparse, dense));
        println!(
            "{:>10} {:>11.1} us {:>9.2}x {:>13.1} us {:>9.1}x",
            if spread_log2 == log2 {
                format!("2^{log2}")
            } else {
                format!("2^{log2}*")
            },
            sparse * 1e6,
            sparse / bs,
            dense * 1e6,
            dense / bd
        );
    }
}
