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


def pa_shape(real: np.ndarray, paraxial: np.ndarray, d_v: float) -> np.ndarray:
    """Eq. (12) of each footprint after its own mean displacement is removed: the
    deformation part of PA (size, shape and rotation of the footprint), without the
    shift of the footprint as a whole. ``real``, ``paraxial``, ``d_v`` as in :func:`pa`.

    The shift is what moves a view to another place in the viewing window (the eye
    meets it elsewhere or not at all); the deformation is what changes the view's
    beam. ``pa_shape ≤ pa`` holds only on average: removing the mean of four
    vectors can lengthen one of them.
    """
    dev = np.asarray(real) - np.asarray(paraxial)
    return pa(dev - np.mean(dev, axis=-2, keepdims=True), np.zeros_like(dev), d_v)


def axis_crossing(pos: np.ndarray, slopes: np.ndarray) -> dict | None:
    """Where rays cross the line of sight, per axis, by least squares.

    ``pos`` (N, 2): the rays' points on a plane z = 0 (the viewing window), ``slopes``
    (N, 2): their dx/dz, dy/dz. Per axis a the ray's distance from the axis on the
    plane z is ``pos_a + slopes_a·z``; the plane that minimizes the sum of its
    squares over the rays is ``z_a = −Σ pos_a·slopes_a / Σ slopes_a²``. With the
    elemental images' centre chief rays this is where the display's real viewing
    window is (the paper: the window is where those rays meet the axis).

    Returns ``{"offset_mm": [z_x, z_y], "rms_mm": [...], "rms_at_window_mm": [...]}``
    (the RMS distance from the axis at z_a and at z = 0), with None for an axis along
    which no ray has a slope (e.g. one column of lenslets); None without rays.
    """
    pos = np.asarray(pos, dtype=np.float64).reshape(-1, 2)
    t = np.asarray(slopes, dtype=np.float64).reshape(-1, 2)
    if len(pos) == 0:
        return None
    out = {"offset_mm": [], "rms_mm": [], "rms_at_window_mm": []}
    for a in range(2):
        tt = float(np.sum(t[:, a] ** 2))
        z = -float(np.sum(pos[:, a] * t[:, a])) / tt if tt > len(t) * 1e-18 else None  # RMS slope > 1e-9
        out["offset_mm"].append(z)
        out["rms_mm"].append(None if z is None else float(np.sqrt(np.mean((pos[:, a] + t[:, a] * z) ** 2))))
        out["rms_at_window_mm"].append(float(np.sqrt(np.mean(pos[:, a] ** 2))))
    return out
