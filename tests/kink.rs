//! Kink-aware comparison (`model/kink.rs`, `io/compare.rs`, docs/oracle.md §7): a correct f32
//! evaluation that lands on the other side of a ReLU kink than the f64 oracle fails the f32
//! tolerance file on its gradients; the f64 dump's kink slack lets it pass, reports the kink
//! pixels, and `kink_slack = false` brings the failure back.
//!
//! The case is built from the golden `cpu-t10` checkpoint (cpu-preset structure): one weight of
//! shader unit u is set so that the unit's f64 pre-activation on pixel 0 is within rounding of 0,
//! then nudged an ulp at a time until the f32 forward puts the unit on the other side of the kink.

use std::path::PathBuf;
use xscale::io::compare::{compare, Status, Tolerances};
use xscale::model::checkpoint::{dump_with, Checkpoint};
use xscale::model::kink::DEFAULT_THRESHOLD;
use xscale::model::Batch;

fn golden(case: &str, file: &str) -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("fixtures/golden")
        .join(case)
        .join(file)
}

/// Unit `u` of shader layer 0 on pixel 0: (f64 pre-activation, f32 post-ReLU output).
fn unit_on_pixel0(ck: &Checkpoint, b: &Batch, u: usize) -> (f64, f32) {
    let m = &ck.model;
    let p64: Vec<f64> = ck.params.iter().map(|&v| v as f64).collect();
    let f64w = m.forward(&p64, b).unwrap();
    let f32w = m.forward(&ck.params, b).unwrap();
    let l = &m.shader.layers[0];
    let w = weight_range(ck);
    let x = &f64w.chunks[0].shader_in[..l.in_dim];
    let pre: f64 = (0..l.in_dim)
        .map(|j| p64[w.start + u * l.in_dim + j] * x[j])
        .sum::<f64>()
        + l.b_off
            .map_or(0.0, |_| unreachable!("cpu-t10 has no shader biases"));
    (pre, f32w.chunks[0].shader.hidden[0][u])
}

fn weight_range(ck: &Checkpoint) -> std::ops::Range<usize> {
    ck.model
        .layout
        .tensors
        .iter()
        .find(|t| t.name == "shader.layers.0.weight")
        .unwrap()
        .range()
}

/// A checkpoint where shader unit `u`'s pre-activation on pixel 0 is ≤ 0 in f64 but > 0 in f32
/// (or the reverse), and the unit index.
fn kink_case() -> (Checkpoint, Batch, usize) {
    let mut ck = Checkpoint::load(golden("cpu-t10", "checkpoint.safetensors")).unwrap();
    let b = Batch::load(golden("cpu-t10", "batch.safetensors")).unwrap();
    let w = weight_range(&ck);
    let in_dim = ck.model.shader.layers[0].in_dim;
    let p64: Vec<f64> = ck.params.iter().map(|&v| v as f64).collect();
    let x: Vec<f64> = ck.model.forward(&p64, &b).unwrap().chunks[0].shader_in[..in_dim].to_vec();
    let xmax = x.iter().fold(0.0f64, |m, v| m.max(v.abs()));
    // The input with the smallest clearly non-zero |x_j|: an ulp of its weight moves the
    // pre-activation far less than f32 rounding does, so the f32 and f64 crossings of 0 fall
    // on different ulps.
    let j = (0..in_dim)
        .filter(|&j| x[j].abs() > 1e-3 * xmax)
        .min_by(|&a, &c| x[a].abs().total_cmp(&x[c].abs()))
        .unwrap();
    for u in 0..ck.model.shader.layers[0].out_dim {
        let k = w.start + u * in_dim + j;
        let orig = ck.params[k];
        let (pre, _) = unit_on_pixel0(&ck, &b, u);
        let centre = (orig as f64 - pre / x[j]) as f32;
        for step in -64i32..=64 {
            let v = f32::from_bits((centre.to_bits() as i32 + step) as u32);
            ck.params[k] = v;
            let (pre, h32) = unit_on_pixel0(&ck, &b, u);
            if (pre > 0.0) != (h32 > 0.0) {
                return (ck, b, u);
            }
        }
        ck.params[k] = orig;
    }
    panic!("no shader unit could be put on its kink");
}

#[test]
fn f32_on_the_other_side_of_a_kink_passes_by_slack_and_fails_without() {
    let (ck, b, u) = kink_case();
    let d64 = dump_with::<f64>(&ck, &b, Some(DEFAULT_THRESHOLD)).unwrap();
    let d32 = dump_with::<f32>(&ck, &b, None).unwrap();
    assert!(
        !d32.tensors.contains_key("kink.margin"),
        "f32 dumps carry no kink tensors"
    );
    let margin = d64.get("kink.margin").unwrap().to_f64().unwrap();
    assert!(margin[0] < 1e-6, "pixel 0's margin {}", margin[0]);
    let pixels = d64.get("kink.pixels").unwrap().to_f64().unwrap();
    assert!(pixels.contains(&0.0), "pixel 0 is a kink pixel: {pixels:?}");

    let tol = Tolerances::read(golden("", "tolerances-f32.toml")).unwrap();
    let with = compare(&d64, &d32, &tol);
    let kinked: Vec<_> = with
        .tensors
        .iter()
        .filter(|t| t.stats.as_ref().is_some_and(|s| s.n_kink > 0))
        .map(|t| t.name.clone())
        .collect();
    assert_eq!(with.exit_code(), 0, "unit {u}: {}", with.to_table());
    assert!(
        !kinked.is_empty(),
        "no element needed the slack: the case is not a kink case"
    );
    assert_eq!(with.kink_pixels, Some(pixels.len()));
    assert!(with.to_table().contains("kink pixels: "));

    let mut off = tol.clone();
    off.kink_slack = false;
    let without = compare(&d64, &d32, &off);
    assert_eq!(without.exit_code(), 1, "{}", without.to_table());
    let failed: Vec<_> = without
        .tensors
        .iter()
        .filter(|t| t.status == Status::Fail)
        .map(|t| t.name.clone())
        .collect();
    assert!(
        failed
            .iter()
            .all(|f| f.starts_with("grad.") && kinked.contains(f)),
        "only the gradients the slack covered fail: {failed:?} vs {kinked:?}"
    );

    // The slack is not a blanket: the same f32 dump with one gradient element of a kink-free
    // pixel moved by 1e-3 of its tensor's peak still fails.
    let mut bad = d32.clone();
    let name = "grad.batch.dirs";
    let mut v = bad.get(name).unwrap().to_f64().unwrap();
    let peak = v.iter().fold(0.0f64, |m, x| m.max(x.abs()));
    let free = (0..margin.len())
        .find(|&p| !pixels.contains(&(p as f64)))
        .unwrap();
    v[free * 3] += 1e-3 * peak;
    let t = bad.get(name).unwrap().clone();
    let vf: Vec<f32> = v.iter().map(|&x| x as f32).collect();
    bad.insert(
        name,
        xscale::io::tensors::Tensor::f32(t.shape.clone(), &vf).unwrap(),
    );
    let r = compare(&d64, &bad, &tol);
    assert_eq!(r.exit_code(), 1, "{}", r.to_table());
}

/// Kink tensors are not data: an f64 dump with them compares with a file without them (the
/// PyTorch reference's) as before, strict or not.
#[test]
fn kink_tensors_are_never_compared_or_missing() {
    let ck = Checkpoint::load(golden("tiny-f64-linear", "checkpoint.safetensors")).unwrap();
    let b = Batch::load(golden("tiny-f64-linear", "batch.safetensors")).unwrap();
    let with = dump_with::<f64>(&ck, &b, Some(1e-2)).unwrap();
    let without = dump_with::<f64>(&ck, &b, None).unwrap();
    assert!(
        with.tensors.keys().any(|k| k.starts_with("kink.slack.")),
        "1e-2 finds kinks"
    );
    let tol = Tolerances {
        strict: true,
        ..Tolerances::default()
    };
    let r = compare(&with, &without, &tol);
    assert_eq!(r.exit_code(), 0, "{}", r.to_table());
    assert!(r.only_in_a.is_empty() && r.tensors.iter().all(|t| !t.name.starts_with("kink.")));
}
