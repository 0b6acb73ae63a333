"""The InI model against the paper's Eqs. (2)-(10) with ideal elements, and GD/PA = 0.

The viewing window is put at z_xp = 0.8, 1.0 and 1.2 f_ep: away from the
design example's operating point (z_xp = f_ep) the sign convention of Eq. (3)
matters, and the ray trace decides it (see lfsim.ini.first_order).
"""

import copy
import json
import math
import tomllib

import numpy as np
import pytest
from conftest import SCENES

import lfsim
from lfsim.analysis.ini_analysis import evaluate
from lfsim.design.errors import DesignError
from lfsim.ini import ini_first_order
from lfsim.ini.model import IniModel
from lfsim.ini.subsystems import sample

F_EP, F_MLA, G, D_MLA_EP = 31.0, 3.5, 4.5, 46.75


def ideal(scenes, z_xp=F_EP, **ini):
    data = tomllib.loads((scenes / "ini_ideal.toml").read_text())
    data["surfaces"][2]["thickness"] = z_xp
    data["ini"].update(ini)
    return lfsim.Design.from_dict(data)


def closed_form(model, k, z_xp):
    f_eff = 1.0 / (1.0 / F_EP + model.tl_power[k])  # TL in contact with the eyepiece
    return ini_first_order(1.0, G, f_eff, z_xp, 17, 9, f_mla=F_MLA, d_mla_ep=D_MLA_EP)


@pytest.mark.parametrize("ratio", [0.8, 1.0, 1.2])
def test_first_order_matches_equations_2_to_10(scenes, ratio):
    z_xp = ratio * F_EP
    model = IniModel(ideal(scenes, z_xp))
    for k, D in enumerate(model.depths):
        st, fo = model.state(k), closed_form(model, k, z_xp)
        assert fo.cdp_diopters == pytest.approx(D, abs=1e-9)
        assert st.cdp_diopters_x == pytest.approx(D, abs=1e-9)
        for got, want in ((st.p_ei[0], fo.p_ei), (st.p_ei[1], fo.p_ei), (st.d_v[0], fo.d_v),
                          (st.D_v[1], fo.D_v), (st.delta_theta_eic_deg[0], fo.delta_theta_eic_deg),
                          (st.theta_eic_deg[1], fo.theta_eic_deg), (st.fov_diag_deg, fo.fov_diag_deg)):
            assert got == pytest.approx(want, rel=1e-9)


@pytest.mark.parametrize("ratio", [0.8, 1.0, 1.2])
def test_real_rays_of_ideal_design(scenes, ratio):
    """Real EI centres on the CDP (Eq. 9), footprint (Eq. 5), window size (Eq. 6); GD = PA = 0."""
    z_xp = ratio * F_EP
    model = IniModel(ideal(scenes, z_xp))
    edge = 1.0 / (1.0 - 1.0 / 125)  # field fraction of the EI's outer edge
    fields = np.array([[0.0, 0.0], [edge, 0.0], [-edge, 0.0], [0.0, edge], [0.0, -edge]])
    lens = [(8, 4), (0, 0), (16, 0), (3, 7), (16, 8)]
    res = evaluate(model, sample(model, lenslets=lens, fields=fields))
    sl = res["sets"].slices
    subs, b = res["subs"], res["bundle"]
    assert np.all(b.ok)
    assert np.max(res["gd"]) < 1e-9 and np.max(res["pa"]) < 1e-9
    assert np.max(res["rms"]) < 1e-12
    for i in range(len(subs)):
        k = subs.k[i]
        fo = closed_form(model, k, z_xp)
        D = model.depths[k]
        # Eq. (9) as an angle: the real chief ray of the EI centre appears at x_c / z_CDP.
        r = res["r"][i, 0, sl["chief"]][0]
        want = np.array([(2 * (subs.m[i] + 1) - 18) / 2, (2 * (subs.n[i] + 1) - 10) / 2])
        step = math.tan(math.radians(fo.delta_theta_eic_deg))
        assert np.allclose(np.abs(r), np.abs(want) * step, rtol=1e-9, atol=1e-12)
        if D > 0:  # the same in length on the virtual CDP
            xc = -(1000.0 / D) * r
            assert np.allclose(np.abs(xc), np.abs(want) * fo.delta_p_eic, rtol=1e-9, atol=1e-9)
        # Eq. (5): footprint of the centre field from the real marginal rays.
        mar = b.pos[i, 0, sl["marginal"]]
        assert abs(mar[0, 0] - mar[1, 0]) == pytest.approx(fo.d_v, rel=1e-9)
        assert abs(mar[2, 1] - mar[3, 1]) == pytest.approx(fo.d_v, rel=1e-9)
        # Eq. (6): chief rays of the EI's edge points span the viewing window.
        ch = b.pos[i, :, sl["chief"]][:, 0]
        assert abs(ch[1, 0] - ch[2, 0]) == pytest.approx(fo.D_v, rel=1e-9)
        assert abs(ch[3, 1] - ch[4, 1]) == pytest.approx(fo.D_v, rel=1e-9)
        # Chief ray of the EI centre crosses the viewing-window centre (Eq. 2's condition).
        assert np.allclose(ch[0], 0.0, atol=1e-12)


def test_telecentric_limit_is_continuous(scenes):
    """Approaching z_xp = f_ep from both sides gives the value at f_ep."""
    at = IniModel(ideal(scenes, F_EP)).state(1)
    for eps in (1e-6, -1e-6):
        st = IniModel(ideal(scenes, F_EP * (1 + eps))).state(1)
        assert all(np.isfinite(v) for v in (*st.p_ei, *st.d_v, *st.D_v, st.fov_diag_deg))
        assert st.p_ei[0] == pytest.approx(at.p_ei[0], rel=1e-5)
        assert st.d_v[0] == pytest.approx(at.d_v[0], rel=1e-5)
        assert st.fov_diag_deg == pytest.approx(at.fov_diag_deg, rel=1e-5)


def test_infinite_cdp_angles_are_finite(scenes):
    model = IniModel(ideal(scenes))
    st = model.state(0)
    assert model.depths[0] == 0.0
    assert st.cdp_diopters_x == pytest.approx(0.0, abs=1e-12)
    assert st.delta_theta_eic_deg == pytest.approx((math.degrees(math.atan(1 / F_EP)),) * 2, rel=1e-12)


def test_tunable_power_is_solved_and_checked(scenes):
    model = IniModel(ideal(scenes))
    # Thin lenses in contact: 1/f = 1/z_IC - 1/a with a = z_CDP - z_xp (Eq. 3 geometry).
    for k, D in enumerate(model.depths):
        a = math.inf if D == 0 else 1000.0 / D - F_EP
        want = 1.0 / (D_MLA_EP - 1 / (1 / F_MLA - 1 / G)) - (0 if D == 0 else 1 / a) - 1 / F_EP
        assert model.tl_power[k] == pytest.approx(want, abs=1e-12)
    data = copy.deepcopy(tomllib.loads((scenes / "ini_ideal.toml").read_text()))
    data["ini"]["tunable"]["range_diopters"] = [-2.0, 2.0]
    with pytest.raises(DesignError, match=r"ini\.tunable\.range_diopters.*3 D needs -3\.30"):
        IniModel(lfsim.Design.from_dict(data))


@pytest.mark.parametrize("key,value,msg", [
    ("mla", "nope", "must name a lenslet array"),
    ("pixel_pitch", -1.0, "must be > 0"),
    ("cdp_diopters", [1.0, -1.0], "each >= 0"),
    ("viewing_window", "EP", "plane dummy surface"),
    ("pixels_per_ei", [125], "two integers"),
])
def test_bad_ini_section(scenes, key, value, msg):
    data = tomllib.loads((scenes / "ini_ideal.toml").read_text())
    data["ini"][key] = value
    with pytest.raises(DesignError, match=msg) as e:
        lfsim.Design.from_dict(data, "x.toml")
    assert f"ini.{key}" in str(e.value) and "\n" not in str(e.value)


def test_fixed_depth_without_tunable_lens(scenes):
    data = tomllib.loads((scenes / "ini_ideal.toml").read_text())
    del data["ini"]["tunable"]
    data["ini"]["cdp_diopters"] = [0.0]
    model = IniModel(lfsim.Design.from_dict(data))
    assert model.depths == [0.0]
    data["ini"]["cdp_diopters"] = [2.0]
    with pytest.raises(DesignError, match="the geometry puts the CDP at 0.0000 D"):
        IniModel(lfsim.Design.from_dict(data))


def _display_side_aa(tmp_path, explicit_stop: bool):
    """ini_coaxial with its aperture array moved to the display side: 1 mm in front of the
    lenslets (the display gap shortened by that much, the mm behind the lenslets given back to
    L2's thickness), so every ray meets the same glass at the same place."""
    text = (SCENES / "ini_coaxial.toml").read_text()
    a, b = text.index('[[surfaces]]\nname = "AA"'), text.index('[[surfaces]]\nname = "F1a"')
    aa = text[a:b].replace("thickness = 6.2019667", "thickness = 1.0")
    text = text[:a] + text[b:]
    text = text.replace("thickness = 0.3\naperture", "thickness = 6.5019667\naperture", 1)
    i = text.index('[[surfaces]]\nname = "L1"')
    text = text[:i] + aa + text[i:]
    text = text.replace("distance = 6.9999162", "distance = 5.9999162", 1)
    if explicit_stop:
        text = text.replace('viewing_window = "VW"', 'viewing_window = "VW"\naperture_array = "AA"', 1)
    path = tmp_path / ("aa_stop.toml" if explicit_stop else "aa_front.toml")
    path.write_text(text)
    return path


def test_a_display_side_aperture_array_leaves_the_lenslet_face_the_stop(tmp_path, capsys):
    from lfsim.analysis.ini_analysis import analyze
    from lfsim.cli import main

    d = lfsim.load(_display_side_aa(tmp_path, False))
    names = [s.name for s in d.system.surfaces]
    assert names[:3] == ["AA", "L1", "L2"] and d.ini.stop == 1  # the first refracting member
    # Its 1 x 1 mm openings 1 mm before the lenslets clip none of the analysis rays: the same
    # figures as the design with the array behind the lenslets.
    got = analyze(d, stride=(8, 4), plots=False)["summary"]
    ref = analyze(lfsim.load(SCENES / "ini_coaxial.toml"), stride=(8, 4), plots=False)["summary"]
    for key in ("gd_max_deg", "gd_mean_deg", "pa_max", "pa_mean", "contrast_nyquist_min"):
        assert got[key] == pytest.approx(ref[key], rel=1e-9, abs=1e-12), key
    # Named as the stop, the array's edge rays miss the lenslet behind it: PA has no value, and
    # analyze says so instead of failing.
    out = tmp_path / "out"
    assert main(["analyze", str(_display_side_aa(tmp_path, True)), "--stride", "8,4", "--no-plots",
                 "--out", str(out)]) == 0
    text = capsys.readouterr().out
    assert "PA (Eq. 12)  max n/a" in text and "marginal rays failed" in text
    assert json.loads((out / "metrics.json").read_text())["summary"]["pa_max"] is None
