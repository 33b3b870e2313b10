//! `xscale dump` end to end: checkpoint + batch files in, a dump out that matches the library's
//! in-process evaluation bit for bit, in both precisions; bad input exits 2 naming the file.

use std::process::Command;
use xscale::io::tensors::{DType, TensorFile};
use xscale::model::checkpoint::{dump, init_checkpoint, Normalization};
use xscale::model::{Batch, ModelConfig};

fn dir(tag: &str) -> std::path::PathBuf {
    let d = std::env::temp_dir().join(format!("xscale-dump-{tag}-{}", std::process::id()));
    std::fs::create_dir_all(&d).unwrap();
    d
}

#[test]
fn dump_cli_matches_library() {
    let d = dir("ok");
    let ckpt = init_checkpoint(&ModelConfig::tiny(), 5, Normalization::unit(), 4).unwrap();
    let batch = Batch::random(9, 64, 4, 4, 0.25);
    ckpt.save(d.join("ckpt.safetensors")).unwrap();
    batch.save(d.join("batch.safetensors")).unwrap();
    for (prec, dtype) in [("f64", DType::F64), ("f32", DType::F32)] {
        let out = d.join(format!("dump-{prec}.safetensors"));
        let st = Command::new(env!("CARGO_BIN_EXE_xscale"))
            .args(["dump", "--checkpoint"])
            .arg(d.join("ckpt.safetensors"))
            .arg("--batch")
            .arg(d.join("batch.safetensors"))
            .arg("--out")
            .arg(&out)
            .args(["--precision", prec])
            .output()
            .unwrap();
        assert!(
            st.status.success(),
            "{}",
            String::from_utf8_lossy(&st.stderr)
        );
        let file = TensorFile::read(&out).unwrap();
        assert_eq!(file.get("fwd.rgb").unwrap().dtype, dtype);
        let mem = if prec == "f64" {
            dump::<f64>(&ckpt, &batch).unwrap()
        } else {
            dump::<f32>(&ckpt, &batch).unwrap()
        };
        assert_eq!(
            file.tensors, mem.tensors,
            "{prec}: file and in-process dump differ"
        );
    }
    std::fs::remove_dir_all(&d).ok();
}

#[test]
fn dump_cli_bad_input_names_the_file() {
    let d = dir("bad");
    std::fs::write(d.join("ckpt.safetensors"), b"not a safetensors file").unwrap();
    Batch::random(1, 4, 1, 0, 0.0)
        .save(d.join("batch.safetensors"))
        .unwrap();
    let st = Command::new(env!("CARGO_BIN_EXE_xscale"))
        .args(["dump", "--checkpoint"])
        .arg(d.join("ckpt.safetensors"))
        .arg("--batch")
        .arg(d.join("batch.safetensors"))
        .arg("--out")
        .arg(d.join("out.safetensors"))
        .output()
        .unwrap();
    assert_eq!(st.status.code(), Some(2));
    let err = String::from_utf8_lossy(&st.stderr);
    assert!(err.contains("ckpt.safetensors"), "{err}");
    assert!(!d.join("out.safetensors").exists());
    std::fs::remove_dir_all(&d).ok();
}

/// `--kink-threshold` is checked: not for f32 dumps (it used to be ignored silently), in [0, 1)
/// (1 would make every unit a kink site); 0 writes no kink tensors, the default writes them.
#[test]
fn dump_cli_kink_threshold_is_checked() {
    let d = dir("kink");
    let ckpt = init_checkpoint(&ModelConfig::tiny(), 5, Normalization::unit(), 4).unwrap();
    ckpt.save(d.join("ckpt.safetensors")).unwrap();
    Batch::random(9, 16, 4, 4, 0.25)
        .save(d.join("batch.safetensors"))
        .unwrap();
    let run = |extra: &[&str]| {
        let out = d.join("out.safetensors");
        std::fs::remove_file(&out).ok();
        let o = Command::new(env!("CARGO_BIN_EXE_xscale"))
            .args(["dump", "--checkpoint"])
            .arg(d.join("ckpt.safetensors"))
            .arg("--batch")
            .arg(d.join("batch.safetensors"))
            .arg("--out")
            .arg(&out)
            .args(extra)
            .output()
            .unwrap();
        let kinks = TensorFile::read(&out)
            .ok()
            .map(|f| f.tensors.contains_key("kink.margin"));
        (
            o.status.code(),
            String::from_utf8_lossy(&o.stderr).into_owned(),
            kinks,
        )
    };
    let (code, err, file) = run(&["--precision", "f32", "--kink-threshold", "1e-3"]);
    assert_eq!((code, file), (Some(2), None), "{err}");
    assert!(err.contains("--kink-threshold"), "{err}");
    for bad in ["1", "2", "nan", "inf"] {
        let (code, err, file) = run(&["--kink-threshold", bad]);
        assert_eq!((code, file), (Some(2), None), "{bad}: {err}");
    }
    assert_eq!(run(&["--kink-threshold", "0"]).2, Some(false));
    assert_eq!(run(&[]).2, Some(true));
    assert_eq!(run(&["--precision", "f32"]).2, Some(false));
    std::fs::remove_dir_all(&d).ok();
}
