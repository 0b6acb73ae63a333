"""Global distortion GD (Eq. 11) and local distortion of each elemental image."""

from __future__ import annotations

import numpy as np


def gd_deg(r_real: np.ndarray, r_paraxial: np.ndarray) -> np.ndarray:
    """Eq. (11): ``GD = atan(|x_c − x'_c| / z_CDP)`` in degrees.

    The chief ray of the EI's centre field reaches the virtual CDP at
    ``x'_c = −z_CDP·r`` (``r`` its retinal tangent, see :mod:`.spot`) and the
    paraxial one at ``x_c = −z_CDP·r_par`` (Eq. 9), so
    ``|x_c − x'_c|/z_CDP = |r − r_par|``, which stays finite at 0 D.

    References
    ----------
    H. Huang and H. Hua, *Opt. Express* 27(18) (2019): Eq. (11), the global
    distortion of the virtual elemental images on the CDP.
    """
    d = np.asarray(r_real) - np.asarray(r_paraxial)
    return np.degrees(np.arctan(np.hypot(d[..., 0], d[..., 1])))


def local_distortion(r_real: np.ndarray, r_paraxial: np.ndarray, center: int = 0) -> np.ndarray:
    """Local distortion of an elemental image (fraction), per field (..., F).

    Field vectors are taken from the EI's centre field (index ``center``) in
    visual-angle tangents; the distortion of field f is
    ``|(r_f − r_0) − (p_f − p_0)| / |p_f − p_0|`` (0 for the centre itself):
    the shape error of the virtual EI once its position error (GD) is removed.
    """
    r = np.asarray(r_real)
    p = np.asarray(r_paraxial)
    dr_ = r - r[..., center:center + 1, :]
    dp = p - p[..., center:center + 1, :]
    num = np.hypot(*np.moveaxis(dr_ - dp, -1, 0))
    den = np.hypot(*np.moveaxis(dp, -1, 0))
    return np.where(den > 0, num / np.where(den > 0, den, 1.0), 0.0)


def gd_deg_jvp(e: np.ndarray, de: np.ndarray):
    """:func:`gd_deg` of ``e = r − r_par`` (..., 2) with its derivatives along ``de`` (..., 2, K).

    Returns ``(gd (...,), dgd (..., K), v (..., 2), dv (..., 2, K))``: GD in degrees, its
    derivative, and the residual vector ``v = gd · e/|e|`` (|v| = GD, smooth at e = 0,
    where it is ``e`` in degrees) with its derivative, for least squares.
    """
    e = np.asarray(e, dtype=np.float64)
    x = np.hypot(e[..., 0], e[..., 1])
    deg = 180.0 / np.pi
    gd = deg * np.arctan(x)
    small = x < 1e-6
    xs = np.where(small, 1.0, x)
    u = np.where(small[..., None], 0.0, e / xs[..., None])
    dx = np.einsum("...a,...ak->...k", u, de)  # d|e|
    dgd = deg / (1.0 + x * x)[..., None] * dx
    # ratio = gd/|e| = deg·atan(x)/x → deg(1 − x²/3) as x → 0; its x-derivative → −2·deg·x/3.
    ratio = np.where(small, deg * (1.0 - x * x / 3.0), gd / xs)
    dratio = np.where(small, -2.0 * deg * x / 3.0, (deg / (1.0 + x * x) - ratio) / xs)
    v = ratio[..., None] * e
    dv = ratio[..., None, None] * de + e[..., :, None] * (dratio[..., None] * dx)[..., None, :]
    return gd, dgd, v, dv


def local_distortion_jvp(r_real, dr_real, r_paraxial, dr_paraxial, center: int = 0):
    """:func:`local_distortion` (..., F) and its derivatives (..., F, K) along ``dr_real``
    and ``dr_paraxial`` (..., F, 2, K). A field exactly on its paraxial shape (or the centre
    field itself) gets no derivative (|·| has none there)."""
    r, p = np.asarray(r_real), np.asarray(r_paraxial)
    vr, vp = r - r[..., center:center + 1, :], p - p[..., center:center + 1, :]
    dvr = dr_real - dr_real[..., center:center + 1, :, :]
    dvp = dr_paraxial - dr_paraxial[..., center:center + 1, :, :]
    dd, ddd = vr - vp, dvr - dvp
    num, den = np.hypot(dd[..., 0], dd[..., 1]), np.hypot(vp[..., 0], vp[..., 1])
    good = den > 0
    dens = np.where(good, den, 1.0)
    ld = np.where(good, num / dens, 0.0)
    u = np.where((num > 0)[..., None], dd / np.where(num > 0, num, 1.0)[..., None], 0.0)
    dnum = np.einsum("...a,...ak->...k", u, ddd)
    dden = np.einsum("...a,...ak->...k", vp / dens[..., None], dvp)
    dld = np.where(good[..., None], (dnum - ld[..., None] * dden) / dens[..., None], 0.0)
    return ld, dld
