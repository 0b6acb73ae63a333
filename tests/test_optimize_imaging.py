"""`lfsim optimize` on a plain lens (no [ini]): the imaging merit, its exact Jacobian, the shipped example."""

import json
import math

import numpy as np
import pytest

import lfsim
from lfsim.cli import main
from lfsim.optics.sampling import field_rays
from lfsim.optimize.imaging import ImagingMerit, polar_pupil


@pytest.fixture
def example(scenes):
    return lfsim.load(scenes / "cooke_triplet_optimize.toml")


def test_polar_pupil_integrates_polynomials_over_the_disc_exactly():
    pts, w = polar_pupil(4)
    assert w.sum() == pytest.approx(1.0, abs=1e-15) and np.all(w > 0)
    r2 = np.sum(pts ** 2, axis=1)
    th = np.arctan2(pts[:, 1], pts[:, 0])
    for a in range(8):  # the disc average of rho^(2a) is 1 / (a + 1)
        assert w @ r2 ** a == pytest.approx(1.0 / (a + 1), rel=1e-13), a
    for b in range(1, 16):  # every azimuthal harmonic below 4 x rings averages to zero
        assert abs(w @ (r2 * np.cos(b * th))) < 1e-14 and abs(w @ (r2 * np.sin(b * th))) < 1e-14


def test_jacobian_matches_central_differences(example):
    """The forward-mode Jacobian (surface parameters and the entrance pupil's move with
    them) against central differences of the residuals at a point off the start."""
    m = ImagingMerit(example, example.optimize)
    x = m.x0 * (1.0 + 0.01 * np.sin(np.arange(len(m.x0)) + 1.0))
    r, J, _ = m.evaluate(x)
    assert np.all(np.isfinite(r)) and np.all(np.isfinite(J))
    for k in range(len(x)):
        h = 1e-6 * max(1.0, abs(x[k]))
        e = np.zeros_like(x)
        e[k] = h
        fd = (m.residuals(x + e) - m.residuals(x - e)) / (2 * h)
        # Central-difference error ~ h² f''' plus rounding ~ 1e-16 |r| / h: ≲ 1e-7 of the column here.
        # Bound: that 1e-7 of the column or 4x the difference's own noise, its change at step 2h
        # (3x the truncation plus the rounding; measured <= 1e-8 of the column), at most 1e-6 of
        # the column. The second step is taken only where the error passes 1e-7 (none here).
        scale = np.abs(J[:, k]).max()
        err = np.abs(fd - J[:, k]).max()
        noise = np.abs((m.residuals(x + 2 * e) - m.residuals(x - 2 * e)) / (4 * h) - fd).max() \
            if err > 1e-7 * scale else 0.0
        tol = max(1e-7 * scale, 4 * noise)
        assert tol <= 1e-6 * scale, (m.cols[k].name, noise, scale)
        assert err <= tol, (m.cols[k].name, err, scale, noise)


def test_rms_spot_agrees_with_a_dense_trace(example):
    """The merit's RMS spot (polar Gauss rule, polychromatic, about the primary chief ray)
    against a dense uniform grid over the entrance pupil traced with Design.trace."""
    m = ImagingMerit(example, example.optimize)
    _, _, det = m.evaluate(m.x0, derivatives=False)
    fo = example.first_order()
    g = np.linspace(-1, 1, 161)
    X, Y = np.meshgrid(g, g)
    disc = np.stack([X.ravel(), Y.ravel()], axis=1)
    disc = disc[np.sum(disc ** 2, axis=1) <= 1.0]
    R_img, _ = example.tracer().frames_numpy()[-1]
    for f, rms in zip(example.system.fields, det["rms_spot_um"]):
        o, d = field_rays(example.system, fo, f, np.vstack([[0.0, 0.0], disc]))
        chief = example.trace(o[:1], d[:1]).positions @ R_img[:, :2]
        ms = []
        for lam in example.system.wavelengths_nm:
            res = example.trace(o[1:], d[1:], wavelength_nm=lam)
            assert np.all(res.status == 0)
            ms.append(np.mean(np.sum((res.positions @ R_img[:, :2] - chief) ** 2, axis=1)))
        dense = 1000.0 * math.sqrt(np.mean(ms))
        assert rms == pytest.approx(dense, rel=5e-3), f  # grid's own error: ~1/161 of the pupil at its rim


def test_cli_optimizes_the_plain_lens_example(scenes, tmp_path, capsys):
    out = tmp_path / "opt"
    assert main(["optimize", str(scenes / "cooke_triplet_optimize.toml"), "--out", str(out), "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    st = doc["stages"][0]
    assert st["stage"] == "full" and st["merit_end"] < 1e-3 * st["merit_start"]
    end = st["blocks_end"]
    assert end["rays_lost"] == 0 and abs(end["efl_mm"] - 50.0) < 0.05
    assert end["rms_spot_mean_um"] < 15.0  # the rounded, defocused start: ~170 µm
    opt = lfsim.load(out / doc["optimized_design"])
    assert opt.first_order().efl == pytest.approx(end["efl_mm"], rel=1e-6)  # the summary keeps 6 decimals
    assert opt.name == "Cooke triplet 50 mm f/5 (optimized)"  # the start's "(optimization start)" replaced
    text = (out / doc["optimized_design"]).read_text()
    assert text.startswith("# Cooke triplet 50 mm f/5: optimized from ")
    assert "# Evaluate with: lfsim layout THIS_FILE --out DIR" in text  # no [ini]: analyze would refuse it
    ba = doc["before_after"]["rms_spot_um"]
    assert all(a < 0.2 * b for a, b in zip(ba["after"], ba["before"]))
    assert (out / "before_after.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert (out / "after" / "spots.png").is_file()


def test_optimized_names():
    """What marks a name as a start is replaced; other names get "(optimized)" once."""
    from lfsim.optimize.workflow import optimized_name

    cases = {"Wearable InI-HMD (MLA + relay), starting point": "Wearable InI-HMD (MLA + relay), optimized",
             "Triplet (optimization start)": "Triplet (optimized)", "Triplet (Start)": "Triplet (optimized)",
             "Triplet; starting point ": "Triplet; optimized", "Ideal": "Ideal (optimized)",
             "A start": "A start (optimized)", "A (jump start)": "A (jump start) (optimized)",
             "B (optimized)": "B (optimized)"}
    for name, want in cases.items():
        assert optimized_name(name) == want, name


def test_plain_lens_refuses_ini_stages(scenes, tmp_path, capsys):
    argv = ["optimize", str(scenes / "cooke_triplet_optimize.toml"), "--out", str(tmp_path / "o"),
            "--stages", "integrated"]
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "--stages" in err and "full" in err
    assert not (tmp_path / "o").exists()


def test_a_curvature_variable_is_bounded_by_its_clear_aperture(scenes):
    """A curvature variable's bounds keep its surface reaching its clear aperture (the loader's
    rule, |c|·h·√(1 + k) < 1): a step past it would end a stage on a design no file can hold.
    L2_front (semi-diameter 8 mm, sphere) given min = −1: its bound is −1/8."""
    import tomllib

    from lfsim.design import Design
    from lfsim.design.errors import DesignError

    raw = tomllib.loads((scenes / "cooke_triplet_optimize.toml").read_text())
    raw["optimize"]["variables"][2] = {"name": "L2_front.curvature", "min": -1.0, "max": 0.0}
    d = Design.from_dict(raw, "cooke")
    m = ImagingMerit(d, d.optimize)
    lo, hi = m.bounds
    assert m.cols[2].name == "L2_front.curvature"
    assert lo[2] == pytest.approx(-1.0 / 8.0, rel=1e-8) and lo[2] > -1.0 / 8.0 and hi[2] == 0.0
    assert lo[1] == -0.05 and hi[1] == 0.05  # bounds tighter than the reach stay as given
    raw["surfaces"][1]["thickness"] = 12.0  # room for so deep a face
    raw["surfaces"][2]["radius"] = 1.0 / lo[2]
    Design.from_dict(raw, "cooke")  # at the bound: a valid design
    raw["surfaces"][2]["radius"] = 1.0 / (lo[2] * (1.0 + 1e-6))
    with pytest.raises(DesignError, match="reaches only"):
        Design.from_dict(raw, "cooke")
