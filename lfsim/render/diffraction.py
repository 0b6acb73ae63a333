"""Diffraction of the apertures that limit a retinal view, as sampled angular kicks.

Method: the Fraunhofer point-spread function of the limiting aperture is
sampled exactly and applied to each ray as a small change of direction in the
aperture's plane (the image is then the geometric image convolved with that
PSF, the standard "geometric ⊗ diffraction" approximation of a system whose
aberrations are either small or large against the diffraction blur). Unlike
ray bending by the Heisenberg uncertainty principle (HURB), which spreads
energy with a smooth, ring-free kernel, the sampled PSF keeps the Airy
pattern's dark rings and its encircled energy.

* **Eye pupil** (circular, diameter D): the Airy pattern
  ``I(x) ∝ [2 J1(x) / x]²``, ``x = π D sin θ / λ``. Its radius is sampled by
  the inverse of the encircled energy ``EE(x) = 1 − J0(x)² − J1(x)²``
  (Rayleigh), tabulated on :data:`AIRY_TABLE` nodes up to ``x = AIRY_X_MAX``
  (99.87 % of the energy; the far tail beyond is left out and the PSF
  renormalized), its azimuth uniformly.

The random numbers come from the Tiny Encryption Algorithm on the bits of
the ray's film and pupil samples (``mi.sample_tea_float32``): the kicks are
independent of the samples that place the ray, and a render stays a pure
function of its seed.
"""

from __future__ import annotations

import math
from functools import lru_cache

import numpy as np

#: Largest Airy radius x = π D sin θ / λ sampled (1 − EE(x) ≈ 2 / (π x): 0.13 % beyond).
AIRY_X_MAX = 500.0
#: Nodes of the tabulated inverse encircled energy.
AIRY_TABLE = 8192


@lru_cache(maxsize=4)
def airy_inverse_ee(n: int = AIRY_TABLE, x_max: float = AIRY_X_MAX) -> np.ndarray:
    """x at ``n`` equally spaced fractions u ∈ [0, 1] of the Airy pattern's energy inside
    ``x_max`` (float64, x[0] = 0, x[-1] = x_max)."""
    from scipy.special import j0, j1

    # Dense where the rings are, then geometric: EE is smooth between its nodes.
    x = np.unique(np.concatenate([np.linspace(0.0, 60.0, 60001), np.geomspace(60.0, x_max, 20001)]))
    ee = 1.0 - j0(x) ** 2 - j1(x) ** 2
    ee = np.maximum.accumulate(ee) / ee[-1]
    return np.interp(np.linspace(0.0, 1.0, n), ee, x)


def airy_fraction(x) -> np.ndarray:
    """The Airy pattern's encircled energy inside radius x (Rayleigh), normalized to x_max."""
    from scipy.special import j0, j1

    x = np.asarray(x, dtype=np.float64)
    ee = lambda v: 1.0 - j0(v) ** 2 - j1(v) ** 2  # noqa: E731
    return ee(x) / ee(AIRY_X_MAX)


def random_pair(mi, s2, s3, salt: int = 0):
    """Two uniform numbers in [0, 1) per lane from the bits of the film sample ``s2`` and the
    pupil sample ``s3`` (Dr.Jit; TEA, 8 rounds)."""
    import drjit as dr

    b = [dr.reinterpret_array(mi.UInt32, v) for v in (s2.x, s2.y, s3.x, s3.y)]
    v0 = b[0] ^ (b[2] * 0x9E3779B9)
    v1 = b[1] ^ (b[3] * 0x85EBCA6B) ^ salt
    return mi.sample_tea_float32(v0, v1, 8), mi.sample_tea_float32(v1 ^ 0x68E31DA4, v0, 8)


class AiryKick:
    """Samples the eye pupil's Airy pattern as a change of direction (Dr.Jit, one variant).

    ``table``: the opaque inverse encircled energy (:func:`airy_inverse_ee`).
    """

    def __init__(self, mi):
        import drjit as dr

        self.mi = mi
        tab = airy_inverse_ee()
        self.n = len(tab)
        self.table = mi.Float(tab.astype(np.float32))
        dr.make_opaque(self.table)

    def sin_theta(self, u, wavelength_nm, diameter_mm):
        """sin θ of the sampled radius, for uniform ``u`` (Dr.Jit Float)."""
        import drjit as dr

        mi = self.mi
        t = u * float(self.n - 1)
        i = mi.UInt32(dr.minimum(dr.floor(t), float(self.n - 2)))
        f = t - mi.Float(i)
        a = dr.gather(mi.Float, self.table, i)
        b = dr.gather(mi.Float, self.table, i + 1)
        x = dr.fma(f, b - a, a)
        return x * (wavelength_nm * 1e-6) * (1.0 / math.pi) / diameter_mm

    def kick(self, d, u1, u2, wavelength_nm, diameter_mm):
        """Unit direction ``d`` (Vector3f) turned by an angle sampled from the Airy pattern of a
        circular aperture of ``diameter_mm`` at ``wavelength_nm``, in a uniform azimuth."""
        import drjit as dr

        mi = self.mi
        s = dr.minimum(self.sin_theta(u1, wavelength_nm, diameter_mm), 1.0)
        c = dr.safe_sqrt(1.0 - s * s)
        phi = 2.0 * math.pi * u2
        frame = mi.Frame3f(d)
        return dr.normalize(c * d + s * (dr.cos(phi) * frame.s + dr.sin(phi) * frame.t))
