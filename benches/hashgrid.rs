//! Hash-grid throughput on the `cpu` preset's grid H (L=16, F=2, T=19), R = f32, positions F64.
//!
//! Workload: 65,536 pixels × 4 sub-samples (γ = 2) on a sphere-like surface, pixels at random
//! places on it (as a training batch draws them), each pixel's sub-samples within one
//! finest-level cell of each other. Reports ns per sub-sample for forward, backward_table,
//! backward_points and forward+backward with 1 and 2 threads (rayon pools built here).
//! Before timing, the f32 outputs and gradients are checked against the f64 path.
//!
//! Run: `cargo bench --bench hashgrid` (env `HASHGRID_BENCH_PIXELS` to change the batch,
//! `HASHGRID_BENCH_T` to change log2_table_size).

mod common;
use common::{env_count, env_parse};
use std::time::Instant;
use xscale::model::config::PositionMode;
use xscale::model::hashgrid::{HashGrid, Touched};
use xscale::model::ModelConfig;
use xscale::rng::{uniform_f64, Purpose};

fn surface_points(pixels: usize) -> Vec<[f64; 3]> {
    let mut pts = Vec::with_capacity(pixels * 4);
    let fp = 1.0 / 2048.0; // pixel footprint ≈ the finest cell
    for i in 0..pixels as u64 {
        let u = |k: u64| uniform_f64(1, Purpose::Test, i, k);
        // A bumpy sphere: radius 0.35 + 0.05 sin(5θ) cos(3φ), centred in the unit cube.
        let z = 2.0 * u(0) - 1.0;
        let phi = std::f64::consts::TAU * u(1);
        let s = (1.0 - z * z).sqrt();
        let n = [s * phi.cos(), s * phi.sin(), z];
        let r = 0.35 + 0.05 * (5.0 * z.acos()).sin() * (3.0 * phi).cos();
        let c = [0.5 + r * n[0], 0.5 + r * n[1], 0.5 + r * n[2]];
        // Tangent frame.
        let a = if n[0].abs() < 0.9 {
            [1.0, 0.0, 0.0]
        } else {
            [0.0, 1.0, 0.0]
        };
        let t1 = normalize(cross(n, a));
        let t2 = cross(n, t1);
        for (sa, sb) in [(0.25, 0.25), (0.75, 0.25), (0.25, 0.75), (0.75, 0.75)] {
            let (da, db) = ((sa - 0.5) * fp, (sb - 0.5) * fp);
            pts.push([
                c[0] + da * t1[0] + db * t2[0],
                c[1] + da * t1[1] + db * t2[1],
                c[2] + da * t1[2] + db * t2[2],
            ]);
        }
    }
    pts
}

fn cross(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}
fn normalize(a: [f64; 3]) -> [f64; 3] {
    let l = (a[0] * a[0] + a[1] * a[1] + a[2] * a[2]).sqrt();
    [a[0] / l, a[1] / l, a[2] / l]
}

/// CPU time of this process so far (all threads), in seconds, from /proc/self/task/*/schedstat
/// (ns resolution). On a machine shared with other jobs the wall time of a run is inflated by
/// waiting for a core; the CPU time is not, so both are reported. None if unavailable.
fn cpu_seconds() -> Option<f64> {
    let mut ns = 0u64;
    for e in std::fs::read_dir("/proc/self/task").ok()? {
        let s = std::fs::read_to_string(e.ok()?.path().join("schedstat")).ok()?;
        ns += s.split_whitespace().next()?.parse::<u64>().ok()?;
    }
    Some(ns as f64 * 1e-9)
}

/// (wall, cpu) seconds of the fastest of `reps` runs (by wall time) after one warm-up.
fn best_of<F: FnMut()>(reps: usize, mut f: F) -> (f64, f64) {
    f(); // warm-up
    (0..reps)
        .map(|_| {
            let c = cpu_seconds().unwrap_or(f64::NAN);
            let t = Instant::now();
            f();
            let w = t.elapsed().as_secs_f64();
            (w, cpu_seconds().unwrap_or(f64::NAN) - c)
        })
        .fold(
            (f64::INFINITY, f64::NAN),
            |a, b| if b.0 < a.0 { b } else { a },
        )
}

fn main() {
    let pixels = env_count("HASHGRID_BENCH_PIXELS", 65_536);
    let mut cfg = ModelConfig::cpu().grid_h;
    if std::env::var_os("HASHGRID_BENCH_T").is_some() {
        // e.g. 10: a cache-resident table, to see the compute cost
        cfg.log2_table_size = env_parse("HASHGRID_BENCH_T", 0, "a log2 table size");
    }
    let g = HashGrid::new(&cfg);
    let mode = PositionMode::F64;
    let pts = surface_points(pixels);
    let n = pts.len();
    let lf = g.out_dim();
    let table: Vec<f32> = g
        .init_table(1, 0)
        .iter()
        .map(|&v| v * 1e4) // O(1) values so the checks below are meaningful
        .collect();
    let d_out: Vec<f32> = (0..n * lf)
        .map(|i| (2.0 * uniform_f64(2, Purpose::Test, 0, i as u64) - 1.0) as f32)
        .collect();

    // Instruction-count mode (for `valgrind --tool=cachegrind`, whose counts do not depend on
    // the machine's load): run one pass once and exit. `none` measures the set-up alone.
    if let Ok(op) = std::env::var("HASHGRID_BENCH_ONLY") {
        let mut out = vec![0.0f32; n * lf];
        let mut d_table = vec![0.0f32; g.n_params()];
        let mut d_pts = vec![0.0f32; n * 3];
        let mut touched = Touched::default();
        match op.as_str() {
            "forward" => g.forward(&table, &pts, mode, &mut out),
            "backward_table" => g.backward_table(&pts, mode, &d_out, &mut d_table, &mut touched),
            "backward_points" => g.backward_points(&table, &pts, mode, &d_out, &mut d_pts),
            _ => {}
        }
        std::hint::black_box((&out, &d_table, &d_pts));
        return;
    }

    // ---- validation: f32 path against the f64 path on a subset.
    {
        let sub = 4096.min(n);
        let t64: Vec<f64> = table.iter().map(|&v| v as f64).collect();
        let mut o32 = vec![0.0f32; sub * lf];
        let mut o64 = vec![0.0f64; sub * lf];
        g.forward(&table, &pts[..sub], mode, &mut o32);
        g.forward(&t64, &pts[..sub], mode, &mut o64);
        let err = o32
            .iter()
            .zip(&o64)
            .map(|(&a, &b)| (a as f64 - b).abs())
            .fold(0.0, f64::max);
        assert!(err < 1e-5, "forward f32 vs f64: max abs error {err}");
        let d64: Vec<f64> = d_out[..sub * lf].iter().map(|&v| v as f64).collect();
        let mut p32 = vec![0.0f32; sub * 3];
        let mut p64 = vec![0.0f64; sub * 3];
        g.backward_points(&table, &pts[..sub], mode, &d_out[..sub * lf], &mut p32);
        g.backward_points(&t64, &pts[..sub], mode, &d64, &mut p64);
        // Relative to the largest gradient: single entries are sums of 16*F*12 terms of size
        // ~scale·|Δv| that cancel, so per-entry relative error is not meaningful in f32.
        let pmax = p64.iter().fold(0.0f64, |m, &b| m.max(b.abs()));
        let perr = p32
            .iter()
            .zip(&p64)
            .map(|(&a, &b)| (a as f64 - b).abs() / pmax)
            .fold(0.0, f64::max);
        assert!(
            perr < 1e-5,
            "backward_points f32 vs f64: max error / max |grad| = {perr}"
        );
        let mut dt32 = vec![0.0f32; g.n_params()];
        let mut dt64 = vec![0.0f64; g.n_params()];
        let (mut tc32, mut tc64) = (Touched::default(), Touched::default());
        g.backward_table(&pts[..sub], mode, &d_out[..sub * lf], &mut dt32, &mut tc32);
        g.backward_table(&pts[..sub], mode, &d64, &mut dt64, &mut tc64);
        assert_eq!(tc32.entries, tc64.entries);
        let terr = tc32
            .entries
            .iter()
            .flat_map(|&e| [e as usize * 2, e as usize * 2 + 1])
            .map(|i| (dt32[i] as f64 - dt64[i]).abs())
            .fold(0.0, f64::max);
        assert!(
            terr < 1e-4,
            "backward_table f32 vs f64: max abs error {terr}"
        );
        println!(
            "validated on {sub} sub-samples: forward {err:.2e}, d_points {perr:.2e} (rel), d_table {terr:.2e}"
        );
    }

    let uptime = std::fs::read_to_string("/proc/loadavg").unwrap_or_default();
    println!(
        "cpu grid H: L={} F={} T={} ({} params), {pixels} pixels x 4 = {n} sub-samples, f32, positions f64",
        g.cfg.levels,
        g.cfg.features,
        g.cfg.log2_table_size,
        g.n_params()
    );
    println!("load average at start: {}", uptime.trim());

    let mut out = vec![0.0f32; n * lf];
    let mut d_table = vec![0.0f32; g.n_params()];
    let mut d_pts = vec![0.0f32; n * 3];
    let mut touched = Touched::default();
    let zero = |d_table: &mut [f32], touched: &mut Touched| {
        for &e in &touched.entries {
            d_table[e as usize * 2] = 0.0;
            d_table[e as usize * 2 + 1] = 0.0;
        }
        touched.entries.clear();
    };
    println!(
        "whole batch: best of 3 wall (cpu) ns per sub-sample; slices: median / min over {} slices of {SLICE}",
        n / SLICE
    );
    let mut results = Vec::new();
    for threads in [1usize, 2] {
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .unwrap();
        pool.install(|| {
            let reps = 3;
            let fwd = best_of(reps, || g.forward(&table, &pts, mode, &mut out));
            let bt = best_of(reps, || {
                zero(&mut d_table, &mut touched);
                g.backward_table(&pts, mode, &d_out, &mut d_table, &mut touched)
            });
            let bp = best_of(reps, || g.backward_points(&table, &pts, mode, &d_out, &mut d_pts));
            let all = best_of(reps, || {
                g.forward(&table, &pts, mode, &mut out);
                zero(&mut d_table, &mut touched);
                g.backward_table(&pts, mode, &d_out, &mut d_table, &mut touched);
                g.backward_points(&table, &pts, mode, &d_out, &mut d_pts);
            });
            let n_touched = touched.entries.len();
            // Per-slice timings: each slice is short enough to usually run without being
            // preempted on a shared machine; the median is robust to the slices that were.
            zero(&mut d_table, &mut touched);
            let sl = slice_stats(n, |r| {
                g.forward(&table, &pts[r.clone()], mode, &mut out[r.start * lf..r.end * lf])
            });
            let sl_bp = slice_stats(n, |r| {
                let dd = &d_out[r.start * lf..r.end * lf];
                g.backward_points(&table, &pts[r.clone()], mode, dd, &mut d_pts[r.start * 3..r.end * 3]);
            });
            let ns = |s: (f64, f64)| format!("{:6.1} ({:6.1})", s.0 * 1e9 / n as f64, s.1 * 1e9 / n as f64);
            println!(
                "{threads} thread(s): forward {}  backward_table {}  backward_points {}  fwd+bwd {}  \
                 [{:.2} M sub-samples/s fwd+bwd; touched {n_touched} entries]",
                ns(fwd),
                ns(bt),
                ns(bp),
                ns(all),
                n as f64 / all.0 / 1e6,
            );
            println!(
                "{threads} thread(s) slices: forward {:6.1} / {:6.1}   backward_points {:6.1} / {:6.1}",
                sl.0, sl.1, sl_bp.0, sl_bp.1
            );
            results.push((threads, fwd.0, all.0));
        });
    }
    if let [(_, f1, a1), (_, f2, a2)] = results[..] {
        println!(
            "speed-up 1→2 threads (whole batch, wall): forward {:.2}x, fwd+bwd {:.2}x",
            f1 / f2,
            a1 / a2
        );
    }
    let uptime = std::fs::read_to_string("/proc/loadavg").unwrap_or_default();
    println!("load average at end: {}", uptime.trim());
}

const SLICE: usize = 4096;

/// (median, min) ns per sub-sample of `f` over consecutive slices of SLICE sub-samples.
fn slice_stats<F: FnMut(std::ops::Range<usize>)>(n: usize, mut f: F) -> (f64, f64) {
    let mut v: Vec<f64> = (0..n / SLICE)
        .map(|s| {
            let t = Instant::now();
            f(s * SLICE..(s + 1) * SLICE);
            t.elapsed().as_secs_f64() * 1e9 / SLICE as f64
        })
        .collect();
    v.sort_by(f64::total_cmp);
    (v[v.len() / 2], v[0])
}
