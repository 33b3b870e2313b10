//! `xscale dump` end to end: checkpoint + batch files in, a dump out that matches the library's
//! in-process evaluation bit for bit, in both precisions; bad input exits 2 naming the file.

use std::path::Path;
use std::process::Command;
use xscale::io::tensors::{DType, TensorFile};
use xscale::model::checkpoint::{dump, init_checkpoint, Checkpoint, Normalization};
use xscale::model::config::LevelWeight;
use xscale::model::{Batch, ModelConfig};

fn dir(tag: &str) -> std::path::PathBuf {
    let d = std::env::temp_dir().join(format!("xscale-dump-{tag}-{}", std::process::id()));
    std::fs::create_dir_all(&d).unwrap();
    d
}

/// A fresh checkpoint of `cfg` (seed 5) with `views` appearance rows and `batch`, written to `d` as
/// `ckpt.safetensors` and `batch.safetensors`.
fn write_inputs(d: &Path, cfg: &ModelConfig, views: usize, batch: &Batch) -> Checkpoint {
    let ckpt = init_checkpoint(cfg, 5, Normalization::unit(), views).unwrap();
    ckpt.save(d.join("ckpt.safetensors")).unwrap();
    batch.save(d.join("batch.safetensors")).unwrap();
    ckpt
}

/// `xscale dump` of `d`'s `ckpt.safetensors` and `batch.safetensors` into `out`, with `extra`
/// options: (exit code, stderr).
fn dump_cli(d: &Path, out: &Path, extra: &[&str]) -> (Option<i32>, String) {
    let o = Command::new(env!("CARGO_BIN_EXE_xscale"))
        .args(["dump", "--checkpoint"])
        .arg(d.join("ckpt.safetensors"))
        .arg("--batch")
        .arg(d.join("batch.safetensors"))
        .arg("--out")
        .arg(out)
        .args(extra)
        .output()
        .unwrap();
    (
        o.status.code(),
        String::from_utf8_lossy(&o.stderr).into_owned(),
    )
}

#[test]
fn dump_cli_matches_library() {
    let d = dir("ok");
    let batch = Batch::random(9, 64, 4, 4, 0.25);
    let ckpt = write_inputs(&d, &ModelConfig::tiny(), 4, &batch);
    for (prec, dtype) in [("f64", DType::F64), ("f32", DType::F32)] {
        let out = d.join(format!("dump-{prec}.safetensors"));
        let (code, err) = dump_cli(&d, &out, &["--precision", prec]);
        assert_eq!(code, Some(0), "{err}");
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
    let (code, err) = dump_cli(&d, &d.join("out.safetensors"), &[]);
    assert_eq!(code, Some(2));
    assert!(err.contains("ckpt.safetensors"), "{err}");
    // In words, not the parser's name for it (`HeaderTooLarge`).
    assert!(
        err.contains("not a valid safetensors file: its first 8 bytes"),
        "{err}"
    );
    assert!(!d.join("out.safetensors").exists());
    // A normalisation with a zero extent: its numbers, not a Rust Debug form.
    let mut f = init_checkpoint(&ModelConfig::tiny(), 5, Normalization::unit(), 4)
        .unwrap()
        .to_tensor_file()
        .unwrap();
    f.set_meta(
        "normalization",
        r#"{"center":[0.5,-2.25,3.0],"extent":[0.0,1.0,1.5]}"#,
    );
    f.write_atomic(d.join("ckpt.safetensors")).unwrap();
    let (code, err) = dump_cli(&d, &d.join("out.safetensors"), &[]);
    assert_eq!(code, Some(2), "{err}");
    assert!(
        err.contains("ckpt.safetensors: normalization (header metadata) has center [0.5, -2.25, 3] and extent [0, 1, 1.5]: every value must be finite and every extent > 0"),
        "{err}"
    );
    assert!(!err.contains("DVec3"), "{err}");
    std::fs::remove_dir_all(&d).ok();
}

/// `--kink-threshold` is checked: not for f32 dumps (it used to be ignored silently), in [0, 1)
/// (1 would make every unit a kink site); 0 writes no kink tensors, the default writes them.
#[test]
fn dump_cli_kink_threshold_is_checked() {
    let d = dir("kink");
    write_inputs(
        &d,
        &ModelConfig::tiny(),
        4,
        &Batch::random(9, 16, 4, 4, 0.25),
    );
    let run = |extra: &[&str]| {
        let out = d.join("out.safetensors");
        std::fs::remove_file(&out).ok();
        let (code, err) = dump_cli(&d, &out, extra);
        let kinks = TensorFile::read(&out)
            .ok()
            .map(|f| f.tensors.contains_key("kink.margin"));
        (code, err, kinks)
    };
    let (code, err, file) = run(&["--precision", "f32", "--kink-threshold", "1e-3"]);
    assert_eq!((code, file), (Some(2), None), "{err}");
    assert!(err.contains("--kink-threshold"), "{err}");
    // A value the flag does not take is a usage error (exit 64; it was 2).
    for bad in ["1", "2", "nan", "inf", "-0.1", "x"] {
        let (code, err, file) = run(&[&format!("--kink-threshold={bad}")]);
        assert_eq!((code, file), (Some(64), None), "{bad}: {err}");
        assert!(
            err.contains("--kink-threshold") && err.contains("must be a number in [0, 1)"),
            "{bad}: {err}"
        );
    }
    assert_eq!(run(&["--kink-threshold", "0"]).2, Some(false));
    assert_eq!(run(&[]).2, Some(true));
    assert_eq!(run(&["--precision", "f32"]).2, Some(false));
    std::fs::remove_dir_all(&d).ok();
}

/// A batch that does not fit the checkpoint (a view without an appearance row; no footprints
/// for the footprint level weighting) is the batch file's error and names it, like its other
/// errors (these two said only "batch: ...").
#[test]
fn dump_cli_batch_that_does_not_fit_the_model_names_the_file() {
    let d = dir("nofit");
    let mut batch = Batch::random(9, 8, 4, 6, 0.25);
    batch.view[0] = 33;
    write_inputs(&d, &ModelConfig::tiny(), 6, &batch);
    let (code, err) = dump_cli(&d, &d.join("out.safetensors"), &[]);
    assert_eq!(code, Some(2), "{err}");
    assert!(
        err.contains("batch.safetensors: batch: pixel 0: view 33 has no appearance code"),
        "{err}"
    );
    let mut cfg = ModelConfig::tiny();
    cfg.level_weight = LevelWeight::Footprint;
    write_inputs(&d, &cfg, 6, &Batch::random(9, 8, 4, 6, 0.25));
    let (code, err) = dump_cli(&d, &d.join("out.safetensors"), &[]);
    assert_eq!(code, Some(2), "{err}");
    assert!(
        err.contains("batch.safetensors: batch: the footprint level weighting"),
        "{err}"
    );
    assert!(!d.join("out.safetensors").exists());
    std::fs::remove_dir_all(&d).ok();
}

/// `--out` naming an input (the checkpoint or the batch, also through another spelling of the
/// path or a hard link) is refused before anything is written: it used to replace the input.
#[test]
fn dump_cli_refuses_to_overwrite_its_input() {
    let d = dir("self");
    write_inputs(
        &d,
        &ModelConfig::tiny(),
        4,
        &Batch::random(9, 8, 4, 4, 0.25),
    );
    let before = |f: &str| std::fs::read(d.join(f)).unwrap();
    let (ck0, b0) = (before("ckpt.safetensors"), before("batch.safetensors"));
    std::fs::hard_link(d.join("ckpt.safetensors"), d.join("link.safetensors")).unwrap();
    for (out, what) in [
        (
            d.join("ckpt.safetensors"),
            "--out is the checkpoint (--checkpoint",
        ),
        (
            d.join(".").join("batch.safetensors"),
            "--out is the batch (--batch",
        ),
        (
            d.join("link.safetensors"),
            "--out is the checkpoint (--checkpoint",
        ),
    ] {
        let (code, err) = dump_cli(&d, &out, &[]);
        assert_eq!(code, Some(2), "{err}");
        assert!(err.contains(what), "{err}");
    }
    assert_eq!(before("ckpt.safetensors"), ck0);
    assert_eq!(before("batch.safetensors"), b0);
    // Another file is written as before.
    let (code, err) = dump_cli(&d, &d.join("out.safetensors"), &[]);
    assert_eq!(code, Some(0), "{err}");
    std::fs::remove_dir_all(&d).ok();
}
