"""Ideal (paraxial) thin lens: perfect imaging, equal optical paths, first order."""

import math

import drjit as dr
import numpy as np
import pytest

IDEAL = """
[system]
aperture = {{ type = "epd", value = 10.0 }}
[[surfaces]]
name = "lens"
type = "paraxial"
focal_length = {f}
thickness = {t}
semi_diameter = 8.0
[[surfaces]]
name = "image"
dummy = true
"""


@pytest.mark.parametrize("f", [50.0, -40.0])
@pytest.mark.parametrize("theta_deg", [0.0, 7.0, 25.0])
def test_plane_waves_focus_on_the_focal_plane_with_equal_paths(make_design, f, theta_deg):
    d = make_design(IDEAL.format(f=f, t=f if f > 0 else 20.0))
    th = math.radians(theta_deg)
    g = np.linspace(-5, 5, 11)
    X, Y = np.meshgrid(g, g)
    dirs = np.tile([0.0, math.sin(th), math.cos(th)], (X.size, 1))
    o = np.stack([X.ravel(), Y.ravel(), np.zeros(X.size)], 1) - 5.0 * dirs
    r = d.trace(o, dirs)
    assert np.all(r.status == 0)
    if f > 0:
        # Real focus on the back focal plane at (0, f tanθ).
        np.testing.assert_allclose(r.positions[:, :2], np.tile([0.0, f * math.tan(th)], (X.size, 1)), atol=1e-12)
        F = np.array([0.0, f * math.tan(th), f])
        # Path from the incoming wavefront (the plane through 0 ⟂ dirs) to F is the same for all rays.
        assert np.ptp(r.opl + o @ dirs[0]) < 1e-11
        assert np.max(np.abs(r.positions - F)) < 1e-12
    else:
        # Virtual focus in front: the exit rays all point away from F = (0, f tanθ, f).
        F = np.array([0.0, f * math.tan(th), f])
        back = r.positions - F
        back /= np.linalg.norm(back, axis=1, keepdims=True)
        assert np.max(np.abs(np.cross(back, r.directions))) < 1e-12
        # Equal paths measured back to the virtual focus: OPL - |P - F| is constant.
        assert np.ptp(r.opl + o @ dirs[0] - np.linalg.norm(r.positions - F, axis=1)) < 1e-11


def test_finite_conjugates_image_perfectly(make_design):
    f, s = 30.0, 75.0
    s_img = 1 / (1 / f - 1 / s)
    d = make_design(IDEAL.format(f=f, t=s_img))
    for y0 in (0.0, 4.0, -9.0):
        src = np.array([1.5, y0, -s])
        g = np.linspace(-5, 5, 9)
        X, Y = np.meshgrid(g, g)
        hits = np.stack([X.ravel(), Y.ravel(), np.zeros(X.size)], 1)
        dirs = hits - src
        r = d.trace(np.tile(src, (len(hits), 1)), dirs)
        m = -s_img / s
        np.testing.assert_allclose(r.positions[:, :2], np.tile([1.5 * m, y0 * m], (len(hits), 1)), atol=1e-12)


def test_first_order_and_power_gradient(make_design):
    d = make_design(IDEAL.format(f=50.0, t=50.0))
    for method in ("paraxial", "parabasal"):
        fo = d.first_order(method=method)
        assert abs(fo.efl - 50.0) < 1e-12 and abs(fo.bfl - 50.0) < 1e-12
    tr = d.tracer()
    rays = tr.rays(np.array([[0.0, 3.0, -1.0]]), np.array([[0.0, 0.1, 1.0]]))
    v0 = np.asarray(d.system.parameter_values(550.0))
    P = tr.params(values=v0)
    dr.enable_grad(P)
    out = tr.trace(P, rays)
    dr.backward(out.p.y)
    ad = np.asarray(dr.grad(P))[d.parameter_names().index("lens.power")]
    # y' = y + t (tan − y φ) → dy'/dφ = −t·y (z-slope form): exact.
    y_hit = 3.0 + 0.1 * 1.0
    assert abs(ad - (-50.0 * y_hit)) < 1e-9


def test_paraxial_lens_rejects_shape_keys(make_design):
    from lfsim import DesignError

    with pytest.raises(DesignError, match=r"surfaces\[0\]\.radius"):
        make_design(IDEAL.format(f=50.0, t=50.0).replace('type = "paraxial"', 'type = "paraxial"\nradius = 10'))
    with pytest.raises(DesignError, match=r"surfaces\[0\]\.focal_length = 0"):
        make_design(IDEAL.format(f=0, t=50.0))
