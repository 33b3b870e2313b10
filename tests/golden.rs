//! Golden test (the correctness oracle): the Rust model against committed dumps of the
//! independent PyTorch reference (`reference/xscale_ref.py`), no Python needed.
//!
//! For every case directory of `fixtures/golden/` (checkpoint after 20 training steps, batch, and
//! the reference's `ref_f64.safetensors` + `ref_grid_f32.safetensors`, made by
//! `fixtures/golden/regenerate.sh`):
//! - the library's dump (`model::checkpoint::dump`, the code path of `xscale dump`) in f64 agrees
//!   with the PyTorch float64 dump under `tolerances-f64.toml` (1e-10 relative, with a 1e-10-of-
//!   the-tensor's-peak floor near zero) on every forward tensor, the loss and every gradient;
//! - the f32 dump agrees with the same float64 dump under `tolerances-f32.toml`;
//! - the f32 grid outputs `fwd.grid_h` / `fwd.grid_d` equal the reference's `grid-fma` (the
//!   SPEC §4.2 f32 fma chain emulated exactly in NumPy) bit for bit, in both positions modes;
//! - `xscale compare` (the built binary) passes the unmodified dump and, on a dump with one
//!   element changed, exits 1 naming the tensor and the element.
//!
//! The fixtures themselves are checked for the coverage the README claims (positions modes,
//! interpolations, deformation on/off, γ = 1 and 2, invalid sub-samples, view −1, trained ξ).

use std::path::{Path, PathBuf};
use std::process::Command;
use xscale::io::compare::{compare, Report, Status, Tolerances};
use xscale::io::tensors::{DType, Tensor, TensorFile};
use xscale::model::checkpoint::{dump, Checkpoint};
use xscale::model::config::{Interpolation, PositionMode};
use xscale::model::Batch;

fn golden_dir() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("fixtures/golden")
}

/// Case directories (those holding a reference dump), sorted.
fn cases() -> Vec<PathBuf> {
    let mut v: Vec<PathBuf> = std::fs::read_dir(golden_dir())
        .expect("fixtures/golden exists")
        .map(|e| e.unwrap().path())
        .filter(|p| p.join("ref_f64.safetensors").is_file())
        .collect();
    v.sort();
    assert!(
        v.len() >= 5,
        "expected >= 5 golden cases in fixtures/golden, found {v:?}"
    );
    v
}

fn name(case: &Path) -> String {
    case.file_name().unwrap().to_string_lossy().into_owned()
}

fn load(case: &Path) -> (Checkpoint, Batch) {
    let ck = Checkpoint::load(case.join("checkpoint.safetensors")).unwrap();
    let b = Batch::load(case.join("batch.safetensors")).unwrap();
    (ck, b)
}

fn tolerances(file: &str) -> Tolerances {
    Tolerances::read(golden_dir().join(file)).unwrap()
}

/// Every forward tensor, the loss and every gradient of the reference must have been compared
/// under a rule and passed; nothing may be missing from either side.
fn assert_all_pass(report: &Report, what: &str) {
    let table = report.to_table();
    assert_eq!(report.exit_code(), 0, "{what}:\n{table}");
    assert!(
        report.only_in_a.is_empty(),
        "{what}: only in the reference: {:?}",
        report.only_in_a
    );
    let mut compared = 0;
    for t in &report.tensors {
        let n = &t.name;
        if n.starts_with("fwd.") || n.starts_with("grad.") || n == "loss" || n.starts_with("batch.")
        {
            assert_eq!(t.status, Status::Pass, "{what}: {n}:\n{table}");
            compared += 1;
        }
    }
    assert!(
        compared >= 15,
        "{what}: only {compared} tensors compared:\n{table}"
    );
}

#[test]
fn f64_dump_matches_pytorch_float64() {
    let tol = tolerances("tolerances-f64.toml");
    for case in cases() {
        let (ck, b) = load(&case);
        let ours = dump::<f64>(&ck, &b).unwrap();
        let reference = TensorFile::read(case.join("ref_f64.safetensors")).unwrap();
        // The reference was made from this very checkpoint (guards against a partial regeneration).
        let ck_file = TensorFile::read(case.join("checkpoint.safetensors")).unwrap();
        assert_eq!(
            reference.meta("config").unwrap(),
            ck_file.meta("config").unwrap(),
            "{}: reference dump made from another checkpoint config",
            name(&case)
        );
        let report = compare(&reference, &ours, &tol);
        assert_all_pass(&report, &format!("{} f64", name(&case)));
        // Every gradient of the model is in the reference (the dump lists exactly the parameters).
        for k in ours.tensors.keys().filter(|k| k.starts_with("grad.")) {
            assert!(
                reference.tensors.contains_key(k),
                "{}: {k} missing from the reference",
                name(&case)
            );
        }
    }
}

#[test]
fn f32_dump_matches_pytorch_float64_within_f32_tolerances() {
    let tol = tolerances("tolerances-f32.toml");
    for case in cases() {
        let (ck, b) = load(&case);
        let ours = dump::<f32>(&ck, &b).unwrap();
        assert_eq!(ours.get("fwd.rgb").unwrap().dtype, DType::F32);
        let reference = TensorFile::read(case.join("ref_f64.safetensors")).unwrap();
        let report = compare(&reference, &ours, &tol);
        assert_all_pass(&report, &format!("{} f32", name(&case)));
    }
}

/// The f32 grid forward is the SPEC §4.2 fma chain bit for bit (0 ULP), in both positions
/// modes; the `tcnn` cases are the tiny-cuda-nn fp32 bit-compatibility claim.
#[test]
fn f32_grids_equal_reference_fma_chain_bit_for_bit() {
    let mut tcnn_cases = 0;
    for case in cases() {
        let (ck, b) = load(&case);
        let ours = dump::<f32>(&ck, &b).unwrap();
        let reference = TensorFile::read(case.join("ref_grid_f32.safetensors")).unwrap();
        let mut grids = vec!["fwd.grid_h"];
        if ck.model.grid_d.is_some() {
            grids.push("fwd.grid_d");
        }
        for g in grids {
            let a = reference.get(g).unwrap();
            let o = ours.get(g).unwrap();
            assert_eq!(
                (a.dtype, &a.shape),
                (DType::F32, &o.shape),
                "{}: {g}",
                name(&case)
            );
            let (av, ov) = (a.to_f32().unwrap(), o.to_f32().unwrap());
            let diff = av
                .iter()
                .zip(&ov)
                .position(|(x, y)| x.to_bits() != y.to_bits());
            if let Some(i) = diff {
                panic!(
                    "{} ({:?} positions): {g} element {i}: reference {:e} ({:#010x}), ours {:e} ({:#010x})",
                    name(&case),
                    ck.model.cfg.positions,
                    av[i],
                    av[i].to_bits(),
                    ov[i],
                    ov[i].to_bits()
                );
            }
            assert!(
                av.iter().any(|&v| v != 0.0),
                "{}: {g} is all zero",
                name(&case)
            );
        }
        // The same through the committed exact-grid tolerance file (what a backend author runs).
        let report = compare(&reference, &ours, &tolerances("tolerances-grid-exact.toml"));
        assert_eq!(
            report.exit_code(),
            0,
            "{}:\n{}",
            name(&case),
            report.to_table()
        );
        assert!(report
            .tensors
            .iter()
            .any(|t| t.name == "fwd.grid_h" && t.status == Status::Pass));
        if ck.model.cfg.positions == PositionMode::Tcnn {
            tcnn_cases += 1;
        }
    }
    assert!(
        tcnn_cases >= 2,
        "the tcnn bit-exactness claim needs tcnn cases"
    );
}

/// The committed cases cover what fixtures/golden/README.md says, and their parameters are
/// non-trivial (trained: ξ's last layer, which starts at zero, has moved).
#[test]
fn fixtures_cover_the_claimed_configurations() {
    let (mut modes, mut interps, mut deform, mut gammas) = (vec![], vec![], vec![], vec![]);
    let (mut invalid, mut mean_view, mut cpu) = (false, false, false);
    for case in cases() {
        let (ck, b) = load(&case);
        let cfg = &ck.model.cfg;
        modes.push(cfg.positions);
        interps.push(cfg.grid_h.interpolation);
        deform.push(cfg.deform.enabled);
        gammas.push(cfg.gamma);
        assert_eq!(
            b.samples_per_pixel(),
            (cfg.gamma * cfg.gamma) as usize,
            "{}",
            name(&case)
        );
        if b.valid.contains(&0) {
            assert!(cfg.gamma > 1);
            invalid = true;
        }
        mean_view |= b.view.contains(&-1);
        cpu |= cfg.grid_h.levels == 16 && cfg.shader.width == 64 && cfg.shader.hidden_layers == 2;
        assert!(
            b.n_pixels() <= 4096,
            "{}: a golden batch has <= 4096 pixels",
            name(&case)
        );
        if ck.model.layout.get("deform.layers.1.weight").is_some() {
            let w = ck.model.layout.view(&ck.params, "deform.layers.1.weight");
            assert!(
                w.iter().filter(|v| v.abs() > 1e-3).count() > w.len() / 2,
                "{}: xi's last layer is (nearly) zero: not a trained checkpoint",
                name(&case)
            );
        }
        let table = ck.model.layout.view(&ck.params, "grid_h.table");
        let big = table.iter().filter(|v| v.abs() > 1e-3).count();
        assert!(
            big > 100,
            "{}: grid H table still at its U(±1e-4) init",
            name(&case)
        );
    }
    for m in [PositionMode::F64, PositionMode::Tcnn] {
        assert!(modes.contains(&m), "no case with positions {m:?}");
    }
    for i in [Interpolation::Linear, Interpolation::Smoothstep] {
        assert!(interps.contains(&i), "no case with {i:?}");
    }
    assert!(deform.contains(&true) && deform.contains(&false));
    assert!(gammas.contains(&1) && gammas.contains(&2));
    assert!(invalid, "no case with invalid sub-samples");
    assert!(mean_view, "no case with view -1");
    assert!(cpu, "no cpu-preset case");
}

/// The golden checkpoints were written by older builds (before `level_weight` existed, and the
/// `cpu` case before that preset turned it on): their stored run configuration must read back
/// as the model they hold, not as today's preset (it read back with the weighting on).
#[test]
fn stored_run_configs_read_back_as_trained() {
    for case in cases() {
        let n = name(&case);
        let f = Checkpoint::read_model_tensors(case.join("checkpoint.safetensors")).unwrap();
        let text = f.meta("run_config").unwrap();
        let run = xscale::train::config::RunConfig::from_stored_toml(text, &n).unwrap();
        let (ck, _) = load(&case);
        let (run, model) = (&run.model, &ck.model.cfg);
        assert_eq!(run.level_weight, model.level_weight, "{n}");
        assert_eq!(run.gamma, model.gamma, "{n}");
        assert_eq!(run.positions, model.positions, "{n}");
        assert_eq!(run.deform.enabled, model.deform.enabled, "{n}");
        assert_eq!(run.grid_h, model.grid_h, "{n}");
    }
}

fn tmpdir(tag: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("xscale-golden-{tag}-{}", std::process::id()));
    std::fs::create_dir_all(&d).unwrap();
    d
}

fn run_compare(a: &Path, b: &Path, tol: &Path) -> (Option<i32>, String) {
    let out = Command::new(env!("CARGO_BIN_EXE_xscale"))
        .arg("compare")
        .arg(a)
        .arg(b)
        .arg("--tolerances")
        .arg(tol)
        .output()
        .unwrap();
    let text = format!(
        "{}{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
    (out.status.code(), text)
}

/// `xscale compare` end to end on a golden case: the Rust f64 dump passes; the same dump with
/// one gradient element changed by 1e-6 relative (10^4 × the tolerance) exits 1 and names the
/// tensor and the element.
#[test]
fn compare_cli_flags_one_perturbed_element() {
    let case = golden_dir().join("tiny-f64-linear");
    let (ck, b) = load(&case);
    let d = tmpdir("perturb");
    let mut ours = dump::<f64>(&ck, &b).unwrap();
    let good = d.join("dump.safetensors");
    ours.write_atomic(&good).unwrap();
    let reference = case.join("ref_f64.safetensors");
    let tol = golden_dir().join("tolerances-f64.toml");
    let (code, text) = run_compare(&reference, &good, &tol);
    assert_eq!(code, Some(0), "{text}");

    // Perturb the table-gradient element of largest magnitude.
    let t = ours.get("grad.grid_h.table").unwrap().clone();
    let mut v = t.to_f64().unwrap();
    let (i, _) = v
        .iter()
        .enumerate()
        .max_by(|a, b| a.1.abs().total_cmp(&b.1.abs()))
        .unwrap();
    v[i] *= 1.0 + 1e-6;
    let f = t.shape[1];
    ours.insert(
        "grad.grid_h.table",
        Tensor::f64(t.shape.clone(), &v).unwrap(),
    );
    let bad = d.join("perturbed.safetensors");
    ours.write_atomic(&bad).unwrap();
    let (code, text) = run_compare(&reference, &bad, &tol);
    assert_eq!(code, Some(1), "{text}");
    let want = format!(
        "FAIL grad.grid_h.table: 1 of {} elements out of tolerance; worst at [{},{}]",
        v.len(),
        i / f,
        i % f
    );
    assert!(text.contains(&want), "expected {want:?} in:\n{text}");
    // Nothing else fails.
    let fail_lines = text.lines().filter(|l| l.starts_with("FAIL")).count();
    assert_eq!(fail_lines, 2, "{text}"); // the table row and the detail line
    std::fs::remove_dir_all(&d).ok();
}
