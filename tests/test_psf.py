"""`lfsim psf` and the diffraction of the eye pupil: the Airy pattern, rendered."""

import json
import math

import numpy as np
import pytest

import lfsim
from lfsim.cli import main
from lfsim.vision.psf import PsfSpec, profile_stats, render_psf


def _lod_arcmin(lam_nm, d_mm):
    return lam_nm * 1e-6 / d_mm * 180 * 60 / math.pi


def test_an_ideal_eye_renders_the_airy_pattern_of_its_pupil(scenes):
    """1 mm pupil at 550 nm: FWHM 1.03 λ/D and the first dark ring at 1.22 λ/D, each ± 5 %;
    without diffraction the same point is a dot of its own size."""
    d = lfsim.load(scenes / "ini_ideal.toml")
    lod = _lod_arcmin(550.0, 1.0)
    _, doc = render_psf(d, PsfSpec(view="natural", depth_d=1.0, focus_d=1.0, pupil_mm=1.0, wavelength_nm=550.0,
                                   fov_arcmin=8.0, resolution=51, spp=32768, seed=1), log=lambda *a: None)
    assert doc["fwhm_arcmin"] == pytest.approx(1.029 * lod, rel=0.05)
    assert doc["first_minimum_arcmin"] == pytest.approx(1.22 * lod, rel=0.05)
    assert doc["ee50_arcmin"] == pytest.approx(1.0697 * lod, rel=0.05)  # Rayleigh: EE = 1/2 at x = 1.680
    # Unit-energy peak of the Airy pattern: π D² / (4 λ²) per steradian.
    peak = math.pi / (4 * (550e-6 / 1.0) ** 2) * (math.pi / (180 * 60)) ** 2
    assert doc["peak"] == pytest.approx(peak, rel=0.1)
    _, geo = render_psf(d, PsfSpec(view="natural", depth_d=1.0, focus_d=1.0, pupil_mm=1.0, wavelength_nm=550.0,
                                   diffraction=False, fov_arcmin=8.0, resolution=51, spp=256), log=lambda *a: None)
    assert geo["ee50_arcmin"] < 0.2 * lod


def test_profile_stats_of_a_sampled_airy_pattern():
    """The figures themselves, on an exactly sampled Airy pattern (no renderer involved)."""
    from lfsim.render.diffraction import airy_inverse_ee

    tab = airy_inverse_ee()
    rng = np.random.default_rng(1)
    u = rng.random(4_000_000)
    t = u * (len(tab) - 1)
    i = np.minimum(t.astype(int), len(tab) - 2)
    x = tab[i] + (t - i) * (tab[i + 1] - tab[i])
    lod = _lod_arcmin(550.0, 1.0)
    r, ph = x / math.pi * lod, rng.random(len(x)) * 2 * math.pi
    n, px = 61, 8.0 / 61
    H, _, _ = np.histogram2d(r * np.sin(ph) / px + n / 2, r * np.cos(ph) / px + n / 2, bins=n,
                             range=[[0, n], [0, n]])
    s = profile_stats(H, px, total=len(x))
    assert s["fwhm_arcmin"] == pytest.approx(1.029 * lod, rel=0.02)
    assert s["first_minimum_arcmin"] == pytest.approx(1.22 * lod, rel=0.03)
    assert s["ee50_arcmin"] == pytest.approx(1.0697 * lod, rel=0.02)
    assert s["energy_in_image"] == pytest.approx(H.sum() / len(x))
    assert np.hypot(*s["centroid_arcmin"]) < 0.05


def test_psf_cli_writes_exr_png_json(scenes, tmp_path, capsys):
    out = tmp_path / "psf"
    rc = main(["psf", str(scenes / "ini_ideal.toml"), "--view", "natural", "--depth-d", "1", "--focus-d", "1.5",
               "--pupil-mm", "3", "--spp", "4096", "--resolution", "31", "--out", str(out), "--json"])
    assert rc == 0
    doc = json.loads(capsys.readouterr().out)
    assert json.loads((out / "psf.json").read_text()) == doc
    for k in ("fwhm_arcmin", "ee50_arcmin", "peak"):
        assert doc[k] > 0
    # Defocus 0.5 D through 3 mm: a blur disk of 1.5 mrad = 5.2 arcmin; half its energy
    # inside 0.71 of its diameter.
    assert doc["ee50_arcmin"] == pytest.approx(0.707 * 5.16, rel=0.15)
    assert (out / "psf.exr").stat().st_size > 0 and (out / "psf.png").stat().st_size > 0


@pytest.mark.parametrize("args,msg", [
    (["--view", "side"], "--view"),
    (["--depth-d", "-1"], "--depth-d"),
    (["--pupil-mm", "0"], "--pupil-mm"),
    (["--wavelength-nm", "2000"], "--wavelength-nm"),
])
def test_psf_bad_input(scenes, tmp_path, capsys, args, msg):
    base = ["psf", str(scenes / "ini_ideal.toml"), "--out", str(tmp_path / "o")]
    try:
        rc = main(base + args)
    except SystemExit as e:  # argparse's own refusals
        rc = e.code
    assert rc == 2
    assert msg in capsys.readouterr().err
    assert not (tmp_path / "o").exists()
