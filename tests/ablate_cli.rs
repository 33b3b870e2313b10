//! `xscale ablate` and `xscale decimate` end to end on the bundled `tiny` fixture, and `xscale
//! bench-geometry` (refinement on and off) on the `tiny` synthetic scene (a handful of steps: this
//! checks the plumbing, the reuse of runs and the tables, not the numbers).

use std::path::{Path, PathBuf};
use std::process::Command;

#[path = "common/metrics.rs"]
mod metrics;
#[path = "common/signal.rs"]
mod signal;

fn fixture() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("fixtures/tiny")
}

fn tmp(name: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("xscale-test-ablate-{}-{name}", std::process::id()));
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

/// `xscale ablate` on the `tiny` fixture into `out`, `steps` steps of 256 pixels, quiet.
fn ablate_args(out: &Path, steps: &str) -> Vec<String> {
    let (scene, out) = (fixture(), out.to_str().unwrap().to_string());
    let args = [
        "ablate",
        "--scene",
        scene.to_str().unwrap(),
        "--out",
        &out,
        "--preset",
        "tiny",
    ];
    let rest = ["--steps", steps, "--batch", "256", "-q"];
    args.iter().chain(&rest).map(|a| a.to_string()).collect()
}

/// `xscale ablate` as [`ablate_args`] says, with `extra` options.
fn run_ablate(out: &Path, steps: &str, extra: &[&str]) -> (bool, String, String) {
    let base = ablate_args(out, steps);
    let args: Vec<&str> = base
        .iter()
        .map(String::as_str)
        .chain(extra.iter().copied())
        .collect();
    xscale(&args)
}

#[test]
fn ablate_writes_the_table_for_every_variant() {
    let out = tmp("run");
    let scene = fixture();
    let (ok, stdout, err) = run_ablate(&out, "4", &[]);
    assert!(ok, "{err}");
    let md = std::fs::read_to_string(out.join("ablation.md")).unwrap();
    assert_eq!(stdout, md, "the table is printed too");
    let variants = [
        "full",
        "no_deform",
        "no_multisampling",
        "mesh10",
        "vertex",
        "vertex_subdiv",
    ];
    assert!(md.contains("| ulr |"), "ulr row missing:\n{md}");
    for v in variants {
        assert!(md.contains(&format!("| {v} |")), "{v} row missing:\n{md}");
        // Each variant is an ordinary run folder.
        assert!(out.join(v).join("checkpoint.safetensors").exists(), "{v}");
        assert!(out.join(v).join("eval.json").exists(), "{v}");
    }
    let json: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("ablation.json")).unwrap()).unwrap();
    let results = json["results"].as_array().unwrap();
    assert_eq!(results.len(), 7);
    assert_eq!(json["steps"], 4);
    let get = |name: &str| results.iter().find(|r| r["name"] == name).unwrap();
    for r in results {
        let p = r["mean"]["psnr_masked"].as_f64().unwrap();
        assert!(p.is_finite() && p > 5.0, "{r}");
        let steps = if r["name"] == "ulr" { 0 } else { 4 };
        assert_eq!(r["steps"], steps);
    }
    // The switches took effect.
    assert_eq!(get("no_multisampling")["gamma"], 1);
    assert_eq!(get("no_deform")["deform"], false);
    assert_eq!(get("vertex")["featurization"], "vertex");
    // The decimated mesh has ~10% of the 2118 faces; the subdivided one 4^k times as many.
    let f10 = get("mesh10")["mesh_faces"].as_u64().unwrap();
    assert!((190..=233).contains(&f10), "{f10}");
    let fs = get("vertex_subdiv")["mesh_faces"].as_u64().unwrap();
    assert!(fs >= 4 * 2118 && fs % 2118 == 0, "{fs}");
    // The vertex baselines' parameter counts are within 2× of the full model's.
    for v in ["vertex", "vertex_subdiv"] {
        let r = get(v)["params_ratio"].as_f64().unwrap();
        assert!((0.5..=2.0).contains(&r), "{v}: {r}");
    }
    // Unknown variants are named.
    let (ok, _, err) = xscale(&[
        "ablate",
        "--scene",
        scene.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
        "--variants",
        "full,nope",
    ]);
    assert!(!ok && err.contains("nope"), "{err}");
    let _ = std::fs::remove_dir_all(&out);
}

fn results(out: &Path) -> Vec<String> {
    let json: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("ablation.json")).unwrap()).unwrap();
    json["results"]
        .as_array()
        .unwrap()
        .iter()
        .map(|r| r["name"].as_str().unwrap().to_string())
        .collect()
}

#[test]
fn an_earlier_ablation_is_refused_kept_or_replaced() {
    let out = tmp("again");
    let ablate = |extra: &[&str]| run_ablate(&out, "4", extra);
    let (ok, _, err) = ablate(&["--variants", "full,ulr"]);
    assert!(ok, "{err}");
    let first = std::fs::read(out.join("ablation.json")).unwrap();
    // Run again: refused before anything is trained or written.
    let (ok, _, err) = ablate(&["--variants", "vertex"]);
    assert!(
        !ok && err.contains("--append") && err.contains("full, ulr"),
        "{err}"
    );
    assert_eq!(std::fs::read(out.join("ablation.json")).unwrap(), first);
    assert!(!out.join("vertex").exists());
    // --append adds a variant to the table, in table order; its parameter budget is matched to
    // the kept full model's.
    let (ok, stdout, err) = ablate(&["--variants", "vertex", "--append"]);
    assert!(ok, "{err}");
    assert_eq!(results(&out), ["full", "vertex", "ulr"]);
    assert!(
        stdout.contains("| full |") && stdout.contains("| vertex |"),
        "{stdout}"
    );
    let json: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("ablation.json")).unwrap()).unwrap();
    let ratio = json["results"][1]["params_ratio"].as_f64().unwrap();
    assert!((0.5..=2.0).contains(&ratio), "{ratio}");
    // A different base configuration or step budget cannot join the table.
    let (ok, _, err) = ablate(&["--variants", "ulr", "--append", "--seed", "9"]);
    assert!(!ok && err.contains("train.seed = 9"), "{err}");
    let (ok, _, err) = run_ablate(&out, "5", &["--variants", "ulr", "--append"]);
    assert!(!ok && err.contains("ran 4 steps"), "{err}");
    // Nor another --ratio: mesh10 would be a 50 % mesh judged by the Table 5 (10 %) claim.
    let (ok, _, err) = ablate(&["--variants", "mesh10", "--append", "--ratio", "0.5"]);
    assert!(
        !ok && err.contains("--ratio 0.1") && err.contains("share it"),
        "{err}"
    );
    assert!(!out.join("mesh10").exists());
    let json: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("ablation.json")).unwrap()).unwrap();
    assert_eq!(json["ratio"], 0.1);
    // A bad option of a later variant is a usage error: nothing trains.
    let (ok, _, err) = ablate(&["--variants", "full,mesh10", "--ratio", "0", "--overwrite"]);
    assert!(!ok && err.contains("'0' for '--ratio"), "{err}");
    assert_eq!(results(&out), ["full", "vertex", "ulr"]);
    // --overwrite starts a new table.
    let (ok, _, err) = ablate(&["--variants", "ulr", "--overwrite"]);
    assert!(ok, "{err}");
    assert_eq!(results(&out), ["ulr"]);
    let _ = std::fs::remove_dir_all(&out);
}

#[test]
fn the_table_is_written_after_every_variant_and_sigterm_stops_between_steps() {
    // SIGTERM once the first report appears: the variant in training stops at its next step,
    // the table holds the variants finished so far (not all three), and the command says how to
    // finish; that command completes the table, continuing the variant stopped halfway.
    let out = tmp("partial");
    let base = ablate_args(&out, "1000");
    let child = Command::new(env!("CARGO_BIN_EXE_xscale"))
        .args(&base)
        .args(["--variants", "full,no_deform,no_multisampling"])
        .stdout(std::process::Stdio::null())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    let t0 = std::time::Instant::now();
    while !out.join("ablation.json").exists() {
        assert!(t0.elapsed().as_secs() < 300, "no ablation.json after 300 s");
        std::thread::sleep(std::time::Duration::from_millis(10));
    }
    // Once the second variant has logged a step, so that it is stopped halfway.
    let second = out.join("no_deform/metrics.jsonl");
    while !std::fs::read_to_string(&second).is_ok_and(|t| !t.is_empty()) {
        assert!(
            t0.elapsed().as_secs() < 300,
            "no_deform never logged a step"
        );
        std::thread::sleep(std::time::Duration::from_millis(2));
    }
    signal::terminate(&child);
    let done = child.wait_with_output().unwrap();
    let err = String::from_utf8_lossy(&done.stderr);
    assert_eq!(done.status.code(), Some(130), "{err}");
    let names = results(&out);
    assert!(
        !names.is_empty() && names.len() < 3 && names[0] == "full",
        "{names:?}"
    );
    assert!(std::fs::read_to_string(out.join("ablation.md"))
        .unwrap()
        .contains("| full |"));
    let rest = err
        .split("--append --variants ")
        .nth(1)
        .unwrap_or_else(|| panic!("{err}"))
        .trim()
        .to_string();
    // The variant stopped halfway has a checkpoint short of its last step…
    let stopped = rest.split(',').next().unwrap().to_string();
    let ckpt = out.join(&stopped).join("checkpoint.safetensors");
    let at = xscale::io::tensors::TensorFile::read_only(&ckpt, |_| false)
        .ok()
        .map(|f| f.meta("step").unwrap().parse::<u64>().unwrap());
    let (ok, stdout, err) = run_ablate(&out, "1000", &["--append", "--variants", &rest]);
    assert!(ok, "{err}");
    assert_eq!(results(&out), ["full", "no_deform", "no_multisampling"]);
    assert!(stdout.contains("| no_multisampling |"), "{stdout}");
    // …and --append continued it from there instead of training it again: its metrics keep the
    // stop's checkpoint line and run on to step 1000 with the time counted on.
    if let Some(k) = at.filter(|&k| k < 1000) {
        let run = out.join(&stopped);
        let saved = metrics::checkpoints(&run);
        assert_eq!(
            saved,
            [k, 1000],
            "{stopped} was not continued from step {k}"
        );
        assert!(metrics::elapsed_runs_on(&run, 2));
    } else {
        panic!("{stopped}: no checkpoint short of step 1000 after the stop ({at:?})");
    }
    let _ = std::fs::remove_dir_all(&out);
}

#[test]
fn decimate_and_subdivide_commands() {
    let out = tmp("mesh");
    std::fs::create_dir_all(&out).unwrap();
    let src = fixture().join("mesh.ply");
    let dst = out.join("m10.ply");
    let (ok, stdout, err) = xscale(&[
        "decimate",
        "--in",
        src.to_str().unwrap(),
        "--ratio",
        "0.1",
        "--out",
        dst.to_str().unwrap(),
    ]);
    assert!(ok, "{err}");
    assert!(stdout.contains("2118 →"), "{stdout}");
    let (m, _) = xscale::scene::mesh::load_mesh(&dst).unwrap();
    assert!(
        (190..=233).contains(&m.triangles.len()),
        "{}",
        m.triangles.len()
    );
    let sub = out.join("s.obj");
    let (ok, _, err) = xscale(&[
        "subdivide",
        "--in",
        dst.to_str().unwrap(),
        "--levels",
        "1",
        "--out",
        sub.to_str().unwrap(),
    ]);
    assert!(ok, "{err}");
    let (s, _) = xscale::scene::mesh::load_mesh(&sub).unwrap();
    assert_eq!(s.triangles.len(), 4 * m.triangles.len());
    // Bad ratio and bad extension are named errors.
    let (ok, _, err) = xscale(&[
        "decimate",
        "--in",
        src.to_str().unwrap(),
        "--ratio",
        "0",
        "--out",
        dst.to_str().unwrap(),
    ]);
    assert!(!ok && err.contains("ratio"), "{err}");
    let (ok, _, err) = xscale(&[
        "decimate",
        "--in",
        src.to_str().unwrap(),
        "--ratio",
        "0.5",
        "--out",
        "x.stl",
    ]);
    assert!(!ok && err.contains(".ply"), "{err}");
    let _ = std::fs::remove_dir_all(&out);
}

/// A mesh output path that is a symlink is written at the link's target (the link kept); an
/// output that is the input mesh (also through a link) is refused with nothing written; a
/// subdivision larger than the memory the process may take is refused before allocating.
#[cfg(unix)]
#[test]
fn mesh_outputs_follow_links_and_never_replace_their_input() {
    let out = tmp("mesh-out");
    let (target, link) = (out.join("target.ply"), out.join("link.ply"));
    std::fs::create_dir_all(&out).unwrap();
    std::fs::write(&target, b"old").unwrap();
    let input = out.join("in.ply");
    let before = std::fs::read(fixture().join("mesh.ply")).unwrap();
    std::fs::write(&input, &before).unwrap();
    std::os::unix::fs::symlink("target.ply", &link).unwrap();
    let i = input.to_str().unwrap();
    let decimate = |to: &Path| {
        let to = to.to_str().unwrap();
        xscale(&["decimate", "--in", i, "--ratio", "0.5", "--out", to])
    };
    let (ok, _, err) = decimate(&link);
    assert!(ok, "{err}");
    assert!(std::fs::symlink_metadata(&link)
        .unwrap()
        .file_type()
        .is_symlink());
    let (m, _) = xscale::scene::mesh::load_mesh(&target).unwrap();
    assert!(m.triangles.len() > 1000, "{}", m.triangles.len());
    // The input as --out, by its own name or through a link: refused, the input untouched.
    let in_link = out.join("in-link.ply");
    std::os::unix::fs::symlink(&input, &in_link).unwrap();
    for to in [&input, &in_link] {
        let (ok, _, err) = decimate(to);
        assert!(
            !ok && err.contains("--out is the input mesh (--in)"),
            "{err}"
        );
        let (ok, _, err) = xscale(&[
            "subdivide",
            "--in",
            i,
            "--levels",
            "1",
            "--out",
            to.to_str().unwrap(),
        ]);
        assert!(
            !ok && err.contains("--out is the input mesh (--in)"),
            "{err}"
        );
    }
    assert_eq!(std::fs::read(&input).unwrap(), before);
    // 6 levels of the fixture's 2,118 faces (8.7 M faces, about 0.45 GB at the peak) under a
    // 300 MB address-space limit: an error naming the estimate (it aborted, exit 134).
    let sub = out.join("big.ply");
    let o = Command::new("sh")
        .arg("-c")
        .arg(format!(
            "ulimit -v 300000; exec '{}' subdivide --in '{i}' --levels 6 --out '{}'",
            env!("CARGO_BIN_EXE_xscale"),
            sub.display()
        ))
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(2), "{err}");
    assert!(
        err.contains("subdivide --levels 6: 8675328 faces would take about")
            && err.contains("use fewer --levels"),
        "{err}"
    );
    assert!(!sub.exists());
    let _ = std::fs::remove_dir_all(&out);
}

/// `bench-geometry`'s values are checked before the scene is synthesised or a proxy built: a
/// value out of range is a usage error (exit 64), a proxy listed twice (`--rms 0,0`, which
/// trained and listed exact_xi/exact_noxi twice) a run-time one (exit 2), nothing written.
#[test]
fn bench_geometry_checks_its_values_up_front() {
    let out = tmp("geo-bad");
    let o = out.to_str().unwrap();
    let run = |extra: &[&str]| {
        let args = ["bench-geometry", "--scene-preset", "tiny", "--out", o, "-q"];
        let r = Command::new(env!("CARGO_BIN_EXE_xscale"))
            .args(args)
            .args(extra)
            .output()
            .unwrap();
        (
            r.status.code(),
            String::from_utf8_lossy(&r.stderr).into_owned(),
        )
    };
    for (extra, code, says) in [
        (
            &["--rms", "0,0"][..],
            2,
            "proxy exact (the exact true surface) is listed twice",
        ),
        (&["--rms", "0.1,0.3,0.10"][..], 2, "proxy rms0.1"),
        (
            &["--decimate", "2"][..],
            64,
            "'2' for '--decimate <DECIMATE>': must be in [0, 1] (0: none)",
        ),
        (
            &["--rms=-1"][..],
            64,
            "'-1' for '--rms <RMS>...': must be a number ≥ 0",
        ),
        (&["--rms", "0,nan"][..], 64, "--rms"),
    ] {
        let (c, err) = run(extra);
        assert_eq!(c, Some(code), "{extra:?}: {err}");
        assert!(err.contains(says), "{extra:?}: {err}");
        assert!(!out.exists(), "{extra:?}: wrote {}", out.display());
    }
}

#[test]
fn bench_geometry_trains_refined_and_fixed_variants_and_reuses_them() {
    let out = tmp("geo");
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

/// The vertex baselines under the default `cpu` preset, whose footprint level weighting a vertex
/// model cannot have: the variant turns it off (it trained, then failed reading its own
/// checkpoint back: "model.level_weight weights hash-grid levels").
#[test]
fn vertex_variants_run_under_the_cpu_preset() {
    let out = tmp("cpu-vertex");
    let scene = fixture();
    let args = [
        "ablate",
        "--scene",
        scene.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
        "--preset",
        "cpu",
        "--variants",
        "vertex",
        "--steps",
        "2",
        "--batch",
        "256",
        "-q",
    ];
    let (ok, _, err) = xscale(&args);
    assert!(ok, "{err}");
    let md = std::fs::read_to_string(out.join("ablation.md")).unwrap();
    assert!(md.contains("| vertex |"), "{md}");
    let cfg = std::fs::read_to_string(out.join("vertex/config.toml")).unwrap();
    assert!(cfg.contains("level_weight = \"none\""), "{cfg}");
    let _ = std::fs::remove_dir_all(&out);
}

/// A `bench-geometry` run killed outright continues from its latest periodic checkpoint; Ctrl-C /
/// SIGTERM stops it with a checkpoint (exit 130); each time the same command continues the run
/// rather than training it again.
#[test]
fn bench_geometry_continues_a_stopped_run() {
    let out = tmp("geo-stop");
    let o = out.to_str().unwrap().to_string();
    let args = [
        "bench-geometry",
        "--scene-preset",
        "tiny",
        "--out",
        &o,
        "--preset",
        "tiny",
        "--steps",
        "5000",
        "--rms",
        "0",
        "--decimate",
        "0",
        "--deform",
        "off",
        "--refine",
        "off",
        "--samples",
        "2000",
        "-q",
    ];
    let spawn = || {
        Command::new(env!("CARGO_BIN_EXE_xscale"))
            .args(args)
            .stdout(std::process::Stdio::null())
            .stderr(std::process::Stdio::piped())
            .spawn()
            .unwrap()
    };
    let run = out.join("runs/exact_noxi");
    // Wait until the run's metrics hold a checkpoint past `after`.
    let wait_for_checkpoint_after = |after: u64| {
        let t0 = std::time::Instant::now();
        while !std::fs::read_to_string(run.join("metrics.jsonl")).is_ok_and(|t| {
            t.lines().any(|l| {
                let j: serde_json::Value = serde_json::from_str(l).unwrap_or_default();
                j["checkpoint"] == true && j["step"].as_u64().is_some_and(|k| k > after)
            })
        }) {
            assert!(
                t0.elapsed().as_secs() < 300,
                "no checkpoint after step {after}"
            );
            std::thread::sleep(std::time::Duration::from_millis(2));
        }
    };
    // SIGKILL once the first periodic checkpoint (a tenth of the run apart, at least 1,000
    // steps) is written: the same command continues from the latest one, keeping the metrics
    // written before it (a fresh run would rewrite the first line with another elapsed_s).
    let mut child = spawn();
    wait_for_checkpoint_after(0);
    child.kill().unwrap();
    child.wait().unwrap();
    let first_line = metrics::lines(&run)[0].to_string();
    let killed_at = *metrics::checkpoints(&run).last().unwrap();
    assert!(killed_at < 5000, "finished before the kill");
    // SIGTERM: a checkpoint at the next step and exit 130.
    let child = spawn();
    wait_for_checkpoint_after(killed_at);
    signal::terminate(&child);
    let done = child.wait_with_output().unwrap();
    let err = String::from_utf8_lossy(&done.stderr);
    assert_eq!(done.status.code(), Some(130), "{err}");
    assert!(err.contains("run the same command again"), "{err}");
    assert!(!out.join("geometry.csv").exists());
    let stopped = metrics::checkpoints(&run);
    assert!(
        stopped[0] == 1000
            && stopped.contains(&killed_at)
            && (killed_at + 1..5000).contains(stopped.last().unwrap()),
        "not continued after the kill, or not stopped halfway: {stopped:?}"
    );
    let (ok, _, err) = xscale(&args);
    assert!(ok, "{err}");
    assert!(out.join("geometry.csv").is_file());
    let all = metrics::checkpoints(&run);
    assert!(
        all.starts_with(&stopped)
            && all.last() == Some(&5000)
            && all.windows(2).all(|w| w[0] < w[1]),
        "not continued: {stopped:?} then {all:?}"
    );
    assert_eq!(
        metrics::lines(&run)[0].to_string(),
        first_line,
        "restarted from step 0"
    );
    assert!(metrics::elapsed_runs_on(&run, 5));
    let _ = std::fs::remove_dir_all(&out);
}

/// Ctrl-C / SIGTERM while `bench-geometry --scene-preset` generates its scene stops it after the
/// view being rendered, saying what is left, exit 3 (nothing trained); the same command then
/// generates the unfinished scene again rather than reusing it. (The signal killed it without a
/// word, and the rerun took the unfinished scene, without cameras, for a finished one.)
#[test]
fn bench_geometry_stops_between_views_of_its_scene() {
    let out = tmp("geo-synth-stop");
    let o = out.to_str().unwrap();
    let args = [
        "bench-geometry",
        "--scene-preset",
        "small",
        "--out",
        o,
        "--steps",
        "5",
        "-q",
    ];
    let first = out.join("scene/images/0000.png");
    // Terminate the command once the scene's first view is written.
    let stop_after_first_view = || {
        let child = Command::new(env!("CARGO_BIN_EXE_xscale"))
            .args(args)
            .stdout(std::process::Stdio::null())
            .stderr(std::process::Stdio::piped())
            .spawn()
            .unwrap();
        let t0 = std::time::Instant::now();
        while !first.is_file() {
            assert!(t0.elapsed().as_secs() < 120, "no view written");
            std::thread::sleep(std::time::Duration::from_millis(10));
        }
        signal::terminate(&child);
        let done = child.wait_with_output().unwrap();
        let err = String::from_utf8_lossy(&done.stderr).into_owned();
        assert_eq!(done.status.code(), Some(3), "{err}");
        assert!(
            err.contains("interrupted: stopped after")
                && err.contains("holds an unfinished scene")
                && err.contains("run the same command again"),
            "{err}"
        );
        assert!(!out.join("scene/scene.toml").exists(), "finished: {err}");
        assert!(!out.join("runs").exists(), "trained: {err}");
    };
    stop_after_first_view();
    // The rerun writes the scene again (the first view included), not taking it as finished.
    std::fs::remove_file(&first).unwrap();
    stop_after_first_view();
    let _ = std::fs::remove_dir_all(&out);
}

/// `vertex_subdiv` checks that its subdivided mesh fits in memory before subdividing, as `xscale
/// subdivide` does, and with `--subdivide` before the first variant trains: 6 levels of the
/// fixture's 2,118 faces (8.7 M faces, about 0.42 GB at the peak) under a 500 MB address-space
/// limit is an error naming the estimate (it aborted: `memory allocation of … bytes failed`,
/// exit 134, after training the variants before it).
#[test]
fn vertex_subdiv_checks_its_memory_before_subdividing() {
    let out = tmp("subdiv-memory");
    let args: Vec<String> = ablate_args(&out, "5")
        .into_iter()
        .chain(["--variants", "full,vertex_subdiv", "--subdivide", "6"].map(String::from))
        .chain(["--threads", "2"].map(String::from))
        .map(|a| format!("'{a}'"))
        .collect();
    let o = Command::new("sh")
        .arg("-c")
        .arg(format!(
            "ulimit -v 500000; exec '{}' {}",
            env!("CARGO_BIN_EXE_xscale"),
            args.join(" ")
        ))
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(2), "{err}");
    assert!(
        err.contains("vertex_subdiv: --subdivide 6: 8675328 faces would take about")
            && err.contains("give --subdivide fewer levels"),
        "{err}"
    );
    assert!(!out.join("full").exists(), "a variant trained first");
    assert!(!out.join("meshes/subdivided_6.ply").exists());
    let _ = std::fs::remove_dir_all(&out);
}
