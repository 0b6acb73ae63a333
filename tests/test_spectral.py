"""Spectral retinal images: the eye's chromatic aberration, the primaries' wavelength nodes, and
lateral colour in a rendered display view against traced chief rays."""

import math

import numpy as np
import pytest

import lfsim
from lfsim.render.eye_models import refraction_diopters
from lfsim.render.spectra import DEFAULT_PRIMARIES, Primary, monochrome, spectral


def thibos_chromatic_eye(lam_nm):
    """Chromatic difference of refraction of the chromatic eye (D; Thibos, Ye, Zhang & Bradley,
    *Appl. Opt.* 31(19), 3594, 1992): p − q / (λ − c), λ in nm."""
    return 1.68524 - 633.46 / (np.asarray(lam_nm, dtype=np.float64) - 214.102)


def test_arizona_eye_longitudinal_chromatic_aberration_matches_the_chromatic_eye():
    lam = np.arange(450.0, 651.0, 10.0)
    ref = 555.0
    arizona = np.array([refraction_diopters(v) - refraction_diopters(ref) for v in lam])
    thibos = thibos_chromatic_eye(lam) - thibos_chromatic_eye(ref)
    assert np.max(np.abs(arizona - thibos)) <= 0.15, np.c_[lam, arizona, thibos]
    # The aberration is real and of the published size: about 1.2 D from 450 to 650 nm.
    assert 1.0 < arizona[-1] - arizona[0] < 1.4


def test_wavelength_nodes_are_the_medians_of_equal_power_strata():
    from scipy.stats import norm

    passes = spectral(4)
    assert [p.channel for p in passes] == [0, 1, 2]
    for p, name in zip(passes, "RGB"):
        prim = DEFAULT_PRIMARIES[name]
        sigma = prim.fwhm_nm / (2 * math.sqrt(2 * math.log(2)))
        want = norm.ppf((np.arange(4) + 0.5) / 4, prim.peak_nm, sigma)
        assert np.allclose(p.nm, want, atol=0.01)
    # A tabulated primary: a box spectrum's nodes split it evenly.
    box = Primary(wavelengths_nm=(500.0, 500.001, 540.0, 540.001), values=(0.0, 1.0, 1.0, 0.0))
    assert np.allclose(box.quantiles([0.125, 0.375, 0.625, 0.875]), [505, 515, 525, 535], atol=0.01)
    assert monochrome(587.5618)[0].channel is None


@pytest.mark.parametrize("bad", [dict(peak_nm=-1, fwhm_nm=20), dict(peak_nm=900, fwhm_nm=20),
                                 dict(wavelengths_nm=(500.0,), values=(1.0,)),
                                 dict(wavelengths_nm=(500.0, 510.0), values=(0.0, 0.0))])
def test_bad_primaries_are_refused(bad):
    with pytest.raises(ValueError):
        Primary(**bad)


def _chief_angles_arcmin(design, cdp_d, lam, s, m, n, focus_mm):
    """(θx, θy) (arcmin, the eye's visual angles) of display point ``s`` seen through lenslet
    (m, n) at wavelength ``lam``: its real chief ray (through the lenslet's stop centre) traced
    to the viewing window, extended back to the eye's focus distance and seen from the pupil
    centre (the ray crosses the viewing window a little off its centre)."""
    from lfsim.ini.model import model_at_depth
    from lfsim.ini.subsystems import trace_rays

    mo = model_at_depth(design, cdp_d, wavelength_nm=lam)
    p, d, _, status, _ = trace_rays(mo, np.asarray(s)[None], [m], [n], np.zeros((1, 2)), [0])
    assert status[0] == 0
    return 60.0 * np.degrees(np.arctan(p[0] / focus_mm - d[0, :2] / d[0, 2]))


def test_lateral_colour_of_a_rendered_display_view_equals_the_traced_chief_rays(scenes):
    """A bright display dot at the centre of an off-axis elemental image, seen through the
    freeform design (3 mm pupil, which holds the dot's whole beamlet): the R and B image
    centroids sit where the R and B chief rays (traced at the passes' wavelength nodes) put
    them, relative to G, within 0.25 px of a 512 px wide image."""
    from lfsim.ini.model import model_at_depth
    from lfsim.render.analytic import ReverseOptics
    from lfsim.render.display import DisplayLayout
    from lfsim.render.display_eye import attach, release
    from lfsim.render.display_eye import sensor_dict as display_sensor
    from lfsim.render.eye import EyeSpec
    from lfsim.render.focal_stack import INTEGRATOR, load_scene, render_passes

    design = lfsim.load(scenes / "ini_freeform_optimized.toml")
    cdp_d = 1000.0 / 750.0
    model = model_at_depth(design, cdp_d)
    layout = DisplayLayout.from_model(model, 0)
    fx, fy = model.state(0).fov_deg
    W, H = 512, int(round(512 * fy / fx))
    m, n = model.arr.m // 2 + 4, model.arr.n // 2 + 2
    centres = layout.pixel_centers()
    s_target = model.ei_centers(0, np.array([m]), np.array([n]))[0]
    i, j = np.unravel_index(np.argmin(np.sum((centres - s_target) ** 2, axis=-1)), centres.shape[:2])
    s = centres[i, j]
    img = np.zeros((layout.height, layout.width, 3), np.float32)
    img[i - 1:i + 2, j - 1:j + 2] = 1.0  # a 3 x 3 pixel dot centred on pixel (i, j)

    passes = spectral(2)
    # Predicted: each channel's mean chief-ray angle over its nodes, in film pixels.
    pred = []
    for p in passes:
        th = np.mean([_chief_angles_arcmin(design, cdp_d, lam, s, m, n, 750.0) for lam in p.nm], axis=0) / 60.0
        pred.append(((0.5 + th[0] / fx) * W - 0.5, (0.5 - th[1] / fy) * H - 0.5))
    pred = np.array(pred)
    shift = np.hypot(*(pred[0] - pred[2]))
    assert shift > 1.5, shift  # the design has lateral colour worth measuring here (1.8 px R to B)

    crop = 40
    x0 = int(round(pred[1, 0])) - crop // 2
    y0 = int(round(pred[1, 1])) - crop // 2
    keys = [attach(ReverseOptics(model, 0, wavelengths=w)) for w in passes]
    try:
        scene = load_scene({"type": "scene", "display": layout.emitter_dict(img), "integrator": INTEGRATOR})
        jobs = []
        for w, key in zip(passes, keys):
            eye = EyeSpec("ideal", 3.0, 750.0, (fx, fy), (W, H), wavelengths=w)
            sd = display_sensor(eye, key, spp=256, seed=3)
            sd["film"].update(crop_offset_x=x0, crop_offset_y=y0, crop_width=crop, crop_height=crop)
            jobs.append((scene, sd))
        out, _ = render_passes(jobs, passes)
    finally:
        for key in keys:
            release(key)
    assert out.shape == (crop, crop, 3) and np.isfinite(out).all()
    yy, xx = np.mgrid[0:crop, 0:crop]
    got = []
    for c in range(3):
        w = out[..., c].astype(np.float64)
        assert w.sum() > 0
        got.append((x0 + (w * xx).sum() / w.sum(), y0 + (w * yy).sum() / w.sum()))
    got = np.array(got)
    # The image sits where the chief rays say (within the spot's own coma, a pixel or so)...
    assert np.max(np.abs(got[1] - pred[1])) < 1.5, (got, pred)
    # ... and the colours are offset from green exactly as the traced chief rays are.
    for c in (0, 2):
        err = (got[c] - got[1]) - (pred[c] - pred[1])
        assert np.max(np.abs(err)) <= 0.25, (c, got, pred)


def test_content_primaries_are_parsed_and_bad_ones_refused(tmp_path):
    from lfsim.content import load_content
    from lfsim.design.errors import DesignError

    base = ('[[objects]]\ncorners = [[-10, -10, -500], [10, -10, -500], [-10, 10, -500]]\n')
    good = tmp_path / "c.toml"
    good.write_text(base + '[display]\nprimaries = { R = { peak_nm = 630.0, fwhm_nm = 20.0 }, '
                    'G = { peak_nm = 525.0, fwhm_nm = 30.0 }, '
                    'B = { wavelengths_nm = [440.0, 450.0, 460.0], values = [0.0, 1.0, 0.0] } }\n')
    c = load_content(good)
    assert c.primaries["R"].peak_nm == 630.0
    assert np.allclose(spectral(1, c.primaries)[2].nm, [450.0])
    bad = tmp_path / "b.toml"
    bad.write_text(base + '[display]\nprimaries = { R = { peak_nm = -630.0, fwhm_nm = 20.0 }, '
                   'G = { peak_nm = 525.0, fwhm_nm = 30.0 }, B = { peak_nm = 450.0, fwhm_nm = 20.0 } }\n')
    with pytest.raises(DesignError, match="display.primaries.R"):
        load_content(bad)
    swapped = tmp_path / "s.toml"
    swapped.write_text(base + '[display]\nprimaries = { R = { peak_nm = 450.0, fwhm_nm = 20.0 }, '
                       'G = { peak_nm = 525.0, fwhm_nm = 30.0 }, B = { peak_nm = 630.0, fwhm_nm = 20.0 } }\n')
    with pytest.raises(DesignError, match=r"display\.primaries.*R 450 nm, G 525 nm, B 630 nm.*swapped"):
        load_content(swapped)


def test_primaries_are_recorded_as_rendered():
    from lfsim.render.spectra import DEFAULT_PRIMARIES, Primary, primaries_doc

    d = primaries_doc()
    assert d["source"] == "default" and d["G"]["peak_nm"] == DEFAULT_PRIMARIES["G"].peak_nm
    # A symmetric Gaussian's median is its peak.
    assert all(d[c]["median_nm"] == pytest.approx(DEFAULT_PRIMARIES[c].peak_nm, abs=0.01) for c in "RGB")
    table = {"R": Primary(wavelengths_nm=(600.0, 610.0, 640.0), values=(0.0, 1.0, 0.0)),
             "G": DEFAULT_PRIMARIES["G"], "B": DEFAULT_PRIMARIES["B"]}
    t = primaries_doc(table)
    assert t["source"] == "content" and t["R"]["wavelengths_nm"] == [600.0, 610.0, 640.0]
    # Triangle 600-610-640 nm, area 20: the median x leaves area 10 = (640 - x)² / 60 to its right.
    x = 640.0 - np.sqrt(600.0)
    assert t["R"]["median_nm"] == pytest.approx(x, abs=0.01)


def _wyman_xyz(lam):
    """The CIE 1931 observer by the multi-lobe fit of Wyman, Sloan & Shirley (JCGT 2(2), 2013,
    Eq. 2): an independent closed form of the table Mitsuba interpolates."""
    def g(mu, a, b):
        t = (lam - mu) * np.where(lam < mu, a, b)
        return np.exp(-0.5 * t * t)
    return np.array([1.056 * g(599.8, 0.0264, 0.0323) + 0.362 * g(442.0, 0.0624, 0.0374)
                     - 0.065 * g(501.1, 0.0490, 0.0382),
                     0.821 * g(568.8, 0.0213, 0.0247) + 0.286 * g(530.9, 0.0613, 0.0322),
                     1.217 * g(437.0, 0.0845, 0.0278) + 0.681 * g(459.0, 0.0385, 0.0725)])


def test_natural_spectra_are_the_srgb_colour_matching_functions():
    """The natural view's channels: equal-energy white through the sRGB colour-matching
    functions. Their quartiles match those of the same functions built from Wyman's closed-form
    observer to 1 nm, and their medians rise B < G < R."""
    from lfsim.render.spectra import RANGE_NM, XYZ_TO_SRGB, natural_primaries, primaries_doc

    nat = natural_primaries()
    lam = np.arange(RANGE_NM[0], RANGE_NM[1] + 0.5, 1.0)
    S = np.maximum(XYZ_TO_SRGB @ _wyman_xyz(lam), 0.0)
    q = [0.25, 0.5, 0.75]
    for k, c in enumerate("RGB"):
        ref = Primary(wavelengths_nm=tuple(lam), values=tuple(S[k] / S[k].max())).quantiles(q)
        assert np.allclose(nat[c].quantiles(q), ref, atol=1.0), c
    med = [nat[c].quantiles([0.5])[0] for c in "BGR"]
    assert med[0] < med[1] < med[2]
    assert primaries_doc()["natural"]["G_median_nm"] == pytest.approx(med[1], abs=1e-3)
    # The natural passes differ from the display's: broadband, not the display's narrow green.
    assert np.ptp(spectral(8, nat)[1].nm) > 2 * np.ptp(spectral(8)[1].nm)
