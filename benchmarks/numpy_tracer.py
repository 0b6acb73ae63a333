"""Vectorized NumPy (float64) sequential tracer: the baseline for the benchmarks.

An independent implementation of the surface, frame and interaction model
documented in :mod:`lfsim.optics.prescription` and :mod:`lfsim.optics.tracer`.
It shares only the plain-data classes (``System``, ``Surface``, materials)
with lfsim, none of its geometry or tracing code, so agreement between the two
is a real cross-check and its speed is a fair "what plain NumPy gives" figure.

Model (per surface, in the surface's local frame, vertex at the origin, +z
the local axis)::

    z(x, y) = c r² / (1 + sqrt(1 − (1 + k) c² r²))
            + Σ A_{2i} r^{2i}
            + Σ c_ij (x/R_n)^i (y/R_n)^j

* Frames: decenter (x, y), then R = Rx·Ry·Rz of ``tilt`` (degrees); the
  following surfaces continue from the frame before the tilt/decenter unless
  ``return_axis`` is false (coordinate breaks default to false); ``thickness``
  then moves along the current z. ``global_position`` places a surface in the
  global frame (tilts about the global axes, decenter applied in the tilted
  frame) and the chain continues from it. ``same_as`` reuses an earlier
  surface's frame and shape.
* Intersection: the base conic in closed form on the branch through the
  vertex, after moving the ray to the vertex plane,
  ``t = −C / (B + sign(B)·sqrt(B² − A C))``; aspheres and XY polynomials by
  Newton's method from the conic root (the vertex plane if the conic is
  missed), tolerance 1e-12 mm on the step, at most 16 steps, then one more
  step whose size (≤ 10·tol) decides convergence.
  The conic's domain is 1 − (1+k) c² r² > 0 (the rim of a hemisphere, with
  infinite slope, is outside); rays with |d_z| ≤ 1e-9 in the local frame are
  solved from where they are instead of from the vertex plane.
* Interactions: refraction (vector Snell's law, failing rays → TIR),
  reflection (mirror), total internal reflection against the surface's
  material (refraction possible → NO_TIR), "none" (dummy), "break"
  (coordinate break, not intersected), "paraxial" (ideal thin lens of power
  φ on a plane in one medium of index n: slopes map as
  tan θ' = tan θ − h·φ/n in x and y, and the path gains
  n·((2 g·h − φ|h|²)/(|g| + |g − φh|) − d·h) with g = d/|d_z|).
* Apertures: circular or rectangular in local (x, y), with decenter; edges
  have a relative slack of 1e-12 (a ray aimed exactly at a rim passes).
* Status codes follow ``lfsim.optics.tracer.Status`` (duplicated below so this
  module does not import the Dr.Jit tracer); the first failure is kept and a
  failed ray keeps its last valid position, direction and OPL.

Lenslet arrays are not supported (``NotImplementedError``).
"""

from __future__ import annotations

import math

import numpy as np

from lfsim.optics.prescription import Surface, System

# Status codes (same values as lfsim.optics.tracer.Status).
OK = 0
MISSED = 1
TIR = 2
VIGNETTED = 3
NOT_CONVERGED = 4
WRONG_LENSLET = 5
NO_TIR = 6

NEWTON_TOL = 1e-12
NEWTON_MAX_ITER = 16
#: Smallest |d_z| (local) for which the ray is first moved to the vertex plane.
DZ_MIN = 1e-9
#: Relative slack of aperture edges.
EDGE_TOL = 1e-12
INTERACTIONS = ("refract", "reflect", "tir", "none", "break", "paraxial")


# ----------------------------------------------------------------- frames
def _rotation(tilt_deg) -> np.ndarray:
    """Active rotation Rx(a)·Ry(b)·Rz(g), angles in degrees, right-handed."""
    a, b, g = (math.radians(v) for v in tilt_deg)
    ca, sa, cb, sb, cg, sg = math.cos(a), math.sin(a), math.cos(b), math.sin(b), math.cos(g), math.sin(g)
    rx = np.array([[1.0, 0.0, 0.0], [0.0, ca, -sa], [0.0, sa, ca]])
    ry = np.array([[cb, 0.0, sb], [0.0, 1.0, 0.0], [-sb, 0.0, cb]])
    rz = np.array([[cg, -sg, 0.0], [sg, cg, 0.0], [0.0, 0.0, 1.0]])
    return rx @ ry @ rz


def surface_frames(system: System) -> list[tuple[np.ndarray, np.ndarray]]:
    """(R, o) of every surface: local point x maps to global ``R @ x + o``."""
    r_cur = np.eye(3)
    o_cur = np.zeros(3)
    frames: list[tuple[np.ndarray, np.ndarray]] = []
    for s in system.surfaces:
        if s.same_as is not None:
            r_s, o_s = frames[s.same_as]
        else:
            rot = _rotation(s.tilt)
            shift = np.array([s.decenter[0], s.decenter[1], 0.0])
            if s.global_position is not None:
                r_s = rot
                o_s = np.asarray(s.global_position, dtype=np.float64) + rot @ shift
            else:
                r_s = r_cur @ rot
                o_s = o_cur + r_cur @ shift
        frames.append((r_s, o_s))
        if not s.return_axis or s.global_position is not None:
            r_cur, o_cur = r_s, o_s
        o_cur = o_cur + r_cur @ np.array([0.0, 0.0, s.thickness])
    return frames


# ----------------------------------------------------------------- shapes
class _Shape:
    """Sag model of one physical surface (float64 scalars)."""

    def __init__(self, s: Surface):
        self.c = float(s.curvature)
        self.k = float(s.conic)
        self.asphere = {int(o): float(v) for o, v in s.asphere.items()}
        self.xy = {(int(i), int(j)): float(v) for (i, j), v in s.xy.items()}
        self.rn = float(s.norm_radius)
        self.newton = bool(s.asphere) or bool(s.xy)

    def sag(self, x, y):
        """z, ∂z/∂x, ∂z/∂y and the base-conic domain mask at local (x, y)."""
        r2 = x * x + y * y
        c = self.c
        if c == 0.0:
            z = np.zeros_like(r2)
            g = np.zeros_like(r2)
            inside = np.ones(r2.shape, dtype=bool)
        else:
            arg = 1.0 - (1.0 + self.k) * c * c * r2
            inside = arg > 0.0
            root = np.sqrt(np.where(inside, arg, 1.0))
            z = c * r2 / (1.0 + root)
            g = c / root  # (1/r) dz/dr of the conic
        if self.asphere:
            # Σ A_{2i} r^{2i} and its (1/r) d/dr = Σ 2i A_{2i} r^{2i-2}, Horner in r².
            top = max(self.asphere) // 2
            poly = np.zeros_like(r2)
            dpoly = np.zeros_like(r2)
            for i in range(top, 0, -1):
                a = self.asphere.get(2 * i, 0.0)
                poly = poly * r2 + a
                dpoly = dpoly * r2 + 2.0 * i * a
            # poly = Σ_{i≥1} A_{2i} r^{2(i-1)} → times r²; dpoly = Σ 2i A_{2i} r^{2(i-1)}.
            z = z + poly * r2
            g = g + dpoly
        zx = x * g
        zy = y * g
        if self.xy:
            inv = 1.0 / self.rn
            u = x * inv
            v = y * inv
            imax = max(i for i, _ in self.xy)
            jmax = max(j for _, j in self.xy)
            upow = [np.ones_like(u), u]
            for _ in range(2, imax + 1):
                upow.append(upow[-1] * u)
            vpow = [np.ones_like(v), v]
            for _ in range(2, jmax + 1):
                vpow.append(vpow[-1] * v)
            for (i, j), cij in self.xy.items():
                z = z + cij * upow[i] * vpow[j]
                if i:
                    zx = zx + (cij * i * inv) * upow[i - 1] * vpow[j]
                if j:
                    zy = zy + (cij * j * inv) * upow[i] * vpow[j - 1]
        return z, zx, zy, inside


def _conic_hit(px, py, pz, dx, dy, dz, c, k):
    """Closed-form hit with the base conic on the vertex branch: (t, ok)."""
    if c == 0.0:  # plane z = 0
        ok = dz != 0.0
        return -pz / np.where(ok, dz, 1.0), ok
    dz_ok = np.abs(dz) > DZ_MIN
    t0 = np.where(dz_ok, -pz / np.where(dz_ok, dz, 1.0), 0.0)
    x = px + t0 * dx
    y = py + t0 * dy
    z = np.where(dz_ok, 0.0, pz)
    e = 1.0 + k
    a = c * (dx * dx + dy * dy + e * dz * dz)
    b = c * (x * dx + y * dy + e * z * dz) - dz
    cc = c * (x * x + y * y + e * z * z) - 2.0 * z
    disc = b * b - a * cc
    ok = disc >= 0.0
    den = b + np.copysign(np.sqrt(np.where(ok, disc, 0.0)), b)
    ok &= den != 0.0
    t1 = np.where(ok, -cc / np.where(ok, den, 1.0), 0.0)
    return t0 + t1, ok


def _newton(shape: _Shape, px, py, pz, dx, dy, dz, t_start):
    """Refine the hit with the full sag: (t, good, converged)."""
    t = t_start.copy()
    active = np.arange(t.size)
    for _ in range(NEWTON_MAX_ITER):
        if active.size == 0:
            break
        ta = t[active]
        ax, ay, az = dx[active], dy[active], dz[active]
        qx = px[active] + ta * ax
        qy = py[active] + ta * ay
        qz = pz[active] + ta * az
        z, zx, zy, inside = shape.sag(qx, qy)
        fp = az - zx * ax - zy * ay
        good = inside & (np.abs(fp) > 1e-12)
        step = np.where(good, (qz - z) / np.where(good, fp, 1.0), 0.0)
        t[active] = ta - step
        active = active[good & (np.abs(step) > NEWTON_TOL)]
    # Final step on every ray: its size decides convergence.
    qx = px + t * dx
    qy = py + t * dy
    qz = pz + t * dz
    z, zx, zy, inside = shape.sag(qx, qy)
    fp = dz - zx * dx - zy * dy
    good = inside & (np.abs(fp) > 1e-12)
    step = np.where(good, (qz - z) / np.where(good, fp, 1.0), 0.0)
    return t - step, good, good & (np.abs(step) <= 10.0 * NEWTON_TOL)


def _ideal_lens(ux, uy, uz, hx, hy, phi, n):
    """Ideal thin lens: new (unnormalized) direction and the added optical path."""
    adz = np.abs(uz)
    inv = 1.0 / np.where(adz > 0.0, adz, 1.0)
    gx, gy = ux * inv, uy * inv  # slopes tan θx, tan θy
    tx = gx - hx * (phi / n)
    ty = gy - hy * (phi / n)
    tz = np.where(uz >= 0.0, 1.0, -1.0)
    g_len = np.sqrt(gx * gx + gy * gy + 1.0)
    gm_len = np.sqrt((gx - phi * hx) ** 2 + (gy - phi * hy) ** 2 + 1.0)
    dopl = n * ((2.0 * (gx * hx + gy * hy) - phi * (hx * hx + hy * hy)) / (g_len + gm_len)
                - (ux * hx + uy * hy))
    return tx, ty, tz, dopl


# ------------------------------------------------------------------ trace
def _is_identity(R):
    return np.array_equal(R, np.eye(3))


def trace_numpy(system: System, origins, directions, wavelength_nm: float | None = None):
    """Trace rays (global frame) through ``system`` to its last surface.

    Parameters
    ----------
    system : lfsim.optics.prescription.System
    origins, directions : (N, 3) array_like
        Ray starts and directions (normalized here).
    wavelength_nm : float, optional
        Default: the system's primary wavelength.

    Returns
    -------
    positions, directions : (N, 3) float64
    status : (N,) int32, codes of ``lfsim.optics.tracer.Status``
    opl : (N,) float64, optical path length from the origin (mm)
    """
    if system.arrays or any(s.array is not None for s in system.surfaces):
        raise NotImplementedError("the NumPy baseline tracer does not support lenslet arrays")
    unknown = sorted({s.interaction for s in system.surfaces} - set(INTERACTIONS))
    if unknown:
        raise NotImplementedError(f"the NumPy baseline tracer does not support interaction(s) {unknown}")
    lam = system.primary_wavelength_nm if wavelength_nm is None else float(wavelength_nm)
    o = np.asarray(origins, dtype=np.float64)
    d = np.asarray(directions, dtype=np.float64)
    n_rays = o.shape[0]
    # Structure of arrays: contiguous x, y, z columns.
    px, py, pz = (np.ascontiguousarray(o[:, i]) for i in range(3))
    inv = 1.0 / np.sqrt(np.einsum("ij,ij->i", d, d))
    dx, dy, dz = (d[:, i] * inv for i in range(3))
    status = np.zeros(n_rays, dtype=np.int32)
    opl = np.zeros(n_rays, dtype=np.float64)

    frames = surface_frames(system)
    media = system.media()  # medium before each surface
    shapes: dict[int, _Shape] = {}

    def fail(mask, code):
        status[(status == OK) & mask] = code

    for i, s in enumerate(system.surfaces):
        if s.interaction == "break":
            continue
        R, org = frames[i]
        ident = _is_identity(R)
        # To local coordinates: Rᵀ (p − o), Rᵀ d.
        qx, qy, qz = px - org[0], py - org[1], pz - org[2]
        if ident:
            lx, ly, lz = qx, qy, qz
            ux, uy, uz = dx, dy, dz
        else:
            lx = R[0, 0] * qx + R[1, 0] * qy + R[2, 0] * qz
            ly = R[0, 1] * qx + R[1, 1] * qy + R[2, 1] * qz
            lz = R[0, 2] * qx + R[1, 2] * qy + R[2, 2] * qz
            ux = R[0, 0] * dx + R[1, 0] * dy + R[2, 0] * dz
            uy = R[0, 1] * dx + R[1, 1] * dy + R[2, 1] * dz
            uz = R[0, 2] * dx + R[1, 2] * dy + R[2, 2] * dz

        owner = i if s.same_as is None else s.same_as
        if owner not in shapes:
            shapes[owner] = _Shape(system.surfaces[owner])
        shape = shapes[owner]

        t, ok = _conic_hit(lx, ly, lz, ux, uy, uz, shape.c, shape.k)
        if shape.newton:
            dz_ok = np.abs(uz) > DZ_MIN
            t_plane = np.where(dz_ok, -lz / np.where(dz_ok, uz, 1.0), 0.0)
            t, ok, conv = _newton(shape, lx, ly, lz, ux, uy, uz, np.where(ok, t, t_plane))
            fail(~ok, MISSED)
            fail(ok & ~conv, NOT_CONVERGED)
        else:
            fail(~ok, MISSED)
        t = np.where(ok, t, 0.0)
        hx = lx + t * ux
        hy = ly + t * uy
        hz = lz + t * uz

        ap = s.aperture
        if ap is not None:
            ax = hx - ap.decenter[0]
            ay = hy - ap.decenter[1]
            slack = 1.0 + EDGE_TOL
            if ap.kind == "circular":
                fail(ax * ax + ay * ay > (ap.radius * slack) ** 2, VIGNETTED)
            else:
                fail((np.abs(ax) > ap.half_width[0] * slack) | (np.abs(ay) > ap.half_width[1] * slack),
                     VIGNETTED)

        n1 = float(media[i].index(lam))
        nx, ny, nz = ux, uy, uz
        extra_opl = 0.0
        if s.interaction in ("refract", "reflect", "tir"):
            _, zx, zy, _ = shape.sag(hx, hy)
            inv_len = 1.0 / np.sqrt(zx * zx + zy * zy + 1.0)
            Nx, Ny, Nz = -zx * inv_len, -zy * inv_len, inv_len
            cos_i = ux * Nx + uy * Ny + uz * Nz
            sgn = np.where(cos_i < 0.0, -1.0, 1.0)  # orient N along the ray
            Nx, Ny, Nz = sgn * Nx, sgn * Ny, sgn * Nz
            cos_i = np.abs(cos_i)
            if s.interaction == "refract":
                mu = n1 / float(s.material.index(lam))
                kk = 1.0 - mu * mu * (1.0 - cos_i * cos_i)
                can = kk >= 0.0
                fail(~can, TIR)
                a = np.sqrt(np.where(can, kk, 1.0)) - mu * cos_i
                nx = np.where(can, mu * ux + a * Nx, ux)
                ny = np.where(can, mu * uy + a * Ny, uy)
                nz = np.where(can, mu * uz + a * Nz, uz)
            else:
                if s.interaction == "tir":
                    mu = n1 / float(s.material.index(lam))
                    fail(1.0 - mu * mu * (1.0 - cos_i * cos_i) >= 0.0, NO_TIR)
                two_c = 2.0 * cos_i
                nx, ny, nz = ux - two_c * Nx, uy - two_c * Ny, uz - two_c * Nz
        elif s.interaction == "paraxial":
            nx, ny, nz, extra_opl = _ideal_lens(ux, uy, uz, hx, hy, float(s.power), n1)

        # Back to global; failed rays keep their last valid state.
        alive = status == OK
        if ident:
            gx, gy, gz = hx + org[0], hy + org[1], hz + org[2]
            ex, ey, ez = nx, ny, nz
        else:
            gx = R[0, 0] * hx + R[0, 1] * hy + R[0, 2] * hz + org[0]
            gy = R[1, 0] * hx + R[1, 1] * hy + R[1, 2] * hz + org[1]
            gz = R[2, 0] * hx + R[2, 1] * hy + R[2, 2] * hz + org[2]
            ex = R[0, 0] * nx + R[0, 1] * ny + R[0, 2] * nz
            ey = R[1, 0] * nx + R[1, 1] * ny + R[1, 2] * nz
            ez = R[2, 0] * nx + R[2, 1] * ny + R[2, 2] * nz
        inv = 1.0 / np.sqrt(ex * ex + ey * ey + ez * ez)
        px = np.where(alive, gx, px)
        py = np.where(alive, gy, py)
        pz = np.where(alive, gz, pz)
        dx = np.where(alive, ex * inv, dx)
        dy = np.where(alive, ey * inv, dy)
        dz = np.where(alive, ez * inv, dz)
        opl = np.where(alive, opl + n1 * t + extra_opl, opl)

    return np.stack([px, py, pz], axis=1), np.stack([dx, dy, dz], axis=1), status, opl
