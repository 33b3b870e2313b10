#!/usr/bin/env python3
"""Build a random but valid tiny checkpoint + batch (SPEC §6 names) for self-tests of the reference.

  python reference/make_case.py --out-dir /tmp/case --seed 1 [--interpolation smoothstep] [--positions tcnn]
      [--loss l2] [--no-deform] [--appearance-dim 0] [--bias] [--pixels 16] [--gamma 2]

Writes checkpoint.safetensors and batch.safetensors. The layout follows the `tiny` preset (SPEC §9) by default:
grid H with L=4, F=2, T=12, N0=4, b=2 (levels 0-2 dense, level 3 hashed), deformation grid L=2, F=2, T=8 here
(smaller than the preset's T=10 so that its level 1 is hashed too), xi hidden 8, shader 1x16, A=2.
Scales follow SPEC §4.2 in float32; sizes follow size_l = min(next_multiple_of_8(min(res^3, 2^31-1)), 2^T).
Unlike a training init, the tables are U(-table_scale, table_scale) (default 0.5) and xi's last layer is not
zero, so every gradient is far from zero and finite differences are informative.
The batch mixes random surface points with special ones (x = 1 exactly: +1 corners past the upper face; x = 0;
points on grid vertices), marks some sub-samples invalid (their positions are NaN unless --invalid-zero) and uses
view = -1 for some pixels. NumPy's PCG64 seeded generator is used (this is test data, not the Rust RNG).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
from safetensors.numpy import save_file

sys.path.insert(0, str(Path(__file__).resolve().parent))
from xscale_ref import spec_level_sizes  # noqa: E402


def spec_scales(levels: int, base: float, per_level_scale: float) -> np.ndarray:
    """scale_l = exp2(l * log2(b)) * N0 - 1 in float32 (SPEC §4.2). NumPy's float32 log2/exp2 may differ from
    tiny-cuda-nn's by an ulp for non-power-of-two b; that is why the table is saved and never recomputed."""
    f = np.float32
    log2b = np.log2(f(per_level_scale))
    return np.array([np.exp2(f(l) * log2b) * f(base) - f(1) for l in range(levels)], dtype=np.float32)


def grid_toml(prefix: str, g: dict) -> str:
    return (f"[{prefix}]\nlevels = {g['levels']}\nfeatures = {g['features']}\n"
            f"log2_table_size = {g['log2_table_size']}\nbase_resolution = {float(g['base_resolution'])}\n"
            f"per_level_scale = {float(g['per_level_scale'])}\ninterpolation = \"{g['interpolation']}\"\n")


def build_case(seed: int = 1, interpolation: str = "linear", positions: str = "f64", loss: str = "l1",
               deform: bool = True, appearance_dim: int = 2, appearance_views: int = 3, bias: bool = False,
               pixels: int = 16, gamma: int = 2, table_scale: float = 0.5, grid_h: dict | None = None,
               grid_d: dict | None = None, deform_hidden: int = 8, shader_hidden_layers: int = 1,
               shader_width: int = 16, invalid_nan: bool = True, special_points: bool = True,
               smooth_l1_delta: float = 0.01):
    """Returns (checkpoint tensors, checkpoint metadata, batch tensors)."""
    rng = np.random.Generator(np.random.PCG64(seed))
    gh = dict(levels=4, features=2, log2_table_size=12, base_resolution=4.0, per_level_scale=2.0,
              interpolation=interpolation)
    gh.update(grid_h or {})
    gd = dict(levels=2, features=2, log2_table_size=8, base_resolution=4.0, per_level_scale=2.0,
              interpolation=interpolation)
    gd.update(grid_d or {})
    cfg = (f"appearance_dim = {appearance_dim}\nappearance_views = {appearance_views}\ngamma = {gamma}\n"
           f"positions = \"{positions}\"\nloss = \"{loss}\"\nsmooth_l1_delta = {smooth_l1_delta}\n\n")
    cfg += grid_toml("grid_h", gh)
    cfg += f"\n[deform]\nenabled = {'true' if deform else 'false'}\nhidden = {deform_hidden}\n\n"
    cfg += grid_toml("deform.grid", gd)
    cfg += (f"\n[shader]\nhidden_layers = {shader_hidden_layers}\nwidth = {shader_width}\n"
            f"bias = {'true' if bias else 'false'}\n")
    t: dict[str, np.ndarray] = {}

    def grid(prefix, g):
        scales = spec_scales(g["levels"], g["base_resolution"], g["per_level_scale"])
        sizes = spec_level_sizes(scales, g["log2_table_size"])
        offsets = np.concatenate([[0], np.cumsum(sizes)]).astype(np.uint32)
        t[f"{prefix}.table"] = rng.uniform(-table_scale, table_scale, (int(offsets[-1]), g["features"])).astype(
            np.float32)
        t[f"{prefix}.scales"] = scales
        t[f"{prefix}.offsets"] = offsets

    def mlp(net, dims):
        for i in range(len(dims) - 1):
            lim = np.sqrt(6.0 / (dims[i] + dims[i + 1]))  # Xavier-uniform
            t[f"{net}.layers.{i}.weight"] = rng.uniform(-lim, lim, (dims[i + 1], dims[i])).astype(np.float32)
            if bias:
                t[f"{net}.layers.{i}.bias"] = rng.uniform(-0.3, 0.3, (dims[i + 1],)).astype(np.float32)

    lf = gh["levels"] * gh["features"]
    grid("grid_h", gh)
    if deform:
        grid("grid_d", gd)
        mlp("deform", [gd["levels"] * gd["features"] + 16, deform_hidden, lf])
    mlp("shader", [lf + 16 + appearance_dim] + [shader_width] * shader_hidden_layers + [3])
    if appearance_dim > 0:
        t["appearance.codes"] = rng.uniform(-0.5, 0.5, (appearance_views, appearance_dim)).astype(np.float32)
    meta = {"format": "xscale-1", "config": cfg,
            "normalization": json.dumps({"center": [0.0, 0.0, 0.0], "extent": [1.0, 1.0, 1.0]})}

    s = gamma * gamma
    pos = rng.uniform(0.0, 1.0, (pixels, s, 3))
    valid = rng.uniform(size=(pixels, s)) < 0.75
    valid[:, 0] = True  # every pixel keeps at least one sub-sample
    if special_points and pixels >= 4:
        pos[0, 0] = [1.0, 1.0, 1.0]  # every +1 corner past the upper face
        pos[1, 0] = [0.0, 0.0, 0.0]
        pos[2, 0] = [1.0, 0.25, 0.5]  # upper face in x only
        pos[3, 0] = [0.5, 1.0, 0.125]  # upper face in y only
    pos[~valid] = np.nan if invalid_nan else 0.0
    d = rng.normal(size=(pixels, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    view = rng.integers(-1, max(appearance_views, 1), size=pixels).astype(np.int32)
    if appearance_dim == 0:
        view[:] = -1
    b = {
        "batch.positions": pos.astype(np.float64),
        "batch.valid": valid.astype(np.uint8),
        "batch.dirs": d.astype(np.float32),
        "batch.view": view,
        "batch.target": rng.uniform(0.0, 1.0, (pixels, 3)).astype(np.float32),
    }
    return t, meta, b


def write_case(out_dir: str | Path, **kw) -> tuple[Path, Path]:
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    t, meta, b = build_case(**kw)
    ck, bp = out_dir / "checkpoint.safetensors", out_dir / "batch.safetensors"
    save_file(t, str(ck), metadata=meta)
    save_file(b, str(bp), metadata={"format": meta["format"]})
    return ck, bp


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out-dir", required=True)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--interpolation", choices=["linear", "smoothstep"], default="linear")
    ap.add_argument("--positions", choices=["f64", "tcnn"], default="f64")
    ap.add_argument("--loss", choices=["l1", "l2", "smooth_l1"], default="l1")
    ap.add_argument("--no-deform", action="store_true")
    ap.add_argument("--appearance-dim", type=int, default=2)
    ap.add_argument("--bias", action="store_true")
    ap.add_argument("--pixels", type=int, default=16)
    ap.add_argument("--gamma", type=int, default=2)
    ap.add_argument("--table-scale", type=float, default=0.5)
    ap.add_argument("--invalid-zero", action="store_true", help="invalid sub-samples at 0 instead of NaN")
    a = ap.parse_args()
    ck, bp = write_case(a.out_dir, seed=a.seed, interpolation=a.interpolation, positions=a.positions, loss=a.loss,
                        deform=not a.no_deform, appearance_dim=a.appearance_dim, bias=a.bias, pixels=a.pixels,
                        gamma=a.gamma, table_scale=a.table_scale, invalid_nan=not a.invalid_zero)
    print(f"wrote {ck} and {bp}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
