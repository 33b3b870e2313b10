//! `docs/spec.md` is the numerics contract the code cites. This test keeps the two together:
//!
//! - every citation `SPEC §N` / `SPEC §N.M` (and the rest of a list such as `SPEC §4.8, §8`) in
//!   `src/`, `tests/`, `benches/`, `docs/`, `reference/`, `fixtures/`, `configs/`, `README.md`
//!   and `Cargo.toml`, and every `§N` cross reference inside `docs/spec.md`, names a section that
//!   exists as a heading of `docs/spec.md`; a citation spelled without `§` (`SPEC 4.2`) and a
//!   mention of a brief or notes file that is not in the repository are errors too. All dangling
//!   citations are listed at once, with file and line.
//! - the generated tables of `docs/spec.md` (presets, Adam groups, per-level grid geometry) are
//!   exactly what `RunConfig::preset` / `HashGrid::new` give. `XSCALE_BLESS=1 cargo test --release
//!   --test spec_refs` rewrites them in place after a deliberate change of a preset.
//! - every configuration key the user docs (`README.md`, `docs/*.md`) name in an inline code span
//!   (`model.grid_h.levels`, `[train] samples = "cache"`, `train.adam.<group>`) or set in a
//!   fenced `toml` block exists, and a value given there has the key's type (an enum's variant);
//!   §4.11's `[model.refine]` table lists exactly `RefineConfig`'s keys with their defaults.
//!
//! This file is the checker, so it is not scanned itself (its examples would count).

use std::collections::{BTreeMap, BTreeSet};
use std::fmt::Write as _;
use std::path::{Path, PathBuf};
use xscale::model::hashgrid::HashGrid;
use xscale::train::adam::AdamGroup;
use xscale::train::config::RunConfig;

const SCAN_DIRS: &[&str] = &[
    "src",
    "tests",
    "benches",
    "docs",
    "reference",
    "fixtures",
    "configs",
];
const SCAN_FILES: &[&str] = &["README.md", "Cargo.toml"];
const TEXT_EXT: &[&str] = &["rs", "md", "py", "toml", "sh", "txt"];
const SPEC: &str = "docs/spec.md";
const SELF: &str = "tests/spec_refs.rs";
/// Files the code once cited that are not part of the repository (their content now lives in
/// `docs/spec.md` and `docs/notes.md`). Built by concatenation so this file does not cite them.
const GONE: [[&str; 2]; 2] = [["NOTES", ".md"], ["SPEC", ".md"]];
const PRESETS: [&str; 3] = ["tiny", "cpu", "paper"];

fn root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}

/// `§N(.M)*` at the start of `s`: the section id ("4", "4.2") and its length in bytes.
fn section_at(s: &str) -> Option<(String, usize)> {
    let rest = s.strip_prefix('§')?;
    let b = rest.as_bytes();
    let mut i = 0;
    while i < b.len() && b[i].is_ascii_digit() {
        i += 1;
    }
    if i == 0 {
        return None;
    }
    // Further `.digits` groups ("4.2"); a trailing '.' ends a sentence.
    while i + 1 < b.len() && b[i] == b'.' && b[i + 1].is_ascii_digit() {
        i += 1;
        while i < b.len() && b[i].is_ascii_digit() {
            i += 1;
        }
    }
    Some((rest[..i].to_string(), '§'.len_utf8() + i))
}

/// Section ids of the numbered headings: `## §4. Model` → "4", `### §4.2 Hash grid` → "4.2".
fn headings(spec: &str) -> BTreeSet<String> {
    spec.lines()
        .filter(|l| l.starts_with('#'))
        .filter_map(|l| section_at(l.trim_start_matches('#').trim_start()).map(|(id, _)| id))
        .collect()
}

fn line_of(text: &str, pos: usize) -> usize {
    text[..pos].bytes().filter(|&c| c == b'\n').count() + 1
}

/// What a scan found in one text: `(line, section id)` citations and `(line, message)` errors.
#[derive(Debug, Default, PartialEq)]
struct Found {
    cites: Vec<(usize, String)>,
    errors: Vec<(usize, String)>,
}

/// After `SPEC`: the list `§a, §b and §c` (comment markers and line breaks may sit between
/// `SPEC` and the first `§`, as in a doc comment wrapped mid-citation).
fn scan_spec_citations(text: &str) -> Found {
    let mut f = Found::default();
    let bytes = text.as_bytes();
    for (pos, _) in text.match_indices("SPEC") {
        let before_ok =
            pos == 0 || !(bytes[pos - 1].is_ascii_alphanumeric() || bytes[pos - 1] == b'_');
        let after = &text[pos + 4..];
        let after_ok = !after
            .as_bytes()
            .first()
            .is_some_and(|c| c.is_ascii_alphanumeric() || *c == b'_' || *c == b'.');
        if !before_ok || !after_ok {
            continue;
        }
        let gap = after
            .find(|c: char| !(c.is_whitespace() || matches!(c, '/' | '!' | '#' | '*')))
            .unwrap_or(after.len());
        let mut rest = &after[gap..];
        if rest.starts_with(|c: char| c.is_ascii_digit()) {
            let p = text.len() - rest.len();
            let n: String = rest
                .chars()
                .take_while(|c| c.is_ascii_digit() || *c == '.')
                .collect();
            f.errors.push((
                line_of(text, p),
                format!("\"SPEC {n}\" cites a section without '§' (write \"SPEC §{n}\")"),
            ));
            continue;
        }
        while let Some((id, len)) = section_at(rest) {
            f.cites.push((line_of(text, text.len() - rest.len()), id));
            rest = &rest[len..];
            // `, §b`, ` and §c`, ` or §c`, `/§b`, `–§b`
            let t = rest.trim_start_matches([',', ' ', '/', '–', '-']);
            let t = t
                .strip_prefix("and ")
                .or_else(|| t.strip_prefix("or "))
                .unwrap_or(t);
            if !t.starts_with('§') {
                break;
            }
            rest = t;
        }
    }
    f
}

/// Every `§N` in `docs/spec.md` (its cross references and its own headings).
fn scan_all_sections(text: &str) -> Found {
    let mut f = Found::default();
    for (pos, _) in text.match_indices('§') {
        if let Some((id, _)) = section_at(&text[pos..]) {
            f.cites.push((line_of(text, pos), id));
        }
    }
    f
}

fn scan_gone_files(text: &str, f: &mut Found) {
    for [stem, ext] in GONE {
        let name = format!("{stem}{ext}");
        for (pos, _) in text.match_indices(&name) {
            f.errors.push((
                line_of(text, pos),
                format!("cites {name}, which is not in the repository (docs/spec.md is the contract, docs/notes.md the anchors' facts)"),
            ));
        }
    }
}

fn text_files(dir: &Path, out: &mut Vec<PathBuf>) {
    let Ok(rd) = std::fs::read_dir(dir) else {
        return;
    };
    let mut entries: Vec<PathBuf> = rd.flatten().map(|e| e.path()).collect();
    entries.sort();
    for p in entries {
        if p.is_dir() {
            text_files(&p, out);
        } else if p
            .extension()
            .and_then(|e| e.to_str())
            .is_some_and(|e| TEXT_EXT.contains(&e))
        {
            out.push(p);
        }
    }
}

fn rel(p: &Path) -> String {
    p.strip_prefix(root())
        .unwrap_or(p)
        .to_string_lossy()
        .replace('\\', "/")
}

#[test]
fn parser_finds_lists_wrapped_citations_and_bad_spellings() {
    let text = "a (SPEC §4.8, §8) b\n//! local frame of SPEC\n//! §4.1. Then pbrt-v4 §6.5.3,\n\
                SPEC §2 and §3; SPEC §7: masked; the SPEC's numerics; SPECIAL §9; SPEC 4.2 x";
    let f = scan_spec_citations(text);
    let cites: Vec<(usize, &str)> = f.cites.iter().map(|(l, s)| (*l, s.as_str())).collect();
    assert_eq!(
        cites,
        [
            (1, "4.8"),
            (1, "8"),
            (3, "4.1"),
            (4, "2"),
            (4, "3"),
            (4, "7")
        ]
    );
    assert_eq!(f.errors.len(), 1, "{:?}", f.errors);
    assert!(f.errors[0].1.contains("SPEC 4.2"), "{:?}", f.errors);
    let h = headings("# T\n## §4. Model\n### §4.2 Grid\n#### §4.2.1 Index\n## Appendix\n§5 text\n");
    assert_eq!(h, ["4", "4.2", "4.2.1"].map(String::from).into());
}

#[test]
fn every_spec_citation_names_a_section_of_docs_spec_md() {
    let root = root();
    let spec = std::fs::read_to_string(root.join(SPEC)).expect("docs/spec.md exists");
    let sections = headings(&spec);
    // The contract keeps the brief's numbering: §0–§9 and §4.1–§4.8 at least.
    for id in [
        "0", "1", "2", "3", "4", "5", "6", "7", "8", "9", "4.1", "4.2", "4.3", "4.4", "4.5", "4.6",
        "4.7", "4.8",
    ] {
        assert!(
            sections.contains(id),
            "docs/spec.md has no heading for §{id}"
        );
    }
    let mut files = Vec::new();
    for d in SCAN_DIRS {
        text_files(&root.join(d), &mut files);
    }
    files.extend(SCAN_FILES.iter().map(|f| root.join(f)));
    let mut dangling = Vec::new();
    let mut n_cites = 0;
    for p in &files {
        let r = rel(p);
        if r == SELF {
            continue;
        }
        let bytes = std::fs::read(p).unwrap_or_else(|e| panic!("{r}: {e}"));
        let text = String::from_utf8_lossy(&bytes);
        let mut f = if r == SPEC {
            scan_all_sections(&text)
        } else {
            scan_spec_citations(&text)
        };
        scan_gone_files(&text, &mut f);
        n_cites += f.cites.len();
        for (line, id) in f.cites {
            if !sections.contains(&id) {
                dangling.push(format!(
                    "{r}:{line}: §{id} is not a section of docs/spec.md"
                ));
            }
        }
        dangling.extend(
            f.errors
                .into_iter()
                .map(|(line, m)| format!("{r}:{line}: {m}")),
        );
    }
    assert!(
        dangling.is_empty(),
        "{} dangling citation(s):\n{}\n(sections of docs/spec.md: {})",
        dangling.len(),
        dangling.join("\n"),
        sections
            .iter()
            .map(|s| format!("§{s}"))
            .collect::<Vec<_>>()
            .join(" ")
    );
    // The scan must have seen the code's citations (a scanner that finds nothing passes nothing).
    assert!(
        n_cites > 150,
        "only {n_cites} citations found: is the scanner broken?"
    );
}

// ------------------------------------------------------------------------------------------------
// Generated tables

fn fmt_value(v: &toml::Value) -> String {
    match v {
        toml::Value::Float(x) => format!("{x:?}"),
        toml::Value::String(s) => format!("`\"{s}\"`"),
        other => other.to_string(),
    }
}

fn flatten(prefix: &str, t: &toml::Table, out: &mut BTreeMap<String, String>) {
    for (k, v) in t {
        let key = if prefix.is_empty() {
            k.clone()
        } else {
            format!("{prefix}.{k}")
        };
        match v {
            toml::Value::Table(sub) => flatten(&key, sub, out),
            other => {
                out.insert(key, fmt_value(other));
            }
        }
    }
}

/// Every field of every preset's run configuration (`train.adam` in its own table).
fn presets_table() -> String {
    let mut rows: BTreeMap<String, Vec<String>> = BTreeMap::new();
    for (i, name) in PRESETS.iter().enumerate() {
        let cfg = RunConfig::preset(name).unwrap();
        let t: toml::Table = toml::from_str(&cfg.to_toml()).unwrap();
        let mut flat = BTreeMap::new();
        flatten("", &t, &mut flat);
        for (k, v) in flat {
            if k == "preset" || k.starts_with("train.adam.") {
                continue;
            }
            let row = rows
                .entry(k)
                .or_insert_with(|| vec!["—".into(); PRESETS.len()]);
            row[i] = v;
        }
    }
    let mut s = String::from("| field | `tiny` | `cpu` | `paper` |\n|---|---|---|---|\n");
    for (k, v) in &rows {
        let same = v.iter().all(|x| x == &v[0]);
        let cells: Vec<String> = v
            .iter()
            .map(|x| if same { x.clone() } else { format!("**{x}**") })
            .collect();
        writeln!(s, "| `{k}` | {} |", cells.join(" | ")).unwrap();
    }
    s
}

fn fmt_group(g: &AdamGroup) -> String {
    let sc = &g.schedule;
    let sched = if sc.warmup_steps == 0 && (sc.decay_interval == 0 || sc.decay_base == 1.0) {
        "none".to_string()
    } else if sc.warmup_steps == 0 {
        format!(
            "×{:?} at step {}, then every {} up to {}",
            sc.decay_base, sc.decay_start, sc.decay_interval, sc.decay_end
        )
    } else {
        format!("{sc:?}")
    };
    format!(
        "{} | {:?} | {:?} | {:?} | {:?} | {} | {sched}",
        if g.sparse { "sparse" } else { "dense" },
        g.lr,
        g.beta1,
        g.beta2,
        g.epsilon,
        if g.sparse {
            format!("not applied (config {:?})", g.l2)
        } else {
            format!("{:?}", g.l2)
        },
    )
}

/// The Adam groups, one row per group and distinct setting with the presets that have it.
fn adam_table() -> String {
    let per: Vec<Vec<(&str, String)>> = PRESETS
        .iter()
        .map(|name| {
            let a = RunConfig::preset(name).unwrap().train.adam;
            vec![
                ("shader", fmt_group(&a.shader)),
                ("deform", fmt_group(&a.deform)),
                ("grid_h", fmt_group(&a.grid_h)),
                ("grid_d", fmt_group(&a.grid_d)),
                ("appearance", fmt_group(&a.appearance)),
                ("vertex", fmt_group(&a.vertex)),
            ]
        })
        .collect();
    // One row per group and distinct setting, naming the presets that have it.
    let mut s = String::from(
        "| group | presets | role | lr | β1 | β2 | ε | L2 | schedule |\n|---|---|---|---|---|---|---|---|---|\n",
    );
    for (i, (g, _)) in per[0].iter().enumerate() {
        let mut seen: Vec<(&String, Vec<&str>)> = Vec::new();
        for (p, name) in per.iter().zip(PRESETS) {
            let row = &p[i].1;
            match seen.iter_mut().find(|(r, _)| *r == row) {
                Some((_, names)) => names.push(name),
                None => seen.push((row, vec![name])),
            }
        }
        for (row, names) in seen {
            let names: Vec<String> = names.iter().map(|n| format!("`{n}`")).collect();
            writeln!(s, "| `{g}` | {} | {row} |", names.join(", ")).unwrap();
        }
    }
    s
}

fn grid_rows(s: &mut String, label: &str, g: &HashGrid) {
    for l in 0..g.cfg.levels as usize {
        writeln!(
            s,
            "| {label} | {l} | {:?} | {} | {} | {} | {} |",
            g.scales[l],
            g.resolutions[l],
            g.offsets[l],
            g.level_entries(l),
            if g.dense[l] { "dense" } else { "hashed" }
        )
        .unwrap();
    }
    writeln!(
        s,
        "| {label} | total | | | {} | | {} parameters |",
        g.n_entries(),
        g.n_params()
    )
    .unwrap();
}

/// Per-level geometry of every preset's grids, before level dropping (§8).
fn levels_table() -> String {
    let mut s = String::from(
        "| grid | l | `scale_l` (f32) | `res_l` | offset | entries | indexing |\n|---|---|---|---|---|---|---|\n",
    );
    // Grids with the same geometry as an earlier one (they may differ in interpolation) are
    // listed once.
    let mut seen: Vec<(String, HashGrid)> = Vec::new();
    for name in PRESETS {
        let m = RunConfig::preset(name).unwrap().model;
        let mut grids = vec![(format!("`{name}` H"), m.grid_h.clone())];
        if m.deform.enabled {
            grids.push((format!("`{name}` D"), m.deform.grid.clone()));
        }
        for (label, g) in grids {
            let grid = HashGrid::new(&g);
            let same = |x: &HashGrid| {
                (
                    &x.scales,
                    &x.resolutions,
                    &x.offsets,
                    &x.dense,
                    x.cfg.features,
                ) == (
                    &grid.scales,
                    &grid.resolutions,
                    &grid.offsets,
                    &grid.dense,
                    g.features,
                )
            };
            if let Some((first, _)) = seen.iter().find(|(_, x)| same(x)) {
                writeln!(s, "| {label} | levels as {first} | | | | | |").unwrap();
                continue;
            }
            grid_rows(&mut s, &label, &grid);
            seen.push((label, grid));
        }
    }
    s
}

/// The text between `<!-- begin generated: NAME -->` and `<!-- end generated: NAME -->`.
fn generated_span(spec: &str, name: &str) -> (usize, usize) {
    let b = format!("<!-- begin generated: {name} -->\n");
    let e = format!("<!-- end generated: {name} -->");
    let start = spec
        .find(&b)
        .unwrap_or_else(|| panic!("docs/spec.md has no marker {b:?}"))
        + b.len();
    let end = start
        + spec[start..]
            .find(&e)
            .unwrap_or_else(|| panic!("docs/spec.md has no marker {e:?}"));
    (start, end)
}

#[test]
fn generated_tables_match_the_code() {
    let path = root().join(SPEC);
    let mut spec = std::fs::read_to_string(&path).unwrap();
    let bless = std::env::var_os("XSCALE_BLESS").is_some();
    let mut stale = Vec::new();
    for (name, want) in [
        ("presets", presets_table()),
        ("adam", adam_table()),
        ("levels", levels_table()),
    ] {
        let (a, b) = generated_span(&spec, name);
        if spec[a..b] != want {
            if bless {
                spec.replace_range(a..b, &want);
            } else {
                stale.push(format!("--- table `{name}` should be:\n{want}"));
            }
        }
    }
    if bless {
        std::fs::write(&path, &spec).unwrap();
    }
    assert!(
        stale.is_empty(),
        "docs/spec.md's generated tables disagree with the code (rerun with XSCALE_BLESS=1 to rewrite them):\n{}",
        stale.join("\n")
    );
}

// ------------------------------------------------------------------------------------------------
// Configuration keys named in the user docs

/// The user docs: `README.md` and every `docs/*.md`.
fn user_docs() -> Vec<PathBuf> {
    let mut files = vec![root().join("README.md")];
    let mut docs: Vec<PathBuf> = std::fs::read_dir(root().join("docs"))
        .unwrap()
        .flatten()
        .map(|e| e.path())
        .filter(|p| p.extension().is_some_and(|e| e == "md"))
        .collect();
    docs.sort();
    files.extend(docs);
    files
}

/// The inline code spans of a Markdown text (fenced blocks skipped), with their line numbers.
fn code_spans(text: &str) -> Vec<(usize, String)> {
    let mut out = Vec::new();
    let mut in_fence = false;
    let mut para = String::new();
    let mut para_line = 1;
    let flush = |para: &mut String, para_line: usize, out: &mut Vec<(usize, String)>| {
        let mut rest = para.as_str();
        let mut consumed = 0;
        while let Some(a) = rest.find('`') {
            let after = &rest[a + 1..];
            let Some(b) = after.find('`') else { break };
            let span = &after[..b];
            let line = para_line + para[..consumed + a].matches('\n').count();
            out.push((line, span.replace('\n', " ")));
            consumed += a + 1 + b + 1;
            rest = &after[b + 1..];
        }
        para.clear();
    };
    for (i, l) in text.lines().enumerate() {
        if l.trim_start().starts_with("```") {
            flush(&mut para, para_line, &mut out);
            in_fence = !in_fence;
            continue;
        }
        if in_fence {
            continue;
        }
        if l.trim().is_empty() {
            flush(&mut para, para_line, &mut out);
            continue;
        }
        if para.is_empty() {
            para_line = i + 1;
        }
        para.push_str(l);
        para.push('\n');
    }
    flush(&mut para, para_line, &mut out);
    out
}

/// The fenced ```toml blocks of a Markdown text, with the line of their first line.
fn toml_blocks(text: &str) -> Vec<(usize, String)> {
    let mut out = Vec::new();
    let mut cur: Option<(usize, String)> = None;
    for (i, l) in text.lines().enumerate() {
        let t = l.trim_start();
        match &mut cur {
            None if t.starts_with("```toml") => cur = Some((i + 2, String::new())),
            Some(_) if t.starts_with("```") => out.push(cur.take().unwrap()),
            Some((_, s)) => {
                s.push_str(l);
                s.push('\n');
            }
            None => {}
        }
    }
    out
}

const ADAM_GROUPS: [&str; 6] = [
    "shader",
    "deform",
    "grid_h",
    "grid_d",
    "appearance",
    "vertex",
];

/// A key as the docs write it (`model.grid_h.levels`, `train.adam.<group>.lr`) and the value
/// they give it, if any: the TOML override that sets it, one per `<group>` expansion.
fn overrides(key: &str, value: Option<&str>) -> Vec<(String, Option<String>)> {
    let keys: Vec<String> = if key.contains("<group>") {
        ADAM_GROUPS
            .iter()
            .map(|g| key.replace("<group>", g))
            .collect()
    } else {
        vec![key.to_string()]
    };
    keys.into_iter()
        .map(|k| {
            let (table, field) = k.rsplit_once('.').unwrap();
            // A value the docs give that is TOML is probed as written; a placeholder (`b`, `Z`)
            // probes the key alone, with a value of no type any key takes.
            let v = value
                .filter(|v| toml::from_str::<toml::Table>(&format!("x = {v}")).is_ok())
                .map(str::to_string);
            let probe = v.clone().unwrap_or_else(|| "\"\\u0001probe\"".into());
            (format!("[{table}]\n{field} = {probe}\n"), v)
        })
        .collect()
}

/// What is wrong with the override `text` (None: the key exists and, if given, takes the value).
/// Validation errors (a value the docs show being refused, a key that needs another) do not
/// count: only an unknown key, or a value of the wrong type or variant.
fn probe(text: &str, valued: bool) -> Option<String> {
    let e = match RunConfig::from_toml_str(text, "cpu", "doc") {
        Ok(_) => return None,
        Err(e) => format!("{e:#}"),
    };
    if e.contains("unknown field") {
        return Some(e);
    }
    if valued && (e.contains("unknown variant") || e.contains("invalid type")) {
        return Some(e);
    }
    None
}

/// `(line, key, value)` of every configuration key an inline code span names: `model.x.y`,
/// `train.x = v`, `[model.grid_h] levels = 1`, `[train] samples`.
fn doc_keys(text: &str) -> Vec<(usize, String, Option<String>)> {
    let mut out = Vec::new();
    for (line, span) in code_spans(text) {
        let s = span.trim();
        let (key, value) = if let Some(rest) = s.strip_prefix('[') {
            let Some((table, after)) = rest.split_once(']') else {
                continue;
            };
            if !(table.starts_with("model") || table.starts_with("train")) || table.contains('[') {
                continue;
            }
            let after = after.trim();
            let field: String = after
                .chars()
                .take_while(|c| c.is_ascii_alphanumeric() || *c == '_')
                .collect();
            if field.is_empty() {
                // A table alone (`[model.refine]`): its name is a key of the table above it.
                (table.to_string(), None)
            } else {
                let v = after[field.len()..].trim().strip_prefix('=');
                (format!("{table}.{field}"), v.map(|v| v.trim().to_string()))
            }
        } else if s.starts_with("model.") || s.starts_with("train.") {
            let key: String = s
                .chars()
                .take_while(|c| c.is_ascii_alphanumeric() || matches!(c, '_' | '.' | '<' | '>'))
                .collect();
            let v = s[key.len()..].trim().strip_prefix('=');
            // `= "stream"` / `"cache"`: the first value; `= 1 (the run has 2)`: up to the note.
            let v = v.map(|v| {
                let v = v.trim();
                v.split(" (").next().unwrap().trim().to_string()
            });
            (key.trim_end_matches('.').to_string(), v)
        } else {
            continue;
        };
        if key.contains('.') {
            out.push((line, key, value));
        }
    }
    out
}

#[test]
fn doc_scanners_find_keys_spans_and_blocks() {
    let text = "a `model.gamma = 1 (the run has 2)` b `[train] samples = \"cache\"` and\n\
                `[model.refine]`, `[train.adam.<group>]` c\n`train.steps`\n\n```toml\n[model]\n\
                gamma = 1\n```\n`model.rs` `[[rule]]`\n";
    let keys = doc_keys(text);
    let got: Vec<(usize, &str, Option<&str>)> = keys
        .iter()
        .map(|(l, k, v)| (*l, k.as_str(), v.as_deref()))
        .collect();
    assert_eq!(
        got,
        [
            (1, "model.gamma", Some("1")),
            (1, "train.samples", Some("\"cache\"")),
            (2, "model.refine", None),
            (2, "train.adam.<group>", None),
            (3, "train.steps", None),
            (9, "model.rs", None),
        ]
    );
    assert_eq!(toml_blocks(text), [(6, "[model]\ngamma = 1\n".to_string())]);
    // The probe tells a missing key and a wrong value from a refused combination.
    assert!(probe("[train]\nstepz = 3\n", false).is_some());
    assert!(probe("[model]\nlevel_weight = \"footprints\"\n", true).is_some());
    assert!(probe("[model.grid_h]\nper_level_scale = 0.5\n", true).is_none());
    assert!(probe("[model]\nrs = \"\\u0001probe\"\n", false).is_some());
}

#[test]
fn config_keys_named_in_the_docs_exist() {
    let mut bad = Vec::new();
    let mut n = 0;
    for p in user_docs() {
        let r = rel(&p);
        let text = std::fs::read_to_string(&p).unwrap();
        for (line, key, value) in doc_keys(&text) {
            // File names (`model.rs`) and code paths are not keys.
            if key.ends_with(".rs") || key.ends_with(".toml") || key.ends_with(".md") {
                continue;
            }
            for (toml, v) in overrides(&key, value.as_deref()) {
                n += 1;
                if let Some(e) = probe(&toml, v.is_some()) {
                    let shown = v.map_or(String::new(), |v| format!(" = {v}"));
                    bad.push(format!("{r}:{line}: `{key}{shown}`: {e}"));
                }
            }
        }
        for (line, block) in toml_blocks(&text) {
            let Ok(t) = toml::from_str::<toml::Table>(&block) else {
                continue;
            };
            // Run configurations only (not scene.toml, tolerance files).
            if t.is_empty()
                || !t
                    .keys()
                    .all(|k| k == "model" || k == "train" || k == "preset")
            {
                continue;
            }
            n += 1;
            if let Some(e) = probe(&block, true) {
                bad.push(format!("{r}:{line}: toml block: {e}"));
            }
        }
    }
    assert!(
        bad.is_empty(),
        "{} configuration key(s) in the docs that the code does not take:\n{}",
        bad.len(),
        bad.join("\n")
    );
    assert!(n > 80, "only {n} keys found: is the scanner broken?");
}

/// The fields a table of the run configuration takes, from serde's list in the error for an
/// unknown one (`expected one of `a`, `b``).
fn fields_of(table: &str) -> BTreeSet<String> {
    let e = RunConfig::from_toml_str(&format!("[{table}]\n__none = 1\n"), "cpu", "probe")
        .err()
        .map(|e| format!("{e:#}"))
        .unwrap();
    let list = e
        .split("expected one of ")
        .nth(1)
        .unwrap_or_else(|| panic!("no field list in {e}"));
    list.split(", ")
        .map_while(|f| f.strip_prefix('`').and_then(|f| f.split('`').next()))
        .map(String::from)
        .collect()
}

/// §4.11's table of `[model.refine]` keys (`| key | default | meaning |`) names every key of
/// `RefineConfig` once, and its defaults are the code's: the table's keys set to the table's
/// defaults give a configuration equal to the preset's.
#[test]
fn refine_table_lists_every_key_with_its_default() {
    let spec = std::fs::read_to_string(root().join(SPEC)).unwrap();
    let start = spec
        .find("| key | default | meaning |")
        .expect("docs/spec.md §4.11 has a `| key | default | meaning |` table");
    let mut keys = Vec::new();
    let mut toml = String::from("[model.refine]\n");
    for row in spec[start..].lines().skip(2) {
        if !row.starts_with('|') {
            break;
        }
        let cells: Vec<&str> = row.split('|').map(str::trim).collect();
        let names: Vec<&str> = cells[1].split(", ").map(|k| k.trim_matches('`')).collect();
        let defaults: Vec<&str> = cells[2].split(", ").map(|v| v.trim_matches('`')).collect();
        // `[32, 512]` is one default, not two.
        let defaults = if defaults.len() != names.len() && names.len() == 1 {
            vec![cells[2].trim_matches('`')]
        } else {
            defaults
        };
        assert_eq!(names.len(), defaults.len(), "§4.11 table row {row:?}");
        for (k, v) in names.iter().zip(&defaults) {
            keys.push(k.to_string());
            writeln!(toml, "{k} = {v}").unwrap();
        }
    }
    let fields = fields_of("model.refine");
    let listed: BTreeSet<String> = keys.iter().cloned().collect();
    assert_eq!(listed.len(), keys.len(), "a key listed twice: {keys:?}");
    assert_eq!(
        listed,
        fields,
        "§4.11's table and RefineConfig's fields differ: only in the table {:?}, only in the code {:?}",
        listed.difference(&fields).collect::<Vec<_>>(),
        fields.difference(&listed).collect::<Vec<_>>()
    );
    let cfg = RunConfig::from_toml_str(&toml, "cpu", "§4.11 table")
        .unwrap_or_else(|e| panic!("§4.11's defaults do not parse: {e:#}\n{toml}"));
    assert_eq!(
        cfg.model.refine,
        RunConfig::preset("cpu").unwrap().model.refine,
        "§4.11's defaults are not the code's:\n{toml}"
    );
}
