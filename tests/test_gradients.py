"""Reverse-mode gradients against float64 central differences."""

import math

import drjit as dr
import numpy as np
import pytest

from lfsim.optics.tracer import RayState

FREEFORM = """
[system]
aperture = { type = "epd", value = 4.0 }
[[surfaces]]
name = "A"
radius = 30.0
conic = -0.5
asphere = { A4 = 1e-5, A6 = -2e-7 }
thickness = 4.0
material = "N-BK7"
tilt = [2.0, -1.0, 0.5]
decenter = [0.1, -0.2]
semi_diameter = 8.0
[[surfaces]]
name = "B"
radius = -25.0
xy = { x2y0 = 0.02, x0y2 = -0.015, x2y1 = 0.004, x0y3 = 0.003, x1y1 = 0.002, x4y0 = 5e-4, x2y2 = -3e-4 }
norm_radius = 5.0
thickness = 3.0
tilt = [-3.0, 1.0, 0.0]
decenter = [0.0, 0.15]
[[surfaces]]
name = "C"
radius = 40.0
thickness = 2.0
material = "PMMA"
tilt = [1.5, 0.0, 0.0]
[[surfaces]]
name = "D"
radius = inf
thickness = 20.0
tilt = [0.0, 2.0, 0.0]
return_axis = false
[[surfaces]]
name = "image"
dummy = true
tilt = [1.0, 0.0, 0.0]
"""


def _bundle(tracer, n=9):
    g = np.linspace(-1.6, 1.6, n)
    X, Y = np.meshgrid(g, g)
    pts = np.stack([X.ravel(), Y.ravel()], 1)
    o, d = [], []
    for ang in (0.0, 3.0):
        a = math.radians(ang)
        dirs = np.tile([0.0, math.sin(a), math.cos(a)], (len(pts), 1))
        o.append(np.concatenate([pts, np.full((len(pts), 1), -2.0)], 1))
        d.append(dirs)
    o, d = np.concatenate(o), np.concatenate(d)
    # Two rays that fail (outside the clear aperture, and missing entirely).
    o = np.concatenate([o, [[0.0, 9.0, -2.0], [0.0, 0.0, -2.0]]])
    d = np.concatenate([d, [[0.0, 0.0, 1.0], [0.0, 1.0, 1e-3]]])
    return tracer.rays(o, d)


def spot_merit(tracer, P, rays):
    """Mean squared distance of the image points from their centroid (mm²)."""
    out = tracer.trace(P, rays)
    ok = out.status == 0
    w = dr.select(ok, 1.0, 0.0)
    n = dr.sum(w)
    cx = dr.sum(dr.select(ok, out.p.x, 0.0)) / n
    cy = dr.sum(dr.select(ok, out.p.y, 0.0)) / n
    r2 = dr.select(ok, dr.square(out.p.x - cx) + dr.square(out.p.y - cy), 0.0)
    return dr.sum(r2) / n, out


@pytest.fixture(scope="module")
def freeform(tmp_path_factory):
    import lfsim

    p = tmp_path_factory.mktemp("ff") / "freeform.toml"
    p.write_text(FREEFORM)
    return lfsim.load(p)


def test_reverse_gradients_match_central_differences(freeform):
    tr = freeform.tracer("float64")
    rays = _bundle(tr)
    v0 = np.asarray(freeform.system.parameter_values(587.5618))
    P = tr.params(values=v0)
    dr.enable_grad(P)
    m, out = spot_merit(tr, P, rays)
    dr.backward(m)
    ad = np.asarray(dr.grad(P))
    status = np.asarray(out.status)
    assert (status != 0).sum() == 2 and np.all(np.isfinite(ad))

    def f(v):
        with dr.suspend_grad():
            return float(spot_merit(tr, tr.params(values=v), rays)[0][0])

    def central(i, h):
        vp, vm = v0.copy(), v0.copy()
        vp[i] += h
        vm[i] -= h
        return (f(vp) - f(vm)) / (2 * h)

    names = freeform.parameter_names()
    steps = [1e-6 * max(1.0, abs(v)) if not names[i].endswith("curvature") else 1e-7 for i, v in enumerate(v0)]
    fd = np.array([central(i, h) for i, h in enumerate(steps)])
    scale = np.max(np.abs(fd))
    checked = np.abs(fd) > 1e-6 * scale
    rel = np.abs(ad - fd) / np.maximum(np.abs(fd), 1e-300)
    # Bound: 1e-7 (float64 rounding of the merit over h) or 4x the difference's own noise,
    # whichever is larger; at most 1e-5, which a wrong derivative must exceed. Noise: the same
    # difference at 2h moves by 3x its truncation (∝ h²) plus its rounding (∝ 1/h); up to 8e-7
    # of the derivative here (A.A6). It is measured where the error passes 1e-7 (5 of 41
    # parameters), the only place the larger of the two can matter.
    noise = np.zeros_like(fd)
    for i in np.where(checked & (rel > 1e-7))[0]:
        noise[i] = abs(central(i, 2 * steps[i]) - fd[i]) / abs(fd[i])
    tol = np.maximum(1e-7, 4 * noise)
    report = {names[i]: (ad[i], fd[i], rel[i], tol[i]) for i in np.where(checked)[0]}
    assert checked.sum() >= 20, report
    assert any(n.startswith("B.x") for n in np.array(names)[checked])
    assert any(".tilt_" in n for n in np.array(names)[checked])
    assert any(".index" in n for n in np.array(names)[checked])
    assert np.all(tol[checked] <= 1e-5), report
    worst = max(report.items(), key=lambda kv: kv[1][2] / kv[1][3])
    assert worst[1][2] < worst[1][3], worst
    # Parameters with no effect have (near) zero gradient in both.
    assert np.all(np.abs(ad[~checked]) <= 1e-5 * scale + 1e-12)


def test_gradients_finite_for_failing_rays(freeform):
    tr = freeform.tracer("float64")
    o = np.array([[0.0, 50.0, -2.0], [0.0, 0.0, -2.0], [0.0, 7.99, -2.0]])
    d = np.array([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [0.0, 0.3, 1.0]])
    rays = tr.rays(o, d)
    P = tr.params()
    dr.enable_grad(P)
    out = tr.trace(P, rays)
    loss = dr.sum(out.p.x + out.p.y + out.p.z + out.opl + out.d.x)
    dr.backward(loss)
    g = np.asarray(dr.grad(P))
    assert np.all(np.isfinite(g))
    assert np.all(np.isfinite(np.asarray(out.p.x)))


def test_batched_parameter_blocks_give_the_same_rays(freeform):
    """Per-ray parameter blocks (for Jacobians / configurations) in one launch."""
    tr = freeform.tracer("float64")
    T = tr.T
    v0 = np.asarray(freeform.system.parameter_values(587.5618))
    v1 = v0.copy()
    v1[freeform.parameter_names().index("B.x0y2")] += 1e-3
    rays = _bundle(tr, 5)
    n = dr.width(rays.p)
    both = RayState(T.Array3(*(dr.concat([rays.p[i], rays.p[i]]) for i in range(3))),
                    T.Array3(*(dr.concat([rays.d[i], rays.d[i]]) for i in range(3))))
    block = T.UInt32(np.repeat([0, 1], n).astype(np.uint32))
    with dr.suspend_grad():
        out = tr.trace(tr.params(values=np.concatenate([v0, v1])), both, block=block)
        ref0 = tr.trace(tr.params(values=v0), rays)
        ref1 = tr.trace(tr.params(values=v1), rays)
    y = np.asarray(out.p.y)
    np.testing.assert_array_equal(y[:n], np.asarray(ref0.p.y))
    np.testing.assert_array_equal(y[n:], np.asarray(ref1.p.y))


def test_batched_forward_jacobian_matches_central_differences(freeform):
    tr = freeform.tracer("float64")
    rays = _bundle(tr, 4)
    v0 = np.asarray(freeform.system.parameter_values(587.5618))
    names = ["A.curvature", "A.A4", "B.x2y1", "B.tilt_x", "B.decenter_y", "C.thickness", "A.index",
             "D.tilt_y", "image.tilt_x"]
    J, status = tr.jacobian(v0, rays, names)
    assert J.shape == (len(names), 6, dr.width(rays.p))
    ok = status == 0
    def central(i, h):
        vp, vm = v0.copy(), v0.copy()
        vp[i] += h
        vm[i] -= h
        with dr.suspend_grad():
            a, b = tr.trace(tr.params(values=vp), rays), tr.trace(tr.params(values=vm), rays)
        return (np.asarray(a.p.y) - np.asarray(b.p.y)) / (2 * h)

    for k, name in enumerate(names):
        i = freeform.parameter_names().index(name)
        h = 1e-6 * max(1.0, abs(v0[i]))
        fd = central(i, h)
        err = np.max(np.abs(J[k, 1, ok] - fd[ok]))
        # Bound (relative to s = max(1, |derivative|)): 1e-8 (float64 rounding over h) or 4x the
        # difference's noise, its change at step 2h (3x its truncation plus its rounding; measured
        # <= 2e-9), whichever is larger; at most 1e-6, which a wrong derivative must exceed. The
        # second step is taken only where the error passes 1e-8 (none here).
        s = max(1.0, np.max(np.abs(fd[ok])))
        noise = np.max(np.abs(central(i, 2 * h) - fd)[ok]) if err >= 1e-8 * s else 0.0
        tol = max(1e-8 * s, 4 * noise)
        assert tol <= 1e-6 * s, (name, noise, s)
        assert err < tol, (name, err, noise)
