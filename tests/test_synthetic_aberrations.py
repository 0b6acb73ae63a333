"""GD (Eq. 11) and PA (Eq. 12) respond to injected distortion and pupil aberration
as in Figs. 4 and 5 of the design method (``examples/synthetic_aberrations.py``).

Small sweeps on a few sub-systems; every injected amplitude is *measured* from
traced rays (distortion % at the grid corner, keystone %, W040 in waves, pupil
tilt in degrees) before GD/PA are compared with it.
"""

import importlib.util
import math
import sys

import numpy as np
import pytest
from conftest import ROOT

_spec = importlib.util.spec_from_file_location("synthetic_aberrations",
                                               ROOT / "examples" / "synthetic_aberrations.py")
sa = importlib.util.module_from_spec(_spec)
sys.modules.setdefault("synthetic_aberrations", sa)  # dataclasses look their module up
_spec.loader.exec_module(sa)

# Centre, edge midpoints and corners of the 11 x 11 grid: GD max sits at a corner.
FEW = [(5, 5), (0, 5), (10, 5), (5, 0), (5, 10), (0, 0), (10, 0), (0, 10), (10, 10)]


@pytest.fixture(scope="module")
def system():
    geom = sa.solve_geometry()
    fo = sa.closed_form(geom)
    d0, m0 = sa.build(geom)
    return geom, fo, d0, m0


def test_geometry_is_the_40_by_40_degree_system_with_1mm_footprints(system):
    geom, fo, d0, m0 = system
    st = m0.state(0)
    step = math.tan(math.radians(st.delta_theta_eic_deg[0]))
    assert math.degrees(math.atan(5 * step)) == pytest.approx(20.0, abs=1e-8)
    assert st.d_v[0] == pytest.approx(1.0, abs=1e-9)
    assert st.tunable_power_diopters == pytest.approx(geom.tl_diopters, abs=1e-9)
    assert fo.d_v == pytest.approx(1.0, abs=1e-9) and fo.z_cdp == pytest.approx(1000.0, abs=1e-6)


def test_zero_injection_gives_zero_gd_and_pa_and_matches_the_independent_trace(system):
    geom, fo, d0, m0 = system
    met = sa.lfsim_metrics(m0, sa.all_lenslets(), m0)
    assert met["gd_max_deg"] < 1e-9 and met["pa_max"] < 1e-9
    assert met["gd_nom_max_deg"] < 1e-9 and met["pa_nom_max"] < 1e-9
    # lfsim's chief rays and paraxial reference vs Design.trace and closed-form Eq. (9).
    v, vp = sa.chief_rays(d0, geom, fo)
    ch = met["res"]["sets"].slices["chief"].start
    r = -met["res"]["r"][:, 0, ch].reshape(v.shape)
    rp = -met["res"]["r_par"][:, 0, ch].reshape(v.shape)
    assert np.max(np.abs(r - v)) < 1e-12 and np.max(np.abs(rp - vp)) < 1e-12
    assert np.max(np.abs(vp[-1, -1])) == pytest.approx(math.tan(math.radians(20.0)), abs=1e-12)


def _distortion_sweep(geom, fo, m0, key, probe, pcts):
    """Coefficients scaled from one probe; returns measured % and lfsim's GD max/mean."""
    mkey = "keystone_pct" if key == "keystone" else "corner_pct"
    unit = sa.measure_distortion(geom, {key: probe}, fo)[mkey] / probe
    rows = []
    for p in pcts:
        inj = {key: p / unit}
        _, m = sa.build(geom, inj)
        met = sa.lfsim_metrics(m, FEW, m0)
        meas = sa.measure_distortion(geom, inj, fo)
        rows.append((meas, met["gd_max_deg"], met["gd_mean_deg"], sa.first_order_change(m, m0),
                     float(np.max(np.abs(met["gd"] - met["gd_nom"])))))
    return rows


@pytest.mark.parametrize("kind,sign", [("barrel", -1.0), ("pincushion", 1.0)])
def test_gd_grows_monotonically_and_linearly_with_radial_distortion(system, kind, sign):
    geom, fo, d0, m0 = system
    rows = _distortion_sweep(geom, fo, m0, "radial_A4", sign * 1e-5, [sign * p for p in (1.0, 3.0, 5.0)])
    dist = np.array([r[0]["corner_pct"] for r in rows])
    gd_max = np.array([r[1] for r in rows])
    gd_mean = np.array([r[2] for r in rows])
    assert np.all(np.sign(dist) == sign)  # barrel shrinks, pincushion stretches the corner
    assert np.all(np.diff(np.abs(dist)) > 0)
    assert np.all(np.diff(gd_max) > 0) and np.all(np.diff(gd_mean) > 0)
    assert np.corrcoef(np.abs(dist), gd_max)[0, 1] > 0.999
    assert 4.0 < gd_max[-1] / gd_max[0] < 6.0
    # At the corner (where GD is largest) GD is the measured distortion itself:
    # tan GD = |D| |v_par(corner)|, v_par = sqrt(2) tan 20 deg.
    corner = math.sqrt(2.0) * math.tan(math.radians(20.0))
    assert np.allclose(np.tan(np.radians(gd_max)), np.abs(dist) / 100 * corner, rtol=1e-6)
    for _, _, _, fo_change, ref_diff in rows:
        assert fo_change < 1e-12  # the injection leaves lfsim's first-order model unchanged
        assert ref_diff < 1e-12  # ... so its reference is the nominal one


def test_keystone_gives_nonzero_gd_growing_with_it(system):
    geom, fo, d0, m0 = system
    rows = _distortion_sweep(geom, fo, m0, "keystone", 1e-3, (1.0, 3.0, 5.0))
    kst = np.array([r[0]["keystone_pct"] for r in rows])
    gd_max = np.array([r[1] for r in rows])
    assert np.allclose(kst, (1.0, 3.0, 5.0), rtol=0.05)
    assert gd_max[0] > 0.1 and np.all(np.diff(gd_max) > 0)
    assert np.corrcoef(kst, gd_max)[0, 1] > 0.99
    assert all(abs(r[0]["corner_pct"]) < 0.2 * r[0]["keystone_pct"] for r in rows)  # not a radial pattern


def test_pa_grows_with_pupil_spherical_aberration(system):
    geom, fo, d0, m0 = system
    nb = sa.bundle(m0, m0, sa.pupil_rho())
    unit = sa.measure_pupil(geom, {"pupil_sa_A4": -0.01}, m0, nb)["w040_waves"] / -0.01
    w, pa = [], []
    for target in (0.25, 0.5, 1.0):
        inj = {"pupil_sa_A4": target / unit}
        meas = sa.measure_pupil(geom, inj, m0, nb)
        _, m = sa.build(geom, inj)
        met = sa.lfsim_metrics(m, [sa.CENTER], m0)
        assert sa.first_order_change(m, m0) < 1e-12
        assert met["pa_max"] == pytest.approx(met["pa_nom_max"], rel=1e-12)
        assert met["gd_max_deg"] < 1e-9  # on axis: no image shift
        w.append(meas["w040_waves"])
        pa.append(met["pa_max"])
        # Thin plate at the eyepiece: the marginal rays move by z_xp * 4 W040 / a on the VW.
        lam = m0.lam * 1e-6
        shift = geom.f_ep * 4 * meas["w040_waves"] * lam / meas["footprint_radius_ep_mm"]
        assert met["pa_max"] == pytest.approx(shift / math.sqrt(2.0), rel=0.03)
    assert np.allclose(w, (0.25, 0.5, 1.0), rtol=0.02)
    assert np.all(np.diff(pa) > 0) and 3.6 < pa[-1] / pa[0] < 4.4


def test_pa_grows_with_pupil_tilt_against_the_nominal_reference(system):
    geom, fo, d0, m0 = system
    nb = sa.bundle(m0, m0, sa.pupil_rho())
    unit = sa.measure_pupil(geom, {"pupil_tilt": 0.01}, m0, nb)["tilt_deg"] / 0.01
    pa = []
    for target in (0.25, 0.5, 1.0):
        inj = {"pupil_tilt": target / unit}
        meas = sa.measure_pupil(geom, inj, m0, nb)
        assert meas["tilt_deg"] == pytest.approx(target, rel=0.01)
        _, m = sa.build(geom, inj)
        met = sa.lfsim_metrics(m, [sa.CENTER], m0)
        assert met["gd_nom_max_deg"] < 1e-9  # a prism at the intermediate image moves no image point
        # The footprint moves by z_xp tan(tilt): PA = that / (sqrt(2) d_v).
        expect = geom.f_ep * math.tan(math.radians(meas["tilt_deg"])) / math.sqrt(2.0)
        assert met["pa_nom_max"] == pytest.approx(expect, rel=0.01)
        pa.append(met["pa_nom_max"])
    assert np.all(np.diff(pa) > 0)


def test_example_runs_and_writes_its_files(tmp_path):
    doc = sa.run(tmp_path, distortion_pcts=(5.0,), sa_waves=(1.0,), tilts_deg=(1.0,), verbose=False)
    for name in ("synthetic_aberrations.json", "synthetic_distortion_gd.png", "synthetic_pupil_pa.png"):
        assert (tmp_path / name).stat().st_size > 0
    rows = {r["case"]: r for r in doc["table"]}
    assert rows["barrel 5%"]["paper"] == 1.78 and rows["barrel 5%"]["gd_max_deg"] > 1.0
    assert rows["pupil SA 1 waves PV"]["paper"] == 0.23 and rows["pupil SA 1 waves PV"]["pa"] > 0.01
