//! Tensor-by-tensor comparison of two safetensors files (SPEC §6, `xscale compare`).
//!
//! This file owns the error measures, the tolerance rules and the report. Definitions:
//!
//! - **abs error** of an element: `|a - b|`, computed in f64 (exact inputs: F32 values widen exactly).
//! - **rel error**: `|a - b| / max(|a|, |b|, floor)`, with `floor` the smallest positive normal number
//!   of the comparison dtype (`f32::MIN_POSITIVE` when either side is F32, else `f64::MIN_POSITIVE`).
//!   Symmetric in a and b, 0 for equal values (0 vs 0 included), at most 2 unless both values are
//!   below `floor`.
//! - **ULP distance**: the number of representable values between a and b in the comparison dtype,
//!   counted on the sign-magnitude → monotone integer map of the bit patterns, so `-0` and `+0` are 0
//!   apart and the distance across zero is the sum of both sides' distances to zero (the smallest
//!   negative and smallest positive subnormal are 2 apart). Comparison dtype: F32 if either side is
//!   F32 (an F64 value is first rounded to the nearest f32, so an F64 oracle against an F32 backend
//!   measures how many f32 ulps the backend is from the correctly rounded result), F64 if both are
//!   F64. For two integer tensors the ULP distance is the integer difference; an integer compared
//!   with a float takes the float's rules.
//! - **NaN / Inf**: as error measures, NaN vs NaN and equal infinities give 0, and NaN vs anything
//!   else, or an infinity vs anything different, is infinitely wrong (abs = rel = ∞, ULP = u64::MAX;
//!   in JSON a NaN, +∞ or −∞ value or error is written as the string `"NaN"`, `"inf"` or `"-inf"`). So an infinity passes only against the same infinity, in the
//!   same place. **A NaN in either file fails its tensor under every rule** (and even without a
//!   rule), unless the rule or the whole file says `allow_nan = true` (`--allow-nan`): an all-NaN
//!   gradient must never pass.
//!
//! Tolerances (TOML, see [`Tolerances`]): rules matched by tensor-name glob (`*` any run of
//! characters, dots included; `?` one character); the first matching rule in file order wins, then
//! `[default]`. **An element is within tolerance if it meets at least one of the limits the rule
//! gives** (`abs <= max_abs` or `rel <= max_rel` or `ulp <= max_ulp` or
//! `abs <= max_rel_peak * peak`), like `numpy.isclose`'s atol-or-rtol: a pure relative limit is
//! useless for values crossing zero, a pure absolute limit for large values. A tensor fails if any
//! element meets none of them.
//! - **peak** of a tensor pair: the largest finite `|value|` in either tensor. `max_rel_peak` is an
//!   absolute limit that scales with the tensor (`abs / peak`, the ∞-norm-relative error): the right
//!   floor for elements near zero (sums that cancel, gradients of entries few samples touch), where
//!   the element-wise rel is meaningless, without a fixed `max_abs` that fits one batch size only.
//!
//! Exit codes ([`Report::exit_code`]): 0 = everything within limits; 1 = a limit exceeded (the
//! report names the tensor and the worst element); 2 = bad input: a shape mismatch, a tensor a
//! `required` rule asks for missing from a file, and (with `strict`) a tensor present in only one
//! file. Unreadable files and bad tolerance files are errors of [`compare_files`] (exit 2 from the
//! CLI). `strict = true` also makes a tensor with no matching rule (and no default) require exact
//! equality (ULP distance 0); without `strict` such a tensor is reported as "norule" and never fails.
//!
//! **Kinks** (`model/kink.rs`, `docs/oracle.md` §7): tensors named `kink.*` are not data but what
//! an f64 dump says about its own kinks; they are never compared, never "only in one file". A
//! `kink.slack.<name>` tensor of file A — the reference: the kink tensors of file B are ignored
//! (and the report says so), since a file must not be able to excuse its own differences —
//! widens the limits of tensor `<name>` element by element (a slack that is not a finite number
//! ≥ 0, or of the wrong size, is bad input): an element outside its rule still passes if `abs − slack`
//! is within it (and neither value is NaN) — the gradient a correct backend may have because it evaluated a
//! ReLU unit or an L1 residual of a *kink pixel* on the other side of its kink. Such elements are
//! counted apart (`n_kink`), the report shows the number of kink pixels, and `kink_slack = false`
//! in the tolerance file (`--no-kink-slack`) turns the widening off.

use super::tensors::{DType, Tensor, TensorFile};
use anyhow::{bail, Context, Result};
use serde::{Deserialize, Serialize};
use std::path::Path;

/// One tolerance rule.
#[derive(Clone, Debug, Default, Deserialize, Serialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct Rule {
    /// Tensor-name glob (`*`, `?`); ignored for the `[default]` rule.
    #[serde(default)]
    pub pattern: String,
    pub max_abs: Option<f64>,
    pub max_rel: Option<f64>,
    pub max_ulp: Option<u64>,
    /// Limit on `abs / peak` (peak = largest finite |value| in either tensor; see module doc).
    pub max_rel_peak: Option<f64>,
    /// Why this tolerance is what it is (shown in the report).
    pub reason: Option<String>,
    /// The matched tensors must exist in both files, and at least one must match (else exit 2).
    #[serde(default)]
    pub required: bool,
    /// Matched tensors are listed but not compared.
    #[serde(default)]
    pub ignore: bool,
    /// NaN is accepted where both files have NaN (without it, any NaN fails the tensor).
    #[serde(default)]
    pub allow_nan: bool,
}

impl Rule {
    fn has_limits(&self) -> bool {
        self.max_abs.is_some()
            || self.max_rel.is_some()
            || self.max_ulp.is_some()
            || self.max_rel_peak.is_some()
    }

    /// Every float limit given is a number ≥ 0 ([`check_limit`]); `what` names the rule.
    fn check_limits(&self, what: &str) -> Result<()> {
        for (key, v) in [
            ("max_abs", self.max_abs),
            ("max_rel", self.max_rel),
            ("max_rel_peak", self.max_rel_peak),
        ] {
            if let Some(x) = v {
                check_limit(x).map_err(|e| anyhow::anyhow!("{what}: {key} = {e}"))?;
            }
        }
        Ok(())
    }

    /// `abs 1e-6 | rel 1e-5 | ulp 4`
    pub fn describe_limits(&self) -> String {
        let mut parts = Vec::new();
        if let Some(x) = self.max_abs {
            parts.push(format!("abs {x:e}"));
        }
        if let Some(x) = self.max_rel {
            parts.push(format!("rel {x:e}"));
        }
        if let Some(x) = self.max_ulp {
            parts.push(format!("ulp {x}"));
        }
        if let Some(x) = self.max_rel_peak {
            parts.push(format!("rel-peak {x:e}"));
        }
        if parts.is_empty() {
            "exact".to_string()
        } else {
            parts.join(" | ")
        }
    }

    /// Whether one element's errors are within this rule (any given limit suffices; a rule
    /// without limits demands exact equality of the values, `abs == 0`). Without the tensor's peak a `max_rel_peak` limit
    /// is never met: use [`Rule::accepts_with_peak`].
    pub fn accepts(&self, e: &ElementError) -> bool {
        self.accepts_with_peak(e, f64::NAN)
    }

    /// As [`Rule::accepts`], with the tensor pair's peak (largest finite |value| in either
    /// tensor) for `max_rel_peak`.
    pub fn accepts_with_peak(&self, e: &ElementError, peak: f64) -> bool {
        if !self.has_limits() {
            // Exact: equal values, as the wider dtype (an F64 value against an F32 one must be
            // that f32 value exactly: one rounded to f32 is 0 f32 ulps away, but not equal).
            return e.abs == 0.0;
        }
        self.max_abs.is_some_and(|l| e.abs <= l)
            || self.max_rel.is_some_and(|l| e.rel <= l)
            || self.max_ulp.is_some_and(|l| e.ulp <= l)
            || self.max_rel_peak.is_some_and(|l| e.abs <= l * peak)
    }
}

/// A float limit (`max_abs`, `max_rel`, `max_rel_peak`, in a tolerance file or on the command
/// line): a number ≥ 0 (`inf` is no limit); NaN or a negative number is an error
/// (`-1 must be a number >= 0`), since no element could meet it.
pub fn check_limit(x: f64) -> std::result::Result<f64, String> {
    if x.is_nan() || x < 0.0 {
        Err(format!("{x} must be a number >= 0"))
    } else {
        Ok(x)
    }
}

/// `xscale compare --max-abs / --max-rel / --max-rel-peak`: a number, then [`check_limit`] (a
/// bad value is a usage error, worded as the tolerance file's).
pub fn parse_limit(s: &str) -> std::result::Result<f64, String> {
    let x: f64 = s
        .trim()
        .parse()
        .map_err(|e| format!("expected a number >= 0 ({e})"))?;
    check_limit(x)
}

/// A tolerance file.
///
/// ```toml
/// strict = false          # optional
/// [default]               # optional: applies to tensors no rule matches
/// max_ulp = 0
/// [[rule]]
/// pattern = "fwd.grid_h"  # glob: * and ?
/// max_abs = 1e-6
/// max_rel = 1e-5
/// max_ulp = 4
/// max_rel_peak = 1e-6    # abs <= 1e-6 * largest |value| of the tensor
/// reason = "fp32 fma chain vs reference"
/// required = true         # optional
/// [[rule]]
/// pattern = "adam.*"
/// ignore = true
/// ```
#[derive(Clone, Debug, Deserialize, Serialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct Tolerances {
    #[serde(default)]
    pub strict: bool,
    /// NaN is accepted (where both files have it) under every rule.
    #[serde(default)]
    pub allow_nan: bool,
    pub default: Option<Rule>,
    #[serde(default, rename = "rule")]
    pub rules: Vec<Rule>,
    /// Use the files' `kink.slack.*` tensors (module doc). Default true.
    #[serde(default = "yes", skip_serializing_if = "is_true")]
    pub kink_slack: bool,
}

fn yes() -> bool {
    true
}

fn is_true(b: &bool) -> bool {
    *b
}

impl Default for Tolerances {
    fn default() -> Self {
        Tolerances {
            strict: false,
            allow_nan: false,
            default: None,
            rules: Vec::new(),
            kink_slack: true,
        }
    }
}

/// Names of tensors that describe a dump's kinks rather than hold data (module doc).
pub fn is_kink_meta(name: &str) -> bool {
    name.starts_with("kink.")
}

impl Tolerances {
    /// Parse TOML text; `label` names the source in errors.
    pub fn from_toml(text: &str, label: &str) -> Result<Tolerances> {
        let t: Tolerances =
            toml::from_str(text).with_context(|| format!("{label}: bad tolerance file"))?;
        for (i, r) in t.rules.iter().enumerate() {
            if r.pattern.is_empty() {
                bail!("{label}: rule {} has no pattern", i + 1);
            }
        }
        for r in &t.rules {
            r.check_limits(&format!("{label}: rule \"{}\"", r.pattern))?;
        }
        if let Some(d) = &t.default {
            d.check_limits(&format!("{label}: [default]"))?;
        }
        Ok(t)
    }

    /// Read a TOML tolerance file.
    pub fn read(path: impl AsRef<Path>) -> Result<Tolerances> {
        let path = path.as_ref();
        let text = std::fs::read_to_string(path)
            .with_context(|| format!("{}: cannot read tolerance file", path.display()))?;
        Self::from_toml(&text, &path.display().to_string())
    }

    /// A built-in tolerance set by name ([`BUILTIN_TOLERANCES`]), `None` for another name.
    pub fn builtin(name: &str) -> Option<Tolerances> {
        builtin_tolerance_text(name).map(|text| {
            Self::from_toml(text, &format!("built-in tolerance set {name:?}"))
                .expect("the built-in tolerance sets parse (tested)")
        })
    }

    /// `--tolerances SPEC`: a built-in set's name (`f32`, `f64`, `fp16`, `grid-exact`, `exact`),
    /// else the path of a TOML file. A file literally named like a set is given as `./f32`.
    pub fn resolve(spec: &str) -> Result<Tolerances> {
        if let Some(t) = Self::builtin(spec) {
            return Ok(t);
        }
        let path = Path::new(spec);
        if !path.exists() && !spec.contains(['/', '\\']) && !spec.ends_with(".toml") {
            bail!(
                "--tolerances {spec:?}: no such file, and not a built-in set (built-in: {})",
                builtin_tolerance_names().join(", ")
            );
        }
        Self::read(path)
    }
}

/// The tolerance sets every build carries (`xscale compare --tolerances f32`, the Python
/// package's `tolerances="f32"`): name and TOML text. The files are `fixtures/golden/
/// tolerances-<name>.toml`, where each rule's reason says why its limits are what they are
/// (docs/oracle.md §7).
pub const BUILTIN_TOLERANCES: &[(&str, &str)] = &[
    (
        "f32",
        include_str!("../../fixtures/golden/tolerances-f32.toml"),
    ),
    (
        "f64",
        include_str!("../../fixtures/golden/tolerances-f64.toml"),
    ),
    (
        "fp16",
        include_str!("../../fixtures/golden/tolerances-fp16.toml"),
    ),
    (
        "grid-exact",
        include_str!("../../fixtures/golden/tolerances-grid-exact.toml"),
    ),
    (
        "exact",
        include_str!("../../fixtures/golden/tolerances-exact.toml"),
    ),
];

/// The TOML text of a built-in tolerance set.
pub fn builtin_tolerance_text(name: &str) -> Option<&'static str> {
    BUILTIN_TOLERANCES
        .iter()
        .find(|(n, _)| *n == name)
        .map(|(_, t)| *t)
}

/// The names of the built-in tolerance sets, in [`BUILTIN_TOLERANCES`] order.
pub fn builtin_tolerance_names() -> Vec<&'static str> {
    BUILTIN_TOLERANCES.iter().map(|(n, _)| *n).collect()
}

impl Tolerances {
    /// The rule for a tensor: the first matching rule, else the default.
    pub fn rule_for(&self, name: &str) -> Option<&Rule> {
        self.rules
            .iter()
            .find(|r| glob_match(&r.pattern, name))
            .or(self.default.as_ref())
    }

    /// How a report names rule `r` of this file: its pattern, or `[default]`.
    fn rule_name(&self, r: &Rule) -> String {
        if self.default.as_ref().is_some_and(|d| std::ptr::eq(d, r)) {
            "[default]".to_string()
        } else {
            r.pattern.clone()
        }
    }
}

/// Glob match: `*` matches any run of characters (dots included), `?` exactly one, everything
/// else itself.
pub fn glob_match(pattern: &str, name: &str) -> bool {
    let p: Vec<char> = pattern.chars().collect();
    let s: Vec<char> = name.chars().collect();
    // Iterative matcher with backtracking to the last '*'.
    let (mut pi, mut si) = (0usize, 0usize);
    let mut star: Option<(usize, usize)> = None;
    while si < s.len() {
        if pi < p.len() && (p[pi] == '?' || p[pi] == s[si]) {
            pi += 1;
            si += 1;
        } else if pi < p.len() && p[pi] == '*' {
            star = Some((pi, si));
            pi += 1;
        } else if let Some((sp, ss)) = star {
            pi = sp + 1;
            si = ss + 1;
            star = Some((sp, ss + 1));
        } else {
            return false;
        }
    }
    while pi < p.len() && p[pi] == '*' {
        pi += 1;
    }
    pi == p.len()
}

/// ULP distance between two f32 values (NaN handling is the caller's; see module doc).
pub fn ulp_distance_f32(a: f32, b: f32) -> u64 {
    fn key(x: f32) -> i64 {
        let bits = x.to_bits();
        let mag = (bits & 0x7fff_ffff) as i64;
        if bits >> 31 == 1 {
            -mag
        } else {
            mag
        }
    }
    (key(a) - key(b)).unsigned_abs()
}

/// ULP distance between two f64 values (NaN handling is the caller's; see module doc).
pub fn ulp_distance_f64(a: f64, b: f64) -> u64 {
    fn key(x: f64) -> i128 {
        let bits = x.to_bits();
        let mag = (bits & 0x7fff_ffff_ffff_ffff) as i128;
        if bits >> 63 == 1 {
            -mag
        } else {
            mag
        }
    }
    let d = (key(a) - key(b)).unsigned_abs();
    d.min(u64::MAX as u128) as u64
}

/// How two elements are compared (see module doc).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
pub enum CompareIn {
    F32,
    F64,
    Int,
}

impl CompareIn {
    fn for_dtypes(a: DType, b: DType) -> CompareIn {
        if a == DType::F32 || b == DType::F32 {
            CompareIn::F32
        } else if a == DType::F64 || b == DType::F64 {
            CompareIn::F64
        } else {
            CompareIn::Int
        }
    }
}

/// The errors of one element pair.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ElementError {
    pub abs: f64,
    pub rel: f64,
    pub ulp: u64,
}

/// Errors of one element pair given as f64 (exact widenings of the stored values).
pub fn element_error(a: f64, b: f64, mode: CompareIn) -> ElementError {
    const EQUAL: ElementError = ElementError {
        abs: 0.0,
        rel: 0.0,
        ulp: 0,
    };
    const INFINITE: ElementError = ElementError {
        abs: f64::INFINITY,
        rel: f64::INFINITY,
        ulp: u64::MAX,
    };
    if a.is_nan() || b.is_nan() {
        return if a.is_nan() && b.is_nan() {
            EQUAL
        } else {
            INFINITE
        };
    }
    if a.is_infinite() || b.is_infinite() {
        return if a == b { EQUAL } else { INFINITE };
    }
    let abs = (a - b).abs();
    let floor = match mode {
        CompareIn::F32 => f32::MIN_POSITIVE as f64,
        _ => f64::MIN_POSITIVE,
    };
    let rel = abs / a.abs().max(b.abs()).max(floor);
    let ulp = match mode {
        CompareIn::F32 => {
            let (fa, fb) = (a as f32, b as f32);
            if fa.is_infinite() || fb.is_infinite() {
                // An F64 value beyond f32 range: as far as it gets.
                if fa == fb {
                    0
                } else {
                    u64::MAX
                }
            } else {
                ulp_distance_f32(fa, fb)
            }
        }
        CompareIn::F64 => ulp_distance_f64(a, b),
        CompareIn::Int => abs as u64,
    };
    ElementError { abs, rel, ulp }
}

/// Read element `i` of a tensor as f64 (every supported dtype widens exactly).
#[inline]
fn elem(t: &Tensor, i: usize) -> f64 {
    let d = &t.data;
    match t.dtype {
        DType::F64 => f64::from_le_bytes(d[i * 8..i * 8 + 8].try_into().unwrap()),
        DType::F32 => f32::from_le_bytes(d[i * 4..i * 4 + 4].try_into().unwrap()) as f64,
        DType::U32 => u32::from_le_bytes(d[i * 4..i * 4 + 4].try_into().unwrap()) as f64,
        DType::I32 => i32::from_le_bytes(d[i * 4..i * 4 + 4].try_into().unwrap()) as f64,
        DType::U8 => d[i] as f64,
    }
}

/// Row-major flat index → multi-dimensional index.
pub fn unravel(mut flat: usize, shape: &[usize]) -> Vec<usize> {
    let mut idx = vec![0; shape.len()];
    for (k, &d) in shape.iter().enumerate().rev() {
        if d > 0 {
            idx[k] = flat % d;
            flat /= d;
        }
    }
    idx
}

/// One element singled out in a report.
#[derive(Clone, Debug, Serialize, PartialEq)]
pub struct Element {
    pub index: Vec<usize>,
    #[serde(serialize_with = "json_f64")]
    pub a: f64,
    #[serde(serialize_with = "json_f64")]
    pub b: f64,
    #[serde(serialize_with = "json_f64")]
    pub abs: f64,
    #[serde(serialize_with = "json_f64")]
    pub rel: f64,
    pub ulp: u64,
}

/// Error statistics of one tensor pair.
#[derive(Clone, Debug, Serialize, PartialEq)]
pub struct Stats {
    pub numel: usize,
    pub compare_in: CompareIn,
    #[serde(serialize_with = "json_f64")]
    pub max_abs: f64,
    #[serde(serialize_with = "json_f64")]
    pub max_rel: f64,
    pub max_ulp: u64,
    /// Largest finite |value| in either tensor.
    #[serde(serialize_with = "json_f64")]
    pub peak: f64,
    /// `max_abs / peak` (0 when equal; ∞ if peak is 0 and the tensors differ).
    #[serde(serialize_with = "json_f64")]
    pub max_rel_peak: f64,
    /// The element with the largest abs error (first one on ties).
    pub worst_abs: Option<Element>,
    /// The element with the largest ULP distance (first one on ties).
    pub worst_ulp: Option<Element>,
    /// Elements outside the rule's tolerance (0 without a rule).
    pub n_fail: usize,
    /// The out-of-tolerance element with the largest abs error (largest ULP distance on ties).
    pub worst_fail: Option<Element>,
    /// Elements that are NaN in either file.
    pub n_nan: usize,
    /// Elements outside the rule's limits that passed by their kink slack (module doc).
    pub n_kink: usize,
}

/// Outcome for one tensor name.
#[derive(Clone, Copy, Debug, Serialize, PartialEq, Eq)]
#[serde(rename_all = "snake_case")]
pub enum Status {
    /// Within the rule's limits.
    Pass,
    /// A limit exceeded.
    Fail,
    /// Compared, but no rule applies (not strict): reported only.
    NoRule,
    /// A rule says `ignore`.
    Ignored,
    /// Shapes differ (bad input).
    ShapeMismatch,
}

/// Report for one tensor present in both files.
#[derive(Clone, Debug, Serialize, PartialEq)]
pub struct TensorReport {
    pub name: String,
    pub dtype_a: String,
    pub dtype_b: String,
    pub shape_a: Vec<usize>,
    pub shape_b: Vec<usize>,
    pub status: Status,
    /// The matched rule's pattern (`"[default]"` for the default rule).
    pub rule: Option<String>,
    pub limits: Option<String>,
    pub reason: Option<String>,
    pub stats: Option<Stats>,
}

/// The whole comparison.
#[derive(Clone, Debug, Serialize, PartialEq)]
pub struct Report {
    pub file_a: String,
    pub file_b: String,
    pub tensors: Vec<TensorReport>,
    pub only_in_a: Vec<String>,
    pub only_in_b: Vec<String>,
    /// Problems with `required` rules (a matched tensor missing from a file, or nothing matched).
    pub missing_required: Vec<String>,
    /// Header metadata keys whose values differ or that only one file has (informational:
    /// never affects the exit code).
    pub metadata_differs: Vec<String>,
    pub strict: bool,
    /// Kink pixels the files report (`kink.pixels`; the larger count if both do), with the
    /// threshold that made them; `None` if neither file has kink tensors.
    pub kink_pixels: Option<usize>,
    #[serde(serialize_with = "json_opt_f64")]
    pub kink_threshold: Option<f64>,
    /// Whether `kink.slack.*` widened the limits (module doc).
    pub kink_slack: bool,
    /// File B has `kink.*` tensors; they are not used (only the reference, file A, may excuse a
    /// difference).
    pub kink_in_b_ignored: bool,
}

impl Report {
    /// 0 = all within limits, 1 = a limit exceeded, 2 = bad input (see module doc).
    pub fn exit_code(&self) -> u8 {
        let bad_input = !self.missing_required.is_empty()
            || self
                .tensors
                .iter()
                .any(|t| t.status == Status::ShapeMismatch)
            || (self.strict && (!self.only_in_a.is_empty() || !self.only_in_b.is_empty()));
        if bad_input {
            2
        } else if self.tensors.iter().any(|t| t.status == Status::Fail) {
            1
        } else {
            0
        }
    }

    /// Aligned human-readable table plus failure details and a summary line.
    pub fn to_table(&self) -> String {
        let mut rows: Vec<[String; 9]> = vec![[
            "status".into(),
            "tensor".into(),
            "dtype".into(),
            "shape".into(),
            "max_abs".into(),
            "max_rel".into(),
            "max_ulp".into(),
            "worst@ (abs)".into(),
            "limits (rule)".into(),
        ]];
        let shape_str = |s: &[usize]| {
            format!(
                "[{}]",
                s.iter()
                    .map(|d| d.to_string())
                    .collect::<Vec<_>>()
                    .join(",")
            )
        };
        for t in &self.tensors {
            let status = match t.status {
                Status::Pass => "ok",
                Status::Fail => "FAIL",
                Status::NoRule => "norule",
                Status::Ignored => "ignored",
                Status::ShapeMismatch => "SHAPE",
            };
            let dtype = if t.dtype_a == t.dtype_b {
                t.dtype_a.clone()
            } else {
                format!("{}/{}", t.dtype_a, t.dtype_b)
            };
            let shape = if t.shape_a == t.shape_b {
                shape_str(&t.shape_a)
            } else {
                format!("{} vs {}", shape_str(&t.shape_a), shape_str(&t.shape_b))
            };
            let (ma, mr, mu, worst) = match &t.stats {
                Some(s) if s.numel > 0 => (
                    fmt_err(s.max_abs),
                    fmt_err(s.max_rel),
                    fmt_ulp(s.max_ulp),
                    match &s.worst_abs {
                        Some(e) if s.max_abs > 0.0 => shape_str(&e.index),
                        _ => "-".into(),
                    },
                ),
                Some(_) => ("-".into(), "-".into(), "-".into(), "(empty)".into()),
                None => ("".into(), "".into(), "".into(), "".into()),
            };
            let limits = match (&t.limits, &t.rule) {
                (Some(l), Some(r)) => format!("{l} ({r})"),
                (None, Some(r)) => format!("({r})"),
                _ => String::new(),
            };
            rows.push([
                status.into(),
                t.name.clone(),
                dtype,
                shape,
                ma,
                mr,
                mu,
                worst,
                limits,
            ]);
        }
        let mut widths = [0usize; 9];
        for r in &rows {
            for (w, c) in widths.iter_mut().zip(r.iter()) {
                *w = (*w).max(c.chars().count());
            }
        }
        let mut out = format!("A: {}\nB: {}\n", self.file_a, self.file_b);
        for r in &rows {
            let mut line = String::new();
            for (k, (c, w)) in r.iter().zip(widths.iter()).enumerate() {
                let pad = w - c.chars().count();
                // Numbers right-aligned, text left-aligned.
                if (4..=6).contains(&k) {
                    line.push_str(&" ".repeat(pad));
                    line.push_str(c);
                } else {
                    line.push_str(c);
                    line.push_str(&" ".repeat(pad));
                }
                line.push_str("  ");
            }
            out.push_str(line.trim_end());
            out.push('\n');
        }
        for t in &self.tensors {
            match t.status {
                Status::Fail => {
                    let s = t.stats.as_ref().unwrap();
                    let e = s.worst_fail.as_ref().unwrap();
                    out.push_str(&format!(
                        "FAIL {}: {} of {} elements out of tolerance; worst at {}: a = {}, b = {}, abs = {}, rel = {}, ulp = {} (limits {}{})\n",
                        t.name,
                        s.n_fail,
                        s.numel,
                        shape_str(&e.index),
                        fmt_value(e.a),
                        fmt_value(e.b),
                        fmt_err(e.abs),
                        fmt_err(e.rel),
                        fmt_ulp(e.ulp),
                        t.limits.as_deref().unwrap_or("exact"),
                        t.reason.as_deref().map(|r| format!("; {r}")).unwrap_or_default()
                    ));
                }
                Status::ShapeMismatch => out.push_str(&format!(
                    "SHAPE {}: {} in A, {} in B\n",
                    t.name,
                    shape_str(&t.shape_a),
                    shape_str(&t.shape_b)
                )),
                _ => {}
            }
        }
        if !self.only_in_a.is_empty() {
            out.push_str(&format!("only in A: {}\n", self.only_in_a.join(", ")));
        }
        if !self.only_in_b.is_empty() {
            out.push_str(&format!("only in B: {}\n", self.only_in_b.join(", ")));
        }
        if !self.metadata_differs.is_empty() {
            out.push_str(&format!(
                "metadata differs (informational): {}\n",
                self.metadata_differs.join(", ")
            ));
        }
        if let Some(k) = self.kink_pixels {
            let (n, t) = self
                .tensors
                .iter()
                .filter_map(|t| t.stats.as_ref().map(|s| s.n_kink))
                .filter(|&n| n > 0)
                .fold((0, 0), |(n, t), k| (n + k, t + 1));
            out.push_str(&format!(
                "kink pixels: {k} (relative margin <= {}); {}\n",
                self.kink_threshold.map_or("?".into(), |t| format!("{t:e}")),
                if self.kink_slack {
                    format!("{n} elements in {t} tensors passed only by their kink slack")
                } else {
                    "kink slack not used (--no-kink-slack)".into()
                }
            ));
        }
        if self.kink_in_b_ignored {
            out.push_str(
                "kink tensors in B ignored: only the reference (file A) may excuse a difference\n",
            );
        }
        for m in &self.missing_required {
            out.push_str(&format!("MISSING {m}\n"));
        }
        let count = |s: Status| self.tensors.iter().filter(|t| t.status == s).count();
        out.push_str(&format!(
            "{} shared tensors: {} ok, {} FAIL, {} no rule, {} ignored, {} shape mismatch; {} only in A, {} only in B{} -> exit {}\n",
            self.tensors.len(),
            count(Status::Pass),
            count(Status::Fail),
            count(Status::NoRule),
            count(Status::Ignored),
            count(Status::ShapeMismatch),
            self.only_in_a.len(),
            self.only_in_b.len(),
            if self.strict { " (strict)" } else { "" },
            self.exit_code()
        ));
        out
    }
}

fn fmt_err(x: f64) -> String {
    if x.is_infinite() {
        "inf".into()
    } else if x == 0.0 {
        "0".into()
    } else {
        format!("{x:.3e}")
    }
}

/// Shortest round-trip text: as f32 when the value is an f32, else as f64.
fn fmt_value(x: f64) -> String {
    if (x as f32) as f64 == x || x.is_nan() {
        format!("{:?}", x as f32)
    } else {
        format!("{x:?}")
    }
}

fn fmt_ulp(x: u64) -> String {
    if x == u64::MAX {
        "inf".into()
    } else {
        x.to_string()
    }
}

/// Compare two tensors of equal shape under an optional rule.
pub fn compare_tensors(a: &Tensor, b: &Tensor, rule: Option<&Rule>) -> Stats {
    compare_tensors_with_slack(a, b, rule, None)
}

/// [`compare_tensors`] where an element outside the rule also passes if its abs error is at most
/// `slack[i]` (kink slack, module doc; `slack` has the tensors' element count).
pub fn compare_tensors_with_slack(
    a: &Tensor,
    b: &Tensor,
    rule: Option<&Rule>,
    slack: Option<&[f64]>,
) -> Stats {
    let mode = CompareIn::for_dtypes(a.dtype, b.dtype);
    let n = a.numel().min(b.numel());
    let peak = (0..n)
        .flat_map(|i| [elem(a, i), elem(b, i)])
        .filter(|v| v.is_finite())
        .fold(0.0f64, |m, v| m.max(v.abs()));
    let mut st = Stats {
        numel: n,
        compare_in: mode,
        max_abs: 0.0,
        max_rel: 0.0,
        max_ulp: 0,
        peak,
        max_rel_peak: 0.0,
        worst_abs: None,
        worst_ulp: None,
        n_fail: 0,
        worst_fail: None,
        n_nan: 0,
        n_kink: 0,
    };
    let mut i_abs = None;
    let mut i_ulp = None;
    let mut i_fail: Option<(usize, ElementError)> = None;
    for i in 0..n {
        let (x, y) = (elem(a, i), elem(b, i));
        let e = element_error(x, y, mode);
        let nan = x.is_nan() || y.is_nan();
        st.n_nan += nan as usize;
        if i_abs.is_none() || e.abs > st.max_abs {
            st.max_abs = e.abs;
            i_abs = Some(i);
        }
        if e.rel > st.max_rel {
            st.max_rel = e.rel;
        }
        if i_ulp.is_none() || e.ulp > st.max_ulp {
            st.max_ulp = e.ulp;
            i_ulp = Some(i);
        }
        if let Some(r) = rule {
            let within = r.accepts_with_peak(&e, peak);
            // The rule's limits on top of the slack: the backend's own rounding still counts.
            let by_slack = !within
                && !nan
                && slack.is_some_and(|s| {
                    e.abs <= s[i]
                        || r.accepts_with_peak(
                            &ElementError {
                                abs: e.abs - s[i],
                                ..e
                            },
                            peak,
                        )
                });
            if !within && by_slack {
                st.n_kink += 1;
            } else if !within || (nan && !r.allow_nan) {
                st.n_fail += 1;
                let worse = match &i_fail {
                    None => true,
                    Some((_, w)) => e.abs > w.abs || (e.abs == w.abs && e.ulp > w.ulp),
                };
                if worse {
                    i_fail = Some((i, e));
                }
            }
        }
    }
    let element = |i: usize| {
        let (x, y) = (elem(a, i), elem(b, i));
        let e = element_error(x, y, mode);
        Element {
            index: unravel(i, &a.shape),
            a: x,
            b: y,
            abs: e.abs,
            rel: e.rel,
            ulp: e.ulp,
        }
    };
    st.max_rel_peak = if st.max_abs == 0.0 {
        0.0
    } else {
        st.max_abs / peak
    };
    st.worst_abs = i_abs.map(element);
    st.worst_ulp = i_ulp.map(element);
    st.worst_fail = i_fail.map(|(i, _)| element(i));
    st
}

/// Compare two loaded files under a tolerance set.
pub fn compare(a: &TensorFile, b: &TensorFile, tol: &Tolerances) -> Report {
    let label = |f: &TensorFile| {
        f.source
            .as_ref()
            .map(|p| p.display().to_string())
            .unwrap_or_else(|| "<in memory>".into())
    };
    let mut report = Report {
        file_a: label(a),
        file_b: label(b),
        tensors: Vec::new(),
        only_in_a: a
            .tensors
            .keys()
            .filter(|k| !b.tensors.contains_key(*k) && !is_kink_meta(k))
            .cloned()
            .collect(),
        only_in_b: b
            .tensors
            .keys()
            .filter(|k| !a.tensors.contains_key(*k) && !is_kink_meta(k))
            .cloned()
            .collect(),
        missing_required: Vec::new(),
        metadata_differs: a
            .metadata
            .keys()
            .chain(b.metadata.keys().filter(|k| !a.metadata.contains_key(*k)))
            .filter(|k| a.metadata.get(*k) != b.metadata.get(*k))
            .cloned()
            .collect(),
        strict: tol.strict,
        kink_pixels: a.tensors.get("kink.pixels").map(|t| t.numel()),
        kink_threshold: a
            .tensors
            .get("kink.threshold")
            .and_then(|t| t.to_f64().ok()?.first().copied()),
        kink_slack: tol.kink_slack,
        kink_in_b_ignored: b.tensors.keys().any(|k| is_kink_meta(k)),
    };
    // Required rules: every tensor whose first matching rule is required must be in both files;
    // and a required rule must match at least one tensor present in both.
    for name in report.only_in_a.iter().chain(report.only_in_b.iter()) {
        if let Some(r) = tol.rule_for(name) {
            if r.required {
                let which = if a.tensors.contains_key(name) {
                    "B"
                } else {
                    "A"
                };
                let by = match tol.rule_name(r) {
                    d if d == "[default]" => d,
                    p => format!("rule \"{p}\""),
                };
                report
                    .missing_required
                    .push(format!("{name}: required by {by} but missing from {which}"));
            }
        }
    }
    for r in tol.rules.iter().filter(|r| r.required) {
        let any = a
            .tensors
            .keys()
            .any(|k| b.tensors.contains_key(k) && !is_kink_meta(k) && glob_match(&r.pattern, k));
        if !any {
            report.missing_required.push(format!(
                "rule \"{}\" is required but no tensor in both files matches it",
                r.pattern
            ));
        }
    }
    for (name, ta) in &a.tensors {
        let Some(tb) = b.tensors.get(name) else {
            continue;
        };
        if is_kink_meta(name) {
            continue;
        }
        let rule = tol.rule_for(name);
        let mut tr = TensorReport {
            name: name.clone(),
            dtype_a: ta.dtype.name().into(),
            dtype_b: tb.dtype.name().into(),
            shape_a: ta.shape.clone(),
            shape_b: tb.shape.clone(),
            status: Status::Pass,
            rule: rule.map(|r| tol.rule_name(r)),
            limits: rule.filter(|r| !r.ignore).map(Rule::describe_limits),
            reason: rule.and_then(|r| r.reason.clone()),
            stats: None,
        };
        if ta.shape != tb.shape {
            tr.status = Status::ShapeMismatch;
        } else if rule.is_some_and(|r| r.ignore) {
            tr.status = Status::Ignored;
        } else {
            // Strict: no rule means exact equality.
            let exact = Rule::default();
            let effective = match rule {
                Some(r) => Some(r),
                None if tol.strict => {
                    tr.rule = Some("strict".into());
                    tr.limits = Some("exact".into());
                    Some(&exact)
                }
                None => None,
            };
            let with_nan;
            let effective = match effective {
                Some(r) if tol.allow_nan && !r.allow_nan => {
                    with_nan = Rule {
                        allow_nan: true,
                        ..r.clone()
                    };
                    Some(&with_nan)
                }
                e => e,
            };
            let slack = if tol.kink_slack {
                kink_slack(a, name, ta.numel(), &mut report.missing_required)
            } else {
                None
            };
            let st = compare_tensors_with_slack(ta, tb, effective, slack.as_deref());
            tr.status = match effective {
                // A NaN fails even a tensor no rule covers, unless NaN is allowed.
                None if st.n_nan > 0 && !tol.allow_nan => Status::Fail,
                None => Status::NoRule,
                Some(_) if st.n_fail > 0 => Status::Fail,
                Some(_) => Status::Pass,
            };
            if st.n_nan > 0 {
                tr.limits = Some(format!(
                    "{}{} NaN{}",
                    tr.limits
                        .as_deref()
                        .map_or(String::new(), |l| format!("{l}; ")),
                    st.n_nan,
                    if tol.allow_nan || effective.is_some_and(|r| r.allow_nan) {
                        " (allowed)"
                    } else {
                        ""
                    }
                ));
            }
            tr.stats = Some(st);
        }
        report.tensors.push(tr);
    }
    report
}

/// The kink slack of tensor `name`: file A's `kink.slack.<name>` (module doc). A slack tensor of
/// the wrong size, or with a value that is not a finite number ≥ 0, is reported as bad input
/// and not used.
fn kink_slack(
    a: &TensorFile,
    name: &str,
    numel: usize,
    problems: &mut Vec<String>,
) -> Option<Vec<f64>> {
    let key = format!("kink.slack.{name}");
    let t = a.tensors.get(&key)?;
    if !matches!(t.dtype, DType::F32 | DType::F64) {
        problems.push(format!(
            "{key} in A: dtype {}, expected F32 or F64 (a slack is a float)",
            t.dtype.name()
        ));
        return None;
    }
    match t.to_f64() {
        Ok(v) if v.len() == numel => {
            if let Some(i) = v.iter().position(|x| !(x.is_finite() && *x >= 0.0)) {
                problems.push(format!(
                    "{key} in A: element {i} is {}, expected a finite number >= 0",
                    v[i]
                ));
                None
            } else {
                Some(v)
            }
        }
        _ => {
            problems.push(format!(
                "{key} in A: {} elements where {name} has {numel}",
                t.numel()
            ));
            None
        }
    }
}

/// Read two files and compare them. Errors (unreadable file) name the file.
pub fn compare_files(a: impl AsRef<Path>, b: impl AsRef<Path>, tol: &Tolerances) -> Result<Report> {
    let fa = TensorFile::read(a)?;
    let fb = TensorFile::read(b)?;
    Ok(compare(&fa, &fb, tol))
}

/// JSON form of a report. JSON has no NaN or infinity: those values are written as the strings
/// `"NaN"`, `"inf"` and `"-inf"` (Python's `float()` reads them back), every other float as a
/// number; a ULP distance that is infinite is `u64::MAX` (18446744073709551615).
pub fn report_json(r: &Report) -> Result<String> {
    Ok(serde_json::to_string_pretty(r)?)
}

/// A float in a JSON report: a number, or `"NaN"` / `"inf"` / `"-inf"` ([`report_json`]).
fn json_f64<S: serde::Serializer>(x: &f64, s: S) -> std::result::Result<S::Ok, S::Error> {
    if x.is_nan() {
        s.serialize_str("NaN")
    } else if x.is_infinite() {
        s.serialize_str(if *x > 0.0 { "inf" } else { "-inf" })
    } else {
        s.serialize_f64(*x)
    }
}

fn json_opt_f64<S: serde::Serializer>(
    x: &Option<f64>,
    s: S,
) -> std::result::Result<S::Ok, S::Error> {
    match x {
        Some(x) => json_f64(x, s),
        None => s.serialize_none(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn glob() {
        assert!(glob_match("fwd.grid_h", "fwd.grid_h"));
        assert!(!glob_match("fwd.grid_h", "fwd.grid_hx"));
        assert!(glob_match("grad.*", "grad.grid_h.table"));
        assert!(glob_match("*.weight", "shader.layers.0.weight"));
        assert!(glob_match(
            "shader.layers.?.weight",
            "shader.layers.1.weight"
        ));
        assert!(!glob_match(
            "shader.layers.?.weight",
            "shader.layers.10.weight"
        ));
        assert!(glob_match("*", ""));
        assert!(glob_match("a*b*c", "axxbyyc"));
        assert!(!glob_match("a*b*c", "axxbyy"));
    }

    #[test]
    fn rel_peak_limit_scales_with_the_tensor() {
        let rule = Rule {
            pattern: "x".into(),
            max_rel: Some(1e-12),
            max_rel_peak: Some(1e-6),
            ..Rule::default()
        };
        // An element near zero (rel 0.5) within 1e-6 of the tensor's peak 10 passes ...
        let a = Tensor::f64(vec![3], &[10.0, 1e-6, -3.0]).unwrap();
        let b = Tensor::f64(vec![3], &[10.0, 1.5e-6, -3.0]).unwrap();
        let st = compare_tensors(&a, &b, Some(&rule));
        assert_eq!((st.peak, st.n_fail), (10.0, 0));
        assert!((st.max_rel_peak - 5e-8).abs() < 1e-20);
        // ... the same abs error in a tensor whose peak is 1e-6 does not.
        let a = Tensor::f64(vec![2], &[1e-6, 0.0]).unwrap();
        let b = Tensor::f64(vec![2], &[1.5e-6, 0.0]).unwrap();
        let st = compare_tensors(&a, &b, Some(&rule));
        assert_eq!(st.n_fail, 1);
        assert_eq!(st.peak, 1.5e-6);
        // Without the peak, a rel-peak limit alone accepts nothing inexact.
        let e = element_error(1.0, 1.0 + 1e-9, CompareIn::F64);
        let only = Rule {
            max_rel_peak: Some(1.0),
            ..Rule::default()
        };
        assert!(!only.accepts(&e) && only.accepts_with_peak(&e, 1.0));
        assert_eq!(only.describe_limits(), "rel-peak 1e0");
        assert!(
            Tolerances::from_toml("[[rule]]\npattern = \"a\"\nmax_rel_peak = -1\n", "t").is_err()
        );
    }

    /// Only the reference (file A) may excuse a difference, and only by a finite slack ≥ 0.
    #[test]
    fn kink_slack_only_from_a_and_only_finite() {
        let tol =
            Tolerances::from_toml("[[rule]]\npattern = \"grad.*\"\nmax_abs = 1e-3\n", "t").unwrap();
        let file = |v: &[f64], slack: Option<&[f64]>| {
            let mut f = TensorFile::new();
            f.insert("grad.x", Tensor::f64(vec![2], v).unwrap());
            if let Some(s) = slack {
                f.insert("kink.slack.grad.x", Tensor::f64(vec![2], s).unwrap());
            }
            f
        };
        let a = file(&[1.0, 2.0], None);
        let b = file(&[1.5, 2.0], None);
        assert_eq!(compare(&a, &b, &tol).exit_code(), 1);
        // B's own slack is ignored, and the report says so.
        let r = compare(&a, &file(&[1.5, 2.0], Some(&[1.0, 0.0])), &tol);
        assert_eq!(r.exit_code(), 1, "{}", r.to_table());
        assert!(r.kink_in_b_ignored && r.to_table().contains("kink tensors in B ignored"));
        // A's slack excuses exactly what it covers.
        let r = compare(&file(&[1.0, 2.0], Some(&[0.6, 0.0])), &b, &tol);
        assert_eq!(r.exit_code(), 0, "{}", r.to_table());
        let r = compare(&file(&[1.0, 2.0], Some(&[0.4, 0.0])), &b, &tol);
        assert_eq!(r.exit_code(), 1, "{}", r.to_table());
        // A slack that is not a finite number >= 0 is bad input, never a pass.
        for bad in [f64::INFINITY, f64::NAN, -1.0] {
            let r = compare(&file(&[1.0, 2.0], Some(&[bad, 0.0])), &b, &tol);
            assert_eq!(r.exit_code(), 2, "{bad}: {}", r.to_table());
        }
    }

    #[test]
    fn unravel_row_major() {
        assert_eq!(unravel(0, &[2, 3]), vec![0, 0]);
        assert_eq!(unravel(5, &[2, 3]), vec![1, 2]);
        assert_eq!(unravel(7, &[2, 3, 4]), vec![0, 1, 3]);
        assert_eq!(unravel(0, &[]), Vec::<usize>::new());
    }
}
