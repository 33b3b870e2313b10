//! Gradient checks: central finite differences in f64 against every hand-written backward,
//! per operation (SH, MLP layers, pooling, sigmoid + each loss, hash grid) and through the whole
//! pipeline (every parameter group of grid H, grid D, ξ, the shader and the appearance codes, and
//! the input positions and directions), for linear and smoothstep interpolation, dense and
//! hashed levels, γ = 1 and γ = 2 with invalid sub-samples, views −1 and ≥ 0.
//!
//! Step and tolerance (the same everywhere):
//! - `H = 1e-6`: central differences have truncation error h²/6·|f'''| ≈ 2e-13·|f'''| and
//!   rounding error ≈ ε·|f|/h ≈ 1e-16·|f|·1e6 = 1e-10·|f| (times a small factor for the
//!   rounding accumulated through the forward). All functions checked have |f| ≲ 1 (losses are
//!   means of values in [0,1]; per-op checks contract outputs with weights in [−1,1]), and |f'''|
//!   stays below ~1e4 here (the finest grid level has scale ≈ 31, so a smoothstep weight's third
//!   derivative w.r.t. a position is 12·31³ ≈ 4e5 times features ≲ 0.5 and a pooling factor ≤ 1,
//!   divided by 3N ≥ 18 in the pipeline), so both error terms stay below ~1e-8.
//! - Pass if `|fd − analytic| ≤ ATOL + RTOL·|analytic|` with `ATOL = 1e-8`, `RTOL = 1e-6`.
//!   ATOL sits ~10× above the worst error budget above; real bugs (a wrong index, a missing
//!   factor, a wrong sign) give errors of the order of the gradient itself (1e-4…1), far above.
//!   The observed worst cases are printed on failure.
//! - Kinks: points are drawn away from grid-cell borders (every level of both grids has its cell
//!   fraction t ∈ [1e-3, 1−1e-3]; a step of h moves t by at most 31·h ≈ 3e-5); a case whose ±h
//!   evaluation changes any ReLU pattern or loss branch (sign of r for L1, |r| < δ for smooth-L1)
//!   is skipped and counted, and the test asserts that few cases were skipped.
//! - The vertex featurization (Fig. 2b baseline, `model/vertex.rs`) is checked per op and
//!   through the whole pipeline (vertex table, shader, codes, directions; positions must get an
//!   exactly zero gradient since they do not enter that model). It is linear in the table, so
//!   only the shader's ReLUs and the loss branches can straddle a kink.
//! - The D-SSIM term (`model/ssim.rs`) is checked per op (patch sides 3, 5 and 12: one window
//!   and 2×2 sliding 11×11 windows per patch, with and without a masked slot) and through the
//!   whole pipeline on a patch batch (case F, λ = 0.2). It is smooth (its denominators are
//!   ≥ C1, C2 > 0), so only the L1 part and the ReLUs have kinks.
//! - Positions are checked in `positions = "f64"` mode (the "tcnn" mode rounds x to f32, a
//!   staircase that finite differences cannot see through).

use xscale::model::batch::Batch;
use xscale::model::config::{
    Featurization, GridConfig, Interpolation, LevelWeight, LossKind, ModelConfig, PositionMode,
};
use xscale::model::hashgrid::{HashGrid, Touched};
use xscale::model::hfm::{pool_backward, pool_forward, Forward, Hfm};
use xscale::model::loss::{loss_backward, loss_forward, sigmoid_backward, sigmoid_forward};
use xscale::model::mlp::{Mlp, MlpActs};
use xscale::model::params::{Grads, Group};
use xscale::model::sh::{sh_backward_one, sh_forward_one, SH_DIM};
use xscale::model::ssim::{combine as ssim_combine, ssim_backward, ssim_forward};
use xscale::model::vertex::{vertex_backward, vertex_forward, VertexTable};
use xscale::rng::{uniform_f64, Purpose};

const H: f64 = 1e-6;
const ATOL: f64 = 1e-8;
const RTOL: f64 = 1e-6;
/// Cell-fraction margin for points (see the header).
const T_MARGIN: f64 = 1e-3;
/// Finite-difference step for the f32 directions (exactly representable, see the pipeline test).
const DIR_STEP: f64 = 1.0 / 16384.0;

fn u(seed: u64, a: u64, b: u64) -> f64 {
    uniform_f64(seed, Purpose::Test, a, b)
}
fn sym(seed: u64, a: u64, b: u64) -> f64 {
    2.0 * u(seed, a, b) - 1.0
}

/// Collects every failure and the worst error seen; asserts once at the end.
#[derive(Default)]
struct Report {
    fails: Vec<String>,
    checked: usize,
    skipped: usize,
    worst: f64,
    worst_label: String,
}

impl Report {
    fn check(&mut self, label: &str, fd: f64, an: f64) {
        self.checked += 1;
        let err = (fd - an).abs();
        let ratio = err / (ATOL + RTOL * an.abs());
        if ratio > self.worst {
            self.worst = ratio;
            self.worst_label = format!("{label}: fd {fd:.12e} analytic {an:.12e}");
        }
        #[allow(clippy::neg_cmp_op_on_partial_ord)] // written so that NaN fails
        if !(err <= ATOL + RTOL * an.abs()) {
            self.fails.push(format!(
                "{label}: fd {fd:.12e} analytic {an:.12e} |diff| {err:.3e}"
            ));
        }
    }
    fn finish(self, what: &str, min_checked: usize) {
        eprintln!(
            "{what}: {} checked, {} skipped at kinks, worst err/tol = {:.3} ({})",
            self.checked, self.skipped, self.worst, self.worst_label
        );
        assert!(
            self.fails.is_empty(),
            "{what}: {} of {} gradient checks failed:\n{}",
            self.fails.len(),
            self.checked,
            self.fails.join("\n")
        );
        assert!(
            self.checked >= min_checked,
            "{what}: only {} cases checked (expected ≥ {min_checked})",
            self.checked
        );
        assert!(
            self.skipped * 10 <= self.checked,
            "{what}: too many cases skipped at kinks ({} of {})",
            self.skipped,
            self.checked
        );
    }
}

/// Central difference of `f` around the current value of `*slot`.
fn central(slot_get: f64, mut f: impl FnMut(f64) -> f64) -> f64 {
    let fp = f(slot_get + H);
    let fm = f(slot_get - H);
    (fp - fm) / (2.0 * H)
}

// ---------------------------------------------------------------------------------------------
// Per operation
// ---------------------------------------------------------------------------------------------

#[test]
fn sh_backward_matches_fd() {
    let mut rep = Report::default();
    for case in 0..12u64 {
        // Directions on and off the unit sphere (the encoding is applied as given).
        let len = if case % 3 == 0 {
            1.0
        } else {
            0.5 + u(1, 0, case)
        };
        let mut d = [sym(1, 1, case), sym(1, 2, case), sym(1, 3, case)];
        let nrm = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
        for v in d.iter_mut() {
            *v *= len / nrm;
        }
        let w: Vec<f64> = (0..SH_DIM as u64).map(|i| sym(1, 4 + case, i)).collect();
        let f = |d: [f64; 3]| {
            let mut y = [0.0; SH_DIM];
            sh_forward_one(d, &mut y);
            y.iter().zip(&w).map(|(a, b)| a * b).sum::<f64>()
        };
        let mut an = [0.0; 3];
        sh_backward_one(d, &w, &mut an);
        for k in 0..3 {
            let fd = central(d[k], |x| {
                let mut dd = d;
                dd[k] = x;
                f(dd)
            });
            rep.check(&format!("sh case {case} d[{k}]"), fd, an[k]);
        }
    }
    rep.finish("sh", 36);
}

/// Random f64 parameters for an MLP (weights and biases U(±0.8)).
fn rand_params(n: usize, seed: u64) -> Vec<f64> {
    (0..n as u64).map(|i| 0.8 * sym(seed, 50, i)).collect()
}

fn relu_pattern(acts: &MlpActs<f64>) -> Vec<bool> {
    acts.hidden.iter().flatten().map(|&v| v > 0.0).collect()
}

#[test]
fn mlp_backward_matches_fd() {
    let mut rep = Report::default();
    for (ci, (dims, bias)) in [
        (vec![6usize, 9, 7, 4], true),
        (vec![5, 8, 3], false),
        (vec![4, 3], true),
    ]
    .into_iter()
    .enumerate()
    {
        let mlp = Mlp::new(&dims, bias);
        let rows = 5;
        let p = rand_params(mlp.n_params, 10 + ci as u64);
        let x: Vec<f64> = (0..(rows * dims[0]) as u64)
            .map(|i| sym(11, ci as u64, i))
            .collect();
        let w_out: Vec<f64> = (0..(rows * mlp.out_dim()) as u64)
            .map(|i| sym(12, ci as u64, i))
            .collect();
        let eval = |p: &[f64], x: &[f64]| {
            let mut acts = MlpActs::default();
            mlp.forward(p, &mlp.transpose_weights(p), x, rows, &mut acts);
            let l: f64 = acts.out.iter().zip(&w_out).map(|(a, b)| a * b).sum();
            (l, relu_pattern(&acts))
        };
        let mut acts = MlpActs::default();
        mlp.forward(&p, &mlp.transpose_weights(&p), &x, rows, &mut acts);
        let base_pat = relu_pattern(&acts);
        let mut dp = vec![0.0; mlp.n_params];
        let mut dx = vec![0.0; x.len()];
        mlp.backward(&p, &x, rows, &acts, w_out.clone(), &mut dp, Some(&mut dx));
        for i in 0..p.len() {
            let (mut pp, mut pm) = (p.clone(), p.clone());
            pp[i] += H;
            pm[i] -= H;
            let ((fp, sp), (fm, sm)) = (eval(&pp, &x), eval(&pm, &x));
            if sp != base_pat || sm != base_pat {
                rep.skipped += 1;
                continue;
            }
            rep.check(&format!("mlp {ci} param {i}"), (fp - fm) / (2.0 * H), dp[i]);
        }
        for i in 0..x.len() {
            let (mut xp, mut xm) = (x.clone(), x.clone());
            xp[i] += H;
            xm[i] -= H;
            let ((fp, sp), (fm, sm)) = (eval(&p, &xp), eval(&p, &xm));
            if sp != base_pat || sm != base_pat {
                rep.skipped += 1;
                continue;
            }
            rep.check(&format!("mlp {ci} input {i}"), (fp - fm) / (2.0 * H), dx[i]);
        }
    }
    rep.finish("mlp", 250);
}

#[test]
fn pooling_backward_matches_fd() {
    let mut rep = Report::default();
    let start = [0usize, 2, 3, 7];
    let lf = 5;
    let v = 7;
    let feat: Vec<f64> = (0..(v * lf) as u64).map(|i| sym(20, 0, i)).collect();
    let delta: Vec<f64> = (0..(v * lf) as u64).map(|i| sym(20, 1, i)).collect();
    let w: Vec<f64> = (0..(3 * lf) as u64).map(|i| sym(20, 2, i)).collect();
    let f = |feat: &[f64], delta: &[f64]| {
        let mut out = vec![0.0; 3 * lf];
        pool_forward(&start, feat, Some(delta), lf, &mut out);
        out.iter().zip(&w).map(|(a, b)| a * b).sum::<f64>()
    };
    let mut d_feat = vec![0.0; v * lf];
    pool_backward(&start, &w, lf, lf, &mut d_feat);
    for i in 0..v * lf {
        let fd = central(feat[i], |x| {
            let mut g = feat.clone();
            g[i] = x;
            f(&g, &delta)
        });
        rep.check(&format!("pool feat {i}"), fd, d_feat[i]);
        let fd = central(delta[i], |x| {
            let mut g = delta.clone();
            g[i] = x;
            f(&feat, &g)
        });
        rep.check(&format!("pool delta {i}"), fd, d_feat[i]);
    }
    rep.finish("pooling", 70);
}

#[test]
fn sigmoid_and_losses_match_fd() {
    let mut rep = Report::default();
    let n = 6;
    for (kind, delta) in [
        (LossKind::L1, 0.01),
        (LossKind::L2, 0.01),
        (LossKind::SmoothL1, 0.2),
    ] {
        let z: Vec<f64> = (0..(n * 3) as u64).map(|i| 3.0 * sym(30, 0, i)).collect();
        let target: Vec<[f32; 3]> = (0..n as u64)
            .map(|i| [u(30, 1, i) as f32, u(30, 2, i) as f32, u(30, 3, i) as f32])
            .collect();
        let f = |z: &[f64]| {
            let mut rgb = vec![0.0; n * 3];
            sigmoid_forward(z, &mut rgb);
            loss_forward(kind, delta, &rgb, &target) / (3 * n) as f64
        };
        let branch = |z: &[f64]| {
            let mut rgb = vec![0.0; n * 3];
            sigmoid_forward(z, &mut rgb);
            rgb.iter()
                .enumerate()
                .map(|(k, &v)| {
                    let r = v - target[k / 3][k % 3] as f64;
                    (r > 0.0, r.abs() < delta)
                })
                .collect::<Vec<_>>()
        };
        let mut rgb = vec![0.0; n * 3];
        sigmoid_forward(&z, &mut rgb);
        let mut d_rgb = vec![0.0; n * 3];
        loss_backward(kind, delta, &rgb, &target, 1.0 / (3 * n) as f64, &mut d_rgb);
        let mut dz = vec![0.0; n * 3];
        sigmoid_backward(&rgb, &d_rgb, &mut dz);
        let b0 = branch(&z);
        for i in 0..n * 3 {
            let (mut zp, mut zm) = (z.clone(), z.clone());
            zp[i] += H;
            zm[i] -= H;
            if branch(&zp) != b0 || branch(&zm) != b0 {
                rep.skipped += 1;
                continue;
            }
            rep.check(
                &format!("{kind:?} z[{i}]"),
                (f(&zp) - f(&zm)) / (2.0 * H),
                dz[i],
            );
        }
        // The smooth-L1 case must exercise both branches.
        if kind == LossKind::SmoothL1 {
            assert!(b0.iter().any(|b| b.1) && b0.iter().any(|b| !b.1), "{b0:?}");
        }
    }
    rep.finish("sigmoid+loss", 50);
}

#[test]
fn ssim_term_matches_fd() {
    let mut rep = Report::default();
    let lambda = 0.2;
    for (ci, (k, patches, masked)) in [
        (3usize, 2usize, None),
        (5, 2, Some(7usize)),
        (12, 2, None),
        (12, 2, Some(150)),
    ]
    .into_iter()
    .enumerate()
    {
        let n = k * k * patches;
        let seed = 40 + ci as u64;
        // Colours in (0.05, 0.95); the photo a noisy copy (SSIM near 1 and far from it both seen).
        let x: Vec<f64> = (0..(n * 3) as u64)
            .map(|i| 0.05 + 0.9 * u(seed, 0, i))
            .collect();
        let target: Vec<[f32; 3]> = (0..n)
            .map(|r| {
                let t = |c: usize| {
                    let v = if r < n / 2 {
                        x[r * 3 + c] + 0.1 * sym(seed, 1 + c as u64, r as u64)
                    } else {
                        u(seed, 4 + c as u64, r as u64)
                    };
                    v.clamp(0.0, 1.0) as f32
                };
                [t(0), t(1), t(2)]
            })
            .collect();
        let mut mask = Vec::new();
        if let Some(m) = masked {
            mask = vec![1u8; n];
            mask[m] = 0;
        }
        let f = |x: &[f64]| {
            let (s, m) = ssim_forward(k, x, &target, &mask);
            ssim_combine(lambda, 0.0, s, m)
        };
        let m = ssim_forward(k, &x, &target, &mask).1;
        assert!(m > 0, "k {k}: no window counted");
        let mut d = vec![0.0; n * 3];
        ssim_backward(k, &x, &target, &mask, -lambda / m as f64, &mut d);
        for i in 0..n * 3 {
            let fd = central(x[i], |v| {
                let mut xp = x.clone();
                xp[i] = v;
                f(&xp)
            });
            rep.check(&format!("ssim k {k} mask {masked:?} x[{i}]"), fd, d[i]);
        }
        if let Some(mr) = masked {
            // The masked slot is in no counted window: its gradient is exactly 0.
            assert!(d[mr * 3..mr * 3 + 3].iter().all(|&v| v == 0.0), "k {k}");
        }
    }
    rep.finish("ssim", 1500);
}

/// A point whose cell fraction in every level of every grid is away from 0 and 1.
fn safe_point(seed: u64, k: u64, grids: &[&HashGrid]) -> [f64; 3] {
    for attempt in 0..1000u64 {
        let p = [
            0.05 + 0.9 * u(seed, 1000 + attempt, 3 * k),
            0.05 + 0.9 * u(seed, 1000 + attempt, 3 * k + 1),
            0.05 + 0.9 * u(seed, 1000 + attempt, 3 * k + 2),
        ];
        let ok = grids.iter().all(|g| {
            g.scales.iter().all(|&s| {
                p.iter().all(|&x| {
                    let q = (s as f64).mul_add(x, 0.5);
                    let t = q - q.floor();
                    t > T_MARGIN && t < 1.0 - T_MARGIN
                })
            })
        });
        if ok {
            return p;
        }
    }
    panic!("no safe point found");
}

fn grid_cfg(levels: u32, log2: u32, interp: Interpolation) -> GridConfig {
    GridConfig {
        levels,
        features: 2,
        log2_table_size: log2,
        base_resolution: 4.0,
        per_level_scale: 2.0,
        interpolation: interp,
        finest_resolution: None,
        log2_table_sizes: None,
    }
}

#[test]
fn hashgrid_backward_matches_fd() {
    let mut rep = Report::default();
    for interp in [Interpolation::Linear, Interpolation::Smoothstep] {
        // Scales 3, 7, 15, 31: levels 0–2 dense, level 3 (32³ > 2^12) hashed.
        let g = HashGrid::new(&grid_cfg(4, 12, interp));
        assert!(
            g.dense[0] && !g.dense[3],
            "want dense and hashed levels: {:?}",
            g.dense
        );
        let table: Vec<f64> = (0..g.n_params() as u64)
            .map(|i| 0.5 * sym(40, 0, i))
            .collect();
        let m = 5;
        let pts: Vec<[f64; 3]> = (0..m as u64).map(|k| safe_point(41, k, &[&g])).collect();
        let od = g.out_dim();
        let w: Vec<f64> = (0..(m * od) as u64).map(|i| sym(42, 0, i)).collect();
        let f = |table: &[f64], pts: &[[f64; 3]]| {
            let mut out = vec![0.0; m * od];
            g.forward(table, pts, PositionMode::F64, &mut out);
            out.iter().zip(&w).map(|(a, b)| a * b).sum::<f64>()
        };
        let mut d_table = vec![0.0; table.len()];
        let mut touched = Touched::default();
        g.backward_table(&pts, PositionMode::F64, &w, &mut d_table, &mut touched);
        let mut d_pts = vec![0.0; m * 3];
        g.backward_points(&table, &pts, PositionMode::F64, &w, &mut d_pts);
        // Every touched entry's features, plus a few untouched entries (gradient exactly 0).
        let fdim = g.cfg.features as usize;
        let mut idx: Vec<usize> = touched
            .entries
            .iter()
            .flat_map(|&e| (0..fdim).map(move |f| e as usize * fdim + f))
            .collect();
        idx.extend([0, 17, table.len() - 1]);
        for &i in &idx {
            let fd = central(table[i], |x| {
                let mut t = table.clone();
                t[i] = x;
                f(&t, &pts)
            });
            rep.check(&format!("{interp:?} table[{i}]"), fd, d_table[i]);
        }
        for k in 0..m * 3 {
            let fd = central(pts[k / 3][k % 3], |x| {
                let mut p = pts.clone();
                p[k / 3][k % 3] = x;
                f(&table, &p)
            });
            rep.check(
                &format!("{interp:?} point {} axis {}", k / 3, k % 3),
                fd,
                d_pts[k],
            );
        }
    }
    rep.finish("hashgrid", 300);
}

// ---------------------------------------------------------------------------------------------
// Whole pipeline
// ---------------------------------------------------------------------------------------------

struct Case {
    name: &'static str,
    cfg: ModelConfig,
    n: usize,
    p_invalid: f64,
}

fn cases() -> Vec<Case> {
    let mut out = Vec::new();
    // A: linear, γ = 2 with invalid sub-samples, ξ on (grid D with a hashed level), A = 2 with
    // 3 rows (views −1 … 2), L1.
    let mut a = ModelConfig::tiny();
    a.deform.grid.log2_table_size = 8; // scales 3, 7 → 64 (dense), 512 > 256 (hashed)
    a.appearance_views = 3;
    out.push(Case {
        name: "A linear γ2 deform codes L1",
        cfg: a,
        n: 7,
        p_invalid: 0.35,
    });
    // B: smoothstep, γ = 1, biases, L2, no appearance codes.
    let mut b = ModelConfig::tiny();
    b.grid_h.interpolation = Interpolation::Smoothstep;
    b.deform.grid.interpolation = Interpolation::Smoothstep;
    b.shader.bias = true;
    b.appearance_dim = 0;
    b.gamma = 1;
    b.loss = LossKind::L2;
    out.push(Case {
        name: "B smoothstep γ1 bias L2",
        cfg: b,
        n: 6,
        p_invalid: 0.0,
    });
    // C: smoothstep, γ = 2 with invalid sub-samples, no ξ, two hidden shader layers, smooth-L1.
    let mut c = ModelConfig::tiny();
    c.grid_h.interpolation = Interpolation::Smoothstep;
    c.deform.enabled = false;
    c.shader.hidden_layers = 2;
    c.appearance_views = 2;
    c.loss = LossKind::SmoothL1;
    c.smooth_l1_delta = 0.15;
    out.push(Case {
        name: "C smoothstep γ2 no-deform smoothL1",
        cfg: c,
        n: 6,
        p_invalid: 0.35,
    });
    // D: footprint level weighting (SPEC §4.10) with ξ, γ = 2: pixel footprints in [0.03, 0.2]
    // give level weights of 1, fractions and 0 (levels then skipped) on the scales 3, 7, 15, 31.
    let mut d = ModelConfig::tiny();
    d.level_weight = LevelWeight::Footprint;
    d.appearance_views = 3;
    out.push(Case {
        name: "D level weighting γ2 deform",
        cfg: d.clone(),
        n: 7,
        p_invalid: 0.35,
    });
    // E: the same without ξ (the weighted gradient then goes straight to grid H).
    d.deform.enabled = false;
    d.grid_h.interpolation = Interpolation::Smoothstep;
    out.push(Case {
        name: "E level weighting smoothstep no-deform",
        cfg: d,
        n: 6,
        p_invalid: 0.2,
    });
    // F: the D-SSIM term on a patch batch (SPEC §4.7): two 4×4 patches (one 4×4 window each),
    // λ = 0.2 with L1, ξ on, γ = 2 with invalid sub-samples (make_batch sets the patch side).
    let mut f = ModelConfig::tiny();
    f.ssim_weight = 0.2;
    f.appearance_views = 2;
    out.push(Case {
        name: "F D-SSIM patches γ2 deform L1",
        cfg: f,
        n: 32,
        p_invalid: 0.35,
    });
    out
}

/// Random parameters that exercise every path (the initial ones would not: ξ's last layer and the
/// codes start at zero).
fn random_params(model: &Hfm, seed: u64) -> Vec<f64> {
    let mut p = vec![0.0f64; model.layout.total];
    for (ti, t) in model.layout.tensors.iter().enumerate() {
        let amp = match t.group {
            Group::GridH | Group::GridD => 0.5,
            Group::Appearance => 0.5,
            Group::Vertex => 0.5,
            _ => {
                if t.name.ends_with(".bias") {
                    0.2
                } else {
                    let s = &t.shape;
                    (6.0 / (s[0] + s[1]) as f64).sqrt() * 1.5
                }
            }
        };
        for (e, v) in p[t.range()].iter_mut().enumerate() {
            *v = amp * sym(seed, 60 + ti as u64, e as u64);
        }
    }
    p
}

fn make_batch(model: &Hfm, case: &Case, seed: u64) -> Batch {
    let s = (case.cfg.gamma * case.cfg.gamma) as usize;
    let mut b = Batch::random(seed, case.n, s, model.appearance_views(), case.p_invalid);
    let mut grids: Vec<&HashGrid> = vec![&model.grid_h];
    if let Some(g) = &model.grid_d {
        grids.push(g);
    }
    for k in 0..b.positions.len() {
        b.positions[k] = safe_point(seed, k as u64, &grids);
    }
    for d in b.dirs.iter_mut() {
        for v in d.iter_mut() {
            *v = ((*v as f64 / DIR_STEP).round() * DIR_STEP) as f32;
        }
    }
    if case.cfg.level_weight == LevelWeight::Footprint {
        b.footprint = (0..case.n)
            .map(|i| (0.03 + 0.17 * u(seed, 90, i as u64)) as f32)
            .collect();
    }
    if case.cfg.ssim_weight > 0.0 {
        b.patch = 4;
        // Photos close to a smooth field so the patches have structure for SSIM to compare.
        for (r, t) in b.target.iter_mut().enumerate() {
            let (x, y) = ((r % 4) as f32, ((r / 4) % 4) as f32);
            *t = [0.2 + 0.1 * x, 0.3 + 0.1 * y, 0.5 + 0.05 * (x - y)].map(|v| v + 0.05 * t[0]);
        }
    }
    if model.appearance_dim() > 0 {
        // Both kinds of pixels: with a code and with the mean code.
        b.view[0] = -1;
        b.view[1] = (model.appearance_views() - 1) as i32;
    }
    b
}

/// ReLU patterns and loss branches of a forward pass: a ±h evaluation whose signature differs
/// from the base one straddles a kink and is skipped.
fn signature(model: &Hfm, fwd: &Forward<f64>, batch: &Batch) -> Vec<bool> {
    let mut s = Vec::new();
    for ch in &fwd.chunks {
        s.extend(ch.shader.hidden.iter().flatten().map(|&v| v > 0.0));
        s.extend(ch.deform.hidden.iter().flatten().map(|&v| v > 0.0));
        for (k, &v) in ch.rgb.iter().enumerate() {
            let r = v - batch.target[ch.pixels.start + k / 3][k % 3] as f64;
            s.push(r > 0.0);
            s.push(r.abs() < model.cfg.smooth_l1_delta);
        }
    }
    s
}

#[test]
fn pipeline_gradients_match_fd() {
    let mut rep = Report::default();
    for (ci, case) in cases().iter().enumerate() {
        let model = Hfm::new(&case.cfg).unwrap();
        // Grid H of the tiny preset has dense levels and a hashed one (scale 31: 32³ > 2^12).
        assert!(model.grid_h.dense.contains(&true) && model.grid_h.dense.contains(&false));
        if ci == 0 {
            let gd = model.grid_d.as_ref().unwrap();
            assert!(
                gd.dense.contains(&true) && gd.dense.contains(&false),
                "{:?}",
                gd.dense
            );
        }
        let params = random_params(&model, 70 + ci as u64);
        let batch = make_batch(&model, case, 80 + ci as u64);
        batch.validate().unwrap();
        if case.p_invalid > 0.0 {
            assert!(
                batch.valid.contains(&0),
                "{}: want invalid sub-samples",
                case.name
            );
        }
        let mut grads = Grads::<f64>::new(&model.layout);
        let fwd = model.forward(&params, &batch).unwrap();
        let base_sig = signature(&model, &fwd, &batch);
        model.backward(&params, &batch, &fwd, &mut grads);

        // Loss and its kink signature at perturbed parameters / inputs.
        let eval = |params: &[f64], batch: &Batch| {
            let f = model.forward(params, batch).unwrap();
            (f.loss, signature(&model, &f, batch))
        };
        let mut fd_case = |label: String, an: f64, fp: (f64, Vec<bool>), fm: (f64, Vec<bool>)| {
            if fp.1 != base_sig || fm.1 != base_sig {
                rep.skipped += 1;
                return;
            }
            rep.check(
                &format!("{}: {label}", case.name),
                (fp.0 - fm.0) / (2.0 * H),
                an,
            );
        };

        // Parameters: every tensor; grid tables at their touched entries plus a few others.
        for t in &model.layout.tensors {
            let idx: Vec<usize> = match t.group {
                Group::GridH | Group::GridD => {
                    let (touched, f) = if t.group == Group::GridH {
                        (&grads.touched_h, case.cfg.grid_h.features as usize)
                    } else {
                        (&grads.touched_d, case.cfg.deform.grid.features as usize)
                    };
                    assert!(
                        !touched.entries.is_empty(),
                        "{}: {} untouched",
                        case.name,
                        t.name
                    );
                    let mut v: Vec<usize> = touched
                        .entries
                        .iter()
                        .step_by(3)
                        .flat_map(|&e| (0..f).map(move |k| e as usize * f + k))
                        .collect();
                    v.extend([1, t.len / 2, t.len - 1]);
                    v
                }
                _ => (0..t.len).step_by(1 + t.len / 40).collect(),
            };
            for i in idx {
                let g = t.offset + i;
                let (mut pp, mut pm) = (params.clone(), params.clone());
                pp[g] += H;
                pm[g] -= H;
                fd_case(
                    format!("{}[{i}]", t.name),
                    grads.params[g],
                    eval(&pp, &batch),
                    eval(&pm, &batch),
                );
            }
        }
        // Input positions (valid ones: through both grids; invalid ones: exactly zero).
        let mut saw_invalid = false;
        for k in 0..batch.positions.len() {
            if batch.valid[k] == 0 {
                saw_invalid = true;
                assert!(
                    grads.positions[k * 3..k * 3 + 3].iter().all(|&v| v == 0.0),
                    "{}: gradient on invalid sub-sample {k}",
                    case.name
                );
            }
            for a in 0..3 {
                let (mut bp, mut bm) = (batch.clone(), batch.clone());
                bp.positions[k][a] += H;
                bm.positions[k][a] -= H;
                fd_case(
                    format!("positions[{k}][{a}] (valid {})", batch.valid[k]),
                    grads.positions[k * 3 + a],
                    eval(&params, &bp),
                    eval(&params, &bm),
                );
            }
        }
        assert_eq!(saw_invalid, case.p_invalid > 0.0);
        // Directions are f32 in the batch: make_batch quantised them to multiples of
        // DIR_STEP = 2^-14, so x ± DIR_STEP is exact in f32 and the step is exactly DIR_STEP
        // (truncation DIR_STEP²/6·|f'''| ≈ 6e-10·|f'''|, with |f'''| ≲ 0.1 here because the loss is
        // a mean over 3N and SH are cubic polynomials: inside ATOL).
        for i in 0..batch.dirs.len() {
            for a in 0..3 {
                let (mut bp, mut bm) = (batch.clone(), batch.clone());
                bp.dirs[i][a] += DIR_STEP as f32;
                bm.dirs[i][a] -= DIR_STEP as f32;
                assert_eq!(bp.dirs[i][a] as f64 - batch.dirs[i][a] as f64, DIR_STEP);
                let (fp, fm) = (eval(&params, &bp), eval(&params, &bm));
                if fp.1 != base_sig || fm.1 != base_sig {
                    rep.skipped += 1;
                    continue;
                }
                let fd = (fp.0 - fm.0) / (2.0 * DIR_STEP);
                rep.check(
                    &format!("{}: dirs[{i}][{a}]", case.name),
                    fd,
                    grads.dirs[i * 3 + a],
                );
            }
        }
    }
    rep.finish("pipeline", 400);
}

/// The check can fail: a backward that scales the grid H feature gradients by the square of the
/// footprint level weights instead of the weights (the same where a level is fully on or off, wrong
/// where it is partly weighted) disagrees with the finite differences, while the real backward
/// passes on the same entries.
#[test]
fn a_broken_level_weight_derivative_fails_the_check() {
    let case = cases()
        .into_iter()
        .find(|c| c.cfg.level_weight == LevelWeight::Footprint)
        .unwrap();
    let model = Hfm::new(&case.cfg).unwrap();
    let params = random_params(&model, 170);
    let batch = make_batch(&model, &case, 180);
    let fwd = model.forward(&params, &batch).unwrap();
    let mut sabotaged = fwd.clone();
    let mut partial = 0;
    for ch in &mut sabotaged.chunks {
        for w in &mut ch.level_w {
            partial += (*w > 0.0 && *w < 1.0) as usize;
            *w *= *w;
        }
    }
    assert!(partial > 0, "the case has no partly weighted level");
    let (mut good, mut bad) = (
        Grads::<f64>::new(&model.layout),
        Grads::<f64>::new(&model.layout),
    );
    model.backward(&params, &batch, &fwd, &mut good);
    model.backward(&params, &batch, &sabotaged, &mut bad);
    let base_sig = signature(&model, &fwd, &batch);
    let t = model
        .layout
        .tensors
        .iter()
        .find(|t| t.group == Group::GridH)
        .unwrap();
    let f = case.cfg.grid_h.features as usize;
    let (mut ok, mut broken_rep) = (Report::default(), Report::default());
    let entries: Vec<u32> = good
        .touched_h
        .entries
        .iter()
        .chain(&bad.touched_h.entries)
        .copied()
        .collect();
    for e in entries.iter().step_by(2) {
        for k in 0..f {
            let g = t.offset + *e as usize * f + k;
            let (mut pp, mut pm) = (params.clone(), params.clone());
            pp[g] += H;
            pm[g] -= H;
            let (fp, fm) = (
                model.forward(&pp, &batch).unwrap(),
                model.forward(&pm, &batch).unwrap(),
            );
            if signature(&model, &fp, &batch) != base_sig
                || signature(&model, &fm, &batch) != base_sig
            {
                continue;
            }
            let fd = (fp.loss - fm.loss) / (2.0 * H);
            ok.check(&format!("table[{g}]"), fd, good.params[g]);
            broken_rep.check(&format!("table[{g}]"), fd, bad.params[g]);
        }
    }
    assert!(ok.checked >= 50, "only {} entries checked", ok.checked);
    assert!(
        ok.fails.is_empty(),
        "the real backward fails: {:?}",
        &ok.fails[..ok.fails.len().min(5)]
    );
    assert!(
        broken_rep.fails.len() >= 10,
        "a backward with squared level weights failed only {} of {} checks",
        broken_rep.fails.len(),
        broken_rep.checked
    );
    eprintln!(
        "squared level weights: {} of {} table checks fail; the real backward: 0",
        broken_rep.fails.len(),
        broken_rep.checked
    );
}

// ---------------------------------------------------------------------------------------------
// Vertex featurization (Fig. 2b baseline)
// ---------------------------------------------------------------------------------------------

/// A small random "mesh": `nv` vertices, `nt` faces with distinct random corners.
fn random_faces(seed: u64, nv: usize, nt: usize) -> Vec<[u32; 3]> {
    (0..nt as u64)
        .map(|t| {
            let a = (u(seed, 200, t) * nv as f64) as u32;
            let b = (a + 1 + (u(seed, 201, t) * (nv - 2) as f64) as u32) % nv as u32;
            let mut c = (u(seed, 202, t) * nv as f64) as u32;
            while c == a || c == b {
                c = (c + 1) % nv as u32;
            }
            [a, b, c]
        })
        .collect()
}

/// Barycentrics (u, v) uniform in the triangle.
fn random_bary(seed: u64, k: u64) -> [f64; 2] {
    let (mut a, mut b) = (u(seed, 210, k), u(seed, 211, k));
    if a + b > 1.0 {
        (a, b) = (1.0 - a, 1.0 - b);
    }
    [a, b]
}

#[test]
fn vertex_backward_matches_fd() {
    let mut rep = Report::default();
    let (nv, z, m) = (9usize, 3usize, 14usize);
    let vt = VertexTable::new(nv, z, random_faces(30, nv, 6).into()).unwrap();
    let table: Vec<f64> = (0..(nv * z) as u64).map(|i| sym(31, 0, i)).collect();
    // Repeated triangles, corners and an edge point (w = 0 for one corner) included.
    let tri: Vec<u32> = (0..m as u64).map(|k| (k % 6) as u32).collect();
    let mut bary: Vec<[f64; 2]> = (0..m as u64).map(|k| random_bary(32, k)).collect();
    bary[3] = [0.0, 0.4];
    let w: Vec<f64> = (0..(m * z) as u64).map(|i| sym(33, 0, i)).collect();
    let f = |table: &[f64]| {
        let mut out = vec![0.0; m * z];
        vertex_forward(&vt, table, &tri, &bary, &mut out);
        out.iter().zip(&w).map(|(a, b)| a * b).sum::<f64>()
    };
    let mut d = vec![0.0; nv * z];
    let mut touched = Touched::default();
    vertex_backward(&vt, &tri, &bary, &w, &mut d, &mut touched);
    // Touched = exactly the vertices of the triangles used, sorted and unique.
    let mut want: Vec<u32> = tri.iter().flat_map(|&t| vt.faces[t as usize]).collect();
    want.sort_unstable();
    want.dedup();
    assert_eq!(touched.entries, want);
    for i in 0..nv * z {
        let fd = central(table[i], |x| {
            let mut t = table.clone();
            t[i] = x;
            f(&t)
        });
        rep.check(&format!("vertex table {i}"), fd, d[i]);
        if !want.contains(&((i / z) as u32)) {
            assert_eq!(d[i], 0.0, "untouched row {} has gradient", i / z);
        }
    }
    // Backward accumulates.
    let d0 = d.clone();
    vertex_backward(&vt, &tri, &bary, &w, &mut d, &mut touched);
    assert!(d
        .iter()
        .zip(&d0)
        .all(|(a, b)| (a - 2.0 * b).abs() <= 1e-12 * (1.0 + b.abs())));
    assert_eq!(touched.entries, want);
    rep.finish("vertex", 27);
}

#[test]
fn vertex_pipeline_gradients_match_fd() {
    let mut rep = Report::default();
    let (nv, nt) = (11usize, 8usize);
    for (ci, (gamma, p_invalid, loss, bias, a)) in [
        (2u32, 0.35, LossKind::L1, false, 2u32),
        (1, 0.0, LossKind::SmoothL1, true, 0),
    ]
    .into_iter()
    .enumerate()
    {
        let mut cfg = ModelConfig::tiny();
        cfg.featurization = Featurization::Vertex;
        cfg.vertex_features = 5;
        cfg.vertex_count = nv as u32;
        cfg.deform.enabled = false;
        cfg.gamma = gamma;
        cfg.loss = loss;
        cfg.smooth_l1_delta = 0.15;
        cfg.shader.bias = bias;
        cfg.appearance_dim = a;
        cfg.appearance_views = if a > 0 { 3 } else { 0 };
        let faces = random_faces(40 + ci as u64, nv, nt);
        let model = Hfm::with_vertex(&cfg, faces.into()).unwrap();
        assert!(model.layout.get("grid_h.table").is_none());
        assert_eq!(model.layout.get("vertex.features").unwrap().shape, [nv, 5]);
        let params = random_params(&model, 41 + ci as u64);
        let s = (gamma * gamma) as usize;
        let n = 7;
        let mut batch = Batch::random(42 + ci as u64, n, s, model.appearance_views(), p_invalid);
        batch.triangle = (0..(n * s) as u64)
            .map(|k| {
                if batch.valid[k as usize] == 0 {
                    u32::MAX
                } else {
                    (u(43, ci as u64, k) * nt as f64) as u32
                }
            })
            .collect();
        batch.bary = (0..(n * s) as u64).map(|k| random_bary(44, k)).collect();
        for d in batch.dirs.iter_mut() {
            for v in d.iter_mut() {
                *v = ((*v as f64 / DIR_STEP).round() * DIR_STEP) as f32;
            }
        }
        if a > 0 {
            batch.view[0] = -1;
            batch.view[1] = 2;
        }
        batch.validate().unwrap();
        // A batch without triangle ids is an error naming what is missing.
        let mut no_ids = batch.clone();
        no_ids.triangle.clear();
        no_ids.bary.clear();
        let e = model.forward(&params, &no_ids).unwrap_err().to_string();
        assert!(e.contains("batch.triangle"), "{e}");

        let mut grads = Grads::<f64>::new(&model.layout);
        let fwd = model.forward(&params, &batch).unwrap();
        let base_sig = signature(&model, &fwd, &batch);
        model.backward(&params, &batch, &fwd, &mut grads);
        assert!(!grads.touched_v.entries.is_empty());
        assert!(grads.touched_h.entries.is_empty() && grads.touched_d.entries.is_empty());
        let eval = |params: &[f64], batch: &Batch| {
            let f = model.forward(params, batch).unwrap();
            (f.loss, signature(&model, &f, batch))
        };
        let name = format!("vertex case {ci}");
        let mut fd_case =
            |label: String, an: f64, fp: (f64, Vec<bool>), fm: (f64, Vec<bool>), h: f64| {
                if fp.1 != base_sig || fm.1 != base_sig {
                    rep.skipped += 1;
                    return;
                }
                rep.check(&format!("{name}: {label}"), (fp.0 - fm.0) / (2.0 * h), an);
            };
        // Every parameter of every tensor (the tables are small here).
        for t in &model.layout.tensors {
            for i in 0..t.len {
                let g = t.offset + i;
                let (mut pp, mut pm) = (params.clone(), params.clone());
                pp[g] += H;
                pm[g] -= H;
                fd_case(
                    format!("{}[{i}]", t.name),
                    grads.params[g],
                    eval(&pp, &batch),
                    eval(&pm, &batch),
                    H,
                );
            }
        }
        // Untouched vertex rows have exactly zero gradient; touched rows are the valid
        // sub-samples' triangles' corners.
        let r = model.layout.range("vertex.features");
        let mut want: Vec<u32> = batch
            .triangle
            .iter()
            .zip(&batch.valid)
            .filter(|(_, &v)| v == 1)
            .flat_map(|(&t, _)| model.vertex.as_ref().unwrap().faces[t as usize])
            .collect();
        want.sort_unstable();
        want.dedup();
        assert_eq!(grads.touched_v.entries, want);
        for (e, row) in grads.params[r].chunks_exact(5).enumerate() {
            if !want.contains(&(e as u32)) {
                assert!(row.iter().all(|&v| v == 0.0), "row {e}");
            }
        }
        // Positions do not enter this model: zero gradient, and the loss does not move.
        assert!(grads.positions.iter().all(|&v| v == 0.0));
        let mut bp = batch.clone();
        for p in bp.positions.iter_mut() {
            p[0] = 0.5 * p[0] + 0.1;
        }
        assert_eq!(eval(&params, &bp).0, fwd.loss);
        // Directions (quantised to DIR_STEP as in the hash pipeline test).
        for i in 0..n {
            for a in 0..3 {
                let (mut bp, mut bm) = (batch.clone(), batch.clone());
                bp.dirs[i][a] += DIR_STEP as f32;
                bm.dirs[i][a] -= DIR_STEP as f32;
                fd_case(
                    format!("dirs[{i}][{a}]"),
                    grads.dirs[i * 3 + a],
                    eval(&params, &bp),
                    eval(&params, &bm),
                    DIR_STEP,
                );
            }
        }
    }
    rep.finish("vertex pipeline", 500);
}

// ---------------------------------------------------------------------------------------------
// Mesh refinement through the hit point (src/refine/hit.rs, field.rs)
// ---------------------------------------------------------------------------------------------

use glam::DVec3;
use xscale::model::refine::RefineConfig;
use xscale::refine::field::{field_backward, field_theta, smoothness, Active, RefineGeom};
use xscale::refine::hit::{
    hits_backward, hits_backward_anchored, intersect, reintersect_batch,
    reintersect_batch_anchored, RayHit,
};
use xscale::scene::{Mesh, Normalization, NormalizeMode};

/// A bumpy 5×4-vertex sheet (per-axis extents 2 : 1.5 : ~0.3, so the per-axis normalisation is
/// far from isotropic) and a refinement config with two grid levels and the residual.
fn refine_scene() -> (Mesh, Normalization, RefineConfig) {
    let (nx, ny) = (4usize, 3usize);
    let mut m = Mesh::default();
    for j in 0..=ny {
        for i in 0..=nx {
            let (x, y) = (0.5 * i as f64, 0.5 * j as f64);
            m.vertices.push(DVec3::new(
                x + 3.0,
                y - 1.0,
                0.12 * (2.1 * x).sin() + 0.09 * (1.7 * y + 0.3).cos() + 10.0,
            ));
        }
    }
    let k = |i: usize, j: usize| (j * (nx + 1) + i) as u32;
    for j in 0..ny {
        for i in 0..nx {
            m.triangles.push([k(i, j), k(i + 1, j), k(i + 1, j + 1)]);
            m.triangles.push([k(i, j), k(i + 1, j + 1), k(i, j + 1)]);
        }
    }
    let norm = Normalization::from_mesh(&m, NormalizeMode::PerAxis);
    let cfg = RefineConfig {
        enabled: true,
        levels: 2,
        base_resolution: 2,
        per_vertex: true,
        laplacian: 0.3,
        bilaplacian: 0.7,
        ..RefineConfig::learned()
    };
    (m, norm, cfg)
}

/// Random offset parameters (θ up to ~±0.03 of the largest extent).
fn refine_params(cfg: &RefineConfig, nv: usize, seed: u64) -> (Vec<Vec<f64>>, Vec<f64>) {
    let grids = (0..cfg.levels)
        .map(|l| {
            (0..(cfg.resolution(l) + 1).pow(3) as u64)
                .map(|e| 0.01 * sym(seed, 300 + l as u64, e))
                .collect()
        })
        .collect();
    let r = (0..nv as u64).map(|i| 0.01 * sym(seed, 310, i)).collect();
    (grids, r)
}

/// Closest hit of a local-frame ray on the mesh at offsets θ, brute force: (triangle, t).
fn brute_hit(geom: &RefineGeom, theta: &[f64], o: DVec3, d: DVec3) -> Option<(usize, f64)> {
    let mut best: Option<(usize, f64)> = None;
    for (ti, t) in geom.triangles.iter().enumerate() {
        let v = t.map(|i| geom.position(i as usize, theta[i as usize]));
        if let Some((tt, _, _)) = xscale::refine::hit::intersect(o, d, v, 0.0) {
            let inside = {
                let (_, b, _) = xscale::refine::hit::intersect(o, d, v, 0.0).unwrap();
                b.iter().all(|&x| (0.0..=1.0).contains(&x))
            };
            if inside && best.is_none_or(|b| tt < b.1) {
                best = Some((ti, tt));
            }
        }
    }
    best
}

/// A batch of rays from a few cameras onto the sheet at offsets θ: every valid sub-sample hits
/// the inside of its triangle (barycentrics ≥ 0.12) unoccluded, at |cos| ≥ 0.3, at a normalised
/// point away from every grid cell border of the model.
fn refine_batch(
    model: &Hfm,
    geom: &RefineGeom,
    theta: &[f64],
    case: &Case,
    seed: u64,
    anchored: bool,
) -> (Batch, Vec<DVec3>) {
    let s = (case.cfg.gamma * case.cfg.gamma) as usize;
    let mut grids: Vec<&HashGrid> = vec![&model.grid_h];
    if let Some(g) = &model.grid_d {
        grids.push(g);
    }
    let safe = |p: DVec3| {
        grids.iter().all(|g| {
            g.scales.iter().all(|&sc| {
                (0..3).all(|a| {
                    let q = (sc as f64).mul_add(p[a], 0.5);
                    let t = q - q.floor();
                    t > T_MARGIN && t < 1.0 - T_MARGIN
                })
            })
        })
    };
    let extent = geom.norm.extent;
    let mut b = Batch::default();
    let mut origins = Vec::new();
    for i in 0..case.n {
        let o = DVec3::new(
            0.6 * sym(seed, 400, i as u64),
            0.5 * sym(seed, 401, i as u64),
            1.6 + 0.4 * u(seed, 402, i as u64),
        );
        origins.push(o);
        let mut dsum = DVec3::ZERO;
        let mut any = false;
        for j in 0..s {
            let k = (i * s + j) as u64;
            let valid = j == 0 || u(seed, 403, k) >= case.p_invalid;
            let mut placed = None;
            if valid {
                for attempt in 0..400u64 {
                    let a = 1000 * k + attempt;
                    let ti = (u(seed, 404, a) * geom.triangles.len() as f64) as usize;
                    let (mut bu, mut bv) = (u(seed, 405, a), u(seed, 406, a));
                    if bu + bv > 1.0 {
                        (bu, bv) = (1.0 - bu, 1.0 - bv);
                    }
                    let beta = [1.0 - bu - bv, bu, bv];
                    if beta.iter().any(|&x| x < 0.12) {
                        continue;
                    }
                    let v =
                        geom.triangles[ti].map(|q| geom.position(q as usize, theta[q as usize]));
                    let x = v[0] * beta[0] + v[1] * beta[1] + v[2] * beta[2];
                    let p = x / extent + DVec3::splat(0.5);
                    let d = (x - o).normalize();
                    let n = (v[1] - v[0]).cross(v[2] - v[0]).normalize();
                    // Anchored: the model is queried at the training mesh's point.
                    let q = if anchored {
                        let b0 = geom.triangles[ti].map(|q| geom.base[q as usize]);
                        (b0[0] * beta[0] + b0[1] * beta[1] + b0[2] * beta[2]) / extent
                            + DVec3::splat(0.5)
                    } else {
                        p
                    };
                    if !safe(q) || n.dot(d).abs() < 0.3 {
                        continue;
                    }
                    if brute_hit(geom, theta, o, d).map(|h| h.0) != Some(ti) {
                        continue;
                    }
                    placed = Some((ti, q, d, [bu, bv]));
                    break;
                }
            }
            match placed {
                Some((ti, p, d, uv)) => {
                    b.positions.push(p.to_array());
                    b.valid.push(1);
                    b.triangle.push(ti as u32);
                    b.bary.push(uv);
                    dsum += d;
                    any = true;
                }
                None => {
                    b.positions.push([0.0; 3]);
                    b.valid.push(0);
                    b.triangle.push(u32::MAX);
                    b.bary.push([0.0; 2]);
                }
            }
        }
        assert!(any, "pixel {i}: no ray placed");
        let dir = dsum.normalize();
        b.dirs.push(
            dir.to_array()
                .map(|v| ((v / DIR_STEP).round() * DIR_STEP) as f32),
        );
        b.view.push(if model.appearance_dim() > 0 {
            (u(seed, 407, i as u64) * (model.appearance_views() as f64 + 1.0)).floor() as i32 - 1
        } else {
            -1
        });
        b.target
            .push([0, 1, 2].map(|c| u(seed, 408 + c, i as u64) as f32));
    }
    if case.cfg.level_weight == LevelWeight::Footprint {
        b.footprint = (0..case.n)
            .map(|i| (0.03 + 0.17 * u(seed, 90, i as u64)) as f32)
            .collect();
    }
    b.validate().unwrap();
    (b, origins)
}

/// ∂L/∂positions of the hits → ∂L/∂θ (the real one is [`hits_backward`]; the tests break it).
type HitsBackward<'a> = dyn Fn(&[RayHit], &[f64], &mut [f64]) + 'a;

/// An energy of the offset field's (grids, residual); `None` where a step crossed one of its kinks.
type FieldEnergy<'a> = dyn Fn(&[Vec<f64>], &[f64]) -> Option<f64> + 'a;

/// Central differences of `energy` (`None`: the step crossed a kink of the energy and is skipped)
/// for every per-vertex residual entry and every grid node with a gradient (plus each grid's first
/// and last node), against the analytic `an` = (grids, residual).
fn check_field(
    grids: &[Vec<f64>],
    r: &[f64],
    an: &(Vec<Vec<f64>>, Vec<f64>),
    rep: &mut Report,
    label: &str,
    energy: &FieldEnergy,
) {
    let mut fd = |lab: String, an: f64, perturb: &dyn Fn(f64) -> (Vec<Vec<f64>>, Vec<f64>)| {
        let (gp, rp) = perturb(H);
        let (gm, rm) = perturb(-H);
        match (energy(&gp, &rp), energy(&gm, &rm)) {
            (Some(fp), Some(fm)) => rep.check(&lab, (fp - fm) / (2.0 * H), an),
            _ => rep.skipped += 1,
        }
    };
    for i in 0..r.len() {
        fd(format!("{label}: refine.vertex[{i}]"), an.1[i], &|h| {
            let mut r = r.to_vec();
            r[i] += h;
            (grids.to_vec(), r)
        });
    }
    for (l, g) in an.0.iter().enumerate() {
        let mut idx: Vec<usize> = (0..g.len()).filter(|&e| g[e] != 0.0).collect();
        idx.extend([0, g.len() - 1]);
        for e in idx {
            fd(format!("{label}: refine.grid.{l}[{e}]"), g[e], &|h| {
                let mut gr = grids.to_vec();
                gr[l][e] += h;
                (gr, r.to_vec())
            });
        }
    }
}

/// Everything one refinement gradient check needs.
struct RefineCheck {
    model: Hfm,
    mparams: Vec<f64>,
    cfg: RefineConfig,
    geom: RefineGeom,
    grids: Vec<Vec<f64>>,
    r: Vec<f64>,
    batch: Batch,
    origins: Vec<DVec3>,
    base_sig: Vec<bool>,
    /// `[model.refine] anchored`: the offsets the rays were cast at (the unperturbed ones).
    traced: Option<Vec<f64>>,
}

impl RefineCheck {
    fn new(case: &Case, seed: u64) -> RefineCheck {
        RefineCheck::build(case, seed, false)
    }

    fn new_anchored(case: &Case, seed: u64) -> RefineCheck {
        RefineCheck::build(case, seed, true)
    }

    fn reintersect(&self, theta: &[f64], b: &mut Batch) -> Vec<RayHit> {
        let origin = |p: usize| self.origins[p];
        match &self.traced {
            None => reintersect_batch(&self.geom, theta, b, &origin, self.cfg.min_cos),
            Some(tr) => {
                reintersect_batch_anchored(&self.geom, theta, tr, b, &origin, self.cfg.min_cos)
            }
        }
    }

    fn build(case: &Case, seed: u64, anchored: bool) -> RefineCheck {
        let (mesh, norm, cfg) = refine_scene();
        let geom = RefineGeom::new(&mesh, &norm);
        let model = Hfm::new(&case.cfg).unwrap();
        let mparams = random_params(&model, seed);
        let (grids, r) = refine_params(&cfg, geom.n_vertices(), seed);
        let theta = RefineCheck::theta_of(&cfg, &geom, &grids, &r);
        let (batch, origins) = refine_batch(&model, &geom, &theta, case, seed, anchored);
        let traced = anchored.then(|| theta.clone());
        let mut c = RefineCheck {
            model,
            mparams,
            cfg,
            geom,
            grids,
            r,
            batch,
            origins,
            base_sig: Vec::new(),
            traced,
        };
        let (_, sig, _) = c.eval(&c.grids.clone(), &c.r.clone());
        c.base_sig = sig;
        c
    }

    fn theta_of(cfg: &RefineConfig, geom: &RefineGeom, grids: &[Vec<f64>], r: &[f64]) -> Vec<f64> {
        (0..geom.n_vertices())
            .map(|i| field_theta(cfg, geom, grids, r, i))
            .collect()
    }

    /// Loss (photometric + smoothness) at offset parameters, its kink signature, the hits.
    fn eval(&self, grids: &[Vec<f64>], r: &[f64]) -> (f64, Vec<bool>, Vec<RayHit>) {
        let theta = RefineCheck::theta_of(&self.cfg, &self.geom, grids, r);
        let mut b = self.batch.clone();
        let hits = self.reintersect(&theta, &mut b);
        let n_valid = self.batch.valid.iter().filter(|&&v| v != 0).count();
        assert_eq!(hits.len(), n_valid, "a sub-sample left its triangle");
        let f = self.model.forward(&self.mparams, &b).unwrap();
        let mut scratch = vec![0.0; r.len()];
        let e = smoothness(&self.cfg, &self.geom, r, &mut scratch);
        (f.loss + e, signature(&self.model, &f, &b), hits)
    }

    /// Analytic gradients of the grids and the residual, with `backward` turning the position
    /// gradient into ∂L/∂θ (the real one: [`hits_backward`]).
    fn analytic(&self, backward: &HitsBackward) -> (Vec<Vec<f64>>, Vec<f64>) {
        let theta = RefineCheck::theta_of(&self.cfg, &self.geom, &self.grids, &self.r);
        let mut b = self.batch.clone();
        let hits = self.reintersect(&theta, &mut b);
        let fwd = self.model.forward(&self.mparams, &b).unwrap();
        let mut grads = Grads::<f64>::new(&self.model.layout);
        self.model.backward(&self.mparams, &b, &fwd, &mut grads);
        let nv = self.geom.n_vertices();
        let mut d_theta = vec![0.0; nv];
        backward(&hits, &grads.positions, &mut d_theta);
        let all: Vec<u32> = (0..nv as u32).collect();
        let mut d_grids: Vec<Vec<f64>> = self.grids.iter().map(|g| vec![0.0; g.len()]).collect();
        let mut d_r = vec![0.0; nv];
        field_backward(
            &self.cfg,
            &self.geom,
            &all,
            &d_theta,
            Active {
                grids: self.grids.len(),
                residual: true,
            },
            &mut d_grids,
            &mut d_r,
        );
        smoothness(&self.cfg, &self.geom, &self.r, &mut d_r);
        (d_grids, d_r)
    }

    /// `real` passes the check and each of `broken` fails at least a third of it.
    fn real_passes_broken_fail(&self, real: &HitsBackward, broken: &[(&str, Box<HitsBackward>)]) {
        let mut ok = Report::default();
        self.check(&self.analytic(real), &mut ok, "real");
        assert!(
            ok.fails.is_empty(),
            "the real gradient fails: {:?}",
            &ok.fails[..ok.fails.len().min(5)]
        );
        for (what, bw) in broken {
            let mut bad = Report::default();
            self.check(&self.analytic(bw.as_ref()), &mut bad, what);
            assert!(
                bad.fails.len() * 3 >= bad.checked,
                "{what}: only {} of {} checks failed",
                bad.fails.len(),
                bad.checked
            );
            eprintln!(
                "{what}: {} of {} refinement checks fail; the real gradient: 0 of {}",
                bad.fails.len(),
                bad.checked,
                ok.checked
            );
        }
    }

    /// Finite differences of every residual entry and of the grid nodes with a gradient (plus
    /// a few without) against `an`.
    fn check(&self, an: &(Vec<Vec<f64>>, Vec<f64>), rep: &mut Report, label: &str) {
        check_field(&self.grids, &self.r, an, rep, label, &|g, r| {
            let (f, sig, _) = self.eval(g, r);
            (sig == self.base_sig).then_some(f)
        });
    }
}

/// ∂L/∂(offset field) through the re-intersected hit points, the per-axis normalisation, the
/// field's trilinear levels and the smoothness energy, against central differences of the loss
/// recomputed from scratch (offsets → vertices → re-intersection → forward).
#[test]
fn mesh_refinement_gradients_match_fd() {
    let mut rep = Report::default();
    for (ci, case) in cases().iter().enumerate() {
        let c = RefineCheck::new(case, 500 + ci as u64);
        // The normalisation is far from isotropic: a bug ignoring it cannot pass by luck.
        let e = c.geom.norm.extent;
        assert!(e.max_element() > 4.0 * e.min_element(), "{e}");
        let an = c.analytic(&|h, dp, dt| hits_backward(&c.geom, h, dp, dt));
        assert!(an.1.iter().filter(|&&g| g != 0.0).count() >= 10);
        let big = an.1.iter().fold(0.0f64, |m, g| m.max(g.abs()));
        eprintln!("{}: largest |dL/dr| {big:.3e}, median {:.3e}", case.name, {
            let mut v: Vec<f64> = an.1.iter().map(|g| g.abs()).collect();
            v.sort_by(f64::total_cmp);
            v[v.len() / 2]
        });
        c.check(&an, &mut rep, case.name);
    }
    rep.finish("mesh refinement", 300);
}

/// The check can fail: the vertex gradient with the per-axis normalisation left out (∂L/∂x_n used
/// as ∂L/∂x up to the isotropic scale) and with the hit moving along the triangle's normal instead
/// of along its ray both disagree with the finite differences, while the real one passes.
#[test]
fn broken_mesh_refinement_gradients_fail_the_check() {
    let case = cases().into_iter().next().unwrap();
    let c = RefineCheck::new(&case, 777);
    let mut iso = c.geom.clone();
    iso.norm.extent = DVec3::splat(iso.norm.extent.max_element());
    let broken: [(&str, Box<HitsBackward>); 2] = [
        (
            "normalisation ignored",
            Box::new(|h: &[RayHit], dp: &[f64], dt: &mut [f64]| hits_backward(&iso, h, dp, dt)),
        ),
        (
            "hit moved along the normal",
            Box::new(|h: &[RayHit], dp: &[f64], dt: &mut [f64]| {
                let along_normal: Vec<RayHit> = h
                    .iter()
                    .map(|x| {
                        let n = x.n.normalize();
                        RayHit {
                            d: if n.dot(x.d) < 0.0 { -n } else { n },
                            ..*x
                        }
                    })
                    .collect();
                hits_backward(&c.geom, &along_normal, dp, dt)
            }),
        ),
    ];
    c.real_passes_broken_fail(&|h, dp, dt| hits_backward(&c.geom, h, dp, dt), &broken);
}

/// `[model.refine] anchored`: the grids are queried at the training mesh's point with the moved
/// hit's barycentrics, so ∂L/∂θ runs through the barycentrics of the re-intersection only
/// (`hits_backward_anchored`), against central differences of the loss recomputed from scratch.
#[test]
fn anchored_mesh_refinement_gradients_match_fd() {
    let mut rep = Report::default();
    for (ci, case) in cases().iter().enumerate() {
        let c = RefineCheck::new_anchored(case, 600 + ci as u64);
        let an = c.analytic(&|h, dp, dt| hits_backward_anchored(&c.geom, h, dp, dt));
        assert!(an.1.iter().filter(|&&g| g != 0.0).count() >= 10);
        c.check(&an, &mut rep, case.name);
    }
    rep.finish("anchored mesh refinement", 300);
}

/// The anchored check can fail: the unanchored gradient (features following the hit), the
/// anchored one with the per-axis normalisation left out, and with the moved triangle's edges
/// replaced by the training triangle's (no pull-back to the moved plane) disagree with it.
#[test]
fn broken_anchored_mesh_refinement_gradients_fail_the_check() {
    let case = cases().into_iter().next().unwrap();
    let c = RefineCheck::new_anchored(&case, 778);
    let mut iso = c.geom.clone();
    iso.norm.extent = DVec3::splat(iso.norm.extent.max_element());
    let broken: [(&str, Box<HitsBackward>); 3] = [
        (
            "unanchored gradient",
            Box::new(|h: &[RayHit], dp: &[f64], dt: &mut [f64]| hits_backward(&c.geom, h, dp, dt)),
        ),
        (
            "normalisation ignored",
            Box::new(|h: &[RayHit], dp: &[f64], dt: &mut [f64]| {
                hits_backward_anchored(&iso, h, dp, dt)
            }),
        ),
        (
            "no pull-back to the moved plane",
            Box::new(|h: &[RayHit], dp: &[f64], dt: &mut [f64]| {
                let flat: Vec<RayHit> = h
                    .iter()
                    .map(|x| {
                        let b = x.tri.map(|i| c.geom.base[i as usize]);
                        RayHit {
                            e: [b[1] - b[0], b[2] - b[0]],
                            ..*x
                        }
                    })
                    .collect();
                hits_backward_anchored(&c.geom, &flat, dp, dt)
            }),
        ),
    ];
    c.real_passes_broken_fail(
        &|h, dp, dt| hits_backward_anchored(&c.geom, h, dp, dt),
        &broken,
    );
}

// ---------------------------------------------------------------------------------------------
// The refinement's photo-consistency term (src/refine/photo.rs)
// ---------------------------------------------------------------------------------------------

use xscale::refine::photo::{
    measure, patch_eval, Neighbour, PatchEval, PatchPoint, PhotoCamera, PhotoImage, Scoring,
};

use xscale::refine::hit::plane_hit_chain;

use xscale::model::refine::PhotoMeasure;

/// A smooth RGB texture rasterised at integer pixels (values in ~[0.15, 0.85]).
fn photo_image(w: u32, h: u32, seed: u64) -> PhotoImage {
    let mut data = Vec::with_capacity((3 * w * h) as usize);
    for y in 0..h {
        for x in 0..w {
            for c in 0..3u64 {
                let (fx, fy) = (x as f64, y as f64);
                let p = 6.0 * u(seed, 900 + c, 0);
                let q = 6.0 * u(seed, 900 + c, 1);
                let v = 0.5
                    + 0.2 * (0.31 * fx + 0.23 * fy + p).sin()
                    + 0.15 * (0.17 * fx - 0.41 * fy + q).cos()
                    + 0.03 * sym(seed, 910 + c, (y * w + x) as u64);
                data.push(v as f32);
            }
        }
    }
    PhotoImage {
        width: w,
        height: h,
        data,
    }
}

/// Everything one photo-consistency gradient check needs: the sheet of the refinement checks,
/// offset parameters, a reference camera centre, patches of rays onto the sheet and the
/// neighbour view that sees them.
struct PhotoCheck {
    cfg: RefineConfig,
    geom: RefineGeom,
    grids: Vec<Vec<f64>>,
    r: Vec<f64>,
    origin: DVec3,
    patches: Vec<Vec<PatchPoint>>,
    cam: PhotoCamera,
    img: PhotoImage,
    measure: PhotoMeasure,
    weight: f64,
    base_cells: Vec<Vec<[i32; 2]>>,
}

impl PhotoCheck {
    fn new(m: PhotoMeasure, seed: u64) -> PhotoCheck {
        PhotoCheck::with_lens(m, seed, xscale::scene::Distortion::None)
    }

    /// The check with the neighbour camera's lens `distortion`.
    fn with_lens(m: PhotoMeasure, seed: u64, distortion: xscale::scene::Distortion) -> PhotoCheck {
        use xscale::scene::Camera;
        let (mesh, norm, cfg) = refine_scene();
        let geom = RefineGeom::new(&mesh, &norm);
        let (grids, r) = refine_params(&cfg, geom.n_vertices(), seed);
        let theta = RefineCheck::theta_of(&cfg, &geom, &grids, &r);
        // The sheet spans x 3…5, y −1…0.5 at z ≈ 10 (world); the reference camera looks down from
        // above and to the side, the neighbour from the other side.
        let target = DVec3::new(4.0, -0.25, 10.0);
        let eye_i = DVec3::new(3.2, -1.6, 13.5);
        let eye_j = DVec3::new(5.1, 0.9, 13.2);
        let (w, h) = (64u32, 48u32);
        let (rot, tr) = xscale::synth::cameras::look_at(eye_j, target, DVec3::Z);
        let cam = Camera {
            width: w,
            height: h,
            fx: 30.0,
            fy: 31.0,
            cx: 31.5,
            cy: 24.5,
            distortion,
            rotation: rot,
            translation: tr,
        };
        let cam = PhotoCamera::new(&cam, norm.center);
        let img = photo_image(w, h, seed);
        let origin = eye_i - norm.center;
        let mut patches = Vec::new();
        for p in 0..6u64 {
            let k = if m == PhotoMeasure::Huber && p % 2 == 0 {
                1
            } else {
                9
            };
            let mut pts = Vec::new();
            for q in 0..k as u64 {
                let tri = (u(seed, 920 + p, q) * geom.triangles.len() as f64) as usize;
                let [b1, b2] = random_bary(seed + 17 * p, q);
                let beta = [1.0 - b1 - b2, b1, b2];
                let x = (0..3).fold(DVec3::ZERO, |acc, c| {
                    let i = geom.triangles[tri][c] as usize;
                    acc + geom.position(i, theta[i]) * beta[c]
                });
                let d = (x - origin).normalize();
                let reference = std::array::from_fn(|c| {
                    (0.5 + 0.25 * sym(seed, 930 + p, 3 * q + c as u64)) as f32
                });
                pts.push(PatchPoint {
                    tri: tri as u32,
                    d,
                    reference,
                });
            }
            patches.push(pts);
        }
        let mut c = PhotoCheck {
            cfg,
            geom,
            grids,
            r,
            origin,
            patches,
            cam,
            img,
            measure: m,
            weight: 0.37,
            base_cells: Vec::new(),
        };
        let (_, cells) = c.eval(&c.grids.clone(), &c.r.clone());
        c.base_cells = cells;
        c
    }

    /// One patch's energy, gradient and cells at offsets `theta`.
    fn patch(&self, theta: &[f64], pts: &[PatchPoint]) -> PatchEval {
        let neighbour = Neighbour {
            cam: &self.cam,
            img: &self.img,
        };
        let scoring = Scoring {
            measure: self.measure,
            min_cos: self.cfg.min_cos,
            weight: self.weight,
        };
        patch_eval(&self.geom, theta, self.origin, pts, neighbour, scoring)
            .expect("every patch is seen by the neighbour")
    }

    /// Energy (photo + smoothness) and every sample's bilinear cell, from scratch.
    fn eval(&self, grids: &[Vec<f64>], r: &[f64]) -> (f64, Vec<Vec<[i32; 2]>>) {
        let theta = RefineCheck::theta_of(&self.cfg, &self.geom, grids, r);
        let mut e = 0.0;
        let mut cells = Vec::new();
        for pts in &self.patches {
            let ev = self.patch(&theta, pts);
            e += ev.energy;
            cells.push(ev.cells);
        }
        let mut scratch = vec![0.0; r.len()];
        e += smoothness(&self.cfg, &self.geom, r, &mut scratch);
        (e, cells)
    }

    /// ∂E/∂θ assembled from the public pieces (intersection, projection, bilinear sample,
    /// measure, hit-point chain), with one of them optionally broken.
    fn pieces(&self, theta: &[f64], broken: PhotoBroken) -> Vec<f64> {
        let mut d_theta = vec![0.0; theta.len()];
        for pts in &self.patches {
            let mut a = Vec::new();
            let mut b = Vec::new();
            let mut geo = Vec::new();
            for p in pts {
                let tri = self.geom.triangles[p.tri as usize];
                let v = tri.map(|i| self.geom.position(i as usize, theta[i as usize]));
                let (t, beta, n) = intersect(self.origin, p.d, v, self.cfg.min_cos).unwrap();
                let x = self.origin + p.d * t;
                let (pi, mut dpi) = self.cam.project(x).unwrap();
                if broken == PhotoBroken::PinholeJacobian {
                    let pinhole = PhotoCamera {
                        distortion: xscale::scene::Distortion::None,
                        ..self.cam.clone()
                    };
                    dpi = pinhole.project(x).unwrap().1;
                }
                if broken == PhotoBroken::NoPerspective {
                    dpi = [
                        self.cam.rot.row(0)
                            * (self.cam.fx / (self.cam.rot * (x - self.cam.origin)).z),
                        self.cam.rot.row(1)
                            * (self.cam.fy / (self.cam.rot * (x - self.cam.origin)).z),
                    ];
                }
                let s = self.img.sample(pi[0], pi[1]).unwrap();
                a.push(p.reference.map(|v| v as f64));
                b.push(s.rgb);
                geo.push((tri, beta, n, dpi, s));
            }
            let jb = vec![[0.0; 3]; pts.len()];
            let mut d_b = vec![[0.0; 3]; pts.len()];
            measure(self.measure, &a, &b, &jb, &mut d_b);
            for (q, p) in pts.iter().enumerate() {
                let (tri, beta, n, dpi, s) = &geo[q];
                let (mut gx, mut gy) = (0.0, 0.0);
                for (c, &db) in d_b[q].iter().enumerate() {
                    let (dx, dy) = if broken == PhotoBroken::SwappedImageGradient {
                        (s.dy[c], s.dx[c])
                    } else {
                        (s.dx[c], s.dy[c])
                    };
                    gx += db * dx;
                    gy += db * dy;
                }
                let g = (dpi[0] * gx + dpi[1] * gy) * self.weight;
                let d = if broken == PhotoBroken::AlongNormal {
                    let nn = n.normalize();
                    if nn.dot(p.d) < 0.0 {
                        -nn
                    } else {
                        nn
                    }
                } else {
                    p.d
                };
                for (i, v) in plane_hit_chain(&self.geom, *tri, *beta, *n, d, g) {
                    d_theta[i as usize] += v;
                }
            }
        }
        d_theta
    }

    /// Analytic gradients of the grids and the residual from `d_theta` (plus smoothness).
    fn to_params(&self, d_theta: &[f64]) -> (Vec<Vec<f64>>, Vec<f64>) {
        let nv = self.geom.n_vertices();
        let all: Vec<u32> = (0..nv as u32).collect();
        let mut d_grids: Vec<Vec<f64>> = self.grids.iter().map(|g| vec![0.0; g.len()]).collect();
        let mut d_r = vec![0.0; nv];
        field_backward(
            &self.cfg,
            &self.geom,
            &all,
            d_theta,
            Active {
                grids: self.grids.len(),
                residual: true,
            },
            &mut d_grids,
            &mut d_r,
        );
        smoothness(&self.cfg, &self.geom, &self.r, &mut d_r);
        (d_grids, d_r)
    }

    /// ∂E/∂θ from `patch_eval` itself.
    fn analytic(&self) -> Vec<f64> {
        let theta = RefineCheck::theta_of(&self.cfg, &self.geom, &self.grids, &self.r);
        let mut d_theta = vec![0.0; theta.len()];
        for pts in &self.patches {
            let ev = self.patch(&theta, pts);
            for (i, g) in ev.grad {
                d_theta[i as usize] += g;
            }
        }
        d_theta
    }

    fn check(&self, an: &(Vec<Vec<f64>>, Vec<f64>), rep: &mut Report, label: &str) {
        check_field(&self.grids, &self.r, an, rep, label, &|g, r| {
            let (f, cells) = self.eval(g, r);
            (cells == self.base_cells).then_some(f)
        });
    }
}

#[derive(Clone, Copy, Debug, PartialEq)]
enum PhotoBroken {
    None,
    NoPerspective,
    SwappedImageGradient,
    AlongNormal,
    /// The distorted projection with the pinhole projection's derivative.
    PinholeJacobian,
}

/// ∂E/∂(offset field) of the photo-consistency energy (zncc on 3×3 patches; huber on single
/// pixels and 3×3 patches) through the bilinear sample, the neighbour's projection, the
/// re-intersected hit points, the field's trilinear levels and the smoothness energy, against
/// central differences of the energy recomputed from scratch.
#[test]
fn photo_consistency_gradients_match_fd() {
    let mut rep = Report::default();
    for (mi, m) in [PhotoMeasure::Zncc, PhotoMeasure::Huber]
        .into_iter()
        .enumerate()
    {
        for s in 0..2u64 {
            let c = PhotoCheck::new(m, 700 + 10 * mi as u64 + s);
            let d = c.analytic();
            // The gradient assembled from the pieces is the same as patch_eval's.
            let theta = RefineCheck::theta_of(&c.cfg, &c.geom, &c.grids, &c.r);
            let p = c.pieces(&theta, PhotoBroken::None);
            for (x, y) in d.iter().zip(&p) {
                assert!((x - y).abs() <= 1e-12 * (1.0 + x.abs()), "{x} vs {y}");
            }
            let an = c.to_params(&d);
            assert!(an.1.iter().filter(|&&g| g != 0.0).count() >= 10);
            c.check(&an, &mut rep, m.name());
        }
    }
    rep.finish("photo consistency", 300);
}

/// The real photo-consistency gradient of `c` passes the check (the control of the tests that
/// break it); returns the offsets θ it was checked at and the number of checks made.
fn real_photo_gradient_passes(c: &PhotoCheck) -> (Vec<f64>, usize) {
    let theta = RefineCheck::theta_of(&c.cfg, &c.geom, &c.grids, &c.r);
    let mut ok = Report::default();
    c.check(
        &c.to_params(&c.pieces(&theta, PhotoBroken::None)),
        &mut ok,
        "real",
    );
    assert!(
        ok.fails.is_empty(),
        "the real gradient fails: {:?}",
        &ok.fails[..ok.fails.len().min(5)]
    );
    (theta, ok.checked)
}

/// The photo check can fail: the projection's derivative without its perspective term, the image
/// gradient's x and y swapped, and the hit moved along the triangle's normal instead of its ray
/// each disagree with the finite differences, while the real gradient passes.
#[test]
fn broken_photo_consistency_gradients_fail_the_check() {
    let c = PhotoCheck::new(PhotoMeasure::Zncc, 790);
    let (theta, real_checked) = real_photo_gradient_passes(&c);
    for b in [
        PhotoBroken::NoPerspective,
        PhotoBroken::SwappedImageGradient,
        PhotoBroken::AlongNormal,
    ] {
        let mut bad = Report::default();
        c.check(&c.to_params(&c.pieces(&theta, b)), &mut bad, "broken");
        assert!(
            bad.fails.len() * 3 >= bad.checked,
            "{b:?}: only {} of {} checks failed",
            bad.fails.len(),
            bad.checked
        );
        eprintln!(
            "{b:?}: {} of {} photo checks fail; the real gradient: 0 of {}",
            bad.fails.len(),
            bad.checked,
            real_checked
        );
    }
}

/// The lenses of the distorted photo checks: the models xscale loads (SPEC §3.3), with
/// coefficients of real phone, drone and fisheye lenses' size (the neighbour's normalised
/// coordinates reach |x| ≈ 1 in the check, where these bend the image by several pixels).
fn check_lenses() -> Vec<xscale::scene::Distortion> {
    use xscale::scene::Distortion as D;
    vec![
        D::OpenCv {
            k1: -0.21,
            k2: 0.07,
            p1: 0.0031,
            p2: -0.0024,
        },
        D::FullOpenCv {
            k: [-0.18, 0.05, -0.01, 0.02, -0.004, 0.001],
            p1: -0.002,
            p2: 0.0015,
        },
        D::Brown {
            k: [-0.12, 0.03, -0.004, 0.0005],
            p1: 0.001,
            p2: -0.0012,
            skew: 0.0008,
        },
        D::Radial {
            k1: 0.09,
            k2: -0.02,
        },
        D::Fisheye {
            k: [0.03, -0.011, 0.002, -0.0003],
        },
        D::ThinPrismFisheye {
            k: [0.02, -0.01, 0.001, 0.0],
            p1: 0.001,
            p2: -0.0007,
            sx1: 0.0009,
            sy1: -0.0005,
        },
        D::RadTanThinPrismFisheye {
            k: [0.02, -0.006, 0.001, 0.0, 0.0, 0.0],
            p: [0.0008, -0.0006],
            s: [0.0004, -0.0002, 0.0003, 0.0001],
        },
        D::Fov { omega: 0.9 },
        D::Division { k: -0.08 },
    ]
}

/// ∂E/∂(offset field) of the photo-consistency energy through a lens-distorted neighbour view
/// (every model xscale loads): the projection's derivative chained through the distortion's
/// exact Jacobian, against central differences of the energy recomputed from scratch.
#[test]
fn photo_consistency_gradients_through_lens_distortion_match_fd() {
    let mut rep = Report::default();
    for (li, lens) in check_lenses().into_iter().enumerate() {
        let m = if li % 2 == 0 {
            PhotoMeasure::Zncc
        } else {
            PhotoMeasure::Huber
        };
        let c = PhotoCheck::with_lens(m, 740 + li as u64, lens);
        let d = c.analytic();
        let theta = RefineCheck::theta_of(&c.cfg, &c.geom, &c.grids, &c.r);
        let p = c.pieces(&theta, PhotoBroken::None);
        for (x, y) in d.iter().zip(&p) {
            assert!((x - y).abs() <= 1e-12 * (1.0 + x.abs()), "{x} vs {y}");
        }
        let an = c.to_params(&d);
        assert!(an.1.iter().filter(|&&g| g != 0.0).count() >= 10);
        c.check(&an, &mut rep, &format!("{lens:?}"));
    }
    rep.finish("photo consistency through lenses", 300);
}

/// The lens check can fail: the distorted projection with the pinhole derivative (the
/// distortion's Jacobian left out) disagrees with the finite differences.
#[test]
fn photo_gradient_without_the_lens_jacobian_fails_the_check() {
    let lens = check_lenses()[0];
    let c = PhotoCheck::with_lens(PhotoMeasure::Zncc, 795, lens);
    let (theta, _) = real_photo_gradient_passes(&c);
    let mut bad = Report::default();
    c.check(
        &c.to_params(&c.pieces(&theta, PhotoBroken::PinholeJacobian)),
        &mut bad,
        "pinhole jacobian",
    );
    assert!(
        bad.fails.len() * 3 >= bad.checked,
        "only {} of {} checks failed",
        bad.fails.len(),
        bad.checked
    );
}
