"""Shared fixtures of the package's tests: the repository's golden cases, the `xscale` binary."""

import os
import shutil
import sys
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
def xscale_cli():
    """The command line to run `xscale` with: the binary cargo built, else the installed package's
    own (`python -m xscale`, the same program: `xscale::cli::main_with`). XSCALE_REQUIRE_BIN
    (CI) insists on the binary."""
    b = xscale_binary()
    if b is not None:
        return [b]
    if os.environ.get("XSCALE_REQUIRE_BIN"):
        pytest.fail("XSCALE_REQUIRE_BIN is set but no xscale binary was found (cargo build --release)")
    return [sys.executable, "-m", "xscale"]


@pytest.fixture(params=GOLDEN_CASES)
def golden_case(request):
    return GOLDEN / request.param
