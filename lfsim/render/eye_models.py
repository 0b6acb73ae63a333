"""Schematic eye models as lfsim optical systems, and the accommodation solve.

The Arizona eye (Schwiegerling, *Field Guide to Visual and Ophthalmic
Optics*, SPIE 2004; table in ``notes/eye-models.md``) is built as an
:class:`lfsim.optics.prescription.System` with (nd, Vd) model media
(:func:`lfsim.optics.materials.abbe`), so it is traced by the same
:class:`~lfsim.optics.tracer.SequentialTracer` and surface code as every
other lfsim design.

Frames (mm):

* **eye frame** (the sensor's local frame): origin at the centre of the
  paraxial entrance pupil of the *unaccommodated* eye (A = 0) at the chosen
  wavelength, the eye looks along −z, +x is the viewer's right, +y up. The
  cornea vertex is at ``z = −e0`` (``e0`` ≈ 3.05 mm at 550 nm) for every A:
  accommodation moves the lens, not the cornea.
* **forward frame** of :func:`arizona_system`: light travels +z into the
  eye, origin at the cornea vertex; ``x, y`` as in the eye frame, so
  ``z_forward = z_eye + e0``.
* **reverse frame** of :func:`arizona_reverse_system` (retina → outside):
  origin at the posterior lens vertex, +z toward the cornea, rotated 180°
  about y: ``(x, y, z)_reverse = (−x, y, z_lp − z)_eye`` with ``z_lp`` the
  eye-frame z of the posterior lens vertex.

Pupil convention: ``pupil_diameter`` everywhere in lfsim's eye code is the
diameter of the *entrance pupil* (the pupil one measures and the disk the
ideal eye samples), located at the eye-frame origin. The iris (the stop, a
circular aperture on the anterior lens surface) gets the diameter whose
paraxial image through the cornea has that size (iris ≈ 0.89 × entrance
pupil), so an ideal and an Arizona eye with the same ``pupil_diameter``
accept the same beam.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from ..backend import to_numpy
from ..optics.first_order import paraxial_matrices
from ..optics.materials import AIR, abbe
from ..optics.prescription import Aperture, Surface, System

#: Axial length of the Arizona eye (cornea vertex → retina vertex, mm), any A.
ARIZONA_AXIAL_LENGTH = 24.0
#: Published total power of the unaccommodated Arizona eye (D) at 589 nm
#: (Schwiegerling 2004, Field Guide to Visual and Ophthalmic Optics).
ARIZONA_POWER_D = 60.0
#: Accommodation range over which the Arizona parametrization is used (D).
A_RANGE = (-3.0, 15.0)


@dataclass(frozen=True)
class EyeSurface:
    """One row of a schematic-eye table (forward direction, mm)."""

    name: str
    radius: float
    conic: float
    thickness: float  # to the next surface
    nd: float  # medium after the surface
    vd: float


def arizona_table(accommodation: float) -> list[EyeSurface]:
    """The Arizona eye's surfaces at accommodation ``A`` (diopters), forward order.

    Cornea, aqueous and vitreous are fixed; the lens front radius, conics,
    thicknesses and lens index follow Schwiegerling's linear/quadratic A
    dependence. The last row is the retina (its nd, vd are the vitreous').
    """
    A = float(accommodation)
    if not (math.isfinite(A) and A_RANGE[0] <= A <= A_RANGE[1]):
        raise ValueError(
            f"accommodation={accommodation!r} is outside the Arizona eye's range "
            f"[{A_RANGE[0]}, {A_RANGE[1]}] D")
    n_lens = 1.42 + 0.00256 * A - 0.00022 * A * A
    return [
        EyeSurface("cornea_anterior", 7.8, -0.25, 0.55, 1.377, 57.1),
        EyeSurface("cornea_posterior", 6.5, -0.25, 2.97 - 0.04 * A, 1.337, 61.3),
        EyeSurface("lens_anterior", 12.0 - 0.4 * A, -7.518749 + 1.285720 * A,
                   3.767 + 0.04 * A, n_lens, 51.9),
        EyeSurface("lens_posterior", -5.224557 + 0.2 * A, -1.353971 - 0.431762 * A,
                   16.713, 1.336, 61.1),
        EyeSurface("retina", -13.4, 0.0, 0.0, 1.336, 61.1),
    ]


def _curv(radius: float) -> float:
    return 0.0 if math.isinf(radius) else 1.0 / radius


def arizona_system(accommodation: float = 0.0, iris_radius: float | None = None,
                   epd: float = 3.0) -> System:
    """Forward Arizona eye (object → cornea → … → retina), forward frame.

    The stop is the anterior lens surface; ``iris_radius`` (mm) makes it a
    circular aperture (None: unclipped). ``epd`` only fills the system's
    aperture setting for first-order reports.
    """
    rows = arizona_table(accommodation)
    surfaces = []
    for r in rows:
        s = Surface(name=r.name, curvature=_curv(r.radius), conic=r.conic,
                    thickness=r.thickness, material=abbe(r.nd, r.vd))
        if r.name == "lens_anterior":
            s.stop = True
            if iris_radius is not None:
                s.aperture = Aperture("circular", radius=float(iris_radius))
        surfaces.append(s)
    return System(surfaces=surfaces, aperture_type="epd", aperture_value=float(epd),
                  name=f"Arizona eye A={accommodation:g} D")


def arizona_reverse_system(accommodation: float, iris_radius: float | None) -> System:
    """The Arizona eye traversed backwards: vitreous → lens → aqueous → cornea → air.

    Reverse frame (see the module docstring): first surface = posterior lens
    vertex at the origin, +z toward the cornea. Radii change sign, conics do
    not; each surface refracts into the medium that precedes it in the
    forward table. The last surface (anterior cornea) refracts into air.
    """
    rows = arizona_table(accommodation)
    vitreous = abbe(rows[3].nd, rows[3].vd)
    order = [3, 2, 1, 0]  # lens posterior, lens anterior, cornea posterior, cornea anterior
    surfaces = []
    for j, i in enumerate(order):
        r = rows[i]
        after = rows[i - 1] if i > 0 else None
        material = abbe(after.nd, after.vd) if after is not None else AIR
        thickness = rows[order[j + 1]].thickness if j + 1 < len(order) else 0.0
        s = Surface(name=r.name, curvature=-_curv(r.radius), conic=r.conic,
                    thickness=thickness, material=material)
        if r.name == "lens_anterior":
            s.stop = True
            if iris_radius is not None:
                s.aperture = Aperture("circular", radius=float(iris_radius))
        surfaces.append(s)
    return System(surfaces=surfaces, object_material=vitreous, object_distance=rows[3].thickness,
                  name=f"Arizona eye reversed A={accommodation:g} D")


@dataclass(frozen=True)
class EyeFirstOrder:
    """Paraxial data of one Arizona eye state (mm, D)."""

    accommodation: float
    wavelength_nm: float
    power_d: float  # total power (D)
    efl: float  # 1/φ (mm)
    ep_position: float  # entrance pupil, from the cornea vertex (+ = inside)
    ep_magnification: float  # entrance-pupil diameter / iris diameter
    xp_position: float  # exit pupil, from the retina vertex (− = in front of it)
    xp_magnification: float  # exit-pupil diameter / iris diameter
    far_point: float  # paraxial conjugate of the retina vertex, from the cornea vertex (− = in front)
    z_lens_posterior: float  # posterior lens vertex, from the cornea vertex
    n_vitreous: float


@lru_cache(maxsize=256)
def arizona_first_order(accommodation: float, wavelength_nm: float = 550.0) -> EyeFirstOrder:
    """Paraxial (y-nu) data of the Arizona eye at ``A`` and ``wavelength_nm``."""
    system = arizona_system(accommodation)
    lam = float(wavelength_nm)
    Mf, Mt, n_o, n_i = paraxial_matrices(system, lam)
    A_, B_ = Mf[0]
    a, b, c, d = Mt.ravel()
    phi = -c
    # Entrance pupil: the stop seen through the cornea. A ray (y0, ν0) at the
    # first vertex plane reaches the stop at y = A_ y0 + B_ ν0; the axial
    # point whose rays cross the stop centre is at z = n B_/A_ (from vertex),
    # and the pupil magnification is 1/A_.
    ep_pos = n_o * B_ / A_
    ep_mag = 1.0 / A_
    Mb = Mt @ np.linalg.inv(Mf)
    xp_pos = -n_i * Mb[0, 1] / Mb[1, 1]
    xp_mag = 1.0 / abs(Mb[1, 1])
    # Far point: object whose image is on the retina vertex: y1 = a y0 + b ν0 = 0
    # for a ray from the axial object point at z = −s (ν0 = n y0 / s) → s = −n b / a.
    far = n_o * b / a if a != 0 else -math.inf
    rows = arizona_table(accommodation)
    z_lp = rows[0].thickness + rows[1].thickness + rows[2].thickness
    return EyeFirstOrder(accommodation, lam, 1000.0 * phi, 1.0 / phi, ep_pos, ep_mag, xp_pos,
                         xp_mag, far, z_lp, float(n_i))


def iris_radius(pupil_diameter: float, accommodation: float, wavelength_nm: float = 550.0) -> float:
    """Iris (stop) radius whose paraxial entrance-pupil image has ``pupil_diameter``."""
    fo = arizona_first_order(float(accommodation), float(wavelength_nm))
    return 0.5 * float(pupil_diameter) / fo.ep_magnification


def eye_origin_depth(wavelength_nm: float = 550.0) -> float:
    """``e0``: depth of the eye-frame origin (A = 0 entrance pupil) behind the cornea vertex."""
    return arizona_first_order(0.0, float(wavelength_nm)).ep_position


# ------------------------------------------------------------------ tracing
@lru_cache(maxsize=8)
def _tracers(precision: str):
    """Forward and reverse tracers (structure is the same for every A)."""
    from ..optics.tracer import SequentialTracer

    fwd = SequentialTracer(arizona_system(0.0), precision)
    rev = SequentialTracer(arizona_reverse_system(0.0, None), precision)
    return fwd, rev


def _params(tracer, system: System, wavelength_nm: float):
    """Parameter block of ``system`` for a tracer built on a same-structure system."""
    return tracer.params(values=np.asarray(system.parameter_values(float(wavelength_nm))))


def _trace(tracer, P, o, d, first=0, clip=False):
    """numpy rays → numpy (p, d, status) at the last surface (no gradients)."""
    import drjit as dr

    with dr.suspend_grad():
        out = tracer.trace(P, tracer.rays(o, d), first=first, clip=clip)
        p, dd, status = to_numpy(out.p, out.d, out.status)  # one kernel
    return p.astype(np.float64), dd.astype(np.float64), status


@dataclass(frozen=True)
class ChiefRayTable:
    """Real chief rays of the Arizona eye vs field angle (forward frame, mm, rad).

    For an object direction at angle ``alpha`` from the axis (azimuth unit
    vector ``u`` in the eye's x, y), the chief ray (through the iris centre)
    lands on the retina at ``(−r·u, z)`` and its vitreous segment, extended,
    crosses the paraxial exit-pupil plane ``z = z_xp`` at ``−h_xp·u``.
    """

    alpha: np.ndarray  # uniform grid, 0..alpha_max
    r: np.ndarray
    z: np.ndarray
    h_xp: np.ndarray
    z_xp: float


def chief_ray_table(accommodation: float, wavelength_nm: float, alpha_max: float,
                    n: int = 257) -> ChiefRayTable:
    """Trace chief rays (float64, lfsim tracer) and tabulate them on a uniform α grid.

    Chief rays are parametrized by their direction inside the lens at the
    iris centre (the anterior lens vertex): the part toward the retina is
    traced through the forward system, the part toward the object through
    the reverse system, so no ray aiming is needed. ``alpha_max`` (rad) is
    the largest field needed; ValueError if the eye cannot reach it.
    """
    A, lam = float(accommodation), float(wavelength_nm)
    fwd, rev = _tracers("float64")
    rows = arizona_table(A)
    z_stop = rows[0].thickness + rows[1].thickness  # forward frame
    t_lens = rows[2].thickness
    fo = arizona_first_order(A, lam)
    z_xp = ARIZONA_AXIAL_LENGTH + fo.xp_position
    P_f = _params(fwd, arizona_system(A), lam)
    P_r = _params(rev, arizona_reverse_system(A, None), lam)
    s = np.linspace(0.0, 0.95, 2001)  # sine of the slope inside the lens
    c = np.sqrt(1.0 - s * s)
    zero = np.zeros_like(s)
    o_f = np.stack([zero, zero, np.full_like(s, z_stop)], axis=1)
    p_ret, d_vit, st_f = _trace(fwd, P_f, o_f, np.stack([s, zero, c], axis=1), first=3)
    o_r = np.stack([zero, zero, np.full_like(s, t_lens)], axis=1)
    _, d_air, st_r = _trace(rev, P_r, o_r, np.stack([s, zero, c], axis=1), first=1)
    # Object-space direction in the eye frame: (−dx, dy, −dz) of the reverse ray.
    alpha = np.arctan2(d_air[:, 0], d_air[:, 2])
    ok = (st_f == 0) & (st_r == 0) & (d_air[:, 2] > 0)
    ok &= np.concatenate([[True], np.diff(alpha) > 0])  # keep the monotone branch
    ok = np.logical_and.accumulate(ok)
    if not ok[1] or alpha[ok][-1] < alpha_max:
        reach = math.degrees(alpha[ok][-1]) if ok.any() else 0.0
        raise ValueError(
            f"field angle {math.degrees(alpha_max):.1f} deg is beyond the Arizona eye's "
            f"traceable field ({reach:.1f} deg)")
    a = alpha[ok]
    grid = np.linspace(0.0, alpha_max, n)
    r = np.interp(grid, a, p_ret[ok, 0])
    z = np.interp(grid, a, p_ret[ok, 2])
    h = p_ret[ok, 0] + (z_xp - p_ret[ok, 2]) * d_vit[ok, 0] / d_vit[ok, 2]
    h_xp = np.interp(grid, a, h)
    return ChiefRayTable(grid, r, z, h_xp, z_xp)


@dataclass(frozen=True)
class PupilTable:
    """Where rays from a retinal point pass the real iris, on the exit-pupil plane.

    For the chief-ray table's fields: the real pupil (rays that pass the
    iris) seen from the retinal point, on the paraxial exit-pupil plane, lies
    inside the disk of centre ``chief crossing − offset·u·ρ`` and radius
    ``k·ρ`` (ρ = paraxial exit-pupil radius, u the field's azimuth), found by
    bisecting the iris edge along 48 directions and padding by 1 %.
    """

    offset: np.ndarray  # centre shift along the landing direction, in units of ρ
    k: np.ndarray  # disk radius / ρ (≥ 1 covers the real pupil)
    rho: float


def pupil_table(table: ChiefRayTable, accommodation: float, wavelength_nm: float,
                iris: float, n_dir: int = 48, n_fields: int = 17) -> PupilTable:
    """Real exit-pupil disks per field of ``table`` (see :class:`PupilTable`)."""
    import drjit as dr

    A, lam = float(accommodation), float(wavelength_nm)
    fo = arizona_first_order(A, lam)
    rho = iris * fo.xp_magnification
    _, rev = _tracers("float64")
    P = _params(rev, arizona_reverse_system(A, iris), lam)
    z_lp = fo.z_lens_posterior
    idx = np.unique(np.linspace(0, len(table.alpha) - 1, n_fields).round().astype(int))
    phi = 2.0 * np.pi * np.arange(n_dir) / n_dir
    F = len(idx)
    # Reverse frame: x_S = −x_F. Landing (F) at +r along x → S at −r; chief crossing likewise.
    Q = np.stack([-table.r[idx], np.zeros(F), z_lp - table.z[idx]], axis=1)
    C = np.stack([-table.h_xp[idx], np.zeros(F), np.full(F, z_lp - table.z_xp)], axis=1)
    lo = np.full((F, n_dir), 0.5)
    hi = np.full((F, n_dir), 1.6)
    cph, sph = np.cos(phi)[None, :], np.sin(phi)[None, :]
    for _ in range(22):
        mid = 0.5 * (lo + hi)
        E = np.stack([C[:, None, 0] + rho * mid * cph, C[:, None, 1] + rho * mid * sph,
                      np.broadcast_to(C[:, None, 2], mid.shape)], axis=-1).reshape(-1, 3)
        o = np.repeat(Q, n_dir, axis=0)
        # Trace only to the iris (the stop is the reverse system's surface 1,
        # untilted and on axis, so its local x, y are the global ones).
        with dr.suspend_grad():
            out = rev.trace(P, rev.rays(o, E - o), last=1, clip=False)
            px, py, status = to_numpy(out.p.x, out.p.y, out.status)
        hit = np.hypot(px, py)
        ok = ((status == 0) & (hit <= iris)).reshape(F, n_dir)
        lo = np.where(ok, mid, lo)
        hi = np.where(ok, hi, mid)
    # Boundary points relative to the chief crossing (units of ρ), x along −u in S... use x.
    bx, by = hi * cph, hi * sph
    cx = 0.5 * (bx.max(axis=1) + bx.min(axis=1))
    k = np.sqrt((bx - cx[:, None]) ** 2 + by ** 2).max(axis=1) * 1.01
    # cx is along +x_S, i.e. along −x_F = +u for the table's field (object at −x): store as offset
    # along the azimuth u of the object direction in the eye frame.
    offset = np.interp(np.arange(len(table.alpha)), idx, cx)
    k_full = np.interp(np.arange(len(table.alpha)), idx, k)
    # Cover the interpolation between bisected fields: take the local maximum.
    k_full = np.maximum.reduce([k_full, np.r_[k_full[:1], k_full[:-1]], np.r_[k_full[1:], k_full[-1:]]])
    return PupilTable(offset, np.maximum(k_full, 1.0), rho)


# ------------------------------------------------------------ accommodation
def _check_distance(distance_mm) -> float:
    d = float(distance_mm)
    if not (d > 0.0):  # also rejects NaN
        raise ValueError(f"distance_mm={distance_mm!r}: must be > 0 mm (inf = 0 D allowed)")
    return d


def _check_pupil(pupil_diameter_mm) -> float:
    p = float(pupil_diameter_mm)
    if not (math.isfinite(p) and p > 0.0):
        raise ValueError(f"pupil_diameter_mm={pupil_diameter_mm!r}: must be a finite number > 0 mm")
    return p


def paraxial_accommodation(distance_mm: float, wavelength_nm: float = 550.0) -> float:
    """A (D) whose *paraxial* far point is ``distance_mm`` from the eye-frame origin.

    Solved with ``scipy.optimize.brentq`` on the y-nu trace condition that
    the axial object point images onto the retina vertex.
    """
    from scipy.optimize import brentq

    d = _check_distance(distance_mm)
    lam = float(wavelength_nm)
    s = d - eye_origin_depth(lam)  # object distance in front of the cornea vertex

    def f(A):
        _, M, n_o, _ = paraxial_matrices(arizona_system(A), lam)
        a, b = M[0]
        return a if math.isinf(s) else a + n_o * b / s

    return float(brentq(f, A_RANGE[0], A_RANGE[1], xtol=1e-10))


def refraction_diopters(wavelength_nm: float, accommodation: float = 0.0) -> float:
    """The Arizona eye's paraxial refractive state at ``wavelength_nm`` (D): the vergence at the
    cornea of the object point imaged on the retina vertex (−1/far point; 0 for an eye focused
    at infinity, negative when it focuses nearer). Its change with wavelength is the eye's
    longitudinal chromatic aberration (the chromatic eye of Thibos et al., *Appl. Opt.* 31,
    3594 (1992), reproduces it: ``tests/test_spectral.py``)."""
    fo = arizona_first_order(float(accommodation), float(wavelength_nm))
    return 0.0 if math.isinf(fo.far_point) else 1000.0 / fo.far_point


def _gauss_legendre_01(n: int):
    x, w = np.polynomial.legendre.leggauss(n)
    return 0.5 * (x + 1.0), 0.5 * w


def axial_rms_spot(accommodation: float, distance_mm: float, pupil_diameter_mm: float,
                   wavelength_nm: float = 550.0, n_rings: int = 24) -> float:
    """On-axis RMS retinal spot radius (mm) of the Arizona eye (lfsim float64 trace).

    The object point is on the axis at ``distance_mm`` from the eye-frame
    origin (inf: a collimated beam). The beam is the one the real iris
    passes: the marginal height on the origin plane is found by tracing a
    fan to the iris (radius from :func:`iris_radius`) and interpolating the
    edge. The pupil is integrated exactly in azimuth (rotational symmetry: a
    ray at height h lands at radius r(h)) and by Gauss–Legendre in h² (equal
    areas) with ``n_rings`` nodes; the centroid is the axis point, so
    RMS² = ∫ r(h)² d(h²) / h_max².
    """
    A, lam = float(accommodation), float(wavelength_nm)
    d = _check_distance(distance_mm)
    pupil = _check_pupil(pupil_diameter_mm)
    e0 = eye_origin_depth(lam)
    fwd, _ = _tracers("float64")
    P = _params(fwd, arizona_system(A), lam)
    iris = iris_radius(pupil, A, lam)

    def rays(h):
        h = np.asarray(h, dtype=np.float64)
        z0 = np.zeros_like(h)
        if math.isinf(d):
            o = np.stack([h, z0, np.full_like(h, -1.0)], axis=1)
            return o, np.tile([0.0, 0.0, 1.0], (len(h), 1))
        obj = np.array([0.0, 0.0, e0 - d])
        target = np.stack([h, z0, np.full_like(h, e0)], axis=1)
        return np.tile(obj, (len(h), 1)), target - obj

    import drjit as dr

    # Real marginal ray: the height on the origin plane that meets the iris edge.
    h = 0.5 * pupil * np.linspace(0.8, 1.2, 81)
    o, dd = rays(h)
    with dr.suspend_grad():
        out = fwd.trace(P, fwd.rays(o, dd), last=2, clip=False)
    x_iris = np.asarray(out.p[0], dtype=np.float64)
    if not (np.all(np.diff(x_iris) > 0) and x_iris[0] < iris < x_iris[-1]):
        raise ValueError(f"distance_mm={distance_mm!r}: cannot find the marginal ray of a "
                         f"{pupil} mm pupil in the Arizona eye (A={A:g} D)")
    h_max = float(np.interp(iris, x_iris, h))
    s, w = _gauss_legendre_01(n_rings)
    o, dd = rays(h_max * np.sqrt(s))
    p, _, st = _trace(fwd, P, o, dd)
    if np.any(st != 0):
        raise ValueError(f"accommodation={A!r}: rays of a {pupil} mm pupil fail in the Arizona eye")
    return float(np.sqrt(np.sum(w * p[:, 0] ** 2)))


@lru_cache(maxsize=512)
def solve_accommodation(distance_mm: float, pupil_diameter_mm: float, wavelength_nm: float = 550.0,
                        criterion: str = "rms", xatol: float = 1e-5, n_rings: int = 24) -> float:
    """Arizona-eye accommodation A (D) that focuses best at ``distance_mm``.

    Parameters
    ----------
    distance_mm : float
        Object distance from the eye-frame origin (the entrance pupil), mm;
        ``inf`` = 0 D vergence.
    pupil_diameter_mm : float
        Entrance-pupil diameter (mm).
    wavelength_nm : float
        Wavelength of the (nd, Vd) model media (default 550 nm).
    criterion : {"rms", "paraxial"}
        "rms": minimize the on-axis RMS retinal spot over the real pupil
        (:func:`axial_rms_spot`, traced with lfsim) with
        ``scipy.optimize.minimize_scalar`` (bounded, ±1.5 D around the
        paraxial answer). "paraxial": the paraxial far point is at the
        distance (:func:`paraxial_accommodation`).
    xatol : float
        Tolerance (D) of the bounded scalar minimization ("rms").
    n_rings : int
        Gauss–Legendre nodes in h² of :func:`axial_rms_spot` ("rms").
        Error against run time of both: ``benchmarks/accuracy_report.py``
        (docs/accuracy.md).

    Notes
    -----
    A is *not* 1000/distance. Two effects move it, both toward smaller A:
    at 550 nm the (nd, Vd) media make the eye ≈ 0.26 D stronger than at its
    design wavelength (587.6 nm, where the paraxial far point is at 1/A),
    which lowers the paraxial A by ≈ 0.2 D, and the eye's positive
    (under-corrected) spherical aberration puts the RMS-best focus in front
    of the paraxial focus. Measured with this function at
    550 nm, 3 mm pupil (A − 1000/d): 600 mm → 1.376 D (−0.29), 750 mm →
    1.020 D (−0.31), 1000 mm → 0.666 D (−0.33), 1400 mm → 0.363 D (−0.35),
    inf → −0.39 D; the shift grows with the pupil (1000 mm: 0.531 D at
    4 mm, 0.017 D at 6 mm). Near focus the spherical aberration changes
    sign (250 mm, 3 mm pupil: 3.94 D vs 4.00). A negative answer (a
    relaxed eye that is slightly myopic at 550 nm for far objects) is
    returned as is; the parametrization is used down to −3 D.
    """
    from scipy.optimize import minimize_scalar

    d = _check_distance(distance_mm)
    pupil = _check_pupil(pupil_diameter_mm)
    if criterion not in ("rms", "paraxial"):
        raise ValueError(f"criterion={criterion!r}: allowed 'rms', 'paraxial'")
    A0 = paraxial_accommodation(d, wavelength_nm)
    if criterion == "paraxial":
        return A0
    lo, hi = max(A_RANGE[0], A0 - 1.5), min(A_RANGE[1], A0 + 1.5)
    res = minimize_scalar(lambda A: axial_rms_spot(A, d, pupil, wavelength_nm, n_rings), bounds=(lo, hi),
                          method="bounded", options={"xatol": float(xatol)})
    return float(res.x)
