"""Stiff and extreme cases of the tracer: finite values of known accuracy or a clear flag."""

import math

import drjit as dr
import numpy as np
import pytest

from lfsim.optics.tracer import Status

from test_examples import sag_numpy


@pytest.mark.parametrize("theta_deg", [85.5, 88.0, 89.5])
def test_grazing_incidence_on_a_sphere_obeys_snell(make_design, theta_deg):
    n2 = 1.5
    d = make_design(f"""
        [[surfaces]]
        radius = 30.0
        thickness = 5.0
        material = {n2}
        [[surfaces]]
        dummy = true
    """)
    # Aim at the point at height h so that the angle to the local normal is theta.
    h = 6.0
    z = 30.0 - math.sqrt(30.0**2 - h * h)
    normal = np.array([0.0, -h, 30.0 - z]) / 30.0  # unit, pointing +z-ish
    th = math.radians(theta_deg)
    # Direction in the y-z plane at angle th from the normal.
    t = np.array([0.0, normal[2], -normal[1]])
    dirs = math.cos(th) * normal + math.sin(th) * t
    hit = np.array([0.0, h, z])
    r = d.trace((hit - 3.0 * dirs)[None], dirs[None], record=True)
    assert r.status[0] == Status.OK
    np.testing.assert_allclose(r.path[0, 0], hit, atol=1e-12)
    cos_out = float(r.directions[0] @ normal)
    sin_out = math.sqrt(max(0.0, 1 - cos_out**2))
    assert abs(n2 * sin_out - math.sin(th)) < 1e-13


@pytest.mark.parametrize("norm_radius", [1.0, 8.0])
def test_xy_coefficients_spanning_1e_2_to_1e_20(make_design, norm_radius):
    # Even-in-x terms of total order 2..10, magnitudes log-spaced from 1e-2 to 1e-20.
    names = [f"x{i}y{order - i}" for order in range(2, 11) for i in range(0, order + 1, 2)]
    mags = np.logspace(-2, -20, len(names))
    coef = {n: float(m) * (1 if k % 2 else -1) for k, (n, m) in enumerate(zip(names, mags))}
    xy = ", ".join(f"{k_} = {v:.17g}" for k_, v in coef.items())
    d = make_design(f"""
        [[surfaces]]
        radius = 40.0
        xy = {{ {xy} }}
        norm_radius = {norm_radius}
        thickness = 5.0
        material = 1.6
        semi_diameter = 6.0
        [[surfaces]]
        dummy = true
    """)
    s = d.surfaces[0]
    assert min(abs(v) for v in s.xy.values()) == pytest.approx(1e-20)
    g = np.linspace(-5.5, 5.5, 23)
    X, Y = np.meshgrid(g, g)
    o = np.stack([X.ravel(), Y.ravel(), np.full(X.size, -1.0)], 1)
    dirs = np.tile([0.0, 0.05, 1.0], (len(o), 1))
    for prec, tol in (("float64", 1e-12), ("float32", 2e-5)):
        r = d.trace(o, dirs, precision=prec, record=True)
        ok = r.status == 0
        assert ok.mean() > 0.7 and set(r.status.tolist()) <= {0, Status.VIGNETTED}
        res = r.path[0, ok, 2] - sag_numpy(s, r.path[0, ok, 0], r.path[0, ok, 1])
        assert np.max(np.abs(res)) < tol, (prec, np.max(np.abs(res)))
    # Gradients with respect to the tiniest and the largest coefficient are finite.
    tr = d.tracer()
    names = d.parameter_names()
    P = tr.params()
    dr.enable_grad(P)
    out = tr.trace(P, tr.rays(o, dirs))
    dr.backward(dr.sum(dr.select(out.status == 0, out.p.y, 0.0)))
    grad = np.asarray(dr.grad(P))
    assert np.all(np.isfinite(grad))
    assert grad[names.index("S1.x0y10")] != 0.0


@pytest.mark.parametrize("frac", [0.999, 0.9999])
def test_hemispherical_lenslets_hit_near_their_rim(make_design, frac):
    R = 0.5  # hemisphere: the lenslet's semi-aperture equals its radius
    lenslet = f"""
        [arrays.mla]
        m = 3
        n = 3
        pitch = 1.0
        [[surfaces]]
        radius = {R}
        material = 1.5
        array = "mla"
        semi_diameter = {R}
    """
    # Full plano-convex lenslet, and a front-face-only copy to check Snell at the rim.
    d = make_design(lenslet + 'thickness = 0.5\n[[surfaces]]\nthickness = 1.0\narray = "mla"\n'
                    "[[surfaces]]\ndummy = true\n")
    front = make_design(lenslet + "thickness = 0.2\n[[surfaces]]\ndummy = true\n", name="front.toml")
    h = frac * R
    o = np.array([[1.0 + h, 1.0, -1.0], [1.0, 1.0 - h, -1.0], [1.0 + 0.3, 1.0, -1.0]])
    r = d.trace(o, np.tile([0.0, 0.0, 1.0], (3, 1)), record=True)
    assert np.all(np.isfinite(r.positions)) and np.all(np.isfinite(r.directions))
    assert r.lenslet.tolist() == [[2, 2]] * 3
    # Inside the glass the rim ray leaves the axis direction by θi − θt; at the flat back
    # face that exceeds the critical angle, so it is totally internally reflected there.
    th_i, th_t = math.asin(frac), math.asin(frac / 1.5)
    assert math.sin(th_i - th_t) > 1 / 1.5
    assert r.status.tolist() == [Status.TIR, Status.TIR, Status.OK] and r.failed_at[:2].tolist() == [1, 1]
    # Snell at the rim itself, on the front-face-only copy.
    f = front.trace(o[:1], np.array([[0.0, 0.0, 1.0]]), record=True)
    assert f.status[0] == Status.OK
    n_hat = (f.path[0, 0] - [1.0, 1.0, R]) / R  # centre of curvature at z = R
    assert abs(math.sqrt(1 - n_hat[2] ** 2) - frac) < 1e-9 * 50  # sin θi = h/R
    sin_t = np.linalg.norm(np.cross(f.directions[0], n_hat))
    assert abs(1.5 * sin_t - frac) < 1e-12


def test_101_by_101_lenslet_array(make_design):
    d = make_design("""
        [arrays.mla]
        m = 101
        n = 101
        pitch = [0.5, 0.4]
        [[surfaces]]
        radius = 1.2
        thickness = 1.0
        material = 1.49
        array = "mla"
        [[surfaces]]
        thickness = 2.0
        array = "mla"
        [[surfaces]]
        dummy = true
    """)
    idx = np.array([[0, 0], [100, 100], [50, 50], [0, 100], [73, 12]])
    x = (idx[:, 0] - 50) * 0.5
    y = (idx[:, 1] - 50) * 0.4
    o = np.stack([x, y, np.full(len(idx), -1.0)], 1)
    for prec, tol in (("float64", 1e-13), ("float32", 1e-5)):
        r = d.trace(o, np.tile([0.0, 0.0, 1.0], (len(idx), 1)), precision=prec)
        assert np.all(r.status == 0) and r.lenslet.tolist() == idx.tolist()
        assert np.max(np.abs(r.positions[:, :2] - o[:, :2])) < tol


def test_one_micron_pixels_over_a_one_metre_path(make_design):
    # Ideal lens f = 333.33 mm imaging 500 mm → 1000 mm: pixels 1 µm apart stay 2 µm apart.
    f = 1.0 / (1 / 500.0 + 1 / 1000.0)
    d = make_design(f"""
        [[surfaces]]
        type = "paraxial"
        focal_length = {f!r}
        thickness = 1000.0
        [[surfaces]]
        dummy = true
    """)
    ys = np.array([0.0, 1e-3, 2e-3, 10.0, 10.001])
    pupil = np.array([[0.0, 0.0], [5.0, 0.0], [0.0, -5.0]])
    for prec, tol in (("float64", 1e-11), ("float32", 2e-4)):
        img = []
        for y in ys:
            src = np.array([0.0, y, -500.0])
            hits = np.concatenate([pupil, np.zeros((3, 1))], 1)
            r = d.trace(np.tile(src, (3, 1)), hits - src, precision=prec)
            assert np.all(r.status == 0)
            assert np.ptp(r.positions[:, 1]) < tol  # a perfect point image
            img.append(r.positions[0, 1])
        np.testing.assert_allclose(np.diff(img), -2.0 * np.diff(ys), atol=tol)


def test_zero_thickness_elements(make_design):
    # A zero-thickness "lens" (two identical surfaces at one vertex) deviates nothing.
    d = make_design("""
        [[surfaces]]
        radius = 20.0
        thickness = 0.0
        material = "N-BK7"
        [[surfaces]]
        radius = 20.0
        thickness = 10.0
        [[surfaces]]
        dummy = true
    """)
    rng = np.random.default_rng(5)
    o = np.concatenate([rng.uniform(-5, 5, (50, 2)), np.full((50, 1), -2.0)], 1)
    dirs = np.concatenate([rng.uniform(-0.2, 0.2, (50, 2)), np.ones((50, 1))], 1)
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    r = d.trace(o, dirs)
    assert np.all(r.status == 0)
    np.testing.assert_allclose(r.directions, dirs, atol=1e-14)
