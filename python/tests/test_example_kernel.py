"""The worked example of testing one kernel: a NumPy hash grid — forward and position backward,
written from docs/spec.md §4.2 the way a backend author writes a CUDA kernel — checked against
the package's op, and a deliberately broken variant (the smoothstep weight's derivative 6t
instead of 6t(1-t)) caught with a message naming the op and the tensor. NumPy only: CI runs it."""

import numpy as np
import pytest

import xscale
from xscale.testing import assert_matches

PRIMES = (1, 2654435761, 805459861)
U32 = np.uint64(0xFFFFFFFF)


def numpy_grid(grid, table, x, d_out, broken=False):
    """F_H(x) [M, L*F] and dL/dx [M, 3] for d_out [M, L*F] (f64 positions mode, float64)."""
    cfg = grid.config
    nf, smooth = cfg["features"], cfg["interpolation"] == "smoothstep"
    scales, offsets, res, dense = grid.scales, grid.offsets, grid.resolutions, grid.dense
    m = len(x)
    out = np.zeros((m, grid.out_dim))
    dx = np.zeros((m, 3))
    for l in range(cfg["levels"]):
        s = float(scales[l])
        p = s * x + 0.5
        c = np.floor(p)
        t = p - c
        if smooth:
            w = t * t * (3 - 2 * t)
            dw = 6 * t if broken else 6 * t * (1 - t)
        else:
            w, dw = t, np.ones_like(t)
        size = np.uint64(offsets[l + 1] - offsets[l])
        cu = c.astype(np.int64).view(np.uint64) & U32
        for k in range(8):
            bits = [(k >> d) & 1 for d in range(3)]
            cc = [(cu[:, d] + np.uint64(bits[d])) & U32 for d in range(3)]
            if dense[l]:
                r = np.uint64(res[l])
                idx = (cc[0] + cc[1] * r + cc[2] * ((r * r) & U32)) & U32
            else:
                idx = ((cc[0] * np.uint64(PRIMES[0])) & U32) ^ ((cc[1] * np.uint64(PRIMES[1])) & U32) ^ (
                    (cc[2] * np.uint64(PRIMES[2])) & U32)
            rows = table[offsets[l] + (idx % size).astype(np.int64)]  # [M, F]
            f = [w[:, d] if bits[d] else 1 - w[:, d] for d in range(3)]
            df = [dw[:, d] if bits[d] else -dw[:, d] for d in range(3)]
            out[:, l * nf:(l + 1) * nf] += (f[0] * f[1] * f[2])[:, None] * rows
            g = d_out[:, l * nf:(l + 1) * nf]
            for d in range(3):
                o = [f[e] for e in range(3) if e != d]
                dx[:, d] += s * df[d] * o[0] * o[1] * (rows * g).sum(1)
    return out, dx


@pytest.mark.parametrize("interp", ["linear", "smoothstep"])
def test_a_numpy_grid_kernel_against_the_op(interp):
    grid = xscale.HashGrid(levels=6, features=2, log2_table_size=10, base_resolution=4, per_level_scale=2.0,
                           interpolation=interp)
    r = np.random.default_rng(0)
    table = r.uniform(-1, 1, (grid.n_entries, 2))
    x = r.random((2000, 3))
    d_out = r.standard_normal((2000, grid.out_dim))
    out, dx = numpy_grid(grid, table, x, d_out)
    assert any(grid.dense) and not all(grid.dense)  # both index paths
    assert_matches(out, grid.forward(table, x), "f64", name="fwd.grid_h", op="numpy grid forward")
    assert_matches(dx, grid.backward_positions(table, x, d_out), "f64", name="grad.batch.positions",
                   op="numpy grid backward_positions")


def test_a_wrong_smoothstep_derivative_is_caught_naming_op_and_tensor():
    grid = xscale.HashGrid(levels=6, features=2, log2_table_size=10, base_resolution=4, per_level_scale=2.0,
                           interpolation="smoothstep")
    r = np.random.default_rng(1)
    table = r.uniform(-1, 1, (grid.n_entries, 2))
    x = r.random((2000, 3))
    d_out = r.standard_normal((2000, grid.out_dim))
    out, dx = numpy_grid(grid, table, x, d_out, broken=True)
    assert_matches(out, grid.forward(table, x), "f64", name="fwd.grid_h", op="numpy grid forward")  # still right
    with pytest.raises(AssertionError) as e:
        assert_matches(dx, grid.backward_positions(table, x, d_out), "f64", name="grad.batch.positions",
                       op="numpy grid backward_positions")
    msg = str(e.value)
    assert msg.startswith("op numpy grid backward_positions: 1 tensor(s) out of tolerance set 'f64' (grad.batch.positions)")
    assert "FAIL grad.batch.positions: " in msg and "worst at [" in msg
