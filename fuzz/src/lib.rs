//! The coverage-guided targets' shared body: the same parsers, seeds and verdict as the
//! mutation harness in the normal tests (`tests/fuzz_parsers.rs`), taken from one table
//! (`tests/common/parser_targets.rs`). A case fails (libFuzzer records a crash) when the parser
//! panics, or when `judge` finds a rejection that does not name the file or an accepted input
//! that is not finite and in range.

use std::path::{Path, PathBuf};
use std::sync::OnceLock;

#[path = "../../tests/common/parser_targets.rs"]
pub mod parser_targets;
use parser_targets::{judge, targets, Target};

struct Fixture {
    targets: Vec<Target>,
    work: PathBuf,
}

fn fixture() -> &'static Fixture {
    static F: OnceLock<Fixture> = OnceLock::new();
    F.get_or_init(|| {
        // One work dir per process: several fuzzers (or -fork/-jobs workers) may run at once.
        let work = std::env::temp_dir().join(format!("xscale-cargo-fuzz-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&work);
        std::fs::create_dir_all(&work).unwrap();
        let fx = Path::new(env!("CARGO_MANIFEST_DIR")).join("../fixtures");
        let targets = targets(&fx, &work);
        Fixture { targets, work }
    })
}

/// Run target `name` on `data`; panics (a libFuzzer crash) on a contract violation.
pub fn check(name: &str, data: &[u8]) {
    let f = fixture();
    let t = f
        .targets
        .iter()
        .find(|t| t.name == name)
        .unwrap_or_else(|| panic!("no fuzz target '{name}'"));
    let tw = f.work.join(name);
    std::fs::create_dir_all(&tw).unwrap();
    let (path, r) = (t.run)(data, &tw);
    if let Err(why) = judge(&path, &r, false) {
        panic!("{name}: {why}");
    }
}
