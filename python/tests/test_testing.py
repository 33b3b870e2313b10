"""xscale.testing.assert_matches: compare's rules (limits, NaN, kink slack, required tensors),
and messages that name the op, the tensor and the worst element."""

import numpy as np
import pytest

import xscale
from xscale.testing import assert_matches, compare

from conftest import GOLDEN

CASE = GOLDEN / "tiny-tcnn-smoothstep"


@pytest.fixture(scope="module")
def dumps():
    m = xscale.Model(CASE / "checkpoint.safetensors")
    b = xscale.load(CASE / "batch.safetensors")
    return m.step(b, "f64", kink_threshold=xscale.DEFAULT_KINK_THRESHOLD), m.step(b, "f32")


def test_f32_dump_passes_f32_set_and_fails_exact(dumps):
    oracle, f32 = dumps
    r = assert_matches(f32, oracle, "f32")
    assert r.exit_code == 0
    # Every tensor is compared under a rule: the echoed parameters too (no "no rule").
    assert {t["status"] for t in r["tensors"]} == {"pass"}
    assert any(t["name"] == "grid_h.table" for t in r["tensors"])
    with pytest.raises(AssertionError, match=r"tensor\(s\) out of tolerance set 'exact'"):
        assert_matches(f32, oracle, "exact")


def test_one_wrong_element_is_named(dumps):
    oracle, f32 = dumps
    mine = dict(f32)
    g = mine["grad.grid_h.table"].copy()
    i = np.unravel_index(np.argmax(np.abs(g)), g.shape)
    g[i] *= 1.01
    mine["grad.grid_h.table"] = g
    with pytest.raises(AssertionError) as e:
        assert_matches(mine, oracle, "f32")
    msg = str(e.value)
    assert "(grad.grid_h.table)" in msg
    assert f"FAIL grad.grid_h.table: 1 of {g.size} elements out of tolerance; worst at [{i[0]},{i[1]}]" in msg
    assert "a = oracle, b = yours" in msg and "rel-peak" in msg


def test_a_missing_required_tensor_fails(dumps):
    oracle, f32 = dumps
    mine = {k: v for k, v in f32.items() if k != "grad.deform.layers.0.weight"}
    with pytest.raises(AssertionError, match=r"MISSING grad.deform.layers.0.weight: required by rule \"grad.\*\" but missing from B"):
        assert_matches(mine, oracle, "f32")
    # Parameters are not required: a backend may leave them out.
    params = set(xscale.Model(CASE / "checkpoint.safetensors").params) | {"grid_h.scales", "grid_h.offsets"}
    assert_matches({k: v for k, v in f32.items() if k not in params}, oracle, "f32")


def test_nan_fails_unless_allowed(dumps):
    oracle, _ = dumps
    x = oracle["fwd.rgb"].copy()
    x[0, 0] = np.nan
    with pytest.raises(AssertionError, match=r"FAIL fwd.rgb: 1 of"):
        assert_matches(x, oracle["fwd.rgb"], "f64", name="fwd.rgb")
    both = {"fwd.rgb": x}
    assert_matches(both, both, "f64", partial=True, allow_nan=True)
    with pytest.raises(AssertionError, match=r"NaN"):
        assert_matches(both, both, "f64", partial=True)


def test_single_op_output_and_unknown_names(dumps):
    oracle, f32 = dumps
    assert_matches(f32["fwd.grid_h"], oracle["fwd.grid_h"], "f32", name="fwd.grid_h", op="HashGrid.forward")
    bad = f32["fwd.grid_h"] * np.float32(1.001)
    with pytest.raises(AssertionError) as e:
        assert_matches(bad, oracle["fwd.grid_h"], "f32", name="fwd.grid_h", op="HashGrid.forward")
    assert str(e.value).startswith("op HashGrid.forward: 1 tensor(s) out of tolerance set 'f32' (fwd.grid_h)")
    with pytest.raises(AssertionError, match=r"NO RULE hashgrid_out: no rule of tolerance set 'f32'"):
        assert_matches(f32["fwd.grid_h"], oracle["fwd.grid_h"], "f32", name="hashgrid_out")
    with pytest.raises(TypeError, match=r"needs name="):
        assert_matches(f32["fwd.grid_h"], oracle["fwd.grid_h"], "f32")
    # A dict of rules, like a tolerance file.
    assert_matches(bad, oracle["fwd.grid_h"], {"rule": [{"pattern": "fwd.*", "max_rel_peak": 2e-3}]}, name="fwd.grid_h")


def test_kink_slack_comes_from_the_oracle_only():
    a = {"grad.x": np.array([1.0, 2.0]), "kink.slack.grad.x": np.array([0.6, 0.0], np.float32),
         "kink.pixels": np.array([0.0]), "kink.threshold": np.array(1e-5)}
    b = {"grad.x": np.array([1.5, 2.0])}
    tol = {"rule": [{"pattern": "grad.*", "max_abs": 1e-3}]}
    r = assert_matches(b, a, tol)
    assert r["tensors"][0]["stats"]["n_kink"] == 1
    with pytest.raises(AssertionError, match=r"FAIL grad.x"):
        assert_matches(b, a, tol, kink_slack=False)
    with pytest.raises(AssertionError, match=r"FAIL grad.x"):
        assert_matches({**b, "kink.slack.grad.x": np.array([9.0, 9.0], np.float32)}, {"grad.x": a["grad.x"]}, tol)


def test_compare_report_and_tolerance_sets(tmp_path):
    assert xscale.tolerance_sets() == ["f32", "f64", "fp16", "grid-exact", "exact"]
    assert "max_rel_peak = 3.814697265625e-6" in xscale.tolerance_text("f32")
    with pytest.raises(ValueError, match=r"not a built-in set"):
        compare({"loss": np.array(1.0)}, {"loss": np.array(1.0)}, "f31")
    f = tmp_path / "t.toml"
    f.write_text('[[rule]]\npattern = "loss"\nmax_abs = 0.5\n')
    r = compare({"loss": np.array(1.2)}, {"loss": np.array(1.0)}, str(f))
    assert r.exit_code == 0 and r["tensors"][0]["stats"]["max_abs"] == pytest.approx(0.2)
