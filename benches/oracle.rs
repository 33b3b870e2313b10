//! The oracle path (`xscale dump`), error against speed: for each precision mode of the dump, the
//! time per dump and, per tensor family, the largest error against the f64 path, in one table.
//!
//! Workload: the golden `cpu-t10` checkpoint (cpu preset structure — grid H L = 16, F = 2; shader
//! 2 × 64; deformation on; A = 4 — with 2^10 tables, after 20 training steps, so every parameter
//! and gradient is non-trivial) on a seeded random batch of `ORACLE_BENCH_PIXELS` pixels (default
//! 4,096) × 4 sub-samples, 10 % of them invalid, views −1..3.
//!
//! Modes (columns): `f64 + kinks` (the default f64 dump, with the kink analysis), `f64` (no
//! kink analysis, `--kink-threshold 0`), `f32`, and `f32 tcnn` (the checkpoint switched to
//! `positions = "tcnn"`, compared against the f64 dump in that mode: what an fp32
//! tiny-cuda-nn backend is held to). Errors per family: the largest `max abs / peak` (the measure
//! the tolerance files limit) over the family's tensors, and in brackets the largest absolute error.
//!
//! Validation before timing: the two f64 dumps agree bit for bit in every tensor they share and
//! with a second evaluation (determinism); each f32 dump passes `fixtures/golden/tolerances-f32.toml`
//! against its f64 dump (with the kink analysis); every family has a tensor in every dump.
//!
//! Timing: in-memory dumps (`model::checkpoint::dump_with`, no file I/O), rounds alternating the
//! modes (A B C D A B C D …, `ORACLE_BENCH_ROUNDS`, default 5), median wall time per mode, plus the
//! CPU time (all threads) of that median run; threads = rayon's default (all cores).
//!
//! Run: `cargo bench --bench oracle` (`ORACLE_BENCH_PIXELS`, `ORACLE_BENCH_ROUNDS`).

mod common;
use common::env_count;
use std::path::PathBuf;
use std::time::Instant;
use xscale::io::compare::{compare, compare_tensors, Tolerances};
use xscale::io::tensors::TensorFile;
use xscale::model::checkpoint::{dump_with, Checkpoint};
use xscale::model::config::PositionMode;
use xscale::model::kink::DEFAULT_THRESHOLD;
use xscale::model::Batch;

/// Tensor families (as `fixtures/golden/golden_tool.py` groups the agreement tables): (label, name prefixes).
const FAMILIES: &[(&str, &[&str])] = &[
    ("fwd.grid_h / fwd.grid_d", &["fwd.grid_h", "fwd.grid_d"]),
    (
        "fwd.deform, fwd.deform_hidden.*",
        &["fwd.deform", "fwd.deform_hidden."],
    ),
    (
        "fwd.pooled, fwd.shader_in, fwd.sh",
        &["fwd.pooled", "fwd.shader_in", "fwd.sh"],
    ),
    (
        "fwd.shader_hidden.*, fwd.logits",
        &["fwd.shader_hidden.", "fwd.logits"],
    ),
    ("fwd.rgb, loss", &["fwd.rgb", "loss"]),
    (
        "grad.grid_h.table, grad.grid_d.table",
        &["grad.grid_h.table", "grad.grid_d.table"],
    ),
    (
        "grad.deform.*, grad.shader.*",
        &["grad.deform.", "grad.shader."],
    ),
    ("grad.appearance.codes", &["grad.appearance.codes"]),
    ("grad.batch.positions", &["grad.batch.positions"]),
    ("grad.batch.dirs", &["grad.batch.dirs"]),
];

fn family(name: &str) -> Option<usize> {
    FAMILIES.iter().position(|(_, prefixes)| {
        prefixes.iter().any(|p| {
            if p.ends_with('.') {
                name.starts_with(p)
            } else {
                name == *p
            }
        })
    })
}

/// Per family: (largest abs / peak, largest abs, tensors).
fn family_errors(reference: &TensorFile, other: &TensorFile) -> Vec<(f64, f64, usize)> {
    let mut out = vec![(0.0f64, 0.0f64, 0usize); FAMILIES.len()];
    for (name, a) in &reference.tensors {
        let (Some(f), Some(b)) = (family(name), other.tensors.get(name)) else {
            continue;
        };
        let st = compare_tensors(a, b, None);
        let e = &mut out[f];
        e.0 = e.0.max(st.max_rel_peak);
        e.1 = e.1.max(st.max_abs);
        e.2 += 1;
    }
    out
}

/// CPU time of this process so far (all threads), from /proc/self/task/*/schedstat.
fn cpu_seconds() -> Option<f64> {
    let mut ns = 0u64;
    for e in std::fs::read_dir("/proc/self/task").ok()? {
        let s = std::fs::read_to_string(e.ok()?.path().join("schedstat")).ok()?;
        ns += s.split_whitespace().next()?.parse::<u64>().ok()?;
    }
    Some(ns as f64 * 1e-9)
}

fn fmt(x: f64) -> String {
    if x == 0.0 {
        "0".into()
    } else {
        format!("{x:.2e}")
    }
}

struct Mode {
    label: &'static str,
    ckpt: Checkpoint,
    f64_kinks: Option<Option<f64>>, // Some(kinks) = f64 dump with that kink setting; None = f32
}

impl Mode {
    fn dump(&self, batch: &Batch) -> TensorFile {
        match self.f64_kinks {
            Some(k) => dump_with::<f64>(&self.ckpt, batch, k).unwrap(),
            None => dump_with::<f32>(&self.ckpt, batch, None).unwrap(),
        }
    }
}

fn main() {
    let pixels = env_count("ORACLE_BENCH_PIXELS", 4096);
    let rounds = env_count("ORACLE_BENCH_ROUNDS", 5);
    let golden = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("fixtures/golden");
    let ckpt = Checkpoint::load(golden.join("cpu-t10/checkpoint.safetensors")).unwrap();
    let views = ckpt.model.appearance_views();
    let batch = Batch::random(7, pixels, 4, views, 0.1);
    let mut tcnn = ckpt.clone();
    tcnn.model.cfg.positions = PositionMode::Tcnn;
    let modes = [
        Mode {
            label: "f64 + kinks",
            ckpt: ckpt.clone(),
            f64_kinks: Some(Some(DEFAULT_THRESHOLD)),
        },
        Mode {
            label: "f64",
            ckpt: ckpt.clone(),
            f64_kinks: Some(None),
        },
        Mode {
            label: "f32",
            ckpt: ckpt.clone(),
            f64_kinks: None,
        },
        Mode {
            label: "f32 tcnn",
            ckpt: tcnn.clone(),
            f64_kinks: None,
        },
    ];

    // ---- validation
    let tol = Tolerances::read(golden.join("tolerances-f32.toml")).unwrap();
    let ref64 = dump_with::<f64>(&ckpt, &batch, Some(DEFAULT_THRESHOLD)).unwrap();
    let ref64_tcnn = dump_with::<f64>(&tcnn, &batch, Some(DEFAULT_THRESHOLD)).unwrap();
    let dumps: Vec<TensorFile> = modes.iter().map(|m| m.dump(&batch)).collect();
    for (name, t) in &dumps[1].tensors {
        assert_eq!(
            Some(t),
            ref64.tensors.get(name),
            "f64 without kinks differs from f64 with kinks in {name}"
        );
    }
    assert!(
        dumps[0] == ref64,
        "two f64 dumps of the same input differ (determinism)"
    );
    let references = [&ref64, &ref64, &ref64, &ref64_tcnn];
    let mut errors = Vec::new();
    for (m, (d, r)) in modes.iter().zip(dumps.iter().zip(references)) {
        if m.f64_kinks.is_none() {
            let rep = compare(r, d, &tol);
            assert_eq!(
                rep.exit_code(),
                0,
                "{}: fails tolerances-f32.toml:\n{}",
                m.label,
                rep.to_table()
            );
        }
        let e = family_errors(r, d);
        for (f, (label, _)) in FAMILIES.iter().enumerate() {
            assert!(e[f].2 > 0, "{}: no tensor of family {label}", m.label);
        }
        errors.push(e);
    }
    let kink_pixels = ref64
        .get("kink.margin")
        .unwrap()
        .to_f64()
        .unwrap()
        .iter()
        .filter(|&&m| m <= DEFAULT_THRESHOLD)
        .count();

    // ---- timing: alternating rounds.
    let mut times: Vec<Vec<(f64, f64)>> = vec![Vec::new(); modes.len()];
    for m in &modes {
        std::hint::black_box(m.dump(&batch)); // warm-up
    }
    for _ in 0..rounds {
        for (i, m) in modes.iter().enumerate() {
            let c = cpu_seconds().unwrap_or(f64::NAN);
            let t = Instant::now();
            std::hint::black_box(m.dump(&batch));
            let w = t.elapsed().as_secs_f64();
            times[i].push((w, cpu_seconds().unwrap_or(f64::NAN) - c));
        }
    }
    let median = |v: &Vec<(f64, f64)>| {
        let mut s = v.clone();
        s.sort_by(|a, b| a.0.total_cmp(&b.0));
        s[s.len() / 2]
    };
    let med: Vec<(f64, f64)> = times.iter().map(median).collect();

    let load = std::fs::read_to_string("/proc/loadavg").unwrap_or_default();
    println!(
        "oracle path: golden cpu-t10 checkpoint, {pixels} pixels x 4 sub-samples, {} threads, {rounds} alternating rounds; load average {}",
        rayon::current_num_threads(),
        load.split_whitespace().take(3).collect::<Vec<_>>().join(" ")
    );
    println!(
        "{kink_pixels} kink pixels at the default threshold; errors: max abs/peak over the family's tensors [max abs], against the f64 dump (f32 tcnn: against the f64 dump in positions mode tcnn)\n"
    );
    let mut header = "| |".to_string();
    let mut sep = "|---|".to_string();
    for m in &modes {
        header.push_str(&format!(" {} |", m.label));
        sep.push_str("---:|");
    }
    println!("{header}\n{sep}");
    let mut row = "| time per dump, ms (CPU ms) |".to_string();
    for (w, c) in &med {
        row.push_str(&format!(" {:.0} ({:.0}) |", w * 1e3, c * 1e3));
    }
    println!("{row}");
    let mut row = "| time / f64 |".to_string();
    for (w, _) in &med {
        row.push_str(&format!(" {:.2} |", w / med[1].0));
    }
    println!("{row}");
    for (f, (label, _)) in FAMILIES.iter().enumerate() {
        let mut row = format!("| {label} |");
        for e in &errors {
            let (rp, abs, _) = e[f];
            if rp == 0.0 && abs == 0.0 {
                row.push_str(" 0 |");
            } else {
                row.push_str(&format!(" {} [{}] |", fmt(rp), fmt(abs)));
            }
        }
        println!("{row}");
    }
    common::emit_json(serde_json::json!({
        "pixels": pixels, "rounds": rounds, "threads": rayon::current_num_threads(),
        "kink_pixels": kink_pixels,
        "modes": modes.iter().map(|m| m.label).collect::<Vec<_>>(),
        "wall_ms": med.iter().map(|(w, _)| w * 1e3).collect::<Vec<_>>(),
        "cpu_ms": med.iter().map(|(_, c)| c * 1e3).collect::<Vec<_>>(),
        "over_f64": med.iter().map(|(w, _)| w / med[1].0).collect::<Vec<_>>(),
        "families": FAMILIES.iter().enumerate().map(|(f, (label, _))| serde_json::json!({
            "family": label,
            "max_abs_over_peak": errors.iter().map(|e| e[f].0).collect::<Vec<_>>(),
            "max_abs": errors.iter().map(|e| e[f].1).collect::<Vec<_>>(),
        })).collect::<Vec<_>>(),
    }));
}
