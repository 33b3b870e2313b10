"""A PyTorch peer of xscale's training step, for timing (benches/torch_peer.rs runs both).

The same model as the Rust trainer at a checkpoint's configuration (the `cpu` preset: grid H with footprint level
weights, the deformation xi with grid D and its MLP, SH of the direction, appearance codes, the shader MLP, sigmoid,
the loss) in float32, written as well as PyTorch allows on a CPU:
- every level and every corner of a grid in one vectorised computation: cells and fractions for all levels at once
  ([M, L, 3]), the per-axis index terms of the lower and upper corner broadcast over the 8 corners, dense and hashed
  levels selected per level with `torch.where`, and ONE `index_select` over the flat table for all L*8 corners;
- no Python loop over levels, corners or pixels; autograd for the backward;
- Adam (`torch.optim.Adam`, fused on the CPU where available, else foreach) over every parameter, tables included
  (dense updates: measured faster here than SparseAdam with sparse gradients);
- the loss (forward, and through AOTAutograd its backward) compiled with `torch.compile` (Inductor's C++ backend:
  the index arithmetic, gathers and weighted sums fused into loops): 2.5x faster than eager on this machine
  (16 grid-H levels, 16,384 pixels, 2 threads: 426 vs 1,072 ms per step). `--eager` times the uncompiled model.
  Compilation happens in the warm-up steps, which are not timed.

It first checks that its loss at the checkpoint equals the one xscale reports (`--expect-loss`, relative 1e-5), so
a fast wrong model is never timed. Prints one JSON line: {"loss0", "ms_per_step", "steps", "threads", ...}.

    python reference/bench_torch.py --checkpoint CK --batch B [--steps 10] [--threads 2] [--expect-loss X]
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
import tomllib
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
import xscale_ref as ref  # noqa: E402  (checkpoint and batch loading, SH)

P1, P2 = 2654435761, 805459861
U32 = 0xFFFFFFFF
P1_I32 = P1 - (1 << 32)  # the same 32 bits as a signed int32
P2_I32 = P2


class Grid:
    """A hash grid's static description as tensors over levels."""

    def __init__(self, levels: list, interpolation: str, positions: str):
        self.scale32 = torch.tensor([float(l.scale) for l in levels], dtype=torch.float32)  # [L]
        self.scale64 = self.scale32.to(torch.float64)
        self.res = torch.tensor([l.res for l in levels], dtype=torch.int64)
        self.size = torch.tensor([l.size for l in levels], dtype=torch.int64)
        self.dense = torch.tensor([l.dense for l in levels])
        self.offset = torch.tensor([l.offset for l in levels], dtype=torch.int64)
        self.smooth = interpolation == "smoothstep"
        self.tcnn = positions == "tcnn"
        self.n = len(levels)
        self.dense_l = torch.nonzero(self.dense).flatten()
        self.hashed_l = torch.nonzero(~self.dense).flatten()
        hs = self.size[self.hashed_l]
        assert bool(((hs & (hs - 1)) == 0).all()), "hashed levels have power-of-two sizes"
        self.mask_h = (hs - 1).to(torch.int32)

    def forward(self, x: torch.Tensor, table: torch.Tensor) -> torch.Tensor:
        """x [M,3] float64 -> [M, L, F] float32 (Eq. 2)."""
        if self.tcnn:
            p = x.to(torch.float32)[:, None, :] * self.scale32[None, :, None] + 0.5  # [M,L,3]
            c = torch.floor(p)
            t = p - c
        else:
            p = x[:, None, :] * self.scale64[None, :, None] + 0.5
            c = torch.floor(p)
            t = (p - c).to(torch.float32)
        c = c.to(torch.int64)
        w = t * t * (3 - 2 * t) if self.smooth else t  # [M,L,3]
        lo_hi = torch.stack([c, c + 1], dim=-1) & U32  # [M,L,3,2]
        # Corner k = (a, b, c) bits along x, y, z: per-axis terms broadcast [.,2,1,1] (z) x [.,1,2,1] (y) x
        # [.,1,1,2] (x). Hashed levels (table size a power of two): x ^ y*P1 ^ z*P2 in int32 (two's complement
        # wrapping = u32 wrapping for *, ^ and the final mask). Dense levels: x + y*res + z*res^2 mod size (int64).
        d, h = self.dense_l, self.hashed_l
        out = torch.empty(lo_hi.shape[:2] + (2, 2, 2), dtype=torch.int64)
        if len(h):
            q = lo_hi[:, h].to(torch.int32)
            hx, hy, hz = q[:, :, 0], q[:, :, 1] * P1_I32, q[:, :, 2] * P2_I32
            hashed = hz[..., :, None, None] ^ hy[..., None, :, None] ^ hx[..., None, None, :]
            out[:, h] = (hashed & self.mask_h[None, :, None, None, None]).to(torch.int64)
        if len(d):
            q = lo_hi[:, d]
            res = self.res[d][None, :, None]
            dx, dy, dz = q[:, :, 0], (q[:, :, 1] * res) & U32, (q[:, :, 2] * ((res * res) & U32)) & U32
            dense = (dz[..., :, None, None] + dy[..., None, :, None] + dx[..., None, None, :]) & U32
            out[:, d] = dense % self.size[d][None, :, None, None, None]
        idx = out + self.offset[None, :, None, None, None]  # [M,L,2,2,2] (z,y,x)
        one = 1 - w
        wx = torch.stack([one[..., 0], w[..., 0]], dim=-1)
        wy = torch.stack([one[..., 1], w[..., 1]], dim=-1)
        wz = torch.stack([one[..., 2], w[..., 2]], dim=-1)
        wk = wz[..., :, None, None] * wy[..., None, :, None] * wx[..., None, None, :]  # [M,L,2,2,2]
        m, nf = x.shape[0], table.shape[1]
        rows = table.index_select(0, idx.reshape(-1)).view(m, self.n, 8, nf)  # one gather, all levels/corners
        return (rows * wk.reshape(m, self.n, 8, 1)).sum(dim=2)  # [M,L,F]


def level_weight(r: torch.Tensor) -> torch.Tensor:
    """w(r) of src/model/level_weight.rs (f64): 1 for r <= 1, 0 from 4, a smoothstep in log2 between."""
    t = (torch.log2(r.clamp(min=1.0)) / 2.0).clamp(0.0, 1.0)
    return 1 - t * t * (3 - 2 * t)


class Peer:
    def __init__(self, ck_path: str, batch_path: str):
        # The footprint level weighting is implemented here (`level_weight` above), not in the
        # reference's model, which refuses it on its own.
        ck = ref.load_checkpoint(ck_path, also=frozenset({"level_weight"}))
        raw = tomllib.loads(ck.meta["config"])
        self.cfg = ck.cfg
        self.ck = ck
        b = ref.load_batch(batch_path, ck)
        cfg = ck.cfg
        self.gh = Grid(ck.levels_h, cfg.grid_h.interpolation, cfg.positions)
        self.gd = Grid(ck.levels_d, cfg.grid_d.interpolation, cfg.positions) if cfg.deform_enabled else None
        self.params = {k: torch.tensor(np.asarray(ck.tensors[k]), dtype=torch.float32).requires_grad_(True)
                       for k in ck.param_names()}
        n, s, _ = b.positions.shape
        vn, vs = np.nonzero(b.valid)
        self.n = n
        self.vn = torch.from_numpy(vn)
        self.x = torch.from_numpy(b.positions[vn, vs])  # [M,3] f64
        self.dirs = torch.from_numpy(b.dirs)
        self.target = torch.from_numpy(b.target)
        self.view = torch.from_numpy(b.view)
        self.count = torch.from_numpy(b.valid.sum(axis=1).astype(np.float32))
        self.lw = None
        if raw.get("level_weight", "none") == "footprint":
            fp = torch.from_numpy(np.asarray(b.tensors["batch.footprint"], dtype=np.float32)).to(torch.float64)
            w = level_weight(fp[:, None] * self.gh.scale64[None, :]).to(torch.float32)  # [N,L]
            self.lw = w[self.vn]  # [M,L] per sub-sample

    def loss(self) -> torch.Tensor:
        p, cfg, ck = self.params, self.cfg, self.ck
        gh = self.gh.forward(self.x, p["grid_h.table"].view(-1, cfg.grid_h.features))  # [M,L,F]
        if self.lw is not None:
            gh = gh * self.lw[:, :, None]
        m = gh.shape[0]
        feat = gh.reshape(m, -1)
        sh = ref.sh_forward(self.dirs)  # [N,16]
        if self.gd is not None:
            gd = self.gd.forward(self.x, p["grid_d.table"].view(-1, cfg.grid_d.features)).reshape(m, -1)
            delta = ref.mlp_forward(torch.cat([gd, sh[self.vn]], dim=1), p, "deform", ck.deform_layers,
                                    ck.deform_bias, None)
            feat = feat + delta  # Eq. 5
        pooled = torch.zeros((self.n, feat.shape[1])).index_add(0, self.vn, feat) / self.count[:, None]  # Eq. 4
        parts = [pooled, sh]
        if cfg.appearance_dim > 0:
            codes = p["appearance.codes"]
            own = codes[self.view.clamp(min=0)]
            parts.append(torch.where((self.view >= 0)[:, None], own, codes.mean(dim=0, keepdim=True)))
        logits = ref.mlp_forward(torch.cat(parts, dim=1), p, "shader", ck.shader_layers, cfg.bias, None)  # Eq. 3
        return ref.loss_forward(torch.sigmoid(logits), self.target, cfg.loss, cfg.smooth_l1_delta)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--checkpoint", required=True)
    ap.add_argument("--batch", required=True)
    ap.add_argument("--steps", type=int, default=10)
    ap.add_argument("--warmup", type=int, default=2)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--expect-loss", type=float, default=None)
    ap.add_argument("--eager", action="store_true", help="do not compile the loss (torch.compile)")
    a = ap.parse_args()
    torch.set_num_threads(a.threads)
    peer = Peer(a.checkpoint, a.batch)
    with torch.no_grad():
        loss0 = float(peer.loss())
    if a.expect_loss is not None and not math.isclose(loss0, a.expect_loss, rel_tol=1e-5):
        print(f"error: the peer's loss {loss0!r} differs from xscale's {a.expect_loss!r}", file=sys.stderr)
        return 1
    params = list(peer.params.values())
    try:
        opt = torch.optim.Adam(params, lr=1e-2, betas=(0.9, 0.99), eps=1e-15, fused=True)
        kind = "fused"
    except (RuntimeError, TypeError):
        opt = torch.optim.Adam(params, lr=1e-2, betas=(0.9, 0.99), eps=1e-15, foreach=True)
        kind = "foreach"

    loss_fn = peer.loss if a.eager else torch.compile(peer.loss)

    def step() -> float:
        opt.zero_grad(set_to_none=True)
        loss = loss_fn()
        loss.backward()
        opt.step()
        return float(loss.detach())

    # Warm-up (and compilation). The first step's loss is the checkpoint's: the compiled model must give it too.
    first = step()
    if not math.isclose(first, loss0, rel_tol=1e-5):
        print(f"error: the compiled loss {first!r} differs from the eager {loss0!r}", file=sys.stderr)
        return 1
    for _ in range(a.warmup - 1):
        step()
    t0 = time.perf_counter()
    for _ in range(a.steps):
        last = step()
    ms = (time.perf_counter() - t0) / a.steps * 1e3
    print(json.dumps({"loss0": loss0, "ms_per_step": ms, "steps": a.steps, "threads": torch.get_num_threads(),
                      "pixels": peer.n, "samples": int(peer.x.shape[0]), "adam": kind, "compiled": not a.eager, "last_loss": last,
                      "torch": torch.__version__}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
