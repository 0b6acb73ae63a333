"""Footprints on the viewing window and the pupil-aberration metric PA (Eq. 12)."""

from __future__ import annotations

import numpy as np


def pa(real: np.ndarray, paraxial: np.ndarray, d_v: float) -> np.ndarray:
    """Eq. (12): ``PA = ¼ Σ_k |v_k − v'_k| / (√2·d_v)``.

    ``real``, ``paraxial``: (..., 4, 2) viewing-window positions of the four
    marginal rays (the stop's edge midpoints) of one field; ``d_v`` the
    paraxial footprint diameter (Eq. 5), so √2·d_v is the footprint's diagonal.

    References
    ----------
    H. Huang and H. Hua, *Opt. Express* 27(18) (2019): Eq. (12), the pupil
    aberration of a sub-system's footprint on the viewing window.
    """
    dev = np.hypot(*np.moveaxis(np.asarray(real) - np.asarray(paraxial), -1, 0))
    return np.mean(dev, axis=-1) / (np.sqrt(2.0) * d_v)


def pa_jvp(dev: np.ndarray, ddev: np.ndarray):
    """:func:`pa` from the normalized footprint errors ``dev = (v − v')/(√2·d_v)``
    (..., 4, 2) and its derivatives along ``ddev`` (..., 4, 2, K): ``(PA (...,), dPA (..., K))``.
    A marginal ray exactly on its paraxial point contributes no derivative (|·| has none there)."""
    dev = np.asarray(dev, dtype=np.float64)
    a = np.hypot(dev[..., 0], dev[..., 1])  # (..., 4)
    u = np.where((a > 0)[..., None], dev / np.where(a > 0, a, 1.0)[..., None], 0.0)
    return np.mean(a, axis=-1), np.mean(np.einsum("...ma,...mak->...mk", u, ddev), axis=-2)
