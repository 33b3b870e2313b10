//! Run folders as users meet them (docs/runs.md): a folder holding a run is refused unless
//! resumed or overwritten, one lock per folder, `--resume` keeps the stored configuration and
//! takes `--steps` as the total, a resume on another scene is refused, SIGTERM stops like
//! Ctrl-C with a checkpoint, a diverging run is stopped, and image names with folders
//! (`images/0000.png`) keep their folders in the outputs.

use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

#[path = "common/metrics.rs"]
mod metrics;
#[path = "common/signal.rs"]
mod signal;

#[path = "common/cli.rs"]
mod cli;
use cli::{fixture, xscale};

fn tmp(name: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("xscale-test-runs-{}-{name}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    d
}

fn train(run: &Path, extra: &[&str]) -> (i32, String) {
    train_on(&fixture(), run, extra)
}

/// `xscale train --scene SCENE --out RUN --no-eval -q EXTRA…`.
fn train_on(scene: &Path, run: &Path, extra: &[&str]) -> (i32, String) {
    let args = train_args(scene, run, extra);
    xscale(&args.iter().map(String::as_str).collect::<Vec<_>>())
}

/// The arguments of [`train_on`].
fn train_args(scene: &Path, run: &Path, extra: &[&str]) -> Vec<String> {
    let mut args = vec![
        "train",
        "--scene",
        scene.to_str().unwrap(),
        "--out",
        run.to_str().unwrap(),
        "--no-eval",
        "-q",
    ];
    args.extend_from_slice(extra);
    args.into_iter().map(String::from).collect()
}

/// `xscale batch --scene fixtures/tiny --out OUT EXTRA…`.
fn batch_file(out: &Path, extra: &[&str]) -> (i32, String) {
    let scene = fixture();
    let args = [
        "batch",
        "--scene",
        scene.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
    ];
    xscale(&[&args[..], extra].concat())
}

/// `xscale train` of 5 `tiny` steps on `scene` into `run`, without evaluation; must succeed.
fn train_tiny_5(scene: &Path, run: &Path) {
    let (code, err) = train_on(scene, run, &["--preset", "tiny", "--steps", "5"]);
    assert_eq!(code, 0, "{err}");
}

/// A fresh run folder `tmp(name)` holding [`train_tiny_5`]'s run on the fixture.
fn tiny_run(name: &str) -> PathBuf {
    let run = tmp(name);
    train_tiny_5(&fixture(), &run);
    run
}

/// Replace the split in `scene`'s scene.toml (`holdout_every` / `test_views` lines) by `split`.
fn set_split(scene: &Path, split: &str) {
    let p = scene.join("scene.toml");
    let mut toml: String = (std::fs::read_to_string(&p).unwrap().lines())
        .filter(|l| !l.starts_with("holdout_every") && !l.starts_with("test_views"))
        .map(|l| format!("{l}\n"))
        .collect();
    toml += split;
    std::fs::write(p, toml + "\n").unwrap();
}

fn step_of(run: &Path) -> u64 {
    xscale::train::state::TrainState::load(&run.join("checkpoint.safetensors"))
        .unwrap()
        .step
}

#[test]
fn a_folder_holding_a_run_is_refused_unless_resumed_or_overwritten() {
    let run = tmp("protect");
    let base = ["--preset", "tiny", "--steps", "20"];
    assert_eq!(train(&run, &base).0, 0);
    let first = std::fs::read(run.join("checkpoint.safetensors")).unwrap();
    let (code, err) = train(&run, &["--preset", "tiny", "--steps", "30", "--seed", "5"]);
    assert_ne!(code, 0);
    assert!(
        err.contains("already holds a run") && err.contains("--overwrite"),
        "{err}"
    );
    // Nothing was touched.
    assert_eq!(
        std::fs::read(run.join("checkpoint.safetensors")).unwrap(),
        first
    );
    // Leftover temporary checkpoint files are removed; --overwrite replaces the run.
    std::fs::write(run.join(".checkpoint.safetensors.tmp.1.2"), b"partial").unwrap();
    let (code, err) = train(&run, &["--preset", "tiny", "--steps", "30", "--overwrite"]);
    assert_eq!(code, 0, "{err}");
    assert_eq!(step_of(&run), 30);
    assert!(!run.join(".checkpoint.safetensors.tmp.1.2").exists());
    let _ = std::fs::remove_dir_all(&run);
}

#[test]
fn a_live_lock_refuses_a_second_run_and_a_stale_one_is_taken_over() {
    let run = tmp("lock");
    std::fs::create_dir_all(&run).unwrap();
    // This test process holds the lock, as a concurrent run would.
    let lock = xscale::run::run_dir::RunLock::acquire(&run).unwrap();
    let (code, err) = train(&run, &["--preset", "tiny", "--steps", "5"]);
    assert_ne!(code, 0);
    assert!(
        err.contains(&format!(
            "another xscale process (pid {})",
            std::process::id()
        )) && err.contains("remove"),
        "{err}"
    );
    assert!(!run.join("checkpoint.safetensors").exists());
    drop(lock);
    // A pid that does not exist, or a live process that is no xscale (pid 1, once a killed
    // run's pid reused): the lock is stale. (Pid 1 used to block the folder for good.)
    for stale in ["4000000000", "1"] {
        std::fs::write(run.join(".lock"), format!("{stale}\n")).unwrap();
        let (code, err) = train(&run, &["--preset", "tiny", "--steps", "5", "--overwrite"]);
        assert_eq!(code, 0, "lock of pid {stale}: {err}");
        assert!(!run.join(".lock").exists(), "the lock is released at exit");
    }
    let _ = std::fs::remove_dir_all(&run);
}

/// `--overwrite` removes the earlier run only once the new one is ready to start: a scene that
/// is not there, a bad configuration value or a batch that cannot fit leave it whole (they used
/// to find the folder emptied). It removes what a run writes, not a user's files in `render/`.
#[test]
fn overwrite_keeps_the_old_run_until_the_new_one_can_start() {
    let run = tiny_run("overwrite-late");
    let ckpt = std::fs::read(run.join("checkpoint.safetensors")).unwrap();
    std::fs::create_dir_all(run.join("render/sub")).unwrap();
    std::fs::write(run.join("render/mine.txt"), "notes").unwrap();
    std::fs::write(run.join("render/sub/0001.png"), "an old render").unwrap();
    // A user's file in the run folder, kept by --overwrite.
    let bad = run.join("bad.toml");
    std::fs::write(&bad, "[model.grid_h]\nper_level_scale = 0.5\n").unwrap();
    let missing = fixture().with_file_name("tinyy");
    let failures: [(&Path, &[&str], &str); 3] = [
        (&missing, &[], "not found"),
        (
            &fixture(),
            &["--config", bad.to_str().unwrap()],
            "model.grid_h.per_level_scale = 0.5",
        ),
        (&fixture(), &["--batch", "100000000"], "a smaller batch"),
    ];
    for (scene, extra, says) in failures {
        let mut args = vec!["--preset", "tiny", "--steps", "5", "--overwrite"];
        args.extend_from_slice(extra);
        let (code, err) = train_on(scene, &run, &args);
        assert_eq!(code, 2, "{err}");
        assert!(err.contains(says), "{err}");
        assert_eq!(
            std::fs::read(run.join("checkpoint.safetensors")).unwrap(),
            ckpt
        );
        assert!(run.join("metrics.jsonl").is_file() && run.join("config.toml").is_file());
    }
    // The bad value is named with its file and line.
    let (_, err) = train_on(
        &fixture(),
        &run,
        &["--config", bad.to_str().unwrap(), "--overwrite"],
    );
    assert!(err.contains(&format!("{}:2", bad.display())), "{err}");
    let (code, err) = train(&run, &["--preset", "tiny", "--steps", "7", "--overwrite"]);
    assert_eq!(code, 0, "{err}");
    assert_eq!(step_of(&run), 7);
    let kept = ["render/mine.txt", "bad.toml"].map(|f| run.join(f).is_file());
    assert_eq!(kept, [true; 2], "a user's files are kept");
    assert!(!run.join("render/sub").exists(), "the run's images go");
    let _ = std::fs::remove_dir_all(&run);
}

/// A folder whose run wrote no checkpoint (killed before its first) is started afresh by the
/// plain command, saying so; `--resume` says to run it without `--resume`. (The plain command
/// used to send the user to --resume, which sent them back.)
#[test]
fn a_folder_without_a_checkpoint_starts_afresh() {
    let run = tiny_run("nockpt");
    std::fs::remove_file(run.join("checkpoint.safetensors")).unwrap();
    let (code, err) = train(&run, &["--preset", "tiny", "--steps", "5", "--resume"]);
    assert_eq!(code, 2, "{err}");
    assert!(
        err.contains("nothing to resume") && err.contains("without --resume"),
        "{err}"
    );
    let (code, err) = train(&run, &["--preset", "tiny", "--steps", "6"]);
    assert_eq!(code, 0, "{err}");
    assert!(
        err.contains("wrote no checkpoint") && err.contains("afresh"),
        "{err}"
    );
    assert_eq!(step_of(&run), 6);
    assert_eq!(metrics::checkpoints(&run), [6], "the old metrics are gone");
    let _ = std::fs::remove_dir_all(&run);
}

#[test]
fn resume_keeps_the_run_config_and_steps_is_the_total() {
    let run = tmp("resume");
    assert_eq!(
        train(
            &run,
            &["--preset", "tiny", "--steps", "100", "--stop-at", "40"]
        )
        .0,
        0
    );
    assert_eq!(step_of(&run), 40);
    // Options that differ from the run are named.
    let (code, err) = train(&run, &["--resume", "--preset", "cpu", "--seed", "3"]);
    assert_ne!(code, 0);
    assert!(
        err.contains("--preset cpu") && err.contains("--seed 3"),
        "{err}"
    );
    let cfg = run.join("c.toml");
    std::fs::write(&cfg, "[model]\ngamma = 1\n").unwrap();
    let (code, err) = train(&run, &["--resume", "--config", cfg.to_str().unwrap()]);
    assert_ne!(code, 0);
    assert!(err.contains("model.gamma = 1"), "{err}");
    // Fewer steps than done is refused; --steps N is a total, not an addition.
    let (code, err) = train(&run, &["--resume", "--steps", "20"]);
    assert_ne!(code, 0);
    assert!(err.contains("already at step 40"), "{err}");
    let (code, err) = train(&run, &["--resume", "--steps", "60"]);
    assert_eq!(code, 0, "{err}");
    assert_eq!(step_of(&run), 60);
    // The run's time runs on across the resume: every checkpoint has its line, and elapsed_s
    // never goes back (it restarted from 0 in the resumed process).
    assert_eq!(metrics::checkpoints(&run), [40, 60]);
    assert!(metrics::elapsed_runs_on(&run, 4));
    // Without --steps the stored total (now 60) stands: nothing left to do.
    let (code, err) = train(&run, &["--resume"]);
    assert_eq!(code, 0, "{err}");
    assert_eq!(step_of(&run), 60);
    // An option equal to the run's is accepted.
    let (code, err) = train(&run, &["--resume", "--steps", "70", "--preset", "tiny"]);
    assert_eq!(code, 0, "{err}");
    assert_eq!(step_of(&run), 70);
    // --mesh naming the scene's own mesh is the run's mesh (relative to the scene or not);
    // another file is a difference.
    let own = fixture().join("mesh.ply");
    for m in ["mesh.ply", own.to_str().unwrap()] {
        let (code, err) = train(&run, &["--resume", "--mesh", m]);
        assert_eq!(code, 0, "--mesh {m}: {err}");
    }
    let (code, err) = train(&run, &["--resume", "--mesh", "mesh.obj"]);
    assert_ne!(code, 0);
    assert!(
        err.contains("mesh.obj") && err.contains("the scene's own, "),
        "{err}"
    );
    // Without --scene a resume takes the scene the run records (RUN/scene.json)…
    let out = run.to_str().unwrap();
    let resume = [
        "train",
        "--out",
        out,
        "--resume",
        "--steps",
        "80",
        "--no-eval",
        "-q",
    ];
    let (code, err) = xscale(&resume);
    assert_eq!(code, 0, "{err}");
    assert_eq!(step_of(&run), 80);
    // …and says so when that scene is gone or not recorded; a new run still needs --scene.
    let fp = run.join("scene.json");
    let text = std::fs::read_to_string(&fp).unwrap();
    let mut j: serde_json::Value = serde_json::from_str(&text).unwrap();
    j["scene"] = serde_json::json!(tmp("resume-gone-scene"));
    std::fs::write(&fp, j.to_string()).unwrap();
    let (code, err) = xscale(&resume);
    assert_ne!(code, 0);
    assert!(
        err.contains("no longer exists") && err.contains("--scene"),
        "{err}"
    );
    std::fs::remove_file(&fp).unwrap();
    let (code, err) = xscale(&resume);
    assert_ne!(code, 0);
    assert!(err.contains("does not record the run's scene"), "{err}");
    let (code, err) = xscale(&["train", "--out", out, "--steps", "5", "-q"]);
    assert_ne!(code, 0);
    assert!(err.contains("--scene"), "{err}");
    assert_eq!(step_of(&run), 80);
    let _ = std::fs::remove_dir_all(&run);
}

#[test]
fn resume_on_another_scene_is_refused() {
    let run = tmp("scene");
    assert_eq!(
        train(
            &run,
            &["--preset", "tiny", "--steps", "30", "--stop-at", "10"]
        )
        .0,
        0
    );
    // The same photos, one camera moved.
    let other = tmp("scene-copy");
    copy_dir(&fixture(), &other);
    let t = other.join("sparse/0/images.txt");
    let text = std::fs::read_to_string(&t).unwrap();
    let mut lines: Vec<String> = text.lines().map(str::to_string).collect();
    let i = lines
        .iter()
        .position(|l| !l.starts_with('#') && !l.trim().is_empty())
        .unwrap();
    let mut f: Vec<String> = lines[i].split_whitespace().map(str::to_string).collect();
    let tx: f64 = f[5].parse().unwrap();
    f[5] = format!("{}", tx + 0.01);
    lines[i] = f.join(" ");
    std::fs::write(&t, lines.join("\n") + "\n").unwrap();
    let (code, err) = xscale(&[
        "train",
        "--scene",
        other.to_str().unwrap(),
        "--out",
        run.to_str().unwrap(),
        "--resume",
        "-q",
    ]);
    assert_ne!(code, 0);
    assert!(err.contains("cameras changed"), "{err}");
    assert_eq!(step_of(&run), 10);
    let _ = std::fs::remove_dir_all(&run);
    let _ = std::fs::remove_dir_all(&other);
}

fn copy_dir(from: &Path, to: &Path) {
    std::fs::create_dir_all(to).unwrap();
    for e in std::fs::read_dir(from).unwrap().flatten() {
        let p = e.path();
        if p.is_dir() {
            copy_dir(&p, &to.join(e.file_name()));
        } else {
            std::fs::copy(&p, to.join(e.file_name())).unwrap();
        }
    }
}

#[test]
fn sigterm_stops_with_a_checkpoint_that_resumes() {
    let run = tmp("sigterm");
    let out = terminated_in_training(&run, 1);
    let err = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(130), "{err}");
    let k = step_of(&run);
    assert!(k > 0, "a checkpoint of the work done is written");
    assert!(!run.join(".lock").exists());
    let (code, err) = train(&run, &["--resume", "--steps", &(k + 5).to_string()]);
    assert_eq!(code, 0, "{err}");
    assert_eq!(step_of(&run), k + 5);
    let _ = std::fs::remove_dir_all(&run);
}

/// A long `tiny` run into `run` (`--steps 1000000 --no-eval -q`), sent SIGTERM `copies` times at
/// once after its first step (its first metrics line), to its end.
fn terminated_in_training(run: &Path, copies: usize) -> std::process::Output {
    let child = Command::new(env!("CARGO_BIN_EXE_xscale"))
        .args(long_run_args(run))
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let t0 = Instant::now();
    while !std::fs::read_to_string(run.join("metrics.jsonl")).is_ok_and(|t| t.lines().count() > 1) {
        assert!(
            t0.elapsed() < Duration::from_secs(60),
            "the run never started"
        );
        std::thread::sleep(Duration::from_millis(20));
    }
    for _ in 0..copies {
        signal::terminate(&child);
    }
    child.wait_with_output().unwrap()
}

fn long_run_args(run: &Path) -> Vec<String> {
    train_args(&fixture(), run, &["--preset", "tiny", "--steps", "1000000"])
}

/// A signal delivered twice at once (`timeout` signals the process, then its process group) is
/// one stop, not "a second Ctrl-C: abort": the run stops with a checkpoint, exit 130, no
/// `.lock` left. (It used to abort: exit 130 with no checkpoint and a stale `.lock`.) Stopped
/// before training began, nothing is saved: exit 3, and the same command starts again.
#[test]
fn copies_of_a_signal_stop_once() {
    let run = tmp("sigcopies");
    let out = terminated_in_training(&run, 2);
    let err = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(130), "{err}");
    assert!(step_of(&run) > 0, "{err}");
    assert!(!run.join(".lock").exists());
    // As timeout(1) does it, during the setup: nothing saved, a distinct code.
    let _ = std::fs::remove_dir_all(&run);
    let out = Command::new("timeout")
        .args(["--preserve-status", "-s", "TERM", "0.05"])
        .arg(env!("CARGO_BIN_EXE_xscale"))
        .args(long_run_args(&run))
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    match out.status.code() {
        // Stopped in the setup, or before the handler was installed (a plain kill).
        Some(3) => assert!(err.contains("nothing new to save"), "{err}"),
        Some(130) => assert!(step_of(&run) > 0, "{err}"),
        c => assert!(out.status.code().is_none(), "exit {c:?}: {err}"),
    }
    assert!(!run.join(".lock").exists(), "{err}");
    let (code, err) = train(&run, &["--preset", "tiny", "--steps", "5", "--overwrite"]);
    assert_eq!(code, 0, "{err}");
    let _ = std::fs::remove_dir_all(&run);
}

/// Output to a closed pipe (`xscale train … 2>&1 | head -2`) is dropped: the command finishes its
/// work and exits as it would have (it used to panic, exit 101, mid-run).
#[test]
fn a_closed_pipe_drops_output_and_the_work_finishes() {
    let run = tmp("closedpipe");
    let (r, scene) = (run.to_str().unwrap(), fixture());
    let train = ["train", "--scene", scene.to_str().unwrap(), "--out", r];
    let (render, eval) = (run.join("render.out"), run.join("eval.out"));
    for args in [
        &[&train[..], &["--preset", "tiny", "--steps", "60"]].concat(),
        &[
            "render",
            "--run",
            r,
            "--views",
            "all",
            "--out",
            render.to_str().unwrap(),
        ][..],
        &["eval", "--run", r, "--out", eval.to_str().unwrap()],
    ] {
        // Both pipes closed before the command writes a byte.
        let mut child = Command::new(env!("CARGO_BIN_EXE_xscale"))
            .args(args)
            .stdout(Stdio::piped())
            .stderr(Stdio::piped())
            .spawn()
            .unwrap();
        drop((child.stdout.take(), child.stderr.take()));
        assert_eq!(child.wait().unwrap().code(), Some(0), "{args:?}");
    }
    assert_eq!(step_of(&run), 60);
    assert!(run.join("eval.json").is_file() && render.join("0007.png").is_file());
    let _ = std::fs::remove_dir_all(&run);
}

/// Resuming a finished run only evaluates it: the checkpoint is not rewritten, and
/// `metrics.jsonl` gets no second final-evaluation or checkpoint line for a step, nor an
/// `elapsed_s` that goes back; a periodic checkpoint at the step the run stops at is written
/// once. (Each used to be written again.)
#[test]
fn resuming_a_finished_run_writes_nothing_twice() {
    let (run, scene) = (tmp("nodupes"), fixture());
    let (out, scene) = (run.to_str().unwrap(), scene.to_str().unwrap());
    // With the final evaluation (`train_on` has none).
    let with = |extra: &[&str]| {
        let mut a = vec!["train", "-q", "--scene", scene, "--out", out];
        a.extend_from_slice(extra);
        let (code, err) = xscale(&a);
        assert_eq!(code, 0, "{extra:?}: {err}");
    };
    // tiny checkpoints every 100 steps.
    with(&["--preset", "tiny", "--steps", "120", "--stop-at", "100"]);
    assert_eq!(metrics::checkpoints(&run), [100]);
    with(&["--resume"]);
    let ckpt = run.join("checkpoint.safetensors");
    let inode = |p: &Path| {
        use std::os::unix::fs::MetadataExt;
        std::fs::metadata(p).unwrap().ino()
    };
    let before = inode(&ckpt);
    with(&["--resume"]);
    assert_eq!(
        inode(&ckpt),
        before,
        "an evaluation-only resume rewrote the checkpoint"
    );
    with(&["--resume", "--steps", "130"]);
    assert_eq!(metrics::checkpoints(&run), [100, 120, 130]);
    let finals: Vec<u64> = metrics::lines(&run)
        .iter()
        .filter(|j| j["final"] == true)
        .map(|j| j["step"].as_u64().unwrap())
        .collect();
    assert_eq!(
        finals,
        [130],
        "the final evaluation of a run continued is redone"
    );
    assert!(metrics::elapsed_runs_on(&run, 10));
    let _ = std::fs::remove_dir_all(&run);
}

/// `--resume --config` may change the `[train]` keys that change no result (checkpoint and log
/// intervals, evaluation cadence, the sample source): the resumed run takes them, says so in one
/// line, and trains the bits of an uninterrupted run; a key that changes results is still refused
/// (and named alone). Both used to be refused alike.
#[test]
fn resume_takes_settings_that_change_no_result() {
    let (run, straight) = (tmp("cadence"), tmp("cadence-straight"));
    let tiny = ["--preset", "tiny", "--steps", "60"];
    assert_eq!(train(&straight, &tiny).0, 0);
    assert_eq!(
        train(&run, &[&tiny[..], &["--stop-at", "30"]].concat()).0,
        0
    );
    let cfg = run.with_extension("toml");
    std::fs::write(
        &cfg,
        "[train]\ncheckpoint_every = 10\nlog_every = 5\neval_every = 0\nsamples = \"stream\"\n",
    )
    .unwrap();
    let (c, o) = (cfg.to_str().unwrap(), run.to_str().unwrap());
    let resume = ["train", "--out", o, "--resume", "--no-eval", "--config", c];
    let (code, err) = xscale(&resume);
    assert_eq!(code, 0, "{err}");
    let said: Vec<&str> = err
        .lines()
        .filter(|l| l.starts_with("--resume: "))
        .collect();
    assert!(
        said.len() == 1
            && said[0].contains("train.checkpoint_every = 10 (the run has 100)")
            && said[0].contains("train.log_every = 5 (the run has 10)")
            && said[0].contains("train.samples = \"stream\"")
            && said[0].contains("not what it computes"),
        "{err}"
    );
    assert_eq!(metrics::checkpoints(&run), [30, 40, 50, 60]);
    let config = std::fs::read_to_string(run.join("config.toml")).unwrap();
    assert!(config.contains("checkpoint_every = 10\n"), "{config}");
    let tensors = |r: &Path| {
        xscale::io::tensors::TensorFile::read(r.join("checkpoint.safetensors"))
            .unwrap()
            .tensors
    };
    assert!(
        tensors(&run) == tensors(&straight),
        "the resumed run trained other bits than the uninterrupted one"
    );
    // A key that changes results is refused, named alone.
    std::fs::write(&cfg, "[model]\ngamma = 1\n[train]\nlog_every = 7\n").unwrap();
    let (code, err) = xscale(&[&resume[..], &["--steps", "70"]].concat());
    assert_eq!(code, 2, "{err}");
    assert!(
        err.contains("model.gamma = 1 (the run has 2)") && !err.contains("log_every"),
        "{err}"
    );
    assert_eq!(step_of(&run), 60);
    let _ = std::fs::remove_dir_all(&run);
    let _ = std::fs::remove_dir_all(&straight);
    let _ = std::fs::remove_file(&cfg);
}

/// A resume takes the run's time from beside its checkpoint (`RUN/checkpoint-time.json`), not
/// from `metrics.jsonl`: with the log deleted, `elapsed_s` restarted at 0.
#[test]
fn elapsed_time_survives_a_deleted_metrics_file() {
    let run = tmp("elapsed");
    let (code, err) = train(
        &run,
        &["--preset", "tiny", "--steps", "100", "--stop-at", "40"],
    );
    assert_eq!(code, 0, "{err}");
    let at_40 = metrics::lines(&run)
        .iter()
        .find(|j| j["checkpoint"] == true)
        .and_then(|j| j["elapsed_s"].as_f64())
        .unwrap();
    let recorded: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(run.join("checkpoint-time.json")).unwrap())
            .unwrap();
    assert_eq!(recorded["step"], 40);
    assert_eq!(recorded["elapsed_s"].as_f64(), Some(at_40));
    std::fs::remove_file(run.join("metrics.jsonl")).unwrap();
    let (code, err) = train(&run, &["--resume", "--steps", "60"]);
    assert_eq!(code, 0, "{err}");
    let after: Vec<f64> = (metrics::lines(&run).iter())
        .filter_map(|j| j["elapsed_s"].as_f64())
        .collect();
    assert!(
        after.len() >= 2 && after.iter().all(|&t| t >= at_40),
        "the time at step 40 was {at_40} s; after the resume: {after:?}"
    );
    assert!(metrics::elapsed_runs_on(&run, 2));
    let _ = std::fs::remove_dir_all(&run);
}

/// With `--resume`, `[train] steps` in a `--config` file is the new total, as `--steps` (it was
/// ignored silently); a hand-edited `RUN/config.toml` is warned about (it was ignored silently).
#[test]
fn resume_takes_a_config_files_steps_and_warns_of_an_edited_config_toml() {
    let run = tiny_run("cfgsteps");
    let cfg = run.with_extension("toml");
    std::fs::write(&cfg, "[train]\nsteps = 9\n").unwrap();
    let (code, err) = train(&run, &["--resume", "--config", cfg.to_str().unwrap()]);
    assert_eq!(code, 0, "{err}");
    assert_eq!(step_of(&run), 9);
    let (code, err) = train(
        &run,
        &[
            "--resume",
            "--config",
            cfg.to_str().unwrap(),
            "--steps",
            "11",
        ],
    );
    assert_eq!(code, 0, "{err}");
    assert_eq!(step_of(&run), 11, "--steps wins over the file");
    let c = run.join("config.toml");
    let text = std::fs::read_to_string(&c).unwrap();
    assert!(text.contains("\ngamma = 2\n"), "{text}");
    std::fs::write(&c, text.replace("\ngamma = 2\n", "\ngamma = 3\n")).unwrap();
    let (code, err) = train(&run, &["--resume", "--steps", "12"]);
    assert_eq!(code, 0, "{err}");
    assert!(
        err.contains("warning:") && err.contains("model.gamma = 3 (the checkpoint has 2)"),
        "{err}"
    );
    let now = std::fs::read_to_string(&c).unwrap();
    assert!(now.contains("\ngamma = 2\n"), "rewritten: {now}");
    let _ = std::fs::remove_dir_all(&run);
    let _ = std::fs::remove_file(&cfg);
}

#[test]
fn a_diverging_run_is_stopped_and_says_why() {
    let run = tmp("diverge");
    let cfg = run.with_extension("toml");
    std::fs::write(
        &cfg,
        "[train.adam.shader]\nlr = 10.0\n[train.adam.grid_h]\nlr = 10.0\n[train.adam.grid_d]\nlr = 10.0\n[train.adam.deform]\nlr = 1.0\n[train.adam.appearance]\nlr = 10.0\n",
    )
    .unwrap();
    let (code, err) = train(
        &run,
        &[
            "--preset",
            "tiny",
            "--steps",
            "2000",
            "--config",
            cfg.to_str().unwrap(),
        ],
    );
    assert_ne!(code, 0, "{err}");
    assert!(
        err.contains("diverged") && err.contains("learning rate"),
        "{err}"
    );
    assert!(run.join("checkpoint-diverged.safetensors").is_file());
    let _ = std::fs::remove_dir_all(&run);
    let _ = std::fs::remove_file(&cfg);
}

#[test]
fn image_names_with_folders_keep_them_in_every_output() {
    let scene = tmp("nested-scene");
    copy_dir(&fixture(), &scene);
    // Use the transforms.json layout, whose names are `images/NNNN.png` (as nerfstudio writes).
    std::fs::write(scene.join("scene.toml"), "format = \"transforms\"\n").unwrap();
    let run = tmp("nested-run");
    let (code, err) = xscale(&[
        "train",
        "--scene",
        scene.to_str().unwrap(),
        "--out",
        run.to_str().unwrap(),
        "--preset",
        "tiny",
        "--steps",
        "10",
        "-q",
    ]);
    assert_eq!(code, 0, "{err}");
    for f in [
        "render/images/0000.png",
        "eval/images/0007.png",
        "eval.json",
    ] {
        assert!(run.join(f).is_file(), "{f} missing");
    }
    let frames = tmp("nested-frames");
    let (code, err) = xscale(&[
        "render",
        "--run",
        run.to_str().unwrap(),
        "--scene",
        scene.to_str().unwrap(),
        "--out",
        frames.to_str().unwrap(),
        "--views",
        "all",
    ]);
    assert_eq!(code, 0, "{err}");
    let n = std::fs::read_dir(frames.join("images")).unwrap().count();
    assert_eq!(n, 8, "one file per view");
    for d in [&scene, &run, &frames] {
        let _ = std::fs::remove_dir_all(d);
    }
}

#[test]
fn usage_errors_and_runtime_errors_have_distinct_exit_codes() {
    // A typo in a flag: clap's message with a suggestion, exit 64 (EX_USAGE).
    let (code, err) = xscale(&["train", "--presett", "tiny"]);
    assert_eq!(code, 64, "{err}");
    assert!(err.contains("--preset"), "{err}");
    let (code, err) = xscale(&["train", "--scene", "x", "--out", "y", "--preset", "cpux"]);
    assert_eq!(code, 64, "{err}");
    assert!(err.contains("tiny") && err.contains("paper"), "{err}");
    // A count of 0 where a count is needed is refused before any work (a distance over 0 samples
    // read as a perfect 0).
    let mesh = fixture().join("mesh.ply");
    let mesh = mesh.to_str().unwrap();
    let distance = |n| {
        xscale(&[
            "mesh-distance",
            "--mesh",
            mesh,
            "--truth",
            mesh,
            "--samples",
            n,
        ])
    };
    let (code, err) = distance("0");
    assert_eq!(code, 64, "{err}");
    assert!(
        err.contains("--samples") && err.contains("at least 1"),
        "{err}"
    );
    // More samples than memory holds: refused with the estimate before allocating (it used to
    // abort: `memory allocation of … bytes failed`, exit 134).
    let (code, err) = distance("100000000000");
    assert_eq!(code, 2, "{err}");
    assert!(
        err.contains("--samples 100000000000 would take about 3200.00 GB")
            && err.contains("use fewer --samples"),
        "{err}"
    );
    // A missing scene: a runtime error, exit 2, naming it.
    let run = tmp("usage");
    let (code, err) = xscale(&[
        "train",
        "--scene",
        "/nonexistent/scene",
        "--out",
        run.to_str().unwrap(),
    ]);
    assert_eq!(code, 2, "{err}");
    assert!(err.contains("/nonexistent/scene"), "{err}");
    let _ = std::fs::remove_dir_all(&run);
    // --help is not an error.
    assert_eq!(xscale(&["train", "--help"]).0, 0);
}

#[test]
fn eval_and_render_find_the_runs_scene() {
    let run = tmp("findscene");
    assert_eq!(train(&run, &["--preset", "tiny", "--steps", "10"]).0, 0);
    let json = run.join("e.json");
    let (code, err) = xscale(&[
        "eval",
        "--run",
        run.to_str().unwrap(),
        "--json",
        json.to_str().unwrap(),
    ]);
    assert_eq!(code, 0, "{err}");
    assert!(json.is_file());
    let frames = run.join("frames");
    let (code, err) = xscale(&[
        "render",
        "--run",
        run.to_str().unwrap(),
        "--out",
        frames.to_str().unwrap(),
    ]);
    assert_eq!(code, 0, "{err}");
    assert!(frames.join("0000.png").is_file());
    // The no-learning baseline through the same commands.
    let ulr = run.join("ulr");
    let (code, err) = xscale(&[
        "render",
        "--run",
        run.to_str().unwrap(),
        "--out",
        ulr.to_str().unwrap(),
        "--method",
        "ulr",
    ]);
    assert_eq!(code, 0, "{err}");
    assert!(ulr.join("0000.png").is_file());
    let (code, err) = xscale(&["eval", "--run", run.to_str().unwrap(), "--method", "ulr"]);
    assert_eq!(code, 0, "{err}");
    // A bare checkpoint does not know its scene: the message says what to give.
    let ck = run.join("checkpoint.safetensors");
    let (code, err) = xscale(&["eval", "--checkpoint", ck.to_str().unwrap()]);
    assert_eq!(code, 2);
    assert!(err.contains("--scene"), "{err}");
    let _ = std::fs::remove_dir_all(&run);
}

#[test]
fn limits_and_bad_settings_get_clear_messages() {
    let scene = fixture();
    // A huge --threads is capped instead of spending minutes creating threads.
    let (code, err) = xscale(&[
        "--threads",
        "100000",
        "cast",
        "--scene",
        scene.to_str().unwrap(),
    ]);
    assert_eq!(code, 0, "{err}");
    assert!(err.contains("--threads 100000: using"), "{err}");
    let run = tmp("limits");
    std::fs::create_dir_all(&run).unwrap();
    let cfg = run.join("bad.toml");
    // A shader without width.
    std::fs::write(&cfg, "[model.shader]\nwidth = 0\n").unwrap();
    let out = run.join("r");
    let (code, err) = train(
        &out,
        &["--preset", "tiny", "--config", cfg.to_str().unwrap()],
    );
    assert_eq!(code, 2);
    // The file and the line that set it.
    assert!(
        err.contains("bad.toml:2: invalid configuration: model.shader.width = 0"),
        "{err}"
    );
    // A bad learning rate names the field, not a Rust struct.
    std::fs::write(&cfg, "[train.adam.shader]\nlr = -1.0\n").unwrap();
    let (code, err) = train(
        &out,
        &["--preset", "tiny", "--config", cfg.to_str().unwrap()],
    );
    assert_eq!(code, 2);
    assert!(
        err.contains("adam.shader: lr = -1") && !err.contains("AdamGroup"),
        "{err}"
    );
    assert!(err.contains("bad.toml:1: "), "{err}");
    // A preset in the file that disagrees with --preset.
    std::fs::write(&cfg, "preset = \"cpu\"\n").unwrap();
    let (code, err) = train(
        &out,
        &["--preset", "tiny", "--config", cfg.to_str().unwrap()],
    );
    assert_eq!(code, 2);
    assert!(err.contains("conflicts with"), "{err}");
    // `init` and `batch` check it the same way (they used to take the file's preset silently);
    // the same preset in both places, or none on the command line, is accepted.
    let ck = run.join("ck.safetensors");
    let scene_s = scene.to_str().unwrap();
    let cfg_s = cfg.to_str().unwrap();
    let ck_s = ck.to_str().unwrap();
    for cmd in [
        &["init", "--scene", scene_s, "--out", ck_s][..],
        &["batch", "--scene", scene_s, "--size", "4", "--out", ck_s][..],
    ] {
        let (code, err) = xscale(&[cmd, &["--config", cfg_s, "--preset", "tiny"]].concat());
        assert_eq!(code, 2, "{cmd:?}: {err}");
        assert!(
            err.contains("--preset tiny conflicts with `preset = \"cpu\"` in"),
            "{cmd:?}: {err}"
        );
        assert!(!ck.exists(), "{cmd:?}: nothing written");
    }
    std::fs::write(&cfg, "preset = \"tiny\"\n").unwrap();
    let (code, err) = batch_file(&ck, &["--size", "4", "--config", cfg_s, "--preset", "tiny"]);
    assert_eq!(code, 0, "{err}");
    let (code, err) = xscale(&["init", "--scene", scene_s, "--out", ck_s, "--config", cfg_s]);
    assert_eq!(code, 0, "{err}");
    let _ = std::fs::remove_dir_all(&run);
}

/// A file-size limit (`ulimit -f`) used to kill the process with SIGXFSZ and no message; now the
/// write fails, the error names the file and a hint names the limit, and no temporary file stays.
/// A failed checkpoint (as on a full disk) says which step the run still holds.
#[cfg(unix)]
#[test]
fn a_file_size_limit_gets_a_message_not_a_silent_kill() {
    let run = tmp("fsize");
    let scene = fixture();
    let cmd = format!(
        "ulimit -f 100; exec '{}' train --scene '{}' --out '{}' --preset tiny --steps 20 --no-eval -q",
        env!("CARGO_BIN_EXE_xscale"),
        scene.display(),
        run.display()
    );
    let out = Command::new("sh").arg("-c").arg(&cmd).output().unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(2), "killed or wrong exit: {out:?}");
    assert!(err.contains("File too large"), "{err}");
    assert!(err.contains("ulimit -f"), "no hint: {err}");
    let leftovers: Vec<_> = std::fs::read_dir(&run)
        .unwrap()
        .filter_map(|e| e.ok())
        .filter(|e| e.file_name().to_string_lossy().contains(".tmp."))
        .collect();
    assert!(leftovers.is_empty(), "temporary files left: {leftovers:?}");
    assert!(
        err.contains(
            "step 20: the checkpoint could not be written; no earlier checkpoint was written"
        ),
        "{err}"
    );
    // A run with a checkpoint that cannot write the next one (a full disk acts the same) says
    // which step it still holds, and continues from it once the cause is gone.
    let (code, err) = train(&run, &["--preset", "tiny", "--steps", "10", "--overwrite"]);
    assert_eq!(code, 0, "{err}");
    let resume = format!(
        "ulimit -f 100; exec '{}' train --out '{}' --resume --steps 20 -q",
        env!("CARGO_BIN_EXE_xscale"),
        run.display()
    );
    let out = Command::new("sh").arg("-c").arg(&resume).output().unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(2), "{err}");
    assert!(
        err.contains(
            "checkpoint.safetensors still holds step 10; once the cause (below) is mended"
        ),
        "{err}"
    );
    let (code, err) = xscale(&[
        "train",
        "--out",
        run.to_str().unwrap(),
        "--resume",
        "--steps",
        "20",
        "-q",
    ]);
    assert_eq!(code, 0, "{err}");
    let _ = std::fs::remove_dir_all(&run);
}

/// `--batch 100000000` on a small scene used to be OOM-killed with no message; the memory check
/// refuses it before anything large is allocated, with the estimate and what to change.
#[test]
fn a_batch_that_cannot_fit_is_refused_before_allocation() {
    let run = tmp("hugebatch");
    let (code, err) = train(&run, &["--preset", "tiny", "--batch", "100000000"]);
    assert_eq!(code, 2, "{err}");
    assert!(
        err.contains("needs about") && err.contains("a smaller batch (--batch 25000000)"),
        "{err}"
    );
    assert!(
        !run.join("checkpoint.safetensors").exists(),
        "nothing was trained"
    );
    let _ = std::fs::remove_dir_all(&run);
}

/// `xscale batch` checks its batch against the memory as `train` does (it used to be killed by
/// the kernel at `--size 100000000`, and to panic with "capacity overflow" at `--size` 2^64 − 1):
/// refused before the batch is drawn, exit 2, naming `--size` and nothing written.
#[test]
fn a_batch_file_that_cannot_fit_is_refused_before_allocation() {
    let out = tmp("hugebatchfile");
    std::fs::create_dir_all(&out).unwrap();
    let file = out.join("b.safetensors");
    for size in ["1000000000", "18446744073709551615"] {
        let (code, err) = batch_file(&file, &["--preset", "tiny", "--size", size]);
        assert_eq!(code, 2, "{size}: {err}");
        assert!(
            err.contains("this batch needs about") && err.contains("a smaller batch (--size "),
            "{size}: {err}"
        );
        assert!(!file.exists(), "{size}: nothing written");
        // The size it suggests is at most a quarter of the one refused (for 2^64 − 1: what fits,
        // not a quarter of it).
        let suggested: u64 = err.split("--size ").nth(1).unwrap()[..]
            .trim_end_matches(|c: char| !c.is_ascii_digit())
            .parse()
            .unwrap();
        assert!(suggested <= 250_000_000, "{size}: {err}");
    }
    let _ = std::fs::remove_dir_all(&out);
}

/// A scene that holds no view out trains, and says there is no final evaluation (instead of
/// skipping it without a word); one that holds every view out is refused, saying how to hold out
/// fewer.
#[test]
fn a_scene_without_held_out_views_gets_a_word() {
    let scene = tmp("noholdout-scene");
    copy_dir(&fixture(), &scene);
    set_split(&scene, "holdout_every = 0");
    let run = tmp("noholdout-run");
    let (code, err) = xscale(&[
        "train",
        "--scene",
        scene.to_str().unwrap(),
        "--out",
        run.to_str().unwrap(),
        "--preset",
        "tiny",
        "--steps",
        "5",
    ]);
    assert_eq!(code, 0, "{err}");
    assert!(err.contains("no held-out views"), "{err}");
    assert!(!run.join("eval.json").exists());
    // The other end: every view held out (a one- or two-view scene under the default split).
    set_split(&scene, "holdout_every = 1");
    let run2 = tmp("allheldout-run");
    let (code, err) = train_on(&scene, &run2, &["--preset", "tiny"]);
    assert_eq!(code, 2, "{err}");
    assert!(
        err.contains("no training views (all 8 are held out")
            && err.contains("holdout_every = N")
            && err.contains("scene.toml"),
        "{err}"
    );
    for d in [&scene, &run, &run2] {
        let _ = std::fs::remove_dir_all(d);
    }
}

/// `--frames 0` used to render one frame; it is a value the flag does not take (a usage error,
/// refused before the model is loaded), like `--batch 0` (it was a run-time error naming the
/// config field `train.batch_pixels`).
#[test]
fn zero_frames_or_batch_is_a_usage_error() {
    let out = tmp("frames0");
    let (code, err) = xscale(&[
        "render",
        "--checkpoint",
        "/nonexistent/checkpoint.safetensors",
        "--scene",
        fixture().to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
        "--path",
        "0,1",
        "--frames",
        "0",
    ]);
    assert_eq!(code, 64, "{err}");
    assert!(
        err.contains("--frames") && err.contains("at least 1"),
        "{err}"
    );
    assert!(!out.exists(), "nothing written");
    let (code, err) = train(&out, &["--preset", "tiny", "--batch", "0"]);
    assert_eq!(code, 64, "{err}");
    assert!(
        err.contains("--batch") && err.contains("at least 1"),
        "{err}"
    );
    assert!(!out.exists(), "nothing written");
    // `xscale batch --size 0` too (it exited 2 after loading the scene).
    let (code, err) = batch_file(&out, &["--size", "0"]);
    assert_eq!(code, 64, "{err}");
    assert!(
        err.contains("--size") && err.contains("at least 1"),
        "{err}"
    );
    assert!(!out.exists(), "nothing written");
}

/// A value a flag does not take is a usage error (exit 64) before anything is read, for every
/// flag whose value alone decides (they used to exit 2, some only after loading the scene); the
/// message names the flag. Values that need the scene to judge stay run-time errors (exit 2).
#[test]
fn flag_values_a_flag_does_not_take_are_usage_errors() {
    let out = tmp("flag-values");
    let o = out.to_str().unwrap();
    let (scene, ck) = (fixture(), "/nonexistent/checkpoint.safetensors");
    let scene = scene.to_str().unwrap();
    let mesh = fixture().join("mesh.ply");
    let m = mesh.to_str().unwrap();
    let render = ["render", "--checkpoint", ck, "--scene", scene, "--out", o];
    let ablate = ["ablate", "--scene", scene, "--out", o];
    let bench_q = ["bench-quality", "--scene", scene, "--out", o];
    let bench_g = ["bench-geometry", "--scene", scene, "--out", o];
    let cases: Vec<(Vec<&str>, &str)> = vec![
        (
            vec!["decimate", "--in", m, "--out", o, "--ratio", "0"],
            "--ratio",
        ),
        (
            vec!["decimate", "--in", m, "--out", o, "--ratio", "1.5"],
            "--ratio",
        ),
        (
            vec!["decimate", "--in", m, "--out", o, "--ratio", "nan"],
            "--ratio",
        ),
        (
            vec!["subdivide", "--in", m, "--out", o, "--levels", "7"],
            "--levels",
        ),
        ([&render[..], &["--gamma", "0"]].concat(), "--gamma"),
        ([&render[..], &["--gamma", "9"]].concat(), "--gamma"),
        (
            [&render[..], &["--downsample", "0"]].concat(),
            "--downsample",
        ),
        ([&render[..], &["--path", "0"]].concat(), "--path"),
        ([&render[..], &["--scale", "0"]].concat(), "--scale"),
        (vec!["cast", "--scene", scene, "--gamma", "5"], "--gamma"),
        ([&bench_q[..], &["--minutes", "0"]].concat(), "--minutes"),
        ([&bench_q[..], &["--configs", "foo"]].concat(), "--configs"),
        ([&ablate[..], &["--ratio", "2"]].concat(), "--ratio"),
        ([&ablate[..], &["--minutes=-1"]].concat(), "--minutes"),
        ([&ablate[..], &["--subdivide", "7"]].concat(), "--subdivide"),
        ([&bench_g[..], &["--decimate", "2"]].concat(), "--decimate"),
        ([&bench_g[..], &["--rms=0.1,-1"]].concat(), "--rms"),
    ];
    for (args, flag) in cases {
        let (code, err) = xscale(&args);
        assert_eq!(code, 64, "{args:?}: {err}");
        assert!(err.contains(flag), "{args:?}: {err}");
    }
    assert!(!out.exists(), "nothing written");
}

/// A negative number given as the next argument (`--max-abs -1`, as users type it) reaches the
/// flag's own check, as `--max-abs=-1` does: `invalid value '-1' for '--max-abs …': …`, exit 64
/// (clap took it for a flag: `unexpected argument '-1' found`, with the tip to write `-- -1`).
#[test]
fn negative_values_after_a_flag_get_the_flags_own_message() {
    let out = tmp("negative-values");
    let o = out.to_str().unwrap();
    let (scene, ck) = (fixture(), "/nonexistent/checkpoint.safetensors");
    let scene = scene.to_str().unwrap();
    let mesh = fixture().join("mesh.ply");
    let m = mesh.to_str().unwrap();
    let render = ["render", "--checkpoint", ck, "--scene", scene, "--out", o];
    let ablate = ["ablate", "--scene", scene, "--out", o];
    let bench_q = ["bench-quality", "--scene", scene, "--out", o];
    let bench_g = ["bench-geometry", "--scene", scene, "--out", o];
    let dump = ["dump", "--checkpoint", ck, "--batch", ck, "--out", o];
    let compare = ["compare", ck, ck];
    let cases: Vec<(Vec<&str>, &str)> = vec![
        ([&compare[..], &["--max-abs", "-1"]].concat(), "--max-abs"),
        (
            [&compare[..], &["--max-rel", "-0.001"]].concat(),
            "--max-rel",
        ),
        (
            [&compare[..], &["--max-rel-peak", "-0.5"]].concat(),
            "--max-rel-peak",
        ),
        (
            [&dump[..], &["--kink-threshold", "-1"]].concat(),
            "--kink-threshold",
        ),
        (
            vec!["decimate", "--in", m, "--out", o, "--ratio", "-0.5"],
            "--ratio",
        ),
        ([&render[..], &["--scale", "-2"]].concat(), "--scale"),
        ([&ablate[..], &["--ratio", "-1"]].concat(), "--ratio"),
        ([&ablate[..], &["--minutes", "-1"]].concat(), "--minutes"),
        ([&bench_q[..], &["--minutes", "-1"]].concat(), "--minutes"),
        ([&bench_g[..], &["--rms", "-1"]].concat(), "--rms"),
        ([&bench_g[..], &["--rms", "0.1,-1"]].concat(), "--rms"),
        (
            [&bench_g[..], &["--decimate", "-0.1"]].concat(),
            "--decimate",
        ),
    ];
    for (args, flag) in cases {
        let (code, err) = xscale(&args);
        assert_eq!(code, 64, "{args:?}: {err}");
        assert!(
            err.contains(&format!("for '{flag} <")),
            "{args:?}: not the flag's own message: {err}"
        );
    }
    assert!(!out.exists(), "nothing written");
}

/// A run trained on a mesh given with `--mesh` whose file is gone: `eval`/`render --run` and
/// `--resume` say which mesh and what to do (they said only "cannot read").
#[test]
fn a_runs_mesh_that_is_gone_is_named() {
    let run = tmp("gone-mesh");
    std::fs::create_dir_all(&run).unwrap();
    let mesh = run.join("copy.ply");
    std::fs::copy(fixture().join("mesh.ply"), &mesh).unwrap();
    let r = run.join("run");
    let (code, err) = train(
        &r,
        &[
            "--preset",
            "tiny",
            "--steps",
            "10",
            "--stop-at",
            "5",
            "--mesh",
            mesh.to_str().unwrap(),
        ],
    );
    assert_eq!(code, 0, "{err}");
    std::fs::remove_file(&mesh).unwrap();
    let (code, err) = xscale(&["eval", "--run", r.to_str().unwrap()]);
    assert_eq!(code, 2, "{err}");
    assert!(
        err.contains("copy.ply") && err.contains("no longer exists") && err.contains("--mesh"),
        "{err}"
    );
    let (code, err) = xscale(&["train", "--out", r.to_str().unwrap(), "--resume", "-q"]);
    assert_eq!(code, 2, "{err}");
    assert!(
        err.contains("copy.ply") && err.contains("no longer exists") && err.contains("--mesh"),
        "{err}"
    );
    // Its new place given with --mesh: the resume checks it is the same mesh, then records it.
    let moved = run.join("moved.ply");
    let resume_on = |m: &Path| {
        xscale(&[
            "train",
            "--out",
            r.to_str().unwrap(),
            "--resume",
            "--mesh",
            m.to_str().unwrap(),
            "--no-eval",
            "-q",
        ])
    };
    let src = fixture().join("mesh.ply");
    let (src, dst) = (src.to_str().unwrap(), moved.to_str().unwrap());
    let decimate = ["decimate", "--in", src, "--ratio", "0.5", "--out", dst];
    assert_eq!(xscale(&decimate).0, 0);
    let (code, err) = resume_on(&moved);
    assert_eq!(code, 2, "another mesh is refused: {err}");
    assert!(err.contains("mesh changed"), "{err}");
    std::fs::copy(fixture().join("mesh.ply"), &moved).unwrap();
    let (code, err) = resume_on(&moved);
    assert_eq!(code, 0, "{err}");
    assert_eq!(step_of(&r), 10);
    let cfg = std::fs::read_to_string(r.join("config.toml")).unwrap();
    assert!(cfg.contains("moved.ply"), "{cfg}");
    let (code, err) = xscale(&["eval", "--run", r.to_str().unwrap()]);
    assert_eq!(code, 0, "eval finds the mesh's new place: {err}");
    let _ = std::fs::remove_dir_all(&run);
}

/// A run `xscale train --overwrite` replaces takes a tool's settings file (`variant.toml`) with
/// it, so `ablate`/`bench-geometry` never take the new run for their own stopped one.
#[test]
fn overwriting_a_tools_run_drops_its_settings() {
    let run = tmp("settings");
    assert_eq!(train(&run, &["--preset", "tiny", "--steps", "5"]).0, 0);
    std::fs::write(run.join("variant.toml"), "preset = \"tiny\"\n").unwrap();
    let (code, err) = train(&run, &["--preset", "tiny", "--steps", "5"]);
    assert_ne!(code, 0);
    assert!(err.contains("variant.toml"), "{err}");
    let (code, err) = train(&run, &["--preset", "tiny", "--steps", "5", "--overwrite"]);
    assert_eq!(code, 0, "{err}");
    assert!(!run.join("variant.toml").exists());
    let _ = std::fs::remove_dir_all(&run);
}

/// `eval` / `render --run` on a scene whose cameras or split changed since the run was trained
/// on it warn (the scores would be for views the model did not learn or was not held out
/// from); the scene as trained, or another copy of it, does not. Training views among the
/// scored ones are named (their scores measure fitting, not novel views).
#[test]
fn eval_warns_when_the_runs_scene_changed() {
    let scene = tmp("changed-scene");
    copy_dir(&fixture(), &scene);
    let run = tmp("changed-run");
    let r = run.to_str().unwrap();
    train_tiny_5(&scene, &run);
    let (code, err) = xscale(&["eval", "--run", r]);
    assert_eq!(code, 0, "{err}");
    assert!(!err.contains("warning: the scene"), "{err}");
    assert!(
        !err.contains("training views"),
        "held-out views only: {err}"
    );
    // A training view among the scored ones is named, and listed in the JSON.
    let json = run.join("mixed.json");
    let (code, err) = xscale(&[
        "eval",
        "--run",
        r,
        "--views",
        "0000,0001",
        "--json",
        json.to_str().unwrap(),
    ]);
    assert_eq!(code, 0, "{err}");
    assert!(
        err.contains("1 of the 2 scored views are training views (0001.png)"),
        "{err}"
    );
    let j: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&json).unwrap()).unwrap();
    assert_eq!(j["training_views"], serde_json::json!(["0001.png"]));
    let (_, err) = xscale(&["eval", "--run", r, "--scene", fixture().to_str().unwrap()]);
    assert!(
        !err.contains("warning: the scene"),
        "a copy of the same scene: {err}"
    );
    set_split(&scene, "holdout_every = 3");
    for cmd in [
        &["eval", "--run", r][..],
        &[
            "render",
            "--run",
            r,
            "--views",
            "0000",
            "--out",
            &format!("{r}/r2"),
        ],
    ] {
        let (code, err) = xscale(cmd);
        assert_eq!(code, 0, "{err}");
        assert!(
            err.contains("its train/test split changed since the run") && err.contains(r),
            "{cmd:?}: {err}"
        );
    }
    let _ = std::fs::remove_dir_all(&scene);
    let _ = std::fs::remove_dir_all(&run);
}

/// A run trained on a transforms.json with an applied_transform read as written (`"keep"`, as
/// xscale read every such file before it undid them) and resumed with the map undone is refused
/// as a changed scene, with the way back named.
#[test]
fn resuming_across_the_applied_transform_change_names_the_setting() {
    let scene = tmp("applied-scene");
    copy_dir(&fixture(), &scene);
    let p = scene.join("transforms.json");
    let mut j: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&p).unwrap()).unwrap();
    j["applied_transform"] = serde_json::json!([[1, 0, 0, 1], [0, 1, 0, 0], [0, 0, 1, 0]]);
    std::fs::write(&p, serde_json::to_string(&j).unwrap()).unwrap();
    let keep = "format = \"transforms\"\napplied_transform = \"keep\"\n";
    std::fs::write(scene.join("scene.toml"), keep).unwrap();
    let run = tmp("applied-run");
    let r = run.to_str().unwrap();
    train_tiny_5(&scene, &run);
    std::fs::write(scene.join("scene.toml"), "format = \"transforms\"\n").unwrap();
    let (code, err) = xscale(&["train", "--out", r, "--resume", "--steps", "10", "-q"]);
    assert_eq!(code, 2, "{err}");
    assert!(
        err.contains("its cameras changed") && err.contains("applied_transform = \"keep\""),
        "{err}"
    );
    std::fs::write(scene.join("scene.toml"), keep).unwrap();
    let (code, err) = xscale(&[
        "train",
        "--out",
        r,
        "--resume",
        "--steps",
        "10",
        "-q",
        "--no-eval",
    ]);
    assert_eq!(code, 0, "{err}");
    let _ = std::fs::remove_dir_all(&scene);
    let _ = std::fs::remove_dir_all(&run);
}
