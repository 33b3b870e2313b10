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


def test_tables_stored_by_rows_come_back_whole(tmp_path, xscale_cli):
    """A trained run's model file stores its hash tables by the rows Adam stepped (docs/spec.md
    §6.2): `load` returns them whole, bit-equal to the parameters the Rust loader builds, and
    `load(stored=True)` the file's own layout, which saves back byte for byte."""
    run = tmp_path / "run"
    r = subprocess.run(xscale_cli + ["train", "--scene", str(REPO / "fixtures" / "tiny"), "--out", str(run),
                                     "--steps", "12", "--batch", "256", "--seed", "5", "--no-eval", "-q"],
                       capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    ck = run / "checkpoint.safetensors"
    raw = xscale.load(ck, stored=True)
    assert "grid_h.table.kept" in raw and "grid_h.table" not in raw and raw.metadata["init_seed"] == "5"
    t = xscale.load(ck)
    assert not any(k.endswith((".kept", ".mask")) for k in t) and "init_seed" not in t.metadata
    assert {k for k in raw if not k.endswith((".kept", ".mask"))} <= set(t)
    for k in raw:
        if not k.endswith((".kept", ".mask")):
            assert t[k].tobytes() == raw[k].tobytes(), k
    model = xscale.Model(ck)
    for g, tensor_id in (("grid_h", 0), ("grid_d", 1)):
        name = g + ".table"
        table = t[name]
        assert table.dtype == np.float32 and table.shape == (int(raw[g + ".offsets"][-1]), 2)
        # Bit-equal to the parameters `xscale render`/`eval` run with.
        assert table.tobytes() == model.params[name].tobytes(), name
        if name + ".mask" not in raw:
            continue
        # The stored rows where the mask says, every other row its initial value.
        bits = np.unpackbits(raw[name + ".mask"], bitorder="little")[: table.shape[0]].astype(bool)
        assert bits.sum() == raw[name + ".kept"].shape[0] and 0 < bits.sum() < bits.size
        assert table[bits].tobytes() == raw[name + ".kept"].tobytes()
        init = getattr(model, g).init_table(seed=5, tensor_id=tensor_id)
        assert table[~bits].tobytes() == init[~bits].tobytes()
    # The whole tables save as a model file the command line reads to the same parameters.
    out = tmp_path / "whole.safetensors"
    xscale.save(out, t)
    back = xscale.Model(out)
    assert all(back.params[k].tobytes() == v.tobytes() for k, v in model.params.items())
    # The stored layout round-trips byte for byte.
    copy = tmp_path / "copy.safetensors"
    xscale.save(copy, raw)
    assert copy.read_bytes() == ck.read_bytes()
    # A damaged file is an error naming the file and the tensor, in either mode of reading it
    # whole (`load`, `Model`).
    bad = dict(raw)
    bad["grid_h.table.kept"] = raw["grid_h.table.kept"][1:]
    xscale.save(tmp_path / "bad.safetensors", bad, raw.metadata)
    with pytest.raises(ValueError, match="grid_h.table.kept"):
        xscale.load(tmp_path / "bad.safetensors")
    assert "grid_h.table.kept" in xscale.load(tmp_path / "bad.safetensors", stored=True)
