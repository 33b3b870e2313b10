//! End-to-end training on the bundled `tiny` fixture: exact resume, thread-count independence,
//! and that training actually learns.

use std::path::{Path, PathBuf};
use xscale::io::tensors::TensorFile;
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

/// The run's model file's bytes followed by its optimizer state's (`optimizer.safetensors`).
fn checkpoint_bytes(run: &Path) -> Vec<u8> {
    let mut b = std::fs::read(run.join("checkpoint.safetensors")).unwrap();
    b.extend(std::fs::read(run.join("optimizer.safetensors")).unwrap());
    b
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
    let (f64_bytes, f64_state) = resume_exact(c, "f64");
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
        f64_state,
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
    let (ssim, _) = resume_exact(c.clone(), "ssim");
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
    let (_, st) = resume_exact(c, "auto");
    let (model, f) = st.to_tensor_files().unwrap();
    let mask = &f.get("adam.mask.grid_h.table").unwrap().data;
    let entries = st.ckpt.model.layout.get("grid_h.table").unwrap().shape[0];
    assert_eq!(mask.len(), entries.div_ceil(8));
    let rows = mask.iter().map(|b| b.count_ones() as usize).sum::<usize>();
    assert!(rows > 0 && rows < entries, "{rows} of {entries} rows kept");
    assert_eq!(f.get("adam.m.grid_h.table").unwrap().shape[0], rows);
    // A grid entry's two features step together: one step count per kept row.
    assert_eq!(f.get("adam.t.grid_h.table").unwrap().shape, vec![rows]);
    // The MLPs step every scalar every step: written whole, without a row mask.
    assert!(!f.tensors.contains_key("adam.mask.shader.layers.0.weight"));
    // Fewer than half of grid H's rows stepped: the model file stores those rows only, with
    // the same mask as the Adam state.
    assert_eq!(&model.get("grid_h.table.mask").unwrap().data, mask);
    assert!(!model.tensors.contains_key("grid_h.table"));
    let st = TrainState::from_tensor_files(&model, &f).unwrap();
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
/// be the same bytes (model file and optimizer state). Returns them and the state they hold.
fn resume_exact(c: RunConfig, tag: &str) -> (Vec<u8>, TrainState) {
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
        finals.push((
            a,
            TrainState::load(&straight.join("checkpoint.safetensors")).unwrap(),
        ));
        let _ = std::fs::remove_dir_all(&straight);
        let _ = std::fs::remove_dir_all(&split);
    }
    assert!(
        finals[0].0 == finals[1].0,
        "{tag}: 1 and 2 threads give different checkpoints"
    );
    finals.pop().unwrap()
}

/// A run of the `cpu` preset (tables from the scene) stepped by hand, `steps` steps.
fn stepped_auto_run(steps: u64, seed: u64) -> TrainState {
    use xscale::model::params::Grads;
    let mut c = RunConfig::preset("cpu").unwrap();
    c.train.budget = xscale::train::config::StepBudget::Fixed;
    c.train.steps = steps;
    c.train.batch_pixels = 512;
    c.train.seed = seed;
    let prepared = xscale::train::setup::prepare(&fixture(), &c, true, &mut |_| {}).unwrap();
    let mut st = TrainState::init(c, &prepared, &mut |_| {}).unwrap();
    let mut grads = Grads::new(&st.ckpt.model.layout);
    grads.inputs = false;
    while st.step < steps {
        let b = xscale::train::sampler::sample_batch(
            &prepared.samples,
            &prepared.tracer,
            seed,
            st.step,
            512,
        );
        st.step(&b, &mut grads).unwrap();
    }
    st
}

/// The model file of a run with tables from the scene stores a table most rows of which no ray
/// reached by its stepped rows (`grid_h.table.mask`, `.kept`, header `init_seed`); loading
/// draws the other rows again from the seed, and every parameter comes back bit for bit — the
/// rows left out are exactly their initial values. The pair (model, optimizer state) loads to
/// the very state trained; a file of another step or run, or a damaged one, is refused with an
/// error naming the file and what was expected.
#[test]
fn stepped_tables_load_back_bit_identical() {
    let st = stepped_auto_run(40, 3);
    let (model, opt) = st.to_tensor_files().unwrap();
    assert_eq!(model.meta("init_seed").unwrap(), "3");
    let rows = st.ckpt.model.layout.get("grid_h.table").unwrap().shape[0];
    let kept = model.get("grid_h.table.kept").unwrap().shape[0];
    assert!(kept > 0 && kept * 2 < rows, "{kept} of {rows} rows");
    assert!(!model.tensors.keys().any(|k| k.starts_with("adam.")));
    assert!(opt.tensors.keys().all(|k| k.starts_with("adam.")));
    let (mb, ob) = (model.to_bytes().unwrap(), opt.to_bytes().unwrap());
    let named = |b: &[u8], name: &str| {
        let mut f = TensorFile::from_bytes(b, name).unwrap();
        f.source = Some(name.into());
        f
    };
    let (model, opt) = (
        named(&mb, "RUN/checkpoint.safetensors"),
        named(&ob, "RUN/optimizer.safetensors"),
    );
    let back = TrainState::from_tensor_files(&model, &opt).unwrap();
    let bits = |p: &[f32]| p.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
    assert!(bits(&back.ckpt.params) == bits(&st.ckpt.params));
    assert_eq!(back.adam.state, st.adam.state);
    assert_eq!(back.step, st.step);
    // The model alone, as render and eval read it.
    let m = xscale::model::checkpoint::Checkpoint::from_tensor_file(&model).unwrap();
    assert!(bits(&m.params) == bits(&st.ckpt.params));
    // Saved again: the same bytes.
    let (m2, o2) = back.to_tensor_files().unwrap();
    assert!(m2.to_bytes().unwrap() == mb && o2.to_bytes().unwrap() == ob);

    // The optimizer state of another step (or run) is not this model's.
    let later = stepped_auto_run(41, 3);
    let (_, other) = later.to_tensor_files().unwrap();
    let other = named(&other.to_bytes().unwrap(), "OTHER/optimizer.safetensors");
    let e = format!(
        "{:#}",
        TrainState::from_tensor_files(&model, &other).err().unwrap()
    );
    assert!(
        e.contains(
            "OTHER/optimizer.safetensors is not the optimizer state of RUN/checkpoint.safetensors"
        ) && e.contains("step 41")
            && e.contains("step 40"),
        "{e}"
    );
    // A model file with no optimizer state is not a resumable checkpoint on its own.
    let e = format!("{:#}", TrainState::from_tensor_file(&model).err().unwrap());
    assert!(e.contains("optimizer.safetensors"), "{e}");
    // Damaged files: each error names the file and the tensor or key, and what was expected.
    let damaged = |edit: &dyn Fn(&mut TensorFile), want: &[&str]| {
        let mut f = model.clone();
        edit(&mut f);
        let e = format!(
            "{:#}",
            xscale::model::checkpoint::Checkpoint::from_tensor_file(&f)
                .err()
                .unwrap_or_else(|| panic!("loaded despite damage (expected {want:?})"))
        );
        for w in want {
            assert!(e.contains(w), "{w:?} not in: {e}");
        }
    };
    use xscale::io::tensors::{DType, Tensor};
    damaged(
        &|f| {
            f.metadata.remove("init_seed");
        },
        &["RUN/checkpoint.safetensors", "init_seed"],
    );
    damaged(
        &|f| f.set_meta("init_seed", "x"),
        &["RUN/checkpoint.safetensors", "init_seed", "not an integer"],
    );
    damaged(
        &|f| {
            let mut m = f.get("grid_h.table.mask").unwrap().data.clone();
            m.push(1); // a byte more than the table's rows need
            let n = m.len();
            f.insert(
                "grid_h.table.mask",
                Tensor::from_bytes(DType::U8, vec![n], m).unwrap(),
            );
        },
        &[
            "RUN/checkpoint.safetensors",
            "grid_h.table.mask",
            "expected U8",
        ],
    );
    damaged(
        &|f| {
            let t = f.get("grid_h.table.kept").unwrap().clone();
            let v = t.to_f32().unwrap();
            f.insert(
                "grid_h.table.kept",
                Tensor::f32(vec![t.shape[0] - 1, 2], &v[2..]).unwrap(),
            );
        },
        &[
            "RUN/checkpoint.safetensors",
            "grid_h.table.kept",
            "expected F32",
            "one row per bit",
        ],
    );
    damaged(
        &|f| {
            f.tensors.remove("grid_h.table.kept");
        },
        &["missing tensor grid_h.table.kept"],
    );
}

/// The rule by bytes (`checkpoint::stores_by_rows`): a table is stored by its stepped rows when
/// that saves at least a quarter of its bytes, whatever the share of rows stepped — so a table
/// 60 % of whose rows are kept is stored by them (the 50 % rule before kept it whole) and one 80 %
/// of whose rows are kept stays whole; either way the parameters load back bit for bit.
#[test]
fn tables_stored_by_rows_when_that_saves_a_quarter() {
    use xscale::model::checkpoint::{stores_by_rows, Checkpoint};
    let st = stepped_auto_run(30, 4);
    let stepped = st.adam.stepped_rows();
    let bits = |p: &[f32]| p.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
    for share in [0.6, 0.8] {
        // The stepped rows and as many unstepped ones as make up `share` of each table (a row
        // never stepped holds its initial value, so keeping it is as right as leaving it out).
        let with = |name: &str| -> anyhow::Result<Vec<u32>> {
            let rows = st.ckpt.model.layout.get(name).unwrap().shape[0];
            let was = &stepped.iter().find(|(n, _)| *n == name).unwrap().1;
            let want = (share * rows as f64) as usize;
            assert!(
                was.len() < want,
                "{name}: {} of {rows} rows stepped",
                was.len()
            );
            let mut kept = was.clone();
            let mut r = 0u32;
            while kept.len() < want {
                if was.binary_search(&r).is_err() {
                    kept.push(r);
                }
                r += 1;
            }
            kept.sort_unstable();
            Ok(kept)
        };
        let model = st.ckpt.to_tensor_file_stepped(4, &with).unwrap();
        for name in ["grid_h.table", "grid_d.table"] {
            let rows = st.ckpt.model.layout.get(name).unwrap().shape[0];
            let kept = with(name).unwrap().len();
            let by_rows = stores_by_rows(rows, kept, 2);
            assert_eq!(by_rows, share < 0.7, "{name} at {share}");
            assert_eq!(
                model.tensors.contains_key(name),
                !by_rows,
                "{name} at {share}"
            );
            if by_rows {
                assert_eq!(model.get(&format!("{name}.kept")).unwrap().shape, [kept, 2]);
            }
        }
        let back = Checkpoint::from_tensor_file(
            &TensorFile::from_bytes(&model.to_bytes().unwrap(), "m").unwrap(),
        )
        .unwrap();
        assert!(bits(&back.params) == bits(&st.ckpt.params), "share {share}");
    }
}

/// `TrainState::save` writes the pair; a save cut after the model's rename (the new optimizer
/// state still in `optimizer.next.safetensors`) resumes from the new pair; a model file alone
/// or beside another step's optimizer state is refused, naming both files.
#[test]
fn the_pair_is_committed_by_the_model_file() {
    let dir = tmp("pair");
    std::fs::create_dir_all(&dir).unwrap();
    let ck = dir.join("checkpoint.safetensors");
    let (a, b) = (stepped_auto_run(20, 0), stepped_auto_run(21, 0));
    a.save(&ck).unwrap();
    assert!(dir.join("optimizer.safetensors").is_file());
    assert!(!dir.join("optimizer.next.safetensors").exists());
    assert_eq!(TrainState::load(&ck).unwrap().step, 20);
    // Cut between the renames: the model is step 21, its state in `.next`.
    let (m, o) = b.to_tensor_files().unwrap();
    o.write_atomic(dir.join("optimizer.next.safetensors"))
        .unwrap();
    m.write_atomic(&ck).unwrap();
    let back = TrainState::load(&ck).unwrap();
    assert_eq!((back.step, back.adam.state == b.adam.state), (21, true));
    assert!(!dir.join("optimizer.next.safetensors").exists());
    // Cut before the model's rename: the step-20 pair, a stale `.next` ignored.
    a.save(&ck).unwrap();
    o.write_atomic(dir.join("optimizer.next.safetensors"))
        .unwrap();
    assert_eq!(TrainState::load(&ck).unwrap().step, 20);
    // A mismatched pair and a missing optimizer state.
    std::fs::remove_file(dir.join("optimizer.next.safetensors")).unwrap();
    o.write_atomic(dir.join("optimizer.safetensors")).unwrap();
    let e = format!("{:#}", TrainState::load(&ck).err().unwrap());
    assert!(
        e.contains("optimizer.safetensors is not the optimizer state of")
            && e.contains("checkpoint.safetensors"),
        "{e}"
    );
    std::fs::remove_file(dir.join("optimizer.safetensors")).unwrap();
    let e = format!("{:#}", TrainState::load(&ck).err().unwrap());
    assert!(
        e.contains("optimizer.safetensors") && e.contains("missing"),
        "{e}"
    );
    // The layout before the split: one file with the whole tables and the Adam state (`adam.*`)
    // still resumes, with no optimizer file beside it.
    let mut one = a.ckpt.to_tensor_file().unwrap();
    one.set_meta("step", "20");
    one.set_meta("run_config", a.cfg.to_toml());
    a.adam.save_compact(&mut one).unwrap();
    one.write_atomic(&ck).unwrap();
    let back = TrainState::load(&ck).unwrap();
    assert_eq!(back.step, 20);
    assert_eq!(back.adam.state, a.adam.state);
    assert!(back.ckpt.params == a.ckpt.params);
    let _ = std::fs::remove_dir_all(&dir);
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
