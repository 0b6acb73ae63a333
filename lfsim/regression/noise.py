"""Noise-aware image statistics for regression tests of Monte Carlo renders.

Every image is rendered twice, with two seeds, at the same spp: the baseline
``B1, B2`` and the candidate ``C1, C2`` (candidate seed k pairs with baseline
seed k). The Monte Carlo noise of different seeds is independent and has
zero mean, so products of *independent* differences estimate noise-free
quantities without any model of the noise itself:

* **change energy** (is the image different?)
  ``x_p = (C1 − B1)_p · (C2 − B2)_p`` has expectation ``(μC − μB)_p²``, the
  squared change of the noise-free image at pixel p, whatever the noise
  level, its spatial correlation or its dependence on the pixel. Its mean
  over the image is reported as an RMS change (% of the image mean).
* **detail energy** (is it blurrier?) with a band pass ``F`` (difference of
  Gaussians, σ = 1 and 2.5 px, as in the focus-cue analysis):
  ``s_p = (F X1)_p · (F X2)_p`` estimates ``(F μX)_p²``, the noise-free
  band-pass energy; candidate against baseline gives the relative loss of
  fine detail, unbiased by the noise that a plain band-pass energy would add.
* **error against the natural view** (does it look less like the real
  scene?): ``e_p = (C1 − N1)_p · (C2 − N2)_p`` with the natural views ``N``
  of the same seeds estimates ``(μC − μN)_p²``, the noise-free squared error.

Significance: the image is cut into square tiles larger than the noise's
correlation length (the reconstruction filter, the band pass); tile sums
``t_i`` of a statistic are nearly independent. Under "nothing changed" each
``t_i`` has zero mean and a symmetric distribution (swapping seed k of the
candidate and the baseline flips its sign), so the self-normalised sum
``z = Σ t_i / sqrt(Σ t_i²)`` obeys ``P(z ≥ a) ≤ exp(−a²/2)`` for any noise
distribution and any mix of noisy and clean tiles (Efron 1969; de la Peña
1999): ``a = 4`` gives a false alarm rate below 3.4e-4 per statistic. A real
change adds the same sign to every affected tile and drives ``z`` up as the
square root of the number of tiles it touches. A check fails when ``|z|``
passes ``z_max`` *and* the effect passes a small floor (so that very high spp
does not flag changes nobody could see).

The same seeds in baseline and candidate (common random numbers, the
default of ``lfsim regress``) make the noise of ``C − B`` far smaller than
that of two seeds, without biasing any of the estimators above.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

LUMA = np.array([0.2126, 0.7152, 0.0722])
#: Difference-of-Gaussians band pass (px), the focus-cue analysis' (lfsim.vision.focus_cues).
BAND_SIGMAS = (1.0, 2.5)


@dataclass
class Statistic:
    """One noise-aware statistic of an image, candidate against baseline.

    ``value``: the effect (see the statistic); ``z``: the self-normalised
    significance (positive = larger in the candidate); ``threshold``: the
    smallest effect that would have reached ``z_max`` at this noise level.
    """

    name: str
    baseline: float
    candidate: float
    value: float
    z: float
    threshold: float
    tiles: int

    def as_dict(self) -> dict:
        return {k: _finite(v) for k, v in self.__dict__.items()}


def _finite(v):
    return None if isinstance(v, float) and not math.isfinite(v) else v


def luminance(img: np.ndarray) -> np.ndarray:
    """(H, W) luminance of an (H, W, 3) linear RGB image (or the single channel)."""
    img = np.asarray(img, np.float64)
    if img.ndim == 2:
        return img
    return img @ LUMA if img.shape[2] == 3 else img.mean(axis=2)


def bandpass(img: np.ndarray) -> np.ndarray:
    """Difference-of-Gaussians band pass of the luminance (σ = 1 and 2.5 px)."""
    from skimage.filters import difference_of_gaussians

    return difference_of_gaussians(luminance(img), *BAND_SIGMAS)


def tile_sums(x: np.ndarray, tile: int) -> np.ndarray:
    """Sums of ``x`` (H, W[, C]) over ``tile`` × ``tile`` pixel tiles (edge tiles may be smaller), flattened."""
    x = np.asarray(x, np.float64)
    if x.ndim == 3:
        x = x.sum(axis=2)
    H, W = x.shape
    rows = np.add.reduceat(x, np.arange(0, H, tile), axis=0)
    return np.add.reduceat(rows, np.arange(0, W, tile), axis=1).ravel()


def self_normalized_z(t: np.ndarray) -> float:
    """``Σ t / sqrt(Σ t²)``: about N(0, 1) for independent zero-mean tiles; 0 when every tile is 0."""
    t = np.asarray(t, np.float64)
    q = math.sqrt(float(np.sum(t * t)))
    return 0.0 if q == 0.0 else float(np.sum(t)) / q


def _threshold(t: np.ndarray, z_max: float) -> float:
    """Smallest total of the tiles that reaches ``z_max`` at their observed spread."""
    return z_max * math.sqrt(float(np.sum(np.asarray(t) ** 2)))


def change(b: tuple, c: tuple, z_max: float, tile: int = 8) -> Statistic:
    """Is the noise-free image different?  ``value``: RMS change as a fraction of the baseline mean.

    ``b``, ``c``: the baseline's and the candidate's two seeds, ``(H, W, C)``
    each, candidate seed k rendered like baseline seed k. ``baseline``: the
    seed-to-seed noise (RMS per pixel and channel of one render, fraction of
    the mean); ``candidate``: the same for the candidate.
    """
    b1, b2 = (np.asarray(v, np.float64) for v in b)
    c1, c2 = (np.asarray(v, np.float64) for v in c)
    n = b1.size
    mean = max(float(np.mean(0.5 * (b1 + b2))), 1e-12)
    t = tile_sums((c1 - b1) * (c2 - b2), tile)
    energy = float(np.sum(t)) / n
    rel = math.copysign(math.sqrt(abs(energy)), energy) / mean
    thr = math.sqrt(_threshold(t, z_max) / n) / mean
    noise_b = math.sqrt(float(np.mean((b1 - b2) ** 2)) / 2.0) / mean
    noise_c = math.sqrt(float(np.mean((c1 - c2) ** 2)) / 2.0) / mean
    return Statistic("change", noise_b, noise_c, rel, self_normalized_z(t), thr, t.size)


def _product_energy(x: tuple, tile: int, fn) -> np.ndarray:
    return tile_sums(fn(x[0]) * fn(x[1]), tile)


def detail(b: tuple, c: tuple, z_max: float, tile: int = 16) -> Statistic:
    """Did fine detail (band-pass energy) change?  ``value``: candidate / baseline − 1 (negative = blurrier).

    ``baseline``, ``candidate``: the noise-free band-pass energies (mean per pixel).
    """
    tb = _product_energy(b, tile, bandpass)
    tc = _product_energy(c, tile, bandpass)
    eb, ec = float(np.sum(tb)), float(np.sum(tc))
    n = luminance(b[0]).size
    scale = max(abs(eb), 1e-300)
    return Statistic("detail", eb / n, ec / n, ec / scale - 1.0, self_normalized_z(tc - tb),
                     _threshold(tc - tb, z_max) / scale, tb.size)


def error_vs(ref_b: tuple, b: tuple, ref_c: tuple, c: tuple, z_max: float, tile: int = 8) -> Statistic:
    """Did the noise-free squared error against a reference view (the natural view) change?

    ``value``: candidate / baseline − 1 of the mean squared error (positive =
    further from the reference); ``baseline``, ``candidate``: the noise-free
    MSE of each against its reference.
    """
    def energy(x, r):
        return tile_sums((np.asarray(x[0], np.float64) - r[0]) * (np.asarray(x[1], np.float64) - r[1]), tile)

    tb, tc = energy(b, ref_b), energy(c, ref_c)
    eb, ec = float(np.sum(tb)), float(np.sum(tc))
    n = np.asarray(b[0]).size
    scale = max(abs(eb), 1e-300)
    return Statistic("error_vs_natural", eb / n, ec / n, ec / scale - 1.0, self_normalized_z(tc - tb),
                     _threshold(tc - tb, z_max) / scale, tb.size)


def noise_free_psnr(mse: float, data_range: float) -> float | None:
    """PSNR (dB) from a noise-free MSE estimate; None when the estimate is not positive."""
    return 10.0 * math.log10(data_range * data_range / mse) if mse > 0 else None
