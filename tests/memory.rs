//! The memory budget of a training run (`train/memory.rs`): a run whose estimate exceeds
//! `[train] memory_gb` stops before it loads a photo or casts a ray, with the figures and what to
//! change; the message names the change that fits the part that is too large; a finished run
//! reports its peak memory on the terminal and in `metrics.jsonl`.

use std::path::{Path, PathBuf};
use std::process::Command;
use xscale::train::config::RunConfig;
use xscale::train::memory::{
    check_budget, check_dump, estimate, resolve_samples, AUTO_CACHE_MAX_BYTES,
    DUMP_BYTES_PER_PIXEL, DUMP_BYTES_PER_SAMPLE_FEATURE,
};
use xscale::train::sampler::SampleMode;

fn fixture() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("fixtures/tiny")
}

fn tmp(name: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("xscale-test-memory-{}-{name}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    d
}

/// `xscale train` on the tiny fixture: (exit code, stdout + stderr).
fn train(run: &Path, extra: &[&str]) -> (i32, String) {
    let scene = fixture();
    let out = Command::new(env!("CARGO_BIN_EXE_xscale"))
        .args([
            "train",
            "--scene",
            scene.to_str().unwrap(),
            "--out",
            run.to_str().unwrap(),
            "--preset",
            "tiny",
            "--no-eval",
        ])
        .args(extra)
        .output()
        .unwrap();
    (
        out.status.code().unwrap_or(-1),
        String::from_utf8_lossy(&out.stdout).into_owned() + &String::from_utf8_lossy(&out.stderr),
    )
}

#[test]
fn a_run_over_its_budget_stops_before_training_with_the_figures() {
    let dir = tmp("over");
    std::fs::create_dir_all(&dir).unwrap();
    let cfg = dir.join("budget.toml");
    // The tiny run is estimated at ~0.22 GB (mostly the fixed part): 0.05 GB cannot hold it.
    std::fs::write(&cfg, "[train]\nmemory_gb = 0.05\n").unwrap();
    let run = dir.join("run");
    let (code, out) = train(&run, &["--steps", "5", "--config", cfg.to_str().unwrap()]);
    assert_eq!(code, 2, "{out}");
    assert!(
        out.contains("needs about") && out.contains("train.memory_gb = 0.05"),
        "{out}"
    );
    assert!(out.contains("To fit:"), "{out}");
    // Stopped before the photos were cast or a step ran: no checkpoint, no metrics.
    assert!(!run.join("checkpoint.safetensors").exists());
    assert!(!run.join("metrics.jsonl").exists());
    // The same run with a budget that holds it trains.
    std::fs::write(&cfg, "[train]\nmemory_gb = 1\n").unwrap();
    let (code, out) = train(
        &run,
        &[
            "--steps",
            "5",
            "--config",
            cfg.to_str().unwrap(),
            "--overwrite",
        ],
    );
    assert_eq!(code, 0, "{out}");
    let _ = std::fs::remove_dir_all(&dir);
}

/// The advice follows the part that does not fit: photos → `[train] downsample` (a config key:
/// `train` has no `--downsample` flag, which the advice used to name), fewer views, and the
/// stream instead of the cache; a batch → `--batch`.
#[test]
fn the_message_names_what_to_change() {
    let mut cfg = RunConfig::preset("cpu").unwrap();
    // 150 photos of 2 Mpixels, the modest real scene.
    let sizes = vec![(1920u32, 1080u32); 150];
    cfg.train.samples = SampleMode::Cache;
    let e = estimate(&cfg, &sizes, 1).unwrap();
    // 90 bytes per pixel at γ = 2: 150 · 2.07 M · 90 ≈ 28 GB.
    assert!(e.samples > 25_000_000_000, "{e:?}");
    cfg.train.memory_gb = 24.0;
    let err = check_budget(&cfg, &sizes, 1).unwrap_err().to_string();
    for want in [
        "the sample cache",
        "samples = \"stream\"",
        "[train] downsample = 2",
        "test_views / holdout_every",
    ] {
        assert!(err.contains(want), "missing {want:?} in: {err}");
    }
    assert!(!err.contains("--downsample"), "{err}");
    assert!(!err.contains("--batch"), "{err}");
    // Streamed, the same scene fits in 2 GB: 3 bytes per pixel plus a bit.
    cfg.train.samples = SampleMode::Stream;
    cfg.train.memory_gb = 2.0;
    check_budget(&cfg, &sizes, 1).unwrap();
    // A batch of 2^20 pixels (4 Mi sub-samples at ~1.5 kB: 6.4 GB) does not fit in 4 GB: the
    // message says --batch, and not downsample (the photos take under a third of the budget).
    cfg.train.batch_pixels = 1 << 20;
    cfg.train.memory_gb = 4.0;
    let err = check_budget(&cfg, &sizes, 1).unwrap_err().to_string();
    assert!(err.contains("--batch 262144"), "{err}");
    assert!(!err.contains("downsample"), "{err}");
}

/// Mesh refinement's photo-consistency term keeps f32 copies of every training photo at its image
/// levels: counted, and named with its remedy when it is what does not fit.
#[test]
fn the_photo_term_is_counted_and_named() {
    let mut cfg = RunConfig::preset("cpu").unwrap();
    let sizes = vec![(1920u32, 1080u32); 150];
    assert_eq!(estimate(&cfg, &sizes, 1).unwrap().photo, 0);
    cfg.model.refine.enabled = true;
    cfg.model.refine.photo = 1.0;
    cfg.model.refine.photo_levels = [2, 0];
    // With the cross-scale levels (photo_reach) every view also keeps levels 3 ..= 6 (1080 >> 6
    // = 16 rows hold a 5 × 5 patch and 2 pixels either side; 1080 >> 7 would not).
    cfg.model.refine.photo_reach = 2.0;
    let e = estimate(&cfg, &sizes, 1).unwrap();
    let level = |l: u32| 12 * 1920u64.div_ceil(1 << l) * 1080u64.div_ceil(1 << l);
    assert_eq!(e.photo, 150 * (0..=6).map(level).sum::<u64>());
    cfg.model.refine.photo_reach = 0.0;
    let e = estimate(&cfg, &sizes, 1).unwrap();
    // 12 bytes per pixel at levels 0, 1, 2: 150 · 12 · (1920·1080 + 960·540 + 480·270) = 4.90 GB.
    assert_eq!(e.photo, 150 * 12 * (1920 * 1080 + 960 * 540 + 480 * 270));
    cfg.train.memory_gb = 4.0;
    let err = check_budget(&cfg, &sizes, 1).unwrap_err().to_string();
    for want in [
        "the photo-consistency term's image levels 4.90 GB",
        "photo_levels = [2, 1]",
    ] {
        assert!(err.contains(want), "missing {want:?} in: {err}");
    }
    // Without its full-resolution level it fits in the same budget.
    cfg.model.refine.photo_levels = [2, 1];
    check_budget(&cfg, &sizes, 1).unwrap();
}

#[test]
fn a_finished_run_reports_its_peak_memory() {
    let run = tmp("peak");
    let (code, out) = train(&run, &["--steps", "5"]);
    assert_eq!(code, 0, "{out}");
    assert!(out.contains("peak memory"), "{out}");
    let metrics = std::fs::read_to_string(run.join("metrics.jsonl")).unwrap();
    let peak = metrics
        .lines()
        .filter_map(|l| serde_json::from_str::<serde_json::Value>(l).ok())
        .find_map(|v| v["peak_rss_bytes"].as_u64())
        .expect("no peak_rss_bytes line in metrics.jsonl");
    // More than the binary's own few MB, less than the machine.
    assert!(peak > 4 << 20 && peak < 8 << 30, "peak {peak} bytes");
    let _ = std::fs::remove_dir_all(&run);
}

/// `samples = "auto"` (the default) caches the rays of a small scene, streams those of a large one
/// or of a run whose budget the cache would crowd, and streams whenever the mesh refinement moves
/// the mesh; the estimate follows the choice.
#[test]
fn auto_samples_cache_what_fits_and_stream_the_rest() {
    let mut cfg = RunConfig::preset("cpu").unwrap();
    assert_eq!(cfg.train.samples, SampleMode::Auto);
    cfg.train.memory_gb = 16.0;
    // 40 views of 200x150 (synth small): 1.2 M pixels, ~0.1 GB cached.
    let small = vec![(200u32, 150u32); 40];
    let (m, why) = resolve_samples(&cfg, &small, 1);
    assert_eq!(m, SampleMode::Cache, "{why}");
    assert!(why.contains("auto") && why.contains("fits"), "{why}");
    let mut c = cfg.clone();
    c.train.samples = SampleMode::Cache;
    assert_eq!(
        estimate(&cfg, &small, 1).unwrap(),
        estimate(&c, &small, 1).unwrap()
    );
    // 150 photos of 2 Mpixels: ~28 GB cached, far over the cap.
    let large = vec![(1920u32, 1080u32); 150];
    let (m, why) = resolve_samples(&cfg, &large, 1);
    assert_eq!(m, SampleMode::Stream, "{why}");
    assert!(why.contains("more than"), "{why}");
    c.train.samples = SampleMode::Stream;
    assert_eq!(
        estimate(&cfg, &large, 1).unwrap(),
        estimate(&c, &large, 1).unwrap()
    );
    // A small cache that would take more than a quarter of a tight budget is not taken.
    let mid = vec![(640u32, 480u32); 40]; // 12.3 M pixels, ~1.1 GB cached
    assert!(
        estimate(
            &{
                let mut c = cfg.clone();
                c.train.samples = SampleMode::Cache;
                c
            },
            &mid,
            1
        )
        .unwrap()
        .samples
            < AUTO_CACHE_MAX_BYTES
    );
    assert_eq!(resolve_samples(&cfg, &mid, 1).0, SampleMode::Cache);
    cfg.train.memory_gb = 4.0;
    assert_eq!(resolve_samples(&cfg, &mid, 1).0, SampleMode::Stream);
    // The mesh refinement moves the mesh: always the stream under auto.
    cfg.train.memory_gb = 16.0;
    cfg.model.refine.enabled = true;
    let (m, why) = resolve_samples(&cfg, &small, 1);
    assert_eq!(m, SampleMode::Stream, "{why}");
    assert!(why.contains("refinement"), "{why}");
    // Given modes are kept.
    cfg.model.refine.enabled = false;
    cfg.train.samples = SampleMode::Stream;
    assert_eq!(resolve_samples(&cfg, &small, 1).0, SampleMode::Stream);
}

/// `xscale dump` is sized the same way before it reads the batch: a batch far beyond the memory
/// (or beyond what a process can address) is refused with the estimate and a `--size` that
/// fits; a golden-sized one passes.
#[test]
fn a_dump_that_cannot_fit_is_refused_with_the_estimate() {
    // The cpu-t10 golden model's 112 features per sub-sample, γ = 2.
    check_dump(64, 4, 112, 100_000, true).unwrap();
    check_dump(4096, 4, 112, 1 << 20, false).unwrap();
    for pixels in [1usize << 40, usize::MAX] {
        let err = check_dump(pixels, 4, 112, 100_000, true)
            .unwrap_err()
            .to_string();
        assert!(
            err.contains("this dump needs about")
                && err.contains(&format!("a batch of {pixels} pixels × 4 sub-samples"))
                && err.contains("a smaller batch (xscale batch --size "),
            "{err}"
        );
    }
    // f64: 40 bytes per sub-sample and feature, plus 2 KB per pixel.
    assert_eq!(
        DUMP_BYTES_PER_SAMPLE_FEATURE * 4 * 112 + DUMP_BYTES_PER_PIXEL,
        19_968
    );
}

/// The cache estimate is an upper bound for every run: a vertex-featurization run's cache also
/// keeps each slot's triangle id and barycentrics (12 more bytes), and the estimate counts them
/// (it used to say `sample cache: 2.5 MB (auto: a cache of at most 1.7 MB …)` on the tiny scene).
#[test]
fn the_cache_estimate_counts_the_vertex_featurizations_triangles() {
    let run = tmp("vertex-cache");
    let config = Path::new(env!("CARGO_MANIFEST_DIR")).join("configs/ablations/vertex.toml");
    let (code, out) = train(
        &run,
        &["--steps", "1", "--config", config.to_str().unwrap()],
    );
    assert_eq!(code, 0, "{out}");
    let mb = |after: &str| -> f64 {
        let i = out
            .find(after)
            .unwrap_or_else(|| panic!("no {after:?} in {out}"))
            + after.len();
        out[i..]
            .split(" MB")
            .next()
            .unwrap()
            .trim()
            .parse()
            .unwrap()
    };
    let (cache, estimate) = (mb("sample cache:"), mb("a cache of at most"));
    assert!(
        cache <= estimate,
        "the cache ({cache} MB) exceeds its estimate ({estimate} MB):\n{out}"
    );
    let _ = std::fs::remove_dir_all(&run);
}

/// A mesh whose BVH does not fit in the memory left (here an address-space limit) is refused in
/// words before the BVH is built, by every command that casts rays. The BVH builder (obvhs)
/// unwraps its allocations: `cast`, `train` and the others used to panic there (`called
/// Result::unwrap() on an Err value`, exit 101; with RUST_BACKTRACE=1 the panic hung).
#[test]
fn a_mesh_whose_bvh_cannot_fit_is_refused_before_it_is_built() {
    let dir = tmp("bvh");
    std::fs::create_dir_all(&dir).unwrap();
    let big = dir.join("big.ply");
    let exe = env!("CARGO_BIN_EXE_xscale");
    // 2118 triangles × 4^5: 2.2 M triangles, a BVH of ~0.8 GB.
    let st = Command::new(exe)
        .args(["subdivide", "--in"])
        .arg(fixture().join("mesh.ply"))
        .args(["--levels", "5", "--out"])
        .arg(&big)
        .output()
        .unwrap();
    assert!(st.status.success(), "{st:?}");
    for cmd in [
        "cast --no-images --gamma 1",
        "train --preset tiny --no-eval --out",
    ] {
        let out_arg = if cmd.ends_with("--out") {
            format!(" '{}'", dir.join("run").display())
        } else {
            String::new()
        };
        let o = Command::new("sh")
            .arg("-c")
            .arg(format!(
                "ulimit -v 400000; exec '{exe}' --threads 1 {cmd}{out_arg} --scene '{}' --mesh '{}'",
                fixture().display(),
                big.display()
            ))
            // With backtraces on, the old panic hung (the backtrace printer itself ran out of
            // memory holding its lock): off, a regression fails instead of hanging the suite.
            .env("RUST_BACKTRACE", "0")
            .output()
            .unwrap();
        let err = String::from_utf8_lossy(&o.stderr);
        assert_eq!(o.status.code(), Some(2), "{cmd}: {err}");
        assert!(
            err.contains("BVH of the mesh's 2168832 triangles")
                && err.contains("xscale decimate")
                && !err.contains("panicked"),
            "{cmd}: {err}"
        );
    }
    let _ = std::fs::remove_dir_all(&dir);
}
