//! `xscale case` end to end, and the built-in tolerance sets: the case holds a trained checkpoint,
//! an edited batch, the f64 oracle dump of the two (bit for bit what `xscale dump` writes), the
//! tolerance set and a manifest listing exactly the dump's tensors; the same command twice writes
//! the same bytes; `xscale compare --tolerances f32` works from any folder and compares every
//! shared tensor under a rule (the echoed parameters too).

use std::path::{Path, PathBuf};
use std::process::Command;
use xscale::io::compare::{compare, Status, Tolerances};
use xscale::io::tensors::TensorFile;
use xscale::model::checkpoint::{dump_with, Checkpoint};
use xscale::model::Batch;

fn dir(tag: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("xscale-case-{tag}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).unwrap();
    d
}

fn xscale(args: &[&str], cwd: &Path) -> (Option<i32>, String) {
    let o = Command::new(env!("CARGO_BIN_EXE_xscale"))
        .args(args)
        .current_dir(cwd)
        .output()
        .unwrap();
    (
        o.status.code(),
        format!(
            "{}{}",
            String::from_utf8_lossy(&o.stdout),
            String::from_utf8_lossy(&o.stderr)
        ),
    )
}

fn files(d: &Path) -> Vec<(String, Vec<u8>)> {
    let mut v: Vec<(String, Vec<u8>)> = std::fs::read_dir(d)
        .unwrap()
        .flatten()
        .filter(|e| e.path().is_file())
        .map(|e| {
            (
                e.file_name().to_string_lossy().to_string(),
                std::fs::read(e.path()).unwrap(),
            )
        })
        .collect();
    v.sort();
    v
}

#[test]
fn case_writes_a_backend_case_and_compare_knows_the_sets() {
    let d = dir("main");
    let case = d.join("case");
    let case_s = case.to_str().unwrap();
    let (code, text) = xscale(&["case", "--out", case_s, "--size", "64"], &d);
    assert_eq!(code, Some(0), "{text}");
    assert!(
        text.contains("tiny-cuda-nn can reproduce this configuration"),
        "{text}"
    );

    // The oracle is the f64 dump (with the kink account) of the case's checkpoint and batch.
    let ck = Checkpoint::load(case.join("checkpoint.safetensors")).unwrap();
    assert_eq!(
        ck.model.cfg.positions,
        xscale::model::config::PositionMode::Tcnn
    );
    let batch = Batch::load(case.join("batch.safetensors")).unwrap();
    assert_eq!(batch.n_pixels(), 64);
    let invalid = batch.valid.iter().filter(|&&v| v == 0).count();
    assert!(
        invalid > 0 && batch.view[..4].iter().all(|&v| v == -1),
        "{invalid}"
    );
    let oracle = TensorFile::read(case.join("oracle.safetensors")).unwrap();
    let again =
        dump_with::<f64>(&ck, &batch, Some(xscale::model::kink::DEFAULT_THRESHOLD)).unwrap();
    assert_eq!(
        oracle.to_bytes().unwrap(),
        {
            let mut a = again.clone();
            a.source = None;
            a.to_bytes().unwrap()
        },
        "the oracle is not the dump of the case's own files"
    );
    // Trained: ξ's last layer moved away from zero.
    let w = oracle.get_f64("deform.layers.1.weight").unwrap();
    assert!(w.iter().any(|v| v.abs() > 1e-3));

    // The manifest lists exactly the dump's tensors (the kink account aside).
    let m: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(case.join("manifest.json")).unwrap())
            .unwrap();
    let listed: Vec<&str> = m["tensors"]
        .as_array()
        .unwrap()
        .iter()
        .map(|t| t["name"].as_str().unwrap())
        .collect();
    let mut want: Vec<&str> = oracle
        .tensors
        .keys()
        .map(|s| s.as_str())
        .filter(|k| !k.starts_with("kink."))
        .collect();
    let mut got = listed.clone();
    want.sort();
    got.sort();
    assert_eq!(got, want);
    assert_eq!(m["tcnn_reproducible"], true);
    assert_eq!(
        std::fs::read_to_string(case.join("tolerances.toml")).unwrap(),
        xscale::io::compare::builtin_tolerance_text("f32").unwrap()
    );

    // The same command twice: the same bytes.
    let before = files(&case);
    let (code, text) = xscale(&["case", "--out", case_s, "--size", "64"], &d);
    assert_eq!(code, Some(0), "{text}");
    assert_eq!(files(&case), before);

    // compare --tolerances by name from another folder; every shared tensor has a rule.
    let f32_dump = d.join("d32.safetensors");
    let (code, text) = xscale(
        &[
            "dump",
            "--checkpoint",
            case.join("checkpoint.safetensors").to_str().unwrap(),
            "--batch",
            case.join("batch.safetensors").to_str().unwrap(),
            "--precision",
            "f32",
            "--out",
            f32_dump.to_str().unwrap(),
        ],
        &d,
    );
    assert_eq!(code, Some(0), "{text}");
    let elsewhere = dir("cwd");
    let oracle_s = case.join("oracle.safetensors");
    let (code, text) = xscale(
        &[
            "compare",
            oracle_s.to_str().unwrap(),
            f32_dump.to_str().unwrap(),
            "--tolerances",
            "f32",
        ],
        &elsewhere,
    );
    assert_eq!(code, Some(0), "{text}");
    assert!(text.contains(" 0 FAIL, 0 no rule, 0 ignored"), "{text}");
    let (code, text) = xscale(
        &[
            "compare",
            oracle_s.to_str().unwrap(),
            f32_dump.to_str().unwrap(),
            "--tolerances",
            "exact",
        ],
        &elsewhere,
    );
    assert_eq!(
        code,
        Some(1),
        "an f32 dump is not the f64 one exactly: {text}"
    );
    let (code, text) = xscale(
        &[
            "compare",
            oracle_s.to_str().unwrap(),
            f32_dump.to_str().unwrap(),
            "--tolerances",
            "f31",
        ],
        &elsewhere,
    );
    assert_eq!(code, Some(2), "{text}");
    assert!(
        text.contains("not a built-in set (built-in: f32, f64, fp16, grid-exact, exact)"),
        "{text}"
    );
    // A file given by path still works.
    let (code, text) = xscale(
        &[
            "compare",
            oracle_s.to_str().unwrap(),
            f32_dump.to_str().unwrap(),
            "--tolerances",
            case.join("tolerances.toml").to_str().unwrap(),
        ],
        &elsewhere,
    );
    assert_eq!(code, Some(0), "{text}");

    // A folder holding something else is refused, naming it.
    let other = d.join("other");
    std::fs::create_dir_all(&other).unwrap();
    std::fs::write(other.join("mine.txt"), "x").unwrap();
    let (code, text) = xscale(&["case", "--out", other.to_str().unwrap()], &d);
    assert_eq!(code, Some(2), "{text}");
    assert!(text.contains("\"mine.txt\""), "{text}");
    // An interrupted case (its marker and some of its files) is made again, not refused.
    let part = d.join("part");
    std::fs::create_dir_all(part.join("scene")).unwrap();
    std::fs::write(part.join(".case-incomplete"), "x").unwrap();
    std::fs::write(part.join("config.toml"), "x").unwrap();
    let (code, text) = xscale(
        &["case", "--out", part.to_str().unwrap(), "--size", "64"],
        &d,
    );
    assert_eq!(code, Some(0), "{text}");
    assert!(!part.join(".case-incomplete").exists());
    assert_eq!(files(&part), before);
    std::fs::remove_dir_all(&d).ok();
    std::fs::remove_dir_all(&elsewhere).ok();
}

/// Every built-in set parses, and in each of f32, f64 and fp16 every tensor of an f64 dump has a
/// rule: the echoed parameters are compared (exactly), never "no rule".
#[test]
fn builtin_sets_cover_every_dump_tensor() {
    for name in xscale::io::compare::builtin_tolerance_names() {
        assert!(Tolerances::builtin(name).is_some(), "{name}");
        assert!(Tolerances::resolve(name).is_ok(), "{name}");
    }
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("fixtures/golden/cpu-t10");
    let ck = Checkpoint::load(root.join("checkpoint.safetensors")).unwrap();
    let b = Batch::load(root.join("batch.safetensors")).unwrap();
    let d = dump_with::<f64>(&ck, &b, None).unwrap();
    for name in ["f32", "f64", "fp16", "exact"] {
        let r = compare(&d, &d, &Tolerances::builtin(name).unwrap());
        assert_eq!(r.exit_code(), 0, "{name}");
        for t in &r.tensors {
            assert_eq!(t.status, Status::Pass, "{name}: {}", t.name);
        }
        assert!(r.tensors.iter().any(|t| t.name == "grid_h.table"));
    }
    // The exact set is exact: one ulp off fails.
    let mut e = d.clone();
    let t = e.get("fwd.rgb").unwrap().clone();
    let mut v = t.to_f64().unwrap();
    v[0] = f64::from_bits(v[0].to_bits() + 1);
    e.insert(
        "fwd.rgb",
        xscale::io::tensors::Tensor::f64(t.shape.clone(), &v).unwrap(),
    );
    assert_eq!(
        compare(&d, &e, &Tolerances::builtin("exact").unwrap()).exit_code(),
        1
    );
    assert_eq!(
        compare(&d, &e, &Tolerances::builtin("f64").unwrap()).exit_code(),
        0
    );
}
