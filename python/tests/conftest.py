"""Shared fixtures of the package's tests: the repository's golden cases, the `xscale` binary."""

import os
import shutil
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
GOLDEN = REPO / "fixtures" / "golden"
GOLDEN_CASES = sorted(p.name for p in GOLDEN.iterdir() if (p / "checkpoint.safetensors").is_file())


def xscale_binary():
    """The `xscale` binary cargo built (XSCALE_BIN, else target/release/xscale, else PATH)."""
    for cand in (os.environ.get("XSCALE_BIN"), REPO / "target" / "release" / "xscale", shutil.which("xscale")):
        if cand and Path(cand).is_file() and os.access(cand, os.X_OK):
            return str(cand)
    return None


@pytest.fixture(scope="session")
def xscale_bin():
    b = xscale_binary()
    if b is None:
        if os.environ.get("XSCALE_REQUIRE_BIN"):
            pytest.fail("XSCALE_REQUIRE_BIN is set but no xscale binary was found (cargo build --release)")
        pytest.skip("no xscale binary (cargo build --release, or XSCALE_BIN=...): the CLI comparisons need it")
    return b


@pytest.fixture(params=GOLDEN_CASES)
def golden_case(request):
    return GOLDEN / request.param
