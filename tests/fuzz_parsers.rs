//! Deterministic mutation fuzzing of every input parser (docs/bad-input.md).
//!
//! Coverage-guided fuzzing (`cargo fuzz`) needs a nightly toolchain or `RUSTC_BOOTSTRAP=1` plus
//! libFuzzer; this harness needs neither and runs in the normal test suite. Each target starts
//! from seed files in `fixtures/` and applies 1–4 seeded mutations per case: bit flips, byte
//! overwrites with boundary values, truncation, deletion and duplication of ranges, insertion
//! of chunks from the other seeds, and (for text formats) replacement of a number with an
//! extreme one (`nan`, `-inf`, `1e308`, `4294967296`, …). Every case must
//!   * not panic (`catch_unwind`), and
//!   * if it fails, fail with a message that names the file it read (so a user can find it), and
//!   * if it parses, give a finite mesh with indices in range, or finite cameras with positive
//!     size and focal length (anything else is a silent wrong answer).
//!
//! All failures are collected and asserted once, with the case seed to replay it
//! (`XSCALE_FUZZ_ONLY=target:case`). The default run does a few thousand cases in total (a
//! few seconds); `cargo test --release --test fuzz_parsers -- --ignored` runs the long pass
//! (`XSCALE_FUZZ_CASES=N` per target, default 200,000; about 10–30 minutes on one core).

use std::panic::{catch_unwind, AssertUnwindSafe};
use std::path::{Path, PathBuf};
use std::sync::Once;

#[path = "common/parser_targets.rs"]
mod parser_targets;
use parser_targets::{judge, targets, Target};

fn fixtures() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("fixtures")
}

/// SplitMix64: small, deterministic, good enough for choosing mutations.
struct Rng(u64);
impl Rng {
    fn next(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }
    fn below(&mut self, n: usize) -> usize {
        if n == 0 {
            0
        } else {
            (self.next() % n as u64) as usize
        }
    }
}

const BYTES: &[u8] = &[
    0, 1, 0x7f, 0x80, 0xff, b'-', b'9', b'.', b'e', b' ', b'\n', b'\r', b'#', b'"', b'[', b'{',
    b'=', 0xc3,
];
const NUMBERS: &[&str] = &[
    "nan",
    "NaN",
    "-inf",
    "inf",
    "1e308",
    "-1e308",
    "1e-320",
    "0",
    "-0",
    "-1",
    "4294967295",
    "4294967296",
    "18446744073709551615",
    "99999999999999999999999",
    "2147483648",
    "-2147483649",
    "0.5",
    "1e9",
    "",
    "x",
];
/// Little-endian words that break binary counts and sizes.
const WORDS: &[u64] = &[
    0,
    1,
    u32::MAX as u64,
    u64::MAX,
    i32::MAX as u64,
    1 << 31,
    1 << 40,
    0x7ff8_0000_0000_0000, // f64 NaN
    0xfff0_0000_0000_0000, // f64 -inf
];

/// Replace the `k`-th run of number-like characters.
fn replace_number(data: &mut Vec<u8>, rng: &mut Rng) {
    let is_num = |b: u8| b.is_ascii_digit() || b == b'.' || b == b'-' || b == b'e' || b == b'+';
    let mut runs = Vec::new();
    let mut i = 0;
    while i < data.len() {
        if data[i].is_ascii_digit() {
            let mut s = i;
            while s > 0 && is_num(data[s - 1]) {
                s -= 1;
            }
            let mut e = i;
            while e < data.len() && is_num(data[e]) {
                e += 1;
            }
            runs.push((s, e));
            i = e;
        } else {
            i += 1;
        }
    }
    if runs.is_empty() {
        return;
    }
    let (s, e) = runs[rng.below(runs.len())];
    let n = NUMBERS[rng.below(NUMBERS.len())].as_bytes();
    data.splice(s..e, n.iter().copied());
}

fn mutate(seed: &[u8], others: &[Vec<u8>], text: bool, rng: &mut Rng) -> Vec<u8> {
    let mut d = seed.to_vec();
    let n = 1 + rng.below(4);
    for _ in 0..n {
        let len = d.len();
        match rng.below(if text { 9 } else { 8 }) {
            0 if len > 0 => {
                let i = rng.below(len);
                d[i] ^= 1 << rng.below(8);
            }
            1 if len > 0 => {
                let i = rng.below(len);
                d[i] = BYTES[rng.below(BYTES.len())];
            }
            2 => d.truncate(rng.below(len + 1)),
            3 if len > 0 => {
                let s = rng.below(len);
                let e = (s + 1 + rng.below(16)).min(len);
                d.drain(s..e);
            }
            4 if len > 0 => {
                let s = rng.below(len);
                let e = (s + 1 + rng.below(64)).min(len);
                let chunk = d[s..e].to_vec();
                let at = rng.below(len + 1);
                d.splice(at..at, chunk);
            }
            5 if !others.is_empty() => {
                let o = &others[rng.below(others.len())];
                if !o.is_empty() {
                    let s = rng.below(o.len());
                    let e = (s + 1 + rng.below(128)).min(o.len());
                    let at = rng.below(len + 1);
                    d.splice(at..at, o[s..e].iter().copied());
                }
            }
            6 if len >= 8 => {
                let w = WORDS[rng.below(WORDS.len())].to_le_bytes();
                let width = [1usize, 4, 8][rng.below(3)];
                let i = rng.below(len - width + 1);
                d[i..i + width].copy_from_slice(&w[..width]);
            }
            7 if len > 0 => {
                let i = rng.below(len);
                d[i] = d[i].wrapping_add(1 + rng.below(3) as u8);
            }
            8 => replace_number(&mut d, rng),
            _ => {}
        }
    }
    d
}

#[derive(Default)]
struct Outcome {
    cases: usize,
    ok: usize,
    errors: usize,
    failures: Vec<String>,
}

fn quiet_panics() {
    static ONCE: Once = Once::new();
    ONCE.call_once(|| {
        let prev = std::panic::take_hook();
        std::panic::set_hook(Box::new(move |info| {
            if std::env::var_os("XSCALE_FUZZ_VERBOSE").is_some() {
                prev(info);
            }
        }));
    });
}

fn run_target(t: &Target, cases: usize, work: &Path) -> Outcome {
    quiet_panics();
    let mut out = Outcome::default();
    let only = std::env::var("XSCALE_FUZZ_ONLY").ok();
    for case in 0..cases {
        if let Some(o) = &only {
            if *o != format!("{}:{case}", t.name) && *o != t.name {
                continue;
            }
        }
        let mut rng = Rng(0x5EED_0000 ^ (case as u64).wrapping_mul(0x1000_0000_01B3));
        let si = rng.below(t.seeds.len());
        let bytes = if case < t.seeds.len() {
            t.seeds[case].clone() // the unmutated seeds parse
        } else {
            mutate(&t.seeds[si], &t.seeds, t.text, &mut rng)
        };
        out.cases += 1;
        let r = catch_unwind(AssertUnwindSafe(|| (t.run)(&bytes, work)));
        match r {
            Err(p) => {
                let msg = p
                    .downcast_ref::<String>()
                    .cloned()
                    .or_else(|| p.downcast_ref::<&str>().map(|s| s.to_string()))
                    .unwrap_or_default();
                if let Some(o) = &only {
                    if o.contains(':') {
                        std::fs::write(work.join("crash.bin"), &bytes).ok();
                    }
                }
                out.failures
                    .push(format!("{}:{case}: PANIC: {msg}", t.name));
            }
            Ok((path, res)) => {
                if res.is_ok() {
                    out.ok += 1;
                } else {
                    out.errors += 1;
                }
                if let (Err(e), Some(_)) = (&res, std::env::var_os("XSCALE_FUZZ_VERBOSE")) {
                    eprintln!("{}:{case}: {e:#}", t.name);
                }
                if let Err(why) = judge(&path, &res, case < t.seeds.len()) {
                    out.failures.push(format!("{}:{case}: {why}", t.name));
                }
            }
        }
    }
    out
}

fn work_dir(tag: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("xscale-fuzz-{tag}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).unwrap();
    d
}

fn fuzz_all(cases: Option<usize>, tag: &str) {
    let work = work_dir(tag);
    let ts = targets(&fixtures(), &work);
    let mut failures = Vec::new();
    let mut total = 0;
    for t in &ts {
        let n = cases.unwrap_or(t.quick);
        let tw = work.join(format!("w-{}", t.name));
        std::fs::create_dir_all(&tw).unwrap();
        let t0 = std::time::Instant::now();
        let o = run_target(t, n, &tw);
        eprintln!(
            "fuzz {:16} cases {:8}  parsed {:7}  rejected {:7}  failures {:4}  ({:.1} s)",
            t.name,
            o.cases,
            o.ok,
            o.errors,
            o.failures.len(),
            t0.elapsed().as_secs_f64()
        );
        total += o.cases;
        failures.extend(o.failures);
    }
    eprintln!("fuzz total cases {total}, failures {}", failures.len());
    for f in failures.iter().take(60) {
        eprintln!("{f}");
    }
    let _ = std::fs::remove_dir_all(&work);
    assert!(
        failures.is_empty(),
        "{} failing cases (replay one with XSCALE_FUZZ_ONLY=target:case):\n{}",
        failures.len(),
        failures
            .iter()
            .take(60)
            .cloned()
            .collect::<Vec<_>>()
            .join("\n")
    );
}

#[test]
fn mutated_inputs_never_panic_and_errors_name_the_file() {
    fuzz_all(None, "quick");
}

/// Long pass: `XSCALE_FUZZ_CASES` per target (default 200,000; roughly 10–30 minutes on one
/// core, dominated by the checkpoint and scene targets).
#[test]
#[ignore]
fn mutated_inputs_long_pass() {
    let n = std::env::var("XSCALE_FUZZ_CASES")
        .ok()
        .and_then(|s| s.parse().ok())
        .unwrap_or(200_000);
    fuzz_all(Some(n), "long");
}

/// The mutator itself changes its input and is deterministic (a harness that returned the seed
/// unchanged would pass every parser).
#[test]
fn mutator_is_deterministic_and_mutates() {
    let seed = b"ply\nformat ascii 1.0\nelement vertex 3\n0 0 0\n1 0 0\n0 1 0\n".to_vec();
    let mut changed = 0;
    for case in 0..200u64 {
        let a = mutate(&seed, &[], true, &mut Rng(case));
        let b = mutate(&seed, &[], true, &mut Rng(case));
        assert_eq!(a, b);
        if a != seed {
            changed += 1;
        }
    }
    assert!(
        changed > 180,
        "only {changed} of 200 mutations changed the input"
    );
}

/// Writes each target's seeds into `fuzz/corpus/<target>/` for `cargo fuzz run <target>`
/// (docs/bad-input.md); run before a first coverage-guided run.
#[test]
#[ignore]
fn write_cargo_fuzz_seed_corpora() {
    let work = work_dir("corpora");
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("fuzz/corpus");
    for t in targets(&fixtures(), &work) {
        let d = root.join(t.name);
        std::fs::create_dir_all(&d).unwrap();
        for (i, s) in t.seeds.iter().enumerate() {
            std::fs::write(d.join(format!("seed-{i}")), s).unwrap();
        }
    }
    let _ = std::fs::remove_dir_all(&work);
}
