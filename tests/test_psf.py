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


def _render_display_dot(design, cdp_d, pixel, pupil_mm, fov_arcmin, res, spp, diffraction, lam_nm, seed=1):
    """The display path's image of one lit display pixel (monochrome), as render_psf renders it."""
    from lfsim.ini.model import model_at_depth
    from lfsim.render.analytic import ReverseOptics
    from lfsim.render.display import DisplayLayout
    from lfsim.render.display_eye import attach, release
    from lfsim.render.display_eye import sensor_dict as display_sensor
    from lfsim.render.eye import EyeSpec
    from lfsim.render.focal_stack import INTEGRATOR, load_scene, render
    from lfsim.render.spectra import monochrome

    model = model_at_depth(design, cdp_d, wavelength_nm=lam_nm)
    layout = DisplayLayout.from_model(model, 0)
    img = np.zeros((layout.height, layout.width, 3), np.float32)
    img[pixel] = 1.0
    w = monochrome(lam_nm)[0]
    key = attach(ReverseOptics(model, 0, wavelengths=w, diffraction_pupil_mm=pupil_mm if diffraction else None))
    try:
        scene = load_scene({"type": "scene", "display": layout.emitter_dict(img), "integrator": INTEGRATOR})
        eye = EyeSpec("ideal", pupil_mm, 1000.0 / cdp_d, (fov_arcmin / 60, fov_arcmin / 60), (res, res),
                      wavelengths=w, diffraction=diffraction)
        out, _ = render(scene, display_sensor(eye, key, spp, seed))
    finally:
        release(key)
    return out[..., 1].astype(np.float64), model, layout


def _mtf_x(img, px_arcmin, cpd):
    lsf = img.sum(axis=0)
    x = (np.arange(len(lsf)) - (lsf * np.arange(len(lsf))).sum() / lsf.sum()) * px_arcmin
    nu = cpd / 60.0
    return float(abs(np.sum(lsf * np.exp(-2j * np.pi * nu * x))) / lsf.sum())


def test_a_lenslet_views_rendered_diffraction_mtf_matches_analyze(scenes, tmp_path):
    """ini_ideal, the central lenslet's view of its elemental image's centre pixel, 4 mm pupil
    (the beamlet fits inside it): the MTF the aperture's diffraction adds to the rendered image
    (the ratio of the diffraction and geometric renders' MTFs, so the pixel's own blur cancels)
    equals `lfsim analyze`'s diffraction MTF at the Nyquist frequency within 0.03."""
    design = lfsim.load(scenes / "ini_ideal.toml")
    lam = design.system.primary_wavelength_nm
    out = tmp_path / "an"
    assert main(["analyze", str(scenes / "ini_ideal.toml"), "--out", str(out), "--no-plots", "--depths", "1"]) == 0
    doc = json.loads((out / "metrics.json").read_text())
    sub = next(s for s in doc["subsystems"] if (s["m"], s["n"], s["depth_diopters"]) == (8, 4, 1.0))
    want = sub["contrast_nyquist_fields"][0]  # the centre field
    nyq = doc["summary"]["nyquist_cpd"]
    from lfsim.ini.model import model_at_depth
    from lfsim.render.display import DisplayLayout

    model = model_at_depth(design, 1.0)
    layout = DisplayLayout.from_model(model, 0)
    c = model.ei_centers(0, np.array([8]), np.array([4]))[0]
    centres = layout.pixel_centers()
    pixel = np.unravel_index(np.argmin(np.sum((centres - c) ** 2, axis=-1)), centres.shape[:2])
    fov, res = 20.0, 101
    on, _, _ = _render_display_dot(design, 1.0, pixel, 4.0, fov, res, 2048, True, lam)
    off, _, _ = _render_display_dot(design, 1.0, pixel, 4.0, fov, res, 2048, False, lam)
    got = _mtf_x(on, fov / res, nyq) / _mtf_x(off, fov / res, nyq)
    assert 0.5 < want < 0.95  # diffraction matters at Nyquist here
    assert abs(got - want) <= 0.03, (got, want)
