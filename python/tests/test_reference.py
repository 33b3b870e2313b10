"""The independent PyTorch reference (reference/xscale_ref.py: autograd gradients, written from the
SPEC only) checked op by op against the package, and a deliberately broken reference — a wrong
derivative of the smoothstep weight — caught with a message naming the op and the tensor.

Needs torch (and safetensors, which the reference reads files with); skipped without them. CI
installs numpy and pytest only, so these run where torch is installed
(`pip install torch safetensors`)."""

import sys

import numpy as np
import pytest

import xscale
from xscale.testing import assert_matches

from conftest import GOLDEN, REPO

torch = pytest.importorskip("torch", reason="the PyTorch reference needs torch (pip install torch); CI runs the numpy-only tests")
pytest.importorskip("safetensors", reason="the PyTorch reference reads files with safetensors (pip install safetensors)")
sys.path.insert(0, str(REPO / "reference"))
import xscale_ref as ref  # noqa: E402

CASES = ["tiny-tcnn-smoothstep", "tiny-f64-linear", "cpu-t10"]


def grid_ops(case, which="h"):
    """The reference's grid on the case's valid positions, forward and autograd backward, and the
    package's three grid passes on the same inputs (float64)."""
    ck = ref.load_checkpoint(GOLDEN / case / "checkpoint.safetensors")
    b = xscale.load(GOLDEN / case / "batch.safetensors")
    x = np.ascontiguousarray(b["batch.positions"][b["batch.valid"].astype(bool)])
    levels = ck.levels_h if which == "h" else ck.levels_d
    gcfg = ck.cfg.grid_h if which == "h" else ck.cfg.grid_d
    table = ck.tensors[f"grid_{which}.table"].astype(np.float64)
    d_out = np.random.default_rng(0).standard_normal((len(x), table.shape[1] * len(levels)))
    x_t = torch.tensor(x, requires_grad=True)
    t_t = torch.tensor(table, requires_grad=True)
    out = ref.grid_forward(x_t, x, levels, t_t, gcfg.interpolation, ck.cfg.positions, "float64")
    out.backward(torch.from_numpy(d_out))
    m = xscale.Model(GOLDEN / case / "checkpoint.safetensors")
    g = m.grid_h if which == "h" else m.grid_d
    ours = (g.forward(table, x), g.backward_table(x, d_out), g.backward_positions(table, x, d_out))
    theirs = (out.detach().numpy(), t_t.grad.numpy(), x_t.grad.numpy())
    return ours, theirs


@pytest.mark.parametrize("case", CASES)
def test_hash_grids(case):
    for which in ("h", "d"):
        ours, theirs = grid_ops(case, which)
        for op, name, a, r in zip(("HashGrid.forward", "HashGrid.backward_table", "HashGrid.backward_positions"),
                                  (f"fwd.grid_{which}", f"grad.grid_{which}.table", "grad.batch.positions"),
                                  theirs, ours):
            assert_matches(a, r, "f64", name=name, op=f"reference {op} (grid {which.upper()})")


def test_sh_mlp_loss():
    r = np.random.default_rng(1)
    dirs = r.standard_normal((300, 3)).astype(np.float32)
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    d_t = torch.tensor(dirs.astype(np.float64), requires_grad=True)
    sh = ref.sh_forward(d_t)
    g = r.standard_normal((300, 16))
    sh.backward(torch.from_numpy(g))
    assert_matches(sh.detach().numpy(), xscale.sh_forward(dirs, dtype="float64"), "f64", name="fwd.sh", op="reference sh_forward")
    assert_matches(d_t.grad.numpy(), xscale.sh_backward(dirs, g), "f64", name="grad.batch.dirs", op="reference sh backward")

    x = r.standard_normal((300, 26))
    ws = [r.standard_normal((16, 26)) * 0.3, r.standard_normal((16, 16)) * 0.3, r.standard_normal((3, 16)) * 0.3]
    bs = [r.standard_normal(16) * 0.1, r.standard_normal(16) * 0.1, r.standard_normal(3) * 0.1]
    params = {f"shader.layers.{i}.weight": torch.tensor(w, requires_grad=True) for i, w in enumerate(ws)}
    params.update({f"shader.layers.{i}.bias": torch.tensor(b, requires_grad=True) for i, b in enumerate(bs)})
    x_t = torch.tensor(x, requires_grad=True)
    hid = []
    y = ref.mlp_forward(x_t, params, "shader", 3, True, hid)
    gy = r.standard_normal((300, 3))
    y.backward(torch.from_numpy(gy))
    hidden, out = xscale.mlp_forward(x, ws, bs)
    d_x, d_ws, d_bs = xscale.mlp_backward(x, ws, hidden, gy, biases=bs)
    for i, h in enumerate(hid):
        assert_matches(h.detach().numpy(), hidden[i], "f64", name=f"fwd.shader_hidden.{i}", op="reference mlp_forward")
    assert_matches(y.detach().numpy(), out, "f64", name="fwd.logits", op="reference mlp_forward")
    assert_matches({"grad.shader_in": x_t.grad.numpy(), **{f"grad.shader.layers.{i}.weight": params[f"shader.layers.{i}.weight"].grad.numpy() for i in range(3)},
                    **{f"grad.shader.layers.{i}.bias": params[f"shader.layers.{i}.bias"].grad.numpy() for i in range(3)}},
                   {"grad.shader_in": d_x, **{f"grad.shader.layers.{i}.weight": d_ws[i] for i in range(3)},
                    **{f"grad.shader.layers.{i}.bias": d_bs[i] for i in range(3)}},
                   "f64", partial=True, op="reference mlp backward")

    rgb = r.random((300, 3))
    tgt = r.random((300, 3)).astype(np.float32)
    for kind in ("l1", "l2", "smooth_l1"):
        rgb_t = torch.tensor(rgb, requires_grad=True)
        loss = ref.loss_forward(rgb_t, torch.tensor(tgt.astype(np.float64)), kind, 0.1)
        loss.backward()
        assert_matches(np.array(loss.item()), np.array(xscale.loss_forward(rgb, tgt, kind=kind, delta=0.1)), "f64",
                       name="loss", op=f"reference loss_forward ({kind})")
        assert_matches(rgb_t.grad.numpy(), xscale.loss_backward(rgb, tgt, kind=kind, delta=0.1), "f64",
                       name="grad.rgb", op=f"reference loss backward ({kind})")


@pytest.mark.parametrize("case", CASES)
def test_whole_step(case):
    ck = ref.load_checkpoint(GOLDEN / case / "checkpoint.safetensors")
    batch = ref.load_batch(GOLDEN / case / "batch.safetensors", ck)
    theirs = ref.compute_dump(ck, batch, "float64")
    ours = xscale.Model(GOLDEN / case / "checkpoint.safetensors").step(GOLDEN / case / "batch.safetensors")
    r = assert_matches(theirs, ours, "f64")
    assert sum(t["status"] == "pass" for t in r["tensors"]) >= 19


def test_a_wrong_smoothstep_derivative_in_the_reference_is_caught(monkeypatch):
    class WrongSmoothstep(torch.autograd.Function):
        @staticmethod
        def forward(ctx, t):
            ctx.save_for_backward(t)
            return t * t * (3 - 2 * t)

        @staticmethod
        def backward(ctx, g):
            (t,) = ctx.saved_tensors
            return g * 6 * t  # should be 6 t (1 - t)

    # The same check passes with the reference as written ...
    ours, theirs = grid_ops("tiny-tcnn-smoothstep")
    assert_matches(theirs[2], ours[2], "f64", name="grad.batch.positions", op="reference HashGrid.backward_positions")
    # ... and fails, naming the op and the tensor, with the broken derivative.
    monkeypatch.setattr(ref, "smoothstep", WrongSmoothstep.apply)
    ours, theirs = grid_ops("tiny-tcnn-smoothstep")
    assert_matches(theirs[0], ours[0], "f64", name="fwd.grid_h", op="reference HashGrid.forward")  # values right
    with pytest.raises(AssertionError) as e:
        assert_matches(theirs[2], ours[2], "f64", name="grad.batch.positions", op="reference HashGrid.backward_positions")
    msg = str(e.value)
    assert msg.startswith("op reference HashGrid.backward_positions: 1 tensor(s) out of tolerance set 'f64' (grad.batch.positions)")
    assert "FAIL grad.batch.positions: " in msg
    # The whole-model check catches it too, in the position gradient only.
    ck = ref.load_checkpoint(GOLDEN / "tiny-tcnn-smoothstep" / "checkpoint.safetensors")
    batch = ref.load_batch(GOLDEN / "tiny-tcnn-smoothstep" / "batch.safetensors", ck)
    theirs = ref.compute_dump(ck, batch, "float64")
    ours = xscale.Model(GOLDEN / "tiny-tcnn-smoothstep" / "checkpoint.safetensors").step(
        GOLDEN / "tiny-tcnn-smoothstep" / "batch.safetensors")
    with pytest.raises(AssertionError) as e:
        assert_matches(theirs, ours, "f64")
    assert "(grad.batch.positions)" in str(e.value)
