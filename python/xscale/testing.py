"""``assert_matches``: a backend's tensors against the oracle's, with ``xscale compare``'s rules.

The comparison is the Rust ``io::compare`` code of ``xscale compare`` (not a re-implementation):
per-tensor rules matched by name glob (an element passes if it meets any limit of its rule:
``max_abs``, ``max_rel``, ``max_ulp``, ``max_rel_peak`` = abs / the tensor's peak), a NaN fails
its tensor unless allowed, an infinity passes only against the same infinity, and the oracle's
``kink.slack.*`` tensors excuse gradients a correct backend computes on the other side of a ReLU
or L1 kink (docs/oracle.md §7). Built-in tolerance sets: ``f32``, ``f64``, ``fp16``,
``grid-exact``, ``exact`` (``xscale.tolerance_text(name)`` shows one with its reasons).
"""

from __future__ import annotations

import json
import os
import re
from typing import Any, Mapping, Optional, Union

import numpy as np

from . import _xscale, load

__all__ = ["assert_matches", "compare", "Report"]

_SIGNED = (np.int8, np.int16, np.int64)
_UNSIGNED = (np.uint16, np.uint64)


def _array(v: Any, name: str) -> np.ndarray:
    if hasattr(v, "detach") and hasattr(v, "cpu"):  # a torch tensor
        v = v.detach().cpu().numpy()
    a = np.asarray(v)
    if a.dtype == np.float16:
        a = a.astype(np.float32)  # exact
    elif a.dtype == np.bool_:
        a = a.astype(np.uint8)
    elif a.dtype.type in _SIGNED or a.dtype.type in _UNSIGNED:
        info = np.iinfo(np.int32 if a.dtype.type in _SIGNED else np.uint32)
        if a.size and (a.min() < info.min or a.max() > info.max):
            raise ValueError(f"{name}: {a.dtype} values outside {info.dtype}'s range")
        a = a.astype(info.dtype)
    return a if a.flags.c_contiguous else a.copy(order="C")


def _dict(x: Any, what: str, name: Optional[str]):
    if isinstance(x, (str, os.PathLike)):
        t = load(x)
        return {k: v for k, v in t.items()}, dict(t.metadata)
    if isinstance(x, Mapping):
        return {k: _array(v, k) for k, v in x.items()}, dict(getattr(x, "metadata", {}) or {})
    if name is None:
        raise TypeError(f"{what}: a single array needs name= (the tensor's name in a dump, e.g. 'fwd.grid_h')")
    return {name: _array(x, name)}, {}


def _tolerance_spec(t: Union[str, "os.PathLike[str]", Mapping[str, Any]]) -> (str, str):
    """(spec for the Rust side, how to name it)."""
    if isinstance(t, Mapping):
        return _xscale._json_to_toml(json.dumps(dict(t))), "<dict>"
    if isinstance(t, os.PathLike) or (isinstance(t, str) and (t.endswith(".toml") or os.sep in t)):
        with open(t, encoding="utf-8") as f:
            return f.read(), os.fspath(t)
    if isinstance(t, str):
        return t, repr(t)
    raise TypeError(f"tolerances: a set's name, a TOML file or a dict, got {type(t).__name__}")


class Report(dict):
    """``xscale compare``'s JSON report (a dict), with ``exit_code`` (0 pass, 1 a limit exceeded,
    2 bad input: a required tensor missing, a shape mismatch) and ``table`` (its text report)."""

    exit_code: int
    table: str


def compare(mine: Any, oracle: Any, tolerances: Any = "f32", *, name: Optional[str] = None,
            partial: Optional[bool] = None, allow_nan: bool = False, kink_slack: bool = True) -> Report:
    """Compare ``mine`` with ``oracle`` (each a dict of arrays, a :class:`xscale.Tensors`, a
    safetensors path, or one array with ``name``); the oracle is file A of ``xscale compare``.
    ``partial`` (default: True for a single array): compare only the tensors ``mine`` has,
    every rule's ``required`` off. Returns the :class:`Report`."""
    single = not isinstance(mine, (Mapping, str, os.PathLike))
    a, am = _dict(oracle, "oracle", name)
    b, bm = _dict(mine, "mine", name)
    if partial is None:
        partial = single
    spec, _ = _tolerance_spec(tolerances)
    code, table, js = _xscale._compare(a, b, spec, a_meta=am, b_meta=bm, partial=partial,
                                       allow_nan=allow_nan, kink_slack=kink_slack)
    r = Report(json.loads(js))
    r.exit_code = code
    r.table = table
    return r


def assert_matches(mine: Any, oracle: Any, tolerances: Any = "f32", *, name: Optional[str] = None,
                   op: Optional[str] = None, partial: Optional[bool] = None, allow_nan: bool = False,
                   kink_slack: bool = True) -> Report:
    """Fail (``AssertionError``) unless ``mine`` matches ``oracle`` under ``tolerances`` — a
    built-in set's name (``f32``, ``f64``, ``fp16``, ``grid-exact``, ``exact``), a TOML file or a
    dict shaped like one — with ``xscale compare``'s rules; see :func:`compare` for the inputs.

    A whole dump against the oracle's: every tensor the set requires (``batch.*``, ``fwd.*``,
    ``loss``, ``grad.*``) must be in ``mine``. One op's output: ``assert_matches(out, ref,
    "f32", name="fwd.grid_h", op="HashGrid.forward")``. The message names the op, the tensor,
    how many elements fail and the worst one (its index, both values, abs/rel/ULP error, the
    limits and their reason). A tensor no rule of the set covers fails too (name it as in a
    dump, or give a set with a ``[default]`` rule). Returns the :class:`Report` when it passes.
    """
    r = compare(mine, oracle, tolerances, name=name, partial=partial, allow_nan=allow_nan,
                kink_slack=kink_slack)
    norule = [t["name"] for t in r["tensors"] if t["status"] == "no_rule"]
    if r.exit_code == 0 and not norule:
        return r
    _, tname = _tolerance_spec(tolerances)
    what = f"op {op}" if op else "xscale.testing.assert_matches"
    lines = []
    for line in r.table.splitlines():
        detail = re.match(r"(FAIL|SHAPE) \S+: ", line)  # not the table's status rows
        kinks = line.startswith("kink pixels") and not line.startswith("kink pixels: 0 ")
        if detail or kinks or line.startswith(("MISSING ", "only in ")):
            lines.append(line.replace("only in A", "only in the oracle").replace("only in B", "only in mine"))
    failing = [t["name"] for t in r["tensors"] if t["status"] in ("fail", "shape_mismatch")]
    for n in norule:
        lines.append(f"NO RULE {n}: no rule of tolerance set {tname} matches it (name it as in a dump, e.g. "
                     f"fwd.grid_h / grad.grid_h.table, or give a set with a [default] rule)")
    head = (f"{what}: {len(failing) + len(norule)} tensor(s) out of tolerance set {tname}"
            + (f" ({', '.join(failing + norule)})" if failing or norule else "")
            + f"; compare exit {r.exit_code}. In each FAIL line a = oracle, b = yours:")
    raise AssertionError("\n".join([head] + lines))
