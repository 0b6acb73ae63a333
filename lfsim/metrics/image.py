"""Image similarity: PSNR and SSIM, one convention for every figure lfsim reports.

``lfsim compare``, ``lfsim regress`` and a focal stack's ``index.json``
(``ssim_vs_natural``, ``psnr_vs_natural``) all use these functions, so the
same pair of images gives the same numbers everywhere:

* **data range**: max − min of the *reference* over all its channels (1 for a
  constant reference);
* **PSNR**: 10 log10(range² / MSE), the MSE over every pixel and channel;
* **SSIM**: scikit-image's ``structural_similarity`` (Wang et al., *IEEE
  Trans. Image Process.* 13(4), 600, 2004) with uniform 7×7
  windows (smaller on a side under 7 px) and that data range, computed per
  channel and averaged over channels;
* **exposure**: the mean of an image over the reference's mean
  (:func:`exposure`); :func:`ssim_matched` is the SSIM after the image is scaled
  by its inverse, so that a display that sends less light into the eye (a
  smaller aperture) is compared by its structure, not by its brightness, which
  the display's drive sets.
"""

from __future__ import annotations

import math

import numpy as np


def data_range(ref: np.ndarray) -> float:
    """Value range of the reference image (max − min); 1 for a constant image."""
    r = float(np.max(ref) - np.min(ref))
    return r if r > 0 else max(float(np.max(np.abs(ref))), 1.0)


def psnr(ref: np.ndarray, img: np.ndarray, rng: float | None = None) -> float:
    """Peak signal-to-noise ratio (dB) of ``img`` against ``ref``; ``inf`` when identical."""
    rng = data_range(ref) if rng is None else rng
    mse = float(np.mean((np.asarray(img, np.float64) - np.asarray(ref, np.float64)) ** 2))
    return math.inf if mse == 0.0 else 10.0 * math.log10(rng * rng / mse)


def ssim(ref: np.ndarray, img: np.ndarray, rng: float | None = None) -> float | None:
    """Mean structural similarity (scikit-image, 7×7 window, mean over channels).

    None for images smaller than 3 px on a side (no window fits).
    """
    from skimage.metrics import structural_similarity

    ref, img = np.asarray(ref, np.float64), np.asarray(img, np.float64)
    if ref.ndim == 2:
        ref, img = ref[..., None], img[..., None]
    side = min(ref.shape[:2])
    if side < 3:
        return None
    win = min(7, side if side % 2 else side - 1)
    rng = data_range(ref) if rng is None else rng
    if ref.shape[2] == 1:
        return float(structural_similarity(ref[..., 0], img[..., 0], data_range=rng, win_size=win))
    return float(structural_similarity(ref, img, data_range=rng, win_size=win, channel_axis=2))


def exposure(ref: np.ndarray, img: np.ndarray) -> float | None:
    """Mean of ``img`` over the mean of ``ref``; None when either mean is not positive."""
    m_ref, m_img = float(np.mean(ref)), float(np.mean(img))
    return m_img / m_ref if m_ref > 0 and m_img > 0 else None


def ssim_matched(ref: np.ndarray, img: np.ndarray, rng: float | None = None) -> float | None:
    """:func:`ssim` of ``img`` scaled to the mean of ``ref`` (None without a positive mean)."""
    e = exposure(ref, img)
    return None if e is None else ssim(ref, np.asarray(img, np.float64) / e, rng)
