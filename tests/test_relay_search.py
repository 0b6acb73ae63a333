"""examples/relay_petzval.py: the paraxial search for a flatter relay at the same first order.

Its Seidel sums are checked against the closed forms of a thin lens (Welford), and a relay it
writes into a design keeps that design's InI first-order model (Eqs. 1-10 from the design's
own maps) while the rules it searches under hold for the design's own relay."""

import importlib.util
import math
import sys
import tomllib
from pathlib import Path

import numpy as np
import pytest
import tomli_w

import lfsim

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "examples"))  # relay_petzval imports relay_variants
spec = importlib.util.spec_from_file_location("relay_petzval", ROOT / "examples" / "relay_petzval.py")
rp = importlib.util.module_from_spec(spec)
sys.modules["relay_petzval"] = rp  # its dataclasses look their module up
spec.loader.exec_module(rp)

KEYS = ("tunable_power_diopters", "cdp_diopters_x", "cdp_diopters_y", "p_ei", "d_v", "D_v", "pixel_arcmin",
        "fov_deg")


def _thin_lens(c1, c2, n=1.5):
    """A relay whose first singlet is a thin lens (t → 0) at the AA plane, the rest empty."""
    z = np.zeros(4)
    return rp.Relay(np.zeros(6), np.array([c1, 0, 0, 0]), np.array([c2, 0, 0, 0]), np.full(4, 1e-12),
                    np.full(4, n)), z


@pytest.mark.parametrize("curved_first", [True, False])
def test_seidel_sums_of_a_thin_lens_match_welford(curved_first):
    # Thin lens in air, object at infinity, stop at the lens (W. T. Welford, Aberrations of Optical
    # Systems, 1986, eqs. 9.x): S_I = y^4 K^3 / 4 [(n/(n-1))^2 + (n+2)/(n(n-1)^2) B^2
    # + 4(n+1)/(n(n-1)) B C + (3n+2)/n C^2], S_III = H^2 K, S_IV = H^2 K / n. For a plano-convex
    # lens |B| = |C| = 1; B C = -1 with the curved face toward the collimated beam (the bending of
    # least spherical aberration), +1 turned round.
    n, R, y, ub = 1.5, 50.0, 2.0, 0.05
    r, _ = _thin_lens(1 / R, 0.0, n) if curved_first else _thin_lens(0.0, -1 / R, n)
    K = (n - 1) / R
    S = rp.seidel(r, 0.0, (y, 0.0), (0.0, ub))
    bc = -1.0 if curved_first else 1.0
    bracket = (n / (n - 1)) ** 2 + (n + 2) / (n * (n - 1) ** 2) + 4 * (n + 1) / (n * (n - 1)) * bc + (3 * n + 2) / n
    H = -ub * y
    assert S[0] == pytest.approx(y ** 4 * K ** 3 / 4 * bracket, rel=1e-9)
    assert S[2] == pytest.approx(H ** 2 * K, rel=1e-9)
    assert S[3] == pytest.approx(H ** 2 * K / n, rel=1e-12)
    assert S[3] / H ** 2 == pytest.approx(r.petzval(), rel=1e-12)


@pytest.mark.parametrize("yb", [0.0, 1.7])
def test_chromatic_sums_of_a_thin_lens_match_welford(yb):
    # Thin lens in air (Welford 1986, sec. 9.x): C_I = y^2 K / V and C_II = y ybar K / V with
    # K = (n - 1)(c1 - c2), V = (n - 1) / (n_F - n_C); independent of the bending and of the
    # object distance; an N-BK7-like dispersion.
    n, dn, y = 1.5168, 0.008054, 2.0
    for c1, c2, u in ((0.02, -0.02, 0.0), (0.05, 0.01, -0.03), (-0.01, -0.04, 0.02)):
        r, _ = _thin_lens(c1, c2, n)
        r.dn = np.array([dn, 0.0, 0.0, 0.0])
        S = rp.seidel(r, 0.0, (y, u), (yb, 0.05))
        K, V = (n - 1) * (c1 - c2), (n - 1) / dn
        assert S[4] == pytest.approx(y * y * K / V, rel=1e-9)
        assert S[5] == pytest.approx(y * yb * K / V, rel=1e-9, abs=1e-15)
    # a glass of no dispersion adds no colour
    r.dn = np.zeros(4)
    assert np.all(rp.seidel(r, 0.0, (y, 0.0), (yb, 0.05))[4:] == 0.0)


def test_the_design_relay_obeys_the_rules_and_a_found_relay_keeps_the_first_order(tmp_path):
    # the shipped design's relay set back on its axis (its lenses are decentred; the search is coaxial)
    raw = tomllib.loads((ROOT / "scenes" / "ini_wearable_optimized.toml").read_text())
    for s_ in raw["surfaces"]:
        if s_.get("name", "").startswith("R") and s_["name"][:2] in ("R1", "R2", "R3", "R4"):
            s_.pop("decenter", None)
    path = tmp_path / "coaxial.toml"
    path.write_text(tomli_w.dumps(raw))
    lam = raw["system"]["primary_wavelength_nm"]
    ref, phis = rp.read_relay(raw, lam)
    rays, marginal = rp.bundle(path)
    S = rp.Search(ref, phis, rays, marginal, rp.Rules())
    x0 = S.start(ref.n)
    assert np.max(np.abs(S.equalities(x0, ref.n))) < 1e-12
    assert np.min(S.inequalities(x0, ref.n, ref.dn)) > -1e-9
    # the relay read from the file: its Petzval sum, sum of (n - 1)(c1 - c2)/n over the four
    # singlets, written out from the file's own surfaces
    surfs = raw["surfaces"]
    byname = {s_.get("name"): i for i, s_ in enumerate(surfs)}
    petzval = 0.0
    for name in rp.LENSES:
        a, b = surfs[byname[name]], surfs[byname[name] + 1]
        c1 = a["curvature"] if "curvature" in a else 1.0 / a["radius"]
        c2 = b.get("curvature", 1.0 / b["radius"] if "radius" in b else 0.0)
        n_ = float(rp.lookup(a["material"]).index(lam))
        petzval += (n_ - 1.0) * (c1 - c2) / n_
    assert ref.petzval() == pytest.approx(petzval, rel=1e-12) and 0.05 < petzval < 0.1
    # the same lenses in N-LASF31A (each lens's matrix kept), then one SLSQP run without the
    # colour rule: every other rule and the first order hold, and the field is flatter ...
    n, dn = np.full(4, float(rp.lookup("N-LASF31A").index(lam))), np.full(4, rp.dispersion("N-LASF31A"))
    assert rp.dispersion("N-LASF31A") == pytest.approx((1.88300 - 1) / 40.76, rel=2e-3)  # catalog nd, vd
    S = rp.Search(ref, phis, rays, marginal, rp.Rules(colour_max=math.inf))
    x, fc, ok = S.solve(n, dn, S.start(n), maxiter=100)
    assert ok and fc < S.field_curvature(x0, ref.n)
    r = S._relay(x, n, dn)
    # ... but the flint-like glass adds colour, which the default rules refuse
    colour = rp.seidel(r, x[18], S.marginal, S.chief)[4:6] / S.seidel0[4:6]
    assert np.max(np.abs(colour)) > 1.1
    strict = rp.Search(ref, phis, rays, marginal, rp.Rules())
    assert np.min(strict.inequalities(x, n, dn)) < -0.1
    semi = S.lens_semi_diameters(S.semi_diameters(x, n)[0])
    p = tmp_path / "found.toml"
    p.write_text(tomli_w.dumps(rp.write_variant(raw, r, ["N-LASF31A"] * 4, S.state_powers(x, n)[0], ref.length,
                                                semi=semi)))
    # the written lenses are as thick at their written rims as the rules say (the package's own
    # edge thickness, sags from the tracer's surface model)
    written = tomllib.loads(p.read_text())["surfaces"]
    from lfsim.ini.model import IniModel
    from lfsim.ini.package import package

    pk = package(IniModel(lfsim.load(p)))
    assert [s["semi_diameter"] for s in written if s.get("name") in rp.LENSES] == pytest.approx(list(semi), abs=1e-12)
    assert pk["min_edge_thickness_mm"] >= S.rules.min_glass - 1e-6
    assert pk["max_clear_diameter_mm"] <= S.rules.clear_diameter + 1e-9
    from relay_variants import first_order

    fa, fb = first_order(path), first_order(p)
    for a, b in zip(fa, fb):
        for k in KEYS[1:]:
            assert np.allclose(np.atleast_1d(b[k]), np.atleast_1d(a[k]), rtol=0, atol=1e-6), (k, a[k], b[k])
    # the tunable power at the 1 D state is one of the search's variables, and the relay's matrix
    # holds the directions of M_a's first row and M_b's second column but not the product of
    # their lengths, the lever k of the tunable power on the CDP: the found relay reaches the same
    # CDPs (above) with the design's power steps times its own k (Search.state_powers), which
    # first_order's independent solve for each state's power reproduces to 1e-7 D
    pa_, pb_ = ([f["tunable_power_diopters"] for f in fo] for fo in (fa, fb))
    k = S.state_powers(x, n)[1]
    assert abs(k - 1.0) < 1e-2
    assert np.allclose(np.diff(pb_), k * np.diff(pa_), rtol=0, atol=1e-7), (k, pa_, pb_)


def test_a_decentred_relay_is_refused_in_one_line(tmp_path, capsys):
    """The search and the variants hold each lens's matrix about one axis: a design whose relay
    lens is decentred (the shipped wearable's) is refused, naming the surface and the value."""
    import relay_variants as rv

    out = tmp_path / "out"
    shipped = str(ROOT / "scenes" / "ini_wearable_optimized.toml")
    assert rp.main(["--design", shipped, "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "decenter" in err and "coaxial" in err and "ini_wearable_optimized" in err, err
    with pytest.raises(SystemExit) as e:
        rv.main(["--design", shipped, "--out", str(out)])
    err = capsys.readouterr().err
    assert e.value.code == 2 and err.count("\n") == 1 and "decenter" in err and "coaxial" in err, err
    assert not out.exists()


@pytest.mark.parametrize("argv, said", [
    (["--starts", "0"], "--starts 0: at least 1"),
    (["--glasses", "N-LAK22,N-LAK22"], "--glasses 'N-LAK22,N-LAK22': four glasses, one per singlet"),
    (["--colour-max", "-1"], "--colour-max -1.0: a positive number or inf"),
    (["--track-limits", "150,abc"], "--track-limits '150,abc': numbers in mm"),
    (["--clear-diameter", "0"], "--clear-diameter 0.0: a positive number of mm"),
    (["--track-limits", "150,20"], "20 mm leaves the relay no length"),
])
def test_bad_arguments_give_one_line_and_write_nothing(tmp_path, capsys, argv, said):
    out = tmp_path / "out"
    with pytest.raises(SystemExit) as e:
        rp.main(["--out", str(out), *argv])
    err = capsys.readouterr().err
    assert e.value.code == 2 and err.count("\n") == 1 and said in err and "usage" not in err, err
    assert not out.exists()
