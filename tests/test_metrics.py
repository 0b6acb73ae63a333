"""Metrics against closed forms: MTF of square pupils, spot statistics, Eq. (11)/(12) forms."""

import json
import math

import numpy as np
import pytest

import lfsim
from lfsim.analysis.ini_analysis import evaluate
from lfsim.cli import main
from lfsim.ini.model import IniModel
from lfsim.ini.subsystems import sample
from lfsim.metrics import distortion, mtf, pupil, spot
from lfsim.metrics.distortion import gd_deg
from lfsim.metrics.footprint import pa

LAM_NM = 550.0
LAM = LAM_NM * 1e-6


def test_diffraction_mtf_of_square_pupil_is_linear():
    """A diffraction-limited square pupil of width w: MTF(ν) = 1 − νλ/w (both axes)."""
    n, w = 32, 1.5
    rho = pupil.mtf_grid(n)
    pup = rho * (w / 2)
    ok = np.ones(len(rho), bool)
    cut = w / LAM
    freqs = np.linspace(0, 1.2 * cut, 25)
    m = mtf.diffraction_mtf(rho, pup[None], np.zeros((1, len(rho))), ok[None], LAM_NM, freqs)[0]
    want = np.clip(1 - freqs / cut, 0, None)
    assert np.allclose(m[:, 0], want, atol=1e-12) and np.allclose(m[:, 1], want, atol=1e-12)


def test_diffraction_otf_of_tilted_square_pupils_adds_to_the_lateral_colour_closed_form():
    """A wavefront tilt W = δ·x moves the image by the angle δ: the OTF of a diffraction-limited
    square pupil becomes (1 − νλ/w)·exp(±2πiνδ) along x and stays real along y. Two such images
    at ±δ/2 (lateral colour δ between two wavelengths of equal weight) average to
    |cos(πνδ)|·(1 − νλ/w): the polychromatic contrast that lateral colour leaves."""
    n, w = 64, 1.5
    rho = pupil.mtf_grid(n)
    pup = rho * (w / 2)
    ok = np.ones(len(rho), bool)
    cut = w / LAM
    freqs = np.linspace(0, 0.9 * cut, 19)
    delta = 0.37 / cut  # rad: 0.37 of the cut-off period
    base = 1 - freqs / cut
    otf = {sgn: mtf.diffraction_otf(rho, pup[None], (sgn * 0.5 * delta * pup[:, 0])[None], ok[None], LAM_NM,
                                    freqs)[0] for sgn in (-1, 1)}
    # the autocorrelation is read between grid cells by bilinear interpolation of its real and
    # imaginary parts: a tilt's phase ramp costs O(1/n²) there (2.5e-5 at n = 64)
    tol = 1e-4
    phase = np.exp(2j * np.pi * freqs * 0.5 * delta)
    sign = 1 if np.allclose(otf[1][:, 0], base * phase, atol=tol) else -1  # the sign convention of the phase
    for sgn, o in otf.items():
        assert np.allclose(np.abs(o), base[:, None], atol=tol)
        assert np.allclose(o[:, 0], base * phase ** (sign * sgn), atol=tol)  # opposite shifts, opposite phases
        assert np.allclose(o[:, 1], base, atol=1e-9)
    poly = np.abs(0.5 * (otf[-1] + otf[1]))
    assert np.allclose(poly[:, 0], np.abs(np.cos(np.pi * freqs * delta)) * base, atol=tol)
    assert np.allclose(poly[:, 1], base, atol=1e-9)
    assert np.allclose(mtf.diffraction_mtf(rho, pup[None], (0.5 * delta * pup[:, 0])[None], ok[None], LAM_NM,
                                           freqs)[0], np.abs(otf[1]), rtol=0, atol=0)


def test_diffraction_mtf_with_defocus_matches_closed_form():
    """Defocus W = a·(ρx² + ρy²): the OTF factorizes, each factor sin(2kas(1−s/2))/(2kas)."""
    n, w, a_waves = 64, 2.0, 0.4
    rho = pupil.mtf_grid(n)
    opd = a_waves * LAM * np.sum(rho**2, axis=1)
    ok = np.ones(len(rho), bool)
    freqs = np.linspace(0, 0.9 * w / LAM, 10)
    m = mtf.diffraction_mtf(rho, (rho * w / 2)[None], opd[None], ok[None], LAM_NM, freqs)[0]
    s = freqs * LAM / (w / 2)  # shift in units of the half-width
    k = 2 * np.pi / LAM
    arg = 2 * k * a_waves * LAM * s * (1 - s / 2)
    want_1d = np.where(s > 0, np.sin(arg) / np.where(s > 0, 2 * k * a_waves * LAM * s, 1), 1.0)
    # Shift along x only: the y factor is the zero-shift value 1. Grid error O(1/n²).
    assert np.allclose(m[:, 0], np.abs(want_1d), atol=2e-3)


def test_geometric_mtf_of_uniform_line_spread():
    """Offsets uniform on [−a, a] (a linear map of the pupil): MTF = |sinc(2aν)|."""
    nodes, w = pupil.gauss_legendre_square(24)
    a = 1e-3
    off = np.stack([a * nodes[:, 0], np.zeros(len(nodes))], axis=1)
    freqs = np.linspace(0, 2.5 / a, 11)
    m = mtf.geometric_mtf(off[None], w, np.ones((1, len(w)), bool), freqs)[0]
    assert np.allclose(m[:, 0], np.abs(np.sinc(2 * a * freqs)), atol=1e-9)
    assert np.allclose(m[:, 1], 1.0)


def test_rms_spot_and_quadrature():
    """Linear aberration δ = a·ρ over the square: RMS = a·sqrt(2/3) exactly with Gauss–Legendre,
    on axis and, the same bundle rotated 20° off axis, in angle (not in tangents)."""
    from scipy.spatial.transform import Rotation

    nodes, w = pupil.gauss_legendre_square(4)
    a = 1e-3
    ok = np.ones((1, len(w)), bool)
    rms, cen, _ = spot.rms_spot(a * nodes[None], w, ok)
    assert rms[0] == pytest.approx(a * math.sqrt(2 / 3), rel=1e-12)
    v = np.column_stack([np.tan(a * nodes), np.ones(len(w))])
    v = Rotation.from_euler("xy", [12.0, 16.0], degrees=True).apply(v / np.linalg.norm(v, axis=1)[:, None])
    rms2, _, _ = spot.rms_spot((v[:, :2] / v[:, 2:])[None], w, ok)
    assert rms2[0] == pytest.approx(a * math.sqrt(2 / 3), rel=1e-5)
    none = spot.rms_spot(a * nodes[None], w, np.zeros((1, len(w)), bool))[0]
    assert np.all(np.isfinite(none))


def test_gd_and_pa_forms():
    assert gd_deg(np.array([0.01, 0.0]), np.array([0.0, 0.0])) == pytest.approx(math.degrees(math.atan(0.01)))
    real = np.array([[0.5, 0.1], [-0.5, 0.1], [0.1, 0.5], [0.1, -0.5]])
    par = np.array([[0.5, 0.0], [-0.5, 0.0], [0.0, 0.5], [0.0, -0.5]])
    assert pa(real, par, 1.0) == pytest.approx(0.1 / math.sqrt(2))


DIRECT = """
name = "real direct view"
[system]
wavelengths_nm = [587.5618]
[object]
distance = 3.0
[arrays.mla]
m = 5
n = 3
pitch = 1.0
[[surfaces]]
name = "L1"
radius = inf
thickness = 0.5
material = "PMMA"
array = "mla"
aperture = { type = "rectangular", half_width = [0.45, 0.45] }
[[surfaces]]
name = "L2"
radius = -1.8
conic = -0.6
thickness = 18.0
array = "mla"
[[surfaces]]
name = "VW"
radius = inf
dummy = true
[ini]
mla = "mla"
pixel_pitch = 0.008
pixels_per_ei = [125, 125]
[ini.analysis]
mtf_grid = 48
"""


def test_opl_and_slope_wavefronts_agree(make_design):
    """Real surfaces: the traced optical path and the wavefront integrated from ray
    directions (used for ideal elements) give the same OPD and contrast."""
    d = make_design(DIRECT)
    model = IniModel(d)
    res = evaluate(model, sample(model, lenslets=[(2, 1), (0, 0), (4, 2)], fields=[[0, 0], [0.3, 0.2]]))
    g = res["sets"].slices["mtf"]
    D = np.array(model.depths)[res["subs"].k][:, None]
    ok = res["bundle"].ok[:, :, g]
    _, cen, _ = spot.rms_spot(res["r"][:, :, g], np.ones(g.stop - g.start), ok)
    opd, pup, _ = mtf.reference_opd(res["bundle"].pos[:, :, g], res["bundle"].dir[:, :, g],
                                    res["bundle"].opl[:, :, g], ok, cen, D)
    w2 = mtf.wavefront_from_slopes(res["sets"].rho[g], pup, spot.angular_offsets(res["r"][:, :, g], cen), ok)
    rms_opl = np.sqrt(np.mean(opd**2, axis=-1)) / LAM
    rms_sl = np.sqrt(np.mean(w2**2, axis=-1)) / LAM
    full = np.all(ok, axis=-1)  # unvignetted pupils (the local pupil map is exact there)
    assert full.sum() >= 3
    assert np.all(rms_opl[full] > 0.02)  # a real, aberrated lenslet
    print(rms_opl[full], rms_sl[full])
    assert np.allclose(rms_sl[full], rms_opl[full], rtol=0.02)
    freqs = np.array([res["nyquist_cpd"]]) * 180 / np.pi
    m1 = mtf.diffraction_mtf(res["sets"].rho[g], pup, opd, ok, model.lam, freqs)
    m2 = mtf.diffraction_mtf(res["sets"].rho[g], pup, w2, ok, model.lam, freqs)
    assert np.allclose(m1[full], m2[full], atol=0.01)


def test_analyze_cli(scenes, tmp_path, capsys):
    out = tmp_path / "a"
    rc = main(["analyze", str(scenes / "ini_ideal.toml"), "--out", str(out), "--stride", "8,4",
               "--depths", "1", "--json"])
    assert rc == 0
    doc = json.loads(capsys.readouterr().out)
    s = doc["summary"]
    for key in ("gd_max_deg", "gd_mean_deg", "pa_max", "pa_mean", "pa_within_target",
                "subsystems_evaluated", "nyquist_cpd"):
        assert key in s
    assert s["subsystems_evaluated"] == 9 and s["gd_max_deg"] < 1e-9
    assert set(doc["by_depth"]) == {"1"}
    assert {"m", "n", "depth_diopters", "gd_deg", "pa_max", "contrast_nyquist"} <= set(doc["subsystems"][0])
    assert json.loads((out / "metrics.json").read_text())["summary"]["pa_max"] == s["pa_max"]
    for name in doc["plots"]:
        assert (out / name).stat().st_size > 10_000
    assert main(["analyze", str(scenes / "ini_ideal.toml"), "--out", str(out), "--depths", "2"]) == 2
    assert "not a CDP depth" in capsys.readouterr().err
    assert main(["analyze", str(scenes / "cooke_triplet.toml"), "--out", str(out)]) == 2
    assert "needs an [ini] section" in capsys.readouterr().err


def test_edge_rays_of_curved_lenslets_are_aimed_onto_the_stop(scenes):
    """Marginal rays (stop edge midpoints) of a real, curved lenslet reach the window:
    they are aimed through the unclipped lenslet onto the aperture's edge, and PA is
    computed from real rays only."""
    model = IniModel(lfsim.load(scenes / "ini_coaxial.toml"))
    res = evaluate(model, sample(model, lenslets=[(8, 4), (0, 0)], depths=[1], fields=[[0, 0], [1, 1]]))
    sl = res["sets"].slices
    ok = res["bundle"].ok[:, :, sl["marginal"]]
    assert np.all(ok[:, 0])  # centre field: all four edge rays get through
    assert res["bundle"].aim_error < 1e-12
    assert res["pa"][0, 0] < 0.01 and np.all(np.isfinite(res["pa"]))  # on-axis lenslet: tiny
    # The corner field loses some edge rays further on (vignetting); PA leaves it out.
    assert np.array_equal(res["pa_ok"], np.all(ok, axis=-1))
    from lfsim.analysis.ini_analysis import summarize

    s = summarize(res)["summary"]
    assert s["pa_fields_failed"] == int(np.sum(~res["pa_ok"]))
    assert s["pa_max"] == pytest.approx(np.max(res["pa"][res["pa_ok"]]))


def test_gd_and_pa_against_a_nominal_reference(scenes, tmp_path):
    """A decentred ideal eyepiece deflects every ray by δ/f: measured against the
    nominal design, GD = atan|δ/f − δ·D| (chief ray, Eq. 11) and every footprint
    moves by z_xp·δ/f = δ on the viewing window, PA = δ/(√2·d_v) (Eq. 12).
    Measured against itself, the shift is part of the reference and GD = PA = 0."""
    import tomllib

    delta, f_ep = 0.1, 31.0
    data = tomllib.loads((scenes / "ini_ideal.toml").read_text())
    nominal = lfsim.Design.from_dict(data)
    data["surfaces"][2]["decenter"] = [delta, 0.0]  # EP; the VW keeps the nominal axis
    moved = lfsim.Design.from_dict(data)
    ref, model = IniModel(nominal), IniModel(moved)
    subs = sample(ref, stride=(8, 4))
    res = evaluate(model, subs, reference=ref)
    D = np.array(ref.depths)[subs.k]
    gd_expect = np.degrees(np.arctan(np.abs(delta / f_ep - delta * D / 1000.0)))
    np.testing.assert_allclose(res["gd"], gd_expect, rtol=1e-9, atol=1e-12)
    d_v = np.array([np.mean(ref.state(k).d_v) for k in subs.k])
    np.testing.assert_allclose(res["pa"], np.broadcast_to((delta / (math.sqrt(2) * d_v))[:, None],
                                                          res["pa"].shape), rtol=1e-9)
    assert np.max(res["pa_shape"]) < 1e-9 * np.max(res["pa"])  # a pure shift: no deformation
    own = evaluate(model, sample(model, stride=(8, 4)))
    assert np.max(own["gd"]) < 1e-9 and np.max(own["pa"]) < 1e-9
    # The CLI flag; a reference with other CDP depths is refused (exit 2).
    text = (scenes / "ini_ideal.toml").read_text()
    ep = 'focal_length = 31.0\nthickness = 31.0'
    assert ep in text
    (tmp_path / "moved.toml").write_text(text.replace(ep, ep + "\ndecenter = [0.1, 0.0]"))
    (tmp_path / "other.toml").write_text(text.replace("cdp_diopters = [0.0, 1.0, 3.0]",
                                                      "cdp_diopters = [0.0, 2.0]"))
    args = ["analyze", str(tmp_path / "moved.toml"), "--stride", "8,4", "--no-plots", "--depths", "0"]
    assert main(args + ["--out", str(tmp_path / "a"), "--reference", str(scenes / "ini_ideal.toml")]) == 0
    doc = json.loads((tmp_path / "a" / "metrics.json").read_text())
    assert doc["summary"]["gd_max_deg"] == pytest.approx(math.degrees(math.atan(delta / f_ep)), rel=1e-9)
    assert main(args + ["--out", str(tmp_path / "b"), "--reference", str(tmp_path / "other.toml")]) == 2
    assert not (tmp_path / "b" / "metrics.json").exists()


def test_pa_shape_is_eq12_without_the_footprints_shift():
    """A footprint shifted as a whole has no shape error; one scaled about its paraxial centre
    has all of its PA as shape error; both together: the shape part is the scaled one's."""
    from lfsim.metrics.footprint import pa_shape

    par = np.array([[1.0, 0.0], [-1.0, 0.0], [0.0, 1.0], [0.0, -1.0]]) * 0.9 + [2.0, -1.0]
    shift = np.array([0.3, -0.4])
    assert pa(par + shift, par, 1.8) == pytest.approx(0.5 / (math.sqrt(2) * 1.8), rel=1e-12)
    assert pa_shape(par + shift, par, 1.8) == pytest.approx(0.0, abs=1e-15)
    scaled = (par - [2.0, -1.0]) * 1.25 + [2.0, -1.0]  # every marginal ray 0.225 mm further out
    assert pa_shape(scaled, par, 1.8) == pytest.approx(pa(scaled, par, 1.8), rel=1e-12)
    assert pa_shape(scaled, par, 1.8) == pytest.approx(0.225 / (math.sqrt(2) * 1.8), rel=1e-12)
    assert pa_shape(scaled + shift, par, 1.8) == pytest.approx(pa_shape(scaled, par, 1.8), rel=1e-12)


def test_axis_crossing_closed_form():
    """Rays built to cross the axis at z = −2 (x) and +3 mm (y), with a spread of ±0.1 mm
    there: the least-squares plane and the RMS distances are the construction's."""
    from lfsim.metrics.footprint import axis_crossing

    t = np.array([[0.1, -0.2], [-0.3, 0.05], [0.2, 0.1], [0.0, -0.1]])
    e = np.array([[0.1, 0.1], [-0.1, -0.1], [-0.1, 0.1], [0.1, -0.1]])  # at the crossing planes
    e -= t * (np.sum(e * t, axis=0) / np.sum(t * t, axis=0))  # orthogonal to the slopes: the plane stays
    z0 = np.array([-2.0, 3.0])
    pos = e - t * z0  # on the plane z = 0
    w = axis_crossing(pos, t)
    np.testing.assert_allclose(w["offset_mm"], z0, rtol=1e-12)
    np.testing.assert_allclose(w["rms_mm"], np.sqrt(np.mean(e ** 2, axis=0)), rtol=1e-12)
    np.testing.assert_allclose(w["rms_at_window_mm"], np.sqrt(np.mean(pos ** 2, axis=0)), rtol=1e-12)
    # One column of lenslets: no slope in x, no crossing in x.
    v = axis_crossing(np.column_stack([np.zeros(4), pos[:, 1]]), np.column_stack([np.zeros(4), t[:, 1]]))
    assert v["offset_mm"][0] is None and v["offset_mm"][1] == pytest.approx(3.0, rel=1e-12)
    assert axis_crossing(np.zeros((0, 2)), np.zeros((0, 2))) is None


def test_real_viewing_window_of_a_moved_eye(scenes):
    """The ideal design with its viewing window moved ε along the line of sight, measured
    against the nominal design (its EI layout aims the centre chief rays at the nominal
    window): at CDP 0 D (the tunable lens off in both designs; at 1 and 3 D the moved design
    sets it for a CDP measured from its own window) those rays cross the axis at −ε in the
    moved window's frame, in x and y, all of them (ideal optics). Measured against itself the
    design's own layout aims them at its own window: 0 in every state."""
    import tomllib

    from lfsim.analysis.ini_analysis import summarize

    eps = 2.5
    data = tomllib.loads((scenes / "ini_ideal.toml").read_text())
    nominal = lfsim.Design.from_dict(data)
    assert data["surfaces"][2]["name"] == "EP"
    data["surfaces"][2]["thickness"] += eps
    ref, model = IniModel(nominal), IniModel(lfsim.Design.from_dict(data))
    doc = summarize(evaluate(model, sample(ref, stride=(4, 2)), reference=ref), package=False)
    assert abs(model.state(0).as_dict()["tunable_power_diopters"]) < 1e-12
    np.testing.assert_allclose(doc["by_depth"]["0"]["viewing_window_real"]["offset_mm"], [-eps, -eps], rtol=1e-9)
    for b in doc["by_depth"].values():
        assert max(b["viewing_window_real"]["rms_mm"]) < 1e-9
        assert min(b["viewing_window_real"]["rms_at_window_mm"]) > 0.1  # and not at the moved window
    own = summarize(evaluate(model, sample(model, stride=(4, 2))), package=False)
    for b in own["by_depth"].values():
        np.testing.assert_allclose(b["viewing_window_real"]["offset_mm"], [0.0, 0.0], atol=1e-9)


def _matches_central_difference(ad, diff, h, rtol, atol=0.0, what=""):
    """``ad`` against the central difference ``diff(h)`` (a function of the step): within
    ``rtol`` |fd| + ``atol`` or 4x the difference's own noise, its change at step 2h (3x its
    truncation plus its rounding; measured <= 0.13 of the tolerance), whichever is larger. The
    noise may not exceed 10x the tolerance (the ceiling a wrong derivative must pass)."""
    fd = diff(h)
    tol = rtol * np.abs(fd) + atol
    noise = np.abs(diff(2 * h) - fd)
    assert np.all(4 * noise <= 10 * tol), (what, np.max(noise / np.maximum(tol, 1e-300)))
    err = np.abs(ad - fd)
    assert np.all(err <= np.maximum(tol, 4 * noise)), (what, np.max(err / np.maximum(tol, 4 * noise, 1e-300)))


def test_metric_derivatives_match_central_differences():
    """gd_deg_jvp, pa_jvp and rms_spot_jvp (the merit's derivatives of Eqs. 11, 12 and the
    RMS spot) against central differences of the value functions, and their values equal
    the value functions'."""
    from lfsim.metrics import footprint

    rng = np.random.default_rng(0)
    S, R, K, h = 5, 30, 3, 1e-7
    r = rng.normal(0, 0.01, (S, R, 2)) + np.array([0.2, -0.1])  # a spot 12° off axis
    dr = rng.normal(0, 1, (S, R, 2, K))
    w, ok = rng.random(R), rng.random((S, R)) > 0.1
    rms, drms, off, doff, wn = spot.rms_spot_jvp(r, dr, w, ok)
    rms0, _, off0 = spot.rms_spot(r, w, ok)
    np.testing.assert_array_equal(rms, rms0)
    np.testing.assert_array_equal(off, off0)
    np.testing.assert_allclose(np.sqrt(np.sum(wn * np.sum(off ** 2, -1), -1)), rms, rtol=1e-14)
    for k in range(K):
        def d_spot(t, i, k=k):
            return (spot.rms_spot(r + t * dr[..., k], w, ok)[i] - spot.rms_spot(r - t * dr[..., k], w, ok)[i]) / (2 * t)
        _matches_central_difference(drms[..., k], lambda t: d_spot(t, 0), h, 1e-6, 1e-12, "rms")
        _matches_central_difference(doff[..., k], lambda t: d_spot(t, 2), h, 1e-6, 1e-10, "offsets")
    e, de = rng.normal(0, 0.02, (S, 2)), rng.normal(0, 1, (S, 2, K))
    e[0] = 0.0  # the GD residual vector is smooth through e = 0
    gd, dgd, v, dv = distortion.gd_deg_jvp(e, de)
    np.testing.assert_array_equal(gd, distortion.gd_deg(e, np.zeros_like(e)))
    np.testing.assert_allclose(np.hypot(v[:, 0], v[:, 1]), gd, rtol=1e-14, atol=1e-300)
    for k in range(K):
        def d_gd(t, i, k=k):
            p, m = distortion.gd_deg_jvp(e + t * de[..., k], de), distortion.gd_deg_jvp(e - t * de[..., k], de)
            return (p[i] - m[i]) / (2 * t)
        _matches_central_difference(dgd[1:, k], lambda t: d_gd(t, 0)[1:], h, 1e-6, what="gd")
        _matches_central_difference(dv[..., k], lambda t: d_gd(t, 2), h, 1e-6, 1e-7, "gd vector")
    dev, ddev = rng.normal(0, 0.1, (S, 4, 2)), rng.normal(0, 1, (S, 4, 2, K))
    pa, dpa = footprint.pa_jvp(dev, ddev)
    np.testing.assert_array_equal(pa, footprint.pa(dev, np.zeros_like(dev), 1 / np.sqrt(2.0)))
    for k in range(K):
        def d_pa(t, k=k):
            p, m = footprint.pa_jvp(dev + t * ddev[..., k], ddev)[0], footprint.pa_jvp(dev - t * ddev[..., k], ddev)[0]
            return (p - m) / (2 * t)
        _matches_central_difference(dpa[:, k], d_pa, h, 1e-6, what="pa")
    rc, pc = rng.normal(0, 0.05, (S, 9, 2)), rng.normal(0, 0.05, (S, 9, 2))
    drc, dpc = rng.normal(0, 1, (S, 9, 2, K)), rng.normal(0, 1, (S, 9, 2, K))
    ld, dld = distortion.local_distortion_jvp(rc, drc, pc, dpc)
    np.testing.assert_array_equal(ld, distortion.local_distortion(rc, pc))
    for k in range(K):
        def d_ld(t, k=k):
            p = distortion.local_distortion(rc + t * drc[..., k], pc + t * dpc[..., k])
            return (p - distortion.local_distortion(rc - t * drc[..., k], pc - t * dpc[..., k])) / (2 * t)
        _matches_central_difference(dld[..., k], d_ld, h, 1e-6, 1e-9, "local distortion")


def test_diffraction_mtf_of_a_pupil_sliver_is_zero_not_an_error():
    """Rays left on one line of the stop (an aperture edge vignettes all but one row)
    make the affine pupil map singular: the beam gets MTF 0, the others are unchanged."""
    from lfsim.metrics.mtf import diffraction_mtf
    from lfsim.metrics.pupil import mtf_grid

    n = 8
    rho = mtf_grid(n)
    pupil = np.stack([rho * 0.5, rho * 0.5])  # two beams, 1 mm square pupils
    ok = np.ones((2, n * n), dtype=bool)
    ok[1] = np.isclose(rho[:, 1], rho[0, 1])  # beam 1: a single row of the stop
    freqs = np.array([100.0, 500.0])  # cycles/rad
    out = diffraction_mtf(rho, pupil, np.zeros((2, n * n)), ok, 550.0, freqs)
    assert np.all(out[1] == 0.0)
    # beam 0: the diffraction-limited square pupil, 1 - nu*lambda/w
    np.testing.assert_allclose(out[0], (1.0 - freqs * 550e-6 / 1.0)[:, None].repeat(2, 1), atol=1e-9)


def test_distortion_terms_recover_a_known_field_and_lower_the_degree_when_undetermined():
    """A displacement field built from chosen monomials is fitted back exactly (each
    coefficient is the term's displacement at the grid's edge, in degrees); with fewer
    points than the cubic's 10 terms the fit falls back to a lower degree."""
    gx, gy = np.meshgrid(np.linspace(-15.0, 15.0, 9), np.linspace(-9.0, 9.0, 5))
    theta = np.column_stack([gx.ravel(), gy.ravel()])  # paraxial angles, deg
    u = theta / np.array([15.0, 9.0])
    smile, keystone, scale_y = -1.2, 0.4, 0.05
    e = np.column_stack([keystone * u[:, 0] * u[:, 1], smile * u[:, 0] ** 2 + scale_y * u[:, 1]])
    r_par = np.tan(np.radians(theta))
    r_real = np.tan(np.radians(theta + e))
    t = distortion.distortion_terms(r_real, r_par)
    assert t["degree"] == 3 and t["normalization_deg"] == pytest.approx([15.0, 9.0])
    assert t["dy"]["x2"] == pytest.approx(smile, abs=1e-12)
    assert t["dx"]["xy"] == pytest.approx(keystone, abs=1e-12)
    assert t["dy"]["y"] == pytest.approx(scale_y, abs=1e-12)
    others = [v for a in "xy" for n, v in t[f"d{a}"].items() if (a, n) not in {("y", "x2"), ("x", "xy"), ("y", "y")}]
    assert np.max(np.abs(others)) < 1e-12 and t["residual_rms_deg"] < 1e-12
    # The terms' own RMS displacements, largest first: the smile's is |c|·RMS(x²) over the grid.
    assert next(iter(t["rms_deg"])) == "dy_x2"
    assert t["rms_deg"]["dy_x2"] == pytest.approx(abs(smile) * np.sqrt(np.mean(u[:, 0] ** 4)))
    # 6 points cannot determine the cubic (10 terms): the quadratic (6) is fitted instead.
    few = distortion.distortion_terms(r_real[:6], r_par[:6])
    assert few is not None and few["degree"] < 3
    assert distortion.distortion_terms(np.zeros((0, 2)), np.zeros((0, 2))) is None


def test_gd_terms_of_a_coaxial_design_are_a_radial_cubic(scenes, tmp_path):
    """On a rotationally symmetric design GD's field is radial, e·r²·(x, y) to third order: the
    fit's cubic terms must stand (within the angle-vs-tangent difference) in the ratios that
    gives (dx·xy2 / dx·x3 = hy²/hx², dy·x2y / dy·y3 = hx²/hy², dx·x3 / hx³ = dy·y3 / hy³), and
    no plane-asymmetric term
    (dx even in x, dy odd in x) may appear. `lfsim analyze` writes them per CDP state."""
    from lfsim.analysis.ini_analysis import analyze

    doc = analyze(lfsim.load(scenes / "ini_coaxial.toml"), tmp_path, stride=(2, 2), symmetry="none", plots=False)
    for b in doc["by_depth"].values():
        t = b["gd_terms"]
        hx, hy = t["normalization_deg"]
        dx, dy = t["dx"], t["dy"]
        assert abs(dx["x3"]) > 0.05  # a distortion worth testing (0.21 deg at the edge)
        assert dx["xy2"] / dx["x3"] == pytest.approx((hy / hx) ** 2, rel=0.03)
        # Radial holds in the tangent plane; the fit's variable is the angle, and tan θ/θ
        # reaches 1.023 at the 15 deg edge, squared in x2y: about 5 % more than the ratio.
        assert dy["x2y"] / dy["y3"] == pytest.approx((hx / hy) ** 2, rel=0.08)
        assert dx["x3"] / hx ** 3 == pytest.approx(dy["y3"] / hy ** 3, rel=0.03)
        asym = [dx[n] for n in ("1", "y", "x2", "y2", "x2y", "y3")] + [dy[n] for n in ("x", "xy", "x3", "xy2")]
        assert np.max(np.abs(asym)) < 1e-9
