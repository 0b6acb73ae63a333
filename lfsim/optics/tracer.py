"""Differentiable sequential real-ray tracer (Dr.Jit).

A :class:`SequentialTracer` compiles a :class:`~lfsim.optics.prescription.System`
into Dr.Jit code. Every design number is one entry of a packed parameter
array ``P`` (see :meth:`System.parameter_table`), read with ``dr.gather`` so a
reverse pass accumulates all gradients in one array. ``P`` may hold several
parameter *blocks* (copies of the whole vector); each ray names its block,
which batches forward-mode Jacobians, zoom configurations and wavelengths
into a single kernel launch.

Per surface: transform to the local frame, intersect (closed form for
conics, Newton for aspheres/XY polynomials), test the aperture (and, inside a
lenslet array, the lenslet cell), then refract (vector Snell's law),
reflect, or reflect by total internal reflection, and accumulate the optical
path length n·t. A ray that fails keeps its status code and its last valid
state, so nothing downstream is NaN.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from enum import IntEnum

import drjit as dr
import numpy as np

from .. import backend
from .prescription import System
from .surfaces import intersect, normal, sag
from .vector import DesignVector


class Status(IntEnum):
    """Per-ray outcome; the first failure along the path is kept."""

    OK = 0
    MISSED = 1  # no intersection on the vertex branch / outside the conic's domain
    TIR = 2  # total internal reflection where refraction was expected
    VIGNETTED = 3  # outside a clear aperture (or outside the lenslet array)
    NOT_CONVERGED = 4  # Newton iteration did not converge
    WRONG_LENSLET = 5  # crossed into a neighbouring lenslet's cell
    NO_TIR = 6  # refraction possible where total internal reflection was required
    BEHIND = 7  # the surface lies behind the ray (it would travel backwards); not on virtual, dummy or ideal surfaces


@dataclass
class RayState:
    """Dr.Jit rays: positions ``p`` and unit directions ``d`` (Array3), global frame."""

    p: object
    d: object


@dataclass
class ProbeHit:
    """Where rays met surface ``i`` (:meth:`SequentialTracer.trace` ``probe``): the local hit
    ``x, y`` (lenslet-relative inside an array, mm), the array's pitch ``(px, py)`` and
    cell ``(m, n)`` (None off an array). Valid where the ray's status is still OK."""

    i: int
    x: object
    y: object
    pitch: tuple | None
    cell: tuple | None


@dataclass
class TraceOutput:
    """Dr.Jit result of :meth:`SequentialTracer.trace` at the last surface."""

    p: object
    d: object
    status: object  # UInt32
    opl: object  # Float, optical path length from the ray origin (mm)
    failed_at: object  # Int32, surface index of the first failure (−1: none)
    lenslet_m: object  # Int32, lenslet column in the first array group (−1: none)
    lenslet_n: object  # Int32
    path: list | None  # (position, direction) after every surface (global), when recorded


def _rot_xyz(ax, ay, az, T):
    """Rotation R = Rx(ax)·Ry(ay)·Rz(az) (radians, right-handed, active)."""
    cx, sx = dr.cos(ax), dr.sin(ax)
    cy, sy = dr.cos(ay), dr.sin(ay)
    cz, sz = dr.cos(az), dr.sin(az)
    sxsy, cxsy = sx * sy, cx * sy
    return T.Matrix3(cy * cz, -cy * sz, sy,
                     sxsy * cz + cx * sz, cx * cz - sxsy * sz, -sx * cy,
                     sx * sz - cxsy * cz, cxsy * sz + sx * cz, cx * cy)


def _ideal_lens(d, h, phi, n, T):
    """Ideal thin lens of power φ (1/mm) in a medium of index n, at local hit h.

    Slopes along the propagation direction map as ``tan θ' = tan θ − h·φ/n``
    (x and y), which images every conjugate perfectly (the lens-design
    programs' paraxial surface). The optical path it adds makes every ray of
    an incoming plane wave equal in path to its focal point F = f·g
    (g = d/|d_z|, f = 1/φ; virtual F for φ < 0):
    ``ΔOPL = n·((2 g·h − φ|h|²)/(|g| + |g − φh|) − d·h)``, a cancellation-free
    form of n·(±(|F| − |F − h|) − d·h) that tends to 0 as φ → 0.
    """
    adz = dr.abs(d.z)
    inv = 1.0 / dr.select(adz > 0.0, adz, 1.0)
    gx, gy = d.x * inv, d.y * inv
    tx = gx - h.x * phi / n
    ty = gy - h.y * phi / n
    d_new = dr.normalize(T.Array3(tx, ty, dr.sign(d.z)))
    g_dot_h = gx * h.x + gy * h.y
    h2 = h.x * h.x + h.y * h.y
    g_len = dr.sqrt(gx * gx + gy * gy + 1.0)
    gm_len = dr.sqrt(dr.square(gx - phi * h.x) + dr.square(gy - phi * h.y) + 1.0)
    dopl = n * ((2.0 * g_dot_h - phi * h2) / (g_len + gm_len) - (d.x * h.x + d.y * h.y))
    return d_new, dopl


class SequentialTracer:
    """Compile a :class:`System` for tracing at one precision.

    Parameters
    ----------
    system : System
        The sequential prescription (last surface = image surface).
    precision : {"float64", "float32"}
    newton_tol : float, optional
        Convergence tolerance on the Newton step |Δt| (mm). Default 1e-12 for
        float64, 1e-5 for float32.
    newton_max_iter : int
        Iteration cap of the Newton loop (default 16).
    """

    def __init__(self, system: System, precision: str = "float64",
                 newton_tol: float | None = None, newton_max_iter: int = 16):
        self.system = system
        self.T = backend.types(precision)
        self.precision = precision
        #: The design vector (names, blocks, shapes, lenslet axes, media).
        self.vector = vec = DesignVector(system)
        self.names = vec.names
        self.index = vec.index
        self.n_params = vec.size
        self.newton_tol = newton_tol if newton_tol is not None else (
            1e-12 if precision == "float64" else 1e-5)
        self.newton_max_iter = int(newton_max_iter)
        #: Relative slack of aperture and lenslet-cell edges, so a ray aimed
        #: exactly at a rim is not vignetted by rounding (1 nm per metre in float64).
        self.edge_tol = 1e-12 if precision == "float64" else 1e-6
        #: How the reverse pass accumulates per-ray parameter adjoints
        #: (the scatter-add that is the derivative of every per-ray gather).
        self.reduce_mode = dr.ReduceMode.Auto
        self.groups = system.array_groups()
        self._group_first = {idx[0]: g for g, idx in self.groups.items()}
        self._opaque: dict = {}

    def const(self, value, kind: str = "Float"):
        """An opaque (evaluated) scalar: a design number that enters kernels as data.

        A Python number in a Dr.Jit expression becomes a literal of the
        kernel's IR, so a design that differs only in that number would
        compile its kernels anew; an opaque scalar is read from memory."""
        key = (kind, float(value) if kind == "Float" else int(value))
        v = self._opaque.get(key)
        if v is None:
            v = self._opaque[key] = dr.opaque(getattr(self.T, kind), key[1])
        return v

    def rays(self, origins, directions) -> RayState:
        """A :class:`RayState` from numpy (N, 3) origins and directions (copied)."""
        T = self.T
        o = np.asarray(origins, dtype=T.np_dtype).reshape(-1, 3)
        d = np.asarray(directions, dtype=T.np_dtype).reshape(-1, 3)
        c = backend.from_numpy(T.Float, *o.T, *d.T)
        return RayState(T.Array3(*c[:3]), T.Array3(*c[3:]))

    # ----------------------------------------------------------- parameters
    def params(self, wavelength_nm=None, values=None):
        """Packed parameter array at ``wavelength_nm``: one block, or one block per wavelength
        of a sequence (a spectral render's nodes, picked per ray with ``trace(block=...)``).

        ``values`` (numpy, length ``n_params`` or a multiple) overrides the
        design values, e.g. for finite differences or several blocks.
        """
        if values is None:
            lam = wavelength_nm if wavelength_nm is not None else self.system.primary_wavelength_nm
            values = (np.concatenate([self.vector.values(v) for v in lam]) if np.ndim(lam)
                      else self.vector.values(lam))
        values = np.asarray(values, dtype=np.float64).ravel()
        if values.size % self.n_params:
            raise ValueError(
                f"parameter array of length {values.size} is not a multiple of {self.n_params}")
        return backend.from_numpy(self.T.Float, values.astype(self.T.np_dtype))

    def shape(self, P, i: int, block):
        """Surface ``i``'s shape (its ``same_as`` owner's coefficients), gathered per
        lane from parameter block ``block`` (UInt32 array) of the packed ``P``."""
        T = self.T
        base = block * self.n_params

        def pr(name):
            return dr.gather(T.Float, P, base + self.index[name], mode=self.reduce_mode)

        owner = self.system.surfaces[self.vector.owner(i)]
        return self.vector.shape(i, pr, const=self.const if owner.xy else float)

    # --------------------------------------------------------------- frames
    def frames(self, P):
        """Local frames (R, o) of every surface, one entry per parameter block.

        Returns lists of Matrix3 / Array3 of width = number of blocks; a point
        in surface i's local frame maps to global as ``R[i] @ x + o[i]``.
        """
        T = self.T
        nb = dr.width(P) // self.n_params
        blk = dr.arange(T.UInt32, nb) * self.n_params

        def g(name):
            return dr.gather(T.Float, P, blk + self.index[name])

        deg = math.pi / 180.0
        R_cur = dr.identity(T.Matrix3, nb)
        o_cur = dr.zeros(T.Array3, nb)
        Rs, os_ = [], []
        for s in self.system.surfaces:
            if s.same_as is not None:
                R_s, o_s = Rs[s.same_as], os_[s.same_as]
            else:
                tilt = _rot_xyz(g(f"{s.name}.tilt_x") * deg, g(f"{s.name}.tilt_y") * deg,
                                g(f"{s.name}.tilt_z") * deg, T)
                shift = T.Array3(g(f"{s.name}.decenter_x"), g(f"{s.name}.decenter_y"), 0.0)
                if s.global_position is not None:
                    pos = T.Array3(g(f"{s.name}.position_x"), g(f"{s.name}.position_y"),
                                   g(f"{s.name}.position_z"))
                    R_s, o_s = tilt, pos + tilt @ shift
                else:
                    R_s, o_s = R_cur @ tilt, o_cur + R_cur @ shift
            Rs.append(R_s)
            os_.append(o_s)
            if not s.return_axis or s.global_position is not None:
                R_cur, o_cur = R_s, o_s
            o_cur = o_cur + R_cur @ T.Array3(0.0, 0.0, g(f"{s.name}.thickness"))
        return Rs, os_

    # ---------------------------------------------------------------- trace
    def trace(self, P, rays: RayState, block=None, lenslet=None, record: bool = False,
              first: int = 0, last: int | None = None, clip: bool = True,
              cells: str = "fixed", kick=None, probe: list | None = None) -> TraceOutput:
        """Trace ``rays`` through every surface; see the module docstring.

        Parameters
        ----------
        P : Float
            Packed parameters (``params()``), possibly several blocks, may
            have gradients enabled.
        rays : RayState
            Origins and directions in the global frame (directions are
            normalized here).
        block : UInt32, optional
            Parameter block of each ray (default: block 0 for all).
        lenslet : (Int32, Int32), optional
            Lenslet (m, n) each ray is aimed through in the first array group;
            by default it is the cell where the ray crosses the group's first
            vertex plane.
        record : bool
            Also return the global hit position at every surface.
        first, last : int
            Trace only surfaces ``first..last`` (inclusive; default: all), for
            rays given in the global frame in front of surface ``first`` and
            in the medium before it. Used for first-order data of a group.
        clip : bool
            Apply clear apertures and lenslet cells (default). ``False`` lets
            rays through them, e.g. to aim a ray at a point on an aperture's edge.
        kick : (int, callable), optional
            ``(i, f)``: after surface ``i``, the ray's direction becomes
            ``f(d, hit, cell, n)`` (local frame of surface ``i``; ``hit``
            lenslet-relative on an array surface, ``cell`` its (m, n) or None,
            ``n`` the index of the medium the ray goes on in): the diffraction
            of an aperture there (:mod:`lfsim.render.diffraction`).
        cells : {"fixed", "per_surface"}
            Lenslet arrays. ``"fixed"`` (default, the sub-system view): a ray
            belongs to the cell it enters at the group's first surface, and
            meeting another cell's part of a later surface is crosstalk
            (``WRONG_LENSLET``), as if the cells were baffled. ``"per_surface"``
            (a monolithic array without baffles, for rendering): each array
            surface is met on the lenslet where the ray actually crosses it.
        probe : list, optional
            Filled with a :class:`ProbeHit` for every surface that carries a
            clear aperture or belongs to a lenslet array: where the ray met
            it, in the coordinates its edges are drawn in (the boundary
            term of :mod:`lfsim.render.boundary` holds those points still).
        """
        if cells not in ("fixed", "per_surface"):
            raise ValueError(f"cells = {cells!r}: expected 'fixed' or 'per_surface'")
        T = self.T
        n = dr.width(rays.p)
        if n == 0:
            raise ValueError("no rays to trace")
        if block is None:
            block = dr.opaque(T.UInt32, 0, n)
        base = block * self.n_params
        Rs, os_ = self.frames(P)
        vec = self.vector

        def pr(name):
            return dr.gather(T.Float, P, base + self.index[name], mode=self.reduce_mode)

        p = T.Array3(rays.p)
        d = dr.normalize(T.Array3(rays.d))
        status = dr.zeros(T.UInt32, n)
        failed_at = dr.full(T.Int32, -1, n)
        opl = dr.zeros(T.Float, n)
        lens_m = dr.full(T.Int32, -1, n)
        lens_n = dr.full(T.Int32, -1, n)
        first_group = min(self._group_first) if self._group_first else None
        cell = {}
        path = [] if record else None

        def fail(mask, code, i):
            nonlocal status, failed_at
            new = (status == 0) & mask
            status = dr.select(new, int(code), status)
            failed_at = dr.select(new, int(i), failed_at)

        # Rays are carried in the local frame of the last surface met, so each
        # surface costs one frame change: x_i = A_i (x_prev − b_i).
        A, b = self._relative_frames(Rs, os_)
        # Every frame in one small kernel (one lane per parameter block, so a compact
        # one): the per-ray gathers below read evaluated arrays (else each gather
        # source compiles a kernel of its own).
        with backend.compact_kernels():
            dr.eval(Rs, os_, list(A.values()), list(b.values()))
        stop_at = len(self.system.surfaces) - 1 if last is None else int(last)
        last = None
        for i, s in enumerate(self.system.surfaces):
            if i < first or i > stop_at:
                continue
            if s.interaction == "break":
                if record:
                    path.append(self._to_global(p, d, Rs, os_, last, block))
                continue
            # Per-ray gathers (also for a single block): the reverse pass then
            # scatter-adds into the frame arrays inside one kernel instead of
            # launching a reduction per broadcast scalar.
            if last is None and i > 0:  # first traced surface: rays come in global coordinates
                Ai = dr.gather(T.Matrix3, Rs[i].T, block, mode=self.reduce_mode)
                bi = dr.gather(T.Array3, os_[i], block, mode=self.reduce_mode)
            else:
                Ai = dr.gather(T.Matrix3, A[i], block, mode=self.reduce_mode)
                bi = dr.gather(T.Array3, b[i], block, mode=self.reduce_mode)
            pl = Ai @ (p - bi)
            dl = Ai @ d

            # Lenslet-array membership: pick the cell at the group's first surface.
            offset = None
            if s.array is not None:
                arr = self.system.arrays[s.array]
                px, py = pr(f"{arr.name}.pitch_x"), pr(f"{arr.name}.pitch_y")
                cx, cy = pr(f"{arr.name}.center_x"), pr(f"{arr.name}.center_y")
                lattice = {f"{arr.name}.pitch_x": px, f"{arr.name}.pitch_y": py,
                           f"{arr.name}.center_x": cx, f"{arr.name}.center_y": cy}
                # Lenslet counts as data: halves, centre offsets, last indices.
                half_m, half_n = self.const(0.5 * arr.m), self.const(0.5 * arr.n)
                cnt_m, cnt_n = self.const(arr.m, "Int32"), self.const(arr.n, "Int32")
                top_m, top_n = self.const(arr.m - 1, "Int32"), self.const(arr.n - 1, "Int32")
                if s.array not in cell or cells == "per_surface":
                    if lenslet is not None and i == first_group:
                        m_idx, n_idx = T.Int32(lenslet[0]), T.Int32(lenslet[1])
                    else:
                        ok_z = dr.abs(dl.z) > 0.0
                        t0 = dr.select(ok_z, -pl.z / dr.select(ok_z, dl.z, 1.0), 0.0)
                        x0, y0 = dr.fma(dl.x, t0, pl.x), dr.fma(dl.y, t0, pl.y)
                        m_idx = T.Int32(dr.floor(dr.detach((x0 - cx) / px) + half_m))
                        n_idx = T.Int32(dr.floor(dr.detach((y0 - cy) / py) + half_n))
                    outside = (m_idx < 0) | (m_idx >= cnt_m) | (n_idx < 0) | (n_idx >= cnt_n)
                    if cells == "per_surface":
                        # The vertex-plane crossing is only a first guess: start
                        # from the nearest edge cell; the hit on the face decides.
                        m_idx = dr.clip(m_idx, 0, top_m)
                        n_idx = dr.clip(n_idx, 0, top_n)
                    else:
                        fail(outside, Status.VIGNETTED, i)
                        m_idx = dr.select(outside, 0, m_idx)
                        n_idx = dr.select(outside, 0, n_idx)
                    cell[s.array] = (m_idx, n_idx)
                    if i == first_group:
                        lens_m = dr.select(outside, -1, m_idx)
                        lens_n = dr.select(outside, -1, n_idx)
                m_idx, n_idx = cell[s.array]
                xm, yn = vec.lenslet_centre(s.array, T.Float(m_idx), T.Float(n_idx), lattice.__getitem__,
                                            const=self.const)
                offset = T.Array3(xm, yn, 0.0)
                pl = pl - offset

            owner = self.system.surfaces[vec.owner(i)]
            shape = self.shape(P, i, block)
            t, ok, conv = intersect(pl, dl, shape, T, owner.needs_newton,
                                    self.newton_tol, self.newton_max_iter)
            if offset is not None and cells == "per_surface":
                # The vertex-plane crossing picked the cell; near a seam the hit
                # on the curved face can lie in the neighbour: move there once.
                hit0 = dr.fma(dl, dr.select(ok, t, 0.0), pl) + offset
                m2 = T.Int32(dr.floor(dr.detach((hit0.x - cx) / px) + half_m))
                n2 = T.Int32(dr.floor(dr.detach((hit0.y - cy) / py) + half_n))
                moved = ok & ((m2 != m_idx) | (n2 != n_idx)) & (m2 >= 0) & (m2 < cnt_m) & (n2 >= 0) & (n2 < cnt_n)
                m_idx, n_idx = dr.select(moved, m2, m_idx), dr.select(moved, n2, n_idx)
                offset2 = T.Array3(*vec.lenslet_centre(s.array, T.Float(m_idx), T.Float(n_idx),
                                                       lattice.__getitem__, const=self.const), 0.0)
                pl = pl + offset - offset2
                offset = offset2
                t, ok, conv = intersect(pl, dl, shape, T, owner.needs_newton,
                                        self.newton_tol, self.newton_max_iter)
            fail(~ok, Status.MISSED, i)
            fail(ok & ~conv, Status.NOT_CONVERGED, i)
            if not (s.virtual or s.interaction in ("none", "break", "paraxial")):
                # A real surface is reached forwards (a rounding's worth of slack); dummy
                # planes are references, reached along the ray's line either way, and so
                # are ideal (paraxial) lenses: planes of zero thickness, of which two in
                # contact tilt against each other (else half the rays die at any tilt).
                fail(ok & (t < -self.const(self.newton_tol * 10.0)), Status.BEHIND, i)
            t = dr.select(ok, t, 0.0)
            hit = dr.fma(dl, t, pl)

            # Apertures (in lenslet-relative coordinates inside an array).
            ap = s.aperture if clip else None
            if ap is not None:
                ax, ay = hit.x - self.const(ap.decenter[0]), hit.y - self.const(ap.decenter[1])
                slack = 1.0 + self.edge_tol
                if ap.kind == "circular":
                    outside = dr.fma(ax, ax, ay * ay) > self.const((ap.radius * slack) ** 2)
                else:
                    outside = ((dr.abs(ax) > self.const(ap.half_width[0] * slack))
                               | (dr.abs(ay) > self.const(ap.half_width[1] * slack)))
                fail(outside, Status.VIGNETTED, i)
            if offset is not None and clip:
                half = 0.5 * (1.0 + self.edge_tol)
                crossed = (dr.abs(hit.x) > half * px) | (dr.abs(hit.y) > half * py)
                if cells == "per_surface":
                    # After the move to the hit's cell, a hit still outside it
                    # lies beyond the array's outer edge.
                    fail(crossed, Status.VIGNETTED, i)
                fail(crossed, Status.WRONG_LENSLET, i)

            if probe is not None and (s.aperture is not None or offset is not None):
                probe.append(ProbeHit(i, hit.x, hit.y, (px, py) if offset is not None else None,
                                      (m_idx, n_idx) if offset is not None else None))

            # Interaction.
            n1 = pr(self.vector.media[i])
            d_new = dl
            if s.interaction in ("refract", "reflect", "tir"):
                if owner.needs_newton:
                    _, zx, zy, _ = sag(hit.x, hit.y, shape)
                    N = normal(zx, zy, T.Array3)
                else:
                    # On a conic, ∇[c(x²+y²+(1+k)z²) − 2z] is the normal: no square root.
                    N = dr.normalize(T.Array3(shape.c * hit.x, shape.c * hit.y,
                                              shape.c * (1.0 + shape.k) * hit.z - 1.0))
                cos_i = dr.dot(dl, N)
                N = dr.select(cos_i < 0.0, -N, N)
                cos_i = dr.abs(cos_i)
                reflected = dl - 2.0 * cos_i * N
                if s.interaction == "reflect":
                    d_new = reflected
                else:
                    n2 = pr(f"{s.name}.index")
                    mu = n1 / n2
                    kk = 1.0 - mu * mu * (1.0 - cos_i * cos_i)
                    can_refract = kk >= 0.0
                    if s.interaction == "refract":
                        fail(~can_refract, Status.TIR, i)
                        root = dr.sqrt(dr.select(can_refract, kk, 1.0))
                        d_new = dr.select(can_refract, mu * dl + (root - mu * cos_i) * N, dl)
                    else:
                        fail(can_refract, Status.NO_TIR, i)
                        d_new = reflected

            elif s.interaction == "paraxial":
                d_new, dopl = _ideal_lens(dl, hit, pr(f"{s.name}.power"), n1, T)
            if kick is not None and i == kick[0]:
                n_on = pr(f"{s.name}.index") if s.interaction == "refract" else n1
                d_new = kick[1](d_new, hit, (m_idx, n_idx) if offset is not None else None, n_on)

            alive = status == 0
            # Failed rays keep their last valid state (re-expressed in this frame).
            p = dr.select(alive, hit + offset if offset is not None else hit, pl + offset if offset is not None else pl)
            d = dr.select(alive, d_new, dl)
            step_opl = n1 * t if s.interaction != "paraxial" else n1 * t + dopl
            opl = dr.select(alive, opl + step_opl, opl)
            last = i
            if record:
                path.append(self._to_global(p, d, Rs, os_, last, block))
        p, d = self._to_global(p, d, Rs, os_, last, block)
        return TraceOutput(p, d, status, opl, failed_at, lens_m, lens_n, path)

    def _relative_frames(self, Rs, os_):
        """Per block: A_i, b_i with x_i = A_i (x_prev − b_i), x_prev in the frame
        of the previous (non-break) surface, or global before the first."""
        A, b = {}, {}
        prev = None
        for i, s in enumerate(self.system.surfaces):
            if s.interaction == "break":
                continue
            if prev is None:
                A[i], b[i] = Rs[i].T, os_[i]
            else:
                A[i] = Rs[i].T @ Rs[prev]
                b[i] = Rs[prev].T @ (os_[i] - os_[prev])
            prev = i
        return A, b

    def _to_global(self, p, d, Rs, os_, i, block):
        """Rays in surface i's local frame → global frame (i None: already global)."""
        if i is None:
            return p, d
        T = self.T
        R = dr.gather(T.Matrix3, Rs[i], block, mode=self.reduce_mode)
        o = dr.gather(T.Array3, os_[i], block, mode=self.reduce_mode)
        return R @ p + o, R @ d

    # ---------------------------------------------------------- numpy API
    def trace_numpy(self, origins, directions, wavelength_nm: float | None = None, lenslet=None,
                    record: bool = False, values=None) -> dict:
        """:meth:`trace` with numpy (N, 3) rays in and numpy arrays out, no gradients.

        The kernels move the data: the trace gathers the rays from the (N, 3)
        buffers (read in place, without a host-side transpose or copy), and a
        second, small kernel of 3N lanes interleaves positions and directions
        into (N, 3) outputs by gathers (contiguous stores; scatters into an
        interleaved buffer launched one kernel per component and cost three
        times as much). Returns a dict with ``positions``, ``directions`` (N,
        3) float64, ``status``, ``opl``, ``failed_at``, ``lenslet`` (N, 2),
        ``direction_norm2`` (N,) (|d|² of each input direction, for the
        caller's check) and, with ``record``, ``path`` (S, N, 3).
        """
        T = self.T
        o = np.ascontiguousarray(origins, dtype=T.np_dtype).reshape(-1, 3)
        d = np.ascontiguousarray(directions, dtype=T.np_dtype).reshape(-1, 3)
        N = len(o)
        with dr.suspend_grad():
            i3 = dr.arange(T.UInt32, N) * 3

            def get(buf):
                return T.Array3(*(dr.gather(T.Float, buf, i3 + c) for c in range(3)))

            lens = None
            if lenslet is not None:
                lz = T.Int32(np.ascontiguousarray(lenslet, dtype=np.int32).ravel())
                i2 = dr.arange(T.UInt32, N) * 2
                lens = (dr.gather(T.Int32, lz, i2), dr.gather(T.Int32, lz, i2 + 1))
            P = self.params(wavelength_nm, values=values)
            d_in = get(T.Float(d.ravel()))
            out = self.trace(P, RayState(get(T.Float(o.ravel())), d_in), lenslet=lens, record=record)
            norm2 = dr.squared_norm(d_in)
            # Integers widened to int64 inside the trace kernel: every output is then a
            # view of Dr.Jit's pooled memory (a host-side astype of a fresh numpy
            # buffer pays its page faults on every call).
            status, failed = T.Int64(out.status), T.Int64(out.failed_at)
            vecs = [out.p, out.d] + [q for q, _ in (out.path or [])]
            dr.eval(*vecs, status, out.opl, failed, out.lenslet_m, out.lenslet_n, norm2)
            # Interleave: lane j of a 3N-lane kernel reads component j % 3 of ray j // 3
            # (and of a 2N-lane one, lenslet index j % 2 of ray j // 2).
            j = dr.arange(T.UInt32, 3 * N)
            row, comp = j // 3, j % 3
            flat = [dr.select(comp == 0, dr.gather(T.Float, v.x, row),
                              dr.select(comp == 1, dr.gather(T.Float, v.y, row), dr.gather(T.Float, v.z, row)))
                    for v in vecs]
            j2 = dr.arange(T.UInt32, 2 * N)
            row2 = j2 // 2
            cells = T.Int64(dr.select(j2 % 2 == 0, dr.gather(T.Int32, out.lenslet_m, row2),
                                      dr.gather(T.Int32, out.lenslet_n, row2)))
            dr.eval(*flat, cells)

        def f64(buf):
            return np.asarray(buf).reshape(N, 3).astype(np.float64, copy=False)

        res = {"positions": f64(flat[0]), "directions": f64(flat[1]), "status": np.asarray(status),
               "opl": np.asarray(out.opl).astype(np.float64, copy=False), "failed_at": np.asarray(failed),
               "lenslet": np.asarray(cells).reshape(N, 2),
               "direction_norm2": np.asarray(norm2).astype(np.float64, copy=False)}
        if record:
            res["path"] = np.stack([f64(q) for q in flat[2:]])
        return res

    # ------------------------------------------------------------ jacobian
    def jacobian(self, values, rays: RayState, names: list[str], outputs=None):
        """Forward-mode Jacobian of ray outputs w.r.t. named parameters, in one launch.

        The rays are replicated once per parameter; copy k uses parameter
        block k, in which only parameter ``names[k]`` depends on a single
        AD seed. One forward pass then yields every column.

        Parameters
        ----------
        values : array_like
            One parameter vector (``n_params``).
        rays : RayState
            N rays.
        names : list of str
            Parameters to differentiate against (K of them).
        outputs : callable, optional
            ``TraceOutput -> list of Float`` (default: final x, y, z, dx, dy, dz).

        Returns
        -------
        J : ndarray (K, n_outputs, N)
            ``J[k, i, j] = d output_i(ray j) / d names[k]``; zero for failed rays.
        status : ndarray (N,)
            Status of each ray at the nominal parameters.
        """
        T = self.T
        values = np.asarray(values, dtype=np.float64).ravel()
        if values.size != self.n_params:
            raise ValueError(f"expected {self.n_params} parameter values, got {values.size}")
        unknown = [n for n in names if n not in self.index]
        if unknown:
            raise ValueError(f"unknown parameter(s) {unknown}: see parameter_names()")
        K, N = len(names), dr.width(rays.p)
        mask = np.zeros(K * self.n_params)
        for k, name in enumerate(names):
            mask[k * self.n_params + self.index[name]] = 1.0
        seed = dr.zeros(T.Float, 1)
        dr.enable_grad(seed)
        P = T.Float(np.tile(values, K).astype(T.np_dtype)) + seed * T.Float(mask.astype(T.np_dtype))
        j = dr.arange(T.UInt32, K * N)
        ray_idx = j % self.const(N, "UInt32")  # counts as data: one kernel for any N, K
        rep = RayState(dr.gather(T.Array3, rays.p, ray_idx), dr.gather(T.Array3, rays.d, ray_idx))
        out = self.trace(P, rep, block=j // self.const(N, "UInt32"))
        outs = outputs(out) if outputs else [out.p.x, out.p.y, out.p.z, out.d.x, out.d.y, out.d.z]
        dr.forward_from(seed)
        st, *grads = backend.to_numpy(out.status, *(dr.grad(v) for v in outs))
        ok = st == 0
        J = np.stack([np.where(ok, np.asarray(g, dtype=np.float64), 0.0).reshape(K, N) for g in grads], axis=1)
        status = st[:N].astype(np.int64)
        return J, status

    # ------------------------------------------------------- numpy helpers
    def frames_numpy(self, P=None) -> list[tuple[np.ndarray, np.ndarray]]:
        """Frames (R 3×3, o 3) of every surface for the first parameter block."""
        P = self.params() if P is None else P
        with dr.suspend_grad(), backend.compact_kernels():
            Rs, os_ = self.frames(P)
            # One kernel for every frame (each entry read alone would launch its own).
            flat = [R[i][j] for R in Rs for i in range(3) for j in range(3)] + [o[i] for o in os_ for i in range(3)]
            vals = backend.to_numpy(*flat, dtype=np.float64)
        nR = 9 * len(Rs)
        return [(np.array([v[0] for v in vals[9 * k:9 * k + 9]]).reshape(3, 3),
                 np.array([v[0] for v in vals[nR + 3 * k:nR + 3 * k + 3]])) for k in range(len(Rs))]

    def sag_numpy(self, i: int, x, y) -> np.ndarray:
        """Sag of surface ``i`` (the same model the tracer intersects) at local (x, y)."""
        T = self.T
        get = self.vector.numpy_getter(self.vector.values())
        shape = self.vector.shape(i, lambda name: T.Float(get(name)))
        x = np.asarray(x, dtype=T.np_dtype)
        y = np.asarray(y, dtype=T.np_dtype)
        with dr.suspend_grad():
            z, _, _, inside = sag(T.Float(x.ravel()), T.Float(y.ravel()), shape)
            z = dr.select(inside, z, dr.nan)
        return np.asarray(z, dtype=np.float64).reshape(x.shape)
