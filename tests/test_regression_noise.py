"""The noise model of regression checks (lfsim.regression.noise) on synthetic Monte Carlo images.

A known noise-free image is "rendered" by averaging spp Bernoulli samples of
its value per pixel (heteroscedastic, bounded noise like a Monte Carlo
render of a binary texture), spread over neighbouring pixels by a small
reconstruction filter (spatially correlated noise). Reseeds must never
reach the threshold; a blur of the noise-free image of a few percent of
detail must.
"""

import numpy as np
from scipy.ndimage import gaussian_filter

from lfsim.regression import noise

Z_MAX = 4.0


def _truth(rng, shape=(72, 128)):
    tex = gaussian_filter(rng.standard_normal(shape), 1.2) > 0
    return gaussian_filter(tex.astype(float), 0.7)


def _render(mu, spp, rng):
    """Mean of ``spp`` Bernoulli(mu) samples per pixel, through a reconstruction filter (σ 0.5 px); RGB."""
    img = rng.binomial(spp, np.clip(mu, 0, 1)) / spp
    img = gaussian_filter(img, 0.5)
    return np.repeat(img[..., None], 3, axis=2)


def test_reseeds_stay_below_the_threshold_and_z_is_calibrated():
    rng = np.random.default_rng(1)
    mu = _truth(rng)
    zs = {"change": [], "detail": []}
    for _ in range(120):
        b = (_render(mu, 16, rng), _render(mu, 16, rng))
        c = (_render(mu, 16, rng), _render(mu, 16, rng))
        zs["change"].append(noise.change(b, c, Z_MAX).z)
        zs["detail"].append(noise.detail(b, c, Z_MAX).z)
    for name, z in zs.items():
        z = np.array(z)
        assert np.max(np.abs(z)) < Z_MAX, (name, np.max(np.abs(z)))
        # Noise of the 120 trials' figures: the mean's standard error std/sqrt(n) (~0.09) and
        # the standard deviation's std/sqrt(2(n - 1)) (~0.07).
        sem, se_std = np.std(z) / np.sqrt(z.size), np.std(z) / np.sqrt(2 * (z.size - 1))
        assert 4 * se_std < 0.3, (name, se_std)  # the calibration window is wider than the noise
        assert 0.5 < np.std(z) < 1.3, (name, np.std(z))  # about N(0, 1): self-normalised
        assert abs(np.mean(z)) < 4 * sem, (name, np.mean(z), sem)  # zero mean, to 4 standard errors


def test_a_blur_of_a_few_percent_of_detail_is_detected():
    rng = np.random.default_rng(2)
    mu = _truth(rng)
    blurred = gaussian_filter(mu, 0.45)
    b = (_render(mu, 16, rng), _render(mu, 16, rng))
    c = (_render(blurred, 16, rng), _render(blurred, 16, rng))
    de = noise.detail(b, c, Z_MAX)
    # the noise-free band-pass energies, for the expected loss
    truth_loss = np.sum(noise.bandpass(np.repeat(blurred[..., None], 3, 2)) ** 2) / \
        np.sum(noise.bandpass(np.repeat(mu[..., None], 3, 2)) ** 2) - 1
    assert -0.2 < truth_loss < -0.01
    assert de.z < -Z_MAX and de.value < -de.threshold
    # Unbiased by the noise: within 10 % of the loss (the reconstruction filter's own blur) or
    # 4 standard errors of the estimate (threshold / z_max, 0.014 here), whichever is larger;
    # the ceiling keeps a zero loss failing.
    tol = max(0.1 * abs(truth_loss), 4 * de.threshold / Z_MAX)
    assert tol < 0.75 * abs(truth_loss), (tol, truth_loss)
    assert abs(de.value - truth_loss) < tol, (de.value, truth_loss, tol)


def test_a_one_pixel_shift_is_a_change_not_a_blur():
    rng = np.random.default_rng(5)
    mu = _truth(rng)
    shifted = np.roll(mu, 1, axis=1)
    b = (_render(mu, 16, rng), _render(mu, 16, rng))
    c = (_render(shifted, 16, rng), _render(shifted, 16, rng))
    ch = noise.change(b, c, Z_MAX)
    truth = np.sqrt(np.mean((shifted - mu) ** 2)) / np.mean(mu)
    assert ch.z > Z_MAX and ch.value > ch.threshold
    # The noise-free RMS change (blurred by the filter: 14 % less) to 25 %, or 4 standard errors
    # of the estimate, whichever is larger (the energy's is threshold² / z_max; ~4 % of the
    # change here); ceiling 50 %.
    se = ch.threshold ** 2 / (2 * Z_MAX * ch.value) / truth
    tol = max(0.25, 4 * se)
    assert tol <= 0.5, (tol, se)
    assert abs(ch.value / truth - 1) < tol, (ch.value / truth, tol)
    assert abs(noise.detail(b, c, Z_MAX).z) < Z_MAX


def test_estimators_are_unbiased_by_noise():
    """A plain band-pass energy grows with noise; the cross-seed product does not."""
    rng = np.random.default_rng(3)
    mu = _truth(rng)
    clean = np.repeat(mu[..., None], 3, 2)
    e_true = np.mean(noise.bandpass(clean) ** 2)
    # the reconstruction filter blurs the truth slightly: compare with the filtered truth
    e_filt = np.mean(noise.bandpass(gaussian_filter(clean, (0.5, 0.5, 0))) ** 2)
    assert 0.8 < e_filt / e_true < 1.0
    for spp in (1, 4, 64):
        ests, naive = [], []
        for _ in range(20):
            x = (_render(mu, spp, rng), _render(mu, spp, rng))
            ests.append(noise.detail(x, x, Z_MAX).baseline)
            naive.append(np.mean(noise.bandpass(x[0]) ** 2))
        ests = np.array(ests) / e_filt
        assert abs(np.mean(ests) - 1) < 4 * np.std(ests) / np.sqrt(len(ests)) + 1e-3, (spp, np.mean(ests))
        if spp == 1:
            assert np.mean(naive) / e_filt > 1.1  # a plain band-pass energy is biased by the noise


def test_identical_candidate_gives_zero_and_tiles_sum_everything():
    rng = np.random.default_rng(4)
    x = rng.random((20, 30))
    t = noise.tile_sums(x, 8)
    assert t.size == 3 * 4 and np.isclose(t.sum(), x.sum())
    b = (np.repeat(x[..., None], 3, 2),) * 2
    ch = noise.change(b, b, Z_MAX)
    assert ch.value == 0 and ch.z == 0
