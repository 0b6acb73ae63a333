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
