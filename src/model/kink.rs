//! Kinks of a forward pass, and how much a correct backend's gradients may differ because of them
//! (`xscale dump`'s `kink.*` tensors, `xscale compare`'s kink slack, `docs/oracle.md` §7).
//!
//! The model is continuous but its gradient is not: a ReLU unit's derivative jumps from 0 to 1
//! where its pre-activation crosses 0, and L1's from −1 to +1 where a residual does. A backend
//! whose arithmetic is correct to its own precision evaluates a pre-activation with an error of
//! up to a few units of that precision times the sum of the magnitudes of its terms; when the
//! oracle's value lies within that distance of 0, the backend may stand on the other side of the
//! kink, and its gradients then differ from the oracle's by the whole gradient that flows through
//! that unit — far beyond any rounding tolerance (seen on a fresh `cpu` checkpoint: a shader unit
//! at −2.75e-8 against a term-magnitude sum of 0.54 moved `grad.batch.dirs` by 5e-2 of its peak).
//!
//! **Margin.** For each ReLU unit and row (the shader per pixel; ξ per valid sub-sample, assigned
//! to its pixel) the *relative margin* is `|pre| / (|b| + Σ_j |W_j x_j|)` with `pre = b + Σ_j W_j
//! x_j`, all in f64 from the forward's own inputs; for L1 it is `|r| / max(|rgb|, |target|)` per
//! channel. A pixel's margin is the smallest over its units and channels (1 if it has none). The
//! sum of term magnitudes is the scale of the rounding error of any evaluation order, so a
//! precision with unit roundoff `u` and dot products of `n` terms can cross a kink only where the
//! margin is below about `n·u` (times the depth of the inputs' own errors).
//!
//! **Slack.** For every *kink site* (a unit or residual of a pixel with margin ≤ a threshold) the
//! gradients are computed a second time with that one site on the other side of its kink (a ReLU
//! output that is 0 is set to the smallest positive normal so its gate opens, a positive one to 0
//! so it closes; an L1 residual is mirrored about 0); the site's slack is `|G_toggled − G|` for
//! every gradient element, and slacks add over sites. A backend that flipped any subset of the
//! sites differs from the oracle by at most the sum of their slacks, plus its ordinary rounding:
//! exactly for sites of different pixels (pixels meet only in sums into shared gradients) and
//! for units of one layer (a gate changes only what flows through its own unit), to first order
//! for units of different layers of one pixel. The forward values change by at most the margin, so they
//! need no slack. The toggled forward is not re-evaluated: the flipped units' outputs differ from
//! the reference's by at most `|pre|`, which is what a backend on the other side computes.

use crate::model::batch::Batch;
use crate::model::config::LossKind;
use crate::model::hfm::{ChunkFwd, Forward, Hfm};
use crate::model::mlp::{Mlp, MlpActs};
use crate::model::params::Grads;
use crate::model::Real;

/// The default kink threshold of `xscale dump`: 2^-16 relative margin (256 f32 unit roundoffs, the
/// f32 tolerance file's gradient limit; ~10× the worst forward error measured in f32).
pub const DEFAULT_THRESHOLD: f64 = 1.0 / 65536.0;

/// One place where a pixel's gradient has a kink.
#[derive(Clone, Copy, Debug, PartialEq)]
enum Site {
    /// Shader hidden layer `layer`, chunk-local pixel row `row`, unit `unit`.
    Shader {
        layer: usize,
        row: usize,
        unit: usize,
    },
    /// ξ hidden layer `layer`, chunk-local sub-sample row `row`, unit `unit`.
    Deform {
        layer: usize,
        row: usize,
        unit: usize,
    },
    /// L1 residual of chunk-local pixel row `row`, channel `ch`.
    Loss { row: usize, ch: usize },
}

/// Every kink of one pixel with its relative margin.
#[derive(Clone, Debug, Default)]
struct PixelKinks {
    chunk: usize,
    sites: Vec<(Site, f64)>,
}

/// The kinks of a forward pass: per pixel, its smallest relative margin, and the sites below a
/// threshold.
#[derive(Clone, Debug)]
pub struct Kinks {
    /// `[N]` each pixel's smallest relative margin (module doc); 1 for a pixel without kinks.
    pub margin: Vec<f64>,
    /// The threshold that makes a kink pixel.
    pub threshold: f64,
    per_pixel: Vec<PixelKinks>,
}

/// `(|pre|, |b| + Σ|W x|)` of every unit of every hidden layer of `mlp` over `rows` rows of `x`.
/// Calls `f(layer, row, unit, relative margin)`.
fn relu_margins<R: Real>(
    mlp: &Mlp,
    p: &[R],
    x: &[R],
    acts: &MlpActs<R>,
    rows: usize,
    mut f: impl FnMut(usize, usize, usize, f64),
) {
    for (k, l) in mlp.layers[..mlp.layers.len() - 1].iter().enumerate() {
        let input: &[R] = if k == 0 { x } else { &acts.hidden[k - 1] };
        for r in 0..rows {
            let xr = &input[r * l.in_dim..(r + 1) * l.in_dim];
            for o in 0..l.out_dim {
                let w = &p[l.w_off + o * l.in_dim..l.w_off + (o + 1) * l.in_dim];
                let b = l.b_off.map_or(0.0, |b| p[b + o].to_f64());
                let (mut pre, mut mag) = (b, b.abs());
                for (wj, xj) in w.iter().zip(xr) {
                    let t = wj.to_f64() * xj.to_f64();
                    pre += t;
                    mag += t.abs();
                }
                let m = if mag > 0.0 { pre.abs() / mag } else { 1.0 };
                f(k, r, o, m);
            }
        }
    }
}

impl Kinks {
    /// Find the kinks of `fwd` (the forward of `params` on `batch`); sites whose margin is at most
    /// `threshold` are kept for [`Kinks::slack`].
    pub fn find<R: Real>(
        model: &Hfm,
        params: &[R],
        batch: &Batch,
        fwd: &Forward<R>,
        threshold: f64,
    ) -> Kinks {
        let n = batch.n_pixels();
        let mut margin = vec![1.0f64; n];
        let mut per_pixel = vec![PixelKinks::default(); n];
        let mut note = |pixel: usize, chunk: usize, site: Site, m: f64| {
            margin[pixel] = margin[pixel].min(m);
            if m <= threshold {
                per_pixel[pixel].chunk = chunk;
                per_pixel[pixel].sites.push((site, m));
            }
        };
        let shader_p = &params[model.r_shader.clone()];
        for (ci, c) in fwd.chunks.iter().enumerate() {
            let rows = c.pixels.len();
            relu_margins(
                &model.shader,
                shader_p,
                &c.shader_in,
                &c.shader,
                rows,
                |layer, row, unit, m| {
                    note(
                        c.pixels.start + row,
                        ci,
                        Site::Shader { layer, row, unit },
                        m,
                    )
                },
            );
            if let Some(mlp) = &model.deform {
                let deform_p = &params[model.r_deform.clone()];
                let v = c.samples.len();
                relu_margins(
                    mlp,
                    deform_p,
                    &c.deform_in,
                    &c.deform,
                    v,
                    |layer, row, unit, m| {
                        let pixel = pixel_of_sample(fwd, c, c.samples.start + row);
                        note(pixel, ci, Site::Deform { layer, row, unit }, m)
                    },
                );
            }
            if model.cfg.loss == LossKind::L1 {
                for row in 0..rows {
                    let t = batch.target[c.pixels.start + row];
                    for (ch, &tc) in t.iter().enumerate() {
                        let y = c.rgb[row * 3 + ch].to_f64();
                        let tc = tc as f64;
                        let scale = y.abs().max(tc.abs());
                        let m = if scale > 0.0 {
                            (y - tc).abs() / scale
                        } else {
                            0.0
                        };
                        note(c.pixels.start + row, ci, Site::Loss { row, ch }, m);
                    }
                }
            }
        }
        Kinks {
            margin,
            threshold,
            per_pixel,
        }
    }

    /// The kink pixels (margin ≤ threshold), ascending.
    pub fn pixels(&self) -> Vec<usize> {
        (0..self.margin.len())
            .filter(|&p| !self.per_pixel[p].sites.is_empty())
            .collect()
    }

    /// The slack of every gradient (module doc): `|G_toggled(site) − G|` summed over every site
    /// of every kink pixel, in a [`Grads`] laid out like `grads` (`grads` = the gradients of
    /// `fwd`, with inputs). A site changes only its own pixel's contribution to the gradients, so
    /// each kink pixel is evaluated alone (a one-pixel batch: one forward, then one backward for
    /// its own sides and one per site, the difference divided by N to give the batch's
    /// normalisation) instead of one backward of the whole batch per site.
    pub fn slack<R: Real>(
        &self,
        model: &Hfm,
        params: &[R],
        batch: &Batch,
        fwd: &Forward<R>,
        grads: &Grads<R>,
    ) -> Grads<R> {
        let mut slack = Grads::<R>::new(&model.layout);
        slack.positions = vec![R::ZERO; grads.positions.len()];
        slack.dirs = vec![R::ZERO; grads.dirs.len()];
        let s = batch.samples_per_pixel();
        let inv_n = R::ONE / R::from_f64(batch.n_pixels() as f64);
        let (fh, fd) = model.grid_features();
        // Reused buffers, zeroed where the last backward wrote (the touched table rows): a
        // one-pixel backward costs what the pixel touches, not the table size.
        let mut base = Grads::<R>::new(&model.layout);
        let mut g = Grads::<R>::new(&model.layout);
        for p in self.pixels() {
            let k = &self.per_pixel[p];
            let sub = one_pixel(batch, p);
            let fwd1 = model
                .forward(params, &sub)
                .expect("a pixel of a valid batch is a valid batch");
            base.zero_sparse(&model.layout, fh, fd);
            model.backward(params, &sub, &fwd1, &mut base);
            // The pixel's first compacted sub-sample, relative to its chunk in `fwd`.
            let first = fwd.start[p] - fwd.chunks[k.chunk].samples.start;
            for &(site, _) in &k.sites {
                let mut toggled = fwd1.clone();
                let c = &mut toggled.chunks[0];
                match site {
                    Site::Shader { layer, unit, .. } => {
                        flip_relu(&mut c.shader.hidden[layer][unit]);
                    }
                    Site::Deform { layer, row, unit } => {
                        let w = model.deform.as_ref().unwrap().layers[layer].out_dim;
                        flip_relu(&mut c.deform.hidden[layer][(row - first) * w + unit]);
                    }
                    Site::Loss { ch, .. } => {
                        let t = R::from_f32(sub.target[0][ch]);
                        let y = &mut c.rgb[ch];
                        *y = t - (*y - t);
                    }
                }
                g.zero_sparse(&model.layout, fh, fd);
                model.backward(params, &sub, &toggled, &mut g);
                // Every element either backward can have written, once (a table row whose
                // gradient is exactly 0 is not recorded as touched, so both sides' rows count).
                let mut reach = written(model, &base);
                reach.extend(written(model, &g));
                reach.sort_unstable();
                reach.dedup();
                for i in reach {
                    slack.params[i] += (g.params[i] - base.params[i]).abs() * inv_n;
                }
                add_abs_diff(
                    &mut slack.positions[p * s * 3..(p + 1) * s * 3],
                    &g.positions,
                    &base.positions,
                    inv_n,
                );
                add_abs_diff(
                    &mut slack.dirs[p * 3..p * 3 + 3],
                    &g.dirs,
                    &base.dirs,
                    inv_n,
                );
            }
        }
        slack
    }

    /// Sites at or below the threshold, over all pixels (one backward each in [`Kinks::slack`]).
    pub fn sites(&self) -> usize {
        self.per_pixel.iter().map(|k| k.sites.len()).sum()
    }
}

/// A ReLU output on the other side of its kink: 0 ↦ the smallest positive normal (the gate opens,
/// the value is negligible), positive ↦ 0.
fn flip_relu<R: Real>(h: &mut R) {
    *h = if *h > R::ZERO {
        R::ZERO
    } else {
        R::from_f64(f64::from(f32::MIN_POSITIVE))
    };
}

/// `acc += |a − b| · scale`.
fn add_abs_diff<R: Real>(acc: &mut [R], a: &[R], b: &[R], scale: R) {
    for ((s, x), y) in acc.iter_mut().zip(a).zip(b) {
        *s += (*x - *y).abs() * scale;
    }
}

/// Flat parameter indices a backward can have written into `g`: every tensor outside the grid
/// and vertex tables whole, those tables at their touched rows.
fn written<R>(model: &Hfm, g: &Grads<R>) -> Vec<usize> {
    use crate::model::params::Group;
    let (fh, fd) = model.grid_features();
    let mut out = Vec::new();
    for t in &model.layout.tensors {
        let (touched, f) = match t.group {
            Group::GridH => (&g.touched_h, fh),
            Group::GridD => (&g.touched_d, fd),
            Group::Vertex => (&g.touched_v, t.shape[1]),
            _ => {
                out.extend(t.range());
                continue;
            }
        };
        for &e in &touched.entries {
            let e0 = t.offset + e as usize * f;
            out.extend(e0..e0 + f);
        }
    }
    out
}

/// The one-pixel batch of pixel `p`.
fn one_pixel(batch: &Batch, p: usize) -> Batch {
    let s = batch.samples_per_pixel();
    let r = p * s..(p + 1) * s;
    let part = |v: &[[f64; 2]]| {
        if v.is_empty() {
            Vec::new()
        } else {
            v[r.clone()].to_vec()
        }
    };
    Batch {
        positions: batch.positions[r.clone()].to_vec(),
        valid: batch.valid[r.clone()].to_vec(),
        dirs: vec![batch.dirs[p]],
        view: vec![batch.view[p]],
        target: vec![batch.target[p]],
        footprint: batch.footprint.get(p).map(|&f| vec![f]).unwrap_or_default(),
        triangle: if batch.triangle.is_empty() {
            Vec::new()
        } else {
            batch.triangle[r.clone()].to_vec()
        },
        bary: part(&batch.bary),
        ..Batch::default()
    }
}

/// The pixel of compacted sub-sample `idx` (which lies in chunk `c`).
fn pixel_of_sample<R>(fwd: &Forward<R>, c: &ChunkFwd<R>, idx: usize) -> usize {
    let px = &fwd.start[c.pixels.start..=c.pixels.end];
    c.pixels.start + px.partition_point(|&s| s <= idx) - 1
}
