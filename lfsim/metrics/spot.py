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


def rms_spot_jvp(r: np.ndarray, dr: np.ndarray, weights: np.ndarray, ok: np.ndarray):
    """:func:`rms_spot` with derivatives along ``dr`` (..., R, 2, K) of the directions.

    Every step of :func:`rms_spot` is differentiated exactly: the centroid, the
    gnomonic basis about it (which turns with the centroid), the projection and
    the angular-centroid shift. Returns ``(rms (...,), drms (..., K), off (..., R, 2),
    doff (..., R, 2, K), wn (..., R))``, ``wn`` the normalized weights (0 for failed
    rays), so ``Σ wn |off|² = rms²``.
    """
    r = np.asarray(r, dtype=np.float64)
    w = np.where(ok, weights, 0.0)
    wsum = np.sum(w, axis=-1, keepdims=True)
    wn = w / np.where(wsum > 0, wsum, 1.0)
    cen = np.einsum("...r,...rk->...k", wn, r)
    dcen = np.einsum("...r,...rak->...ak", wn, dr)  # (..., 2, K)
    K = dr.shape[-1]
    zeros = np.zeros(cen.shape[:-1] + (1, K))
    # c = a/|a|, a = (cen, 1)
    a = np.concatenate([cen, np.ones(cen.shape[:-1] + (1,))], axis=-1)
    da = np.concatenate([dcen, zeros], axis=-2)  # (..., 3, K)
    na = np.linalg.norm(a, axis=-1, keepdims=True)
    c = a / na

    def unit_jvp(vec, dvec, norm):
        return (dvec - vec[..., :, None] * np.einsum("...i,...ik->...k", vec, dvec)[..., None, :]) / norm[..., None]

    dc = unit_jvp(c, da, na)
    # e1 = b/|b|, b = ex − (ex·c) c
    cx = c[..., 0:1]
    b = -cx * c
    b[..., 0] += 1.0
    db = -(dc[..., 0:1, :] * c[..., :, None] + cx[..., None] * dc)
    nb = np.linalg.norm(b, axis=-1, keepdims=True)
    e1 = b / nb
    de1 = unit_jvp(e1, db, nb)
    e2 = np.cross(c, e1)
    de2 = (np.cross(np.moveaxis(dc, -1, -2), e1[..., None, :]) + np.cross(c[..., None, :], np.moveaxis(de1, -1, -2)))
    de2 = np.moveaxis(de2, -2, -1)  # (..., 3, K)
    v = np.concatenate([r, np.ones(r.shape[:-1] + (1,))], axis=-1)  # (..., R, 3)
    dv = np.concatenate([dr, np.zeros(r.shape[:-1] + (1, K))], axis=-2)  # (..., R, 3, K)
    den = np.einsum("...rk,...k->...r", v, c)
    dden = np.einsum("...rik,...i->...rk", dv, c) + np.einsum("...ri,...ik->...rk", v, dc)
    offs, doffs = [], []
    for e_, de_ in ((e1, de1), (e2, de2)):
        num = np.einsum("...rk,...k->...r", v, e_)
        dnum = np.einsum("...rik,...i->...rk", dv, e_) + np.einsum("...ri,...ik->...rk", v, de_)
        o = num / den
        offs.append(o)
        doffs.append((dnum - o[..., None] * dden) / den[..., None])
    off = np.stack(offs, axis=-1)  # (..., R, 2)
    doff = np.stack(doffs, axis=-2)  # (..., R, 2, K)
    shift = np.einsum("...r,...rk->...k", wn, off)
    dshift = np.einsum("...r,...rak->...ak", wn, doff)
    off = off - shift[..., None, :]
    doff = doff - dshift[..., None, :, :]
    rms = np.sqrt(np.einsum("...r,...r->...", wn, np.sum(off * off, axis=-1)))
    drms = np.einsum("...r,...ra,...rak->...k", wn, off, doff) / np.where(rms > 0, rms, 1.0)[..., None]
    return rms, drms, off, doff, wn
