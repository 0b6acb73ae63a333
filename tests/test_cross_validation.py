"""Side by side with an established open-source lens tracer (optiland, float64).

The Cooke triplet with constant indices: first-order data and real-ray
intercepts at every surface must agree to 1e-9 mm.
"""

import math
import warnings

import numpy as np
import pytest

import lfsim

optiland = pytest.importorskip("optiland")

N_SK16, N_F2 = 1.6204, 1.62004
RADII = [22.01359, -435.76044, -22.21328, 20.29192, 79.68360, -18.39533]
THICK = [3.25896, 6.00755, 0.99997, 4.75041, 2.95208, 42.20778]
MATS = [N_SK16, None, N_F2, None, N_SK16, None]


def lfsim_triplet(tmp_path, object_distance=math.inf):
    lines = ["[system]", 'aperture = { type = "epd", value = 10.0 }']
    if math.isinf(object_distance):
        lines += ['field = { type = "angle", values = [0.0, 14.0, 20.0] }', "[object]", "distance = inf"]
    else:
        lines += ['field = { type = "height", values = [0.0, 5.0] }', "[object]", f"distance = {object_distance}"]
    for i, (r, t, m) in enumerate(zip(RADII, THICK, MATS)):
        lines += ["[[surfaces]]", f"radius = {r}", f"thickness = {t}"]
        if m is not None:
            lines.append(f"material = {m}")
        if i == 3:
            lines.append("stop = true")
    lines += ["[[surfaces]]", "dummy = true"]
    p = tmp_path / "triplet_const.toml"
    p.write_text("\n".join(lines))
    return lfsim.load(p)


def optiland_triplet(object_distance=math.inf):
    import optiland.backend as be

    be.set_backend("numpy")
    be.set_precision("float64")
    from optiland.materials import IdealMaterial
    from optiland.optic import Optic

    lens = Optic()
    lens.surfaces.add(index=0, radius=np.inf, thickness=np.inf if math.isinf(object_distance) else object_distance)
    for i, (r, t, m) in enumerate(zip(RADII, THICK, MATS), start=1):
        kw = {"material": IdealMaterial(n=m, k=0)} if m is not None else {}
        lens.surfaces.add(index=i, radius=r, thickness=t, is_stop=(i == 4), **kw)
    lens.surfaces.add(index=7)
    lens.set_aperture(aperture_type="EPD", value=10)
    lens.fields.set_type(field_type="angle" if math.isinf(object_distance) else "object_height")
    lens.fields.add(y=0)
    lens.wavelengths.add(value=0.55, is_primary=True)
    return lens


def _scalar(v):
    return float(np.ravel(v)[0])


def test_first_order_matches_optiland(tmp_path):
    ours = lfsim_triplet(tmp_path).first_order(550.0)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        p = optiland_triplet().paraxial
        ref = {
            "efl": _scalar(p.f2()),
            "front_focal_point": _scalar(p.F1()),
            "back_focal_point": _scalar(p.F2()),
            "front_principal_plane": _scalar(p.P1()),
            "back_principal_plane": _scalar(p.P2()),
            "entrance_pupil_position": _scalar(p.EPL()),
            "entrance_pupil_diameter": _scalar(p.EPD()),
            "exit_pupil_position": _scalar(p.XPL()),
            "exit_pupil_diameter": _scalar(p.XPD()),
            "fno": _scalar(p.FNO()),
        }
    ref["bfl"] = THICK[-1] + ref["back_focal_point"]
    for key, val in ref.items():
        assert abs(getattr(ours, key) - val) < 1e-9, (key, getattr(ours, key), val)


def test_finite_conjugate_magnification_matches_optiland(tmp_path):
    ours = lfsim_triplet(tmp_path, object_distance=100.0).first_order(550.0)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        lens = optiland_triplet(object_distance=100.0)
        m = _scalar(lens.paraxial.magnification())
        ya, ua = lens.paraxial.marginal_ray()
        img = -_scalar(ya[-2]) / _scalar(ua[-2])
    assert abs(ours.magnification - m) < 1e-9
    assert abs(ours.paraxial_image_distance - img) < 1e-9


def test_parabasal_first_order_equals_paraxial(tmp_path):
    d = lfsim_triplet(tmp_path)
    a = d.first_order(550.0, method="paraxial").as_dict()
    b = d.first_order(550.0, method="parabasal").as_dict()
    for k, v in a.items():
        if isinstance(v, float):
            assert abs(v - b[k]) < 1e-9 * max(1.0, abs(v)), k


def test_real_ray_intercepts_match_optiland(tmp_path):
    from optiland.rays import RealRays

    rng = np.random.default_rng(7)
    n = 400
    # Rays across the pupil and a ±20° field, launched from z = -10.
    ang = np.radians(rng.uniform(-20, 20, (n, 2)))
    d = np.stack([np.tan(ang[:, 0]), np.tan(ang[:, 1]), np.ones(n)], 1)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    o = np.concatenate([rng.uniform(-4, 4, (n, 2)), np.full((n, 1), -10.0)], 1)
    o[:, :2] -= 10.0 * d[:, :2] / d[:, 2:]  # aim roughly at the first vertex region

    ours = lfsim_triplet(tmp_path).trace(o, d, wavelength_nm=550.0, record=True)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        lens = optiland_triplet()
        rays = RealRays(*o.T, *d.T, intensity=np.ones(n), wavelength=np.full(n, 0.55))
        lens.surfaces.trace(rays)
        S = lens.surfaces
        ref_path = np.stack([np.stack([np.asarray(S.x)[k], np.asarray(S.y)[k], np.asarray(S.z)[k]], 1)
                             for k in range(1, 8)])
        ref_dir = np.stack([np.asarray(S.L)[-1], np.asarray(S.M)[-1], np.asarray(S.N)[-1]], 1)
    ok = (ours.status == 0) & np.all(np.isfinite(ref_path), axis=(0, 2))
    assert ok.sum() > 0.5 * n  # most rays pass (no clear apertures on this variant)
    assert np.max(np.abs(ours.path[:, ok] - ref_path[:, ok])) < 1e-9
    assert np.max(np.abs(ours.positions[ok] - ref_path[-1, ok])) < 1e-9
    assert np.max(np.abs(ours.directions[ok] - ref_dir[ok])) < 1e-12
    # Rays optiland could not trace (NaN) are flagged by lfsim, not silently traced.
    bad = ~np.all(np.isfinite(ref_path), axis=(0, 2))
    assert np.all(ours.status[bad] != 0)
