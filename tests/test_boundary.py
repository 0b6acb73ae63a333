"""Boundary term of render derivatives (lfsim/render/boundary.py): the total derivative
against the full central difference and its Monte Carlo noise, the per-pixel Jacobian
against the reverse-mode term, exact zeros where no edge moves, and the refusals."""

import numpy as np
import pytest
from conftest import ROOT

SMALL = {"arrays.mla.m": 5, "arrays.mla.n": 3}  # ini_ideal with 5 x 3 lenslets


@pytest.fixture(scope="module")
def setup():
    from lfsim.content import load_content
    from lfsim.design.overrides import load_with_overrides
    from lfsim.render import gradcheck as gc
    from lfsim.render.diff_render import AnalyticRenderer, ViewSpec

    design = load_with_overrides(ROOT / "scenes/ini_ideal.toml", SMALL)
    content = load_content(ROOT / "scenes/fig9_wall.toml")
    r = AnalyticRenderer(design, ViewSpec(resolution=(48, 27), spp=64, focus_mm=[600.0, 1400.0], cdp_mm=750.0),
                         content=content)
    targets = gc.natural_targets(r, content, spp=64)
    return r, content, targets, gc.RenderLoss(r, targets)


def test_total_derivative_matches_the_full_difference(setup):
    """Total AD (interior + boundary) = the full central difference at the edge step, within
    5 % or 3 sigma of the difference's noise; the interior alone misses it."""
    from lfsim.render import gradcheck as gc

    r, _, targets, _ = setup
    # Measured here: totals within 1.4 sigma; interior AD 5.5, 10.9 and 5.7 sigma off.
    names = ["TL.power", "EP.power", "EP.thickness"]
    doc = gc.gradcheck(r, targets, names)
    assert doc["total"]
    missed = 0
    for p in doc["params"]:
        assert {"ad_total", "ad_boundary", "fd_total", "fd_noise", "total_rel_err", "total_sigma",
                "total_ok"} <= set(p)
        # The yardstick is tight enough to fail: the noise is a fraction of the derivative.
        assert 0.0 < p["fd_noise"] < 0.35 * abs(p["fd_total"]), p
        assert p["total_ok"], p
        assert np.isclose(p["ad_total"], p["ad"] + p["ad_boundary"], rtol=1e-12)
        tol = max(gc.TOTAL_REL_TOL * abs(p["fd_total"]), gc.TOTAL_SIGMAS * p["fd_noise"])
        missed += abs(p["ad"] - p["fd_total"]) > tol
    # Interior-only AD fails the same test for the parameters that move lenslet edges.
    assert missed == len(names), doc["params"]


def test_parameters_that_move_no_edge_have_no_boundary_term(setup):
    """The lenslet power and the display gap do not move where eye rays meet the cells or
    apertures: their boundary term is 0 (to rounding of the other terms)."""
    from lfsim.render import gradcheck as gc

    r, _, _, loss = setup
    names = ["MLA.power", "object.distance", "TL.power"]
    idx = [r.index[n] for n in names]
    _, gi = gc.gradient(loss, None, idx)
    _, gt = gc.gradient(loss, None, idx, total=True)
    b = (gt - gi)[idx]
    assert abs(b[0]) <= 1e-12 * abs(gi[idx[0]]) and abs(b[1]) <= 1e-12 * abs(gi[idx[1]]), b
    assert abs(b[2]) > abs(gi[idx[2]]), b  # the tunable lens: mostly boundary


def test_per_pixel_boundary_jacobian_sums_to_the_reverse_term(setup):
    """Σ_p dL/dI_p · (boundary column of pixel p) = the reverse-mode boundary term."""
    from lfsim.render import gradcheck as gc
    from lfsim.render.boundary import BoundaryTerm

    r, _, _, loss = setup
    names = ["TL.power", "MLA.thickness", "EP.tilt_x"]
    idx = [r.index[n] for n in names]
    _, gi = gc.gradient(loss, None, idx)
    _, gt = gc.gradient(loss, None, idx, total=True)
    bt = BoundaryTerm(r)
    acc = np.zeros(len(idx))
    for k in range(len(r.view.focus_mm)):
        Jb = bt.jacobian(None, idx, k)
        assert Jb.shape == (r.n_pixels, r.channels, len(idx)) and np.isfinite(Jb).all()
        w = 2.0 * loss.norm * (r.image_numpy(None, k).reshape(r.n_pixels, -1) - loss.targets_np[k])
        acc += np.einsum("pc,pci->i", w, Jb)
    # gt − gi cancels to the rounding of the two gradients (EP.tilt_x: boundary 9e-6).
    tol = 1e-8 * np.abs(acc) + 1e-12 * (np.abs(gt[idx]) + np.abs(gi[idx]) + np.abs(acc).max())
    assert np.all(np.abs(acc - (gt - gi)[idx]) <= tol), (acc, (gt - gi)[idx])


def test_total_gradient_of_every_design_number_is_finite(setup):
    """No NaN leaves the boundary term: the total gradient over the whole design vector
    (rays that miss, are vignetted or leave the display included) is finite."""
    from lfsim.render import gradcheck as gc

    r, _, _, loss = setup
    _, g = gc.gradient(loss, None, None, total=True)
    assert g.shape == (len(r.names),) and np.isfinite(g).all(), [n for n, v in zip(r.names, g) if not np.isfinite(v)]


def test_boundary_term_needs_the_ideal_eye(setup):
    from lfsim.render.boundary import BoundaryTerm
    from lfsim.render.diff_render import AnalyticRenderer, ViewSpec
    from lfsim.render.gradcheck import total_available

    r, _, _, _ = setup
    az = AnalyticRenderer(r.design, ViewSpec(resolution=(8, 6), spp=2, focus_mm=[1000.0], eye_model="arizona"),
                          display=r.display)
    assert not total_available(az) and total_available(r)
    with pytest.raises(ValueError, match="needs the ideal eye"):
        BoundaryTerm(az)
