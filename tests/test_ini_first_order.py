"""InI first-order model, Eqs. (1)–(10), against a ray trace of ideal elements."""

import math

import numpy as np
import pytest

import lfsim
from lfsim.ini import ini_first_order
from lfsim.ini.first_order import IniInputError

M, N, P_MLA, F_MLA, G, D_ME, F_EP = 5, 3, 1.0, 3.0, 3.5, 40.0, 25.0


def ideal_ini(z_xp, g=G, d=D_ME):
    return lfsim.Design.from_dict({
        "arrays": {"mla": {"m": M, "n": N, "pitch": P_MLA}},
        "surfaces": [
            {"name": "mla", "type": "paraxial", "focal_length": F_MLA, "thickness": d, "array": "mla"},
            {"name": "eyepiece", "type": "paraxial", "focal_length": F_EP, "thickness": z_xp},
            {"name": "window", "dummy": True},
        ],
    })


def shoot(design, starts, targets_on_mla, g=G):
    o = np.array([[x, y, -g] for x, y in starts])
    t = np.array([[x, y, 0.0] for x, y in targets_on_mla])
    r = design.trace(o, t - o, record=True)
    assert np.all(r.status == 0), r.status
    return r


def back_intersection(r, i, j):
    """Closest approach of rays i and j extended backwards after the eyepiece (z)."""
    p1, d1, p2, d2 = r.positions[i], r.directions[i], r.positions[j], r.directions[j]
    w = p1 - p2
    a, b, c = d1 @ d1, d1 @ d2, d2 @ d2
    dd, e = d1 @ w, d2 @ w
    s = (b * e - c * dd) / (a * c - b * b)
    return p1 + s * d1


@pytest.mark.parametrize("z_xp_over_f", [1.0, 0.8, 1.2])
def test_equations_match_ideal_ray_trace(z_xp_over_f):
    z_xp = z_xp_over_f * F_EP
    fo = ini_first_order(P_MLA, G, F_EP, z_xp, M, N, f_mla=F_MLA, d_mla_ep=D_ME)
    design = ideal_ini(z_xp)
    for m in range(1, M + 1):
        for n in range(1, N + 1):
            u, v = fo.lenslet_center(m, n)
            s, t = fo.ei_center(m, n)
            # Eq. (2)/(4): the chief ray of the EI centre crosses the window centre.
            r = shoot(design, [(s, t)], [(u, v)])
            assert np.max(np.abs(r.positions[0, :2])) < 1e-9 * max(1.0, abs(s))
            # Eq. (5): footprint of the EI-centre bundle through the lenslet edges.
            h = 0.49 * P_MLA
            r = shoot(design, [(s, t)] * 2, [(u - h, v), (u + h, v)])
            assert abs(abs(r.positions[1, 0] - r.positions[0, 0]) * P_MLA / (2 * h) - fo.d_v) < 1e-6 * fo.d_v
            # Eqs. (7), (9): the bundle's virtual focus is the virtual EI centre on the CDP.
            q = back_intersection(r, 0, 1)
            window_z = D_ME + z_xp
            assert abs((window_z - q[2]) - fo.z_cdp) < 1e-6 * fo.z_cdp
            xc, _ = fo.virtual_ei_center(m, n)
            assert abs(q[0] - xc) < 1e-6 * max(1.0, abs(xc))
            # Eq. (6): chief rays of the EI edges span the viewing window.
            r = shoot(design, [(s - 0.49 * fo.p_ei, t), (s + 0.49 * fo.p_ei, t)], [(u, v)] * 2)
            span = abs(r.positions[1, 0] - r.positions[0, 0]) / 0.98
            assert abs(span - fo.D_v) < 1e-6 * fo.D_v
            # Eq. (8): size of the virtual EI on the CDP.
            r = shoot(design, [(s - 0.49 * fo.p_ei, t)] * 2 + [(s + 0.49 * fo.p_ei, t)] * 2,
                      [(u - 0.3, v), (u + 0.3, v)] * 2)
            a, b = back_intersection(r, 0, 1), back_intersection(r, 2, 3)
            assert abs(abs(b[0] - a[0]) / 0.98 - fo.p_eic) < 1e-6 * fo.p_eic


def test_stiff_limits_are_finite_and_continuous():
    base = dict(p_mla=P_MLA, g=G, f_ep=F_EP, m=17, n=9, f_mla=F_MLA, d_mla_ep=D_ME)
    at = ini_first_order(z_xp=F_EP, **base)
    for eps in (1e-6, 1e-9):
        lo, hi = ini_first_order(z_xp=F_EP * (1 - eps), **base), ini_first_order(z_xp=F_EP * (1 + eps), **base)
        for k in ("p_ei", "d_v", "D_v", "delta_theta_eic_deg", "fov_diag_deg", "z_cdp"):
            a, b, c = getattr(lo, k), getattr(at, k), getattr(hi, k)
            assert all(math.isfinite(v) for v in (a, b, c)), k
            assert abs(a - b) < 1e-4 * abs(b) + 1e-12 and abs(c - b) < 1e-4 * abs(b) + 1e-12, k
    assert math.isinf(at.z_xp_image) and at.p_ei == P_MLA
    # CDP at 0 D: angular quantities stay finite, lengths on the CDP are infinite.
    z0 = ini_first_order(P_MLA, G, F_EP, F_EP, 17, 9, f_mla=F_MLA, cdp_diopters=0.0)
    assert math.isinf(z0.z_cdp) and math.isfinite(z0.fov_diag_deg) and z0.cdp_diopters == 0.0
    near = ini_first_order(P_MLA, G, F_EP, F_EP, 17, 9, f_mla=F_MLA, cdp_diopters=1e-6)
    assert abs(near.fov_diag_deg - z0.fov_diag_deg) < 1e-6 * z0.fov_diag_deg
    # g = f_MLA: intermediate CDP at infinity.
    gf = ini_first_order(P_MLA, F_MLA, F_EP, 0.8 * F_EP, 17, 9, f_mla=F_MLA, d_mla_ep=D_ME)
    near = ini_first_order(P_MLA, F_MLA * (1 + 1e-9), F_EP, 0.8 * F_EP, 17, 9, f_mla=F_MLA, d_mla_ep=D_ME)
    assert math.isinf(gf.l)
    for k in ("p_ei", "d_v", "D_v", "fov_diag_deg", "z_cdp", "theta_eic_deg"):
        assert math.isfinite(getattr(gf, k))
        assert abs(getattr(gf, k) - getattr(near, k)) < 1e-5 * max(1.0, abs(getattr(gf, k))), k


def test_cdp_diopters_round_trip():
    fo = ini_first_order(P_MLA, G, F_EP, 0.9 * F_EP, M, N, f_mla=F_MLA, cdp_diopters=1.0)
    assert abs(fo.z_cdp - 1000.0) < 1e-9 and abs(fo.cdp_diopters - 1.0) < 1e-12
    again = ini_first_order(P_MLA, G, F_EP, 0.9 * F_EP, M, N, f_mla=F_MLA, z_ic=fo.z_ic)
    assert abs(again.z_cdp - 1000.0) < 1e-9


@pytest.mark.parametrize("kw,fragment", [
    (dict(p_mla=-1.0), "p_mla = -1.0"),
    (dict(g=0.0), "g = 0.0"),
    (dict(f_ep=0.0), "f_ep = 0.0"),
    (dict(m=0), "m = 0"),
])
def test_nonsense_inputs(kw, fragment):
    base = dict(p_mla=P_MLA, g=G, f_ep=F_EP, z_xp=F_EP, m=M, n=N)
    base.update(kw)
    with pytest.raises(IniInputError, match=fragment):
        ini_first_order(**base, f_mla=F_MLA, d_mla_ep=D_ME)
