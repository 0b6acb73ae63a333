"""Extreme operating points of the InI model and its real-ray metrics, in float64 and float32.

Each case is an ideal-element InI-HMD (every element a thin lens, ``type =
"paraxial"``), where the first-order quantities have closed forms (Eqs. 2-10,
:func:`lfsim.ini.ini_first_order`) and the real-ray metrics known values (GD =
PA = RMS spot = 0; the contrast of the centre beam is the diffraction limit of
its square footprint, ``1 − νλ/d_v``): the telecentric viewing window (z_xp =
f_ep) with the CDP at 0 D, the display in the lenslets' focal plane (g = f_MLA:
intermediate CDP at infinity), and the tunable lens at the ends of its power
range. Every case is also traced in float32 and its agreement with float64 is
checked and recorded (see the ``accuracy`` fixture in conftest.py); a real
design (ini_coaxial) closes the file with its float32-vs-float64 agreement.
"""

from __future__ import annotations

import copy
import math
import tomllib
from dataclasses import replace

import numpy as np
import pytest

import lfsim
from lfsim.analysis.ini_analysis import evaluate
from lfsim.design.errors import DesignError
from lfsim.ini import ini_first_order
from lfsim.ini.model import IniModel
from lfsim.ini.subsystems import sample

F_EP, F_MLA, G, D_MLA_EP, Z_XP = 31.0, 3.5, 4.5, 46.75, 31.0
LENSLETS = [(8, 4), (0, 0), (16, 8)]  # centre, a corner, the opposite corner (0-based)
ARCMIN = 60.0 * 180.0 / math.pi
#: float32 unit roundoff. Each float32 bound below is a stated multiple of the case's rounding
#: noise: EPS32 times the magnitude rounded. Positions: EPS32 · L, L the display-to-viewing-window
#: path (82 mm ideal, 381 mm ini_coaxial); PA (and a real design's contrast): that over the
#: smallest footprint d_v; angles: EPS32 rad; diopters: EPS32 of the eyepiece's 32 D; relative
#: figures and the diffraction-limited contrast: EPS32. Margins over what is measured (the
#: table at the end of the run) are 5x or more.
EPS32 = 2.0**-24
P_EP = 1000.0 / F_EP  # the eyepiece's power (D): the scale of the tunable-lens solve
F32_D = 64 * EPS32 * P_EP  # float32 bound on powers and depths (D); measured <= 1.3e-5 D


def f32_scales(model):
    """(L, L / d_v): the display-to-viewing-window path (mm) and that over the smallest footprint."""
    L = abs(float(model.o_vw[2])) + model.g
    return L, L / min(min(model.state(k).d_v) for k in range(len(model.depths)))


def ideal(scenes, **changes):
    """scenes/ini_ideal.toml with ``object.distance`` (g) and ``[ini]`` entries changed."""
    data = tomllib.loads((scenes / "ini_ideal.toml").read_text())
    if "g" in changes:
        data["object"]["distance"] = changes.pop("g")
    tunable = changes.pop("tunable", {})
    data["ini"]["tunable"].update(tunable)
    data["ini"].update(changes)
    return lfsim.Design.from_dict(data, "ini_ideal_variant.toml")


def measure(design, precision, depths=None):
    """Model and metrics of the three LENSLETS × 9 fields (pupil: 2×2 and 4×4 Gauss–Legendre, 8² MTF grid)."""
    model = IniModel(design, precision=precision)
    m = copy.copy(model)
    m.spec = replace(model.spec, pupil=2, mtf_grid=8)
    subs = sample(m, lenslets=LENSLETS, depths=depths)
    res = evaluate(m, subs)
    assert np.all(res["bundle"].ok), "every ray of an ideal design reaches the viewing window"
    for key in ("gd", "pa", "rms", "contrast", "local"):
        assert np.all(np.isfinite(res[key])), key
    return model, res


def centre_contrast_error(model, res):
    """|contrast − (1 − νλ/d_v)| of the centre lenslet's centre field, per CDP state evaluated."""
    nu = res["nyquist_cpd"] * 180.0 / math.pi  # cycles per radian
    errs = []
    for i in np.flatnonzero((res["subs"].m == 8) & (res["subs"].n == 4)):
        st = model.state(int(res["subs"].k[i]))
        want = min(1.0 - nu * model.lam * 1e-6 / w for w in st.d_v)
        errs.append(abs(res["contrast"][i, 0] - want))
    return max(errs)


def check_ideal_metrics(accuracy, model, res, m32, r32, what):
    """GD, PA, RMS spot and the centre contrast at their known values, and float32 against float64."""
    accuracy(f"{what}: GD max (deg)", np.max(res["gd"]), 1e-9)
    accuracy(f"{what}: PA max", np.max(res["pa"]), 1e-9)
    accuracy(f"{what}: RMS spot max (arcmin)", np.max(res["rms"]) * ARCMIN, 1e-9)
    accuracy(f"{what}: centre contrast vs 1 - nu lambda/d_v", centre_contrast_error(model, res), 1e-9)
    L, L_dv = f32_scales(model)
    accuracy(f"{what}: GD max (deg)", np.max(r32["gd"]), 16 * EPS32 * 180 / math.pi, "float32")
    accuracy(f"{what}: PA max", np.max(r32["pa"]), 16 * EPS32 * L_dv, "float32")
    accuracy(f"{what}: VW positions (mm)", np.max(np.abs(r32["bundle"].pos - res["bundle"].pos)), 16 * EPS32 * L,
             "f32 vs f64")
    accuracy(f"{what}: contrast", np.max(np.abs(r32["contrast"] - res["contrast"])), 64 * EPS32, "f32 vs f64")
    accuracy(f"{what}: RMS spot (arcmin)", np.max(np.abs(r32["rms"] - res["rms"])) * ARCMIN, 16 * EPS32 * ARCMIN,
             "f32 vs f64")


def check_first_order(accuracy, state, fo, what, precision="float64", rel=1e-9):
    got = [state.p_ei[0], state.p_ei[1], state.d_v[0], state.D_v[1], state.delta_theta_eic_deg[0],
           state.theta_eic_deg[1], state.fov_diag_deg]
    want = [fo.p_ei, fo.p_ei, fo.d_v, fo.D_v, fo.delta_theta_eic_deg, fo.theta_eic_deg, fo.fov_diag_deg]
    assert all(math.isfinite(v) for v in got), got
    err = max(abs(a - b) / abs(b) for a, b in zip(got, want))
    return accuracy(f"{what}: Eqs. 2-10 (relative)", err, rel, precision)


def test_telecentric_viewing_window_with_the_cdp_at_infinity(scenes, accuracy):
    """z_xp = f_ep: z'_xp = ∞ in Eqs. (2), (3), (7); CDP at 0 D: z_CDP = ∞ in Eqs. (7)-(10)."""
    design = ideal(scenes)
    model, res = measure(design, "float64", depths=[0])
    m32, r32 = measure(design, "float32", depths=[0])
    assert model.depths[0] == 0.0
    accuracy("telecentric, 0 D: solved tunable-lens power (D)", abs(1000.0 * model.tl_power[0]), 1e-12)
    accuracy("telecentric, 0 D: solved tunable-lens power (D)", abs(1000.0 * m32.tl_power[0]), F32_D, "float32")
    fo = ini_first_order(1.0, G, F_EP, Z_XP, 17, 9, f_mla=F_MLA, cdp_diopters=0.0)
    assert math.isinf(fo.z_xp_image) and math.isinf(fo.z_cdp) and fo.p_ei == 1.0
    for mod, prec, rel in ((model, "float64", 1e-9), (m32, "float32", 128 * EPS32)):
        st = mod.state(0)
        check_first_order(accuracy, st, fo, "telecentric, 0 D", prec, rel)
        accuracy("telecentric, 0 D: paraxial CDP depth (D)", abs(st.cdp_diopters_x), 1e-9 if prec == "float64"
                 else F32_D, prec)
    check_ideal_metrics(accuracy, model, res, m32, r32, "telecentric, 0 D")


def test_display_in_the_lenslet_focal_plane(scenes, accuracy):
    """g = f_MLA: the intermediate CDP is at infinity (l = ∞); the tunable lens then sets the CDP
    alone: its power is 1/(z_xp − z_CDP) − 1/f_ep (0 D: it cancels the eyepiece)."""
    design = ideal(scenes, g=F_MLA, cdp_diopters=[0.0, 1.0], tunable={"range_diopters": [-40.0, 40.0]})
    model, res = measure(design, "float64")
    m32, r32 = measure(design, "float32")
    want = [1000.0 * (-1.0 / F_EP), 1000.0 * (1.0 / (Z_XP - 1000.0) - 1.0 / F_EP)]
    for mod, prec, bound in ((model, "float64", 1e-9), (m32, "float32", F32_D)):
        err = max(abs(1000.0 * p - w) for p, w in zip(mod.tl_power, want))
        accuracy("g = f_MLA: tunable-lens power (D)", err, bound, prec)
    # At 1 D the eyepiece and tunable lens in contact are one thin lens of focal length f_eff.
    f_eff = 1.0 / (model.tl_power[1] + 1.0 / F_EP)
    fo = ini_first_order(1.0, F_MLA, f_eff, Z_XP, 17, 9, f_mla=F_MLA, d_mla_ep=D_MLA_EP)
    assert math.isinf(fo.l) and fo.z_cdp == pytest.approx(1000.0, rel=1e-12)
    check_first_order(accuracy, model.state(1), fo, "g = f_MLA, 1 D")
    check_first_order(accuracy, m32.state(1), fo, "g = f_MLA, 1 D", "float32", 128 * EPS32)
    st0 = model.state(0)
    assert all(math.isfinite(v) for v in (*st0.p_ei, *st0.d_v, *st0.D_v, st0.fov_diag_deg, st0.nyquist_cpd))
    check_ideal_metrics(accuracy, model, res, m32, r32, "g = f_MLA, 0 and 1 D")


def test_tunable_lens_at_the_ends_of_its_range(scenes, accuracy):
    """ini_ideal's lens spans [−10, 10] D. In contact with the eyepiece its power is −1/(z_CDP − z_xp),
    so −10 D serves z_CDP = 131 mm (7.634 D): accepted at the end, refused just beyond it; +10 D
    makes no virtual CDP (a real image 69 mm behind the viewing window, −14.49 D): reported as such."""
    d_end = 1000.0 / 131.0
    design = ideal(scenes, cdp_diopters=[0.0, d_end])
    model, res = measure(design, "float64")
    m32, r32 = measure(design, "float32")
    accuracy("-10 D end: solved power (D)", abs(1000.0 * model.tl_power[1] + 10.0), 1e-9)
    accuracy("-10 D end: solved power (D)", abs(1000.0 * m32.tl_power[1] + 10.0), F32_D, "float32")
    accuracy("-10 D end: paraxial CDP depth (D)", abs(model.state(1).cdp_diopters_x - d_end), 1e-9)
    check_ideal_metrics(accuracy, model, res, m32, r32, "-10 D end")
    with pytest.raises(DesignError, match=r"ini\.tunable\.range_diopters = \[-10\.0, 10\.0\].*needs -10\.00"):
        IniModel(ideal(scenes, cdp_diopters=[0.0, d_end * (1 + 1e-4)]))
    # The other end, given explicitly: the state is finite and says where its image is.
    plus = ideal(scenes, cdp_diopters=[0.0], tunable={"power_diopters": [10.0]})
    for prec, bound in (("float64", 1e-9), ("float32", F32_D)):
        st = IniModel(plus, precision=prec).state(0)
        assert st.tunable_power_diopters == pytest.approx(10.0, abs=bound)
        assert all(math.isfinite(v) for v in (*st.p_ei, *st.d_v, *st.D_v, st.fov_diag_deg, st.nyquist_cpd))
        accuracy("+10 D end: made CDP depth (D)", abs(st.cdp_diopters_x - 1000.0 / (Z_XP - 100.0)), bound, prec)


def test_real_design_float32_agrees_with_float64(scenes, accuracy):
    """ini_coaxial (aspheric lenslets, glass relay and eyepiece) at 0, 1 and 3 D in both precisions."""
    design = lfsim.load(scenes / "ini_coaxial.toml")
    runs = {}
    for prec in ("float64", "float32"):
        model = IniModel(design, precision=prec)
        m = copy.copy(model)
        m.spec = replace(model.spec, pupil=2, mtf_grid=8)
        runs[prec] = evaluate(m, sample(m, lenslets=[(8, 4), (16, 8)]))
        if prec == "float64":
            L, L_dv = f32_scales(model)
    a, b = runs["float64"], runs["float32"]
    same = a["bundle"].ok & b["bundle"].ok
    differ = a["bundle"].ok != b["bundle"].ok
    edge = a["sets"].slices["perimeter"]  # rays aimed exactly at the stop's edge go either way
    inside = np.ones(differ.shape[-1], bool)
    inside[edge] = False
    assert not np.any(differ[..., inside]), "rays inside the stop fail in one precision only"
    accuracy("ini_coaxial: stop-edge rays whose status differs", np.mean(differ[..., edge]), 0.02, "f32 vs f64")
    accuracy("ini_coaxial: VW positions (mm)", np.max(np.abs(a["bundle"].pos - b["bundle"].pos)[same]),
             16 * EPS32 * L, "f32 vs f64")
    accuracy("ini_coaxial: GD (deg)", np.max(np.abs(a["gd"] - b["gd"])), 16 * EPS32 * 180 / math.pi, "f32 vs f64")
    accuracy("ini_coaxial: PA", np.max(np.abs(a["pa"] - b["pa"])), 16 * EPS32 * L_dv, "f32 vs f64")
    accuracy("ini_coaxial: RMS spot (arcmin)", np.max(np.abs(a["rms"] - b["rms"])) * ARCMIN, 16 * EPS32 * ARCMIN,
             "f32 vs f64")
    # The aberrated footprints' contrast moves with their rounded positions: 64 EPS32 · L / d_v.
    accuracy("ini_coaxial: contrast at Nyquist", np.max(np.abs(a["contrast"] - b["contrast"])), 64 * EPS32 * L_dv,
             "f32 vs f64")
