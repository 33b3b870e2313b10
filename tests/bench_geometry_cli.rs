//! `xscale bench-geometry` end to end on the `tiny` synthetic scene with refinement on and off (a
//! handful of steps: this checks the plumbing, the reuse of runs and the table, not the numbers;
//! the measured benchmark is docs/geometry.md).

use std::path::PathBuf;
use std::process::Command;

fn tmp(name: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("xscale-test-geo-{}-{name}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    d
}

fn xscale(args: &[&str]) -> (bool, String, String) {
    let out = Command::new(env!("CARGO_BIN_EXE_xscale"))
        .args(args)
        .output()
        .unwrap();
    (
        out.status.success(),
        String::from_utf8_lossy(&out.stdout).into_owned(),
        String::from_utf8_lossy(&out.stderr).into_owned(),
    )
}

#[test]
fn bench_geometry_trains_refined_and_fixed_variants_and_reuses_them() {
    let out = tmp("run");
    std::fs::create_dir_all(&out).unwrap();
    let cfg = out.join("refine.toml");
    // The mesh moves from step 1 to 7 of 8, updated every 2 steps with a rate large enough to
    // move it measurably.
    std::fs::write(
        &cfg,
        "[model.refine]\nstart = 0.1\nstop = 0.9\nupdate_every = 2\nlevels = 2\nlr = 1e-2\nlr_end = 1e-3\n",
    )
    .unwrap();
    let o = out.to_str().unwrap();
    // Both list spellings: "0 0.3" (several values) and "on,off" (comma-separated).
    let args = [
        "bench-geometry",
        "--scene-preset",
        "tiny",
        "--out",
        o,
        "--preset",
        "tiny",
        "--config",
        cfg.to_str().unwrap(),
        "--steps",
        "8",
        "--rms",
        "0",
        "0.3",
        "--decimate",
        "0",
        "--deform",
        "off",
        "--refine",
        "on,off",
        "--samples",
        "3000",
    ];
    let (ok, _, err) = xscale(&args);
    assert!(ok, "{err}");
    let csv = std::fs::read_to_string(out.join("geometry.csv")).unwrap();
    let mut lines = csv.lines();
    let header: Vec<&str> = lines.next().unwrap().split(',').collect();
    let col = |name: &str| header.iter().position(|h| *h == name).unwrap();
    let rows: Vec<Vec<String>> = lines
        .map(|l| l.split(',').map(str::to_string).collect())
        .collect();
    assert_eq!(rows.len(), 4, "{csv}");
    for r in &rows {
        let refined = &r[col("refine")];
        let rms = &r[col("refined_rms")];
        let psnr: f64 = r[col("psnr_masked")].parse().unwrap();
        assert!(psnr.is_finite() && psnr > 0.0, "{csv}");
        if refined == "true" {
            // The refined mesh was written and measured, and it moved off the exact surface.
            let rms: f64 = rms.parse().unwrap_or_else(|_| panic!("{csv}"));
            assert!(rms.is_finite(), "{csv}");
            if r[col("proxy")] == "exact" {
                assert!(rms > 0.0, "the exact mesh did not move: {csv}");
            }
        } else {
            assert_eq!(rms, "NaN", "no refined mesh: {csv}");
        }
    }
    for v in ["exact_noxi_refine", "rms0.3_noxi_refine"] {
        assert!(
            out.join("runs").join(v).join("refined.ply").is_file(),
            "{v}"
        );
    }
    // A second call reuses every run and writes the same table.
    let (ok, _, err) = xscale(&args);
    assert!(ok, "{err}");
    let reused = err
        .lines()
        .filter(|l| l.starts_with("== ") && l.contains(": reusing "))
        .count();
    assert_eq!(reused, 4, "{err}");
    assert_eq!(
        std::fs::read_to_string(out.join("geometry.csv")).unwrap(),
        csv
    );
    // A typo in a switch is an error naming the values it takes.
    let mut bad = args.to_vec();
    let i = bad.iter().position(|a| *a == "on,off").unwrap();
    bad[i] = "on,of";
    let (ok, _, err) = xscale(&bad);
    assert!(!ok && err.contains("possible values"), "{err}");
    let _ = std::fs::remove_dir_all(&out);
}
