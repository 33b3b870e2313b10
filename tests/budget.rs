//! The training budget (`[train] budget`, `train/setup.rs` `resolve_budget`, SPEC §8): the `cpu`
//! preset chooses the step count from the training pixels when a run starts, prints it, stores it
//! in `config.toml` and the checkpoint (a resume continues to it); `--steps` and `[train] steps`
//! fix it; a run's own `config.toml` given back chooses it again.

use std::path::{Path, PathBuf};
use xscale::train::config::{RunConfig, StepBudget};
use xscale::train::setup::{budget_steps, prepare, BUDGET_MIN_STEPS};

#[path = "common/cli.rs"]
mod cli;
use cli::{fixture, xscale};

fn tmp(name: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("xscale-test-budget-{}-{name}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    d
}

fn stored(run: &Path) -> RunConfig {
    let text = std::fs::read_to_string(run.join("config.toml")).unwrap();
    RunConfig::from_stored_toml(&text, "config.toml").unwrap()
}

#[test]
fn the_cpu_budget_follows_the_pixels_is_stored_and_resumed() {
    // What the rule chooses for the fixture: its few pixels are under the floor.
    let cfg = RunConfig::preset("cpu").unwrap();
    assert_eq!(cfg.train.budget, StepBudget::Auto);
    let p = prepare(&fixture(), &cfg, false, &mut |_| {}).unwrap();
    let want = budget_steps(p.samples.len(), cfg.train.batch_pixels);
    assert_eq!(want, BUDGET_MIN_STEPS, "{} pixels", p.samples.len());

    let run = tmp("auto");
    let fx = fixture();
    let (scene, out) = (fx.to_str().unwrap(), run.to_str().unwrap());
    let (code, err) = xscale(&[
        "train",
        "--scene",
        scene,
        "--out",
        out,
        "--stop-at",
        "2",
        "--no-eval",
    ]);
    assert_eq!(code, 0, "{err}");
    assert!(
        err.contains(&format!("training budget (auto): {want} steps")),
        "{err}"
    );
    let c = stored(&run);
    assert_eq!((c.train.budget, c.train.steps), (StepBudget::Auto, want));
    // The resume continues to the stored count.
    let (code, err) = xscale(&[
        "train",
        "--out",
        out,
        "--resume",
        "--stop-at",
        "4",
        "--no-eval",
    ]);
    assert_eq!(code, 0, "{err}");
    assert!(err.contains(&format!("at step 2 of {want}")), "{err}");

    // --steps fixes it.
    let fixed = tmp("fixed");
    let (code, err) = xscale(&[
        "train",
        "--scene",
        scene,
        "--out",
        fixed.to_str().unwrap(),
        "--steps",
        "7",
        "--stop-at",
        "1",
        "--no-eval",
    ]);
    assert_eq!(code, 0, "{err}");
    assert!(err.contains("training budget (fixed): 7 steps"), "{err}");
    let c = stored(&fixed);
    assert_eq!((c.train.budget, c.train.steps), (StepBudget::Fixed, 7));
    for d in [run, fixed] {
        let _ = std::fs::remove_dir_all(d);
    }
}

#[test]
fn a_config_file_steps_fix_the_budget_unless_it_asks_for_auto() {
    let resolve = |text: &str| {
        let p = std::env::temp_dir().join(format!(
            "xscale-test-budget-{}-{}.toml",
            std::process::id(),
            text.len()
        ));
        std::fs::write(&p, text).unwrap();
        let r = RunConfig::resolve("cpu", Some(&p)).unwrap();
        let _ = std::fs::remove_file(&p);
        r
    };
    let c = resolve("[train]\nsteps = 9\n");
    assert_eq!((c.train.budget, c.train.steps), (StepBudget::Fixed, 9));
    // As a run's own config.toml holds them: the rule chooses again.
    let c = resolve("[train]\nsteps = 9\nbudget = \"auto\"\n");
    assert_eq!(c.train.budget, StepBudget::Auto);
    let c = resolve("[train]\nseed = 3\n");
    assert_eq!(c.train.budget, StepBudget::Auto, "other keys leave it auto");
    // Other presets keep their fixed counts; a config stored before the budget existed is fixed.
    for p in ["tiny", "paper"] {
        assert_eq!(
            RunConfig::preset(p).unwrap().train.budget,
            StepBudget::Fixed
        );
    }
    let old = RunConfig::preset("cpu")
        .unwrap()
        .to_toml()
        .replace("budget = \"auto\"\n", "");
    assert!(!old.contains("budget"), "{old}");
    let c = RunConfig::from_stored_toml(&old, "old").unwrap();
    assert_eq!(c.train.budget, StepBudget::Fixed);
}
