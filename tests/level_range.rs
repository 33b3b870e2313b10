//! Grid H's level range (`train/setup.rs` `resolve_levels`, SPEC §8): `auto` follows the training
//! views' footprints with tiny-cuda-nn's per-level-scale formula, the same with streamed or cached
//! samples; a config file's `per_level_scale` or `finest_resolution` fixes it.

use std::path::PathBuf;
use xscale::model::config::per_level_scale_for;
use xscale::train::config::{LevelRange, RunConfig};
use xscale::train::sampler::SampleMode;
use xscale::train::setup::{auto_levels, prepare, resolve_levels, LEVEL_QUANTILE};

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
        config("[train]\nlevel_range = \"auto\"\n[model.grid_h]\nper_level_scale = 1.5\n")
            .unwrap_err()
    );
    assert!(e.contains("level_range"), "{e}");
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
