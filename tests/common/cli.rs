//! The `xscale` binary as a test calls it, and the bundled fixture.

#![allow(dead_code)]

use std::path::{Path, PathBuf};
use std::process::Command;

/// The bundled tiny scene.
pub fn fixture() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("fixtures/tiny")
}

/// `xscale ARGS`: (exit code, stderr).
pub fn xscale(args: &[&str]) -> (i32, String) {
    let out = Command::new(env!("CARGO_BIN_EXE_xscale"))
        .args(args)
        .output()
        .unwrap();
    (
        out.status.code().unwrap_or(-1),
        String::from_utf8_lossy(&out.stderr).into_owned(),
    )
}
