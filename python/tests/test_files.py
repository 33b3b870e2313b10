"""Checkpoints, batches and dumps as dicts: load, save back byte for byte, configs as dicts."""

import subprocess
import sys

import numpy as np
import pytest

import xscale

from conftest import GOLDEN, REPO


@pytest.mark.parametrize("name", ["checkpoint.safetensors", "batch.safetensors", "ref_f64.safetensors"])
def test_load_save_round_trip_is_byte_identical(golden_case, tmp_path, name):
    src = golden_case / name
    t = xscale.load(src)
    assert all(isinstance(v, np.ndarray) and v.flags.c_contiguous for v in t.values())
    out = tmp_path / name
    xscale.save(out, t)
    back = xscale.load(out)
    assert sorted(back) == sorted(t) and back.metadata == t.metadata
    for k in t:
        assert back[k].dtype == t[k].dtype and back[k].shape == t[k].shape and back[k].tobytes() == t[k].tobytes()
    again = tmp_path / ("again-" + name)
    xscale.save(again, back)
    assert again.read_bytes() == out.read_bytes()


def test_a_file_the_cli_wrote_comes_back_byte_for_byte(tmp_path):
    ck = tmp_path / "init.safetensors"
    r = subprocess.run([sys.executable, "-m", "xscale", "init", "--scene", str(REPO / "fixtures" / "tiny"),
                        "--preset", "tiny", "--seed", "3", "--out", str(ck)], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    out = tmp_path / "copy.safetensors"
    xscale.save(out, xscale.load(ck))
    assert out.read_bytes() == ck.read_bytes()


def test_config_and_normalization_are_dicts(tmp_path):
    ck = xscale.load(GOLDEN / "cpu-t10" / "checkpoint.safetensors")
    cfg = ck.config
    assert cfg["grid_h"]["levels"] == 16 and cfg["deform"]["enabled"] is True and cfg["positions"] == "f64"
    assert set(ck.normalization) == {"center", "extent"}
    assert ck["grid_h.scales"].dtype == np.float32 and ck["grid_h.offsets"].dtype == np.uint32
    # A config edited as a dict and saved back is a valid checkpoint of the edited model.
    cfg["positions"] = "tcnn"
    out = tmp_path / "tcnn.safetensors"
    xscale.save(out, ck, {**ck.metadata, "config": cfg})
    m = xscale.Model(out)
    assert m.positions == "tcnn" and m.grid_h.mode == "tcnn"
    assert np.array_equal(m.grid_h.scales, ck["grid_h.scales"])
    b = xscale.load(GOLDEN / "cpu-t10" / "batch.safetensors")
    assert b.config is None and b["batch.view"].dtype == np.int32 and b["batch.valid"].dtype == np.uint8
    # Non-contiguous arrays are saved (a copy); 0-d arrays stay 0-d.
    xscale.save(tmp_path / "v.safetensors", {"a": np.arange(12.0).reshape(3, 4).T, "loss": np.array(2.5)})
    v = xscale.load(tmp_path / "v.safetensors")
    assert np.array_equal(v["a"], np.arange(12.0).reshape(3, 4).T) and v["loss"].shape == ()
