"""Retinal coordinates and the RMS spot in visual angle.

An ideal eye lens at the viewing window focused at ``D`` diopters maps a ray
leaving the window at ``h`` with slopes ``t`` to the retinal point
``f_eye·(t − h·D/1000)``: the tangent of the visual angle of the point the ray
appears to come from on the plane at 1000/D mm (finite at 0 D). Spots are
measured as angles about their centroid direction (gnomonic coordinates, which
are isometric to first order there), so a spot 15° off axis is not stretched
by the 1/cos² of tangent coordinates.
"""

from __future__ import annotations

import numpy as np

ARCMIN = 180.0 * 60.0 / np.pi


def retinal_tan(pos: np.ndarray, slopes: np.ndarray, diopters) -> np.ndarray:
    """``t − h·D/1000`` (..., 2); ``diopters`` broadcasts against the leading axes."""
    D = np.asarray(diopters, dtype=np.float64)[..., None]
    return slopes - pos * (D / 1000.0)


def _basis(center: np.ndarray):
    c = np.concatenate([center, np.ones(center.shape[:-1] + (1,))], axis=-1)
    c /= np.linalg.norm(c, axis=-1, keepdims=True)
    ex = np.zeros_like(c)
    ex[..., 0] = 1.0
    e1 = ex - np.sum(ex * c, axis=-1, keepdims=True) * c
    e1 /= np.linalg.norm(e1, axis=-1, keepdims=True)
    e2 = np.cross(c, e1)
    return c, e1, e2


def angular_offsets(r: np.ndarray, center: np.ndarray) -> np.ndarray:
    """Angles (rad, (..., R, 2)) of directions ``r`` (tan, (..., R, 2)) about ``center`` (..., 2).

    Gnomonic projection onto the plane perpendicular to the centre direction:
    axis 0 lies in the plane of the centre and the x axis (horizontal), axis 1
    completes it (vertical)."""
    c, e1, e2 = _basis(center)
    v = np.concatenate([r, np.ones(r.shape[:-1] + (1,))], axis=-1)
    den = np.einsum("...rk,...k->...r", v, c)
    return np.stack([np.einsum("...rk,...k->...r", v, e1) / den,
                     np.einsum("...rk,...k->...r", v, e2) / den], axis=-1)


def rms_spot(r: np.ndarray, weights: np.ndarray, ok: np.ndarray):
    """Weighted RMS spot radius of directions ``r`` (..., R, 2).

    ``weights`` (R,) is the pupil quadrature rule, ``ok`` (..., R) excludes
    failed rays (their weight is dropped and the rest renormalized).
    Returns ``(rms_rad, centroid_tan, offsets_rad)``; ``rms`` is NaN-free: a
    bundle with no ray left gives 0 with ``ok`` all false.

    References
    ----------
    H. Huang and H. Hua, *Opt. Express* 27(18) (2019): the RMS spot of each
    sub-system's ray bundle in visual angle, one of the design method's
    image-quality targets.
    """
    w = np.where(ok, weights, 0.0)
    wsum = np.sum(w, axis=-1, keepdims=True)
    wn = w / np.where(wsum > 0, wsum, 1.0)
    cen = np.einsum("...r,...rk->...k", wn, r)
    off = angular_offsets(r, cen)
    # Refine the centre to the angular centroid (the tangent centroid is off by O(spot²)).
    shift = np.einsum("...r,...rk->...k", wn, off)
    off = off - shift[..., None, :]
    rms = np.sqrt(np.einsum("...r,...r->...", wn, np.sum(off * off, axis=-1)))
    return rms, cen, off
