"""`xscale.case` / `xscale case`, the manifest, and the README's backend check run as written."""

import json
import re
import subprocess
import sys

import numpy as np
import pytest

import xscale
import xscale.testing

from conftest import REPO


@pytest.fixture(scope="module")
def case_dir(tmp_path_factory):
    d = tmp_path_factory.mktemp("cases") / "case"
    xscale.case(d)
    return d


def snippet(path, heading):
    """The first ```python block after `heading` in a Markdown file."""
    text = path.read_text()
    i = text.index(heading)
    m = re.search(r"```python\n(.*?)```", text[i:], re.S)
    return m.group(1)


def test_the_case_holds_what_a_backend_needs(case_dir):
    c = xscale.load_case(case_dir)
    assert sorted(p.name for p in case_dir.iterdir()) == sorted(
        ["batch.safetensors", "checkpoint.safetensors", "config.toml", "manifest.json", "oracle.safetensors",
         "scene", "tolerances.toml"])
    cfg = c.checkpoint.config
    assert cfg["positions"] == "tcnn" and cfg["level_weight"] == "none" and not cfg["shader"]["bias"]
    assert c.manifest["tcnn_reproducible"] is True
    assert c.tolerances == xscale.tolerance_text("f32") and c.tolerance_set == "f32"
    b = c.batch
    assert b["batch.positions"].shape == (256, 4, 3)
    invalid = (b["batch.valid"] == 0).mean()
    assert 0.2 < invalid < 0.4 and b["batch.valid"].sum(1).min() >= 1
    assert (b["batch.view"][:16] == -1).all() and (b["batch.view"][16:] >= 0).all()
    # Trained: xi's last layer has moved from zero, so grid D and xi's first layer get gradient.
    assert np.abs(c.checkpoint["deform.layers.1.weight"]).max() > 1e-3
    assert np.abs(c.oracle["grad.grid_d.table"]).max() > 0 and np.abs(c.oracle["grad.deform.layers.0.weight"]).max() > 0
    # The manifest lists exactly the oracle's tensors (kink.* aside), with shapes and dtypes.
    tensors = {t["name"]: t for t in c.manifest["tensors"]}
    assert set(tensors) == {k for k in c.oracle if not k.startswith("kink.")}
    for k, t in tensors.items():
        assert tuple(t["shape"]) == c.oracle[k].shape and t["meaning"], k
        assert t["required"] == (not k.startswith(("grid_", "deform.", "shader.", "appearance."))), k
    sw = {s["key"]: s for s in c.manifest["switches"]}
    assert [n for n, _ in sw["model.shader.bias"]["other_adds"]] == [
        "deform.layers.0.bias", "deform.layers.1.bias", "grad.deform.layers.0.bias", "grad.deform.layers.1.bias",
        "grad.shader.layers.0.bias", "grad.shader.layers.1.bias", "shader.layers.0.bias", "shader.layers.1.bias"]
    assert "fwd.grid_d" in [n for n, _ in sw["model.deform.enabled"]["other_removes"]]
    assert sw["model.level_weight"]["tcnn_reproducible"] and sw["model.positions"]["value"] == "tcnn"
    # Model.manifest gives the same document for the same checkpoint and batch.
    m = xscale.Model(c.checkpoint).manifest(c.batch)
    assert m["tensors"] == c.manifest["tensors"] and m["switches"] == c.manifest["switches"]


def test_case_twice_is_the_same_case(case_dir, tmp_path):
    before = {p.name: p.read_bytes() for p in case_dir.iterdir() if p.is_file()}
    r = subprocess.run([sys.executable, "-m", "xscale", "case", "--out", str(case_dir)], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    assert {p.name: p.read_bytes() for p in case_dir.iterdir() if p.is_file()} == before
    other = tmp_path / "other"
    other.mkdir()
    (other / "notes.txt").write_text("mine")
    r = subprocess.run([sys.executable, "-m", "xscale", "case", "--out", str(other)], capture_output=True, text=True)
    assert r.returncode == 2 and "holds \"notes.txt\" and is not an earlier case" in r.stderr
    r = subprocess.run([sys.executable, "-m", "xscale", "case", "--out", str(other / "x"), "--invalid", "2"],
                       capture_output=True, text=True)
    assert r.returncode == 64 and "--invalid" in r.stderr


def test_the_readme_backend_check_runs_as_written(case_dir, tmp_path, monkeypatch):
    code = snippet(REPO / "python" / "README.md", "## Check a backend")
    assert len(code.strip().splitlines()) <= 10
    # docs/oracle.md opens with the same lines.
    assert snippet(REPO / "docs" / "oracle.md", "# xscale as a correctness oracle") == code
    # ... and so does the repository's README, on its first screen.
    assert snippet(REPO / "README.md", "# xscale") == code
    (tmp_path / "case").symlink_to(case_dir)
    monkeypatch.chdir(tmp_path)

    def run(backend):
        exec(compile(code, "python/README.md", "exec"), {"my_backend": backend})

    # A backend: the oracle's f32 instantiation (an fp32 implementation of the model).
    run(lambda ck, b: xscale.Model(ck).step(b, precision="f32"))
    # Another: the model composed from the per-op functions in float32, batch tensors copied.
    run(lambda ck, b: xscale.step_from_ops(xscale.Model(ck), b, precision="f32"))

    # A broken backend: xi's output layer gradient transposed in one block.
    def broken(ck, b):
        d = dict(xscale.Model(ck).step(b, precision="f32"))
        g = d["grad.deform.layers.1.weight"].copy()
        g[:2, :2] = g[:2, :2].T.copy()
        d["grad.deform.layers.1.weight"] = g
        return d

    with pytest.raises(AssertionError, match=r"FAIL grad.deform.layers.1.weight: \d+ of 64 elements out of tolerance; worst at \["):
        run(broken)


def test_python_m_xscale_is_the_command_line():
    r = subprocess.run([sys.executable, "-m", "xscale", "--help"], capture_output=True, text=True)
    assert r.returncode == 0 and "case" in r.stdout and "compare" in r.stdout
    r = subprocess.run([sys.executable, "-m", "xscale", "dump", "--nope"], capture_output=True, text=True)
    assert r.returncode == 64
