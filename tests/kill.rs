//! Crash safety: training killed with SIGKILL at 20 moments (many of them inside a checkpoint
//! write: one is written every 5 steps) always leaves a checkpoint that loads, a stale lock that
//! the next run takes over, and resuming to the end writes the same checkpoint bytes as a run
//! never killed.

use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::Duration;

fn fixture() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("fixtures/tiny")
}

fn tmp(name: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("xscale-test-kill-{}-{name}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    d
}

fn args<'a>(run: &'a str, scene: &'a str, cfg: &'a str) -> Vec<&'a str> {
    vec![
        "train",
        "--scene",
        scene,
        "--out",
        run,
        "--preset",
        "tiny",
        "--config",
        cfg,
        "--no-eval",
        "-q",
    ]
}

#[test]
fn sigkill_at_random_moments_never_loses_the_run() {
    let scene = fixture();
    let dir = tmp("work");
    std::fs::create_dir_all(&dir).unwrap();
    let cfg = dir.join("c.toml");
    std::fs::write(
        &cfg,
        "[train]\nsteps = 400\nbatch_pixels = 512\ncheckpoint_every = 5\neval_every = 0\n",
    )
    .unwrap();
    let (scene_s, cfg_s) = (scene.to_str().unwrap(), cfg.to_str().unwrap());
    let bin = env!("CARGO_BIN_EXE_xscale");
    // The uninterrupted run.
    let straight = dir.join("straight");
    let st = Command::new(bin)
        .args(args(straight.to_str().unwrap(), scene_s, cfg_s))
        .status()
        .unwrap();
    assert!(st.success());
    // Killed 20 times at pseudo-random moments (a fixed sequence, so failures reproduce).
    let run = dir.join("killed");
    let run_s = run.to_str().unwrap();
    let mut x: u64 = 0x9E37_79B9_7F4A_7C15;
    let mut started = false;
    let mut loaded = 0;
    for k in 0..20 {
        x ^= x << 13;
        x ^= x >> 7;
        x ^= x << 17;
        let wait = Duration::from_millis(60 + x % 400);
        let mut a = args(run_s, scene_s, cfg_s);
        if started {
            a.push("--resume");
        }
        let mut child = Command::new(bin)
            .args(&a)
            .stderr(Stdio::null())
            .spawn()
            .unwrap();
        std::thread::sleep(wait);
        let _ = child.kill(); // SIGKILL
        let _ = child.wait();
        let ck = run.join("checkpoint.safetensors");
        if ck.exists() {
            started = true;
            let s = xscale::train::state::TrainState::load(&ck).unwrap_or_else(|e| {
                panic!("kill {k} after {wait:?}: the checkpoint does not load: {e:#}")
            });
            assert!(s.step <= 400);
            loaded += 1;
        } else {
            // Killed before the first checkpoint: start afresh next time.
            let _ = std::fs::remove_dir_all(&run);
        }
    }
    assert!(
        loaded >= 10,
        "only {loaded} of 20 kills came after a checkpoint: the test tests little"
    );
    // Finish (the stale lock of the last killed process is taken over) and compare.
    let mut a = args(run_s, scene_s, cfg_s);
    if started {
        a.push("--resume");
    }
    let out = Command::new(bin).args(&a).output().unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let (x1, x2) = (
        std::fs::read(straight.join("checkpoint.safetensors")).unwrap(),
        std::fs::read(run.join("checkpoint.safetensors")).unwrap(),
    );
    assert!(
        x1 == x2,
        "the killed-and-resumed run differs from the uninterrupted one"
    );
    let _ = std::fs::remove_dir_all(&dir);
}
