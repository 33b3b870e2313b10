#!/usr/bin/env python3
"""Independent PyTorch reference of the xscale model's forward pass; gradients come from autograd.

Written from the design brief (now docs/spec.md, SPEC §4 and §6) and the XScale-NVS paper (Eq. 2-5), never from the Rust code. It reads a checkpoint
and a batch (safetensors, SPEC §6 names) and writes the same dump tensors as `xscale dump`:

  python reference/xscale_ref.py --checkpoint CK.safetensors --batch B.safetensors --out DUMP.safetensors \
      --dtype float64
  python reference/xscale_ref.py grid-fma --checkpoint CK --batch B --out GRID.safetensors

The second form evaluates only the hash grids in float32 with the SPEC's fma-chain (bit-exact, see
xscale_fma.py) so the Rust float32 grid (positions "tcnn" or "f64") can be compared bit for bit.

Model (per pixel n with sub-samples j, SPEC §4):
  F_H(x_j)                       hash grid H                                         (Eq. 2)
  F'(x_j) = F_H(x_j) + xi([F_D(x_j), SH(d_n)])   manifold deformation                (Eq. 5)
  pooled_n = mean over valid j of F'(x_j)        surface multisampling               (Eq. 4)
  rgb_n = sigmoid(MLP([pooled_n, SH(d_n), code(view_n)]))   neural shader            (Eq. 3)
  loss = mean over pixels and channels of L1 / L2 / smooth-L1 of (rgb - target)

Precision (--dtype):
  float64: everything float64; f32 tables/weights are widened exactly. positions "f64": p = fma(scale, x, 0.5) is
           a correctly rounded float64 fma. positions "tcnn": c and t come from the float32 fma exactly as below
           (the mode is part of the model's definition), t widened exactly; everything after t is float64.
  float32: tables, weights, activations float32. positions "f64": p is the float64 fma, t = RN32(p - floor(p));
           positions "tcnn": x -> RN32(x), p = fma32(scale, x, 0.5), t = p - floor(p) (exact).
           The grid outputs are replaced (value only, gradients untouched) by the SPEC's float32 fma-chain, so
           fwd.grid_h / fwd.grid_d are bit-exact; everything after the grid is ordinary float32 PyTorch (its
           summation order is not the Rust one: compare with float32 tolerances).
Positions gradients flow through t only (c = floor(p) is piecewise constant): t is computed exactly in NumPy
and re-attached to autograd as t + scale * (x - x.detach()), whose value is exactly t.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import tomllib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
from safetensors import safe_open
from safetensors.numpy import save_file

sys.path.insert(0, str(Path(__file__).resolve().parent))
from xscale_fma import fma_f32, fma_f64  # noqa: E402

U32 = np.uint64(0xFFFFFFFF)
HASH_PRIMES = (1, 2654435761, 805459861)  # SPEC §4.2 (tiny-cuda-nn's coherent prime hash)
SH_DIM = 16


class RefError(Exception):
    """Bad input: the message names the file and what was expected."""


# ----------------------------------------------------------------------------------------------------------------
# Config


@dataclass
class GridConfig:
    levels: int
    features: int
    log2_table_size: int
    base_resolution: float
    per_level_scale: float
    interpolation: str  # "linear" | "smoothstep"


@dataclass
class ModelConfig:
    grid_h: GridConfig
    deform_enabled: bool
    deform_hidden: int
    grid_d: GridConfig | None
    shader_hidden_layers: int
    shader_width: int
    bias: bool  # shader biases ([shader] bias)
    deform_bias: bool | None  # [deform] bias if given; None: decided by the tensors present
    appearance_dim: int
    appearance_views: int
    positions: str  # "f64" | "tcnn"
    loss: str  # "l1" | "l2" | "smooth_l1"
    smooth_l1_delta: float
    raw: dict = field(default_factory=dict)


def _grid_config(d: dict, where: str) -> GridConfig:
    try:
        g = GridConfig(
            levels=int(d["levels"]),
            features=int(d["features"]),
            log2_table_size=int(d["log2_table_size"]),
            base_resolution=float(d["base_resolution"]),
            per_level_scale=float(d["per_level_scale"]),
            interpolation=str(d.get("interpolation", "linear")),
        )
    except KeyError as e:
        raise RefError(f"config [{where}]: missing key {e}") from None
    if g.interpolation not in ("linear", "smoothstep"):
        raise RefError(f"config [{where}]: interpolation {g.interpolation!r}, expected linear or smoothstep")
    if g.levels < 1 or g.features < 1:
        raise RefError(f"config [{where}]: levels and features must be >= 1")
    return g


# The model config keys (SPEC §9, `ModelConfig`) this reference implements, by table. Any other key, or
# a value of one it does not implement, is refused: ignoring it would give a wrong reference with exit 0
# (it used to ignore `level_weight = "footprint"`, the cpu preset's default). `finest_resolution` only
# records how per_level_scale was chosen; `gamma` is the batch's S = gamma^2; `[refine]` moves the mesh
# batches are drawn from, not the evaluation of a batch.
_GRID_KEYS = {"levels", "features", "log2_table_size", "base_resolution", "per_level_scale", "interpolation",
              "finest_resolution", "log2_table_sizes"}
_KEYS = {
    "": {"grid_h", "deform", "shader", "appearance_dim", "appearance_views", "gamma", "positions", "loss",
         "smooth_l1_delta", "level_weight", "featurization", "refine"},
    "grid_h": _GRID_KEYS,
    "deform": {"enabled", "hidden", "bias", "grid"},
    "deform.grid": _GRID_KEYS,
    "shader": {"hidden_layers", "width", "bias"},
}
# Values of implemented keys that select something this reference does not implement.
_UNSUPPORTED = {
    "level_weight": ("none", "the footprint level weighting (SPEC §4.10)"),
    "featurization": ("hash", "the vertex featurization (SPEC §4.9)"),
}


def check_implemented(raw: dict, where: str, also: frozenset = frozenset()) -> None:
    """Refuse a model config with a key or value this reference does not implement (RefError).
    `also`: keys of _UNSUPPORTED the caller implements itself (bench_torch.py's footprint weighting)."""
    for table, keys in _KEYS.items():
        d = raw
        for part in table.split(".") if table else []:
            d = d.get(part, {})
        if not isinstance(d, dict):
            continue
        for k in d:
            if k not in keys:
                name = f"{table}.{k}" if table else k
                raise RefError(f"{where}: {name} is not implemented by this reference (a config it does not know "
                               f"cannot be evaluated faithfully); use `xscale dump` for this checkpoint")
    for k, (only, what) in _UNSUPPORTED.items():
        if k in also:
            continue
        v = raw.get(k, only)
        if v != only:
            raise RefError(f"{where}: {k} = {v!r}: {what} is not implemented by this reference (only {k} = "
                           f"{only!r}); use `xscale dump --precision f64` of this checkpoint as the oracle (docs/oracle.md §5)")


def parse_config(text: str, where: str = "config", also: frozenset = frozenset()) -> ModelConfig:
    try:
        raw = tomllib.loads(text)
    except tomllib.TOMLDecodeError as e:
        raise RefError(f"{where}: TOML: {e}") from None
    if "grid_h" not in raw:
        raise RefError(f"{where}: missing [grid_h]")
    check_implemented(raw, where, also)
    deform = raw.get("deform", {})
    enabled = bool(deform.get("enabled", False))
    shader = raw.get("shader", {})
    cfg = ModelConfig(
        grid_h=_grid_config(raw["grid_h"], "grid_h"),
        deform_enabled=enabled,
        deform_hidden=int(deform.get("hidden", 0)),
        grid_d=_grid_config(deform["grid"], "deform.grid") if enabled else None,
        shader_hidden_layers=int(shader.get("hidden_layers", 0)),
        shader_width=int(shader.get("width", 0)),
        bias=bool(shader.get("bias", False)),
        deform_bias=bool(deform["bias"]) if "bias" in deform else None,
        appearance_dim=int(raw.get("appearance_dim", 0)),
        appearance_views=int(raw.get("appearance_views", 0)),
        positions=str(raw.get("positions", "f64")),
        loss=str(raw.get("loss", "l1")),
        smooth_l1_delta=float(raw.get("smooth_l1_delta", 0.01)),
        raw=raw,
    )
    if enabled and "grid" not in deform:
        raise RefError(f"{where}: deform.enabled = true but no [deform.grid]")
    if cfg.positions not in ("f64", "tcnn"):
        raise RefError(f"{where}: positions = {cfg.positions!r}, expected \"f64\" or \"tcnn\"")
    if cfg.loss not in ("l1", "l2", "smooth_l1"):
        raise RefError(f"{where}: loss = {cfg.loss!r}, expected l1, l2 or smooth_l1")
    return cfg


# ----------------------------------------------------------------------------------------------------------------
# Files


def read_safetensors(path: str | Path) -> tuple[dict[str, np.ndarray], dict[str, str]]:
    path = Path(path)
    try:
        with safe_open(str(path), framework="np") as f:
            meta = f.metadata() or {}
            tensors = {k: f.get_tensor(k) for k in f.keys()}
    except FileNotFoundError:
        raise RefError(f"{path}: no such file") from None
    except Exception as e:  # safetensors raises its own error types
        raise RefError(f"{path}: not a readable safetensors file: {e}") from None
    return tensors, meta


@dataclass
class Level:
    scale: np.float32  # saved scale (never recomputed)
    res: int  # grid vertices per axis = ceil(scale) + 1
    size: int  # entries in this level (from offsets)
    dense: bool
    offset: int  # first entry of the level in the table


def grid_levels(scales: np.ndarray, offsets: np.ndarray, where: str) -> list[Level]:
    """SPEC §4.2: res_l = ceil(scale_l) + 1; size_l from the saved offsets; dense iff res_l <= 1625 and
    res_l^3 <= size_l."""
    scales = np.asarray(scales)
    offsets = np.asarray(offsets).astype(np.int64)
    if scales.dtype != np.float32:
        raise RefError(f"{where}.scales: dtype {scales.dtype}, expected float32")
    if offsets.shape != (scales.shape[0] + 1,):
        raise RefError(f"{where}.offsets: shape {offsets.shape}, expected [{scales.shape[0] + 1}]")
    levels = []
    for l in range(scales.shape[0]):
        s = np.float32(scales[l])
        if not np.isfinite(s) or s < 0:
            raise RefError(f"{where}.scales[{l}] = {s}: expected a finite non-negative scale")
        size = int(offsets[l + 1] - offsets[l])
        if size <= 0:
            raise RefError(f"{where}.offsets: level {l} has {size} entries")
        res = int(math.ceil(float(s))) + 1
        dense = res <= 1625 and res**3 <= size
        levels.append(Level(scale=s, res=res, size=size, dense=dense, offset=int(offsets[l])))
    return levels


def spec_level_sizes(scales: np.ndarray, log2_table_size: int) -> list[int]:
    """size_l = min(next_multiple_of_8(min(res_l^3, 2^31-1)), 2^T) (SPEC §4.2); used to build test checkpoints."""
    out = []
    for s in np.asarray(scales, dtype=np.float32):
        res = int(math.ceil(float(s))) + 1
        n = min(res**3, 2**31 - 1)
        n = (n + 7) // 8 * 8
        out.append(min(n, 2**log2_table_size))
    return out


@dataclass
class Checkpoint:
    cfg: ModelConfig
    tensors: dict[str, np.ndarray]  # every tensor of the file (adam.* included, unused)
    meta: dict[str, str]
    levels_h: list[Level]
    levels_d: list[Level] | None
    deform_layers: int
    shader_layers: int
    deform_bias: bool = False

    def param_names(self) -> list[str]:
        """Trainable parameter tensors (those that get grad.<name>), in a fixed order."""
        names = ["grid_h.table"]
        if self.cfg.deform_enabled:
            names.append("grid_d.table")
            for i in range(self.deform_layers):
                names.append(f"deform.layers.{i}.weight")
                if self.deform_bias:
                    names.append(f"deform.layers.{i}.bias")
        for i in range(self.shader_layers):
            names.append(f"shader.layers.{i}.weight")
            if self.cfg.bias:
                names.append(f"shader.layers.{i}.bias")
        if self.cfg.appearance_dim > 0:
            names.append("appearance.codes")
        return names


def _count_layers(tensors: dict, net: str) -> int:
    n = 0
    while f"{net}.layers.{n}.weight" in tensors:
        n += 1
    return n


def _check_mlp(ck_path, tensors, net, n_layers, n_in, n_out, width, bias):
    prev = n_in
    for i in range(n_layers):
        name = f"{net}.layers.{i}.weight"
        w = tensors[name]
        out = n_out if i == n_layers - 1 else width
        if w.ndim != 2 or w.shape != (out, prev):
            raise RefError(f"{ck_path}: {name}: shape {list(w.shape)}, expected [{out}, {prev}]")
        if bias:
            bname = f"{net}.layers.{i}.bias"
            if bname not in tensors:
                raise RefError(f"{ck_path}: {bname} missing (config has bias = true)")
            if tensors[bname].shape != (out,):
                raise RefError(f"{ck_path}: {bname}: shape {list(tensors[bname].shape)}, expected [{out}]")
        prev = out


def _check_grid(ck_path, tensors, prefix, gcfg: GridConfig) -> list[Level]:
    for k in ("table", "scales", "offsets"):
        if f"{prefix}.{k}" not in tensors:
            raise RefError(f"{ck_path}: missing tensor {prefix}.{k}")
    table = tensors[f"{prefix}.table"]
    scales = tensors[f"{prefix}.scales"]
    if scales.shape != (gcfg.levels,):
        raise RefError(f"{ck_path}: {prefix}.scales: shape {list(scales.shape)}, expected [{gcfg.levels}]")
    levels = grid_levels(scales, tensors[f"{prefix}.offsets"], f"{ck_path}: {prefix}")
    entries = int(np.asarray(tensors[f"{prefix}.offsets"]).astype(np.int64)[-1])
    if table.shape != (entries, gcfg.features):
        raise RefError(
            f"{ck_path}: {prefix}.table: shape {list(table.shape)}, expected [{entries}, {gcfg.features}]"
        )
    if not np.all(np.isfinite(table)):
        raise RefError(f"{ck_path}: {prefix}.table holds NaN or Inf")
    return levels


_MASK64 = (1 << 64) - 1


def _fmix(z):
    """SPEC §5.1: the SplitMix64 finaliser, on a Python int (masked to 64 bits) or a uint64 array."""
    if isinstance(z, int):
        z ^= z >> 30
        z = (z * 0xBF58476D1CE4E5B9) & _MASK64
        z ^= z >> 27
        z = (z * 0x94D049BB133111EB) & _MASK64
        return z ^ (z >> 31)
    z = z ^ (z >> np.uint64(30))
    z = z * np.uint64(0xBF58476D1CE4E5B9)
    z = z ^ (z >> np.uint64(27))
    z = z * np.uint64(0x94D049BB133111EB)
    return z ^ (z >> np.uint64(31))


def init_table(seed: int, tensor_id: int, n: int) -> np.ndarray:
    """SPEC §4.2 / §5.1: the initial table, element e = f32(-1e-4 + 2e-4 * uniform_f64(seed, InitTable = 1,
    tensor_id, e)), in f64 then rounded once."""
    h = _fmix((seed ^ 0x9E3779B97F4A7C15) & _MASK64)
    h = _fmix(h ^ ((1 * 0xBF58476D1CE4E5B9) & _MASK64))
    h = _fmix(h ^ ((tensor_id * 0x94D049BB133111EB) & _MASK64))
    e = np.arange(n, dtype=np.uint64)
    bits = _fmix(np.uint64(h) ^ (e * np.uint64(0xD6E8FEB86659FD93)))
    u = (bits >> np.uint64(11)).astype(np.float64) * (1.0 / (1 << 53))
    return (-1e-4 + 2e-4 * u).astype(np.float32)


def _expand_stepped_tables(path, tensors: dict, meta: dict) -> None:
    """SPEC §6.2: a grid table stored by its stepped rows (`<name>.mask`, `<name>.kept`, header `init_seed`) is
    rebuilt whole: every row its initial value from the seed, the kept rows over them."""
    for name, tensor_id in (("grid_h.table", 0), ("grid_d.table", 1)):
        mk, kn = name + ".mask", name + ".kept"
        if name in tensors or mk not in tensors:
            continue
        grid = name.split(".")[0]
        if kn not in tensors or grid + ".offsets" not in tensors:
            raise RefError(f"{path}: {mk} without {kn} and {grid}.offsets")
        if "init_seed" not in meta:
            raise RefError(f"{path}: {name} is stored by its stepped rows ({mk}) but the header has no 'init_seed'")
        try:
            seed = int(meta["init_seed"])
        except ValueError:
            raise RefError(f"{path}: header 'init_seed' = {meta['init_seed']!r}, expected an integer") from None
        rows = int(np.asarray(tensors[grid + ".offsets"])[-1])
        mask, kept = tensors[mk], tensors[kn]
        if mask.dtype != np.uint8 or mask.shape != ((rows + 7) // 8,):
            raise RefError(f"{path}: {mk}: {mask.dtype} {list(mask.shape)}, expected uint8 [{(rows + 7) // 8}]")
        idx = np.flatnonzero(np.unpackbits(mask, bitorder="little"))
        if idx.size and idx[-1] >= rows:
            raise RefError(f"{path}: {mk}: bit of row {idx[-1]} set, beyond the table's {rows} rows")
        if kept.dtype != np.float32 or kept.ndim != 2 or kept.shape[0] != idx.size:
            raise RefError(f"{path}: {kn}: {kept.dtype} {list(kept.shape)}, expected float32 [{idx.size}, F] "
                           f"(one row per bit set in {mk})")
        table = init_table(seed, tensor_id, rows * kept.shape[1]).reshape(rows, kept.shape[1])
        table[idx] = kept
        tensors[name] = table
        del tensors[mk], tensors[kn]


def load_checkpoint(path: str | Path, also: frozenset = frozenset()) -> Checkpoint:
    """`also`: as check_implemented's, for a caller that implements those parts itself."""
    tensors, meta = read_safetensors(path)
    _expand_stepped_tables(path, tensors, meta)
    if "config" not in meta:
        raise RefError(f"{path}: header metadata has no 'config'")
    cfg = parse_config(meta["config"], f"{path}: config", also)
    levels_h = _check_grid(path, tensors, "grid_h", cfg.grid_h)
    lf = cfg.grid_h.levels * cfg.grid_h.features
    levels_d = None
    deform_layers = 0
    deform_bias = False
    if cfg.deform_enabled:
        levels_d = _check_grid(path, tensors, "grid_d", cfg.grid_d)
        deform_layers = _count_layers(tensors, "deform")
        if deform_layers < 1:
            raise RefError(f"{path}: deform.enabled but no deform.layers.0.weight")
        n_in = cfg.grid_d.levels * cfg.grid_d.features + SH_DIM
        # The schema has one `bias` switch, under [shader]; a [deform] bias key wins if present, else the
        # deformation MLP has biases iff the file holds deform.layers.0.bias.
        deform_bias = cfg.deform_bias if cfg.deform_bias is not None else "deform.layers.0.bias" in tensors
        _check_mlp(path, tensors, "deform", deform_layers, n_in, lf, cfg.deform_hidden, deform_bias)
    shader_layers = _count_layers(tensors, "shader")
    if shader_layers != cfg.shader_hidden_layers + 1:
        raise RefError(
            f"{path}: {shader_layers} shader.layers.*.weight tensors, expected hidden_layers + 1 = "
            f"{cfg.shader_hidden_layers + 1}"
        )
    n_in = lf + SH_DIM + cfg.appearance_dim
    _check_mlp(path, tensors, "shader", shader_layers, n_in, 3, cfg.shader_width, cfg.bias)
    if cfg.appearance_dim > 0:
        codes = tensors.get("appearance.codes")
        if codes is None:
            raise RefError(f"{path}: appearance_dim = {cfg.appearance_dim} but no appearance.codes")
        if codes.ndim != 2 or codes.shape[1] != cfg.appearance_dim or codes.shape[0] < 1:
            raise RefError(
                f"{path}: appearance.codes: shape {list(codes.shape)}, expected [views, {cfg.appearance_dim}]"
            )
        if "appearance_views" in cfg.raw and codes.shape[0] != cfg.appearance_views:
            raise RefError(f"{path}: appearance.codes has {codes.shape[0]} rows, config appearance_views = "
                           f"{cfg.appearance_views}")
    ck = Checkpoint(cfg, tensors, meta, levels_h, levels_d, deform_layers, shader_layers, deform_bias)
    for name in ck.param_names():
        if not np.all(np.isfinite(tensors[name])):
            raise RefError(f"{path}: {name} holds NaN or Inf")
    return ck


@dataclass
class Batch:
    positions: np.ndarray  # [N,S,3] f64
    valid: np.ndarray  # [N,S] bool
    dirs: np.ndarray  # [N,3] f32
    view: np.ndarray  # [N] i32
    target: np.ndarray  # [N,3] f32
    tensors: dict[str, np.ndarray]


def load_batch(path: str | Path, ck: Checkpoint | None = None) -> Batch:
    t, _ = read_safetensors(path)
    for k in ("batch.positions", "batch.valid", "batch.dirs", "batch.view", "batch.target"):
        if k not in t:
            raise RefError(f"{path}: missing tensor {k}")
    pos, valid, dirs, view, target = (t[k] for k in ("batch.positions", "batch.valid", "batch.dirs", "batch.view",
                                                     "batch.target"))
    if pos.ndim != 3 or pos.shape[2] != 3:
        raise RefError(f"{path}: batch.positions: shape {list(pos.shape)}, expected [N, S, 3]")
    n, s, _ = pos.shape
    want = {"batch.valid": (n, s), "batch.dirs": (n, 3), "batch.view": (n,), "batch.target": (n, 3)}
    for k, shp in want.items():
        if t[k].shape != shp:
            raise RefError(f"{path}: {k}: shape {list(t[k].shape)}, expected {list(shp)}")
    if pos.dtype != np.float64:
        raise RefError(f"{path}: batch.positions: dtype {pos.dtype}, expected float64")
    valid_b = valid.astype(bool)
    empty = np.nonzero(~valid_b.any(axis=1))[0]
    if empty.size:
        raise RefError(f"{path}: pixel {int(empty[0])} has no valid sub-sample")
    if not np.all(np.isfinite(pos[valid_b])):
        bad = np.argwhere(~np.isfinite(pos) & valid_b[..., None])[0]
        raise RefError(f"{path}: batch.positions[{bad[0]}, {bad[1]}] is not finite")
    if not np.all(np.isfinite(dirs)) or not np.all(np.isfinite(target)):
        raise RefError(f"{path}: batch.dirs / batch.target hold NaN or Inf")
    view = view.astype(np.int64)
    if ck is not None and ck.cfg.appearance_dim > 0:
        rows = ck.tensors["appearance.codes"].shape[0]
        bad = np.nonzero((view < -1) | (view >= rows))[0]
        if bad.size:
            raise RefError(f"{path}: batch.view[{int(bad[0])}] = {int(view[bad[0]])}, expected -1..{rows - 1}")
    return Batch(pos, valid_b, dirs.astype(np.float32), view, target.astype(np.float32), t)


# ----------------------------------------------------------------------------------------------------------------
# Hash grid (Eq. 2, SPEC §4.2)


def _u32(a: np.ndarray) -> np.ndarray:
    """i64 -> u32 (two's complement wrap), held in uint64."""
    return (a.astype(np.int64).view(np.uint64)) & U32


def corner_index(cc: np.ndarray, lvl: Level) -> np.ndarray:
    """cc: [M,3] int64 corner coordinates (may be c+1 past the upper face; never clamped). Returns [M] int64 index
    inside the level: dense c.x + c.y*res + c.z*res^2 or hashed c.x*1 ^ c.y*P1 ^ c.z*P2, both u32 wrapping,
    then % size."""
    u = _u32(cc)  # [M,3] uint64 holding u32 values
    if lvl.dense:
        r = np.uint64(lvl.res)
        idx = (u[:, 0] + u[:, 1] * r + u[:, 2] * ((r * r) & U32)) & U32
    else:
        idx = ((u[:, 0] * np.uint64(HASH_PRIMES[0])) & U32) ^ ((u[:, 1] * np.uint64(HASH_PRIMES[1])) & U32) ^ (
            (u[:, 2] * np.uint64(HASH_PRIMES[2])) & U32
        )
    return (idx % np.uint64(lvl.size)).astype(np.int64)


def level_coords(x: np.ndarray, lvl: Level, dtype: str, positions: str) -> tuple[np.ndarray, np.ndarray]:
    """x: [M,3] float64 normalized positions. Returns (t [M,3] in dtype, c [M,3] int64) per SPEC §4.2.
    positions "tcnn" defines the cell and fraction in float32 whatever the model's dtype (the mode is part of the
    model: a float64 evaluation of a "tcnn" model uses the same c and t as its float32 evaluation, t widened
    exactly), so a float64 dump of a "tcnn" checkpoint is the oracle for an fp32 tiny-cuda-nn backend."""
    if positions == "tcnn":
        x32 = x.astype(np.float32)
        p = fma_f32(lvl.scale, x32, np.float32(0.5))  # float32, fused
        c = np.floor(p)
        t = p - c  # exact in float32
        return t.astype(np.float32 if dtype == "float32" else np.float64), c.astype(np.int64)
    p = fma_f64(np.float64(lvl.scale), x, 0.5)  # float64, fused
    c = np.floor(p)
    t = p - c  # exact in float64
    if dtype == "float32":
        t = t.astype(np.float32)  # one rounding: only the fraction goes to f32
    return t, c.astype(np.int64)


def smoothstep_np(t):
    return (t * t) * (t.dtype.type(3) - t.dtype.type(2) * t)


def grid_fma_f32(x: np.ndarray, levels: list[Level], table: np.ndarray, interpolation: str,
                 positions: str) -> np.ndarray:
    """Bit-exact float32 grid forward of SPEC §4.2. x: [M,3] f64. Returns [M, L*F] float32.
    weights in float32 (w_d = t or t*t*(3-2t); corner weight ((1*w_0)*w_1)*w_2 with w_d or 1-w_d), then per
    feature out = fma(weight_k, table[index_k, f], out) for k = 0..7 starting from out = 0."""
    table = np.asarray(table, dtype=np.float32)
    m = x.shape[0]
    nf = table.shape[1]
    out = np.zeros((m, len(levels) * nf), dtype=np.float32)
    one = np.float32(1)
    for l, lvl in enumerate(levels):
        t, c = level_coords(x, lvl, "float32", positions)
        w = smoothstep_np(t) if interpolation == "smoothstep" else t
        acc = np.zeros((m, nf), dtype=np.float32)
        for k in range(8):
            weight = np.ones(m, dtype=np.float32)
            cc = c.copy()
            for d in range(3):
                if (k >> d) & 1:
                    weight = weight * w[:, d]
                    cc[:, d] += 1
                else:
                    weight = weight * (one - w[:, d])
            rows = table[lvl.offset + corner_index(cc, lvl)]  # [M,F]
            acc = fma_f32(weight[:, None], rows, acc)
        out[:, l * nf:(l + 1) * nf] = acc
    return out


def smoothstep(t: torch.Tensor) -> torch.Tensor:
    """w(t) = t*t*(3-2t); autograd differentiates it (dw/dt = 6t(1-t)). A module-level function so
    that a test can swap in a deliberately wrong derivative and see the op checks catch it."""
    return t * t * (3 - 2 * t)


def grid_forward(x_t: torch.Tensor, x_np: np.ndarray, levels: list[Level], table: torch.Tensor,
                 interpolation: str, positions: str, dtype: str) -> torch.Tensor:
    """Differentiable grid forward. x_t: [M,3] float64 (autograd), x_np: the same values in NumPy, table:
    [E,F] torch in dtype. Returns [M, L*F]. Gradients: table via gather, positions via t (dt/dx = scale)."""
    tdt = table.dtype
    m, nf = x_np.shape[0], table.shape[1]
    weights = []  # L*8 tensors [M], level-major then corner k
    indices = []  # L*8 arrays [M] (absolute table rows)
    for lvl in levels:
        t_np, c = level_coords(x_np, lvl, dtype, positions)
        if dtype == "float32" and positions == "tcnn":
            x32 = x_t.to(torch.float32)
            t = torch.from_numpy(t_np) + torch.tensor(lvl.scale, dtype=torch.float32) * (x32 - x32.detach())
        else:
            dx = float(lvl.scale) * (x_t - x_t.detach())  # float64, value exactly 0
            t = torch.from_numpy(t_np) + dx.to(tdt)
        w = smoothstep(t) if interpolation == "smoothstep" else t
        for k in range(8):
            weight = None
            cc = c.copy()
            for d in range(3):
                if (k >> d) & 1:
                    wd = w[:, d]
                    cc[:, d] += 1
                else:
                    wd = 1 - w[:, d]
                weight = wd if weight is None else weight * wd  # product in order d = 0, 1, 2
            weights.append(weight)
            indices.append(lvl.offset + corner_index(cc, lvl))
    # One gather for every level and corner: its backward is a single index_add into one zero table (a gather
    # per corner would allocate a table-sized gradient per corner and level).
    idx = torch.from_numpy(np.concatenate(indices))
    rows = table.index_select(0, idx).view(len(levels), 8, m, nf)  # [L,8,M,F]
    wts = torch.stack(weights).view(len(levels), 8, m, 1)  # [L,8,M,1]
    out = (wts * rows).sum(dim=1)  # [L,M,F]
    out = out.permute(1, 0, 2).reshape(m, len(levels) * nf)  # [M, L*F], feature index l*F + f
    if dtype == "float32":
        # Value-replace with the SPEC's f32 fma-chain (bit-exact); the gradient is that of the graph above.
        exact = torch.from_numpy(
            grid_fma_f32(x_np, levels, table.detach().numpy(), interpolation, positions))
        # exact + (out - out.detach()) has exactly the value `exact` (the bracket is +0; the fma-chain never
        # yields -0 since it starts from +0) and the gradient of `out`.
        out = exact + (out - out.detach())
    return out


# ----------------------------------------------------------------------------------------------------------------
# Spherical harmonics, degree 4 (16 values), SPEC §4.3


def sh_constants() -> list[float]:
    """Constants of the real SH of bands 0-3 in Cartesian form (the standard table, e.g. Sloan's "Stupid SH
    tricks" appendix / Wikipedia's "Table of spherical harmonics"), as closed forms in sqrt(pi)."""
    sp = math.sqrt(math.pi)
    return [
        1 / (2 * sp),  # 0: Y00
        math.sqrt(3) / (2 * sp),  # 1..3
        math.sqrt(15) / (2 * sp),  # 4,5,7: xy, yz, xz
        math.sqrt(5) / (4 * sp),  # 6: (3z^2 - 1)
        math.sqrt(15) / (4 * sp),  # 8: (x^2 - y^2)
        math.sqrt(70) / (8 * sp),  # 9, 15
        math.sqrt(105) / (2 * sp),  # 10: xyz
        math.sqrt(42) / (8 * sp),  # 11, 13
        math.sqrt(7) / (4 * sp),  # 12
        math.sqrt(105) / (4 * sp),  # 14
    ]


def sh_forward(d: torch.Tensor) -> torch.Tensor:
    """d: [N,3] (not renormalised). Real SH with the Condon-Shortley phase (-1)^m, ordered m = -l..l per band
    (tiny-cuda-nn's order). Returns [N,16]."""
    k0, k1, k2, k2z, k2d, k3a, k3b, k3c, k3z, k3e = sh_constants()
    x, y, z = d[:, 0], d[:, 1], d[:, 2]
    xx, yy, zz = x * x, y * y, z * z
    cols = [
        torch.full_like(x, k0),
        -k1 * y,  # m = -1 (CS sign)
        k1 * z,
        -k1 * x,  # m = +1 (CS sign)
        k2 * x * y,  # m = -2
        -k2 * y * z,  # m = -1 (CS sign)
        k2z * (3 * zz - 1),  # m = 0
        -k2 * x * z,  # m = +1 (CS sign)
        k2d * (xx - yy),  # m = +2
        -k3a * y * (3 * xx - yy),  # m = -3 (CS sign)
        k3b * x * y * z,  # m = -2
        -k3c * y * (5 * zz - 1),  # m = -1 (CS sign)
        k3z * z * (5 * zz - 3),  # m = 0
        -k3c * x * (5 * zz - 1),  # m = +1 (CS sign)
        k3e * z * (xx - yy),  # m = +2
        -k3a * x * (xx - 3 * yy),  # m = +3 (CS sign)
    ]
    return torch.stack(cols, dim=1)


# ----------------------------------------------------------------------------------------------------------------
# Model


def mlp_forward(h: torch.Tensor, params: dict, net: str, n_layers: int, bias: bool,
                hidden_out: list | None) -> torch.Tensor:
    """y = W x (+ b); ReLU after every layer but the last. hidden_out collects post-ReLU activations."""
    for i in range(n_layers):
        h = h @ params[f"{net}.layers.{i}.weight"].T
        if bias:
            h = h + params[f"{net}.layers.{i}.bias"]
        if i < n_layers - 1:
            h = torch.relu(h)
            if hidden_out is not None:
                hidden_out.append(h)
    return h


def loss_forward(rgb: torch.Tensor, target: torch.Tensor, kind: str, delta: float) -> torch.Tensor:
    r = rgb - target
    if kind == "l1":
        e = r.abs()  # autograd: d|r|/dr = sign(r), 0 at r = 0
    elif kind == "l2":
        e = r * r  # mean r^2, no 1/2
    else:
        a = r.abs()
        e = torch.where(a < delta, 0.5 * r * r / delta, a - 0.5 * delta)
    return e.mean()


TORCH_DT = {"float32": torch.float32, "float64": torch.float64}


def make_params(ck: Checkpoint, dtype: str) -> dict[str, torch.Tensor]:
    return {
        name: torch.tensor(np.asarray(ck.tensors[name]), dtype=TORCH_DT[dtype]).requires_grad_(True)
        for name in ck.param_names()
    }


def forward(ck: Checkpoint, batch: Batch, dtype: str, params: dict | None = None,
            positions: torch.Tensor | None = None, dirs: torch.Tensor | None = None) -> dict[str, torch.Tensor]:
    """Forward pass. Returns every dump tensor (fwd.*, loss) plus the leaves under "_params", "_positions",
    "_dirs". positions/dirs may be given (float64 / dtype leaves) for finite-difference tests."""
    cfg = ck.cfg
    tdt = TORCH_DT[dtype]
    if params is None:
        params = make_params(ck, dtype)
    n, s, _ = batch.positions.shape
    if positions is None:
        positions = torch.tensor(batch.positions, dtype=torch.float64, requires_grad=True)
    if dirs is None:
        dirs = torch.tensor(batch.dirs, dtype=tdt, requires_grad=True)
    pos_np = positions.detach().numpy()
    vn, vs = np.nonzero(batch.valid)  # valid sub-samples, row-major
    vn_t, vs_t = torch.from_numpy(vn), torch.from_numpy(vs)
    xv = positions[vn_t, vs_t]  # [M,3] f64
    xv_np = pos_np[vn, vs]
    lf = cfg.grid_h.levels * cfg.grid_h.features
    out: dict[str, torch.Tensor] = {}

    def scatter(rows: torch.Tensor) -> torch.Tensor:  # [M,C] -> [N,S,C], invalid rows zero
        full = torch.zeros((n, s, rows.shape[1]), dtype=rows.dtype)
        return full.index_put((vn_t, vs_t), rows)

    gh = grid_forward(xv, xv_np, ck.levels_h, params["grid_h.table"], cfg.grid_h.interpolation, cfg.positions,
                      dtype)  # [M, L*F]   Eq. 2
    out["fwd.grid_h"] = scatter(gh)
    sh = sh_forward(dirs)  # [N,16]
    out["fwd.sh"] = sh
    feat = gh
    if cfg.deform_enabled:
        gd = grid_forward(xv, xv_np, ck.levels_d, params["grid_d.table"], cfg.grid_d.interpolation, cfg.positions,
                          dtype)  # [M, L_D*F_D]
        out["fwd.grid_d"] = scatter(gd)
        hidden: list = []
        delta = mlp_forward(torch.cat([gd, sh[vn_t]], dim=1), params, "deform", ck.deform_layers, ck.deform_bias,
                            hidden)  # [M, L*F]
        for i, h in enumerate(hidden):
            out[f"fwd.deform_hidden.{i}"] = scatter(h)
        out["fwd.deform"] = scatter(delta)
        feat = gh + delta  # Eq. 5
    count = torch.from_numpy(batch.valid.sum(axis=1).astype(np.float64)).to(tdt)  # [N]
    pooled = torch.zeros((n, lf), dtype=tdt).index_add(0, vn_t, feat) / count[:, None]  # Eq. 4
    out["fwd.pooled"] = pooled
    parts = [pooled, sh]
    if cfg.appearance_dim > 0:
        codes = params["appearance.codes"]
        view = torch.from_numpy(batch.view)
        mean = codes.mean(dim=0, keepdim=True).expand(n, -1)
        own = codes[view.clamp(min=0)]
        parts.append(torch.where((view >= 0)[:, None], own, mean))
    shader_in = torch.cat(parts, dim=1)
    out["fwd.shader_in"] = shader_in
    hidden = []
    logits = mlp_forward(shader_in, params, "shader", ck.shader_layers, cfg.bias, hidden)  # Eq. 3
    for i, h in enumerate(hidden):
        out[f"fwd.shader_hidden.{i}"] = h
    out["fwd.logits"] = logits
    rgb = torch.sigmoid(logits)
    out["fwd.rgb"] = rgb
    target = torch.from_numpy(batch.target).to(tdt)
    out["loss"] = loss_forward(rgb, target, cfg.loss, cfg.smooth_l1_delta)
    out["_params"] = params
    out["_positions"] = positions
    out["_dirs"] = dirs
    return out


def _contig(a: np.ndarray) -> np.ndarray:
    """C-contiguous copy that keeps 0-d arrays 0-d (np.ascontiguousarray would make `loss` shape [1])."""
    return np.array(a, copy=True, order="C")


def compute_dump(ck: Checkpoint, batch: Batch, dtype: str) -> dict[str, np.ndarray]:
    fw = forward(ck, batch, dtype)
    fw["loss"].backward()
    npdt = np.float64 if dtype == "float64" else np.float32
    dump: dict[str, np.ndarray] = {k: _contig(v) for k, v in batch.tensors.items()
                                   if k.startswith("batch.")}
    for k, v in fw.items():
        if not k.startswith("_"):
            dump[k] = _contig(v.detach().numpy().astype(npdt))
    for name, p in fw["_params"].items():
        g = p.grad if p.grad is not None else torch.zeros_like(p)
        dump[f"grad.{name}"] = _contig(g.numpy().astype(npdt))
    gp = fw["_positions"].grad
    dump["grad.batch.positions"] = _contig(gp.numpy().astype(npdt))
    gd = fw["_dirs"].grad
    dump["grad.batch.dirs"] = _contig(gd.numpy().astype(npdt))
    return dump


def kink_margin(ck: Checkpoint, batch: Batch, dump: dict[str, np.ndarray]) -> np.ndarray:
    """[N] each pixel's smallest relative distance to a kink (docs/oracle.md section 7, "Kinks"), from a float64
    dump's own forward tensors: for every hidden ReLU unit (shader per pixel; xi per valid sub-sample, counted for
    its pixel) |pre| / (|b| + sum_j |W_j x_j|) with pre = b + sum_j W_j x_j (1 where that sum is 0); for the L1
    loss, per channel |rgb - target| / max(|rgb|, |target|) (0 where both are 0). 1 for a pixel without units.
    The Rust oracle's `kink.margin` is the same quantity; computing it here is an independent check."""
    n = batch.positions.shape[0]
    margin = np.ones(n)
    vn, vs = np.nonzero(batch.valid)

    def units(x: np.ndarray, net: str, n_layers: int, bias: bool, hidden: list[np.ndarray]) -> np.ndarray:
        """[rows] smallest margin over the hidden units of every layer but the last."""
        best = np.ones(x.shape[0])
        for i in range(n_layers - 1):
            inp = x if i == 0 else hidden[i - 1]
            w = np.asarray(ck.tensors[f"{net}.layers.{i}.weight"], dtype=np.float64)  # [out, in]
            terms = inp[:, None, :] * w[None, :, :]  # [rows, out, in]
            pre = terms.sum(axis=2)
            mag = np.abs(terms).sum(axis=2)
            if bias:
                b = np.asarray(ck.tensors[f"{net}.layers.{i}.bias"], dtype=np.float64)
                pre = pre + b
                mag = mag + np.abs(b)
            m = np.where(mag > 0, np.abs(pre) / np.where(mag > 0, mag, 1.0), 1.0)
            best = np.minimum(best, m.min(axis=1))
        return best

    sh = dump["fwd.sh"].astype(np.float64)
    shader_hidden = [dump[f"fwd.shader_hidden.{i}"].astype(np.float64) for i in range(ck.shader_layers - 1)]
    margin = np.minimum(margin, units(dump["fwd.shader_in"].astype(np.float64), "shader", ck.shader_layers,
                                      ck.cfg.bias, shader_hidden))
    if ck.cfg.deform_enabled:
        gd = dump["fwd.grid_d"].astype(np.float64)[vn, vs]
        hidden = [dump[f"fwd.deform_hidden.{i}"].astype(np.float64)[vn, vs] for i in range(ck.deform_layers - 1)]
        per_sample = units(np.concatenate([gd, sh[vn]], axis=1), "deform", ck.deform_layers, ck.deform_bias,
                           hidden)
        np.minimum.at(margin, vn, per_sample)
    if ck.cfg.loss == "l1":
        y = dump["fwd.rgb"].astype(np.float64)
        t = batch.target.astype(np.float64)
        scale = np.maximum(np.abs(y), np.abs(t))
        m = np.where(scale > 0, np.abs(y - t) / np.where(scale > 0, scale, 1.0), 0.0)
        margin = np.minimum(margin, m.min(axis=1))
    return margin


def compute_grid_fma(ck: Checkpoint, batch: Batch) -> dict[str, np.ndarray]:
    vn, vs = np.nonzero(batch.valid)
    xv = batch.positions[vn, vs]
    n, s, _ = batch.positions.shape
    res = {}
    grids = [("fwd.grid_h", ck.levels_h, "grid_h.table", ck.cfg.grid_h)]
    if ck.cfg.deform_enabled:
        grids.append(("fwd.grid_d", ck.levels_d, "grid_d.table", ck.cfg.grid_d))
    for name, levels, tname, g in grids:
        rows = grid_fma_f32(xv, levels, ck.tensors[tname], g.interpolation, ck.cfg.positions)
        full = np.zeros((n, s, rows.shape[1]), dtype=np.float32)
        full[vn, vs] = rows
        res[name] = full
    return res


def _metadata(ck: Checkpoint, what: str, dtype: str) -> dict[str, str]:
    meta = {"producer": "reference/xscale_ref.py", "what": what, "dtype": dtype}
    for k in ("format", "config", "normalization"):
        if k in ck.meta:
            meta[k] = ck.meta[k]
    return meta


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    sub = "dump"
    if argv and argv[0] in ("grid-fma", "dump"):
        sub = argv.pop(0)
    ap = argparse.ArgumentParser(
        prog="xscale_ref.py" + (" grid-fma" if sub == "grid-fma" else ""),
        description="Independent PyTorch reference of the xscale forward/backward pass (SPEC §4, §6).")
    ap.add_argument("--checkpoint", required=True)
    ap.add_argument("--batch", required=True)
    ap.add_argument("--out", required=True)
    if sub == "dump":
        ap.add_argument("--dtype", choices=["float64", "float32"], default="float64")
        ap.add_argument("--kink-margin", action="store_true",
                        help="float64 only: also write kink.margin [N] (each pixel's smallest relative distance "
                             "to a ReLU or L1 kink; never compared, see docs/oracle.md section 7)")
    args = ap.parse_args(argv)
    torch.set_num_threads(1)  # deterministic reduction order on CPU
    try:
        ck = load_checkpoint(args.checkpoint)
        batch = load_batch(args.batch, ck)
        if sub == "grid-fma":
            out = compute_grid_fma(ck, batch)
            save_file(out, args.out, metadata=_metadata(ck, "grid-fma", "float32"))
        else:
            out = compute_dump(ck, batch, args.dtype)
            if args.kink_margin:
                if args.dtype != "float64":
                    raise RefError("--kink-margin: the kink margin belongs to the float64 dump")
                out["kink.margin"] = kink_margin(ck, batch, out)
            save_file(out, args.out, metadata=_metadata(ck, "dump", args.dtype))
    except RefError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    print(f"wrote {args.out}: {len(out)} tensors")
    return 0


if __name__ == "__main__":
    sys.exit(main())
