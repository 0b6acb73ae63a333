"""`lfsim accommodation`: the predicted accommodation response of the display and the natural view."""

import json
import math

import numpy as np
import pytest
from conftest import SCENES

import lfsim
from lfsim.cli import main
from lfsim.vision.accommodation import AccommodationSpec, band_mtf, curve, peak, response, sweep_states

CDP = 1.0
TARGETS = (0.5, 1.0, 2.0)


def _spec(pupil_mm, **kw):
    # The ideal eye at one wavelength: no chromatic or spherical aberration to move the peak.
    return AccommodationSpec(depths_d=TARGETS, cdp_d=CDP, pupil_mm=pupil_mm, eye="ideal", wavelength_nm=555.0,
                             fov_arcmin=96.0, resolution=64, spp=128, **kw)


@pytest.fixture(scope="module")
def sweeps():
    d = lfsim.load(SCENES / "ini_ideal.toml")
    quiet = lambda *a: None  # noqa: E731
    return {p: {q["target_d"]: q for q in response(d, _spec(p), log=quiet)["points"]} for p in (3.0, 1.5)}


def test_band_mtf_of_a_gaussian_psf():
    """A Gaussian PSF of σ arcmin has the MTF exp(−2 π² σ² f²) (f in cycles/arcmin): its
    mean over 3–10 cpd, against the closed form averaged over the same band."""
    px, N, sigma = 0.5, 256, 2.0
    y, x = np.mgrid[0:N, 0:N] - N / 2
    lum = np.exp(-(x ** 2 + y ** 2) * px ** 2 / (2 * sigma ** 2))
    f = np.linspace(3.0, 10.0, 2001) / 60.0
    expect = float(np.mean(np.exp(-2 * math.pi ** 2 * sigma ** 2 * f ** 2)))
    assert band_mtf(lum, px, (3.0, 10.0)) == pytest.approx(expect, abs=0.01)
    # A point (one pixel) has modulation 1 at every frequency.
    dot = np.zeros((64, 64))
    dot[32, 32] = 1.0
    assert band_mtf(dot, 1.0, (3.0, 10.0)) == pytest.approx(1.0, abs=1e-12)


def test_peak_refines_with_a_parabola():
    a = np.linspace(0.0, 2.0, 21)
    s = 1.0 - (a - 1.234) ** 2
    assert peak(a, s) == pytest.approx(1.234, abs=1e-9)
    assert peak(a, a) == 2.0  # a curve rising to the end: the end state
    st = sweep_states(0.5, 1.0, AccommodationSpec(step_d=0.1, margin_d=0.5))
    assert st[0] == 0.0 and st[-1] == pytest.approx(1.5) and len(st) == 16


def test_response_equals_the_target_at_the_cdp(sweeps):
    assert sweeps[3.0][CDP]["response_d"] == pytest.approx(CDP, abs=0.1)


def test_response_rises_with_the_target(sweeps):
    r = [sweeps[3.0][t]["response_d"] for t in TARGETS]
    assert r[0] < r[1] < r[2]


def test_away_from_the_cdp_the_response_lies_between_target_and_cdp(sweeps):
    for t in (0.5, 2.0):
        r = sweeps[3.0][t]["response_d"]
        lo, hi = min(t, CDP), max(t, CDP)
        assert lo - 0.05 <= r <= hi + 0.05, (t, r)
        # ...and strictly away from both ends: the display does drive accommodation, partly.
        assert abs(r - CDP) > 0.1 and abs(r - t) > 0.1, (t, r)


def test_fewer_views_in_the_pupil_pull_the_response_to_the_cdp(sweeps):
    """A 1.5 mm pupil holds about one elemental view, a 3 mm pupil several."""
    for t in (0.5, 2.0):
        assert abs(sweeps[1.5][t]["response_d"] - CDP) < abs(sweeps[3.0][t]["response_d"] - CDP) - 0.2, t


def test_the_natural_view_follows_the_target(sweeps):
    for t in TARGETS:
        assert sweeps[3.0][t]["natural_response_d"] == pytest.approx(t, abs=0.1)


def test_a_broadband_natural_target_is_focused_at_its_depth_by_the_chromatic_eye():
    """The Arizona eye, spectral: a real (equal-energy white) target seen through the sRGB
    colour-matching functions is focused, at the 555 nm reference, at its own depth. Seen in
    the display's primaries instead, the green-weighted image is sharpest 0.1-0.15 D farther
    (the eye's chromatic offset at 530 nm), which this bound refuses."""
    d = lfsim.load(SCENES / "ini_ideal.toml")
    spec = AccommodationSpec(depths_d=(1.0,), cdp_d=1.0, pupil_mm=4.0, eye="arizona", fov_arcmin=96.0,
                             resolution=64, spp=128, margin_d=0.3)
    for t in TARGETS:
        states = sweep_states(t, t, spec)
        assert peak(states, curve(d, spec, "natural", t, CDP, states)) == pytest.approx(t, abs=0.1), t


def test_accommodation_cli_writes_json_and_plot(scenes, tmp_path, capsys):
    out = tmp_path / "acc"
    rc = main(["accommodation", str(scenes / "ini_ideal.toml"), "--depths-d", "1.5", "--cdp-d", "1",
               "--eye", "ideal", "--wavelength-nm", "555", "--resolution", "32", "--spp", "16",
               "--fov-arcmin", "96", "--step-d", "0.25", "--out", str(out), "--json"])
    assert rc == 0
    doc = json.loads(capsys.readouterr().out)
    assert json.loads((out / "accommodation.json").read_text()) == doc
    assert {"cdp_d", "pupil_mm", "metric", "points"} <= set(doc)
    (p,) = doc["points"]
    assert {"target_d", "response_d", "natural_response_d", "curve"} <= set(p)
    assert [a for a, _ in p["curve"]] == pytest.approx([0.5, 0.75, 1.0, 1.25, 1.5, 1.75, 2.0])
    assert (out / "accommodation.png").stat().st_size > 0


@pytest.mark.parametrize("args,msg", [
    (["--depths-d", "1,x"], "--depths-d"),
    (["--depths-d", "-1"], "--depths-d"),
    (["--band-cpd", "10,3"], "--band-cpd"),
    (["--band-cpd", "3,40", "--resolution", "32"], "Nyquist"),
    (["--step-d", "0"], "--step-d"),
    (["--pupil-mm", "0"], "--pupil-mm"),
    (["--eye", "other"], "--eye"),
])
def test_accommodation_bad_input(scenes, tmp_path, capsys, args, msg):
    try:
        rc = main(["accommodation", str(scenes / "ini_ideal.toml"), "--out", str(tmp_path / "o")] + args)
    except SystemExit as e:  # argparse's own refusals
        rc = e.code
    assert rc == 2
    assert msg in capsys.readouterr().err
    assert not (tmp_path / "o").exists()
