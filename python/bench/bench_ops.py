"""What calling the oracle from Python costs, measured side by side in one run.

1. Per-op call overhead: every op of a whole step composed from the ops (``xscale.step_from_ops``)
   on a 4,096-pixel batch (so 4,096 rows for the pixel ops and ~3,700 valid sub-samples × 4 for
   the grid ops), f32 and f64: the wall time of each call and, inside it, the Rust computation
   (``xscale._xscale._last_kernel_seconds``); the difference is the binding's overhead (argument
   checks, array conversion, the GIL, the thread pool's dispatch). Their sum is compared with the
   whole composed step.
2. The whole step in one call (``Model.step``) against the ``xscale dump`` command's round trip
   (the process, reading the checkpoint and batch files, writing the dump, loading it back with
   ``xscale.load``), f64 and f32, alternating rounds.

Workload: the golden ``cpu-t10`` checkpoint (the cpu preset's structure: grid H 16 levels × 2
features, ξ with grid D 8 × 2 and 32 hidden units, a 2 × 64 shader, A = 4; tables 2^10) on a seeded
random batch of 4,096 pixels × 4 sub-samples (10 % invalid, some view −1), as ``cargo bench --bench
oracle``. Before timing it checks that the composed step equals ``Model.step`` bit for bit and that
the command's dump equals ``Model.step``'s (every tensor). Medians over ``--rounds`` rounds.

    python python/bench/bench_ops.py [--pixels 4096] [--rounds 7] [--threads N] [--xscale PATH] [--json OUT]
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

import xscale
import xscale.compose as compose
import xscale.testing
from xscale import _xscale

REPO = Path(__file__).resolve().parents[2]
CASE = REPO / "fixtures" / "golden" / "cpu-t10"


def random_batch(m: xscale.Model, n: int, seed: int = 0) -> xscale.Tensors:
    r = np.random.default_rng(seed)
    s = m.config["gamma"] ** 2
    valid = (r.random((n, s)) > 0.1).astype(np.uint8)
    valid[valid.sum(1) == 0, 0] = 1
    pos = r.random((n, s, 3))
    pos[valid == 0] = 0.0
    dirs = r.standard_normal((n, 3)).astype(np.float32)
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    views = m.params["appearance.codes"].shape[0] if "appearance.codes" in m.params else 0
    view = r.integers(-1, max(views, 1), n).astype(np.int32)
    t = {"batch.positions": pos, "batch.valid": valid, "batch.dirs": dirs, "batch.view": view,
         "batch.target": r.random((n, 3)).astype(np.float32)}
    if m.config.get("level_weight") == "footprint":
        t["batch.footprint"] = (10 ** r.uniform(-4, -1, n)).astype(np.float32)
    return xscale.Tensors(t, {"format": "xscale-1"})


class Timed:
    """Wraps an op: records (wall, kernel) seconds of every call under its name."""

    def __init__(self, name, fn, log):
        self.name, self.fn, self.log = name, fn, log

    def __call__(self, *a, **k):
        t0 = time.perf_counter()
        out = self.fn(*a, **k)
        wall = time.perf_counter() - t0
        self.log.setdefault(self.name, []).append((wall, _xscale._last_kernel_seconds()))
        return out


class TimedGrid:
    def __init__(self, grid, label, log):
        self._g = grid
        for meth in ("forward", "backward_table", "backward_positions"):
            setattr(self, meth, Timed(f"HashGrid.{meth} ({label})", getattr(grid, meth), log))

    def __getattr__(self, k):
        return getattr(self._g, k)


OPS = ["sh_forward", "sh_backward", "deform_forward", "deform_backward", "pool_forward", "pool_backward",
       "appearance_forward", "appearance_backward", "mlp_forward", "mlp_backward", "sigmoid_forward",
       "sigmoid_backward", "loss_forward", "loss_backward", "level_weights", "apply_level_weights"]


def composed_step(m, b, precision, log):
    """One step_from_ops with every op call timed; returns (wall seconds, dump)."""
    saved = {k: getattr(compose, k) for k in OPS}
    grids = (m.grid_h, m.grid_d)
    try:
        for k in OPS:
            setattr(compose, k, Timed(k, saved[k], log))
        m.grid_h = TimedGrid(grids[0], "grid H", log)
        if grids[1] is not None:
            m.grid_d = TimedGrid(grids[1], "grid D", log)
        t0 = time.perf_counter()
        d = compose.step_from_ops(m, b, precision)
        return time.perf_counter() - t0, d
    finally:
        for k, v in saved.items():
            setattr(compose, k, v)
        m.grid_h, m.grid_d = grids


def cli_round_trip(xbin, ck, bpath, precision, out, threads):
    t0 = time.perf_counter()
    subprocess.run([xbin, "--threads", str(threads), "dump", "--checkpoint", str(ck), "--batch", str(bpath), "--precision", precision,
                    "--out", str(out)], check=True, capture_output=True)
    d = xscale.load(out)
    return time.perf_counter() - t0, d


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--pixels", type=int, default=4096)
    ap.add_argument("--rounds", type=int, default=7)
    ap.add_argument("--threads", type=int, default=0, help="worker threads (0: one per core)")
    ap.add_argument("--xscale", default=None, help="the xscale binary (default: target/release/xscale)")
    ap.add_argument("--json", default=None, help="also write the figures as JSON")
    a = ap.parse_args(argv)
    xbin = a.xscale or os.environ.get("XSCALE_BIN") or str(REPO / "target" / "release" / "xscale")
    if not Path(xbin).is_file():
        xbin = shutil.which("xscale")
    if not xbin:
        sys.exit("no xscale binary: cargo build --release, or --xscale PATH")
    if a.threads:
        xscale.set_num_threads(a.threads)
    threads = xscale.get_num_threads()
    m = xscale.Model(CASE / "checkpoint.safetensors")
    b = random_batch(m, a.pixels)
    tmp = Path(tempfile.mkdtemp(prefix="xscale-bench-"))
    try:
        bpath = tmp / "batch.safetensors"
        xscale.save(bpath, b)
        ck = CASE / "checkpoint.safetensors"

        # Validate before timing.
        for prec in ("f64", "f32"):
            ref = m.step(b, prec)
            xscale.testing.assert_matches(xscale.step_from_ops(m, b, prec), ref, "exact")
            _, cli = cli_round_trip(xbin, ck, bpath, prec, tmp / "cli.safetensors", threads)
            # The command's f64 dump adds the kink account; the step's tensors are equal.
            for k in ref:
                assert np.array_equal(ref[k], cli[k], equal_nan=True), (prec, k)

        per_op = {p: {} for p in ("f32", "f64")}
        composed = {p: [] for p in ("f32", "f64")}
        step = {p: [] for p in ("f32", "f64")}
        cli = {p: [] for p in ("f32", "f64")}
        for _ in range(a.rounds):
            for prec in ("f64", "f32"):
                w, _ = composed_step(m, b, prec, per_op[prec])
                composed[prec].append(w)
                t0 = time.perf_counter()
                m.step(b, prec)
                step[prec].append(time.perf_counter() - t0)
                w, _ = cli_round_trip(xbin, ck, bpath, prec, tmp / "cli.safetensors", threads)
                cli[prec].append(w)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)

    med = statistics.median
    n_valid = int(b["batch.valid"].sum())
    out = {
        "host": platform.node(), "cpu": platform.processor() or platform.machine(),
        "date": datetime.datetime.now().strftime("%Y-%m-%d %H:%M"),
        "load_average": os.getloadavg()[0], "threads": threads, "pixels": a.pixels, "valid_subsamples": n_valid,
        "rounds": a.rounds, "python": platform.python_version(), "numpy": np.__version__,
        "ops": {}, "steps": {},
    }
    print(f"# xscale from Python: call overhead ({out['date']}, {out['host']}, {threads} threads, "
          f"load average {out['load_average']:.1f}; {a.pixels} pixels, {n_valid} valid sub-samples, "
          f"median of {a.rounds} rounds)\n")
    print("| op | calls/step | f32 wall µs | f32 Rust µs | f32 overhead µs | f64 wall µs | f64 Rust µs | f64 overhead µs |")
    print("|---|---:|---:|---:|---:|---:|---:|---:|")
    names = sorted(per_op["f64"], key=lambda k: -med(w for w, _ in per_op["f64"][k]))
    tot = {p: [0.0, 0.0] for p in ("f32", "f64")}
    for k in names:
        row = [k, str(len(per_op["f64"][k]) // a.rounds)]
        out["ops"][k] = {}
        for prec in ("f32", "f64"):
            calls = per_op[prec][k]
            per_step = len(calls) // a.rounds
            wall = med(w for w, _ in calls)
            kern = med(r for _, r in calls)
            over = med(w - r for w, r in calls)
            tot[prec][0] += over * per_step
            tot[prec][1] += wall * per_step
            out["ops"][k][prec] = {"wall_us": wall * 1e6, "rust_us": kern * 1e6, "overhead_us": over * 1e6,
                                   "calls_per_step": per_step}
            row += [f"{wall * 1e6:.0f}", f"{kern * 1e6:.0f}", f"{over * 1e6:.1f}"]
        print("| " + " | ".join(row) + " |")
    print()
    print("| whole step, 4,096 pixels | f32 | f64 |")
    print("|---|---:|---:|")
    for label, key in (("composed from the ops (step_from_ops), ms", "composed"),
                       ("  of which op calls, ms", "ops"),
                       ("  of which the ops' overhead, ms", "overhead"),
                       ("overhead / composed step", "share"),
                       ("Model.step (one call), ms", "step"),
                       ("xscale dump round trip (process + files + load), ms", "cli"),
                       ("round trip / Model.step", "ratio")):
        vals = []
        for prec in ("f32", "f64"):
            v = {"composed": med(composed[prec]) * 1e3, "ops": tot[prec][1] * 1e3, "overhead": tot[prec][0] * 1e3,
                 "share": tot[prec][0] / med(composed[prec]), "step": med(step[prec]) * 1e3,
                 "cli": med(cli[prec]) * 1e3, "ratio": med(cli[prec]) / med(step[prec])}[key]
            out["steps"].setdefault(prec, {})[key] = v
            vals.append(f"{v:.3f}" if key in ("share", "ratio") else f"{v:.1f}")
        print(f"| {label} | " + " | ".join(vals) + " |")
    if a.json:
        Path(a.json).write_text(json.dumps(out, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
