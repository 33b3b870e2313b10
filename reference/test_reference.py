"""Self-tests of the independent PyTorch reference (run: `python -m pytest reference/ -q`).

Owns the checks that make the reference trustworthy on its own, before any comparison with the Rust side:
  - exact fma emulation (float32 and float64) against the C library's fmaf/fma, including double-rounding cases;
  - SH constants/signs (tiny-cuda-nn's band-1/2/3 convention) and orthonormality;
  - autograd gradients vs central finite differences in float64 (every parameter kind, positions, directions);
  - float32 vs float64 agreement, bit-exact float32 grid (fma-chain) vs an independent scalar implementation;
  - dense/hashed level selection, hand-computed corner indices, the un-clamped +1 corner wrap;
  - invalid sub-samples, view = -1, the CLI, bad inputs.
Tolerances are stated next to each check with the reason.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import math
import struct
import sys
from fractions import Fraction
from pathlib import Path

import numpy as np
import pytest
import torch
from safetensors.numpy import load_file, save_file

sys.path.insert(0, str(Path(__file__).resolve().parent))
import make_case  # noqa: E402
import xscale_ref as xr  # noqa: E402
from xscale_fma import fma_f32, fma_f64, fma_f64_fraction  # noqa: E402

_LIBM = ctypes.CDLL(ctypes.util.find_library("m"))
_LIBM.fmaf.argtypes = [ctypes.c_float] * 3
_LIBM.fmaf.restype = ctypes.c_float
_LIBM.fma.argtypes = [ctypes.c_double] * 3
_LIBM.fma.restype = ctypes.c_double


def libm_fmaf(a, b, c) -> np.float32:
    return np.float32(_LIBM.fmaf(float(a), float(b), float(c)))


def bits32(a) -> np.ndarray:
    return np.asarray(a, dtype=np.float32).view(np.uint32)


def case(tmp_path, **kw):
    ck_path, b_path = make_case.write_case(tmp_path, **kw)
    ck = xr.load_checkpoint(ck_path)
    return ck, xr.load_batch(b_path, ck), ck_path, b_path


# ---------------------------------------------------------------------------------------------------------------
# fma emulation


def _double_rounding_cases():
    """(a, b, c) float32 triples where RN32(RN64(a*b + c)) != RN32(a*b + c): the exact value lies a hair above
    (or below) a float32 midpoint, the float64 rounding lands exactly on the midpoint and ties-to-even then goes
    the wrong way."""
    f = np.float32
    cases = []
    for e in range(-20, 21, 5):
        s = 2.0**e
        # c + a*b = s*(1 + 2^-23) - s*2^-24*(1 - 2^-46) = s*(1 + 2^-24 + 2^-70): above the midpoint s*(1 + 2^-24).
        cases.append((f(-s * 2.0**-24 * (1 + 2.0**-23)), f(1 - 2.0**-23), f(s * (1 + 2.0**-23))))
        # c + a*b = s*(1 + 2^-23 + 2^-24) + s*2^-24*(... ) mirrored below: s*(1+2^-23+2^-24) - tiny lands on the
        # midpoint between s*(1+2^-23) (odd) and s*(1+2^-22) (even) -> naive rounds up, correct rounds down.
        cases.append((f(s * 2.0**-24 * (1 + 2.0**-23)), f(1 - 2.0**-23), f(s * (1 + 2.0**-23))))
    return cases


def test_fma_f32_double_rounding_cases():
    cases = _double_rounding_cases()
    a, b, c = (np.array(v, dtype=np.float32) for v in zip(*cases))
    ours = fma_f32(a, b, c)
    ref = np.array([libm_fmaf(*t) for t in cases], dtype=np.float32)
    naive = (a.astype(np.float64) * b.astype(np.float64) + c.astype(np.float64)).astype(np.float32)
    assert np.array_equal(bits32(ours), bits32(ref))
    # The cases are meaningful: the naive double-rounded evaluation gets some of them wrong.
    assert np.sum(bits32(naive) != bits32(ref)) >= len(cases) // 2


def test_fma_f32_random_matches_libm():
    rng = np.random.Generator(np.random.PCG64(7))
    n = 20000
    # Mixed magnitudes, signs, subnormals, exact cancellations and ties.
    a = (rng.normal(size=n) * np.exp2(rng.integers(-30, 30, n))).astype(np.float32)
    b = (rng.normal(size=n) * np.exp2(rng.integers(-30, 30, n))).astype(np.float32)
    c = (rng.normal(size=n) * np.exp2(rng.integers(-60, 60, n))).astype(np.float32)
    c[:2000] = -(a[:2000].astype(np.float64) * b[:2000]).astype(np.float32)  # near-cancellation
    a[2000:3000] = np.float32(1e-30)
    b[2000:3000] = np.float32(1e-15)  # products in the f32 subnormal range
    c[3000:4000] = 0.0
    a[4000:5000] = rng.uniform(0, 1, 1000).astype(np.float32)  # grid-like: weights x table values
    b[4000:5000] = rng.uniform(-1e-4, 1e-4, 1000).astype(np.float32)
    ours = fma_f32(a, b, c)
    ref = np.array([libm_fmaf(x, y, z) for x, y, z in zip(a, b, c)], dtype=np.float32)
    assert np.array_equal(bits32(ours), bits32(ref))


def test_fma_f64_matches_libm():
    rng = np.random.Generator(np.random.PCG64(8))
    scales = np.float32(rng.uniform(1, 4000, 3000)).astype(np.float64)
    x = rng.uniform(0, 1, 3000)
    ours = fma_f64(scales, x, 0.5)
    ref = np.array([_LIBM.fma(s, v, 0.5) for s, v in zip(scales, x)])
    assert np.array_equal(ours.view(np.uint64), ref.view(np.uint64))
    # and it is the correct rounding of the exact value
    for s, v, o in zip(scales[:200], x[:200], ours[:200]):
        exact = Fraction(s) * Fraction(v) + Fraction(1, 2)
        assert abs(Fraction(o) - exact) <= Fraction(math.ulp(o)) / 2
        assert o == fma_f64_fraction(s, v, 0.5)
    # general arguments (signs, magnitudes, cancellation)
    a = rng.normal(size=3000) * np.exp2(rng.integers(-40, 40, 3000))
    b = rng.normal(size=3000) * np.exp2(rng.integers(-40, 40, 3000))
    c = rng.normal(size=3000) * np.exp2(rng.integers(-80, 80, 3000))
    c[:500] = -(a[:500] * b[:500])
    ours = fma_f64(a, b, c)
    ref = np.array([_LIBM.fma(p, q, r) for p, q, r in zip(a, b, c)])
    assert np.array_equal(ours.view(np.uint64), ref.view(np.uint64))


# ---------------------------------------------------------------------------------------------------------------
# Spherical harmonics


def test_sh_constants_and_signs():
    # Constants as printed in tiny-cuda-nn's sh_enc (mathematical values: sqrt(3)/(2 sqrt(pi)), ...).
    k = xr.sh_constants()
    assert abs(k[0] - 0.28209479177387814) < 1e-16
    assert abs(k[1] - 0.48860251190291987) < 1e-16
    assert abs(k[2] - 1.0925484305920792) < 1e-15
    assert abs(3 * k[3] - 0.94617469575755997) < 1e-15 and abs(k[3] - 0.31539156525251999) < 1e-16
    assert abs(k[4] - 0.54627421529603959) < 1e-16
    assert abs(k[5] - 0.59004358992664352) < 1e-16
    assert abs(k[6] - 2.8906114426405538) < 1e-15
    assert abs(k[7] - 0.45704579946446572) < 1e-16
    assert abs(k[8] - 0.3731763325901154) < 1e-15
    assert abs(k[9] - 1.4453057213202769) < 1e-15
    r = 1 / math.sqrt(2)
    d = torch.tensor([[1.0, 0, 0], [0, 1.0, 0], [0, 0, 1.0], [r, r, 0], [0, r, r], [r, 0, r]], dtype=torch.float64)
    sh = xr.sh_forward(d).numpy()
    c1 = 0.48860251190291987
    # band 1 = -c*y, +c*z, -c*x
    assert np.allclose(sh[0, 1:4], [0, 0, -c1]) and np.allclose(sh[1, 1:4], [-c1, 0, 0])
    assert np.allclose(sh[2, 1:4], [0, c1, 0])
    # band 2: +xy, -yz, -xz
    assert sh[3, 4] > 0 and sh[4, 5] < 0 and sh[5, 7] < 0
    assert np.isclose(sh[3, 4], 1.0925484305920792 * 0.5)
    assert np.isclose(sh[3, 8], 0.0) and np.isclose(sh[0, 8], 0.54627421529603959)
    assert np.isclose(sh[2, 6], 0.94617469575755997 - 0.31539156525251999)
    # band 3 at +y: y*(-3x^2 + y^2) * 0.59.. > 0 ; -0.457*y*(5z^2-1) -> +0.457 at +y
    assert np.isclose(sh[1, 9], 0.59004358992664352) and np.isclose(sh[1, 11], 0.45704579946446572)
    assert np.isclose(sh[0, 15], -0.59004358992664352) and np.isclose(sh[2, 12], 2 * 0.3731763325901154)


def test_sh_orthonormal():
    # Gauss-Legendre in z (8 nodes) x 16 uniform phi: exact for the degree <= 6 products of bands 0..3.
    zs, wz = np.polynomial.legendre.leggauss(8)
    phi = np.arange(16) * 2 * np.pi / 16
    Z, P = np.meshgrid(zs, phi, indexing="ij")
    W = np.repeat(wz[:, None], 16, axis=1) * (2 * np.pi / 16)
    s = np.sqrt(1 - Z**2)
    d = torch.tensor(np.stack([s * np.cos(P), s * np.sin(P), Z], -1).reshape(-1, 3))
    y = xr.sh_forward(d).numpy()
    gram = (y * W.reshape(-1, 1)).T @ y
    assert np.abs(gram - np.eye(16)).max() < 1e-12


# ---------------------------------------------------------------------------------------------------------------
# Finite differences (float64)


def _fd_loss(ck, batch, params_np, pos=None, dirs=None):
    params = {k: torch.tensor(v, dtype=torch.float64) for k, v in params_np.items()}
    p = torch.tensor(batch.positions if pos is None else pos, dtype=torch.float64)
    d = torch.tensor(batch.dirs.astype(np.float64) if dirs is None else dirs, dtype=torch.float64)
    with torch.no_grad():
        return float(xr.forward(ck, batch, "float64", params=params, positions=p, dirs=d)["loss"])


def _min_margin(ck, x):
    """Smallest distance of t to a cell border over every level of both grids (float64 positions)."""
    m = 1.0
    for levels in [ck.levels_h] + ([ck.levels_d] if ck.levels_d else []):
        for lvl in levels:
            t, _ = xr.level_coords(x[None, :], lvl, "float64", "f64")
            m = min(m, float(np.min(np.minimum(t, 1 - t))))
    return m


@pytest.mark.parametrize(
    "kw",
    [
        dict(loss="l2", interpolation="linear"),
        dict(loss="smooth_l1", interpolation="smoothstep", smooth_l1_delta=0.2, bias=True),
        dict(loss="l1", interpolation="smoothstep", appearance_dim=3, appearance_views=4),
        dict(loss="l2", interpolation="linear", deform=False, appearance_dim=0),
    ],
    ids=["l2-linear", "smoothl1-smoothstep-bias", "l1-smoothstep", "l2-nodeform-noappearance"],
)
def test_gradients_vs_central_fd(tmp_path, kw):
    ck, batch, _, _ = case(tmp_path, seed=3, pixels=6, **kw)
    fw = xr.forward(ck, batch, "float64")
    fw["loss"].backward()
    params_np = {k: np.asarray(ck.tensors[k], dtype=np.float64) for k in ck.param_names()}
    rng = np.random.Generator(np.random.PCG64(11))
    # h = 1e-6: truncation error O(h^2 f''') ~ 1e-12 (x scale^3 ~ 3e4 for positions), rounding ~ 1e-16/h = 1e-10.
    h = 1e-6
    checked = 0
    for name, arr in params_np.items():
        grad = fw["_params"][name].grad.numpy()
        flat = np.flatnonzero(grad) if "table" in name else np.arange(arr.size)
        picks = list(rng.choice(flat, size=min(6, flat.size), replace=False))
        if "table" in name:  # an entry no sample touches must have exactly zero gradient
            untouched = np.flatnonzero(grad == 0)
            picks.append(int(untouched[0]))
        for i in picks:
            pp = {k: v.copy() for k, v in params_np.items()}
            pm = {k: v.copy() for k, v in params_np.items()}
            pp[name].reshape(-1)[i] += h
            pm[name].reshape(-1)[i] -= h
            fd = (_fd_loss(ck, batch, pp) - _fd_loss(ck, batch, pm)) / (2 * h)
            g = grad.reshape(-1)[i]
            assert abs(g - fd) <= 1e-8 + 1e-6 * abs(fd), f"{name}[{i}]: autograd {g} vs fd {fd}"
            checked += 1
    gpos = fw["_positions"].grad.numpy()
    vn, vs = np.nonzero(batch.valid)
    npos = 0
    for n_, s_ in zip(vn, vs):
        if _min_margin(ck, batch.positions[n_, s_]) < 1e-3 or npos >= 6:
            continue
        npos += 1
        for a in range(3):
            pp, pm = batch.positions.copy(), batch.positions.copy()
            pp[n_, s_, a] += h
            pm[n_, s_, a] -= h
            fd = (_fd_loss(ck, batch, params_np, pos=pp) - _fd_loss(ck, batch, params_np, pos=pm)) / (2 * h)
            g = gpos[n_, s_, a]
            assert abs(g - fd) <= 1e-8 + 1e-5 * abs(fd), f"positions[{n_},{s_},{a}]: {g} vs {fd}"
    assert npos >= 3
    assert np.all(gpos[~batch.valid] == 0)
    gdir = fw["_dirs"].grad.numpy()
    d0 = batch.dirs.astype(np.float64)
    for n_ in range(batch.dirs.shape[0]):
        for a in range(3):
            dp, dm = d0.copy(), d0.copy()
            dp[n_, a] += h
            dm[n_, a] -= h
            fd = (_fd_loss(ck, batch, params_np, dirs=dp) - _fd_loss(ck, batch, params_np, dirs=dm)) / (2 * h)
            assert abs(gdir[n_, a] - fd) <= 1e-8 + 1e-6 * abs(fd), f"dirs[{n_},{a}]: {gdir[n_, a]} vs {fd}"
    assert checked >= 19


# ---------------------------------------------------------------------------------------------------------------
# float32 vs float64, bit-exact grid


@pytest.mark.parametrize("positions", ["f64", "tcnn"])
def test_float32_agrees_with_float64(tmp_path, positions):
    ck, batch, _, _ = case(tmp_path, seed=5, pixels=32, positions=positions, interpolation="smoothstep",
                           loss="l2")
    d64 = xr.compute_dump(ck, batch, "float64")
    d32 = xr.compute_dump(ck, batch, "float32")
    assert set(d64) == set(d32)
    for k in d64:
        if not (k.startswith("fwd.") or k.startswith("grad.") or k == "loss"):
            continue
        a, b = d64[k], d32[k].astype(np.float64)
        assert d32[k].dtype == np.float32 and d64[k].dtype == np.float64
        scale = max(float(np.abs(a).max()), 1e-30)
        # float32 round-off through ~5 layers: ~1e-6 relative to the tensor's scale. "tcnn" additionally rounds x
        # to f32 (|dt| <= scale_l * 2^-24 ~ 2e-6 on the finest level), positions gradients carry t's error x scale.
        tol = 2e-5 if positions == "tcnn" else 5e-6
        err = float(np.abs(a - b).max()) / scale
        assert err < tol, f"{k}: relative error {err}"


def _scalar_grid_f32(x, levels, table, interpolation, positions):
    """Second, deliberately plain implementation of SPEC §4.2 in float32: one sample at a time, Python ints for
    the indices, libm's fmaf for every fused operation. Used to prove grid_fma_f32 bit for bit."""
    f = np.float32
    nf = table.shape[1]
    out = np.zeros(len(levels) * nf, dtype=np.float32)
    for l, lvl in enumerate(levels):
        c, t = [], []
        for d in range(3):
            if positions == "tcnn":
                p = libm_fmaf(lvl.scale, f(x[d]), f(0.5))
                fl = math.floor(p)
                c.append(fl)
                t.append(f(p - f(fl)))
            else:
                p = _LIBM.fma(float(lvl.scale), float(x[d]), 0.5)
                fl = math.floor(p)
                c.append(fl)
                t.append(f(p - fl))
        if interpolation == "smoothstep":
            w = [f(f(tt * tt) * f(f(3) - f(2) * tt)) for tt in t]
        else:
            w = t
        acc = [f(0)] * nf
        for k in range(8):
            weight = f(1)
            cc = []
            for d in range(3):
                if (k >> d) & 1:
                    weight = f(weight * w[d])
                    cc.append(c[d] + 1)
                else:
                    weight = f(weight * f(f(1) - w[d]))
                    cc.append(c[d])
            cc = [v & 0xFFFFFFFF for v in cc]
            if lvl.dense:
                idx = (cc[0] + cc[1] * lvl.res + cc[2] * lvl.res * lvl.res) & 0xFFFFFFFF
            else:
                idx = (cc[0] ^ ((cc[1] * 2654435761) & 0xFFFFFFFF) ^ ((cc[2] * 805459861) & 0xFFFFFFFF))
            idx %= lvl.size
            for j in range(nf):
                acc[j] = libm_fmaf(weight, table[lvl.offset + idx, j], acc[j])
        out[l * nf:(l + 1) * nf] = acc
    return out


@pytest.mark.parametrize("positions", ["tcnn", "f64"])
@pytest.mark.parametrize("interpolation", ["linear", "smoothstep"])
def test_grid_fma_bit_exact_and_close_to_float64(tmp_path, positions, interpolation):
    # table_scale 0.05 (init is 1e-4): "tcnn" rounds p = fma(31, x, 0.5) to f32, ulp(p) = 2^-19 on the finest
    # level, so |dt| <= 2^-20 ~ 1e-6 and |d out| <= 1e-6 * 1.5 (smoothstep slope) * 2 max|table|: ~1.5e-7 here.
    ck, batch, _, _ = case(tmp_path, seed=9, pixels=24, positions=positions, interpolation=interpolation,
                           table_scale=0.05)
    vn, vs = np.nonzero(batch.valid)
    x = batch.positions[vn, vs]
    table = ck.tensors["grid_h.table"]
    got = xr.grid_fma_f32(x, ck.levels_h, table, interpolation, positions)
    plain = np.stack([_scalar_grid_f32(xi, ck.levels_h, table, interpolation, positions) for xi in x])
    assert np.array_equal(bits32(got), bits32(plain))
    # vs the float64 torch grid: 8 f32 fma steps and f32 weights -> ~1e-8 here; "tcnn" also rounds x and p
    # (see above). Brief's tolerance: 1e-6.
    x_t = torch.tensor(x)
    g64 = xr.grid_forward(x_t, x, ck.levels_h, torch.tensor(table, dtype=torch.float64), interpolation, positions,
                          "float64").detach().numpy()
    assert np.abs(got - g64).max() < 1e-6
    if positions == "tcnn":  # same, at the f32-rounded positions
        x32 = x.astype(np.float32).astype(np.float64)
        g64b = xr.grid_forward(torch.tensor(x32), x32, ck.levels_h, torch.tensor(table, dtype=torch.float64),
                               interpolation, "f64", "float64").detach().numpy()
        assert np.abs(got - g64b).max() < 1e-6


def test_grid_fma_differs_from_unfused(tmp_path):
    ck, batch, _, _ = case(tmp_path, seed=12, pixels=64, positions="tcnn")
    vn, vs = np.nonzero(batch.valid)
    x = batch.positions[vn, vs]
    table = ck.tensors["grid_h.table"]
    fused = xr.grid_fma_f32(x, ck.levels_h, table, "linear", "tcnn")
    # same weights and indices, but acc = acc + w*v with two roundings
    x_t = torch.tensor(x)
    unfused = []
    for lvl in ck.levels_h:
        t, c = xr.level_coords(x, lvl, "float32", "tcnn")
        acc = np.zeros((x.shape[0], 2), np.float32)
        for k in range(8):
            wgt = np.ones(x.shape[0], np.float32)
            cc = c.copy()
            for d in range(3):
                if (k >> d) & 1:
                    wgt = wgt * t[:, d]
                    cc[:, d] += 1
                else:
                    wgt = wgt * (np.float32(1) - t[:, d])
            acc = acc + wgt[:, None] * table[lvl.offset + xr.corner_index(cc, lvl)]
        unfused.append(acc)
    unfused = np.concatenate(unfused, 1)
    assert np.abs(fused - unfused).max() < 1e-6
    assert np.any(bits32(fused) != bits32(unfused))
    del x_t


# ---------------------------------------------------------------------------------------------------------------
# Level selection, indices, wrap


def test_dense_vs_hashed_selection():
    scales = make_case.spec_scales(4, 4.0, 2.0)
    assert scales.tolist() == [3.0, 7.0, 15.0, 31.0]
    sizes = xr.spec_level_sizes(scales, 12)
    assert sizes == [64, 512, 4096, 4096]  # res^3 = 64, 512, 4096 (= 2^12: still dense), 32768 -> 2^T
    offsets = np.concatenate([[0], np.cumsum(sizes)]).astype(np.uint32)
    lv = xr.grid_levels(scales, offsets, "t")
    assert [l.res for l in lv] == [4, 8, 16, 32]
    assert [l.dense for l in lv] == [True, True, True, False]
    # res^3 > size by a little -> hashed; non-integer scale: res = ceil(scale) + 1
    lv2 = xr.grid_levels(np.array([3.0, 2.5], np.float32), np.array([0, 56, 56 + 64], np.uint32), "t")
    assert (lv2[0].res, lv2[0].dense) == (4, False)
    assert (lv2[1].res, lv2[1].dense) == (4, True)


def _one_sample_grid(scale, size, table, x, interpolation="linear"):
    lv = xr.grid_levels(np.array([scale], np.float32), np.array([0, size], np.uint32), "t")
    out = xr.grid_forward(torch.tensor([x], dtype=torch.float64), np.array([x], np.float64), lv,
                          torch.tensor(table, dtype=torch.float64), interpolation, "f64", "float64")
    return lv[0], out.detach().numpy()[0]


def test_corner_indices_by_hand():
    rng = np.random.Generator(np.random.PCG64(2))
    # Dense level: scale 7, res 8, size 512. x = (3/8, 5/8, 1/8): p = 7x + 0.5 = 3.125, 4.875, 1.375 (exact).
    table = rng.uniform(-1, 1, (512, 1))
    lvl, out = _one_sample_grid(7.0, 512, table, [3 / 8, 5 / 8, 1 / 8])
    assert lvl.dense
    c, t = (3, 4, 1), (0.125, 0.875, 0.375)
    exp = 0.0
    for k in range(8):
        b = [(k >> d) & 1 for d in range(3)]
        w = math.prod(t[d] if b[d] else 1 - t[d] for d in range(3))
        exp += w * table[(c[0] + b[0]) + (c[1] + b[1]) * 8 + (c[2] + b[2]) * 64, 0]
    assert abs(out[0] - exp) < 1e-15
    # Hashed level: scale 31, res 32, size 4096 (32^3 > 4096). x = (5/8, 1/4, 7/8): p = 19.875, 8.25, 27.625.
    table = rng.uniform(-1, 1, (4096, 1))
    lvl, out = _one_sample_grid(31.0, 4096, table, [5 / 8, 1 / 4, 7 / 8])
    assert not lvl.dense
    c, t = (19, 8, 27), (0.875, 0.25, 0.625)
    exp = 0.0
    for k in range(8):
        b = [(k >> d) & 1 for d in range(3)]
        w = math.prod(t[d] if b[d] else 1 - t[d] for d in range(3))
        h = ((c[0] + b[0]) ^ (((c[1] + b[1]) * 2654435761) % 2**32) ^ (((c[2] + b[2]) * 805459861) % 2**32)) % 4096
        exp += w * table[h, 0]
    assert abs(out[0] - exp) < 1e-15
    # spot value of the hash by hand: c = (19, 8, 27): 8*2654435761 = 21235486088 -> mod 2^32 = 4055616904,
    # 27*805459861 = 21747416247 -> mod 2^32 = 272579767; 19 ^ 4055616904 ^ 272579767 = 3783586092 -> % 4096 = 300
    assert xr.corner_index(np.array([[19, 8, 27]]), lvl)[0] == 300


def test_upper_face_corner_wraps_not_clamped():
    rng = np.random.Generator(np.random.PCG64(4))
    table = rng.uniform(-1, 1, (64, 2))
    # Dense level 0 of the tiny preset: scale 3, res 4, size 64. x = 1: p = 3.5, c = 3, t = 0.5, so the +1
    # corners sit at coordinate 4 = res, past the upper face. By hand: c + b*1 -> index (cx + 4 cy + 16 cz) % 64:
    # (3,3,3)=63 (4,3,3)=64->0 (3,4,3)=67->3 (4,4,3)=68->4 (3,3,4)=79->15 (4,3,4)=80->16 (3,4,4)=83->19 (4,4,4)=84->20
    lvl, out = _one_sample_grid(3.0, 64, table, [1.0, 1.0, 1.0])
    wrapped = table[[63, 0, 3, 4, 15, 16, 19, 20]].mean(axis=0)
    assert np.allclose(out, wrapped, rtol=0, atol=1e-15)
    assert not np.allclose(out, table[63], atol=1e-3)  # a clamped grid would return table[63]
    cc = np.array([[4, 4, 4]])
    assert xr.corner_index(cc, lvl)[0] == 20


# ---------------------------------------------------------------------------------------------------------------
# Pooling, invalid rows, appearance, CLI, bad inputs


def test_invalid_rows_pooling_and_view_mean(tmp_path):
    ck, batch, _, _ = case(tmp_path, seed=6, pixels=16)  # invalid positions are NaN: must never be evaluated
    d = xr.compute_dump(ck, batch, "float64")
    inv = ~batch.valid
    assert inv.any() and (batch.view == -1).any() and (batch.view >= 0).any()
    for k in ("fwd.grid_h", "fwd.grid_d", "fwd.deform", "fwd.deform_hidden.0", "grad.batch.positions"):
        assert np.all(d[k][inv] == 0), k
        assert np.all(np.isfinite(d[k])), k
    feat = d["fwd.grid_h"] + d["fwd.deform"]  # Eq. 5 (zeros on invalid rows)
    pooled = feat.sum(axis=1) / batch.valid.sum(axis=1, keepdims=True)  # Eq. 4 over valid sub-samples
    assert np.allclose(d["fwd.pooled"], pooled, atol=1e-15)
    lf, a = 8, 2
    si = d["fwd.shader_in"]
    assert np.array_equal(si[:, :lf], d["fwd.pooled"]) and np.array_equal(si[:, lf:lf + 16], d["fwd.sh"])
    codes = ck.tensors["appearance.codes"].astype(np.float64)
    for n in range(si.shape[0]):
        want = codes.mean(axis=0) if batch.view[n] < 0 else codes[batch.view[n]]
        assert np.allclose(si[n, lf + 16:lf + 16 + a], want, atol=1e-15)
    assert np.allclose(d["fwd.rgb"], 1 / (1 + np.exp(-d["fwd.logits"])), atol=1e-15)


@pytest.mark.parametrize("kind", ["l1", "l2", "smooth_l1"])
def test_loss_formulas(tmp_path, kind):
    ck, batch, _, _ = case(tmp_path, seed=2, loss=kind, smooth_l1_delta=0.3)
    d = xr.compute_dump(ck, batch, "float64")
    r = d["fwd.rgb"] - batch.target.astype(np.float64)
    if kind == "l1":
        want = np.abs(r).mean()
    elif kind == "l2":
        want = (r**2).mean()
    else:
        want = np.where(np.abs(r) < 0.3, 0.5 * r**2 / 0.3, np.abs(r) - 0.15).mean()
    assert d["loss"].shape == () and abs(float(d["loss"]) - want) < 1e-15


def test_cli_dump_and_grid_fma(tmp_path):
    _, _, ckp, bp = case(tmp_path, seed=1, positions="tcnn")
    out64, out32, grid = tmp_path / "d64.safetensors", tmp_path / "d32.safetensors", tmp_path / "g.safetensors"
    base = ["--checkpoint", str(ckp), "--batch", str(bp)]
    assert xr.main(base + ["--out", str(out64), "--dtype", "float64"]) == 0
    assert xr.main(base + ["--out", str(out32), "--dtype", "float32"]) == 0
    assert xr.main(["grid-fma"] + base + ["--out", str(grid)]) == 0
    d64, d32, g = load_file(str(out64)), load_file(str(out32)), load_file(str(grid))
    n, s = 16, 4
    shapes = {
        "fwd.grid_h": (n, s, 8), "fwd.grid_d": (n, s, 4), "fwd.deform_hidden.0": (n, s, 8), "fwd.deform": (n, s, 8),
        "fwd.pooled": (n, 8), "fwd.sh": (n, 16), "fwd.shader_in": (n, 26), "fwd.shader_hidden.0": (n, 16),
        "fwd.logits": (n, 3), "fwd.rgb": (n, 3), "loss": (), "grad.grid_h.table": (8768, 2),
        "grad.grid_d.table": (320, 2), "grad.deform.layers.0.weight": (8, 20), "grad.deform.layers.1.weight": (8, 8),
        "grad.shader.layers.0.weight": (16, 26), "grad.shader.layers.1.weight": (3, 16),
        "grad.appearance.codes": (3, 2), "grad.batch.positions": (n, s, 3), "grad.batch.dirs": (n, 3),
        "batch.positions": (n, s, 3), "batch.valid": (n, s), "batch.dirs": (n, 3), "batch.view": (n,),
        "batch.target": (n, 3),
    }
    assert set(d64) == set(shapes)
    for k, shp in shapes.items():
        assert d64[k].shape == shp, k
        if k.startswith(("fwd.", "grad.")) or k == "loss":
            assert d64[k].dtype == np.float64 and d32[k].dtype == np.float32
    assert d64["batch.positions"].dtype == np.float64 and d64["batch.valid"].dtype == np.uint8
    assert np.array_equal(bits32(g["fwd.grid_h"]), bits32(d32["fwd.grid_h"]))
    assert np.array_equal(bits32(g["fwd.grid_d"]), bits32(d32["fwd.grid_d"]))


REPO = Path(__file__).resolve().parent.parent
XSCALE = REPO / "target" / "release" / "xscale"
GOLDEN_CASES = sorted(p.parent for p in (REPO / "fixtures" / "golden").glob("*/ref_f64.safetensors"))


def test_kink_margin_finds_a_constructed_kink(tmp_path):
    """Pixel 0's shader unit 0 set to a pre-activation of ~0 (its SH band-0 weight solved for it): its margin is
    tiny; every margin lies in [0, 1]; the CLI writes it for float64 only."""
    ck, batch, ckp, bp = case(tmp_path, seed=3)
    d = xr.compute_dump(ck, batch, "float64")
    m = xr.kink_margin(ck, batch, d)
    assert m.shape == (16,) and np.all((m >= 0) & (m <= 1))
    w = np.array(ck.tensors["shader.layers.0.weight"])  # [16, 26]
    x = d["fwd.shader_in"][0]
    col = 8  # [pooled (8), SH (16), code (2)]: SH band 0, a constant 0.282
    pre = float(w[0].astype(np.float64) @ x)
    w[0, col] = np.float32(float(w[0, col]) - pre / x[col])
    ck.tensors["shader.layers.0.weight"] = w
    d = xr.compute_dump(ck, batch, "float64")
    m2 = xr.kink_margin(ck, batch, d)
    assert m2[0] < 1e-6 < m[0], (m[0], m2[0])
    out = tmp_path / "k.safetensors"
    base = ["--checkpoint", str(ckp), "--batch", str(bp), "--out", str(out)]
    assert xr.main(base + ["--kink-margin"]) == 0
    assert np.array_equal(load_file(str(out))["kink.margin"], m)
    assert xr.main(base + ["--kink-margin", "--dtype", "float32"]) == 2


@pytest.mark.skipif(not XSCALE.exists(), reason="needs the Rust binary (cargo build --release)")
@pytest.mark.parametrize("case_dir", GOLDEN_CASES, ids=lambda p: p.name)
def test_kink_margin_matches_rust(tmp_path, case_dir):
    """The Rust oracle's kink.margin (xscale dump, float64) is the same quantity computed independently here; both
    are f64 sums of the same terms in different orders: |pre| is off by ~1e-16 of the term magnitudes, so the
    margins agree to ~1e-16 absolute (measured <= 3.7e-16 on the five golden cases; limit 1e-14)."""
    import subprocess

    ckp, bp = case_dir / "checkpoint.safetensors", case_dir / "batch.safetensors"
    out = tmp_path / "rust.safetensors"
    subprocess.run([str(XSCALE), "dump", "--checkpoint", str(ckp), "--batch", str(bp), "--out", str(out)],
                   check=True, capture_output=True)
    rust = load_file(str(out))["kink.margin"]
    ck = xr.load_checkpoint(ckp)
    batch = xr.load_batch(bp, ck)
    ours = xr.kink_margin(ck, batch, xr.compute_dump(ck, batch, "float64"))
    assert rust.shape == ours.shape
    assert np.max(np.abs(rust - ours)) < 1e-14, np.max(np.abs(rust - ours))


def test_unimplemented_config_is_refused(tmp_path):
    """A checkpoint whose config asks for what this reference does not implement (the footprint level
    weighting, the cpu preset's default; the vertex featurization; a key it does not know) is refused with
    exit 2 instead of giving a wrong dump with exit 0; the golden cases' configs all load."""
    t, meta, b = make_case.build_case(seed=1)
    bp = tmp_path / "b.safetensors"
    save_file(b, str(bp))
    for extra, match in [
        ('level_weight = "footprint"\n', "level_weight = 'footprint': the footprint level weighting"),
        ('featurization = "vertex"\n', "featurization = 'vertex': the vertex featurization"),
        ('new_option = 1\n', "new_option is not implemented"),
    ]:
        p = tmp_path / "ck.safetensors"
        save_file(t, str(p), metadata={**meta, "config": extra + meta["config"]})
        with pytest.raises(xr.RefError, match=match):
            xr.load_checkpoint(p)
        assert xr.main(["--checkpoint", str(p), "--batch", str(bp), "--out", str(tmp_path / "o")]) == 2
        assert not (tmp_path / "o").exists()
    p = tmp_path / "ck.safetensors"
    save_file(t, str(p), metadata={**meta, "config": meta["config"].replace("[grid_h]", "[grid_h]\nsmooth = 1", 1)})
    with pytest.raises(xr.RefError, match="grid_h.smooth is not implemented"):
        xr.load_checkpoint(p)
    # What it implements, spelled out, is accepted.
    save_file(t, str(p), metadata={**meta, "config": 'level_weight = "none"\nfeaturization = "hash"\n' + meta["config"]})
    xr.load_checkpoint(p)
    # A caller that implements a part itself (bench_torch.py, the footprint weighting) names it, and only it.
    save_file(t, str(p), metadata={**meta, "config": 'level_weight = "footprint"\n' + meta["config"]})
    xr.load_checkpoint(p, also=frozenset({"level_weight"}))
    with pytest.raises(xr.RefError, match="level_weight = 'footprint'"):
        xr.load_checkpoint(p, also=frozenset({"featurization"}))
    for case_dir in GOLDEN_CASES:
        xr.load_checkpoint(case_dir / "checkpoint.safetensors")


def test_bad_inputs(tmp_path):
    t, meta, b = make_case.build_case(seed=1)
    ok_ck, ok_b = tmp_path / "ck.safetensors", tmp_path / "b.safetensors"
    save_file(t, str(ok_ck), metadata=meta)
    save_file(b, str(ok_b))
    # missing tensor
    t2 = dict(t)
    del t2["shader.layers.1.weight"]
    p = tmp_path / "ck2.safetensors"
    save_file(t2, str(p), metadata=meta)
    with pytest.raises(xr.RefError, match="ck2.safetensors.*shader"):
        xr.load_checkpoint(p)
    # wrong table shape
    t3 = dict(t)
    t3["grid_h.table"] = t["grid_h.table"][:-1]
    p = tmp_path / "ck3.safetensors"
    save_file(t3, str(p), metadata=meta)
    with pytest.raises(xr.RefError, match="grid_h.table: shape"):
        xr.load_checkpoint(p)
    # bad config
    p = tmp_path / "ck4.safetensors"
    save_file(t, str(p), metadata={**meta, "config": meta["config"].replace('"l1"', '"huber"')})
    with pytest.raises(xr.RefError, match="loss"):
        xr.load_checkpoint(p)
    ck = xr.load_checkpoint(ok_ck)
    # pixel without a valid sub-sample
    b2 = dict(b)
    v = b["batch.valid"].copy()
    v[5] = 0
    b2["batch.valid"] = v
    p = tmp_path / "b2.safetensors"
    save_file(b2, str(p))
    with pytest.raises(xr.RefError, match="b2.safetensors: pixel 5"):
        xr.load_batch(p, ck)
    # view out of range
    b3 = dict(b)
    b3["batch.view"] = np.full_like(b["batch.view"], 7)
    p = tmp_path / "b3.safetensors"
    save_file(b3, str(p))
    with pytest.raises(xr.RefError, match=r"batch.view\[0\] = 7"):
        xr.load_batch(p, ck)
    # not a safetensors file; CLI exit code 2
    p = tmp_path / "junk.safetensors"
    p.write_bytes(b"not a file")
    with pytest.raises(xr.RefError, match="junk.safetensors"):
        xr.load_checkpoint(p)
    assert xr.main(["--checkpoint", str(p), "--batch", str(ok_b), "--out", str(tmp_path / "o")]) == 2


@pytest.mark.skipif(not XSCALE.exists(), reason="needs the Rust binary (cargo build --release)")
def test_stepped_tables_are_rebuilt_bit_identical(tmp_path):
    """SPEC §6.2: a table stored by its stepped rows (`<name>.mask`, `<name>.kept`, header `init_seed`) is rebuilt
    from the seed (SPEC §5.1's generator, written here from the spec): the initial tables `xscale init` writes are
    drawn again bit for bit, and a file holding some rows (changed) and the seed loads to the whole table; a
    damaged one is refused naming the tensor."""
    import subprocess

    fixture = REPO / "fixtures" / "tiny"
    ckp = tmp_path / "init.safetensors"
    subprocess.run([str(XSCALE), "init", "--scene", str(fixture), "--preset", "tiny", "--seed", "5", "--out", str(ckp)],
                   check=True, capture_output=True)
    t, meta = xr.read_safetensors(ckp)
    for name, tensor_id in (("grid_h.table", 0), ("grid_d.table", 1)):
        drawn = xr.init_table(5, tensor_id, t[name].size).reshape(t[name].shape)
        assert np.array_equal(drawn.view(np.uint32), t[name].view(np.uint32)), name
    whole = dict(t)
    rows = t["grid_h.table"].shape[0]
    kept = np.arange(3, rows, 7)
    trained = t["grid_h.table"].copy()
    trained[kept] += np.float32(0.5)
    whole["grid_h.table"] = trained
    sparse = {k: v for k, v in t.items() if k != "grid_h.table"}
    bits = np.zeros(rows + (-rows) % 8, dtype=np.uint8)
    bits[kept] = 1
    sparse["grid_h.table.mask"] = np.packbits(bits, bitorder="little")
    sparse["grid_h.table.kept"] = trained[kept]
    p = tmp_path / "sparse.safetensors"
    save_file(sparse, str(p), metadata={**meta, "init_seed": "5"})
    ck = xr.load_checkpoint(p)
    assert np.array_equal(ck.tensors["grid_h.table"].view(np.uint32), trained.view(np.uint32))
    save_file(sparse, str(p), metadata=meta)
    with pytest.raises(xr.RefError, match="init_seed"):
        xr.load_checkpoint(p)
    sparse["grid_h.table.kept"] = trained[kept][1:]
    save_file(sparse, str(p), metadata={**meta, "init_seed": "5"})
    with pytest.raises(xr.RefError, match="grid_h.table.kept"):
        xr.load_checkpoint(p)
