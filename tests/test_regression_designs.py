"""lfsim's own image-quality regression tests: shipped designs against the baselines in tests/lfsim_baselines/.

Small renders (128x72 px, 16 spp, the Fig. 9 wall seen with the eye focused
at the CDP) and a strided set of design metrics, checked with the
``lfsim_regression`` fixture (lfsim.regression.pytest_plugin) and the
baseline's own seeds (common random numbers: the most sensitive check).
After an intended change of what lfsim renders or computes, re-create them:

    .venv/bin/python -m pytest tests/test_regression_designs.py -m "slow or not slow" --lfsim-update-baselines
"""

from pathlib import Path

import pytest

SCENES = Path(__file__).resolve().parents[1] / "scenes"
SMALL = {"content": str(SCENES / "fig9_wall.toml"), "resolution": (128, 72), "spp": 16, "focus_mm": [750.0],
         "stride": (4, 4), "depths": [1.0], "set": ["ini.analysis.refine=0"]}


def test_ini_ideal_fig9_wall(lfsim_regression):
    r = lfsim_regression.check(SCENES / "ini_ideal.toml", **SMALL)
    assert r.doc["seeds"]["common_random_numbers"] and not r.doc["options_changed"]
    assert {c.group for c in r.checks} == {"image", "render", "metric"}


@pytest.mark.slow
def test_ini_coaxial_fig9_wall(lfsim_regression):
    lfsim_regression.check(SCENES / "ini_coaxial.toml", **SMALL)
