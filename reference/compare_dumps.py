#!/usr/bin/env python3
"""Stop-gap comparison of two dumps (until `xscale compare` exists): per shared tensor, max abs error, max relative
error (|a-b| / max(|a|, |b|), 0 where both are 0) and max ULP distance in the narrower of the two float dtypes.

  python reference/compare_dumps.py A.safetensors B.safetensors [--atol 1e-10] [--rtol 1e-8]

Exits 1 if some tensor exceeds BOTH --atol and --rtol somewhere (an element passes if |a-b| <= atol + rtol*|b|),
if shapes differ, or if the files share no tensor.
"""

from __future__ import annotations

import argparse
import sys

import numpy as np
from safetensors.numpy import load_file


def ulp_distance(a: np.ndarray, b: np.ndarray, dt) -> int:
    """Max distance in units in the last place of dt, via the monotone integer mapping of IEEE bit patterns."""
    ia = np.asarray(a, dtype=dt)
    ib = np.asarray(b, dtype=dt)
    it, bits = (np.int32, 31) if dt == np.float32 else (np.int64, 63)
    va, vb = ia.view(it).astype(np.int64), ib.view(it).astype(np.int64)
    # map sign-magnitude to a monotone two's complement line (-0 and +0 both map to 0)
    va = np.where(va < 0, -(va & ((1 << bits) - 1)), va)
    vb = np.where(vb < 0, -(vb & ((1 << bits) - 1)), vb)
    if va.size == 0:
        return 0
    return int(np.max(np.abs(va.astype(np.float64) - vb.astype(np.float64))))  # exact below 2^53 ulps


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("a")
    ap.add_argument("b")
    ap.add_argument("--atol", type=float, default=0.0)
    ap.add_argument("--rtol", type=float, default=0.0)
    args = ap.parse_args()
    A, B = load_file(args.a), load_file(args.b)
    shared = sorted(set(A) & set(B))
    bad = not shared
    print(f"{'tensor':40s} {'shape':>16s} {'max abs':>11s} {'max rel':>11s} {'max ulp':>10s}")
    for k in shared:
        a, b = A[k], B[k]
        if a.shape != b.shape:
            print(f"{k:40s} shape {list(a.shape)} vs {list(b.shape)}")
            bad = True
            continue
        if a.dtype.kind != "f" or b.dtype.kind != "f":
            same = np.array_equal(a, b)
            print(f"{k:40s} {str(list(a.shape)):>16s} {'equal' if same else 'DIFFERENT'}")
            bad |= not same
            continue
        a64, b64 = a.astype(np.float64), b.astype(np.float64)
        fin = np.isfinite(a64) & np.isfinite(b64)
        if not np.array_equal(np.isfinite(a64), np.isfinite(b64)):
            print(f"{k:40s} non-finite values differ")
            bad = True
        d = np.abs(a64 - b64)[fin]
        den = np.maximum(np.abs(a64), np.abs(b64))[fin]
        rel = np.divide(d, den, out=np.zeros_like(d), where=den > 0)
        dt = np.float32 if np.float32 in (a.dtype.type, b.dtype.type) else np.float64
        ulp = ulp_distance(a64[fin], b64[fin], dt)
        mabs = float(d.max()) if d.size else 0.0
        mrel = float(rel.max()) if rel.size else 0.0
        fail = bool(np.any(d > args.atol + args.rtol * np.abs(b64[fin])))
        bad |= fail
        print(f"{k:40s} {str(list(a.shape)):>16s} {mabs:11.3e} {mrel:11.3e} {ulp:10d}{'  FAIL' if fail else ''}")
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
