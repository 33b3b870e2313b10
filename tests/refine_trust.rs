//! The mesh refinement's trust region (`[model.refine] trust_batches`, `trust_holdout`;
//! src/refine/trust.rs): bit-identical on 1, 2 and 4 threads, exact resume across accepted and
//! rejected updates, a rejected update leaves the mesh where it was, and the validation-view
//! variant runs. Its own test binary: it sets `XSCALE_REFINE_LOG` (process-wide) to read each
//! update's decision.

use std::path::Path;
use xscale::run::trainer::train;
use xscale::train::config::RunConfig;
use xscale::train::state::TrainState;

#[path = "common/pool.rs"]
mod pool;
use pool::in_pool;
#[path = "common/refine_run.rs"]
mod refine_run;
use refine_run::{cfg, fixture, opts, tmp};

/// The shared refinement run (`common/refine_run.rs`: steps 40 to 144 of 160, updates every 17
/// steps, so the resume point 100 falls between two) with the features anchored, each update
/// tested on two acceptance batches; `margin` decides how many are kept.
fn trust_cfg(margin: f64, holdout: u32) -> RunConfig {
    let mut c = cfg();
    let r = &mut c.model.refine;
    r.anchored = true;
    r.trust_batches = 2;
    r.trust_halvings = 1;
    r.trust_margin = margin;
    r.trust_holdout = holdout;
    r.prior = 1e-3;
    c.validate().unwrap();
    c
}

/// Run `f` with the refinement log at `log` (removed first); return the log's trust decisions
/// as (step, accepted).
fn logged<T>(log: &Path, f: impl FnOnce() -> T) -> (T, Vec<(u64, bool)>) {
    let _ = std::fs::remove_file(log);
    std::env::set_var("XSCALE_REFINE_LOG", log);
    let out = f();
    std::env::remove_var("XSCALE_REFINE_LOG");
    let text = std::fs::read_to_string(log).unwrap_or_default();
    let decisions = text
        .lines()
        .filter_map(|l| {
            let v: serde_json::Value = serde_json::from_str(l).unwrap();
            let t = v.get("trust")?;
            Some((
                v["step"].as_u64().unwrap(),
                t["accepted"].as_bool().unwrap(),
            ))
        })
        .collect();
    let _ = std::fs::remove_file(log);
    (out, decisions)
}

/// The tests of this binary run one at a time (the log variable is process-wide).
static SERIAL: std::sync::Mutex<()> = std::sync::Mutex::new(());

fn offsets(run: &Path) -> Vec<f32> {
    let st = TrainState::load(&run.join("checkpoint.safetensors")).unwrap();
    st.ckpt.refine.unwrap().offsets
}

#[test]
fn trust_region_is_thread_independent_resumes_exactly_and_rejects_by_holding_still() {
    let _serial = SERIAL.lock().unwrap_or_else(|e| e.into_inner());
    let c = trust_cfg(0.0, 0);
    let mut finals = Vec::new();
    let mut logs = Vec::new();
    for threads in [1, 2, 4] {
        let run = tmp(&format!("straight{threads}"));
        let (r, log) = logged(&tmp(&format!("log{threads}")), || {
            in_pool(threads, || {
                train(&fixture(), &run, c.clone(), &opts(false, None))
            })
        });
        r.unwrap();
        finals.push(std::fs::read(run.join("checkpoint.safetensors")).unwrap());
        logs.push(log);
        let _ = std::fs::remove_dir_all(&run);
    }
    assert!(finals[0] == finals[1], "1 and 2 threads differ");
    assert!(finals[0] == finals[2], "1 and 4 threads differ");
    assert_eq!(logs[0], logs[1]);
    // Updates after steps 57, 74, 91 (then 108, 125, 142, 144): both outcomes before the
    // resume point, so the resumed run continues across each.
    let log = &logs[0];
    assert_eq!(log.len(), 7, "{log:?}");
    let early: Vec<bool> = log.iter().filter(|d| d.0 <= 100).map(|d| d.1).collect();
    assert!(
        early.contains(&true) && early.contains(&false),
        "want accepted and rejected updates before step 100: {log:?}"
    );
    // Stopped at 100 and resumed (2 threads): the same bytes and decisions.
    let split = tmp("split");
    let (_, log_split) = logged(&tmp("log-split"), || {
        in_pool(2, || {
            let s = train(&fixture(), &split, c.clone(), &opts(false, Some(100))).unwrap();
            assert!(s.interrupted && s.steps == 100);
            train(&fixture(), &split, c.clone(), &opts(true, None)).unwrap();
        })
    });
    assert!(
        std::fs::read(split.join("checkpoint.safetensors")).unwrap() == finals[1],
        "a resumed trust-region run differs from the uninterrupted one"
    );
    assert_eq!(&log_split, log);
    // Stopped after 74 steps, the last of which made an update (no rebuild yet), and resumed.
    let cut = tmp("cut");
    let (_, log_cut) = logged(&tmp("log-cut"), || {
        in_pool(2, || {
            train(&fixture(), &cut, c.clone(), &opts(false, Some(74))).unwrap();
            train(&fixture(), &cut, c.clone(), &opts(true, None)).unwrap();
        })
    });
    assert!(
        std::fs::read(cut.join("checkpoint.safetensors")).unwrap() == finals[1],
        "a run resumed right after an update differs from the uninterrupted one"
    );
    assert_eq!(
        log_cut.iter().map(|d| d.1).collect::<Vec<_>>(),
        log.iter().map(|d| d.1).collect::<Vec<_>>()
    );
    let moved = offsets(&split);
    assert!(
        moved.iter().any(|&t| t != 0.0),
        "accepted updates move the mesh"
    );
    let _ = std::fs::remove_dir_all(&split);

    // A margin no update meets: every update is rejected and the mesh never moves.
    let still = tmp("still");
    let (r, log) = logged(&tmp("log-still"), || {
        in_pool(2, || {
            train(&fixture(), &still, trust_cfg(0.9, 0), &opts(false, None))
        })
    });
    r.unwrap();
    assert!(log.len() == 7 && log.iter().all(|d| !d.1), "{log:?}");
    assert!(offsets(&still).iter().all(|&t| t == 0.0));
    let _ = std::fs::remove_dir_all(&still);
}

#[test]
fn validation_views_variant_is_thread_independent_and_configs_are_checked() {
    let _serial = SERIAL.lock().unwrap_or_else(|e| e.into_inner());
    // The tiny fixture's training views: every second one is a validation view.
    let c = trust_cfg(0.0, 2);
    let mut finals = Vec::new();
    for threads in [1, 2] {
        let run = tmp(&format!("holdout{threads}"));
        in_pool(threads, || {
            train(&fixture(), &run, c.clone(), &opts(false, None))
        })
        .unwrap();
        finals.push(std::fs::read(run.join("checkpoint.safetensors")).unwrap());
        let _ = std::fs::remove_dir_all(&run);
    }
    assert!(finals[0] == finals[1], "1 and 2 threads differ");
    let check = |text: &str, want: &str| {
        let e = RunConfig::from_toml_str(text, "tiny", "r.toml").unwrap_err();
        let msg = format!("{e:#}");
        assert!(msg.contains("r.toml") && msg.contains(want), "{msg}");
    };
    check("[model.refine]\ntrust_margin = 1.5\n", "trust_margin");
    check("[model.refine]\ntrust_holdout = 4\n", "trust_batches");
    check(
        "[model.refine]\ntrust_batches = 2\ntrust_holdout = 1\n",
        "trust_holdout = 1",
    );
    check("[model.refine]\nprior = -1\n", "prior");
    // Off by default and absent from saved configs; set, it round-trips.
    let plain = RunConfig::from_toml_str("[model.refine]\nenabled = true\n", "cpu", "p").unwrap();
    assert!(!plain.to_toml().contains("trust"), "{}", plain.to_toml());
    assert_eq!(
        RunConfig::from_toml_str(&c.to_toml(), "tiny", "again").unwrap(),
        c
    );
}
