"""Tracer against closed-form answers (float64 unless stated)."""

import math

import numpy as np
import pytest

from lfsim.optics.tracer import Status


def _parallel_rays(hmax, n=41, z0=-5.0):
    h = np.linspace(-hmax, hmax, n)
    o = np.concatenate([np.stack([np.zeros(n), h, np.full(n, z0)], 1),
                        np.stack([h, np.zeros(n), np.full(n, z0)], 1),
                        np.stack([h / math.sqrt(2), h / math.sqrt(2), np.full(n, z0)], 1)])
    return o, np.tile([0.0, 0.0, 1.0], (len(o), 1))


def test_paraboloid_mirror_focuses_parallel_rays(make_design):
    # Concave paraboloid R = -200 (focal length 100): focus at z = R/2 = -100.
    d = make_design("""
        [[surfaces]]
        radius = -200.0
        conic = -1.0
        mirror = true
        thickness = -100.0
        semi_diameter = 60.0
        [[surfaces]]
        radius = inf
        dummy = true
    """)
    # The mirror's rim is 7.56 mm in front of its vertex: start the rays before it.
    o, dirs = _parallel_rays(55.0, z0=-10.0)
    r = d.trace(o, dirs)
    assert np.all(r.status == 0)
    assert np.max(np.abs(r.positions[:, :2])) < 1e-9
    np.testing.assert_allclose(r.positions[:, 2], -100.0, atol=1e-12)
    # From inside the bowl (z = -5), the rim rays would have to travel backwards to reach it.
    o, dirs = _parallel_rays(55.0)
    behind = d.trace(o, dirs).status
    h = np.abs(np.concatenate([o[:41, 1], o[41:82, 0], o[82:, 0] * math.sqrt(2)]))
    assert np.all(behind[h ** 2 / 400.0 > 5.0 + 1e-9] == Status.BEHIND) and np.all(behind[h ** 2 / 400.0 < 5.0] == 0)
    # Every ray travels the same optical path to a perfect focus (Fermat).
    assert np.ptp(r.opl) < 1e-9
    assert np.all(r.directions[:, 2] < 0)


@pytest.mark.parametrize("n", [1.5, 1.7])
def test_hyperbolic_surface_images_infinity_to_a_point(make_design, n):
    # Plano-hyperbolic lens: collimated light inside glass meets a hyperboloid
    # with k = -n^2 and focuses perfectly at z' = -R/(n-1) behind its vertex.
    R = -10.0
    f = -R / (n - 1)
    d = make_design(f"""
        [object]
        material = {n}
        [[surfaces]]
        radius = {R}
        conic = {-n * n}
        thickness = {f}
        semi_diameter = 6.0
        [[surfaces]]
        radius = inf
        dummy = true
    """)
    o, dirs = _parallel_rays(5.5)
    r = d.trace(o, dirs)
    assert np.all(r.status == 0)
    assert np.max(np.abs(r.positions[:, :2])) < 1e-9
    assert np.ptp(r.opl) < 1e-9  # equal optical paths to the focus


def test_ellipsoid_surface_images_infinity_inside_glass(make_design):
    # Air → glass: the ellipsoid k = -1/n^2 focuses at its far focus z' = nR/(n-1).
    n, R = 1.6, 12.0
    f = n * R / (n - 1)
    d = make_design(f"""
        [[surfaces]]
        radius = {R}
        conic = {-1 / n**2}
        thickness = {f}
        material = {n}
        semi_diameter = 7.0
        [[surfaces]]
        radius = inf
        dummy = true
    """)
    o, dirs = _parallel_rays(6.5)
    r = d.trace(o, dirs)
    assert np.all(r.status == 0)
    assert np.max(np.abs(r.positions[:, :2])) < 1e-9


@pytest.mark.parametrize("theta_deg", [0.0, 10.0, 30.0, 60.0, 85.0, 89.0])
def test_plane_parallel_plate_lateral_shift(make_design, theta_deg):
    n, t = 1.5168, 7.0
    d = make_design(f"""
        [[surfaces]]
        thickness = {t}
        material = {n}
        [[surfaces]]
        thickness = 3.0
        [[surfaces]]
        dummy = true
    """)
    th = math.radians(theta_deg)
    o = np.array([[0.0, -10.0 * math.sin(th), -10.0 * math.cos(th)]])
    dirs = np.array([[0.0, math.sin(th), math.cos(th)]])
    r = d.trace(o, dirs)
    assert r.status[0] == 0
    np.testing.assert_allclose(r.directions[0], dirs[0], atol=1e-14)
    # Perpendicular distance between the exit ray and the undeviated line.
    shift_expected = t * math.sin(th) * (1 - math.cos(th) / math.sqrt(n * n - math.sin(th) ** 2))
    p = r.positions[0]
    rel = p - o[0]
    shift = np.linalg.norm(rel - np.dot(rel, dirs[0]) * dirs[0])
    assert abs(shift - shift_expected) < 1e-12
    # Optical path: n·(glass path) + air path, in closed form.
    sin2 = math.sin(th) / n
    glass = t / math.sqrt(1 - sin2 * sin2)
    air_before = 10.0
    air_after = 3.0 / math.cos(th)
    expected = air_before + n * glass + air_after
    assert abs(r.opl[0] - expected) < 1e-12 * expected


@pytest.mark.parametrize("theta_deg", [5.0, 30.0, 45.0, 70.0])
@pytest.mark.parametrize("tilt_deg", [0.0, 20.0])
def test_snell_law_on_a_tilted_plane(make_design, theta_deg, tilt_deg):
    n1, n2 = 1.0, 1.62
    d = make_design(f"""
        [[surfaces]]
        tilt = [{tilt_deg}, 0, 0]
        thickness = 5.0
        material = {n2}
        [[surfaces]]
        dummy = true
        tilt = [{tilt_deg}, 0, 0]
    """)
    th = math.radians(theta_deg)
    dirs = np.array([[0.0, math.sin(th), math.cos(th)]])
    r = d.trace(np.array([[0.0, 0.0, -3.0]]) - 3 * dirs + [0, 0, 3], dirs)
    assert r.status[0] == 0
    # The surface normal is the local z axis rotated about x by tilt.
    a = math.radians(tilt_deg)
    N = np.array([0.0, -math.sin(a), math.cos(a)])
    cos_i = float(dirs[0] @ N)
    sin_t = n1 / n2 * math.sqrt(1 - cos_i**2)
    cos_t = float(r.directions[0] @ N)
    assert abs(math.sqrt(1 - cos_t**2) - sin_t) < 1e-14
    # Refracted ray stays in the plane of incidence.
    assert abs(np.dot(np.cross(dirs[0], N), r.directions[0])) < 1e-15


def _glass_to_air(make_design, tir: bool):
    return make_design(f"""
        [object]
        material = 1.5
        [[surfaces]]
        thickness = {-4.0 if tir else 4.0}
        {'tir = true' if tir else ''}
        [[surfaces]]
        dummy = true
    """)


@pytest.mark.parametrize("eps", [1e-9, 1e-6, 1e-3])
def test_total_internal_reflection_exactly_past_the_critical_angle(make_design, eps):
    crit = math.asin(1 / 1.5)
    refr, tirs = _glass_to_air(make_design, False), _glass_to_air(make_design, True)
    below = np.array([[0.0, math.sin(crit - eps), math.cos(crit - eps)]])
    above = np.array([[0.0, math.sin(crit + eps), math.cos(crit + eps)]])
    o = np.array([[0.0, 0.0, -1.0]]) - below
    assert refr.trace(o, below).status[0] == Status.OK
    r = refr.trace(o, above)
    assert r.status[0] == Status.TIR and r.failed_at[0] == 0
    assert np.all(np.isfinite(r.positions)) and np.all(np.isfinite(r.directions))
    # A surface that relies on TIR reflects just past the angle and flags just before it.
    t = tirs.trace(o, above)
    assert t.status[0] == Status.OK
    np.testing.assert_allclose(t.directions[0], above[0] * [1, 1, -1], atol=1e-15)
    assert tirs.trace(o, below).status[0] == Status.NO_TIR
    # Grazing refraction just below the critical angle: sin(exit) -> 1.
    g = refr.trace(o, below)
    assert 1 - math.hypot(*g.directions[0, :2]) < 1e-8 * max(1.0, eps / 1e-9)


def test_missed_and_vignetted_rays_are_flagged_without_nan(make_design):
    d = make_design("""
        [[surfaces]]
        radius = 5.0
        thickness = 2.0
        material = "N-BK7"
        semi_diameter = 4.0
        [[surfaces]]
        radius = -5.0
        thickness = 5.0
        virtual = true  # the faces cross inside the 4 mm aperture: deliberate, to test the flags
        [[surfaces]]
        dummy = true
    """)
    o = np.array([[0, 0, -1.0], [0, 4.5, -1], [0, 7.0, -1], [0, 0, -1]])
    dirs = np.array([[0, 0, 1.0], [0, 0, 1], [0, 0, 1], [0, 1, 1e-3]])
    r = d.trace(o, dirs)
    assert r.status.tolist() == [Status.OK, Status.VIGNETTED, Status.MISSED, Status.MISSED]
    for a in (r.positions, r.directions, r.opl):
        assert np.all(np.isfinite(a))


def test_a_surface_behind_the_ray_is_flagged_unless_virtual(scenes, tmp_path):
    """A ray aimed away from the lens (direction -z, in front of it) would reach every
    surface backwards: status BEHIND at the first one; `virtual = true` lets it through."""
    import lfsim

    src = (scenes / "cooke_triplet.toml").read_text()
    d = lfsim.load(scenes / "cooke_triplet.toml")
    o = np.array([[0.0, 1.0, -10.0], [0.0, 1.0, -10.0]])
    dirs = np.array([[0.0, 0.0, -1.0], [0.0, 0.0, 1.0]])
    r = d.trace(o, dirs)
    assert r.status.tolist() == [Status.BEHIND, Status.OK] and r.failed_at[0] == 0
    assert np.all(np.isfinite(r.positions)) and r.opl[0] == 0.0  # the failed ray keeps its start
    p = tmp_path / "virtual.toml"
    p.write_text(src.replace('semi_diameter = 10.0\n', 'semi_diameter = 10.0\nvirtual = true\n', 1))
    r = lfsim.load(p).trace(o[:1], dirs[:1])
    assert r.status[0] == Status.BEHIND and r.failed_at[0] == 1  # now the second surface stops it
