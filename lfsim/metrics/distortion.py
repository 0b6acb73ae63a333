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


def _monomials(degree: int) -> list[tuple[int, int]]:
    """(i, j) of the monomials x^i·y^j of total degree 0 … ``degree``, in the order
    1, x, y, x², xy, y², x³, x²y, xy², y³, …"""
    return [(t - j, j) for t in range(degree + 1) for j in range(t + 1)]


def _power(v: str, p: int) -> str:
    return "" if p == 0 else (v if p == 1 else f"{v}{p}")


def _monomial_name(i: int, j: int) -> str:
    return (_power("x", i) + _power("y", j)) or "1"


def distortion_terms(r_real, r_paraxial, degree: int = 3) -> dict | None:
    """GD's displacement field (Eq. 11) as a polynomial in the field: which distortion it is.

    ``r_real``, ``r_paraxial`` (P, 2): retinal tangents of the EI centres' real and
    paraxial chief rays (the two sides of :func:`gd_deg`) over the lenslets of one CDP
    state. The displacement ``e = atan(r) − atan(r_par)`` (degrees, x and y) is fitted by
    least squares with the monomials ``x^i·y^j`` (i + j ≤ ``degree``) of the normalized
    paraxial field ``x = θx/hx``, ``y = θy/hy``, where ``hx``, ``hy`` are the largest
    paraxial angles of the points: each coefficient is that term's displacement at the
    grid's edge, in degrees. In a design symmetric about its y–z plane, ``dx`` has only
    x-odd terms and ``dy`` only x-even ones; there ``dy·x2`` is the smile (the rows
    bow), ``dx·xy`` with ``dy·y2`` the keystone, ``dx·x`` and ``dy·y`` a scale error
    of the paraxial model per axis, and ``dx·x3 + dx·xy2``, ``dy·x2y + dy·y3`` in the
    ratios ``hy²/hx²`` and ``hx²/hy²`` a rotationally symmetric third-order distortion.

    The degree is lowered until the fit is determined (at least as many points as
    terms, full rank); None where not even the constant is (no point).
    Returns ``{"degree", "normalization_deg": [hx, hy], "dx": {name: c}, "dy": {…},
    "rms_deg": {"dy_x2": …}, "residual_rms_deg", "residual_max_deg"}``, ``rms_deg``
    being each term's own RMS displacement over the points (degrees), largest first,
    keyed ``d<axis>_<monomial>`` (written ``dy·x2`` in the docs).
    """
    r = np.asarray(r_real, dtype=np.float64).reshape(-1, 2)
    p = np.asarray(r_paraxial, dtype=np.float64).reshape(-1, 2)
    good = np.all(np.isfinite(r), axis=1) & np.all(np.isfinite(p), axis=1)
    r, p = r[good], p[good]
    if len(p) == 0:
        return None
    theta = np.degrees(np.arctan(p))
    e = np.degrees(np.arctan(r)) - theta
    h = np.max(np.abs(theta), axis=0)
    h = np.where(h > 0, h, 1.0)
    u = theta / h
    for deg in range(int(degree), -1, -1):
        terms = _monomials(deg)
        A = np.stack([u[:, 0] ** i * u[:, 1] ** j for i, j in terms], axis=1)
        if len(u) >= len(terms) and np.linalg.matrix_rank(A) == len(terms):
            break
    else:  # pragma: no cover - the constant always fits one point
        return None
    coef, *_ = np.linalg.lstsq(A, e, rcond=None)  # (T, 2)
    resid = e - A @ coef
    names = [_monomial_name(i, j) for i, j in terms]
    rms = {f"d{a}_{name}": float(np.sqrt(np.mean((A[:, t] * coef[t, ax]) ** 2)))
           for ax, a in enumerate("xy") for t, name in enumerate(names)}
    return {
        "degree": deg,
        "normalization_deg": [float(v) for v in h],
        "dx": {n: float(c) for n, c in zip(names, coef[:, 0])},
        "dy": {n: float(c) for n, c in zip(names, coef[:, 1])},
        "rms_deg": dict(sorted(rms.items(), key=lambda kv: -kv[1])),
        "residual_rms_deg": float(np.sqrt(np.mean(np.sum(resid ** 2, axis=1)))),
        "residual_max_deg": float(np.max(np.hypot(resid[:, 0], resid[:, 1]))),
    }
