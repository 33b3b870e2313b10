//! `xscale bench-quality` on the bundled fixture: a row per evaluation (budget·2^-k, k = 5..0)
//! with growing wall time, the ULR row, the plot, and a clear error for an unknown configuration.

use std::path::{Path, PathBuf};
use xscale::experiments::bench_quality::{bench_quality, read_rows, replot, Existing};

/// A fresh output folder for this test process.
fn fresh_out(tag: &str) -> PathBuf {
    let out = std::env::temp_dir().join(format!("xscale-bq{tag}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&out);
    out
}

/// `tiny` and `ulr` on the bundled fixture for 0.6 s each into `out`; `stop` as Ctrl-C.
fn tiny_and_ulr(
    out: &Path,
    stop: &dyn Fn() -> bool,
) -> (Vec<xscale::experiments::bench_quality::Row>, Vec<String>) {
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let configs = ["tiny".to_string(), "ulr".to_string()];
    bench_quality(
        &root.join("fixtures/tiny"),
        out,
        &configs,
        0.01,
        Existing::Refuse,
        &mut |_| {},
        stop,
    )
    .unwrap()
}

#[test]
fn bench_quality_writes_rows_and_the_plot() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let out = fresh_out("");
    let (rows, _) = tiny_and_ulr(&out, &|| false);
    let tiny: Vec<_> = rows.iter().filter(|r| r.config == "tiny").collect();
    assert_eq!(tiny.len(), 6);
    // Evaluations 19 ms apart at first: on a loaded machine two can fall within one step (the
    // same step and time, a fresh clone's test run saw it), so in order, not strictly, and the
    // budget's run as a whole moves on.
    assert!(tiny
        .windows(2)
        .all(|w| w[1].wall_s >= w[0].wall_s && w[1].step >= w[0].step));
    assert!(tiny[5].step > tiny[0].step && tiny[5].wall_s > tiny[0].wall_s);
    assert!(tiny
        .iter()
        .all(|r| r.psnr_masked.is_finite() && r.psnr_masked > 10.0));
    let ulr: Vec<_> = rows.iter().filter(|r| r.config == "ulr").collect();
    assert_eq!(ulr.len(), 1);
    // ULR trains nothing: 0 training seconds (its render and scores are evaluation, not counted,
    // as for the learned configurations; it used to hold them).
    assert_eq!((ulr[0].wall_s, ulr[0].step), (0.0, 0));
    let csv = std::fs::read_to_string(out.join("bench.csv")).unwrap();
    assert_eq!(csv.lines().count(), 1 + 7);
    assert!(csv.starts_with("config,setup_s,wall_s,step,psnr_masked,ssim_masked"));
    assert!(std::fs::metadata(out.join("pareto.png")).unwrap().len() > 1000);
    let e = bench_quality(
        &root.join("fixtures/tiny"),
        &out,
        &["cpux".into()],
        0.01,
        Existing::Overwrite,
        &mut |_| {},
        &|| false,
    )
    .unwrap_err();
    assert!(
        format!("{e:#}").contains("unknown configuration \"cpux\""),
        "{e:#}"
    );
    let _ = std::fs::remove_dir_all(&out);
}

/// `--replot` reads bench.csv back (rows of two runs concatenated) and redraws the plot; a bad
/// line is an error naming the file and line.
#[test]
fn replot_reads_the_csv_back_and_names_a_bad_line() {
    let out = std::env::temp_dir().join(format!("xscale-test-replot-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&out);
    std::fs::create_dir_all(&out).unwrap();
    let header = "config,setup_s,wall_s,step,psnr_masked,ssim_masked,psnr_near,psnr_far\n";
    let csv = format!(
        "{header}a,0.5,1.0,10,20.0,0.5,19.0,21.0\na,0.5,2.0,20,22.0,0.6,21.0,23.0\n\
         {header}b,0.1,1.0,0,21.0,0.7,20.0,22.0\n"
    );
    std::fs::write(out.join("bench.csv"), &csv).unwrap();
    let mut said = Vec::new();
    let rows = replot(&out, "t", &mut |m| said.push(m)).unwrap();
    assert_eq!(rows.len(), 3);
    assert_eq!(rows[2].config, "b");
    assert!(out.join("pareto.png").is_file());
    assert!(said.iter().any(|m| m.contains("22.00 dB  a")), "{said:?}");
    std::fs::write(
        out.join("bench.csv"),
        format!("{header}a,0.5,x,10,20.0,0.5,19.0,21.0\n"),
    )
    .unwrap();
    let e = format!("{:#}", replot(&out, "t", &mut |_| {}).unwrap_err());
    assert!(
        e.contains("bench.csv: line 2") && e.contains("\"x\""),
        "{e}"
    );
    let _ = std::fs::remove_dir_all(&out);
}

/// A second run into a folder holding bench.csv is refused (nothing written) unless it appends
/// (earlier rows kept, a configuration run again replacing its own) or overwrites.
#[test]
fn an_earlier_bench_csv_is_refused_kept_or_replaced() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let scene = root.join("fixtures/tiny");
    let out = std::env::temp_dir().join(format!("xscale-bq-again-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&out);
    std::fs::create_dir_all(&out).unwrap();
    let csv = out.join("bench.csv");
    let header = "config,setup_s,wall_s,step,psnr_masked,ssim_masked,psnr_near,psnr_far\n";
    // An earlier run: configuration "a" finished, "ulr" cut short.
    let earlier = format!(
        "{header}a,0.5,1.0,10,20.0,0.5,19.0,21.0\na,0.5,2.0,20,22.0,0.6,21.0,23.0\nulr,0.1,1.0,0,9.0,0.1,9.0,9.0\n"
    );
    std::fs::write(&csv, &earlier).unwrap();
    let run = |configs: &[&str], existing| {
        let configs: Vec<String> = configs.iter().map(|c| c.to_string()).collect();
        bench_quality(&scene, &out, &configs, 0.01, existing, &mut |_| {}, &|| {
            false
        })
        .map(|(rows, _)| rows)
    };

    let e = format!("{:#}", run(&["ulr"], Existing::Refuse).unwrap_err());
    assert!(
        e.contains("bench.csv") && e.contains("3 rows: a, ulr") && e.contains("--append"),
        "{e}"
    );
    assert_eq!(
        std::fs::read_to_string(&csv).unwrap(),
        earlier,
        "refused, yet written"
    );

    let e = format!("{:#}", run(&["ulr", "ulr"], Existing::Append).unwrap_err());
    assert!(e.contains("\"ulr\" is listed twice"), "{e}");

    // Rows written without a record of their scene and budget (an older xscale's) cannot be
    // checked: --append refuses them, naming the way out.
    let e = format!("{:#}", run(&["ulr"], Existing::Append).unwrap_err());
    assert!(
        e.contains("older xscale") && e.contains("bench.json") && e.contains("--overwrite"),
        "{e}"
    );
    assert_eq!(std::fs::read_to_string(&csv).unwrap(), earlier);
    let record = format!(
        "{{\"scene\": {:?}, \"minutes\": 0.01}}",
        std::fs::canonicalize(&scene).unwrap()
    );
    std::fs::write(out.join("bench.json"), &record).unwrap();

    let rows = run(&["ulr"], Existing::Append).unwrap();
    let configs: Vec<&str> = rows.iter().map(|r| r.config.as_str()).collect();
    assert_eq!(configs, ["a", "a", "ulr"]);
    assert!(
        rows[2].psnr_masked > 10.0,
        "the old ulr row (9 dB) was not replaced"
    );
    let on_disk = read_rows(&csv).unwrap();
    assert_eq!(on_disk.len(), 3);
    assert_eq!(on_disk[2].psnr_masked.to_bits(), {
        let p = rows[2].psnr_masked;
        format!("{p:.4}").parse::<f64>().unwrap().to_bits()
    });
    assert!(out.join("pareto.png").is_file());
    // No temporary file is left beside the kept rows (`io::atomic` names them `.bench.csv.tmp.*`).
    let leftovers: Vec<String> = std::fs::read_dir(&out)
        .unwrap()
        .flatten()
        .map(|e| e.file_name().to_string_lossy().into_owned())
        .filter(|n| n.contains(".tmp"))
        .collect();
    assert!(leftovers.is_empty(), "{leftovers:?}");

    let rows = run(&["ulr"], Existing::Overwrite).unwrap();
    assert_eq!(rows.len(), 1);
    assert_eq!(read_rows(&csv).unwrap().len(), 1);

    // A header-only file (a run stopped before its first evaluation) holds nothing to lose.
    std::fs::write(&csv, header).unwrap();
    assert_eq!(run(&["ulr"], Existing::Refuse).unwrap().len(), 1);

    // A malformed earlier file is named, line and all, before anything is written.
    std::fs::write(&csv, format!("{header}a,0.5,x,10,20.0,0.5,19.0,21.0\n")).unwrap();
    let e = format!("{:#}", run(&["ulr"], Existing::Append).unwrap_err());
    assert!(
        e.contains("bench.csv: line 2") && e.contains("--overwrite"),
        "{e}"
    );
    let _ = std::fs::remove_dir_all(&out);
}

/// Stopped (Ctrl-C) during the first configuration: the rows it measured so far are kept in
/// bench.csv and plotted, and the configurations not finished are returned, the stopped one
/// first (the CLI names them in the command that finishes the run). Stopped before any
/// evaluation: nothing measured, no plot, no error.
#[test]
fn a_stopped_run_keeps_its_rows_and_names_what_is_left() {
    // The stop comes once the first row is in bench.csv (flushed as each evaluation ends), so
    // the outcome does not depend on the machine's speed: exactly that row is kept.
    let out = fresh_out("-stop");
    let csv = out.join("bench.csv");
    let stop = || std::fs::read_to_string(&csv).is_ok_and(|t| t.lines().count() >= 2);
    let (rows, stopped) = tiny_and_ulr(&out, &stop);
    assert_eq!(stopped, ["tiny", "ulr"]);
    assert_eq!(rows.len(), 1);
    assert_eq!(rows[0].config, "tiny");
    assert_eq!(read_rows(&csv).unwrap().len(), 1);
    assert!(out.join("pareto.png").is_file());
    // At the first check: before anything was measured.
    let out = fresh_out("-stop0");
    let (rows, stopped) = tiny_and_ulr(&out, &|| true);
    assert_eq!((rows.len(), stopped.len()), (0, 2));
    assert!(!out.join("pareto.png").exists());
    let _ = std::fs::remove_dir_all(&out);
    let _ = std::fs::remove_dir_all(
        out.with_file_name(format!("xscale-bq-stop-{}", std::process::id())),
    );
}

/// `timeout`'s SIGTERM reaches the process twice (the process, then its group): one stop, which
/// keeps and plots the rows measured and names the command that finishes the run, exit 130. (The
/// copy used to abort it at once: no pareto.png, no `--append` command.)
#[test]
fn a_signal_delivered_twice_stops_the_cli_once() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let out = fresh_out("-sig2");
    let child = std::process::Command::new(env!("CARGO_BIN_EXE_xscale"))
        .args(["bench-quality", "--scene"])
        .arg(root.join("fixtures/tiny"))
        .arg("--out")
        .arg(&out)
        .args(["--configs", "tiny", "--minutes", "0.5"])
        .stderr(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    let t0 = std::time::Instant::now();
    let csv = out.join("bench.csv");
    while !std::fs::read_to_string(&csv).is_ok_and(|t| t.lines().count() >= 2) {
        assert!(t0.elapsed().as_secs() < 60, "no row measured");
        std::thread::sleep(std::time::Duration::from_millis(20));
    }
    for _ in 0..2 {
        let st = std::process::Command::new("kill")
            .args(["-TERM", &child.id().to_string()])
            .status()
            .unwrap();
        assert!(st.success());
    }
    let o = child.wait_with_output().unwrap();
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(130), "{err}");
    assert!(err.contains("--append --configs tiny"), "{err}");
    assert!(out.join("pareto.png").is_file(), "{err}");
    let _ = std::fs::remove_dir_all(&out);
}

/// `--append` adds rows only to a bench of the same scene and budget (recorded in bench.json):
/// another scene or another `--minutes` is refused, every difference named, before anything is
/// written (rows of another scene used to be plotted beside the first's).
#[test]
fn append_refuses_another_scene_or_budget() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let scene = root.join("fixtures/tiny");
    let out = fresh_out("-mix");
    let run = |scene: &Path, minutes: f64, existing| {
        bench_quality(
            scene,
            &out,
            &["ulr".to_string()],
            minutes,
            existing,
            &mut |_| {},
            &|| false,
        )
    };
    run(&scene, 0.01, Existing::Refuse).unwrap();
    let record: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("bench.json")).unwrap()).unwrap();
    assert_eq!(record["minutes"], 0.01);
    let csv = std::fs::read_to_string(out.join("bench.csv")).unwrap();
    // Another scene (the check comes before the scene is read) and another budget, together.
    let other = root.join("fixtures");
    let e = format!("{:#}", run(&other, 0.02, Existing::Append).unwrap_err());
    assert!(
        e.contains("\n  scene ") && e.contains("fixtures/tiny)"),
        "{e}"
    );
    assert!(
        e.contains("--minutes 0.02 (the earlier run's is 0.01)"),
        "{e}"
    );
    let e = format!("{:#}", run(&scene, 0.02, Existing::Append).unwrap_err());
    assert!(
        e.contains("\n  --minutes 0.02") && !e.contains("\n  scene"),
        "{e}"
    );
    assert_eq!(std::fs::read_to_string(out.join("bench.csv")).unwrap(), csv);
    // The same scene, given another way (a path with `..`), and budget: appended.
    let same = root.join("fixtures/../fixtures/tiny");
    assert_eq!(run(&same, 0.01, Existing::Append).unwrap().0.len(), 1);
    let _ = std::fs::remove_dir_all(&out);
}

/// A configuration named twice in `--configs` is a usage error (exit 64) naming it, as an unknown
/// one is, before anything is written (it exited 2, from the run).
#[test]
fn a_configuration_listed_twice_is_a_usage_error() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let out = fresh_out("-twice");
    for (list, says) in [
        ("ulr,ulr", "configuration \"ulr\" is listed twice"),
        ("tiny, ulr,tiny", "configuration \"tiny\" is listed twice"),
        ("ulr,foo", "unknown configuration \"foo\""),
    ] {
        let o = std::process::Command::new(env!("CARGO_BIN_EXE_xscale"))
            .args(["bench-quality", "--scene"])
            .arg(root.join("fixtures/tiny"))
            .arg("--out")
            .arg(&out)
            .args(["--configs", list])
            .output()
            .unwrap();
        let err = String::from_utf8_lossy(&o.stderr);
        assert_eq!(o.status.code(), Some(64), "{list}: {err}");
        assert!(
            err.contains("--configs") && err.contains(says),
            "{list}: {err}"
        );
        assert!(!out.exists(), "{list}: wrote {}", out.display());
    }
}
