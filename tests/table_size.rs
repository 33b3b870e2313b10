//! Per-level hash table sizes (`[model.grid_h] log2_table_size = "auto"`, `train/setup.rs`
//! `resolve_table_sizes`, SPEC §4.2 and §8): chosen from the surface cells the training rays
//! reach, the same with streamed or cached samples and on any thread count, carried by the
//! checkpoint; an integer keeps one size for every level.

use std::path::PathBuf;
use xscale::model::checkpoint::Checkpoint;
use xscale::model::config::GridConfig;
use xscale::model::hashgrid::{level_size, HashGrid};
use xscale::train::config::{RunConfig, TableSize};
use xscale::train::sampler::SampleMode;
use xscale::train::setup::{
    auto_log2_size, prepare, reached_cells, resolve_levels, resolve_table_sizes,
    TABLE_CEILING_LOG2, TABLE_FLOOR_LOG2,
};

fn fixture() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("fixtures/tiny")
}

fn config(name: &str, text: &str) -> anyhow::Result<RunConfig> {
    let p = std::env::temp_dir().join(format!(
        "xscale-test-table-{}-{name}.toml",
        std::process::id()
    ));
    std::fs::write(&p, text).unwrap();
    let r = RunConfig::resolve("cpu", Some(&p));
    let _ = std::fs::remove_file(&p);
    r
}

#[test]
fn auto_is_the_cpu_default_and_an_integer_fixes_it() {
    assert_eq!(
        RunConfig::preset("cpu").unwrap().train.table_size,
        TableSize::Auto
    );
    for p in ["tiny", "paper"] {
        assert_eq!(
            RunConfig::preset(p).unwrap().train.table_size,
            TableSize::Fixed,
            "{p}"
        );
    }
    let c = config("int", "[model.grid_h]\nlog2_table_size = 18\n").unwrap();
    assert_eq!(c.train.table_size, TableSize::Fixed);
    assert_eq!(c.model.grid_h.log2_table_size, 18);
    let c = config(
        "auto",
        "preset = \"paper\"\n[model.grid_h]\nlog2_table_size = \"auto\"\n",
    )
    .unwrap();
    assert_eq!(c.train.table_size, TableSize::Auto);
    assert_eq!(
        c.model.grid_h.log2_table_size, 22,
        "the preset's value stays"
    );
    let e = config("typo", "[model.grid_h]\nlog2_table_size = \"atuo\"\n").unwrap_err();
    let m = format!("{e:#}");
    assert!(m.contains("expected \"auto\" or an integer"), "{m}");
    let e = config(
        "both",
        "[model.grid_h]\nlog2_table_size = \"auto\"\nlog2_table_sizes = [12, 12]\n",
    )
    .unwrap_err();
    assert!(
        format!("{e:#}").contains("remove log2_table_sizes"),
        "{e:#}"
    );
}

#[test]
fn the_rule_rounds_and_clamps() {
    assert_eq!(auto_log2_size(0.0), TABLE_FLOOR_LOG2);
    assert_eq!(auto_log2_size(1e12), TABLE_CEILING_LOG2);
    // At least TABLE_HEADROOM = 8 entries per cell, the next power of two.
    assert_eq!(auto_log2_size(8192.0), 16);
    assert_eq!(auto_log2_size(8193.0), 17);
    assert_eq!(auto_log2_size(5000.0), 16);
}

fn grid(sizes: Option<Vec<u32>>) -> GridConfig {
    let mut g = RunConfig::preset("cpu").unwrap().model.grid_h;
    g.levels = 4;
    g.per_level_scale = 8.0;
    g.log2_table_size = 19;
    g.log2_table_sizes = sizes;
    g
}

#[test]
fn each_level_has_its_own_size() {
    // scales 15, 127, 1023, 8191: level 0 dense (16^3 = 4096 entries) whatever T_l.
    let g = HashGrid::new(&grid(Some(vec![12, 19, 14, 16])));
    let want = [4096usize, 1 << 19, 1 << 14, 1 << 16];
    for (l, &w) in want.iter().enumerate() {
        assert_eq!(g.level_entries(l), w, "level {l}");
    }
    assert!(g.dense[0] && !g.dense[1] && !g.dense[2] && !g.dense[3]);
    assert_eq!(g.n_entries(), want.iter().sum::<usize>());
    assert_eq!(level_size(128, 14), 1 << 14);
    // Absent: one T for all levels, as tiny-cuda-nn.
    let fixed = HashGrid::new(&grid(None));
    assert_eq!(fixed.level_entries(3), 1 << 19);
    // One value per level, each at most 31.
    let e = HashGrid::try_new(&grid(Some(vec![12, 19]))).unwrap_err();
    assert!(format!("{e}").contains("one per level"), "{e}");
    let e = HashGrid::try_new(&grid(Some(vec![12, 19, 32, 12]))).unwrap_err();
    assert!(format!("{e}").contains("log2_table_sizes[2] = 32"), "{e}");
}

#[test]
fn auto_sizes_follow_the_cells_and_are_the_same_streamed_or_cached_on_any_thread_count() {
    let mut seen: Vec<(Vec<f64>, GridConfig, GridConfig)> = Vec::new();
    for (mode, threads) in [
        (SampleMode::Stream, 1),
        (SampleMode::Cache, 2),
        (SampleMode::Cache, 1),
    ] {
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .unwrap();
        let got = pool.install(|| {
            let mut cfg = RunConfig::preset("cpu").unwrap();
            cfg.train.samples = mode;
            let p = prepare(&fixture(), &cfg, false, &mut |_| {}).unwrap();
            resolve_levels(&mut cfg, &p.samples);
            let cells = reached_cells(&cfg.model.grid_h, true, &p.samples, &p.tracer);
            let msgs = resolve_table_sizes(&mut cfg, &p.samples, &p.tracer);
            assert!(msgs[0].starts_with("grid H tables (auto"), "{msgs:?}");
            assert!(msgs[1].starts_with("grid D tables (auto"), "{msgs:?}");
            (cells, cfg.model.grid_h, cfg.model.deform.grid)
        });
        seen.push(got);
    }
    assert_eq!(seen[0], seen[1]);
    assert_eq!(seen[1], seen[2]);
    let (cells, h, d) = &seen[0];
    let t = h.log2_table_sizes.as_ref().unwrap();
    assert_eq!(t.len(), h.levels as usize);
    assert_eq!(
        d.log2_table_sizes.as_ref().unwrap().len(),
        d.levels as usize
    );
    // Levels dense with the preset's 2^19 stay dense; the others follow the rule.
    let fixed = HashGrid::new(&GridConfig {
        log2_table_sizes: None,
        log2_table_size: 19,
        ..h.clone()
    });
    let auto = HashGrid::new(h);
    let mut hashed = 0;
    for (l, (&c, &tl)) in cells.iter().zip(t).enumerate() {
        if fixed.dense[l] {
            assert_eq!(tl, 19, "level {l}");
            assert!(auto.dense[l], "level {l}");
            assert_eq!(auto.level_entries(l), fixed.level_entries(l));
        } else {
            assert_eq!(tl, auto_log2_size(c), "level {l}");
            hashed += 1;
        }
    }
    assert!(hashed > 5, "{hashed} hashed levels");
    // Grid D follows the rule but never grows past the preset's size (it may shrink).
    let d_cfg = RunConfig::preset("cpu").unwrap().model.deform.grid;
    let td = d.log2_table_sizes.as_ref().unwrap();
    assert!(td.iter().all(|&x| x <= d_cfg.log2_table_size), "{td:?}");
    assert!(td.iter().any(|&x| x < d_cfg.log2_table_size), "{td:?}");
    assert_eq!(d.log2_table_size, *td.iter().max().unwrap());
    assert!(HashGrid::new(d).n_params() <= HashGrid::new(&d_cfg).n_params());
    assert_eq!(h.log2_table_size, *t.iter().max().unwrap());
    // Coarse levels reach few cells, finer ones more (the fixture's 18k pixels).
    assert!(cells[0] > 0.0 && cells[0] < cells[5], "{cells:?}");
    // The whole model is far smaller than with 2^19 on every level.
    assert!(
        auto.n_params() * 2 < fixed.n_params(),
        "{} {}",
        auto.n_params(),
        fixed.n_params()
    );
}

#[test]
fn a_checkpoint_carries_the_sizes() {
    let mut cfg = RunConfig::preset("cpu").unwrap();
    cfg.train.samples = SampleMode::Cache;
    let p = prepare(&fixture(), &cfg, false, &mut |_| {}).unwrap();
    let (cfg, ckpt) = p.init_model(cfg, &mut |_| {}).unwrap();
    let path = std::env::temp_dir().join(format!("xscale-test-table-{}.st", std::process::id()));
    ckpt.save(&path).unwrap();
    let back = Checkpoint::load(&path).unwrap();
    let _ = std::fs::remove_file(&path);
    assert_eq!(back.model.cfg.grid_h, cfg.model.grid_h);
    assert_eq!(back.model.cfg.deform.grid, cfg.model.deform.grid);
    assert!(back.model.cfg.grid_h.log2_table_sizes.is_some());
    assert_eq!(back.model.grid_h.offsets, ckpt.model.grid_h.offsets);
    assert_eq!(back.params, ckpt.params);
}
