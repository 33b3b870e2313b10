//! Measured figures live on one generated page, `docs/results.md` (written by `cargo run
//! --release --example results`), so that no two pages can disagree. This test fails when
//! `README.md` or a page under `docs/` (except `results.md` itself and `changelog.md`, which keeps
//! old figures as history) quotes a figure that `results.md` does not hold.
//!
//! A *figure* is a number with a unit of measurement: dB, s, ms, µs, ns, min, minutes, seconds,
//! %, × or x (a ratio: `6.8×`, not a size `64×48`), pixels/s, px/s, rays/s, Mrays/s, B, KB, kB,
//! MB, GB, TB, KiB, MiB, GiB; a range `1.5–1.8 ms` counts both ends. Numbers inside code spans and
//! fenced blocks are commands and values a user types, not figures, and are skipped. A figure is
//! *held* by `results.md` when that page has the same number with the same unit, in its prose or
//! in a table column whose header names the unit (`masked PSNR (dB)`, `pixels/s`, `ms/step`).
//!
//! [`ALLOWED`] lists the constants of the specification and of the code that docs may state with
//! a unit (thresholds, defaults, sizes that follow from a preset), each with its reason. It is not
//! a place for measurements: those go to `docs/results.md`.

use std::collections::BTreeSet;
use std::path::{Path, PathBuf};

/// (page or "*", figure as written, why it is not a measurement).
const ALLOWED: &[(&str, &str, &str)] = &[
    ("*", "2 GB", "train.samples = \"auto\" takes the sample cache up to 2 GB (src/train/memory.rs)"),
    ("docs/spec.md", "64 KB", "Metashape detection reads a file's first 64 KB (§3.1)"),
    ("*", "1.4 GB", "the paper preset's grid H: 44,043,888 entries × 8 features × 4 bytes (§9)"),
    ("*", "10 %", "the automatic level range takes each view's 10 % footprint quantile (§8); ablate's mesh10 keeps 10 % of the faces"),
    ("*", "95 %", "divergence: the loss never fell below 95 % of its step-10 value (docs/runs.md)"),
    ("*", "95%", "divergence: the loss never fell below 95 % of its step-10 value (docs/runs.md)"),
    ("*", "3×", "divergence: the loss stayed above 3× its best (docs/runs.md)"),
    ("*", "2 s", "synth and long commands report progress at least every 2 s"),
    ("*", "0.1 %", "photo check: a ray meets the mesh within 0.1 % of its diagonal (spec §3.9)"),
    ("*", "4×", "ULR and photo check: footprint ratios up to 4× (spec §3.9, §4.11)"),
    ("*", "10%", "ablate's mesh10 keeps 10% of the faces (the paper's Table 5)"),
    ("*", "2 %", "bench-geometry --decimate 0.02: the decimated proxy keeps 2 % of the faces"),
    ("*", "0.1 %", "bench-geometry's proxies: smooth displacement of RMS 0.1 % of the diagonal"),
    ("*", "0.3 %", "bench-geometry's proxies: smooth displacement of RMS 0.3 % of the diagonal"),
    ("*", "1 %", "bench-geometry's proxies: smooth displacement of RMS 1 % of the diagonal"),
    ("*", "5 %", "photo check: moved up by 5 % of the diagonal (a test case of spec §3.9)"),
    ("*", "3 %", "photo check: moved sideways 3 % (a test case of spec §3.9)"),
    ("*", "1 s", "a copy of a stop signal within 1 s of the first counts as one (docs/runs.md)"),
    ("docs/ablation-small.md", "2 dB", "ablate's claim: the full model beats the vertex baselines by at least 2 dB (src/experiments/ablate.rs)"),
    ("docs/ablation-small.md", "1 dB", "ablate's claim: the decimated mesh costs at most 1 dB (src/experiments/ablate.rs)"),
    ("docs/numerics.md", "0.4 dB", "the bound tests/numerics.rs asserts for the tiny invariance cases"),
    ("docs/numerics.md", "0.6 dB", "the bound tests/numerics.rs asserts for the small invariance cases"),
    ("docs/numerics.md", "1 dB", "the bound tests/numerics.rs asserts between f32 and f64 long runs"),
    ("docs/bad-input.md", "10×", "mesh-distance warns when the bounding boxes differ more than 10× (src/cli/mesh_distance.rs)"),
    ("docs/bad-input.md", "1000×", "the scene check warns for a mesh 1000× or more larger than the cameras' spread"),
    ("docs/spec.md", "73 %", "stored by rows when that saves a quarter of a table's bytes: with 2 features, about 73 % of its rows stepped or fewer (§6.2, checkpoint::stores_by_rows)"),
    ("docs/spec.md", "30 %", "the points check's threshold: under 30 % of the in-box points on the mesh (§3.9)"),
    ("docs/spec.md", "40 %", "the points check's threshold: under 40 % of the mesh's samples covered (§3.9)"),
    ("docs/spec.md", "0.5 %", "a test case of the photo check: the mesh moved sideways by 0.5 % of its diagonal (§3.9)"),
    ("docs/spec.md", "8 %", "a test case of the points check: the mesh moved up by 8 % of the seen size (§3.9, tests/scene_formats.rs)"),
    ("docs/oracle.md", "30 %", "the golden cases mark about 30 % of their sub-samples invalid (fixtures/golden/README.md)"),
    ("docs/oracle.md", "13×", "the margin the f64 tolerance file leaves by design (fixtures/golden/tolerances-f64.toml)"),
    ("docs/oracle.md", "30×", "fp16 limits are 30–100× looser than fp32 by design (fixtures/golden/tolerances-fp16.toml)"),
    ("docs/oracle.md", "100×", "fp16 limits are 30–100× looser than fp32 by design (fixtures/golden/tolerances-fp16.toml)"),
    ("docs/oracle.md", "10×", "the default kink threshold is about 10× the worst fp32 forward error, by design"),
];

const UNITS: &[&str] = &[
    "dB", "s", "ms", "µs", "us", "ns", "min", "minutes", "seconds", "%", "×", "x", "pixels/s",
    "px/s", "rays/s", "Mrays/s", "B", "KB", "kB", "MB", "GB", "TB", "KiB", "MiB", "GiB",
];

/// A figure: the number as written (commas removed) and its unit.
type Figure = (String, String);

fn root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}

/// The text of `md` without fenced blocks, inline code spans and HTML comments, line by line
/// (blanked, so line numbers stay).
fn prose(md: &str) -> Vec<String> {
    let mut out = Vec::new();
    let mut fenced = false;
    let mut comment = false;
    for line in md.lines() {
        if line.trim_start().starts_with("```") {
            fenced = !fenced;
            out.push(String::new());
            continue;
        }
        if fenced {
            out.push(String::new());
            continue;
        }
        let mut s = String::new();
        let mut code = false;
        let b: Vec<char> = line.chars().collect();
        let mut i = 0;
        while i < b.len() {
            if comment {
                if b[i..].starts_with(&['-', '-', '>']) {
                    comment = false;
                    i += 3;
                } else {
                    i += 1;
                }
                continue;
            }
            if !code && b[i..].starts_with(&['<', '!', '-', '-']) {
                comment = true;
                i += 4;
                continue;
            }
            if b[i] == '`' {
                code = !code;
                s.push(' ');
            } else if !code {
                s.push(b[i]);
            }
            i += 1;
        }
        out.push(s);
    }
    out
}

fn is_space(c: char) -> bool {
    c == ' ' || c == '\u{a0}' || c == '\u{2009}' || c == '\u{202f}'
}

/// The figures of one line of prose.
fn figures(line: &str) -> Vec<Figure> {
    let c: Vec<char> = line.chars().collect();
    let mut out = Vec::new();
    let mut pending: Vec<String> = Vec::new();
    let mut i = 0;
    while i < c.len() {
        let starts = c[i].is_ascii_digit()
            && (i == 0 || !(c[i - 1].is_alphanumeric() || "_.^/-–·".contains(c[i - 1])));
        // A range's second number follows '–' or '-' directly.
        let range_end =
            c[i].is_ascii_digit() && !pending.is_empty() && i > 0 && "–-".contains(c[i - 1]);
        if !(starts || range_end) {
            i += 1;
            continue;
        }
        let mut j = i;
        while j < c.len()
            && (c[j].is_ascii_digit()
                || ((c[j] == ',' || c[j] == '.') && j + 1 < c.len() && c[j + 1].is_ascii_digit()))
        {
            j += 1;
        }
        let num: String = c[i..j].iter().filter(|&&x| x != ',').collect();
        // "2^19", "1e-6", "3.2k": exponents and multipliers.
        let mut k = j;
        if k < c.len()
            && (c[k] == 'k' || c[k] == 'M')
            && (k + 1 >= c.len() || !c[k + 1].is_alphabetic())
        {
            k += 1;
        }
        if k < c.len()
            && (c[k] == 'e' || c[k] == '^')
            && k + 1 < c.len()
            && (c[k + 1].is_ascii_digit() || c[k + 1] == '-')
        {
            pending.clear();
            i = k + 1;
            while i < c.len() && (c[i].is_ascii_digit() || c[i] == '-') {
                i += 1;
            }
            continue;
        }
        let num = num + &c[j..k].iter().collect::<String>();
        // A range: number, dash, number, then the unit.
        if k < c.len() && "–-".contains(c[k]) && k + 1 < c.len() && c[k + 1].is_ascii_digit() {
            pending.push(num);
            i = k + 1;
            continue;
        }
        let mut u = k;
        while u < c.len() && is_space(c[u]) {
            u += 1;
        }
        let mut e = u;
        while e < c.len() && (c[e].is_alphabetic() || "%×/µ".contains(c[e])) {
            e += 1;
            // A ratio sign is a unit of its own ("6.8×faster" is not written).
            if c[e - 1] == '×' || c[e - 1] == '%' {
                break;
            }
        }
        let unit: String = c[u..e].iter().collect();
        let unit = unit.trim_end_matches('/').to_string();
        let mut ok = UNITS.contains(&unit.as_str());
        // `x` only right after the number ("6.8x"), never as a word ("4 x 4").
        if unit == "x" && u != k {
            ok = false;
        }
        // "64×48", "2 × 64": a size, not a ratio.
        if unit == "×" {
            let mut n = e;
            while n < c.len() && is_space(c[n]) {
                n += 1;
            }
            if n < c.len()
                && (c[n].is_ascii_digit()
                    || c[n] == 'γ'
                    || c[n].is_alphabetic() && c[n].is_uppercase())
            {
                ok = false;
            }
        }
        if ok {
            for p in pending.drain(..) {
                out.push((p, unit.clone()));
            }
            out.push((num, unit));
        }
        pending.clear();
        i = e.max(j);
    }
    out
}

/// Same number? "35.4" and "35.40" are the same figure; "1,000" and "1000" too.
fn norm(n: &str) -> String {
    let n = n.replace(',', "");
    if n.contains('.') && !n.ends_with('k') && !n.ends_with('M') {
        n.trim_end_matches('0').trim_end_matches('.').to_string()
    } else {
        n
    }
}

fn canon_unit(u: &str) -> &str {
    match u {
        "x" => "×",
        "seconds" => "s",
        "minutes" => "min",
        "us" => "µs",
        "px/s" => "pixels/s",
        _ => u,
    }
}

/// What `results.md` holds: its prose figures, and every number of a table column whose header
/// names a unit.
fn held(results: &str) -> BTreeSet<(String, String)> {
    let mut set = BTreeSet::new();
    for line in prose(results) {
        for (n, u) in figures(&line) {
            set.insert((norm(&n), canon_unit(&u).to_string()));
        }
    }
    let mut header: Option<Vec<Option<String>>> = None;
    for line in results.lines() {
        let t = line.trim();
        if !t.starts_with('|') {
            header = None;
            continue;
        }
        let cells: Vec<String> = t
            .trim_matches('|')
            .split('|')
            .map(|c| c.trim().to_string())
            .collect();
        match &header {
            None => {
                header = Some(
                    cells
                        .iter()
                        .map(|h| {
                            if let (Some(a), Some(b)) = (h.rfind('('), h.rfind(')')) {
                                if a < b {
                                    return Some(h[a + 1..b].to_string());
                                }
                            }
                            if h.ends_with("pixels/s") {
                                return Some("pixels/s".into());
                            }
                            h.strip_prefix("ms/").map(|_| "ms".to_string())
                        })
                        .collect(),
                )
            }
            Some(h) => {
                for (i, cell) in cells.iter().enumerate() {
                    if let Some(Some(u)) = h.get(i) {
                        if cell
                            .chars()
                            .next()
                            .is_some_and(|c| c.is_ascii_digit() || c == '-')
                        {
                            set.insert((norm(cell), canon_unit(u).to_string()));
                            // A ratio column may be written "1.82" on the page and "1.82×" in prose.
                        }
                    }
                }
            }
        }
    }
    set
}

fn allowed(page: &str, n: &str, u: &str) -> bool {
    let written = |sep: &str| format!("{n}{sep}{u}");
    ALLOWED.iter().any(|(p, fig, _)| {
        (*p == "*" || *p == page) && (*fig == written("") || *fig == written(" "))
    })
}

/// The pages the guard reads: README.md and docs/**/*.md except results.md and changelog.md.
fn pages(root: &Path) -> Vec<PathBuf> {
    let mut v = vec![root.join("README.md")];
    let mut stack = vec![root.join("docs")];
    while let Some(d) = stack.pop() {
        for e in std::fs::read_dir(&d).unwrap().flatten() {
            let p = e.path();
            if p.is_dir() {
                stack.push(p);
            } else if p.extension().is_some_and(|x| x == "md")
                && !p.ends_with("docs/results.md")
                && !p.ends_with("docs/changelog.md")
            {
                v.push(p);
            }
        }
    }
    v.sort();
    v
}

/// Every figure of `text` (page `name`) that `results` does not hold and no allowance covers.
fn stray(name: &str, text: &str, results: &BTreeSet<(String, String)>) -> Vec<String> {
    let mut bad = Vec::new();
    for (ln, line) in prose(text).iter().enumerate() {
        for (n, u) in figures(line) {
            let key = (norm(&n), canon_unit(&u).to_string());
            if !results.contains(&key) && !allowed(name, &n, &u) {
                bad.push(format!("{name}:{}: {n} {u}", ln + 1));
            }
        }
    }
    bad
}

#[test]
fn docs_quote_only_figures_results_md_holds() {
    let root = root();
    let results = std::fs::read_to_string(root.join("docs/results.md"))
        .expect("docs/results.md: run `cargo run --release --example results`");
    let held = held(&results);
    let mut bad = Vec::new();
    for p in pages(&root) {
        let name = p.strip_prefix(&root).unwrap().display().to_string();
        let text = std::fs::read_to_string(&p).unwrap();
        bad.extend(stray(&name, &text, &held));
    }
    assert!(
        bad.is_empty(),
        "figures quoted outside docs/results.md that it does not hold (link to the section of \
         docs/results.md instead, move history to docs/changelog.md, or, for a constant of the \
         spec, add it to ALLOWED in tests/doc_figures.rs with its reason):\n{}",
        bad.join("\n")
    );
}

/// The guard itself: a stray figure fails, a held one, a size, a command and an allowed constant
/// do not.
#[test]
fn the_guard_catches_a_stray_figure() {
    let results = "# Results\n\n| steps | masked PSNR (dB) | pixels/s |\n|---|---|---|\n| 1000 | 34.27 | 203,114 |\n\nThe render took 1.74 s.\n";
    let held = held(results);
    let page = "After 1000 steps: 34.27 dB (203,114 pixels/s); a render takes 1.74 s.\n\
                Images of 64×48, a 2 × 64 shader, `--minutes 0.5`, the cache up to 2 GB.\n\
                ```\nxscale bench-quality --minutes 0.25   # 12 s\n```\n";
    assert_eq!(stray("README.md", page, &held), Vec::<String>::new());
    for planted in [
        "The default reaches 36.38 dB.",
        "It runs at 135k pixels/s.",
        "PyTorch is 6.8× slower.",
        "PyTorch is 6.8x slower.",
        "A step takes 19.1–20.2 ms.",
        "Peak memory 0.79 GB.",
        "Adam is 27 % of a step.",
        "A render takes 1.7 s.",
    ] {
        let bad = stray("README.md", planted, &held);
        assert!(!bad.is_empty(), "not caught: {planted}");
    }
    // A range counts both ends.
    assert_eq!(stray("x.md", "19.1–20.2 ms", &held).len(), 2);
}

/// `docs/results.md` is the rendering of `docs/results/*.json`, not a page edited by hand: every
/// section's title is on it, and it has exactly as many table rows as the sections' files hold
/// (`cargo run --release --example results -- --render-only` rewrites it from them).
#[test]
fn results_md_is_rendered_from_its_sections() {
    let root = root();
    let page = std::fs::read_to_string(root.join("docs/results.md")).unwrap();
    assert!(
        page.contains("Generated by `cargo run --release --example results`"),
        "docs/results.md lost its generated-page marker"
    );
    let mut rows = 0;
    let mut sections = 0;
    for e in std::fs::read_dir(root.join("docs/results"))
        .unwrap()
        .flatten()
    {
        let p = e.path();
        if p.extension().is_none_or(|x| x != "json") {
            continue;
        }
        let v: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(&p).unwrap()).unwrap();
        let title = v["title"]
            .as_str()
            .unwrap_or_else(|| panic!("{}: no title", p.display()));
        assert!(
            page.contains(&format!("## {title}")),
            "{}: its section is not on docs/results.md (rerun the example with --render-only)",
            p.display()
        );
        for k in ["host", "date", "commit", "commands"] {
            assert!(!v[k].is_null(), "{}: no {k}", p.display());
        }
        for t in v["tables"].as_array().into_iter().flatten() {
            rows += t["rows"].as_array().map_or(0, |r| r.len());
        }
        sections += 1;
    }
    assert!(sections > 0, "docs/results/ holds no section");
    // Table rows on the page: lines starting with '|' minus each table's header and rule.
    let mut on_page = 0;
    let mut in_table = 0;
    for line in page.lines() {
        if line.trim_start().starts_with('|') {
            in_table += 1;
            if in_table > 2 {
                on_page += 1;
            }
        } else {
            in_table = 0;
        }
    }
    assert_eq!(
        on_page, rows,
        "docs/results.md has {on_page} table rows, its sections' files {rows}: edited by hand?"
    );
}
