//! `xscale ablate` and `xscale decimate` end to end on the bundled `tiny` fixture (a handful of
//! steps: this checks the plumbing and the table, not the numbers).

use std::path::{Path, PathBuf};
use std::process::Command;

fn fixture() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("fixtures/tiny")
}

fn tmp(name: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("xscale-test-ablate-{}-{name}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    d
}

fn xscale(args: &[&str]) -> (bool, String, String) {
    let out = Command::new(env!("CARGO_BIN_EXE_xscale"))
        .args(args)
        .output()
        .unwrap();
    (
        out.status.success(),
        String::from_utf8_lossy(&out.stdout).into_owned(),
        String::from_utf8_lossy(&out.stderr).into_owned(),
    )
}

#[test]
fn ablate_writes_the_table_for_every_variant() {
    let out = tmp("run");
    let scene = fixture();
    let (ok, stdout, err) = xscale(&[
        "ablate",
        "--scene",
        scene.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
        "--preset",
        "tiny",
        "--steps",
        "4",
        "--batch",
        "256",
        "--quiet",
    ]);
    assert!(ok, "{err}");
    let md = std::fs::read_to_string(out.join("ablation.md")).unwrap();
    assert_eq!(stdout, md, "the table is printed too");
    let variants = [
        "full",
        "no_deform",
        "no_multisampling",
        "mesh10",
        "vertex",
        "vertex_subdiv",
    ];
    assert!(md.contains("| ulr |"), "ulr row missing:\n{md}");
    for v in variants {
        assert!(md.contains(&format!("| {v} |")), "{v} row missing:\n{md}");
        // Each variant is an ordinary run folder.
        assert!(out.join(v).join("checkpoint.safetensors").exists(), "{v}");
        assert!(out.join(v).join("eval.json").exists(), "{v}");
    }
    let json: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("ablation.json")).unwrap()).unwrap();
    let results = json["results"].as_array().unwrap();
    assert_eq!(results.len(), 7);
    assert_eq!(json["steps"], 4);
    let get = |name: &str| results.iter().find(|r| r["name"] == name).unwrap();
    for r in results {
        let p = r["mean"]["psnr_masked"].as_f64().unwrap();
        assert!(p.is_finite() && p > 5.0, "{r}");
        let steps = if r["name"] == "ulr" { 0 } else { 4 };
        assert_eq!(r["steps"], steps);
    }
    // The switches took effect.
    assert_eq!(get("no_multisampling")["gamma"], 1);
    assert_eq!(get("no_deform")["deform"], false);
    assert_eq!(get("vertex")["featurization"], "vertex");
    // The decimated mesh has ~10% of the 2118 faces; the subdivided one 4^k times as many.
    let f10 = get("mesh10")["mesh_faces"].as_u64().unwrap();
    assert!((190..=233).contains(&f10), "{f10}");
    let fs = get("vertex_subdiv")["mesh_faces"].as_u64().unwrap();
    assert!(fs >= 4 * 2118 && fs % 2118 == 0, "{fs}");
    // The vertex baselines' parameter counts are within 2× of the full model's.
    for v in ["vertex", "vertex_subdiv"] {
        let r = get(v)["params_ratio"].as_f64().unwrap();
        assert!((0.5..=2.0).contains(&r), "{v}: {r}");
    }
    // Unknown variants are named.
    let (ok, _, err) = xscale(&[
        "ablate",
        "--scene",
        scene.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
        "--variants",
        "full,nope",
    ]);
    assert!(!ok && err.contains("nope"), "{err}");
    let _ = std::fs::remove_dir_all(&out);
}

#[test]
fn decimate_and_subdivide_commands() {
    let out = tmp("mesh");
    std::fs::create_dir_all(&out).unwrap();
    let src = fixture().join("mesh.ply");
    let dst = out.join("m10.ply");
    let (ok, stdout, err) = xscale(&[
        "decimate",
        "--in",
        src.to_str().unwrap(),
        "--ratio",
        "0.1",
        "--out",
        dst.to_str().unwrap(),
    ]);
    assert!(ok, "{err}");
    assert!(stdout.contains("2118 →"), "{stdout}");
    let (m, _) = xscale::scene::mesh::load_mesh(&dst).unwrap();
    assert!(
        (190..=233).contains(&m.triangles.len()),
        "{}",
        m.triangles.len()
    );
    let sub = out.join("s.obj");
    let (ok, _, err) = xscale(&[
        "subdivide",
        "--in",
        dst.to_str().unwrap(),
        "--levels",
        "1",
        "--out",
        sub.to_str().unwrap(),
    ]);
    assert!(ok, "{err}");
    let (s, _) = xscale::scene::mesh::load_mesh(&sub).unwrap();
    assert_eq!(s.triangles.len(), 4 * m.triangles.len());
    // Bad ratio and bad extension are named errors.
    let (ok, _, err) = xscale(&[
        "decimate",
        "--in",
        src.to_str().unwrap(),
        "--ratio",
        "0",
        "--out",
        dst.to_str().unwrap(),
    ]);
    assert!(!ok && err.contains("ratio"), "{err}");
    let (ok, _, err) = xscale(&[
        "decimate",
        "--in",
        src.to_str().unwrap(),
        "--ratio",
        "0.5",
        "--out",
        "x.stl",
    ]);
    assert!(!ok && err.contains(".ply"), "{err}");
    let _ = std::fs::remove_dir_all(&out);
}
