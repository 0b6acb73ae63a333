import math
import os
import warnings
from pathlib import Path

import numpy as np
import pytest

os.environ.setdefault("NUMBA_CACHE_DIR", "/tmp/lfsim-numba-cache")
os.environ.setdefault("MPLBACKEND", "Agg")
# The suite's launches are small and its time goes to compiling kernels: at LLVM
# vector width 4 (the AVX2 width of float64) they compile 2-3x faster than at the
# CPU's default 8, with the same per-lane arithmetic. test_kernel_reuse.py checks
# that traces, first-order data and aimed bundles are bit for bit the same at 8 and 4.
os.environ.setdefault("LFSIM_VECTOR_WIDTH", "4")
# Tests that check a one-line error must not see a heartbeat line when a loaded machine makes
# the work before the error take over 2 s (tests/test_progress.py checks the heartbeat itself).
os.environ.setdefault("LFSIM_HEARTBEAT_AFTER", "60")

ROOT = Path(__file__).resolve().parents[1]
SCENES = ROOT / "scenes"


@pytest.fixture
def scenes():
    return SCENES


def design_from(text: str, tmp_path, name="d.toml"):
    import lfsim

    p = tmp_path / name
    p.write_text(text)
    return lfsim.load(p)


@pytest.fixture
def make_design(tmp_path):
    return lambda text, name="d.toml": design_from(text, tmp_path, name)


def pytest_configure(config):
    warnings.filterwarnings("ignore", message=".*NumbaIRAssumptionWarning.*")
    np.set_printoptions(precision=15)


# ------------------------------------------------ measured accuracy of stiff cases
_ACCURACY: list[tuple[str, str, str, float, float]] = []


@pytest.fixture
def accuracy(request):
    """Check and record a measured error: ``accuracy(quantity, value, bound, precision="float64")``.

    Asserts ``value <= bound`` (a finite value; ``bound=None`` only reports it) and keeps the figure, so every
    stiff or extreme case reports what it measured: the table is printed at
    the end of the run (section "measured accuracy of stiff and extreme cases").
    ``precision`` says what was compared, e.g. "float64" (against a known
    value) or "f32 vs f64" (float32 against float64).
    """
    case = request.node.name.removeprefix("test_")

    def check(quantity: str, value, bound: float | None, precision: str = "float64") -> float:
        v = float(value)
        # Carried on the test's report, so the table is complete with parallel workers (xdist).
        request.node.user_properties.append(("lfsim_accuracy", (case, quantity, precision, v, bound)))
        assert math.isfinite(v), f"{case}: {quantity} ({precision}) = {v!r}"
        if bound is not None:  # None: a figure that is reported, not bounded
            assert v <= bound, f"{case}: {quantity} ({precision}) = {v:.3g} > {bound:.3g}"
        return v

    return check


def pytest_runtest_logreport(report):
    if report.when == "call":
        _ACCURACY.extend(tuple(v) for k, v in report.user_properties if k == "lfsim_accuracy")


def pytest_terminal_summary(terminalreporter):
    if not _ACCURACY:
        return
    tr = terminalreporter
    tr.section("measured accuracy of stiff and extreme cases")
    tr.write_line(f"{'case':56s} {'quantity':52s} {'compared':10s} {'measured':>10s}  bound")
    for case, q, prec, v, b in _ACCURACY:
        tr.write_line(f"{case[:56]:56s} {q[:52]:52s} {prec:10s} {v:10.3g}  {'-' if b is None else f'{b:.0e}'}")
