"""`lfsim analyze`'s lateral colour: the chief rays of the same display point at the design's
shortest and longest wavelengths, against a paraxial y-nu trace written out here (the limit of
small fields), a dispersion-free limit (0), and the single-wavelength case (not reported)."""

from __future__ import annotations

import tomllib

import numpy as np
import pytest

import lfsim
from lfsim.analysis.ini_analysis import analyze, lateral_colour
from lfsim.ini.model import IniModel
from lfsim.ini.subsystems import sample
from lfsim.metrics.spot import ARCMIN
from lfsim.optics.materials import lookup

G = 4.5  # display gap (mm)
F_MLA, L_TL, F_EP, T_W, T_M = 3.5, 46.75, 45.0, 3.0, 2.0
R_W, R_M1, R_M2 = 100.0, 60.0, 80.0
GAP_EP_W, GAP_W_M, GAP_M_VW = 10.0, 4.0, 12.0
WAVELENGTHS = [486.1327, 587.5618, 656.2725]


def _text(glass: str = '"N-BK7"', wavelengths=WAVELENGTHS) -> str:
    """An InI design of ideal lenslets, an ideal eyepiece lens and two real singlets before the
    viewing window (the lenses of ``test_package``)."""
    return f'''
name = "lateral colour test"
[system]
wavelengths_nm = {list(wavelengths)}
[object]
distance = {G}
[arrays.mla]
m = 5
n = 3
pitch = [1.0, 1.0]
[[surfaces]]
name = "MLA"
type = "paraxial"
focal_length = {F_MLA}
array = "mla"
aperture = {{ type = "rectangular", half_width = [0.5, 0.5] }}
thickness = {L_TL}
[[surfaces]]
name = "TL"
type = "paraxial"
focal_length = inf
thickness = 0.0
semi_diameter = 10.0
[[surfaces]]
name = "EP"
type = "paraxial"
focal_length = {F_EP}
thickness = {GAP_EP_W}
semi_diameter = 10.0
[[surfaces]]
name = "W1"
radius = {R_W}
thickness = {T_W}
material = {glass}
semi_diameter = 12.0
[[surfaces]]
name = "W2"
radius = {-R_W}
thickness = {GAP_W_M}
semi_diameter = 12.0
[[surfaces]]
name = "M1"
radius = {R_M1}
thickness = {T_M}
material = {glass}
semi_diameter = 10.0
[[surfaces]]
name = "M2"
radius = {R_M2}
thickness = {GAP_M_VW}
semi_diameter = 10.0
[[surfaces]]
name = "VW"
dummy = true
[ini]
mla = "mla"
pixel_pitch = 0.008
pixels_per_ei = [125, 125]
cdp_diopters = [0.0, 1.0, 3.0]
viewing_window = "VW"
[ini.tunable]
surface = "TL"
range_diopters = [-30.0, 30.0]
'''


def _design(text: str):
    return lfsim.Design.from_dict(tomllib.loads(text))


def _paraxial_r(s: float, c: float, tl_power: float, n: float, D: float) -> float:
    """The retinal tangent (``slope − height·D/1000`` at the viewing window, one axis) of the
    chief ray from display point ``s`` through the lenslet centre ``c``, by y-nu matrices."""
    y, u = c, (c - s) / G  # the ideal lenslet does not bend a ray through its centre

    def move(t):
        nonlocal y
        y = y + t * u

    def lens(phi):
        nonlocal u
        u = u - y * phi

    def face(curv, n1, n2):  # refraction, reduced slopes kept as real slopes
        nonlocal u
        u = (n1 * u - y * (n2 - n1) * curv) / n2

    move(L_TL)
    lens(tl_power)
    lens(1.0 / F_EP)
    move(GAP_EP_W)
    face(1.0 / R_W, 1.0, n)
    move(T_W)
    face(-1.0 / R_W, n, 1.0)
    move(GAP_W_M)
    face(1.0 / R_M1, 1.0, n)
    move(T_M)
    face(1.0 / R_M2, n, 1.0)
    move(GAP_M_VW)
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
