"""`lfsim analyze`'s lateral colour: the chief rays of the same display point at the design's
shortest and longest wavelengths, against a paraxial y-nu trace written out here (the limit of
small fields), a dispersion-free limit (0), and the single-wavelength case (not reported)."""

from __future__ import annotations

import tomllib

import numpy as np
import pytest
from helpers import SMALL, small_ini

import lfsim
from lfsim.analysis.ini_analysis import analyze, evaluate, lateral_colour, polychromatic_contrast
from lfsim.ini.model import IniModel
from lfsim.ini.subsystems import sample
from lfsim.metrics.spot import ARCMIN
from lfsim.optics.materials import lookup

WAVELENGTHS = [486.1327, 587.5618, 656.2725]


def _text(glass: str = '"N-BK7"', wavelengths=WAVELENGTHS) -> str:
    return small_ini(glass=glass, wavelengths=wavelengths)


def _design(text: str):
    return lfsim.Design.from_dict(tomllib.loads(text))


def _paraxial_r(s: float, c: float, tl_power: float, n: float, D: float) -> float:
    """The retinal tangent (``slope − height·D/1000`` at the viewing window, one axis) of the
    chief ray from display point ``s`` through the lenslet centre ``c``, by y-nu matrices."""
    L = SMALL
    y, u = c, (c - s) / L["g"]  # the ideal lenslet does not bend a ray through its centre

    def move(t):
        nonlocal y
        y = y + t * u

    def lens(phi):
        nonlocal u
        u = u - y * phi

    def face(curv, n1, n2):  # refraction, reduced slopes kept as real slopes
        nonlocal u
        u = (n1 * u - y * (n2 - n1) * curv) / n2

    move(L["l_tl"])
    lens(tl_power)
    lens(1.0 / L["f_ep"])
    move(L["gap_ep_w"])
    face(1.0 / L["r_w"], 1.0, n)
    move(L["t_w"])
    face(-1.0 / L["r_w"], n, 1.0)
    move(L["gap_w_m"])
    face(1.0 / L["r_m1"], 1.0, n)
    move(L["t_m"])
    face(1.0 / L["r_m2"], n, 1.0)
    move(L["t_vw"])
    return u - y * D / 1000.0


def test_lateral_colour_tends_to_the_paraxial_y_nu_trace():
    model = IniModel(_design(_text()))
    fields = np.array([[0.0, 0.0], [0.02, 0.0], [0.04, 0.0], [-0.03, 0.0]])
    subs = sample(model, lenslets=[(2, 1)], fields=fields)  # the central lenslet, on the axis
    lc = lateral_colour(model, subs)
    assert lc["wavelengths_nm"] == [486.1327, 656.2725]
    assert np.all(lc["ok"])
    glass = lookup("N-BK7")
    for i in range(len(subs)):
        k = int(subs.k[i])
        D, tl = model.depths[k], model.state(k).tunable_power_diopters / 1000.0
        c = float(model.lenslet_center(subs.m[i], subs.n[i])[0])
        assert c == 0.0
        for f in range(len(fields)):
            s = float(subs.display[i, f, 0])
            rF, rC = (_paraxial_r(s, c, tl, float(glass.index(w)), D) for w in (486.1327, 656.2725))
            expect = abs(np.arctan(rF) - np.arctan(rC)) * ARCMIN  # one axis: the angle difference
            got = lc["arcmin"][i, f]
            if fields[f, 0] == 0.0:
                assert s == pytest.approx(0.0, abs=1e-12) and got < 1e-9
            else:
                assert expect > 1e-3  # the test sees the colour ...
                assert got == pytest.approx(expect, rel=2e-4)  # ... and the real rays' limit is it


def test_a_design_without_dispersion_has_no_lateral_colour():
    model = IniModel(_design(_text(glass="1.5168")))
    lc = lateral_colour(model, sample(model, stride=(1, 1)))
    assert np.all(lc["ok"]) and np.max(lc["arcmin"]) < 1e-9


def test_metrics_json_reports_lateral_colour_and_none_for_one_wavelength(tmp_path):
    doc = analyze(_design(_text()), out_dir=tmp_path / "a", stride=(2, 1), plots=False)
    s = doc["summary"]
    assert s["lateral_colour_wavelengths_nm"] == [486.1327, 656.2725]
    per_field = [v for sub in doc["subsystems"] for v in sub["lateral_colour_arcmin"]]
    assert s["lateral_colour_max_arcmin"] == pytest.approx(max(per_field), rel=1e-12)
    assert s["lateral_colour_mean_arcmin"] == pytest.approx(np.mean(per_field), rel=1e-12)
    assert s["lateral_colour_max_arcmin"] > 0.1
    for b in doc["by_depth"].values():
        assert 0 < b["lateral_colour_mean_arcmin"] <= b["lateral_colour_max_arcmin"] <= s["lateral_colour_max_arcmin"]
    one = analyze(_design(_text(wavelengths=[587.5618])), stride=(2, 1), plots=False)
    assert one["summary"]["lateral_colour_max_arcmin"] is None
    assert one["summary"]["lateral_colour_wavelengths_nm"] is None
    assert all(sub["lateral_colour_arcmin"] is None for sub in one["subsystems"])


def test_polychromatic_contrast_tends_to_the_monochromatic_one_without_colour():
    """Wavelengths 0.1 pm apart in a glass without dispersion: the polychromatic OTF is the
    monochromatic one (same rays, same image point), so its contrast is the analysis's own."""
    waves = [587.5617, 587.5618, 587.5619]
    model = IniModel(_design(_text(glass="1.5168", wavelengths=waves)))
    res = evaluate(model, sample(model, stride=(2, 1)), refine=0)
    poly = polychromatic_contrast(res)
    assert poly["wavelengths_nm"] == waves
    assert np.min(res["contrast"]) > 0.05
    assert np.allclose(poly["contrast"], res["contrast"], rtol=1e-5, atol=1e-7)


def test_polychromatic_contrast_in_metrics_json(tmp_path):
    """Reported when asked (summary, per depth, per field), null when not or with one wavelength;
    with N-BK7's dispersion it differs from the monochromatic contrast."""
    doc = analyze(_design(_text()), out_dir=tmp_path / "a", stride=(2, 1), plots=False, polychromatic=True)
    s = doc["summary"]
    per_field = [v for sub in doc["subsystems"] for v in sub["contrast_nyquist_poly_fields"]]
    mono = [v for sub in doc["subsystems"] for v in sub["contrast_nyquist_fields"]]
    assert s["contrast_poly_wavelengths_nm"] == WAVELENGTHS
    assert s["contrast_nyquist_poly_min"] == pytest.approx(min(per_field), rel=1e-12)
    assert s["contrast_nyquist_poly_mean"] == pytest.approx(np.mean(per_field), rel=1e-12)
    assert all(0 <= v <= 1 for v in per_field) and np.max(np.abs(np.subtract(per_field, mono))) > 1e-3
    for b in doc["by_depth"].values():
        assert s["contrast_nyquist_poly_min"] <= b["contrast_nyquist_poly_min"] <= b["contrast_nyquist_poly_mean"]
    off = analyze(_design(_text()), stride=(2, 1), plots=False)
    one = analyze(_design(_text(wavelengths=[587.5618])), stride=(2, 1), plots=False, polychromatic=True)
    for d in (off, one):
        s_ = d["summary"]
        assert s_["contrast_nyquist_poly_mean"] is None and s_["contrast_poly_wavelengths_nm"] is None
        assert all(sub["contrast_nyquist_poly_fields"] is None for sub in d["subsystems"])
    assert off["summary"]["contrast_nyquist_mean"] == doc["summary"]["contrast_nyquist_mean"]
