//! Grid H's level range (`train/setup.rs` `resolve_levels`, SPEC §8): `auto` follows the training
//! views' footprints with tiny-cuda-nn's per-level-scale formula, the same with streamed or cached
//! samples; a config file's `per_level_scale` or `finest_resolution` fixes it.

use std::path::PathBuf;
use xscale::model::config::per_level_scale_for;
use xscale::train::config::{LevelRange, RunConfig, TableSize};
use xscale::train::sampler::SampleMode;
use xscale::train::setup::{
    auto_levels, prepare, resolve_levels, resolve_table_sizes, AUTO_FINEST_MAX, LEVEL_QUANTILE,
};
use xscale::train::state::TrainState;

fn fixture() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("fixtures/tiny")
}

fn config(text: &str) -> anyhow::Result<RunConfig> {
    let p = std::env::temp_dir().join(format!(
        "xscale-test-levels-{}-{}.toml",
        std::process::id(),
        text.len()
    ));
    std::fs::write(&p, text).unwrap();
    let r = RunConfig::resolve("cpu", Some(&p));
    let _ = std::fs::remove_file(&p);
    r
}

#[test]
fn auto_follows_the_footprints_in_both_sample_modes() {
    let mut scales = Vec::new();
    for mode in [SampleMode::Stream, SampleMode::Cache] {
        let mut cfg = RunConfig::preset("cpu").unwrap();
        cfg.train.samples = mode;
        cfg.train.drop_fine_levels = false;
        assert_eq!(cfg.train.level_range, LevelRange::Auto);
        let p = prepare(&fixture(), &cfg, false, &mut |_| {}).unwrap();
        let fp = p.samples.footprint_quantile_min(LEVEL_QUANTILE).unwrap();
        let min = p.samples.footprint_min().unwrap() as f64;
        assert!(
            fp >= min,
            "the quantile is not below the smallest footprint"
        );
        let msgs = resolve_levels(&mut cfg, &p.samples);
        assert!(msgs[0].contains("auto"), "{msgs:?}");
        let preset_scale = RunConfig::preset("cpu")
            .unwrap()
            .model
            .grid_h
            .per_level_scale;
        let g = &cfg.model.grid_h;
        let finest = (1.0 / fp).max(32.0);
        let levels = auto_levels(16.0, finest, preset_scale, 16);
        assert_eq!(g.levels, levels);
        let want = per_level_scale_for(16.0, finest, levels);
        assert_eq!(g.per_level_scale, want);
        assert!(
            want <= preset_scale * (1.0 + 1e-12),
            "levels are added rather than spread thinner: {want} > {preset_scale}"
        );
        assert_eq!(g.finest_resolution, Some((1.0 / fp).max(32.0)));
        scales.push(g.per_level_scale);
    }
    assert_eq!(
        scales[0], scales[1],
        "stream and cache choose the same range"
    );

    // `fixed` leaves the preset's scale alone.
    let mut cfg = RunConfig::preset("cpu").unwrap();
    cfg.train.level_range = LevelRange::Fixed;
    let before = cfg.model.grid_h.clone();
    let p = prepare(&fixture(), &cfg, false, &mut |_| {}).unwrap();
    cfg.train.drop_fine_levels = false;
    resolve_levels(&mut cfg, &p.samples);
    assert_eq!(cfg.model.grid_h, before);
}

/// `level_range = "auto"` with a `per_level_scale` keeps the automatic range and adds levels at
/// that spacing: fewer, wider-spaced levels up to the same finest level.
#[test]
fn auto_with_a_spacing_adds_levels_at_that_spacing() {
    let mut cfg = config(
        "[train]\nlevel_range = \"auto\"\ndrop_fine_levels = false\n[model.grid_h]\nlevels = 1\nper_level_scale = 2.0\n",
    )
    .unwrap();
    assert_eq!(cfg.train.level_range, LevelRange::Auto);
    assert_eq!(cfg.model.grid_h.per_level_scale, 2.0);
    let p = prepare(&fixture(), &cfg, false, &mut |_| {}).unwrap();
    let fp = p.samples.footprint_quantile_min(LEVEL_QUANTILE).unwrap();
    resolve_levels(&mut cfg, &p.samples);
    let finest = (1.0 / fp).max(32.0);
    let g = &cfg.model.grid_h;
    assert_eq!(g.levels, auto_levels(16.0, finest, 2.0, 1));
    assert_eq!(
        g.per_level_scale,
        per_level_scale_for(16.0, finest, g.levels)
    );
    assert!(
        g.per_level_scale <= 2.0 * (1.0 + 1e-12) && g.per_level_scale > 2f64.sqrt(),
        "about 2 apart: {}",
        g.per_level_scale
    );
    assert_eq!(g.finest_resolution, Some(finest));
    // The preset's spacing on the same views needs more levels.
    let mut preset = RunConfig::preset("cpu").unwrap();
    preset.train.drop_fine_levels = false;
    resolve_levels(&mut preset, &p.samples);
    assert!(
        preset.model.grid_h.levels > g.levels,
        "{} levels at the preset's spacing, {} at 2",
        preset.model.grid_h.levels,
        g.levels
    );
}

#[test]
fn config_files_fix_the_range() {
    let c = config("[model.grid_h]\nper_level_scale = 1.5\n").unwrap();
    assert_eq!(c.train.level_range, LevelRange::Fixed);
    assert_eq!(c.model.grid_h.per_level_scale, 1.5);
    let c = config("[model.grid_h]\nfinest_resolution = 8192.0\n").unwrap();
    assert_eq!(c.train.level_range, LevelRange::Fixed);
    assert_eq!(
        c.model.grid_h.per_level_scale,
        per_level_scale_for(16.0, 8192.0, 16)
    );
    let e = format!(
        "{:#}",
        config("[model.grid_h]\nfinest_resolution = 8192.0\nper_level_scale = 1.5\n").unwrap_err()
    );
    assert!(e.contains("not both"), "{e}");
    let e = format!(
        "{:#}",
        config("[train]\nlevel_range = \"auto\"\n[model.grid_h]\nfinest_resolution = 4096.0\n")
            .unwrap_err()
    );
    assert!(
        e.contains("level_range") && e.contains("finest_resolution"),
        "{e}"
    );
    // A file that says nothing about the range keeps the preset's rule.
    assert_eq!(
        config("[train]\nsteps = 5\n").unwrap().train.level_range,
        LevelRange::Auto
    );
}

/// `auto_levels`: the configured count when the configured scale already reaches the finest
/// resolution, more levels (about the configured scale apart) when it does not, never above
/// `MAX_LEVELS`.
#[test]
fn auto_adds_levels_rather_than_thinning_them() {
    let b = per_level_scale_for(16.0, 2048.0, 16);
    assert_eq!(auto_levels(16.0, 2048.0, b, 16), 16);
    assert_eq!(auto_levels(16.0, 512.0, b, 16), 16);
    let l = auto_levels(16.0, 14079.0, b, 16);
    assert_eq!(l, 22, "16 · b^21 ≥ 14079 > 16 · b^20");
    let spread = per_level_scale_for(16.0, 14079.0, l);
    assert!(spread <= b && spread > 1.36, "{spread}");
    assert_eq!(
        auto_levels(16.0, 1e300, b, 16),
        xscale::model::hashgrid::MAX_LEVELS
    );
    assert_eq!(auto_levels(16.0, 16.0, b, 4), 4);
}

/// Through the CLI, as a user meets it: a `cpu` run (automatic range, footprint level weighting)
/// prints its choice, saves it in `config.toml` (levels, per-level scale, finest resolution: what
/// `eval`, `render` and other backends rebuild the model from), trains the same checkpoint bytes
/// with 1 and 2 threads, and `eval --run` scores it; `paper` keeps its fixed range unless asked.
#[test]
fn a_cpu_run_records_its_range_and_is_thread_independent() {
    let xs = |args: &[&str]| {
        let o = std::process::Command::new(env!("CARGO_BIN_EXE_xscale"))
            .args(args)
            .output()
            .unwrap();
        assert!(
            o.status.success(),
            "{args:?}: {}",
            String::from_utf8_lossy(&o.stderr)
        );
        String::from_utf8_lossy(&o.stdout).into_owned() + &String::from_utf8_lossy(&o.stderr)
    };
    let scene = fixture();
    let base = std::env::temp_dir().join(format!("xscale-test-levels-cli-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&base);
    let mut bytes = Vec::new();
    for threads in ["1", "2"] {
        let run = base.join(format!("t{threads}"));
        let out = xs(&[
            "train",
            "--scene",
            scene.to_str().unwrap(),
            "--out",
            run.to_str().unwrap(),
            "--steps",
            "4",
            "--batch",
            "256",
            "--no-eval",
            "--threads",
            threads,
        ]);
        assert!(out.contains("grid H level range (auto)"), "{out}");
        let saved = RunConfig::from_toml_str(
            &std::fs::read_to_string(run.join("config.toml")).unwrap(),
            "cpu",
            "config.toml",
        )
        .unwrap();
        // What resolve_levels chooses for this scene, independently of the run.
        let mut want = RunConfig::preset("cpu").unwrap();
        let p = prepare(&scene, &want, false, &mut |_| {}).unwrap();
        resolve_levels(&mut want, &p.samples);
        resolve_table_sizes(&mut want, &p.samples, &p.tracer);
        assert_eq!(saved.model.grid_h, want.model.grid_h);
        assert!(saved.model.grid_h.finest_resolution.is_some());
        bytes.push(std::fs::read(run.join("checkpoint.safetensors")).unwrap());
    }
    assert!(
        bytes[0] == bytes[1],
        "1 and 2 threads trained different bits"
    );
    let run = base.join("t1");
    let out = xs(&["eval", "--run", run.to_str().unwrap()]);
    assert!(out.contains("PSNR"), "{out}");
    // paper: fixed, unless the config asks for auto.
    let paper = RunConfig::preset("paper").unwrap();
    assert_eq!(paper.train.level_range, LevelRange::Fixed);
    let f = base.join("auto.toml");
    std::fs::write(&f, "[train]\nlevel_range = \"auto\"\n").unwrap();
    let c = RunConfig::resolve("paper", Some(&f)).unwrap();
    assert_eq!(c.train.level_range, LevelRange::Auto);
    assert_eq!(c.model.grid_h.log2_table_size, 22, "still the paper's grid");
    let _ = std::fs::remove_dir_all(&base);
}

/// A copy of the `tiny` fixture whose camera of `0001.png` (a close-up) has its focal length
/// multiplied by `zoom`: one view whose pixels are `zoom` times finer than they were.
fn zoomed_fixture(name: &str, zoom: f64) -> PathBuf {
    let dir =
        std::env::temp_dir().join(format!("xscale-test-levels-{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    for sub in ["images", "sparse/0"] {
        std::fs::create_dir_all(dir.join(sub)).unwrap();
        for e in std::fs::read_dir(fixture().join(sub)).unwrap() {
            let e = e.unwrap();
            std::fs::copy(e.path(), dir.join(sub).join(e.file_name())).unwrap();
        }
    }
    for f in ["mesh.ply", "scene.toml"] {
        std::fs::copy(fixture().join(f), dir.join(f)).unwrap();
    }
    let cams = dir.join("sparse/0/cameras.txt");
    let text = std::fs::read_to_string(&cams).unwrap();
    let out: Vec<String> = text
        .lines()
        .map(|l| {
            let mut f: Vec<String> = l.split_whitespace().map(str::to_string).collect();
            if f.first().map(String::as_str) == Some("2") {
                for i in [4, 5] {
                    f[i] = (f[i].parse::<f64>().unwrap() * zoom).to_string();
                }
                f.join(" ")
            } else {
                l.to_string()
            }
        })
        .collect();
    std::fs::write(&cams, out.join("\n") + "\n").unwrap();
    dir
}

/// One view with a focal length 10^6 times too long (pixels of 4e-10 of the scene): the
/// automatic range caps the finest level at what a grid holds and says so, and the model builds.
/// It used to ask for 60 levels up to 2.4e9 cells and every run failed building the model
/// ("config: grid_h: grid: scale of level 57 is 1291043200, expected a finite number in [0, 1e9]").
#[test]
fn auto_caps_the_finest_level_at_what_a_grid_holds() {
    let scene = zoomed_fixture("zoom", 1e6);
    let mut cfg = RunConfig::preset("cpu").unwrap();
    let p = prepare(&scene, &cfg, false, &mut |_| {}).unwrap();
    let fp = p.samples.footprint_quantile_min(LEVEL_QUANTILE).unwrap();
    assert!(fp < 1e-9, "the zoomed view is that fine: {fp}");
    let msgs = resolve_levels(&mut cfg, &p.samples);
    let warning = msgs
        .iter()
        .find(|m| m.starts_with("warning:"))
        .unwrap_or_else(|| panic!("{msgs:?}"));
    assert!(
        warning.contains("capped at 500000000 cells per unit") && warning.contains("xscale cast"),
        "{warning}"
    );
    assert_eq!(cfg.model.grid_h.finest_resolution, Some(AUTO_FINEST_MAX));
    cfg.validate().unwrap();
    xscale::model::hashgrid::HashGrid::try_new(&cfg.model.grid_h).unwrap();
    let _ = std::fs::remove_dir_all(&scene);
}

/// The memory check is made again once the automatic range has sized the model: a 1000× close-up
/// asks for 37 levels instead of 16, and a budget the preset's grid fits but that one does not is
/// refused before the model is allocated, naming the levels. The check used to be made only at
/// setup, on the preset's grid: `memory_gb = 0.6` trained a model needing 0.95 GB.
#[test]
fn the_memory_check_sees_the_levels_the_range_added() {
    let scene = zoomed_fixture("zoom-memory", 1e3);
    let mut cfg = RunConfig::preset("cpu").unwrap();
    cfg.train.memory_gb = 0.6;
    // The preset's 2^19 tables on every level (auto sizes make these 37 levels fit).
    cfg.train.table_size = TableSize::Fixed;
    let p = prepare(&scene, &cfg, false, &mut |_| {}).unwrap();
    let mut fixed = cfg.clone();
    fixed.train.level_range = LevelRange::Fixed;
    TrainState::init(fixed, &p, &mut |_| {}).expect("the preset's grid fits");
    let mut resolved = cfg.clone();
    resolve_levels(&mut resolved, &p.samples);
    assert!(
        resolved.model.grid_h.levels > 30,
        "{:?}",
        resolved.model.grid_h
    );
    let err = TrainState::init(cfg, &p, &mut |_| {})
        .err()
        .expect("refused")
        .to_string();
    assert!(
        err.contains("train.memory_gb = 0.6")
            && err.contains("level_range = \"fixed\"")
            && err.contains("the 37 the closest views ask for"),
        "{err}"
    );
    let _ = std::fs::remove_dir_all(&scene);
}

/// `xscale init` checks the model the level range sized, as `train` does: a budget the preset's
/// grid fits but the 37 levels a 1000× close-up asks for do not is refused, nothing written (it
/// wrote the checkpoint; only the setup's check of the configured grid ran).
#[test]
fn init_checks_the_memory_of_the_levels_the_range_added() {
    let scene = zoomed_fixture("zoom-init", 1e3);
    let cfg = scene.join("mem.toml");
    // The preset's 2^19 tables on every level (auto sizes make these 37 levels fit).
    std::fs::write(
        &cfg,
        "[train]\nmemory_gb = 0.6\n[model.grid_h]\nlog2_table_size = 19\n",
    )
    .unwrap();
    let out = scene.join("init.safetensors");
    let o = std::process::Command::new(env!("CARGO_BIN_EXE_xscale"))
        .args(["init", "--preset", "cpu", "--scene"])
        .arg(&scene)
        .arg("--config")
        .arg(&cfg)
        .arg("--out")
        .arg(&out)
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(2), "{err}");
    assert!(
        err.contains("train.memory_gb = 0.6") && err.contains("the 37 the closest views ask for"),
        "{err}"
    );
    assert!(!out.exists(), "init wrote {}", out.display());
    let _ = std::fs::remove_dir_all(&scene);
}
