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

The random numbers (:func:`kick_samples`) are the next two dimensions of the
sensor's own sampler during a render: with the ``multijitter`` sampler the
kicks are stratified per pixel like the film, pupil and wavelength samples,
independently of them (each sampler dimension has its own permutation).
Outside a render (a sensor sampled directly), they come from the Tiny
Encryption Algorithm on the bits of the ray's film and pupil samples
(:func:`random_pair`). Either way a render is a pure function of its seed.
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


def kick_samples(mi, sensor, s2, s3, active=True, salt: int = 0):
    """Two uniform numbers per ray for a diffraction kick: the next 2D dimension of
    ``sensor``'s sampler when a render has seeded it for this wavefront (stratified per
    pixel), else :func:`random_pair` (TEA) of the film and pupil samples."""
    import drjit as dr

    sampler = sensor.sampler()
    if sampler is not None and sampler.wavefront_size() == dr.width(s2):
        u = sampler.next_2d(active)
        return u.x, u.y
    return random_pair(mi, s2, s3, salt)


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


#: Largest slit coordinate t = π w s / λ sampled (1 − CDF ≈ 1 / (π² t / 2)... : 0.1 % beyond).
SLIT_T_MAX = 200.0 * math.pi


@lru_cache(maxsize=4)
def slit_inverse_cdf(n: int = AIRY_TABLE, t_max: float = SLIT_T_MAX) -> np.ndarray:
    """|t| at ``n`` equally spaced fractions of the slit pattern ``sinc²(t)``'s energy on
    [0, t_max] (one side; ``∫₀ᵀ sin² t / t² dt = Si(2T) − sin² T / T``)."""
    from scipy.special import sici

    t = np.unique(np.concatenate([np.linspace(0.0, 60.0, 60001), np.geomspace(60.0, t_max, 20001)]))
    tt = np.maximum(t, 1e-12)
    F = sici(2.0 * tt)[0] - np.sin(tt) ** 2 / tt
    F = np.maximum.accumulate(F) / F[-1]
    return np.interp(np.linspace(0.0, 1.0, n), F, t)


class ViewApertureKick:
    """Diffraction of an elemental view's aperture on the display path (Dr.Jit, in the
    reverse trace at the lenslet stop: the aperture-array opening or the lenslet's face).

    The view's aperture is the stop's opening clipped by the image of the eye pupil in the
    stop's plane. For the ray that crossed the pupil at ``q`` and meets the stop at ``a``
    (lenslet-relative), that image is the ellipse ``a − K q + K·disk(R)``, ``K`` the inverse
    of the lenslet's Jacobian ``J = ∂(viewing-window position) / ∂(stop position)`` (traced
    per lenslet from its elemental-image centre). The ellipse is replaced by its bounding
    box, so the aperture is a rectangle (exact when the pupil does not clip the view, the
    usual case of a small stop and a large pupil; a clipped view's curved edge becomes a
    straight one), and its Fraunhofer pattern is the separable ``sinc²`` of its widths
    ``w_x, w_y``: direction cosines change by ``s = t λ / (π w)`` per axis, ``t`` sampled
    from :func:`slit_inverse_cdf`, ``λ`` in the medium at the stop.
    """

    def __init__(self, model, k: int, pupil_diameter_mm: float, T):
        import drjit as dr

        from ..ini.subsystems import trace_rays

        self.T = T
        self.pupil_mm = float(pupil_diameter_mm)
        M, N = model.arr.m, model.arr.n
        mm, nn = np.meshgrid(np.arange(M), np.arange(N), indexing="ij")
        mm, nn = mm.ravel(), nn.ravel()
        s0 = model.ei_centers(k, mm, nn)
        eps = 0.01
        rho = np.array([[0.0, 0.0], [eps, 0.0], [0.0, eps]])
        L = len(mm)
        pos, _, _, status, _ = trace_rays(model, np.repeat(s0, 3, axis=0), np.repeat(mm, 3), np.repeat(nn, 3),
                                          np.tile(rho, (L, 1)), np.full(3 * L, k), iterations=12)
        pos, ok = pos.reshape(L, 3, 2), (status.reshape(L, 3) == 0).all(axis=1)
        half = np.asarray(model.stop_half, dtype=np.float64)
        J = np.stack([(pos[:, 1] - pos[:, 0]) / (eps * half[0]), (pos[:, 2] - pos[:, 0]) / (eps * half[1])], axis=2)
        K = np.zeros_like(J)
        det = np.linalg.det(J)
        good = ok & np.isfinite(det) & (np.abs(det) > 1e-12)
        K[good] = np.linalg.inv(J[good])
        R = 0.5 * self.pupil_mm
        ext = R * np.sqrt(np.sum(K ** 2, axis=2))  # (L, 2): the ellipse's half extents along x, y
        ext[~good] = 1e9  # no Jacobian (a lenslet no ray of the EI centre gets through): no clipping
        self.K = K
        self.extent = ext
        self.half = half
        self.n_lens = N
        # Lenslet index m·N + n → its K (4) and extents (2), opaque.
        self._K = T.Float(K.reshape(-1).astype(T.np_dtype))
        self._E = T.Float(ext.reshape(-1).astype(T.np_dtype))
        tab = slit_inverse_cdf()
        self.n = len(tab)
        self._tab = T.Float(tab.astype(T.np_dtype))
        dr.make_opaque(self._K, self._E, self._tab)
        self._hx = dr.opaque(T.Float, float(half[0]))
        self._hy = dr.opaque(T.Float, float(half[1]))

    def _slit(self, u):
        """Signed slit coordinate t for u ∈ [0, 1): sign from u < ½, |t| from the table."""
        import drjit as dr

        T = self.T
        v = dr.abs(2.0 * u - 1.0)
        x = v * float(self.n - 1)
        i = T.UInt32(dr.minimum(dr.floor(x), float(self.n - 2)))
        f = x - T.Float(i)
        a = dr.gather(T.Float, self._tab, i)
        b = dr.gather(T.Float, self._tab, i + 1)
        return dr.select(u < 0.5, -1.0, 1.0) * dr.fma(f, b - a, a)

    def widths(self, hit, cell, q):
        """Per ray (w_x, w_y) (mm): the stop opening ∩ the bounding box of the pupil's image."""
        import drjit as dr

        T = self.T
        L = T.UInt32(cell[0]) * self.n_lens + T.UInt32(cell[1])
        k = [dr.gather(T.Float, self._K, L * 4 + j) for j in range(4)]
        ex, ey = dr.gather(T.Float, self._E, L * 2), dr.gather(T.Float, self._E, L * 2 + 1)
        cx = hit.x - (k[0] * q[0] + k[1] * q[1])
        cy = hit.y - (k[2] * q[0] + k[3] * q[1])
        wx = dr.minimum(self._hx, cx + ex) - dr.maximum(-self._hx, cx - ex)
        wy = dr.minimum(self._hy, cy + ey) - dr.maximum(-self._hy, cy - ey)
        tiny = 1e-4 * dr.minimum(self._hx, self._hy)
        return dr.maximum(wx, tiny), dr.maximum(wy, tiny)

    def kick(self, d, hit, cell, q, lam_mm, u1, u2):
        """Direction ``d`` (local to the stop surface) changed by the Fraunhofer pattern of the
        view's aperture; ``lam_mm``: the wavelength in the medium there."""
        import drjit as dr

        wx, wy = self.widths(hit, cell, q)
        sx = self._slit(u1) * lam_mm / (math.pi * wx)
        sy = self._slit(u2) * lam_mm / (math.pi * wy)
        ax, ay = d.x + sx, d.y + sy
        r2 = dr.fma(ax, ax, ay * ay)
        # A kick beyond the hemisphere (the far tail of a tiny aperture) is evanescent: keep d.
        ok = r2 < 1.0
        az = dr.select(d.z < 0.0, -1.0, 1.0) * dr.safe_sqrt(1.0 - r2)
        T = self.T
        return T.Array3(dr.select(ok, ax, d.x), dr.select(ok, ay, d.y), dr.select(ok, az, d.z))
