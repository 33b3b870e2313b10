"""xscale — the correctness oracle of the hash featurized manifold (XScale-NVS) in Python.

Every op of the model, forward and backward, on NumPy arrays (float32 or float64), computed by the
same Rust functions as the ``xscale`` command line (no second implementation); checkpoints,
batches and dumps as ``{name: ndarray}`` dicts; the whole model step; and
``xscale.testing.assert_matches`` with ``xscale compare``'s rules. Check a backend::

    import xscale, xscale.testing
    case = xscale.case("case")          # trained checkpoint, batch, f64 oracle dump, manifest
    xscale.testing.assert_matches(my_backend(case.checkpoint, case.batch), case.oracle, tolerances="f32")

Numerics: docs/spec.md §4 (the contract), docs/oracle.md (the guide). Inputs are never converted
silently: a wrong dtype is a ``TypeError``, a non-C-contiguous array, a wrong shape or a
non-finite position/direction a ``ValueError`` naming the argument. Results are new arrays,
bit-identical for any thread count (``set_num_threads``).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path
from typing import Any, Dict, Iterable, List, Mapping, Optional, Union

import numpy as np

from . import _xscale
from ._xscale import (  # noqa: F401  (the public ops)
    DEFAULT_KINK_THRESHOLD,
    PIXEL_CHUNK,
    SH_DIM,
    HashGrid,
    appearance_backward,
    appearance_forward,
    apply_level_weights,
    deform_backward,
    deform_forward,
    get_num_threads,
    level_weights,
    linear_backward,
    linear_forward,
    loss_backward,
    loss_forward,
    mlp_backward,
    mlp_forward,
    pool_backward,
    pool_forward,
    relu_backward,
    relu_forward,
    set_num_threads,
    sh_backward,
    sh_forward,
    sigmoid_backward,
    sigmoid_forward,
    tolerance_sets,
    tolerance_text,
)

__version__ = _xscale.__version__

PathLike = Union[str, "os.PathLike[str]"]

__all__ = [
    "Case",
    "HashGrid",
    "Model",
    "Tensors",
    "appearance_backward",
    "appearance_forward",
    "apply_level_weights",
    "case",
    "deform_backward",
    "deform_forward",
    "get_num_threads",
    "level_weights",
    "linear_backward",
    "linear_forward",
    "load",
    "load_case",
    "loss_backward",
    "loss_forward",
    "mlp_backward",
    "mlp_forward",
    "pixel_chunks",
    "pool_backward",
    "pool_forward",
    "relu_backward",
    "relu_forward",
    "save",
    "set_num_threads",
    "sh_backward",
    "sh_forward",
    "sigmoid_backward",
    "sigmoid_forward",
    "step_from_ops",
    "tolerance_sets",
    "tolerance_text",
]


class Tensors(dict):
    """A safetensors file as ``{name: numpy.ndarray}`` plus ``metadata`` (``{str: str}``).

    ``config`` is the ``config`` metadata (the model config, TOML) parsed into a dict, and
    ``normalization`` the ``normalization`` metadata (JSON) parsed; both None when absent.
    ``torch.from_numpy(t[name])`` gives a tensor without a copy.
    """

    def __init__(self, tensors: Mapping[str, Any] = (), metadata: Optional[Mapping[str, str]] = None):
        super().__init__(tensors)
        self.metadata: Dict[str, str] = dict(metadata or {})

    @property
    def config(self) -> Optional[dict]:
        text = self.metadata.get("config")
        return None if text is None else json.loads(_xscale._toml_to_json(text))

    @property
    def normalization(self) -> Optional[dict]:
        text = self.metadata.get("normalization")
        return None if text is None else json.loads(text)

    def __repr__(self) -> str:
        parts = [f"{k}: {v.dtype}{list(v.shape)}" for k, v in self.items()]
        return f"Tensors({len(self)} tensors: {', '.join(parts[:6])}{', …' if len(parts) > 6 else ''}; metadata {sorted(self.metadata)})"


def load(path: PathLike, stored: bool = False) -> Tensors:
    """Read a checkpoint, batch or dump (safetensors) into a :class:`Tensors` dict.

    A training run's model file may store a hash table by the rows Adam stepped only
    (``grid_h.table.kept`` + ``grid_h.table.mask``, header ``init_seed``; docs/spec.md §6.2):
    such a table comes back whole as ``grid_h.table`` (likewise ``grid_d.table``), every row
    left out drawn again from the seed by the same Rust code the ``xscale`` loader runs (the
    very values it trains and renders with, bit for bit), and ``init_seed`` is dropped from the
    metadata. ``stored=True`` returns the tensors and metadata exactly as the file holds them.
    """
    t, m = _xscale.load(os.fspath(path), stored)
    return Tensors(t, m)


def _c_contiguous(a: Any) -> np.ndarray:
    a = np.asarray(a)
    return a if a.flags.c_contiguous else a.copy(order="C")


def save(path: PathLike, tensors: Mapping[str, Any], metadata: Optional[Mapping[str, Any]] = None) -> None:
    """Write ``tensors`` (and ``metadata``, by default ``tensors.metadata``) as a safetensors file,
    with xscale's byte-identical atomic writer. A ``config`` given as a dict is written as TOML.
    Arrays must be float64, float32, uint32, int32 or uint8 (any layout)."""
    if metadata is None:
        metadata = getattr(tensors, "metadata", {})
    meta = {}
    for k, v in dict(metadata).items():
        if k == "config" and isinstance(v, Mapping):
            v = _xscale._json_to_toml(json.dumps(v))
        elif k == "normalization" and isinstance(v, Mapping):
            v = json.dumps(v)
        if not isinstance(v, str):
            raise TypeError(f"metadata {k!r}: values must be str (or a dict for config/normalization)")
        meta[k] = v
    _xscale.save(os.fspath(path), {k: _c_contiguous(v) for k, v in tensors.items()}, meta)


def _as_tensors(x: Union[PathLike, Mapping[str, Any]], what: str) -> Tensors:
    if isinstance(x, (str, os.PathLike)):
        return load(x)
    if isinstance(x, Mapping):
        return x if isinstance(x, Tensors) else Tensors(x, getattr(x, "metadata", None))
    raise TypeError(f"{what}: expected a path or a dict of arrays, got {type(x).__name__}")


def pixel_chunks(n: int) -> List[int]:
    """Row boundaries ``[0, 128, 256, …, n]`` of the model's pixel chunks: the shader's weight
    gradients are summed per chunk, then the chunks in order (SPEC §5); pass them as
    ``mlp_backward(..., chunks=pixel_chunks(N))`` to reproduce the model's step bit for bit."""
    return list(range(0, n, PIXEL_CHUNK)) + [n]


class Model:
    """A checkpoint's model: ``Model("checkpoint.safetensors")`` or ``Model(tensors)``.

    ``step(batch)`` is the whole model step (every ``fwd.*``, ``loss``, every ``grad.*``: what
    ``xscale dump`` writes); ``grid_h`` / ``grid_d`` are :class:`HashGrid` objects with the
    checkpoint's saved scales and positions mode; ``params`` the parameters (float32) by name;
    ``config`` the model config (dict).
    """

    def __init__(self, checkpoint: Union[PathLike, Mapping[str, Any]]):
        label = os.fspath(checkpoint) if isinstance(checkpoint, (str, os.PathLike)) else "checkpoint"
        t = _as_tensors(checkpoint, "checkpoint")
        keep = {k: _c_contiguous(v) for k, v in t.items() if not k.startswith("adam.")}
        self._m = _xscale._Model(keep, dict(t.metadata), label)
        self.config: dict = json.loads(_xscale._toml_to_json(self._m.config_toml))
        self.normalization: dict = json.loads(self._m.normalization_json)
        self.params: Dict[str, np.ndarray] = self._m.params
        self.grid_h: HashGrid = self._m.grid_h
        self.grid_d: Optional[HashGrid] = self._m.grid_d

    @property
    def positions(self) -> str:
        """The positions mode of both grids, "f64" or "tcnn" (SPEC §4.2)."""
        return self.config["positions"]

    def weights(self, net: str) -> List[np.ndarray]:
        """``net``'s ("shader" or "deform") weight matrices [out, in], layer order."""
        return [self.params[f"{net}.layers.{i}.weight"] for i in range(self._layers(net))]

    def biases(self, net: str) -> Optional[List[np.ndarray]]:
        """``net``'s biases, or None (``shader.bias = false``)."""
        if not self.config["shader"]["bias"]:
            return None
        return [self.params[f"{net}.layers.{i}.bias"] for i in range(self._layers(net))]

    def _layers(self, net: str) -> int:
        return sum(1 for k in self.params if k.startswith(f"{net}.layers.") and k.endswith(".weight"))

    def step(self, batch: Union[PathLike, Mapping[str, Any]], precision: str = "f64",
             kink_threshold: Optional[float] = None) -> Tensors:
        """The dump of ``batch``: inputs, every intermediate, the loss and every gradient, in
        ``precision`` ("f64" or "f32"); ``kink_threshold`` (f64 only) adds the ``kink.*``
        account (``xscale dump``'s default is ``DEFAULT_KINK_THRESHOLD``; None: none)."""
        b = _as_tensors(batch, "batch")
        t, m = self._m.step({k: _c_contiguous(v) for k, v in b.items()}, precision, kink_threshold)
        return Tensors(t, m)

    def manifest(self, batch: Union[PathLike, Mapping[str, Any]]) -> dict:
        """Every tensor a backend must write for ``batch`` (name, shape, dtype, meaning,
        required) and the model's switches (what tiny-cuda-nn can reproduce, what each adds)."""
        b = _as_tensors(batch, "batch")
        return json.loads(self._m.manifest({k: _c_contiguous(v) for k, v in b.items()}))

    def __repr__(self) -> str:
        g = self.config["grid_h"]
        return (f"Model(grid_h L={g['levels']} F={g['features']} T={g['log2_table_size']}, "
                f"deform={'on' if self.grid_d is not None else 'off'}, positions={self.positions!r}, "
                f"{sum(v.size for v in self.params.values())} parameters)")


class Case:
    """A backend test case (``xscale case``): ``checkpoint``, ``batch`` and ``oracle`` (the f64
    dump) as :class:`Tensors`, ``manifest`` (dict), ``tolerances`` (the TOML text of its set),
    ``tolerance_set`` (its name), ``path``."""

    def __init__(self, path: PathLike):
        p = Path(path)
        mf = p / "manifest.json"
        if not mf.is_file():
            raise ValueError(f"{p}: no manifest.json: not a case folder (make one with xscale.case({str(p)!r}))")
        self.path = p
        self.manifest: dict = json.loads(mf.read_text())
        if self.manifest.get("format") != "xscale-case-1":
            raise ValueError(f"{mf}: format {self.manifest.get('format')!r}, expected 'xscale-case-1'")
        files = self.manifest["files"]
        self.checkpoint = load(p / files["checkpoint"])
        self.batch = load(p / files["batch"])
        self.oracle = load(p / files["oracle"])
        self.tolerances: str = (p / files["tolerances"]).read_text()
        self.tolerance_set: str = files.get("tolerance_set", "f32")

    def model(self) -> Model:
        return Model(self.checkpoint)

    def __repr__(self) -> str:
        return (f"Case({str(self.path)!r}: {self.manifest['pixels']} pixels × {self.manifest['samples_per_pixel']} "
                f"sub-samples, {sum(1 for t in self.manifest['tensors'] if t['required'])} required tensors, "
                f"tolerances {self.tolerance_set!r})")


def load_case(path: PathLike) -> Case:
    """Load a case folder written by ``xscale case`` / :func:`case`."""
    return Case(path)


def case(path: PathLike, *, scene: Optional[PathLike] = None, preset: Optional[str] = None,
         config: Optional[PathLike] = None, steps: int = 20, size: int = 256, seed: int = 0,
         invalid: float = 0.3, mean_view: Optional[int] = None, tolerances: str = "f32",
         quiet: bool = True) -> Case:
    """The backend test case in folder ``path``: made by ``xscale case`` if the folder has none
    (the bundled tiny scene unless ``scene``; the tiny preset with tiny-cuda-nn-safe settings
    unless ``config``; see ``python -m xscale case --help``), loaded as it is otherwise."""
    p = Path(path)
    if not (p / "manifest.json").is_file():
        argv = [sys.executable, "-m", "xscale", "case", "--out", os.fspath(p), "--steps", str(steps),
                "--size", str(size), "--seed", str(seed), "--invalid", repr(float(invalid)),
                "--tolerances", tolerances]
        if scene is not None:
            argv += ["--scene", os.fspath(scene)]
        if preset is not None:
            argv += ["--preset", preset]
        if config is not None:
            argv += ["--config", os.fspath(config)]
        if mean_view is not None:
            argv += ["--mean-view", str(mean_view)]
        # A process of its own: training installs a Ctrl-C handler for its whole process.
        r = subprocess.run(argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        if r.returncode != 0:
            raise RuntimeError(f"xscale case failed (exit {r.returncode}):\n{r.stderr.strip()}")
        if not quiet:
            sys.stderr.write(r.stderr)
    return Case(p)


from .compose import step_from_ops  # noqa: E402  (needs the names above)
