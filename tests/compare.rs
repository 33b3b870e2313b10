//! `xscale compare`: error measures, tolerance rules and exit codes (library API and the binary).

use std::path::{Path, PathBuf};
use std::process::Command;
use xscale::io::compare::{
    compare, compare_files, element_error, ulp_distance_f32, ulp_distance_f64, CompareIn, Status,
    Tolerances,
};
use xscale::io::{Tensor, TensorFile};

fn tmpdir(tag: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("xscale-compare-{tag}-{}", std::process::id()));
    std::fs::create_dir_all(&d).unwrap();
    d
}

fn base_file() -> TensorFile {
    let mut f = TensorFile::new();
    let v: Vec<f32> = (0..24).map(|i| (i as f32 - 7.0) * 0.37).collect();
    f.insert("fwd.grid_h", Tensor::f32(vec![2, 3, 4], &v).unwrap());
    f.insert(
        "fwd.rgb",
        Tensor::f32(vec![2, 3], &[0.1, 0.2, 0.3, 0.4, 0.5, 0.6]).unwrap(),
    );
    f.insert("batch.view", Tensor::i32(vec![2], &[0, -1]).unwrap());
    f.insert("loss", Tensor::scalar_f32(0.125));
    f
}

fn write(f: &TensorFile, p: &Path) {
    f.write_atomic(p).unwrap();
}

fn run_cli(args: &[&str]) -> (i32, String) {
    let out = Command::new(env!("CARGO_BIN_EXE_xscale"))
        .arg("compare")
        .args(args)
        .output()
        .unwrap();
    let text = format!(
        "{}{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
    (out.status.code().unwrap(), text)
}

const TOL: &str = r#"
[default]
max_ulp = 0

[[rule]]
pattern = "fwd.*"
max_abs = 1e-6
max_rel = 1e-5
max_ulp = 4
reason = "fp32 fma chain vs reference"
"#;

#[test]
fn ulp_known_values() {
    assert_eq!(ulp_distance_f32(1.0, 1.0), 0);
    assert_eq!(
        ulp_distance_f32(1.0, f32::from_bits(1.0f32.to_bits() + 1)),
        1
    );
    assert_eq!(ulp_distance_f32(1.0, 1.0 + f32::EPSILON), 1);
    // Below 1.0 the spacing halves: 1 - eps is 2 ulps below 1.
    assert_eq!(ulp_distance_f32(1.0, 1.0 - f32::EPSILON), 2);
    assert_eq!(ulp_distance_f32(-0.0, 0.0), 0);
    let tiny = f32::from_bits(1); // smallest positive subnormal
    assert_eq!(ulp_distance_f32(-tiny, tiny), 2, "across zero");
    assert_eq!(ulp_distance_f32(-tiny, 0.0), 1);
    assert_eq!(ulp_distance_f32(-1.0, 1.0), 2 * 1.0f32.to_bits() as u64);
    assert_eq!(ulp_distance_f32(f32::MAX, f32::INFINITY), 1);
    assert_eq!(ulp_distance_f64(1.0, 1.0 + f64::EPSILON), 1);
    assert_eq!(ulp_distance_f64(-0.0, 0.0), 0);
    let t64 = f64::from_bits(1);
    assert_eq!(ulp_distance_f64(-t64, t64), 2);
    assert_eq!(
        ulp_distance_f64(-f64::MAX, f64::MAX),
        2 * f64::MAX.to_bits(),
        "largest span fits in u64"
    );
}

#[test]
fn element_error_definitions() {
    let e = element_error(1.0, 1.0 + f32::EPSILON as f64, CompareIn::F32);
    assert_eq!(e.ulp, 1);
    assert_eq!(e.abs, f32::EPSILON as f64);
    assert!((e.rel - f32::EPSILON as f64 / (1.0 + f32::EPSILON as f64)).abs() < 1e-20);
    // 0 vs 0 and -0 vs +0: all zero (floor avoids 0/0).
    assert_eq!(element_error(0.0, -0.0, CompareIn::F32).rel, 0.0);
    // NaN vs NaN equal, NaN vs number infinite.
    let e = element_error(f64::NAN, f64::NAN, CompareIn::F32);
    assert_eq!((e.abs, e.rel, e.ulp), (0.0, 0.0, 0));
    let e = element_error(f64::NAN, 1.0, CompareIn::F64);
    assert!(e.abs.is_infinite() && e.rel.is_infinite() && e.ulp == u64::MAX);
    let e = element_error(f64::INFINITY, f64::INFINITY, CompareIn::F64);
    assert_eq!(e.ulp, 0);
    let e = element_error(f64::INFINITY, 1.0, CompareIn::F64);
    assert!(e.abs.is_infinite());
    // Mixed F64 vs F32: ulps counted in f32 after rounding the f64 value.
    let x = 0.1f64; // not representable in f32
    let e = element_error(x, 0.1f32 as f64, CompareIn::F32);
    assert_eq!(
        e.ulp, 0,
        "correctly rounded f32 is 0 ulp from the f64 reference"
    );
    assert!(e.abs > 0.0);
    let next = f32::from_bits(0.1f32.to_bits() + 1) as f64;
    assert_eq!(element_error(x, next, CompareIn::F32).ulp, 1);
    // Integers: ulp = integer difference.
    assert_eq!(element_error(-3.0, 4.0, CompareIn::Int).ulp, 7);
}

#[test]
fn identical_files_exit_0() {
    let d = tmpdir("same");
    let (a, b) = (d.join("a.safetensors"), d.join("b.safetensors"));
    write(&base_file(), &a);
    write(&base_file(), &b);
    let tol = Tolerances::from_toml(TOL, "tol").unwrap();
    let r = compare_files(&a, &b, &tol).unwrap();
    assert_eq!(r.exit_code(), 0, "{}", r.to_table());
    assert!(r.tensors.iter().all(|t| t.status == Status::Pass));
    let (code, out) = run_cli(&[a.to_str().unwrap(), b.to_str().unwrap()]);
    assert_eq!(code, 0, "{out}");
    std::fs::remove_dir_all(&d).unwrap();
}

#[test]
fn perturbed_element_exit_1_names_tensor_and_index() {
    let d = tmpdir("perturb");
    let (a, b, t) = (
        d.join("a.safetensors"),
        d.join("b.safetensors"),
        d.join("tol.toml"),
    );
    let fa = base_file();
    let mut fb = base_file();
    let mut v = fb.get_f32("fwd.grid_h").unwrap();
    // flat index 17 of shape [2,3,4] is [1,1,1].
    v[17] += 1e-3;
    // A tiny perturbation elsewhere stays within 4 ulps: passes.
    v[3] = f32::from_bits(v[3].to_bits() + 2);
    fb.insert("fwd.grid_h", Tensor::f32(vec![2, 3, 4], &v).unwrap());
    write(&fa, &a);
    write(&fb, &b);
    std::fs::write(&t, TOL).unwrap();
    let tol = Tolerances::read(&t).unwrap();
    let r = compare_files(&a, &b, &tol).unwrap();
    assert_eq!(r.exit_code(), 1);
    let tr = r.tensors.iter().find(|t| t.name == "fwd.grid_h").unwrap();
    assert_eq!(tr.status, Status::Fail);
    let s = tr.stats.as_ref().unwrap();
    assert_eq!(s.n_fail, 1);
    assert_eq!(s.worst_fail.as_ref().unwrap().index, vec![1, 1, 1]);
    assert_eq!(s.worst_abs.as_ref().unwrap().index, vec![1, 1, 1]);
    assert!((s.max_abs - 1e-3).abs() < 1e-6);
    let (code, out) = run_cli(&[
        a.to_str().unwrap(),
        b.to_str().unwrap(),
        "--tolerances",
        t.to_str().unwrap(),
        "--json",
        d.join("r.json").to_str().unwrap(),
    ]);
    assert_eq!(code, 1, "{out}");
    assert!(
        out.contains("FAIL fwd.grid_h") && out.contains("[1,1,1]"),
        "{out}"
    );
    let json: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(d.join("r.json")).unwrap()).unwrap();
    assert!(json["tensors"]
        .as_array()
        .unwrap()
        .iter()
        .any(|t| t["name"] == "fwd.grid_h"
            && t["status"] == "fail"
            && t["stats"]["worst_fail"]["index"] == serde_json::json!([1, 1, 1])));
    // Without a tolerance file or limits the comparison is exact: it cannot pass by default.
    let (code, out) = run_cli(&[a.to_str().unwrap(), b.to_str().unwrap()]);
    assert_eq!(code, 1, "{out}");
    assert!(
        out.contains("exact comparison (strict)") && out.contains("FAIL"),
        "{out}"
    );
    let (code, out) = run_cli(&[a.to_str().unwrap(), a.to_str().unwrap()]);
    assert_eq!(code, 0, "a file equals itself: {out}");
    // --strict: no rule means exact equality.
    let (code, _) = run_cli(&[a.to_str().unwrap(), b.to_str().unwrap(), "--strict"]);
    assert_eq!(code, 1);
    // A command-line default limit loose enough passes.
    let (code, out) = run_cli(&[
        a.to_str().unwrap(),
        b.to_str().unwrap(),
        "--max-abs",
        "2e-3",
    ]);
    assert_eq!(code, 0, "{out}");
    std::fs::remove_dir_all(&d).unwrap();
}

#[test]
fn shape_mismatch_exit_2() {
    let fa = base_file();
    let mut fb = base_file();
    let v = fb.get_f32("fwd.rgb").unwrap();
    fb.insert("fwd.rgb", Tensor::f32(vec![3, 2], &v).unwrap());
    let r = compare(&fa, &fb, &Tolerances::default());
    assert_eq!(r.exit_code(), 2);
    assert!(r.to_table().contains("SHAPE fwd.rgb"));
    let d = tmpdir("shape");
    let (a, b) = (d.join("a.st"), d.join("b.st"));
    write(&fa, &a);
    write(&fb, &b);
    let (code, out) = run_cli(&[a.to_str().unwrap(), b.to_str().unwrap()]);
    assert_eq!(code, 2, "{out}");
    // Unreadable file: exit 2 naming it.
    let (code, out) = run_cli(&[a.to_str().unwrap(), d.join("nope.st").to_str().unwrap()]);
    assert_eq!(code, 2);
    assert!(out.contains("nope.st"), "{out}");
    std::fs::remove_dir_all(&d).unwrap();
}

#[test]
fn missing_required_tensor_exit_2_and_only_in_lists() {
    let fa = base_file();
    let mut fb = base_file();
    fb.tensors.remove("fwd.rgb");
    fb.insert("extra", Tensor::u8(vec![1], &[1]).unwrap());
    fb.set_meta("format", "other");
    let r = compare(&fa, &fb, &Tolerances::default());
    assert_eq!(r.metadata_differs, vec!["format".to_string()]);
    assert_eq!(r.only_in_a, vec!["fwd.rgb".to_string()]);
    assert_eq!(r.only_in_b, vec!["extra".to_string()]);
    assert_eq!(r.exit_code(), 0, "not strict, nothing required");
    let strict = Tolerances {
        strict: true,
        ..Default::default()
    };
    assert_eq!(compare(&fa, &fb, &strict).exit_code(), 2);
    let tol = Tolerances::from_toml(
        "[[rule]]\npattern = \"fwd.rgb\"\nmax_abs = 1e-6\nrequired = true\n",
        "t",
    )
    .unwrap();
    let r = compare(&fa, &fb, &tol);
    assert_eq!(r.exit_code(), 2);
    assert!(
        r.missing_required[0].contains("fwd.rgb"),
        "{:?}",
        r.missing_required
    );
}

#[test]
fn first_matching_rule_wins_and_ignore() {
    let fa = base_file();
    let mut fb = base_file();
    fb.insert("loss", Tensor::scalar_f32(0.5));
    let tol = Tolerances::from_toml(
        r#"
[[rule]]
pattern = "loss"
ignore = true
[[rule]]
pattern = "*"
max_ulp = 0
"#,
        "t",
    )
    .unwrap();
    let r = compare(&fa, &fb, &tol);
    assert_eq!(r.exit_code(), 0);
    let l = r.tensors.iter().find(|t| t.name == "loss").unwrap();
    assert_eq!(l.status, Status::Ignored);
    // Reversed order: the catch-all wins and the loss fails.
    let tol = Tolerances::from_toml("[[rule]]\npattern = \"*\"\nmax_ulp = 0\n", "t").unwrap();
    assert_eq!(compare(&fa, &fb, &tol).exit_code(), 1);
}

#[test]
fn any_limit_suffices_per_element() {
    // Near zero the relative error is large but the absolute one tiny; for large values the
    // reverse: with both limits given, both elements pass.
    let mut fa = TensorFile::new();
    let mut fb = TensorFile::new();
    fa.insert("x", Tensor::f64(vec![2], &[1e-12, 1e6]).unwrap());
    fb.insert("x", Tensor::f64(vec![2], &[-1e-12, 1e6 + 1e-3]).unwrap());
    let both = Tolerances::from_toml("[default]\nmax_abs = 1e-9\nmax_rel = 1e-8\n", "t").unwrap();
    assert_eq!(compare(&fa, &fb, &both).exit_code(), 0);
    let abs_only = Tolerances::from_toml("[default]\nmax_abs = 1e-9\n", "t").unwrap();
    let r = compare(&fa, &fb, &abs_only);
    assert_eq!(r.exit_code(), 1);
    assert_eq!(
        r.tensors[0]
            .stats
            .as_ref()
            .unwrap()
            .worst_fail
            .as_ref()
            .unwrap()
            .index,
        vec![1]
    );
    let rel_only = Tolerances::from_toml("[default]\nmax_rel = 1e-8\n", "t").unwrap();
    let r = compare(&fa, &fb, &rel_only);
    assert_eq!(r.exit_code(), 1);
    assert_eq!(r.tensors[0].stats.as_ref().unwrap().max_rel, 2.0);
}

#[test]
fn nan_handling_in_files() {
    let mut fa = TensorFile::new();
    let mut fb = TensorFile::new();
    fa.insert("x", Tensor::f32(vec![3], &[f32::NAN, 1.0, 2.0]).unwrap());
    fb.insert("x", Tensor::f32(vec![3], &[f32::NAN, 1.0, 2.0]).unwrap());
    let tol = Tolerances::from_toml("[default]\nmax_ulp = 0\n", "t").unwrap();
    // NaN against NaN fails under every rule (an all-NaN gradient must not pass) ...
    let r = compare(&fa, &fb, &tol);
    assert_eq!(r.exit_code(), 1);
    assert_eq!(r.tensors[0].stats.as_ref().unwrap().n_nan, 1);
    let loose = Tolerances::from_toml("[default]\nmax_abs = 1e300\n", "t").unwrap();
    assert_eq!(compare(&fa, &fb, &loose).exit_code(), 1);
    // ... and even without any rule ...
    assert_eq!(compare(&fa, &fb, &Tolerances::default()).exit_code(), 1);
    // ... unless allowed, by the rule or for the whole file.
    let allow = Tolerances::from_toml("[default]\nmax_ulp = 0\nallow_nan = true\n", "t").unwrap();
    assert_eq!(compare(&fa, &fb, &allow).exit_code(), 0);
    let allow_all =
        Tolerances::from_toml("allow_nan = true\n[default]\nmax_ulp = 0\n", "t").unwrap();
    assert_eq!(compare(&fa, &fb, &allow_all).exit_code(), 0);
    // An infinity passes only against the same infinity in the same place.
    let (mut ia, mut ib) = (TensorFile::new(), TensorFile::new());
    ia.insert("y", Tensor::f32(vec![2], &[f32::INFINITY, 1.0]).unwrap());
    ib.insert("y", Tensor::f32(vec![2], &[f32::INFINITY, 1.0]).unwrap());
    assert_eq!(compare(&ia, &ib, &loose).exit_code(), 0);
    ib.insert(
        "y",
        Tensor::f32(vec![2], &[f32::NEG_INFINITY, 1.0]).unwrap(),
    );
    assert_eq!(compare(&ia, &ib, &loose).exit_code(), 1);
    ib.insert("y", Tensor::f32(vec![2], &[1.0, f32::INFINITY]).unwrap());
    assert_eq!(compare(&ia, &ib, &loose).exit_code(), 1);
    let tol = allow;
    fb.insert(
        "x",
        Tensor::f32(vec![3], &[f32::NAN, f32::NAN, 2.0]).unwrap(),
    );
    let r = compare(&fa, &fb, &tol);
    assert_eq!(r.exit_code(), 1);
    let s = r.tensors[0].stats.as_ref().unwrap();
    assert_eq!(s.worst_fail.as_ref().unwrap().index, vec![1]);
    assert!(s.max_abs.is_infinite());
    // Huge limits still fail a NaN-vs-number element.
    let loose = Tolerances::from_toml("[default]\nmax_abs = 1e300\n", "t").unwrap();
    assert_eq!(compare(&fa, &fb, &loose).exit_code(), 1);
}

#[test]
fn mixed_f64_f32_compares_in_f32_ulps() {
    let mut fa = TensorFile::new();
    let mut fb = TensorFile::new();
    let ref64 = [0.1f64, 1.0 / 3.0, -2.7];
    let back32: Vec<f32> = ref64.iter().map(|&x| x as f32).collect();
    fa.insert("x", Tensor::f64(vec![3], &ref64).unwrap());
    fb.insert("x", Tensor::f32(vec![3], &back32).unwrap());
    let tol = Tolerances::from_toml("[default]\nmax_ulp = 0\n", "t").unwrap();
    let r = compare(&fa, &fb, &tol);
    assert_eq!(r.exit_code(), 0, "{}", r.to_table());
    assert_eq!(
        r.tensors[0].stats.as_ref().unwrap().compare_in,
        CompareIn::F32
    );
}

/// An exact rule (no limits: `batch.*` in the tolerance files, and the strict default) asks for
/// equal values: an F64 tensor rounded to F32 is 0 f32 ulps from it but not equal, and fails
/// (it passed, so a backend that evaluated an f32-rounded batch passed "batch.* exact"). An F64
/// value that is an f32 value exactly still equals its F32 copy.
#[test]
fn exact_rules_fail_f64_values_rounded_to_f32() {
    let (mut fa, mut fb) = (TensorFile::new(), TensorFile::new());
    let pos = [0.1f64, 0.5, -2.7];
    fa.insert("batch.positions", Tensor::f64(vec![3], &pos).unwrap());
    let rounded: Vec<f32> = pos.iter().map(|&x| x as f32).collect();
    fb.insert("batch.positions", Tensor::f32(vec![3], &rounded).unwrap());
    let exact =
        Tolerances::from_toml("[[rule]]\npattern = \"batch.*\"\nrequired = true\n", "t").unwrap();
    let strict = Tolerances {
        strict: true,
        ..Default::default()
    };
    for tol in [&exact, &strict] {
        let r = compare(&fa, &fb, tol);
        assert_eq!(r.exit_code(), 1, "{}", r.to_table());
        let st = r.tensors[0].stats.as_ref().unwrap();
        // 0.1 and -2.7 are not f32 values; 0.5 is.
        assert_eq!((st.n_fail, st.max_ulp), (2, 0), "{}", r.to_table());
    }
    // Widened exactly, the F32 file's values pass against it.
    let widened: Vec<f64> = rounded.iter().map(|&x| x as f64).collect();
    fa.insert("batch.positions", Tensor::f64(vec![3], &widened).unwrap());
    assert_eq!(compare(&fa, &fb, &exact).exit_code(), 0);
    assert_eq!(compare(&fa, &fb, &strict).exit_code(), 0);
    // The command line's default (strict, exact) says so too.
    let d = tmpdir("exact32");
    let (a, b) = (d.join("a.st"), d.join("b.st"));
    fa.insert("batch.positions", Tensor::f64(vec![3], &pos).unwrap());
    write(&fa, &a);
    write(&fb, &b);
    let (code, out) = run_cli(&[a.to_str().unwrap(), b.to_str().unwrap()]);
    assert_eq!(code, 1, "{out}");
    assert!(out.contains("FAIL batch.positions: 2 of 3"), "{out}");
    std::fs::remove_dir_all(&d).unwrap();
}

#[test]
fn bad_tolerance_files_are_errors() {
    assert!(Tolerances::from_toml("[[rule]]\nmax_abs = 1\n", "t.toml")
        .unwrap_err()
        .to_string()
        .contains("no pattern"));
    let e = format!(
        "{:#}",
        Tolerances::from_toml("[[rule]]\npattern = \"x\"\nmax_abss = 1\n", "t.toml").unwrap_err()
    );
    assert!(e.contains("t.toml") && e.contains("max_abss"), "{e}");
    let e = Tolerances::from_toml("[[rule]]\npattern = \"x\"\nmax_abs = -1\n", "t")
        .unwrap_err()
        .to_string();
    assert_eq!(e, "t: rule \"x\": max_abs = -1 must be a number >= 0");
    let e = Tolerances::from_toml("[default]\nmax_rel = nan\n", "t")
        .unwrap_err()
        .to_string();
    assert_eq!(e, "t: [default]: max_rel = NaN must be a number >= 0");
}

/// The same limits on the command line are usage errors (exit 64), worded as the file's check;
/// they used to be taken, and then failed identical files with exit 1.
#[test]
fn bad_command_line_limits_are_usage_errors() {
    let d = tmpdir("badlimits");
    let a = d.join("a.st");
    write(&base_file(), &a);
    let a = a.to_str().unwrap();
    for (arg, shown) in [
        ("--max-abs=-1", "-1 must be a number >= 0"),
        ("--max-abs=nan", "NaN must be a number >= 0"),
        ("--max-rel-peak=-0.5", "-0.5 must be a number >= 0"),
        ("--max-rel=-inf", "-inf must be a number >= 0"),
        ("--max-rel=x", "expected a number >= 0"),
    ] {
        let (code, out) = run_cli(&[a, a, arg]);
        assert_eq!(code, 64, "{arg}: {out}");
        let flag = arg.split('=').next().unwrap();
        assert!(out.contains(flag) && out.contains(shown), "{arg}: {out}");
    }
    let (code, out) = run_cli(&[a, a, "--max-abs=inf", "--max-rel=0"]);
    assert_eq!(code, 0, "{out}");
    std::fs::remove_dir_all(&d).unwrap();
}

/// Report wording: a kink slack of the wrong dtype says so (it said "416 elements where ... has
/// 416"); a tensor the `[default]` rule requires names `[default]` (it said `rule ""`).
#[test]
fn report_names_a_bad_slack_dtype_and_the_default_rule() {
    let mut fa = base_file();
    fa.insert(
        "kink.slack.fwd.rgb",
        Tensor::u8(vec![2, 3], &[0; 6]).unwrap(),
    );
    let r = compare(&fa, &base_file(), &Tolerances::default());
    assert_eq!(r.exit_code(), 2);
    assert_eq!(
        r.missing_required,
        ["kink.slack.fwd.rgb in A: dtype U8, expected F32 or F64 (a slack is a float)"]
    );
    let mut fb = base_file();
    fb.tensors.remove("loss");
    let tol = Tolerances::from_toml("[default]\nrequired = true\n", "t").unwrap();
    let r = compare(&base_file(), &fb, &tol);
    assert_eq!(r.exit_code(), 2);
    assert_eq!(
        r.missing_required,
        ["loss: required by [default] but missing from B"]
    );
    assert!(r.to_table().contains("MISSING loss: required by [default]"));
}

/// `--json`: NaN, +inf and -inf are told apart (strings "NaN", "inf", "-inf"; all three used to
/// be `null`), finite values are numbers.
#[test]
fn json_report_tells_nan_and_infinities_apart() {
    let (mut fa, mut fb) = (TensorFile::new(), TensorFile::new());
    fa.insert(
        "x",
        Tensor::f32(vec![3], &[f32::NAN, f32::INFINITY, 1.0]).unwrap(),
    );
    fb.insert(
        "x",
        Tensor::f32(vec![3], &[1.0, f32::NEG_INFINITY, 1.0]).unwrap(),
    );
    let r = compare(&fa, &fb, &Tolerances::default());
    let j: serde_json::Value =
        serde_json::from_str(&xscale::io::compare::report_json(&r).unwrap()).unwrap();
    let st = &j["tensors"][0]["stats"];
    assert_eq!(st["max_abs"], "inf");
    assert_eq!(st["peak"], 1.0);
    let worst = |k: &str| st["worst_abs"][k].clone();
    // The first element with the largest error: NaN against 1.
    assert_eq!((worst("a"), worst("b")), ("NaN".into(), 1.0.into()));
    // Element 1: +inf against -inf, written apart.
    let mut fa1 = TensorFile::new();
    fa1.insert("x", Tensor::f32(vec![1], &[f32::INFINITY]).unwrap());
    let mut fb1 = TensorFile::new();
    fb1.insert("x", Tensor::f32(vec![1], &[f32::NEG_INFINITY]).unwrap());
    let r = compare(&fa1, &fb1, &Tolerances::default());
    let j: serde_json::Value =
        serde_json::from_str(&xscale::io::compare::report_json(&r).unwrap()).unwrap();
    let e = &j["tensors"][0]["stats"]["worst_abs"];
    assert_eq!(
        (e["a"].clone(), e["b"].clone()),
        ("inf".into(), "-inf".into())
    );
}

/// Files that are not safetensors are described in words, not by the parser's internal error
/// names (`MetadataIncompleteBuffer`, `HeaderTooLarge`).
#[test]
fn unreadable_files_say_what_is_wrong() {
    let d = tmpdir("words");
    let good = d.join("good.st");
    write(&base_file(), &good);
    let bytes = std::fs::read(&good).unwrap();
    let trunc = d.join("trunc.st");
    std::fs::write(&trunc, &bytes[..bytes.len() - 5]).unwrap();
    let text = d.join("text.st");
    std::fs::write(&text, "this is a text file, not tensors\n").unwrap();
    let header = d.join("header.st");
    std::fs::write(&header, &bytes[..40]).unwrap();
    let extra = d.join("extra.st");
    std::fs::write(&extra, [&bytes[..], b"xyz"].concat()).unwrap();
    let g = good.to_str().unwrap();
    for (file, want) in [
        (&trunc, "truncated: its header declares"),
        (&text, "not a valid safetensors file: its first 8 bytes give a header length of"),
        (&header, "not a valid safetensors file: truncated header: its first 8 bytes give a header length of"),
        (&extra, "3 bytes of extra data after the"),
    ] {
        let (code, out) = run_cli(&[g, file.to_str().unwrap()]);
        assert_eq!(code, 2, "{out}");
        assert!(out.contains(file.to_str().unwrap()) && out.contains(want), "{out}");
        assert!(
            !out.contains("MetadataIncompleteBuffer") && !out.contains("HeaderTooLarge") && !out.contains("InvalidHeaderLength"),
            "{out}"
        );
    }
    std::fs::remove_dir_all(&d).unwrap();
}
