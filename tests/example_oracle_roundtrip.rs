//! `examples/oracle_roundtrip.rs` runs: the library's dump of a golden case passes the committed
//! PyTorch float64 reference under the case's tolerance file, and a perturbed dump fails it.

#[path = "../examples/oracle_roundtrip.rs"]
mod oracle_roundtrip;

use std::path::Path;

#[test]
fn the_oracle_example_passes_the_golden_case() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let out = std::env::temp_dir().join(format!(
        "xscale-oracle-ex-{}.safetensors",
        std::process::id()
    ));
    let report =
        oracle_roundtrip::run(&root.join("fixtures/golden/tiny-f64-linear"), &out).unwrap();
    assert_eq!(report.exit_code(), 0, "{}", report.to_table());
    // The comparison can fail: one gradient element off by 1e-6 relative.
    let mut f = xscale::io::tensors::TensorFile::read(&out).unwrap();
    let t = f.get("grad.shader.layers.0.weight").unwrap().clone();
    let mut v = t.to_f64().unwrap();
    v[3] *= 1.0 + 1e-6;
    f.insert(
        "grad.shader.layers.0.weight",
        xscale::io::tensors::Tensor::f64(t.shape.clone(), &v).unwrap(),
    );
    f.write_atomic(&out).unwrap();
    let tol =
        xscale::io::compare::Tolerances::read(root.join("fixtures/golden/tolerances-f64.toml"))
            .unwrap();
    let r = xscale::io::compare::compare_files(
        root.join("fixtures/golden/tiny-f64-linear/ref_f64.safetensors"),
        &out,
        &tol,
    )
    .unwrap();
    assert_eq!(r.exit_code(), 1);
    let _ = std::fs::remove_file(&out);
}
