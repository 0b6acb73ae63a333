"""The worst-contrast search between fields (``[ini.analysis] refine``) against a dense field grid."""

import copy
from dataclasses import replace

import numpy as np

import lfsim
from lfsim.analysis.ini_analysis import contrast_min, evaluate, summarize
from lfsim.ini.model import IniModel
from lfsim.ini.subsystems import sample


def test_search_finds_the_dense_grid_minimum(scenes):
    """ini_freeform, 1 D, every 8th lenslet: 3² fields miss the worst contrast of a 17² grid by
    > 0.01 (the prism's astigmatism peaks between fields); 2 levels of search come within 0.01,
    never above the grid's own minimum, and more levels never make it worse."""
    base = IniModel(lfsim.load(scenes / "ini_freeform.toml"))

    def run(fields, refine):
        m = copy.copy(base)
        m.spec = replace(base.spec, pupil=2, mtf_grid=8, fields=fields, refine=refine)
        return evaluate(m, sample(m, stride=(8, 8), depths=[1]))

    dense = contrast_min(run(17, 0))
    grid = run(3, 0)
    found = {L: contrast_min(run(3, L)) for L in (1, 2, 3)}
    assert np.max(np.abs(contrast_min(grid) - dense)) > 0.01
    assert np.max(np.abs(found[2] - dense)) < 0.01
    for L in (1, 2, 3):
        assert np.all(found[L] <= np.min(grid["contrast"], axis=1) + 1e-15)
    assert np.all(found[2] <= found[1] + 1e-15) and np.all(found[3] <= found[2] + 1e-15)
    res = run(3, 2)
    doc = summarize(res)
    assert doc["summary"]["contrast_nyquist_min"] <= doc["summary"]["contrast_nyquist_min_grid"]
    assert doc["summary"]["contrast_refine_levels"] == 2
    worst = np.array([s["contrast_nyquist_worst_field"] for s in doc["subsystems"]])
    assert worst.shape == (len(res["subs"]), 2) and np.all(np.abs(worst) <= 1.0)
