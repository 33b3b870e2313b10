//! What a backend must produce for a checkpoint and a batch (`xscale case`'s `manifest.json`, the
//! Python package's `Model.manifest`): every tensor of the oracle's dump with its shape, dtype and
//! meaning, which of them a comparison requires, and the model's switches — which a backend may
//! turn on, which tiny-cuda-nn can reproduce, and which tensors each adds or removes.
//!
//! The tensor list is read off a real dump ([`crate::model::checkpoint::dump_with`]), so it
//! cannot disagree with what `xscale dump` writes; the switches' effects likewise come from dumps
//! of the model with the switch flipped (on a one-pixel batch).

use crate::io::tensors::TensorFile;
use crate::model::batch::Batch;
use crate::model::checkpoint::{dump_with, init_checkpoint, Checkpoint};
use crate::model::config::{Interpolation, LevelWeight, LossKind, ModelConfig, PositionMode};
use anyhow::Result;
use serde::Serialize;
use std::collections::BTreeMap;

/// One tensor of a dump.
#[derive(Clone, Debug, Serialize, PartialEq)]
pub struct Entry {
    pub name: String,
    pub shape: Vec<usize>,
    /// The oracle's dtype (`F64` in an f64 dump). A backend writes floats as F32 or F64 (compare
    /// widens both); `batch.*` and the echoed parameters keep their dtypes exactly.
    pub dtype: String,
    /// `batch`, `forward`, `loss`, `gradient` or `parameter`.
    pub kind: &'static str,
    /// Whether the built-in tolerance sets require it in a backend's dump.
    pub required: bool,
    pub meaning: String,
}

/// One switch of the model config and what it does to a backend's work.
#[derive(Clone, Debug, Serialize, PartialEq)]
pub struct Switch {
    /// The config key (`[model]` table of a run config).
    pub key: &'static str,
    /// Its value in this checkpoint.
    pub value: String,
    /// The other value(s) a backend may meet.
    pub other: String,
    /// Whether tiny-cuda-nn (fp32) can reproduce the oracle with this switch at `value`.
    pub tcnn_reproducible: bool,
    /// Tensors the other value adds to the dump (name and shape at this batch's N and S).
    pub other_adds: Vec<(String, Vec<usize>)>,
    /// Tensors the other value removes from the dump.
    pub other_removes: Vec<(String, Vec<usize>)>,
    pub note: &'static str,
}

/// The meaning of a dump tensor (SPEC §6.4), by name.
pub fn meaning(name: &str) -> String {
    let fixed = match name {
        "batch.positions" => "normalised sub-sample positions x_n (copy unchanged; invalid rows are ignored)",
        "batch.valid" => "1 = the sub-sample hit the mesh; only valid sub-samples are evaluated (copy unchanged)",
        "batch.dirs" => "unit view direction of each pixel (copy unchanged)",
        "batch.view" => "appearance row of each pixel, -1 = the mean of all rows (copy unchanged)",
        "batch.target" => "target RGB of each pixel (copy unchanged)",
        "batch.footprint" => "pixel footprint in normalised units, read only by level_weight = \"footprint\" (copy unchanged)",
        "batch.triangle" | "batch.bary" => "vertex featurization only: hit triangle / barycentrics (copy unchanged)",
        "fwd.grid_h" => "F_H(x_j): grid H at each valid sub-sample, level-major then feature (Eq. 2); invalid rows 0",
        "fwd.vertex" => "F_V(x_j): vertex features interpolated at each valid sub-sample (Fig. 2b); invalid rows 0",
        "fwd.grid_d" => "F_D(x_j): deformation grid D at each valid sub-sample; invalid rows 0",
        "fwd.deform" => "xi's output delta_j, added to F_H(x_j) before pooling (Eq. 5); invalid rows 0",
        "fwd.pooled" => "mean over the pixel's valid sub-samples of F_H + delta (Eq. 4)",
        "fwd.sh" => "SH(d): degree-4 real spherical harmonics of batch.dirs, tiny-cuda-nn's order (SPEC §4.3)",
        "fwd.shader_in" => "the shader's input [pooled, SH(d), appearance code]",
        "fwd.logits" => "the shader's linear output, before the sigmoid",
        "fwd.rgb" => "sigmoid(logits) (Eq. 3)",
        "loss" => "mean over pixels and channels of the loss (SPEC §4.7)",
        "grad.batch.positions" => "dL/dx_n: grid H's and grid D's position gradients; invalid rows 0",
        "grad.batch.dirs" => "dL/dd through SH(d) (shader and xi parts)",
        "grid_h.scales" | "grid_d.scales" => "per-level scale_l: use these, never recompute (docs/oracle.md §6)",
        "grid_h.offsets" | "grid_d.offsets" => "first table entry of each level, then the total (tiny-cuda-nn's offset table)",
        "grid_h.table" => "hash table of grid H [entries, F], level-major, then entry, then feature",
        "grid_d.table" => "hash table of grid D [entries, F]",
        "appearance.codes" => "one appearance code per training view",
        _ => "",
    };
    if !fixed.is_empty() {
        return fixed.to_string();
    }
    if let Some(i) = name.strip_prefix("fwd.deform_hidden.") {
        return format!("xi's hidden layer {i} after ReLU, per valid sub-sample; invalid rows 0");
    }
    if let Some(i) = name.strip_prefix("fwd.shader_hidden.") {
        return format!("the shader's hidden layer {i} after ReLU");
    }
    if let Some(p) = name.strip_prefix("grad.") {
        return format!("dL/d {p} (the loss as defined, unscaled)");
    }
    if name.ends_with(".weight") {
        return "linear layer weight [out, in], y = W x".to_string();
    }
    if name.ends_with(".bias") {
        return "linear layer bias [out] (shader.bias = true)".to_string();
    }
    String::new()
}

fn kind_of(name: &str) -> &'static str {
    if name.starts_with("batch.") {
        "batch"
    } else if name.starts_with("fwd.") {
        "forward"
    } else if name == "loss" {
        "loss"
    } else if name.starts_with("grad.") {
        "gradient"
    } else {
        "parameter"
    }
}

/// The entries of a dump (its `kink.*` tensors, which only the oracle writes, left out).
pub fn entries(dump: &TensorFile) -> Vec<Entry> {
    let mut out: Vec<Entry> = dump
        .tensors
        .iter()
        .filter(|(k, _)| !crate::io::compare::is_kink_meta(k))
        .map(|(k, t)| {
            let kind = kind_of(k);
            Entry {
                name: k.clone(),
                shape: t.shape.clone(),
                dtype: t.dtype.name().to_string(),
                kind,
                required: kind != "parameter",
                meaning: meaning(k),
            }
        })
        .collect();
    let rank = |k: &str| match k {
        "batch" => 0,
        "forward" => 1,
        "loss" => 2,
        "gradient" => 3,
        _ => 4,
    };
    out.sort_by_key(|e| rank(e.kind));
    out
}

fn names(f: &TensorFile) -> BTreeMap<String, Vec<usize>> {
    f.tensors
        .iter()
        .filter(|(k, _)| !crate::io::compare::is_kink_meta(k))
        .map(|(k, t)| (k.clone(), t.shape.clone()))
        .collect()
}

/// The dump names (and shapes) of a model with config `cfg` on `batch`'s first pixel, with N
/// and S of the whole batch substituted into the batch axes.
fn names_for(cfg: &ModelConfig, batch: &Batch) -> Result<BTreeMap<String, Vec<usize>>> {
    let mut cfg = cfg.clone();
    // The mesh refinement's state is not part of a backend's step (and needs the mesh).
    cfg.refine = Default::default();
    let cfg = &cfg;
    let views = if cfg.appearance_dim > 0 {
        cfg.appearance_views.max(1) as usize
    } else {
        0
    };
    let ck = init_checkpoint(cfg, 0, crate::scene::Normalization::unit(), views)?;
    let s = batch.samples_per_pixel();
    let mut one = Batch {
        positions: batch.positions[..s].to_vec(),
        valid: batch.valid[..s].to_vec(),
        dirs: batch.dirs[..1].to_vec(),
        view: vec![if views > 0 { 0 } else { -1 }],
        target: batch.target[..1].to_vec(),
        footprint: batch
            .footprint
            .get(..1)
            .map(<[f32]>::to_vec)
            .unwrap_or_default(),
        ..Batch::default()
    };
    if cfg.level_weight == LevelWeight::Footprint && one.footprint.is_empty() {
        one.footprint = vec![0.0];
    }
    let n = batch.n_pixels();
    let mut out = names(&dump_with::<f32>(&ck, &one, None)?);
    for (k, shape) in out.iter_mut() {
        if (k.starts_with("batch.") || k.starts_with("fwd.") || k.starts_with("grad.batch."))
            && !shape.is_empty()
        {
            shape[0] = n;
        }
    }
    Ok(out)
}

/// What flipping a switch adds and removes (names with shapes at the batch's N, S).
type Diff = (Vec<(String, Vec<usize>)>, Vec<(String, Vec<usize>)>);

fn diff(base: &BTreeMap<String, Vec<usize>>, other: &BTreeMap<String, Vec<usize>>) -> Diff {
    let adds = other
        .iter()
        .filter(|(k, _)| !base.contains_key(*k))
        .map(|(k, s)| (k.clone(), s.clone()))
        .collect();
    let removes = base
        .iter()
        .filter(|(k, _)| !other.contains_key(*k))
        .map(|(k, s)| (k.clone(), s.clone()))
        .collect();
    (adds, removes)
}

/// The model's switches and their effect on a backend (see the module doc).
pub fn switches(ckpt: &Checkpoint, batch: &Batch) -> Result<Vec<Switch>> {
    let cfg = &ckpt.model.cfg;
    anyhow::ensure!(
        cfg.featurization.is_hash(),
        "the vertex featurization is the Fig. 2b baseline, not a model a backend reproduces: no manifest"
    );
    let base = names_for(cfg, batch)?;
    let flipped = |f: &dyn Fn(&mut ModelConfig)| -> Result<Diff> {
        let mut c = cfg.clone();
        f(&mut c);
        Ok(diff(&base, &names_for(&c, batch)?))
    };
    let mut out = Vec::new();
    let onoff = |b: bool| if b { "true" } else { "false" }.to_string();

    let (adds, removes) = flipped(&|c| c.deform.enabled = !c.deform.enabled)?;
    out.push(Switch {
        key: "model.deform.enabled",
        value: onoff(cfg.deform.enabled),
        other: onoff(!cfg.deform.enabled),
        tcnn_reproducible: true,
        other_adds: adds,
        other_removes: removes,
        note: "the manifold deformation xi (Eq. 5): grid D (a second tcnn HashGrid) and a 1-hidden-layer ReLU MLP (pad a hidden width below 16 with zero rows/columns for FullyFusedMLP)",
    });
    let (adds, removes) = flipped(&|c| c.shader.bias = !c.shader.bias)?;
    out.push(Switch {
        key: "model.shader.bias",
        value: onoff(cfg.shader.bias),
        other: onoff(!cfg.shader.bias),
        tcnn_reproducible: !cfg.shader.bias,
        other_adds: adds,
        other_removes: removes,
        note: "biases on every linear layer of the shader and of xi (one switch for both); tiny-cuda-nn's MLPs have none",
    });
    let a_other = if cfg.appearance_dim > 0 { 0 } else { 4 };
    let (adds, removes) = flipped(&|c| c.appearance_dim = a_other)?;
    out.push(Switch {
        key: "model.appearance_dim",
        value: cfg.appearance_dim.to_string(),
        other: a_other.to_string(),
        tcnn_reproducible: true,
        other_adds: adds,
        other_removes: removes,
        note: "per-view appearance codes appended to the shader input (view -1 = the mean code); plain tensor code, not a tcnn op",
    });
    out.push(Switch {
        key: "model.positions",
        value: match cfg.positions {
            PositionMode::Tcnn => "tcnn",
            PositionMode::F64 => "f64",
        }
        .into(),
        other: match cfg.positions {
            PositionMode::Tcnn => "f64",
            PositionMode::F64 => "tcnn",
        }
        .into(),
        tcnn_reproducible: cfg.positions == PositionMode::Tcnn,
        other_adds: vec![],
        other_removes: vec![],
        note: "\"tcnn\": x rounded to f32, p = fma(scale, x, 0.5) in f32, as tiny-cuda-nn (required for an fp32 tcnn backend); \"f64\" computes p in f64, which an f32-position backend cannot reproduce on fine levels (docs/oracle.md §5)",
    });
    out.push(Switch {
        key: "model.level_weight",
        value: match cfg.level_weight {
            LevelWeight::None => "none",
            LevelWeight::Footprint => "footprint",
        }
        .into(),
        other: match cfg.level_weight {
            LevelWeight::None => "footprint",
            LevelWeight::Footprint => "none",
        }
        .into(),
        tcnn_reproducible: cfg.level_weight == LevelWeight::None,
        other_adds: vec![],
        other_removes: vec![],
        note: "\"footprint\" (the cpu preset's default, beyond the paper) scales grid H's levels by the pixel footprint (SPEC §4.10) and reads batch.footprint; no tiny-cuda-nn equivalent and no independent reference: compare with it off",
    });
    let interp = |i: Interpolation| match i {
        Interpolation::Linear => "linear",
        Interpolation::Smoothstep => "smoothstep",
    };
    out.push(Switch {
        key: "model.grid_h.interpolation",
        value: interp(cfg.grid_h.interpolation).into(),
        other: "linear | smoothstep".into(),
        tcnn_reproducible: true,
        other_adds: vec![],
        other_removes: vec![],
        note: "tcnn \"interpolation\": \"Linear\" | \"Smoothstep\" (grid D has its own key, model.deform.grid.interpolation)",
    });
    out.push(Switch {
        key: "model.loss",
        value: match cfg.loss {
            LossKind::L1 => "l1",
            LossKind::L2 => "l2",
            LossKind::SmoothL1 => "smooth_l1",
        }
        .into(),
        other: "l1 | l2 | smooth_l1 (model.smooth_l1_delta)".into(),
        tcnn_reproducible: true,
        other_adds: vec![],
        other_removes: vec![],
        note:
            "written in the backend's tensor code (mean over pixels and channels; L2 without 1/2)",
    });
    out.push(Switch {
        key: "model.gamma",
        value: cfg.gamma.to_string(),
        other: "any integer >= 1".into(),
        tcnn_reproducible: true,
        other_adds: vec![],
        other_removes: vec![],
        note: "gamma^2 sub-samples per pixel (the S axis); pooling divides by the pixel's VALID sub-samples",
    });
    Ok(out)
}

/// [`manifest_json`] without a dump at hand: the tensor list from a dump of `batch`'s first
/// pixels, with N set to the whole batch's.
pub fn manifest_for(
    ckpt: &Checkpoint,
    batch: &Batch,
    files: &BTreeMap<&str, String>,
) -> Result<serde_json::Value> {
    let n = batch.n_pixels();
    let m = n.min(8);
    let s = batch.samples_per_pixel();
    let mut few = batch.clone();
    few.positions.truncate(m * s);
    few.valid.truncate(m * s);
    few.dirs.truncate(m);
    few.view.truncate(m);
    few.target.truncate(m);
    few.footprint.truncate(m);
    few.triangle.truncate(m * s);
    few.bary.truncate(m * s);
    let mut dump = dump_with::<f64>(ckpt, &few, None)?;
    for (k, t) in dump.tensors.iter_mut() {
        if (k.starts_with("batch.") || k.starts_with("fwd.") || k.starts_with("grad.batch."))
            && !t.shape.is_empty()
        {
            t.shape[0] = n;
        }
    }
    manifest_json(ckpt, batch, &dump, files)
}

/// The whole manifest as JSON: the tensors of `dump` and the switches of `ckpt`.
pub fn manifest_json(
    ckpt: &Checkpoint,
    batch: &Batch,
    dump: &TensorFile,
    files: &BTreeMap<&str, String>,
) -> Result<serde_json::Value> {
    let cfg = &ckpt.model.cfg;
    Ok(serde_json::json!({
        "format": "xscale-case-1",
        "files": files,
        "pixels": batch.n_pixels(),
        "samples_per_pixel": batch.samples_per_pixel(),
        "config": toml::to_string(cfg)?,
        "tcnn_reproducible": cfg.positions == PositionMode::Tcnn
            && cfg.level_weight == LevelWeight::None
            && !cfg.shader.bias
            && cfg.featurization.is_hash(),
        "tensors": entries(dump),
        "switches": switches(ckpt, batch)?,
        "notes": [
            "Write every tensor marked required under its name (floats as F32 or F64): batch.* copied unchanged, fwd.*, loss, grad.*.",
            "Parameters (kind parameter) are echoed by the oracle; a backend may write them too (then they are compared exactly) or leave them out.",
            "kink.* tensors are the oracle's own account of ReLU/L1 kinks (docs/oracle.md §7); a backend never writes them.",
            "Compare: xscale compare oracle.safetensors mine.safetensors --tolerances f32 (or f64, fp16), or in Python xscale.testing.assert_matches(mine, oracle, tolerances=\"f32\")."
        ],
    }))
}
