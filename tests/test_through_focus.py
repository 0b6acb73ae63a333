"""The through-focus analysis (`lfsim analyze --through-focus`): each field's best focus per
orientation, against closed forms (a defocused square pupil), the first-order model's CDP (a
detuned tunable lens, an injected astigmatism) and the analysis's own contrast."""

import json
import math

import numpy as np
import pytest
import tomli_w
from conftest import SCENES

import lfsim
from lfsim.analysis import ini_analysis as A
from lfsim.cli import main
from lfsim.design.loader import read_toml
from lfsim.ini.model import IniModel
from lfsim.ini.subsystems import sample
from lfsim.metrics import mtf, pupil


def _load(raw, tmp_path, name="d.toml"):
    p = tmp_path / name
    p.write_text(tomli_w.dumps(raw))
    return lfsim.load(p)


def _centre(model, k):
    """The centre lenslet's sub-system at CDP state k, EI-centre field only."""
    m, n = model.arr.m // 2, model.arr.n // 2
    return sample(model, lenslets=[(m, n)], depths=[k], fields=np.zeros((1, 2)))


def test_otf_at_one_frequency_is_the_fft_otf():
    """The direct sum at one frequency equals the FFT autocorrelation read by bilinear
    interpolation, for aberrated, vignetted, sheared and sliver pupils, at shifts up to and
    beyond the cut-off."""
    rng = np.random.default_rng(3)
    n = 16
    rho = pupil.mtf_grid(n)
    L = 7
    shear = np.array([[[0.6, 0.1], [-0.05, 0.45]]]) * (1 + 0.3 * rng.random((L, 1, 1)))
    pup = np.einsum("lab,rb->lra", shear, rho) + rng.normal(0, 0.01, (L, 1, 2))
    opd = 550e-6 * (0.3 * rng.normal(size=(L, 1)) * rho[None, :, 0] ** 2
                    + 0.2 * rng.normal(size=(L, 1)) * rho[None, :, 0] * rho[None, :, 1] ** 2
                    + 0.05 * rng.normal(size=(L, len(rho))))
    ok = np.ones((L, len(rho)), bool)
    ok[1] = rho[:, 0] < 0.4  # vignetted
    ok[2] = np.isclose(rho[:, 1], rho[0, 1])  # a sliver: singular map, OTF 0
    ok[3, :5] = False
    for f in (0.0, 150.0, 800.0, 1900.0, 2300.0, 4000.0):  # cycles/rad; cut-off about 1.1e3-2.4e3
        want = mtf.diffraction_otf(rho, pup, opd, ok, 550.0, np.array([f]))[:, 0, :]
        got = mtf.diffraction_otf_at(rho, pup, opd, ok, 550.0, f)
        np.testing.assert_allclose(got, want, rtol=0, atol=1e-13)
    assert np.all(got[2] == 0)


@pytest.fixture(scope="module")
def ideal_raw():
    return read_toml(SCENES / "ini_ideal.toml")


def test_through_focus_of_the_ideal_design_is_a_defocused_square_pupil(ideal_raw, tmp_path):
    """ini_ideal is aberration-free: the centre field's contrast with the eye focused δ away
    from its CDP is the defocused square pupil's, (1 − s)·|sinc(8·W20·s·(1 − s))| per axis,
    s = νλ/w, W20 = (δ/1000)·(w/2)²/2 / λ waves at the beam's edge (w its width on the window).
    Its best focus is the CDP in both orientations, with no astigmatism."""
    model = IniModel(_load(ideal_raw, tmp_path))
    subs = _centre(model, 1)
    res = A.evaluate(model, subs, refine=0)
    tf = A.through_focus(res, A.focus_offsets(1.0, 0.05))
    g = res["sets"].slices["mtf"]
    b = res["bundle"]
    _, pup, _ = mtf.reference_opd(b.pos[:, :, g], b.dir[:, :, g], b.opl[:, :, g], b.ok[:, :, g], res["cen"],
                                  np.array([[1.0]]))
    Amap = mtf.affine_fit(res["sets"].rho[g], pup[0], b.ok[0, :, g])[0]
    lam = model.lam * 1e-6
    nu = res["nyquist_cpd"] * A.CPD_TO_CPR
    for ax in range(2):
        w = 2.0 * abs(Amap[ax, ax])
        s = nu * lam / w
        w20 = (tf["offsets_d"] / 1000.0) * (w / 2) ** 2 / 2 / lam
        want = (1 - s) * np.abs(np.sinc(8 * w20 * s * (1 - s)))
        # the pupil grid's error (n = 32 cells): it grows as W20² (measured 6.1e-3 at 0.88 waves,
        # 1.2e-3 at 0.44), as the sampled defocus phase steps further between cells
        err = np.abs(tf["contrast"][:, 0, 0, ax] - want)
        assert np.all(err <= 1e-4 + 0.01 * w20 ** 2), np.max(err / (1e-4 + 0.01 * w20 ** 2))
        assert np.max(w20) > 0.5  # the sweep reaches more than half a wave of defocus
    np.testing.assert_allclose(tf["best_d"][0, 0], [0.0, 0.0], atol=1e-6)
    assert not tf["edge"].any()
    # offset 0 is the analysis's own contrast, to rounding
    np.testing.assert_allclose(np.min(tf["contrast"][len(tf["offsets_d"]) // 2], axis=-1), res["contrast"],
                               rtol=0, atol=1e-14)


def test_best_focus_follows_the_first_order_cdp_of_a_detuned_tunable_lens(ideal_raw, tmp_path):
    """The tunable lens set 0.4 D off its 1 D power moves the CDP the first-order model reports
    (``cdp_diopters_x/y``); the through-focus best focus (diffraction, real rays) lands there."""
    raw = json.loads(json.dumps(ideal_raw))
    nominal = IniModel(_load(raw, tmp_path, "a.toml"))
    powers = [nominal.state(k).tunable_power_diopters for k in range(3)]
    powers[1] += 0.4
    raw["ini"]["tunable"]["power_diopters"] = powers
    model = IniModel(_load(raw, tmp_path, "b.toml"))
    st = model.state(1)
    assert abs(st.cdp_diopters_x - 1.0) > 0.2  # the CDP really moved
    res = A.evaluate(model, _centre(model, 1), refine=0)
    tf = A.through_focus(res, A.focus_offsets(1.0, 0.02))
    np.testing.assert_allclose(tf["best_d"][0, 0], [st.cdp_diopters_x - 1.0, st.cdp_diopters_y - 1.0], atol=2e-3)


def _astigmatic(raw, a):
    """ini_ideal with a thin plate of sag a·(x² − y²) (index 1.5) in contact with the eyepiece."""
    raw = json.loads(json.dumps(raw))
    surf = raw["surfaces"]
    i = next(j for j, s in enumerate(surf) if s["name"] == "EP")
    surf[i:i] = [{"name": "AS_in", "radius": math.inf, "material": 1.5, "thickness": 0.0, "virtual": True},
                 {"name": "AS", "radius": math.inf, "xy": {"x2y0": a, "x0y2": -a}, "norm_radius": 1.0,
                  "material": "air", "thickness": 0.0, "virtual": True}]
    return raw


def test_astigmatism_is_the_first_order_models_and_follows_the_injected_cylinder(ideal_raw, tmp_path):
    """An astigmatic plate at the eyepiece: each orientation's best focus is the first-order
    model's CDP in that meridian (x, y); the astigmatism flips with the plate's sign and scales
    with its size, and the mean of the two foci stays at the CDP (the plate's x² and y² terms
    cancel in it)."""
    astig = {}
    for a in (4e-4, -2.5e-4):
        model = IniModel(_load(_astigmatic(ideal_raw, a), tmp_path, f"a{a:g}.toml"))
        st = model.state(1)
        res = A.evaluate(model, _centre(model, 1), refine=0)
        tf = A.through_focus(res, A.focus_offsets(1.5, 0.02))
        want = np.array([st.cdp_diopters_x, st.cdp_diopters_y]) - 1.0
        np.testing.assert_allclose(tf["best_d"][0, 0], want, atol=5e-3)
        summary = A._through_focus_summary(tf, np.ones(1, bool))
        astig[a] = summary["astigmatism_d"]["mean"]
        assert astig[a] == pytest.approx(want[0] - want[1], abs=5e-3)
        assert summary["field_curvature_d"]["mean"] == pytest.approx(0.0, abs=0.02)
    assert abs(astig[4e-4]) > 0.3
    assert astig[4e-4] * astig[-2.5e-4] < 0
    assert astig[4e-4] / astig[-2.5e-4] == pytest.approx(-4e-4 / 2.5e-4, rel=0.03)


def test_analyze_through_focus_cli_writes_the_sweep_the_maps_and_refuses_bad_input(tmp_path, capsys):
    """`--through-focus HALF,STEP`: ``by_depth[D].through_focus`` and each sub-system's
    ``best_focus_offset_d`` in metrics.json, ``through_focus.png``, a console line per state; a bad
    sweep is one line naming the flag, exit 2, and nothing written."""
    out = tmp_path / "a"
    rc = main(["analyze", str(SCENES / "ini_ideal.toml"), "--out", str(out), "--stride", "5,5", "--depths", "1",
               "--through-focus", "0.5,0.1"])
    assert rc == 0
    text = capsys.readouterr().out
    assert "through focus at 1 D: best focus - CDP mean" in text
    doc = json.loads((out / "metrics.json").read_text())
    t = doc["by_depth"]["1"]["through_focus"]
    assert t["focus_offsets_d"] == pytest.approx(np.arange(-5, 6) * 0.1, abs=1e-15)
    assert {"contrast_mean", "contrast_min", "best_focus_x_d", "best_focus_y_d", "field_curvature_d",
            "astigmatism_d", "contrast_at_best_focus", "contrast_each_axis_at_best_focus", "fields",
            "fields_without_a_peak", "peaks_at_sweep_edge"} <= set(t)
    # the offset-0 mean is the analysis's own contrast mean
    assert t["contrast_mean"][5] == pytest.approx(doc["by_depth"]["1"]["contrast_nyquist_mean"], abs=1e-12)
    assert t["contrast_at_best_focus"]["mean"] >= t["contrast_mean"][5] - 1e-12
    assert t["contrast_each_axis_at_best_focus"]["mean"] >= t["contrast_at_best_focus"]["mean"] - 1e-3
    sub = doc["subsystems"][0]
    assert len(sub["best_focus_offset_d"]) == doc["summary"]["fields_per_subsystem"]
    assert "through_focus.png" in doc["plots"] and (out / "through_focus.png").stat().st_size > 10_000
    bad = tmp_path / "b"
    for arg in ("0,0.1", "1,-0.05", "1", "x,0.1", "10,0.01"):
        assert main(["analyze", str(SCENES / "ini_ideal.toml"), "--out", str(bad), "--through-focus", arg]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and "--through-focus" in err[0], err
    assert not bad.exists()
    # without the flag nothing of it is computed or written
    doc = A.analyze(lfsim.load(SCENES / "ini_ideal.toml"), None, stride=(8, 8),
                     depths_diopters=[1.0])
    assert doc["by_depth"]["1"]["through_focus"] is None and doc["subsystems"][0]["best_focus_offset_d"] is None


def test_focus_bounds_example_orders_the_bounds_and_leaves_a_focused_design_as_it_is(tmp_path):
    """examples/focus_bounds.py: on the aberration-free design every field is already at its
    best focus, so refocusing per lenslet, on a focus surface or per field gives back nothing."""
    import importlib.util

    spec = importlib.util.spec_from_file_location("focus_bounds", SCENES.parent / "examples" / "focus_bounds.py")
    ex = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(ex)
    assert ex.main([str(SCENES / "ini_ideal.toml"), "--stride", "4,4", "--half", "0.5", "--step", "0.1",
                    "--out", str(tmp_path)]) == 0
    doc = json.loads((tmp_path / "focus_bounds.json").read_text())
    for key in ("per_lenslet", "focus_surface", "per_field", "per_orientation"):
        assert doc[key] == pytest.approx(doc["nominal"], abs=1e-9), key
    assert doc["nominal"] > 0.7  # the diffraction limit of the 1 mm beams at 10.7 cpd
