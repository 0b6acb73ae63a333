"""Arrayed surfaces: each ray through its own lenslet; crossings are flagged."""

import numpy as np
import pytest

from lfsim.optics.tracer import Status

M, N, PX, PY = 5, 3, 1.0, 1.2
R_LENS, T_LENS, N_GLASS = 1.5, 1.0, 1.5
# A ray parallel to the axis of a plano-convex lenslet (convex side first) focuses
# at BFL = f - T/n from the flat back face, f = R/(n-1).
F = R_LENS / (N_GLASS - 1)
BFL = F - T_LENS / N_GLASS

MLA = f"""
[system]
aperture = {{ type = "epd", value = 0.5 }}
[arrays.mla]
m = {M}
n = {N}
pitch = [{PX}, {PY}]
center = [0.3, -0.2]
[[surfaces]]
name = "front"
radius = {R_LENS}
thickness = {T_LENS}
material = {N_GLASS}
array = "mla"
[[surfaces]]
name = "back"
radius = inf
thickness = {BFL}
array = "mla"
[[surfaces]]
name = "image"
dummy = true
"""


def centre(m, n):
    return 0.3 + (m - (M - 1) / 2) * PX, -0.2 + (n - (N - 1) / 2) * PY


@pytest.fixture(scope="module")
def mla(tmp_path_factory):
    import lfsim

    p = tmp_path_factory.mktemp("mla") / "mla.toml"
    p.write_text(MLA)
    return lfsim.load(p)


def test_ray_along_a_lenslet_axis_is_undeviated(mla):
    o, idx = [], []
    for m in range(M):
        for n in range(N):
            x, y = centre(m, n)
            o.append([x, y, -1.0])
            idx.append([m, n])
    o = np.array(o)
    r = mla.trace(o, np.tile([0.0, 0.0, 1.0], (len(o), 1)))
    assert np.all(r.status == 0)
    np.testing.assert_array_equal(r.lenslet, idx)
    np.testing.assert_allclose(r.positions[:, :2], o[:, :2], atol=1e-14)
    np.testing.assert_allclose(r.directions, np.tile([0, 0, 1.0], (len(o), 1)), atol=1e-15)


def test_paraxial_rays_focus_on_their_own_lenslet_axis(mla):
    rng = np.random.default_rng(1)
    o, idx = [], []
    for m in range(M):
        for n in range(N):
            x, y = centre(m, n)
            for dx, dy in rng.uniform(-1e-3, 1e-3, (4, 2)):
                o.append([x + dx, y + dy, -1.0])
                idx.append((m, n))
    o = np.array(o)
    r = mla.trace(o, np.tile([0.0, 0.0, 1.0], (len(o), 1)))
    c = np.array([centre(*k) for k in idx])
    assert np.all(r.status == 0)
    # Paraxial focus: residual spherical aberration at h = 1 µm is < 1e-9 mm.
    assert np.max(np.abs(r.positions[:, :2] - c)) < 1e-9


def test_ray_crossing_into_a_neighbour_is_flagged(mla):
    x, y = centre(2, 1)
    # Enters lenslet (2, 1) near its +x edge heading outward steeply: at the back
    # face it is in lenslet (3, 1)'s cell.
    o = np.array([[x + 0.45, y, -0.01], [x + 0.1, y, -0.01]])
    d = np.array([[0.5, 0.0, 1.0], [0.05, 0.0, 1.0]])
    r = mla.trace(o, d)
    assert r.status.tolist() == [Status.WRONG_LENSLET, Status.OK]
    assert r.failed_at[0] == 1  # the back face
    assert r.lenslet.tolist() == [[2, 1], [2, 1]]
    assert np.all(np.isfinite(r.positions))


def test_explicit_lenslet_assignment(mla):
    x, y = centre(1, 2)
    o = np.array([[x, y, -1.0], [x, y, -1.0]])
    d = np.tile([0.0, 0.0, 1.0], (2, 1))
    r = mla.trace(o, d, lenslet=np.array([[1, 2], [2, 2]]))
    # Aimed through (1, 2): fine. Forced through (2, 2): its cell does not contain the ray.
    assert r.status.tolist() == [Status.OK, Status.WRONG_LENSLET]


def test_rays_outside_the_array_are_vignetted(mla):
    r = mla.trace(np.array([[10.0, 0.0, -1.0]]), np.array([[0.0, 0.0, 1.0]]))
    assert r.status[0] == Status.VIGNETTED and r.lenslet[0].tolist() == [-1, -1]


def test_float32_agrees_with_float64_on_the_array(mla):
    rng = np.random.default_rng(2)
    o = np.concatenate([rng.uniform(-2.5, 2.5, (500, 1)) + 0.3, rng.uniform(-1.7, 1.7, (500, 1)) - 0.2,
                        np.full((500, 1), -1.0)], 1)
    d = np.tile([0.0, 0.0, 1.0], (500, 1))
    a = mla.trace(o, d, precision="float64")
    b = mla.trace(o, d, precision="float32")
    ok = (a.status == 0) & (b.status == 0)
    assert ok.mean() > 0.9
    # Float32 rounding noise: EPS32 (2^-24) of the largest coordinate (3.3 mm); measured 1.3 of it.
    # Bound 8x that (2.6e-6 mm), at most 1e-5 mm.
    tol = 8 * 2.0**-24 * np.abs(a.positions[ok]).max()
    assert tol < 1e-5, tol
    assert np.max(np.abs(a.positions[ok] - b.positions[ok])) < tol


def test_monolithic_array_cell_is_picked_by_the_hit(mla):
    """cells="per_surface": a steep ray that crosses the vertex plane beyond the
    array's edge but meets the sagged face inside the edge lenslet goes through
    (the vertex-plane cell is only a first guess); a ray that misses the array
    is still vignetted; the baffled view (cells="fixed") vignettes both."""
    tr = mla.tracer()
    x_edge = 0.3 + 0.5 * M * PX
    o = np.array([[x_edge + 0.05, -0.2, -0.01], [x_edge + 0.5, -0.2, -1.0]])
    d = np.array([[-1.0, 0.0, 1.0], [0.0, 0.0, 1.0]])
    st = {}
    for cells in ("per_surface", "fixed"):
        out = tr.trace(tr.params(), tr.rays(o, d), cells=cells, record=True)
        st[cells] = np.asarray(out.status).tolist()
        if cells == "per_surface":
            hit = out.path[0][0]
            x0 = float(np.asarray(hit.x)[0])
    assert st["per_surface"] == [Status.OK, Status.VIGNETTED]
    assert st["fixed"] == [Status.VIGNETTED, Status.VIGNETTED]
    assert x_edge - 0.5 * PX < x0 < x_edge  # met inside the edge lenslet's cell
