//! End-to-end training on the bundled `tiny` fixture: exact resume, thread-count independence,
//! and that training actually learns.

use std::path::{Path, PathBuf};
use xscale::run::trainer::{train, TrainOptions};
use xscale::train::config::RunConfig;
use xscale::train::state::TrainState;

#[path = "common/pool.rs"]
mod pool;
use pool::in_pool;

fn fixture() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("fixtures/tiny")
}

fn tmp(name: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("xscale-test-train-{}-{name}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    d
}

fn cfg(steps: u64) -> RunConfig {
    let mut c = RunConfig::preset("tiny").unwrap();
    c.train.steps = steps;
    c.train.batch_pixels = 512;
    c.train.eval_every = 50;
    c.train.checkpoint_every = 30;
    c
}

fn quiet(resume: bool, stop_at: Option<u64>) -> TrainOptions {
    TrainOptions {
        resume,
        stop_at,
        no_final_eval: true,
        quiet: true,
        ..Default::default()
    }
}

fn checkpoint_bytes(run: &Path) -> Vec<u8> {
    std::fs::read(run.join("checkpoint.safetensors")).unwrap()
}

/// 200 steps straight, and 100 + resume + 100: byte-identical checkpoints, with 1 and 2 threads
/// (and the same across thread counts).
#[test]
fn resume_is_exact_and_thread_independent() {
    resume_exact(cfg(200), "f32");
}

/// The same with the model's arithmetic in f64 (`[train] arithmetic = "f64"`, train/precision.rs):
/// exact resume and thread independence, a result that differs from f32 training (the switch is
/// real) and a held-out loss as good.
#[test]
fn f64_arithmetic_resumes_exactly_and_differs_from_f32() {
    let mut c = cfg(200);
    c.train.arithmetic = xscale::train::config::Arithmetic::F64;
    let f64_bytes = resume_exact(c, "f64");
    let f32_run = tmp("f32ref");
    in_pool(2, || {
        train(&fixture(), &f32_run, cfg(200), &quiet(false, None))
    })
    .unwrap();
    let f32_bytes = checkpoint_bytes(&f32_run);
    assert!(
        f64_bytes != f32_bytes,
        "f64 arithmetic trained the same bits as f32"
    );
    let (a, b) = (
        TrainState::load(&f32_run.join("checkpoint.safetensors")).unwrap(),
        TrainState::from_tensor_file(
            &xscale::io::tensors::TensorFile::from_bytes(&f64_bytes, "f64 run").unwrap(),
        )
        .unwrap(),
    );
    let diff = a
        .ckpt
        .params
        .iter()
        .zip(&b.ckpt.params)
        .map(|(x, y)| (x - y).abs())
        .fold(0.0f32, f32::max);
    assert!(
        diff > 0.0 && diff < 0.5,
        "largest parameter difference {diff}"
    );
    let _ = std::fs::remove_dir_all(&f32_run);
}

/// The D-SSIM term on patch batches (`[model] ssim_weight`, `[train] patch`): exact resume and
/// thread independence, and a result that differs from L1 on single pixels (the switch is real).
#[test]
fn ssim_patches_resume_exactly_and_differ_from_l1() {
    let mut c = cfg(200);
    c.model.ssim_weight = 0.2;
    c.train.patch = 4;
    c.validate().unwrap();
    let ssim = resume_exact(c.clone(), "ssim");
    let l1 = tmp("l1ref");
    in_pool(2, || train(&fixture(), &l1, cfg(200), &quiet(false, None))).unwrap();
    assert!(
        ssim != checkpoint_bytes(&l1),
        "the D-SSIM term trained the same bits as L1"
    );
    let _ = std::fs::remove_dir_all(&l1);
    // Configuration errors name the key.
    c.train.patch = 0;
    let e = c.validate().unwrap_err().to_string();
    assert!(e.contains("ssim_weight") && e.contains("patch"), "{e}");
    c.train.patch = 5;
    let e = c.validate().unwrap_err().to_string();
    assert!(e.contains("batch_pixels") && e.contains("25"), "{e}");
}

/// The `cpu` preset's tables sized from the scene: its checkpoint leaves out the Adam state of
/// the grid entries no ray reached (`adam.mask.*`), loads back to the very state trained (what
/// the full layout writes), and a resumed run is still byte-identical on 1 and 2 threads.
#[test]
fn compact_adam_state_resumes_exactly() {
    let mut c = RunConfig::preset("cpu").unwrap();
    assert_eq!(c.train.table_size, xscale::train::config::TableSize::Auto);
    c.train.budget = xscale::train::config::StepBudget::Fixed;
    c.train.steps = 200;
    c.train.batch_pixels = 512;
    c.train.eval_every = 50;
    c.train.checkpoint_every = 30;
    let bytes = resume_exact(c, "auto");
    let f = xscale::io::tensors::TensorFile::from_bytes(&bytes, "auto run").unwrap();
    let mask = &f.get("adam.mask.grid_h.table").unwrap().data;
    let entries = f.get("grid_h.table").unwrap().shape[0];
    assert_eq!(mask.len(), entries.div_ceil(8));
    let rows = mask.iter().map(|b| b.count_ones() as usize).sum::<usize>();
    assert!(rows > 0 && rows < entries, "{rows} of {entries} rows kept");
    assert_eq!(f.get("adam.m.grid_h.table").unwrap().shape[0], rows);
    // A grid entry's two features step together: one step count per kept row.
    assert_eq!(f.get("adam.t.grid_h.table").unwrap().shape, vec![rows]);
    // The MLPs step every scalar every step: written whole, without a row mask.
    assert!(!f.tensors.contains_key("adam.mask.shader.layers.0.weight"));
    let st = TrainState::from_tensor_file(&f).unwrap();
    let mut full = xscale::io::tensors::TensorFile::default();
    st.adam.save(&mut full).unwrap();
    let names: Vec<(String, Vec<usize>)> = st
        .adam
        .slots
        .iter()
        .map(|s| (s.name.clone(), s.shape.clone()))
        .collect();
    let back = xscale::train::adam::AdamState::load(&full, &names).unwrap();
    assert_eq!(back.state, st.adam.state);
    // The left-out rows are exactly the never-stepped ones.
    let r = st.adam.range("grid_h.table").unwrap();
    let t = st.adam.t(r);
    let width = t.len() / entries;
    let stepped = (0..entries)
        .filter(|&e| t[e * width..(e + 1) * width].iter().any(|&x| x > 0))
        .count();
    assert_eq!(stepped, rows);
}

/// Train `c` straight and interrupted + resumed, on 1 and 2 threads; all four checkpoints must
/// be the same bytes. Returns them.
fn resume_exact(c: RunConfig, tag: &str) -> Vec<u8> {
    let mut finals = Vec::new();
    for threads in [1, 2] {
        let straight = tmp(&format!("straight{tag}{threads}"));
        in_pool(threads, || {
            train(&fixture(), &straight, c.clone(), &quiet(false, None))
        })
        .unwrap();
        let split = tmp(&format!("split{tag}{threads}"));
        let s = in_pool(threads, || {
            train(&fixture(), &split, c.clone(), &quiet(false, Some(100)))
        })
        .unwrap();
        assert!(s.interrupted && s.steps == 100);
        assert_eq!(
            TrainState::load(&split.join("checkpoint.safetensors"))
                .unwrap()
                .step,
            100
        );
        in_pool(threads, || {
            train(&fixture(), &split, c.clone(), &quiet(true, None))
        })
        .unwrap();
        let (a, b) = (checkpoint_bytes(&straight), checkpoint_bytes(&split));
        assert!(
            a == b,
            "{tag}, {threads} threads: resumed checkpoint differs from the uninterrupted one"
        );
        finals.push(a);
        let _ = std::fs::remove_dir_all(&straight);
        let _ = std::fs::remove_dir_all(&split);
    }
    assert!(
        finals[0] == finals[1],
        "{tag}: 1 and 2 threads give different checkpoints"
    );
    finals.pop().unwrap()
}

/// Training lowers the loss and reaches a held-out PSNR well above the untrained model's.
#[test]
fn training_learns() {
    let run = tmp("learns");
    let mut c = cfg(300);
    c.train.batch_pixels = 1024;
    let s = train(
        &fixture(),
        &run,
        c,
        &TrainOptions {
            quiet: true,
            ..Default::default()
        },
    )
    .unwrap();
    let m = s.final_scores.expect("held-out views were evaluated");
    // The untrained model outputs ~0.5 grey (PSNR ≈ 8–10 dB on these images).
    assert!(
        m.psnr_masked > 18.0,
        "held-out masked PSNR {}",
        m.psnr_masked
    );
    let lines = std::fs::read_to_string(run.join("metrics.jsonl")).unwrap();
    let losses: Vec<f64> = lines
        .lines()
        .filter_map(|l| serde_json::from_str::<serde_json::Value>(l).ok())
        .filter_map(|v| v.get("loss").and_then(|x| x.as_f64()))
        .collect();
    assert!(
        losses.len() > 5 && losses.last().unwrap() < &(0.5 * losses[0]),
        "{losses:?}"
    );
    for f in [
        "config.toml",
        "eval.json",
        "render/0000.png",
        "eval/0007.png",
    ] {
        assert!(run.join(f).is_file(), "{f} missing");
    }
    let _ = std::fs::remove_dir_all(&run);
}

#[test]
fn resume_without_checkpoint_is_an_error() {
    let run = tmp("nockpt");
    let e = train(&fixture(), &run, cfg(10), &quiet(true, None))
        .err()
        .unwrap();
    assert!(format!("{e:#}").contains("checkpoint.safetensors"), "{e:#}");
}

/// An interrupt raised while the scene is prepared (casting a large scene's views takes seconds
/// to minutes) stops there: no step trained, no checkpoint written, a resumed run's checkpoint
/// untouched. It used to sit through the casting, train one step and save it.
#[test]
fn an_interrupt_during_setup_stops_before_training() {
    static STOP: std::sync::atomic::AtomicBool = std::sync::atomic::AtomicBool::new(true);
    let run = tmp("setup-stop");
    let opts = TrainOptions {
        interrupt: Some(&STOP),
        ..quiet(false, None)
    };
    let s = train(&fixture(), &run, cfg(10), &opts).unwrap();
    assert!(s.interrupted && s.steps == 0);
    assert!(!run.join("checkpoint.safetensors").exists());
    assert!(!run.join("metrics.jsonl").exists());
    // Train 10 steps, then resume towards 20 with the flag raised: the step-10 checkpoint stays.
    train(&fixture(), &run, cfg(10), &quiet(false, None)).unwrap();
    let before = checkpoint_bytes(&run);
    let opts = TrainOptions {
        interrupt: Some(&STOP),
        ..quiet(true, None)
    };
    let s = train(&fixture(), &run, cfg(20), &opts).unwrap();
    assert!(s.interrupted);
    assert_eq!(checkpoint_bytes(&run), before);
    let _ = std::fs::remove_dir_all(&run);
}

/// An interrupt during the final evaluation stops it between views (`evaluate_until` gives
/// `None`); a tool's run stopped there counts as stopped (`stopped_run_of`), so the tool
/// resumes it at its last step, which only evaluates, instead of training it again.
#[test]
fn an_interrupted_final_evaluation_is_resumed_not_retrained() {
    let run = tmp("eval-stop");
    let c = cfg(10);
    let opts = TrainOptions {
        settings: Some(c.results_toml()),
        ..quiet(false, None)
    };
    train(&fixture(), &run, c.clone(), &opts).unwrap();
    let state = TrainState::load(&run.join("checkpoint.safetensors")).unwrap();
    let prepared =
        xscale::train::setup::prepare(&fixture(), &state.cfg, true, &mut |_| {}).unwrap();
    let eval =
        |stop| xscale::run::trainer::evaluate_until(&state, &prepared, 0, None, stop).unwrap();
    assert!(eval(&|| true).is_none());
    assert_eq!(eval(&|| false).unwrap().len(), prepared.scene.test.len());
    // At its last step without eval.json (no final evaluation ran): stopped.
    assert!(xscale::run::run_dir::stopped_run_of(&run, &c));
    std::fs::write(run.join("eval.json"), "{}").unwrap();
    assert!(!xscale::run::run_dir::stopped_run_of(&run, &c));
    let _ = std::fs::remove_dir_all(&run);
}
