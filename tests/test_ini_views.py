"""Stacked first-order views (lfsim.ini.views) against the model's per-view methods."""

import numpy as np

import lfsim
from lfsim.ini.model import IniModel
from lfsim.ini.subsystems import sample
from lfsim.ini.views import StackedViews
from lfsim.metrics import pupil


def test_stacked_views_equal_the_per_view_references(scenes):
    """Display layout (Eqs. 1-2), paraxial chief and marginal rays, d_v (Eq. 5), the
    FOV (Eqs. 7-9) and the EFL of several re-linearized views, all at once, equal each view's own
    ``ei_centers`` / ``paraxial_vw`` / ``state`` to 1e-12 mm."""
    model = IniModel(lfsim.load(scenes / "ini_freeform.toml"))
    names = model.tracer.names
    nd = len(model.depths)
    base = np.array([model.values(k) for k in range(nd)])
    vals = []
    for name, h in (("S3.x2y0", 0.05), ("A1a.curvature", 1e-3), ("S1.tilt_x", 0.3)):
        b = base.copy()
        b[:, names.index(name)] += h
        vals.append(b)
    views = model.linear_views(np.array(vals))
    subs = sample(model, stride=(8, 4), symmetry="none")
    ref = StackedViews(model, views).references(subs)
    for v, w in enumerate(views):
        own = sample(w, stride=(8, 4), symmetry="none")
        assert np.max(np.abs(ref["display"][v] - own.display)) < 1e-12
        for kk in range(nd):
            sel = subs.k == kk
            sd = own.display[sel]
            c = np.broadcast_to(subs.center[sel][:, None, :], sd.shape)
            pc = w.paraxial_vw(kk, sd, c, np.zeros_like(sd))
            par_c = pc[..., 2:4] - pc[..., 0:2] * (w.depths[kk] / 1000.0)
            assert np.max(np.abs(ref["par_c"][v][sel] - par_c)) < 1e-12
            sm = np.broadcast_to(sd[:, :, None, :], sd.shape[:2] + (4, 2))
            cm = np.broadcast_to(subs.center[sel][:, None, None, :], sm.shape)
            pm = w.paraxial_vw(kk, sm, cm, np.broadcast_to(pupil.MARGINAL, sm.shape))[..., 0:2]
            assert np.max(np.abs(ref["par_m"][v][sel] - pm)) < 1e-12
            assert np.allclose(ref["d_v"][v][sel], np.mean(w.state(kk).d_v), rtol=1e-13, atol=0)
        efl = -0.5 * (1.0 / w.JG[:, 2, 0] + 1.0 / w.JG[:, 3, 1])
        assert np.allclose(ref["efl"][v], efl, rtol=1e-14, atol=0)
        for kk in range(nd):
            assert np.allclose(ref["fov"][v, kk], w.state(kk).fov_deg, rtol=1e-12, atol=0)
            assert np.allclose(ref["pixel"][v, kk], w.state(kk).pixel_arcmin, rtol=1e-12, atol=0)
            assert np.allclose(ref["ei_pitch"][v, kk], w.state(kk).p_ei, rtol=1e-12, atol=0)
    # the views really differ (the test would not notice a stack that ignores them)
    assert np.max(np.abs(ref["display"][0] - ref["display"][2])) > 1e-4
