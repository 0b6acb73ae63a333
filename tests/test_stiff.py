"""Stiff and extreme cases of the tracer: finite values of known accuracy or a clear flag.

Every case is traced in float64 and float32; each measured error (against a
known value in float64, and float32 against float64) is checked against its
bound and recorded by the ``accuracy`` fixture (printed at the end of the run).
The InI model's extreme operating points are in test_extreme.py.
"""

import math

import drjit as dr
import numpy as np
import pytest
from test_examples import sag_numpy

from lfsim.optics.tracer import Status

PRECISIONS = ("float64", "float32")
#: float32 unit roundoff. Each float32 bound below is a stated multiple of the case's rounding
#: noise, EPS32 times the magnitude rounded (mm for positions, 1 for unit vectors and sines),
#: amplified where the geometry amplifies it; the table at the end of the run lists each
#: measured error and its bound (margins 7x or more).
EPS32 = 2.0**-24


@pytest.mark.parametrize("theta_deg", [85.5, 88.0, 89.5])
def test_grazing_incidence_on_a_sphere_obeys_snell(make_design, accuracy, theta_deg):
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
    out = {}
    # Float32: a launch point rounded by EPS32 · h moves the grazing hit along the surface by
    # 1/cos θ of that (measured: up to 0.07 of it); bound 2x. Unit vectors: 16 EPS32 (measured <= 2).
    hit32 = 2 * EPS32 * h / math.cos(th)
    for prec, bound in (("float64", 1e-13), ("float32", 16 * EPS32)):
        r = d.trace((hit - 3.0 * dirs)[None], dirs[None], record=True, precision=prec)
        assert r.status[0] == Status.OK
        assert np.max(np.abs(r.path[0, 0] - hit)) < (1e-12 if prec == "float64" else hit32)
        cos_out = float(r.directions[0] @ normal)
        sin_out = math.sqrt(max(0.0, 1 - cos_out**2))
        accuracy(f"{theta_deg} deg: Snell residual n2 sin t - sin i", abs(n2 * sin_out - math.sin(th)), bound, prec)
        out[prec] = r.directions[0]
    accuracy(f"{theta_deg} deg: refracted direction", np.max(np.abs(out["float32"] - out["float64"])),
             16 * EPS32, "f32 vs f64")


@pytest.mark.parametrize("side", [-1, 1])
@pytest.mark.parametrize("interaction", ["refract", "tir"])
def test_total_internal_reflection_at_the_critical_angle(make_design, accuracy, side, interaction):
    """Glass (n = 1.5) to air at θc ± 1e-9 rad: below θc a refracting surface refracts (the ray
    leaves almost along the surface, at 90° − √(2 n cos θc · 1e-9) rad) and a TIR surface flags
    ``no_tir``; above θc the refracting surface flags ``tir`` and the TIR surface reflects.
    float32 resolves angles to about 1e-7 rad: there the status may go either way, but the
    values stay finite and the reflected or refracted ray obeys the law to float32 rounding."""
    n = 1.5
    d = make_design(f"""
        [object]
        material = {n}
        [[surfaces]]
        radius = inf
        thickness = 1.0
        material = "air"
        {'tir = true' if interaction == 'tir' else ''}
        [[surfaces]]
        dummy = true
    """)
    th = math.asin(1.0 / n) + side * 1e-9
    dirs = np.array([[0.0, math.sin(th), math.cos(th)]])
    o = np.array([[0.0, -math.tan(th), -1.0]])  # hits the vertex
    above = side > 0
    # Float32 noise: unit vectors rounded to EPS32 (bound 16 EPS32; measured <= 0.5). A ray leaving
    # at grazing has cos θt = √(1 − (n sin θ)²): a rounding of n sin θ by EPS32 moves it by up to
    # √(2 EPS32) (3.5e-4), so cos θt and the refracted direction are bounded by 3-4 √(2 EPS32).
    grazing32 = math.sqrt(2 * EPS32)
    want = {("refract", False): Status.OK, ("refract", True): Status.TIR,
            ("tir", False): Status.NO_TIR, ("tir", True): Status.OK}[(interaction, above)]
    res = {}
    for prec in PRECISIONS:
        r = d.trace(o, dirs, precision=prec, record=True)
        assert np.all(np.isfinite(r.directions)) and np.all(np.isfinite(r.positions))
        if prec == "float64":
            assert r.status[0] == want, (interaction, side, Status(int(r.status[0])).name)
        res[prec] = r
        if r.status[0] == Status.OK and interaction == "refract":
            # Snell: n sin θ = sin θt; cos θt = √(1 − n² sin² θ) ≈ √(2 n cos θc · 1e-9) ≈ 4.7e-5.
            dz = r.directions[0, 2]
            want_dz = math.sqrt(max(0.0, 1.0 - (n * math.sin(th)) ** 2))
            accuracy(f"{interaction} at θc{'+' if above else '-'}1e-9: cos θt (= {want_dz:.3g})",
                     abs(dz - want_dz) / want_dz if prec == "float64" else abs(dz - want_dz), 1e-6 if prec == "float64"
                     else 3 * grazing32, prec)
        elif r.status[0] == Status.OK:
            refl = np.array([0.0, math.sin(th), -math.cos(th)])
            accuracy(f"{interaction} at θc{'+' if above else '-'}1e-9: reflected direction",
                     np.max(np.abs(r.directions[0] - refl)), 1e-15 if prec == "float64" else 16 * EPS32, prec)
    a, b = res["float64"], res["float32"]
    if a.status[0] == b.status[0]:
        accuracy(f"{interaction} at θc{'+' if above else '-'}1e-9: direction",
                 np.max(np.abs(a.directions - b.directions)), 4 * grazing32, "f32 vs f64")
    else:  # 1e-9 rad is below float32's angular resolution: the status may differ, the values are finite
        assert {int(a.status[0]), int(b.status[0])} <= {Status.OK, Status.TIR, Status.NO_TIR}
        accuracy(f"{interaction} at θc{'+' if above else '-'}1e-9: float32 status {Status(int(b.status[0])).name}"
                 " (below its resolution)", int(b.status[0]), None, "float32")


@pytest.mark.parametrize("norm_radius", [1.0, 8.0])
def test_xy_coefficients_spanning_1e_2_to_1e_20(make_design, accuracy, norm_radius):
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
    out = {}
    # Float32 noise: EPS32 of coordinates up to 6 mm; bound 16x (measured <= 0.4 of it).
    for prec, tol in (("float64", 1e-12), ("float32", 16 * EPS32 * 6.0)):
        r = d.trace(o, dirs, precision=prec, record=True)
        ok = r.status == 0
        assert ok.mean() > 0.7 and set(r.status.tolist()) <= {0, Status.VIGNETTED}
        res = r.path[0, ok, 2] - sag_numpy(s, r.path[0, ok, 0], r.path[0, ok, 1])
        accuracy(f"R = {norm_radius}: hit - sag (mm)", np.max(np.abs(res)), tol, prec)
        out[prec] = r
    both = (out["float64"].status == 0) & (out["float32"].status == 0)
    assert np.mean(out["float64"].status != out["float32"].status) < 0.01
    scale = float(np.abs(out["float64"].positions[both]).max())  # the largest image coordinate (mm)
    accuracy(f"R = {norm_radius}: image positions (mm)",
             np.max(np.abs(out["float64"].positions[both] - out["float32"].positions[both])), 16 * EPS32 * scale,
             "f32 vs f64")
    # Gradients with respect to the tiniest and the largest coefficient are finite.
    tr = d.tracer()
    names = d.parameter_names()
    P = tr.params()
    dr.enable_grad(P)
    res_ = tr.trace(P, tr.rays(o, dirs))
    dr.backward(dr.sum(dr.select(res_.status == 0, res_.p.y, 0.0)))
    grad = np.asarray(dr.grad(P))
    assert np.all(np.isfinite(grad))
    assert grad[names.index("S1.x0y10")] != 0.0


@pytest.mark.parametrize("frac", [0.999, 0.9999])
def test_hemispherical_lenslets_hit_near_their_rim(make_design, accuracy, frac):
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
    # Inside the glass the rim ray leaves the axis direction by θi − θt; at the flat back
    # face that exceeds the critical angle, so it is totally internally reflected there.
    th_i, th_t = math.asin(frac), math.asin(frac / 1.5)
    assert math.sin(th_i - th_t) > 1 / 1.5
    # Float32 noise at the rim: EPS32 amplified by the face's slope there, 1/cos θi (22x, 71x);
    # bound 16x that (measured: 2 EPS32 for the angles, 1.2x the amplified noise for the
    # refracted direction).
    rim32 = 16 * EPS32 / math.sqrt(1 - frac**2)
    dirs = {}
    for prec in PRECISIONS:
        r = d.trace(o, np.tile([0.0, 0.0, 1.0], (3, 1)), record=True, precision=prec)
        assert np.all(np.isfinite(r.positions)) and np.all(np.isfinite(r.directions))
        assert r.lenslet.tolist() == [[2, 2]] * 3
        assert r.status.tolist() == [Status.TIR, Status.TIR, Status.OK] and r.failed_at[:2].tolist() == [1, 1]
        # Snell at the rim itself, on the front-face-only copy.
        f = front.trace(o[:1], np.array([[0.0, 0.0, 1.0]]), record=True, precision=prec)
        assert f.status[0] == Status.OK
        n_hat = (f.path[0, 0] - [1.0, 1.0, R]) / R  # centre of curvature at z = R
        accuracy(f"rim at {frac}: sin θi - h/R", abs(math.sqrt(1 - n_hat[2] ** 2) - frac),
                 5e-8 if prec == "float64" else rim32, prec)
        sin_t = np.linalg.norm(np.cross(f.directions[0], n_hat))
        accuracy(f"rim at {frac}: Snell residual", abs(1.5 * sin_t - frac), 1e-12 if prec == "float64" else rim32,
                 prec)
        dirs[prec] = f.directions[0]
    accuracy(f"rim at {frac}: refracted direction", np.max(np.abs(dirs["float64"] - dirs["float32"])), rim32,
             "f32 vs f64")


@pytest.mark.parametrize("frac", [0.999, 1.001])
def test_square_lenslets_hit_at_0999_of_their_semi_aperture(make_design, accuracy, frac):
    """A 3×3 array of square 1 mm lenslets: a ray at 0.999 of the half-width from a lenslet's axis
    (toward every edge and corner) stays in that lenslet; at 1.001 it is in the neighbour's cell."""
    d = make_design("""
        [arrays.mla]
        m = 3
        n = 3
        pitch = 1.0
        [[surfaces]]
        radius = 2.0
        conic = -0.5
        asphere = { A4 = 0.01 }
        thickness = 1.0
        material = 1.5
        array = "mla"
        aperture = { type = "rectangular", half_width = [0.5, 0.5] }
        [[surfaces]]
        thickness = 2.0
        array = "mla"
        [[surfaces]]
        dummy = true
    """)
    e = frac * 0.5
    offsets = np.array([[e, 0], [-e, 0], [0, e], [0, -e], [e, e], [-e, -e]])
    o = np.column_stack([offsets, np.full(len(offsets), -1.0)])
    res = {}
    for prec in PRECISIONS:
        r = d.trace(o, np.tile([0.0, 0.0, 1.0], (len(o), 1)), lenslet=np.ones((len(o), 2), np.int64),
                    precision=prec, record=True)
        assert np.all(np.isfinite(r.positions))
        if frac < 1:
            assert np.all(r.status == Status.OK), r.status
            # Hit on the front face at the launch point (x, y unchanged along +z).
            # float32: the launch point's own rounding, EPS32 · e; bound 4x (measured 0.2 of it).
            accuracy("0.999 of the half-width: hit (x, y) error (mm)", np.max(np.abs(r.path[0, :, :2] - offsets)),
                     1e-15 if prec == "float64" else 4 * EPS32 * e, prec)
        else:
            assert np.all(r.status == Status.VIGNETTED), r.status
        res[prec] = r
    scale = float(np.abs(res["float64"].positions).max())  # the largest image coordinate (mm)
    accuracy(f"{frac} of the half-width: positions at the image (mm)",
             np.max(np.abs(res["float64"].positions - res["float32"].positions)), 16 * EPS32 * scale, "f32 vs f64")


def test_101_by_101_lenslet_array(make_design, accuracy):
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
    out = {}
    scale = float(np.abs(o).max())  # corner lenslets 25 mm off axis
    # Float32 noise: EPS32 of the 25 mm coordinates; bound 4x (measured 0.13 of it).
    for prec, tol in (("float64", 1e-13), ("float32", 4 * EPS32 * scale)):
        r = d.trace(o, np.tile([0.0, 0.0, 1.0], (len(idx), 1)), precision=prec)
        assert np.all(r.status == 0) and r.lenslet.tolist() == idx.tolist()
        accuracy("axis rays of corner lenslets: (x, y) drift (mm)", np.max(np.abs(r.positions[:, :2] - o[:, :2])),
                 tol, prec)
        out[prec] = r.positions
    accuracy("axis rays: image positions (mm)", np.max(np.abs(out["float64"] - out["float32"])), 4 * EPS32 * scale,
             "f32 vs f64")


def test_one_micron_pixels_over_a_one_metre_path(make_design, accuracy):
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
    imgs = {}
    # Float32 noise: EPS32 of image heights up to 20 mm; bound 32x (measured <= 3.9 of it).
    f32 = 32 * EPS32 * 20.0
    for prec, tol in (("float64", 1e-11), ("float32", f32)):
        img, spread = [], 0.0
        for y in ys:
            src = np.array([0.0, y, -500.0])
            hits = np.concatenate([pupil, np.zeros((3, 1))], 1)
            r = d.trace(np.tile(src, (3, 1)), hits - src, precision=prec)
            assert np.all(r.status == 0)
            spread = max(spread, np.ptp(r.positions[:, 1]))  # a perfect point image
            img.append(r.positions[0, 1])
        accuracy("point image spread over the pupil (mm)", spread, tol, prec)
        accuracy("1 µm pixel spacing imaged (mm)", np.max(np.abs(np.diff(img) + 2.0 * np.diff(ys))), tol, prec)
        imgs[prec] = np.array(img)
    accuracy("image heights (mm)", np.max(np.abs(imgs["float64"] - imgs["float32"])), f32, "f32 vs f64")


def test_zero_thickness_elements(make_design, accuracy):
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
    out = {}
    # Float32 noise: unit vectors (two refractions) and coordinates up to ~10 mm rounded to EPS32;
    # bounds 32 EPS32 (measured 4.3) and 16 EPS32 of the largest coordinate (measured ~1).
    for prec, tol in (("float64", 1e-14), ("float32", 32 * EPS32)):
        r = d.trace(o, dirs, precision=prec)
        assert np.all(r.status == 0)
        accuracy("direction change through the element", np.max(np.abs(r.directions - dirs)), tol, prec)
        out[prec] = r.positions
    scale = float(np.abs(out["float64"]).max())
    accuracy("positions at the image (mm)", np.max(np.abs(out["float64"] - out["float32"])), 16 * EPS32 * scale,
             "f32 vs f64")
