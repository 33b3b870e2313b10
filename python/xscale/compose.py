"""The whole model step composed from the per-op functions — a readable, runnable statement of
how the ops chain into the model (docs/spec.md §4), and the worked example of a backend built
op by op.

In float64 (``precision="f64"``) it reproduces ``Model.step`` / ``xscale dump --precision f64``
bit for bit (``python/tests/test_golden.py`` checks every tensor of every golden case with the
``exact`` tolerance set); in float32 it is the f32 dump. Every numerical operation is one of the
package's ops; what is done in NumPy here is only moving values (gathering valid rows, scattering
them back, concatenating, slicing), which rounds nothing.
"""

from __future__ import annotations

from typing import Any, Dict, Mapping, Union

import numpy as np

from . import (
    Model,
    Tensors,
    _as_tensors,
    appearance_backward,
    appearance_forward,
    apply_level_weights,
    deform_backward,
    deform_forward,
    level_weights,
    loss_backward,
    loss_forward,
    mlp_backward,
    mlp_forward,
    pixel_chunks,
    pool_backward,
    pool_forward,
    sh_backward,
    sh_forward,
    sigmoid_backward,
    sigmoid_forward,
)


def _c(a: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(a)


def step_from_ops(model: Union[Model, Any], batch: Union[Any, Mapping[str, Any]], precision: str = "f64") -> Tensors:
    """The dump of ``batch`` (``batch.*``, ``fwd.*``, ``loss``, ``grad.*``) computed op by op.

    ``model`` a :class:`Model` (or a checkpoint path / dict), ``batch`` a batch path or dict,
    ``precision`` "f64" or "f32". The footprint level weighting is applied when the model has it;
    the vertex featurization (a baseline) is not supported.
    """
    m = model if isinstance(model, Model) else Model(model)
    b = _as_tensors(batch, "batch")
    cfg = m.config
    if cfg.get("featurization", "hash") != "hash":
        raise NotImplementedError("step_from_ops: the vertex featurization (a baseline) is not composed here")
    dt = {"f64": np.float64, "f32": np.float32}[precision]
    pos, valid = b["batch.positions"], b["batch.valid"]
    dirs, view, target = b["batch.dirs"], b["batch.view"], b["batch.target"]
    n, s, _ = pos.shape
    vmask = valid.astype(bool)
    x = _c(pos[vmask])  # the valid sub-samples in batch order (pixel-major, then j)
    pixel_of_row = np.nonzero(vmask)[0]
    P = {k: v.astype(dt) for k, v in m.params.items()}  # f32 parameters widened exactly
    gh, gd = m.grid_h, m.grid_d
    lf = gh.out_dim
    a = cfg["appearance_dim"]

    def full(rows: np.ndarray) -> np.ndarray:  # [V, C] -> [N, S, C], invalid rows 0
        o = np.zeros((n, s, rows.shape[1]), dtype=rows.dtype)
        o[vmask] = rows
        return o

    out: Dict[str, np.ndarray] = {k: v for k, v in b.items() if k.startswith("batch.")}

    # ---- forward
    # Eq. 2: F_H at the valid sub-samples (footprint level weighting, SPEC §4.10, if the model has it).
    weighted = cfg.get("level_weight", "none") == "footprint"
    if weighted:
        w_pix, act_pix = level_weights(gh.scales, b["batch.footprint"], dtype=np.dtype(dt).name)
        w_rows, act_rows = _c(w_pix[pixel_of_row]), _c(act_pix[pixel_of_row])
        f_h = apply_level_weights(w_rows, gh.forward(P["grid_h.table"], x, active=act_rows))
    else:
        f_h = gh.forward(P["grid_h.table"], x)
    out["fwd.grid_h"] = full(f_h)
    sh = sh_forward(dirs, dtype=np.dtype(dt).name)  # SPEC §4.3
    out["fwd.sh"] = sh
    delta = None
    if gd is not None:  # Eq. 5: delta_j = xi([F_D(x_j), SH(d_n)])
        out["fwd.grid_d"] = full(gd.forward(P["grid_d.table"], x))
        w_d, b_d = [P[k] for k in _names(P, "deform", "weight")], _maybe(P, "deform")
        d_hidden, delta = deform_forward(out["fwd.grid_d"], sh, valid, w_d, b_d)
        for i, h in enumerate(d_hidden):
            out[f"fwd.deform_hidden.{i}"] = h
        out["fwd.deform"] = delta
    pooled = pool_forward(out["fwd.grid_h"], valid, delta)  # Eq. 4
    out["fwd.pooled"] = pooled
    parts = [pooled, sh]
    if a > 0:
        parts.append(appearance_forward(P["appearance.codes"], view))
    shader_in = _c(np.concatenate(parts, axis=1))
    out["fwd.shader_in"] = shader_in
    w_s, b_s = [P[k] for k in _names(P, "shader", "weight")], _maybe(P, "shader")
    s_hidden, logits = mlp_forward(shader_in, w_s, b_s)  # Eq. 3
    for i, h in enumerate(s_hidden):
        out[f"fwd.shader_hidden.{i}"] = h
    out["fwd.logits"] = logits
    rgb = sigmoid_forward(logits)
    out["fwd.rgb"] = rgb
    kind, dl = cfg["loss"], cfg["smooth_l1_delta"]
    out["loss"] = np.array(loss_forward(rgb, target, kind=kind, delta=dl), dtype=dt)

    # ---- backward
    d_rgb = loss_backward(rgb, target, kind=kind, delta=dl)
    d_logits = sigmoid_backward(rgb, d_rgb)
    d_in, d_ws, d_bs = mlp_backward(shader_in, w_s, s_hidden, d_logits, biases=b_s, chunks=pixel_chunks(n))
    grads: Dict[str, np.ndarray] = {}
    _put(grads, "shader", d_ws, d_bs)
    d_sh = _c(d_in[:, lf:lf + 16])
    d_feat = pool_backward(_c(d_in[:, :lf]), valid)  # dL/dF_H = dL/ddelta  [N, S, LF]
    if gd is not None:
        d_gd, d_sh, d_wd, d_bd = deform_backward(out["fwd.grid_d"], sh, valid, w_d, d_hidden, d_feat,
                                                 biases=b_d, d_sh=d_sh)
        _put(grads, "deform", d_wd, d_bd)
    d_rows = _c(d_feat[vmask])
    if weighted:
        d_rows = apply_level_weights(w_rows, d_rows)
    grads["grid_h.table"] = gh.backward_table(x, d_rows)
    d_x = gh.backward_positions(P["grid_h.table"], x, d_rows)
    if gd is not None:
        d_gd_rows = _c(d_gd[vmask])
        grads["grid_d.table"] = gd.backward_table(x, d_gd_rows)
        d_x = d_x + gd.backward_positions(P["grid_d.table"], x, d_gd_rows)
    if a > 0:
        grads["appearance.codes"] = appearance_backward(_c(d_in[:, lf + 16:]), view, P["appearance.codes"].shape[0])
    for k in m.params:
        out[f"grad.{k}"] = grads[k]
    out["grad.batch.positions"] = full(d_x)
    out["grad.batch.dirs"] = sh_backward(dirs, d_sh)
    meta = {"format": "xscale-1", "precision": precision}
    return Tensors(out, meta)


def _names(P: Mapping[str, np.ndarray], net: str, what: str):
    k = 0
    names = []
    while f"{net}.layers.{k}.{what}" in P:
        names.append(f"{net}.layers.{k}.{what}")
        k += 1
    return names


def _maybe(P: Mapping[str, np.ndarray], net: str):
    names = _names(P, net, "bias")
    return [P[k] for k in names] if names else None


def _put(grads: Dict[str, np.ndarray], net: str, d_ws, d_bs) -> None:
    for i, g in enumerate(d_ws):
        grads[f"{net}.layers.{i}.weight"] = g
    for i, g in enumerate(d_bs or []):
        grads[f"{net}.layers.{i}.bias"] = g
