import os
import warnings
from pathlib import Path

import numpy as np
import pytest

os.environ.setdefault("NUMBA_CACHE_DIR", "/tmp/lfsim-numba-cache")
os.environ.setdefault("MPLBACKEND", "Agg")

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
