"""Per-op agreement of the package with the command line's dump on the golden cases
(fixtures/golden/*): every forward op evaluated on the dump's own inputs, every backward op
through the composed step, and the whole step, all bit-identical (tolerance set `exact`)."""

import subprocess

import numpy as np
import pytest

import xscale
from xscale.testing import assert_matches

from conftest import GOLDEN


def cli_dump(xscale_cli, case, tmp_path, precision):
    out = tmp_path / f"cli-{precision}.safetensors"
    subprocess.run([*xscale_cli, "dump", "--checkpoint", str(case / "checkpoint.safetensors"),
                    "--batch", str(case / "batch.safetensors"), "--precision", precision, "--out", str(out)],
                   check=True, capture_output=True)
    return xscale.load(out)


DT = {"f64": np.float64, "f32": np.float32}


@pytest.mark.parametrize("precision", ["f64", "f32"])
def test_each_forward_op_equals_the_cli_dump(golden_case, xscale_cli, tmp_path, precision):
    d = cli_dump(xscale_cli, golden_case, tmp_path, precision)
    m = xscale.Model(golden_case / "checkpoint.safetensors")
    dt = DT[precision]
    P = {k: v.astype(dt) for k, v in m.params.items()}
    valid = d["batch.valid"]
    vmask = valid.astype(bool)
    x = np.ascontiguousarray(d["batch.positions"][vmask])
    lf = m.grid_h.out_dim

    def full(rows):
        o = np.zeros(valid.shape + (rows.shape[1],), rows.dtype)
        o[vmask] = rows
        return o

    checks = [
        ("HashGrid.forward (grid H)", "fwd.grid_h", full(m.grid_h.forward(P["grid_h.table"], x))),
        ("sh_forward", "fwd.sh", xscale.sh_forward(d["batch.dirs"], dtype=np.dtype(dt).name)),
    ]
    delta = None
    if m.grid_d is not None:
        checks.append(("HashGrid.forward (grid D)", "fwd.grid_d", full(m.grid_d.forward(P["grid_d.table"], x))))
        hidden, delta = xscale.deform_forward(d["fwd.grid_d"], d["fwd.sh"], valid, [w.astype(dt) for w in m.weights("deform")],
                                              m.biases("deform") and [b.astype(dt) for b in m.biases("deform")])
        checks += [("deform_forward", f"fwd.deform_hidden.{i}", h) for i, h in enumerate(hidden)]
        checks.append(("deform_forward", "fwd.deform", delta))
        delta = d["fwd.deform"]
    checks.append(("pool_forward", "fwd.pooled", xscale.pool_forward(d["fwd.grid_h"], valid, delta)))
    if "appearance.codes" in P:
        checks.append(("appearance_forward", "fwd.shader_in",
                       (xscale.appearance_forward(P["appearance.codes"], d["batch.view"]),
                        np.ascontiguousarray(d["fwd.shader_in"][:, lf + 16:]))))
    ws = [w.astype(dt) for w in m.weights("shader")]
    bs = m.biases("shader") and [b.astype(dt) for b in m.biases("shader")]
    hidden, logits = xscale.mlp_forward(d["fwd.shader_in"], ws, bs)
    checks += [("mlp_forward (shader)", f"fwd.shader_hidden.{i}", h) for i, h in enumerate(hidden)]
    checks.append(("mlp_forward (shader)", "fwd.logits", logits))
    y0 = xscale.linear_forward(d["fwd.shader_in"], ws[0], bs[0] if bs else None)
    checks.append(("linear_forward + relu_forward", "fwd.shader_hidden.0", xscale.relu_forward(y0)))
    checks.append(("sigmoid_forward", "fwd.rgb", xscale.sigmoid_forward(d["fwd.logits"])))
    cfg = m.config
    loss = xscale.loss_forward(d["fwd.rgb"], d["batch.target"], kind=cfg["loss"], delta=cfg["smooth_l1_delta"])
    checks.append(("loss_forward", "loss", np.array(loss, dtype=dt)))
    for op, name, mine in checks:
        mine, ref = mine if isinstance(mine, tuple) else (mine, d[name])
        assert mine.dtype == ref.dtype, (op, name, mine.dtype, ref.dtype)
        assert_matches(mine, ref, "exact", name=name, op=op)
    assert len(checks) >= 8


@pytest.mark.parametrize("precision", ["f64", "f32"])
def test_backward_ops_and_whole_step_equal_the_cli_dump(golden_case, xscale_cli, tmp_path, precision):
    d = cli_dump(xscale_cli, golden_case, tmp_path, precision)
    m = xscale.Model(golden_case / "checkpoint.safetensors")
    b = xscale.load(golden_case / "batch.safetensors")
    # Every backward op chained (loss, sigmoid, MLP, pooling, xi, grids, SH, codes): every grad.*.
    ops = xscale.step_from_ops(m, b, precision)
    r = assert_matches(ops, d, "exact")
    grads = [t for t in r["tensors"] if t["name"].startswith("grad.") and t["status"] == "pass"]
    assert len(grads) >= 6 and all(t["stats"]["max_abs"] == 0 for t in grads)
    # The whole step in one call is the dump itself, kink account included.
    kink = xscale.DEFAULT_KINK_THRESHOLD if precision == "f64" else None
    step = m.step(b, precision, kink_threshold=kink)
    assert sorted(step) == sorted(d)
    for k in d:
        assert step[k].dtype == d[k].dtype and np.array_equal(step[k], d[k], equal_nan=True), k


def test_step_is_bit_identical_for_any_thread_count():
    case = GOLDEN / "cpu-t10"
    m = xscale.Model(case / "checkpoint.safetensors")
    b = xscale.load(case / "batch.safetensors")
    before = xscale.get_num_threads()
    try:
        runs = {}
        for n in (1, 2, 4):
            xscale.set_num_threads(n)
            assert xscale.get_num_threads() == n
            runs[n] = (m.step(b, "f32"), m.grid_h.backward_table(
                np.ascontiguousarray(b["batch.positions"][b["batch.valid"].astype(bool)]),
                np.ones((int(b["batch.valid"].sum()), m.grid_h.out_dim), np.float32)))
        for n in (2, 4):
            for k in runs[1][0]:
                assert runs[n][0][k].tobytes() == runs[1][0][k].tobytes(), (n, k)
            assert runs[n][1].tobytes() == runs[1][1].tobytes()
    finally:
        xscale.set_num_threads(before)
