"""MTF in visual angle: geometric (from the ray spot) and diffraction (from the optical path).

Frequencies are in cycles per radian of visual angle (``cpd·180/π``); the two
orientations are horizontal (x) and vertical (y) bars, i.e. modulation along
the spot's angular axes 0 and 1 (see :func:`lfsim.metrics.spot.angular_offsets`).
"""

from __future__ import annotations

import numpy as np
from scipy.ndimage import map_coordinates

from .spot import _basis


def geometric_mtf(offsets: np.ndarray, weights: np.ndarray, ok: np.ndarray, freqs: np.ndarray) -> np.ndarray:
    """Geometric MTF ``|Σ w e^{−2πi ν δ}| / Σ w`` of angular ray offsets δ (rad).

    ``offsets`` (..., R, 2), ``weights`` (R,) quadrature rule, ``ok`` (..., R),
    ``freqs`` (K,) cycles/rad. Returns (..., K, 2): axis −1 is the orientation
    (modulation along x, along y).

    The sums run in one Dr.Jit kernel, one lane per (bundle, frequency,
    orientation), with a symbolic loop over the R rays (the counts are data,
    so the kernel compiles once): ``|Σ w cos φ − i Σ w sin φ|`` with
    ``φ = 2π ν δ``. A full-resolution analysis evaluates ~10⁸ phases, which
    numpy's complex ``exp`` took seconds for.

    References
    ----------
    H. Huang and H. Hua, *Opt. Express* 27(18) (2019): the MTF of each InI
    sub-system (here its geometric limit, the Fourier transform of the ray
    spot).
    """
    import drjit as dr

    from ..backend import from_numpy, types

    offsets = np.asarray(offsets, dtype=np.float64)
    lead, R = offsets.shape[:-2], offsets.shape[-2]
    f = np.asarray(freqs, dtype=np.float64).ravel()
    K = len(f)
    w = np.where(ok, weights, 0.0).reshape(-1, R)
    wsum = np.sum(w, axis=-1)
    L = w.shape[0]
    if L == 0 or K == 0 or R == 0:
        return np.zeros(lead + (K, 2))
    T = types("float64")
    with dr.suspend_grad():
        off_d, w_d, f_d = from_numpy(T.Float, offsets.reshape(-1), w.reshape(-1), f)
        nK, nR = dr.opaque(T.UInt32, K), dr.opaque(T.UInt32, R)
        lane = dr.arange(T.UInt32, L * K * 2)
        axis = lane % 2
        k = (lane // 2) % nK
        first = (lane // (2 * nK)) * nR  # the bundle's first ray
        nu = dr.gather(T.Float, f_d, k) * (2.0 * np.pi)

        def body(r, re, im):
            j = first + r
            sn, cs = dr.sincos(nu * dr.gather(T.Float, off_d, 2 * j + axis))
            wj = dr.gather(T.Float, w_d, j)
            return r + 1, dr.fma(wj, cs, re), dr.fma(wj, sn, im)

        _, re, im = dr.while_loop(state=(dr.zeros(T.UInt32, L * K * 2), dr.zeros(T.Float, L * K * 2),
                                         dr.zeros(T.Float, L * K * 2)),
                                  cond=lambda r, re, im: r < nR, body=body, labels=("r", "re", "im"),
                                  label="lfsim_geometric_mtf")
        mod = dr.sqrt(dr.fma(re, re, im * im))
        dr.eval(mod)
    out = np.asarray(mod, dtype=np.float64).reshape(L, K, 2) / np.where(wsum > 0, wsum, 1.0)[:, None, None]
    return out.reshape(lead + (K, 2))


def reference_opd(pos: np.ndarray, dirs: np.ndarray, opl: np.ndarray, ok: np.ndarray,
                  r_center: np.ndarray, diopters) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Optical path difference to the reference sphere about the CDP image point.

    The eye is focused on the CDP at ``D`` diopters (z_CDP = 1000/D in front of
    the viewing window), so the ideal wave leaving the window diverges from the
    point ``Q = −z_CDP·(r̄, 1)`` seen in direction ``r̄`` (the spot centroid). Each
    ray is carried from its window point ``h`` along its direction to the
    sphere about Q through the bundle's centre ``X0`` (the stable root of
    ``|h + s·d − Q| = |X0 − Q|``, which tends to the plane-wave form at 0 D);
    OPD = OPL + s, piston removed.

    Shapes: ``pos`` (..., R, 2) on the window plane, ``dirs`` (..., R, 3),
    ``opl`` (..., R), ``ok`` (..., R), ``r_center`` (..., 2).
    Returns ``(opd_mm (..., R), pupil (..., R, 2), u (..., 3))``: OPD, the ray
    positions projected on the plane normal to the reference direction ``u``
    (axes as in :func:`angular_offsets`), and ``u``.
    """
    D = np.asarray(diopters, dtype=np.float64)[..., None] / 1000.0  # (..., 1)
    w8 = ok.astype(np.float64)
    n_ok = np.maximum(np.sum(w8, axis=-1, keepdims=True), 1.0)
    X0 = np.sum(pos * w8[..., None], axis=-2) / n_ok  # (..., 2)
    a = np.concatenate([X0 * D + r_center, np.ones(X0.shape[:-1] + (1,))], axis=-1)
    alen = np.linalg.norm(a, axis=-1, keepdims=True)
    u = a / alen
    c = D / alen  # 1/|X0 − Q|, (..., 1)
    wv = np.concatenate([pos - X0[..., None, :], np.zeros(pos.shape[:-1] + (1,))], axis=-1)
    dw = np.sum(dirs * wv, axis=-1)
    ud = np.einsum("...rk,...k->...r", dirs, u)
    uw = np.einsum("...rk,...k->...r", wv, u)
    ww = np.sum(wv * wv, axis=-1)
    bq = c * dw + ud
    cq = c * ww + 2.0 * uw
    s = -cq / (bq + np.sqrt(np.maximum(bq * bq - c * cq, 0.0)))
    opd = opl + s
    opd = opd - np.sum(opd * w8, axis=-1, keepdims=True) / n_ok
    opd = np.where(ok, opd, 0.0)
    _, e1, e2 = _basis(u[..., :2] / u[..., 2:3])
    pupil = np.stack([np.einsum("...rk,...k->...r", wv, e1), np.einsum("...rk,...k->...r", wv, e2)], axis=-1)
    return opd, pupil, u


def affine_fit(rho: np.ndarray, pupil: np.ndarray, ok: np.ndarray) -> np.ndarray:
    """Least-squares affine maps ``pupil ≈ A·ρ + b`` per bundle: A (L, 2, 2).

    ``rho`` (R, 2), ``pupil`` (L, R, 2), ``ok`` (L, R). Fully traced bundles
    share one pseudo-inverse; vignetted ones are solved on their own rays.
    """
    X = np.column_stack([rho, np.ones(len(rho))])
    A = np.tile(np.eye(2), (len(pupil), 1, 1))
    full = np.all(ok, axis=-1)
    if np.any(full):
        coef = np.einsum("kr,lrc->lkc", np.linalg.pinv(X), pupil[full])  # (L, 3, 2)
        A[full] = np.swapaxes(coef[:, :2, :], 1, 2)
    for j in np.flatnonzero(~full):
        sel = ok[j]
        if sel.sum() >= 3 and np.linalg.matrix_rank(X[sel]) == 3:
            coef, *_ = np.linalg.lstsq(X[sel], pupil[j][sel], rcond=None)
            A[j] = coef[:2].T
        else:  # the rays left lie on one line of the stop: no 2-D map (singular)
            A[j] = 0.0
    return A


def _flat_bundles(rho, pupil, opd_mm, ok):
    """``(n, lead, L, pupil (L, n², 2), opd (L, n²), ok (L, n²))``: the bundles of an OTF call
    flattened to one axis over the stop's n × n grid."""
    n = int(round(np.sqrt(len(rho))))
    lead = opd_mm.shape[:-1]
    L = int(np.prod(lead)) if lead else 1
    return n, lead, L, pupil.reshape(L, n * n, 2), opd_mm.reshape(L, n * n), ok.reshape(L, n * n)


def diffraction_mtf(rho: np.ndarray, pupil: np.ndarray, opd_mm: np.ndarray, ok: np.ndarray,
                    wavelength_nm: float, freqs: np.ndarray, chunk: int = 256) -> np.ndarray:
    """Diffraction MTF from the optical path across the lenslet's square stop: the modulus of
    :func:`diffraction_otf` (which see)."""
    return np.abs(diffraction_otf(rho, pupil, opd_mm, ok, wavelength_nm, freqs, chunk))


def diffraction_otf(rho: np.ndarray, pupil: np.ndarray, opd_mm: np.ndarray, ok: np.ndarray,
                    wavelength_nm: float, freqs: np.ndarray, chunk: int = 256) -> np.ndarray:
    """Diffraction OTF (complex) from the optical path across the lenslet's square stop.

    ``rho`` (n², 2) is the :func:`~lfsim.metrics.pupil.mtf_grid` of the stop;
    ``pupil`` (..., n², 2) the rays' positions projected normal to the beam
    (mm), ``opd_mm`` (..., n²) and ``ok`` (..., n²). The pupil function
    ``P = ok·exp(2πi·OPD/λ)`` on the stop grid is autocorrelated by FFT (zero
    padded to 2n); the map from stop coordinates to the projected pupil is
    taken as the least-squares affine fit of the traced positions (pupil
    distortion beyond affine is neglected, as lens-design programs' FFT MTF
    does), so a visual frequency ν (cycles/rad) along axis a is the shift
    ``Δρ = A⁻¹·λν·e_a`` of the autocorrelation, read by bilinear interpolation.
    Returns (..., K, 2) complex, like :func:`geometric_mtf` (its modulus is the
    MTF). A diffraction-limited square pupil of width w gives ``1 − ν λ / w``
    exactly; a tilt of the wavefront that moves the image by an angle δ along
    the axis multiplies it by ``exp(−2πi ν δ)``, so OTFs of several wavelengths,
    each with its path referred to the same image point, add to the
    polychromatic OTF (lateral colour lowers its modulus).

    References
    ----------
    H. Huang and H. Hua, *Opt. Express* 27(18) (2019): the MTF of each
    sub-system and its contrast at the display's Nyquist frequency, the design
    method's image-quality targets. J. W. Goodman, *Introduction to Fourier
    Optics* (the OTF as the normalized autocorrelation of the pupil function).
    """
    n, lead, L, pup, opd, okf = _flat_bundles(rho, pupil, opd_mm, ok)
    lam = wavelength_nm * 1e-6
    freqs = np.asarray(freqs, dtype=np.float64)
    out = np.zeros((L, len(freqs), 2), dtype=np.complex128)
    A_all = affine_fit(rho, pup, okf)
    for a0 in range(0, L, chunk):
        a1 = min(L, a0 + chunk)
        okc = okf[a0:a1]
        P = np.where(okc, np.exp(2j * np.pi * opd[a0:a1] / lam), 0.0).reshape(-1, n, n)
        F = np.fft.fft2(P, s=(2 * n, 2 * n))
        ac = np.fft.ifft2(np.abs(F) ** 2)  # autocorrelation, zero shift at [0, 0]
        norm = np.sum(okc, axis=-1).astype(np.float64)
        ac = np.fft.fftshift(ac, axes=(-2, -1)) / np.where(norm > 0, norm, 1.0)[:, None, None]
        for j in range(a1 - a0):
            # Fewer than 3 rays, or rays on one line (an aperture's edge leaves a sliver of
            # the pupil): the affine map is singular; such a beam is left at MTF 0.
            if okc[j].sum() < 3 or not np.linalg.cond(A_all[a0 + j]) < 1e12:
                continue
            Ainv = np.linalg.inv(A_all[a0 + j])
            for ax in range(2):
                shift = lam * freqs[:, None] * np.eye(2)[ax][None, :]  # (K, 2) mm
                drho = shift @ Ainv.T  # (K, 2) in ρ units
                cells = drho * (n / 2.0)  # grid cells (x, y)
                coords = np.array([n + cells[:, 1], n + cells[:, 0]])
                re = map_coordinates(ac[j].real, coords, order=1, mode="constant", cval=0.0)
                im = map_coordinates(ac[j].imag, coords, order=1, mode="constant", cval=0.0)
                out[a0 + j, :, ax] = re + 1j * im
    return out.reshape(lead + (len(freqs), 2))


def diffraction_otf_at(rho: np.ndarray, pupil: np.ndarray, opd_mm: np.ndarray, ok: np.ndarray,
                       wavelength_nm: float, freq: float, chunk: int = 256) -> np.ndarray:
    """:func:`diffraction_otf` at one frequency ``freq`` (cycles/rad), without the FFT: (..., 2)
    complex, the two orientations.

    :func:`diffraction_otf` reads the pupil function's autocorrelation by bilinear
    interpolation between whole grid cells of shift. Here the four whole-cell shifts around each
    orientation's shift are summed directly, ``Σ P(ρ + s)·P*(ρ)`` (zero outside the stop), and
    interpolated with the same weights, zero where the shift lies beyond the padded FFT's range
    as there: the same OTF to rounding, in a few array operations for every bundle at once (a
    through-focus sweep or a contrast search evaluates only the Nyquist frequency).
    """
    n, lead, L, pup, opd, okf = _flat_bundles(rho, pupil, opd_mm, ok)
    lam = wavelength_nm * 1e-6
    out = np.zeros((L, 2), dtype=np.complex128)
    A_all = affine_fit(rho, pup, okf)
    good = okf.sum(axis=-1) >= 3
    good[good] = np.linalg.cond(A_all[good]) < 1e12  # as diffraction_otf: a singular map leaves 0
    idx = np.flatnonzero(good)
    ar = np.arange(n)
    for a0 in range(0, len(idx), chunk):
        sel = idx[a0:a0 + chunk]
        V = len(sel)
        P = np.where(okf[sel], np.exp(2j * np.pi * opd[sel] / lam), 0.0).reshape(V, n, n)
        norm = np.sum(okf[sel], axis=-1).astype(np.float64)
        Pp = np.zeros((V, 3 * n, 3 * n), dtype=np.complex128)
        Pp[:, n:2 * n, n:2 * n] = P
        conjP = np.conj(P)
        Ainv = np.linalg.inv(A_all[sel])
        for ax in range(2):
            cells = (lam * freq) * Ainv[:, :, ax] * (n / 2.0)  # (V, 2): x, y in grid cells
            cy, cx = n + cells[:, 1], n + cells[:, 0]  # coordinates in the 2n × 2n autocorrelation
            inside = (cy >= 0) & (cy <= 2 * n - 1) & (cx >= 0) & (cx <= 2 * n - 1)
            r0, c0 = np.floor(cy), np.floor(cx)
            fy, fx = cy - r0, cx - c0
            val = np.zeros(V, dtype=np.complex128)
            for dy, dx, wgt in ((0, 0, (1 - fy) * (1 - fx)), (0, 1, (1 - fy) * fx),
                                (1, 0, fy * (1 - fx)), (1, 1, fy * fx)):
                sy = np.clip(r0 + dy - n, -n, n).astype(np.int64)  # whole-cell shift; |s| = n: no overlap
                sx = np.clip(c0 + dx - n, -n, n).astype(np.int64)
                rows = n + sy[:, None, None] + ar[None, :, None]
                cols = n + sx[:, None, None] + ar[None, None, :]
                shifted = Pp[np.arange(V)[:, None, None], rows, cols]
                val += wgt * np.sum(shifted * conjP, axis=(1, 2))
            out[sel, ax] = np.where(inside, val / np.where(norm > 0, norm, 1.0), 0.0)
    return out.reshape(lead + (2,))


def _legendre_terms(degree: int):
    return [(i, j) for t in range(1, degree + 1) for i in range(t + 1) for j in (t - i,)]


def wavefront_from_slopes(rho: np.ndarray, pupil: np.ndarray, offsets: np.ndarray, ok: np.ndarray,
                          degree: int = 10) -> np.ndarray:
    """Wavefront (mm) whose gradient is the rays' angular aberration (Malus–Dupin).

    Every ray is normal to the wavefront, so across the projected pupil ``p``
    the wavefront's slope equals the ray's angular offset from the reference
    direction: ``∇_p W = δ``. With the affine stop → pupil map ``p = Aρ + b``
    (least squares over the rays) this is ``∇_ρ W = Aᵀδ``, fitted in least
    squares by Legendre products ``P_i(ρx)·P_j(ρy)``, ``1 ≤ i + j ≤ degree``.
    On a fully traced grid the local Jacobian ``∂p/∂ρ`` (pupil distortion
    included) replaces A, by second-order finite differences along the grid.
    This gives the optical path of designs with ideal (paraxial) elements,
    whose ray mapping is perfect for every conjugate but cannot carry one
    optical-path term that is right for all of them; for real surfaces it
    agrees with the traced OPL (see the tests).

    Shapes: ``rho`` (R, 2), ``pupil`` (..., R, 2) mm, ``offsets`` (..., R, 2)
    rad, ``ok`` (..., R). Returns (..., R) with piston removed, 0 where not ok.
    """
    from numpy.polynomial import legendre as L

    terms = _legendre_terms(degree)
    Vx = L.legvander(rho[:, 0], degree)
    Vy = L.legvander(rho[:, 1], degree)
    dVx = np.stack([L.legval(rho[:, 0], L.legder(np.eye(degree + 1)[i])) for i in range(degree + 1)], axis=1)
    dVy = np.stack([L.legval(rho[:, 1], L.legder(np.eye(degree + 1)[i])) for i in range(degree + 1)], axis=1)
    val = np.stack([Vx[:, i] * Vy[:, j] for i, j in terms], axis=1)
    gx = np.stack([dVx[:, i] * Vy[:, j] for i, j in terms], axis=1)
    gy = np.stack([Vx[:, i] * dVy[:, j] for i, j in terms], axis=1)
    lead = ok.shape[:-1]
    Lc = int(np.prod(lead)) if lead else 1
    pup = pupil.reshape(Lc, -1, 2)
    off = offsets.reshape(Lc, -1, 2)
    okf = ok.reshape(Lc, -1)
    A = affine_fit(rho, pup, okf)
    J = np.broadcast_to(A[:, None], (Lc, len(rho), 2, 2)).copy()  # ∂p/∂ρ per ray
    n = int(round(np.sqrt(len(rho))))
    full = np.all(okf, axis=-1)
    if n * n == len(rho) and n >= 3 and np.any(full):
        # Fully traced grids: the local Jacobian (pupil distortion included), by
        # second-order differences along the grid (ρ spacing 2/n).
        grid = pup[full].reshape(-1, n, n, 2)
        dx = np.gradient(grid, 2.0 / n, axis=2, edge_order=2)
        dy = np.gradient(grid, 2.0 / n, axis=1, edge_order=2)
        J[full] = np.stack([dx, dy], axis=-1).reshape(-1, n * n, 2, 2)
    g = np.einsum("lra,lrab->lrb", off, J)  # Jᵀδ per ray: dW/dρ
    M = np.concatenate([gx, gy])
    W = np.zeros(okf.shape)
    if np.any(full):
        a = np.einsum("tr,lr->lt", np.linalg.pinv(M), np.concatenate([g[full, :, 0], g[full, :, 1]], axis=1))
        W[full] = a @ val.T
    for j in np.flatnonzero(~full):
        sel = okf[j]
        if sel.sum() < len(terms) // 2 + 3:
            continue
        a, *_ = np.linalg.lstsq(np.concatenate([gx[sel], gy[sel]]),
                                np.concatenate([g[j, sel, 0], g[j, sel, 1]]), rcond=None)
        W[j] = val @ a
    W = W - (np.sum(W * okf, axis=-1, keepdims=True) / np.maximum(np.sum(okf, axis=-1, keepdims=True), 1))
    W = np.where(okf, W, 0.0)
    return W.reshape(ok.shape)
