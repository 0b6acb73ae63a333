"""The InI-HMD as a whole: its paraxial model, CDP states and elemental-image layout.

The paper's Eqs. (1)–(10) describe thin elements. A real design (thick aspheric
lenslets, a relay with a tunable lens, a tilted freeform prism) has the same
first-order structure, which lfsim takes from the design itself: the exact
first-order (parabasal) maps of

* the lenslet (display state → stop hit and → state behind the MLA), about the
  axis of one lenslet — every lenslet is the same, shifted by its centre,
  Eq. (1); and
* the eyepiece group (state behind the MLA → state on the viewing window, in
  the viewing-window frame), about the system axis, per CDP state,

obtained with Dr.Jit forward-mode AD of the real tracer (the zero-step limit of
parabasal rays). Composed, they give every sub-system's paraxial ray as an
affine function of the display point ``s`` and slope ``t``. Ray states are
``(x, y, tan_x, tan_y)`` on a plane (slopes dx/dz, dy/dz). For ideal (paraxial)
elements the maps are the thin-lens equations and the model reproduces
Eqs. (2)–(10) exactly (see the tests); for real designs it is their thick,
anamorphic generalization and the reference for GD (Eq. 11) and PA (Eq. 12).

Conventions: lenslet (m, n) is 0-based here (``m = 0..M−1``); reports use the
paper's 1-based indices. The *retinal angle* of a ray leaving the viewing
window at ``h`` with slope ``t``, for an ideal eye focused at ``D`` diopters,
is ``r = t − h·D/1000`` (tangent of the visual angle of the point it appears to
come from on the CDP; finite at 0 D): the ideal eye lens maps it to the retinal
point ``f_eye·r``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import drjit as dr
import numpy as np

from ..backend import compact_kernels, to_numpy
from ..design.errors import DesignError
from ..optics.tracer import RayState, Status
from ..optics.vector import GAP


class IniModelError(ValueError):
    """The design's optics do not form a working InI-HMD (e.g. the axis ray fails)."""


@dataclass
class DepthState:
    """First-order data of one CDP state (lengths mm, angles deg, powers D)."""

    diopters: float  # CDP depth the state serves
    tunable_power_diopters: float | None
    cdp_diopters_x: float  # paraxial CDP depth actually made, x and y meridians
    cdp_diopters_y: float
    p_ei: tuple[float, float]  # Eq. (2): EI pitch on the display
    d_v: tuple[float, float]  # Eq. (5): footprint width on the viewing window
    D_v: tuple[float, float]  # Eq. (6): viewing-window size
    delta_theta_eic_deg: tuple[float, float]  # Eq. (7) as an angle (tan step, in degrees of atan)
    theta_eic_deg: tuple[float, float]  # Eq. (8) as an angle
    fov_deg: tuple[float, float]  # full FOV between the edge EI centres' outer edges
    fov_diag_deg: float  # Eq. (10)
    pixel_arcmin: tuple[float, float]  # one display pixel seen from the viewing window
    nyquist_cpd: float  # display Nyquist angular frequency (cycles/degree)

    def as_dict(self) -> dict:
        from dataclasses import asdict

        return asdict(self)

    #: Unit of each field (x, y pairs share one).
    UNITS = {"diopters": "D", "tunable_power_diopters": "D", "cdp_diopters_x": "D", "cdp_diopters_y": "D",
             "p_ei": "mm", "d_v": "mm", "D_v": "mm", "delta_theta_eic_deg": "deg", "theta_eic_deg": "deg",
             "fov_deg": "deg", "fov_diag_deg": "deg", "pixel_arcmin": "arcmin", "nyquist_cpd": "cycles/deg"}


def _tan_deg(t: float) -> float:
    return math.degrees(math.atan(t))


class IniModel:
    """Paraxial model, CDP states and EI layout of a design with an ``[ini]`` section.

    Parameters
    ----------
    design : lfsim.Design
    wavelength_nm : float, optional
        Default: the design's primary wavelength.
    precision : str
    values : array, optional
        The packed parameter vector (``design.tracer().names``) to use instead of
        the design's own (an optimizer's trial point: nothing is re-validated).
    tunable_power_diopters : list of float, optional
        With ``values``: the tunable lens's power per CDP state (instead of the
        design's given or solved powers).
    """

    def __init__(self, design, wavelength_nm: float | None = None, precision: str = "float64", values=None,
                 tunable_power_diopters=None):
        if design.ini is None:
            raise DesignError(design.path or "<dict>", "ini", None, "the design has no [ini] section")
        self.design = design
        self.spec = spec = design.ini
        self.system = design.system
        self.file = design.path or "<dict>"
        self.lam = float(wavelength_nm or self.system.primary_wavelength_nm)
        self.tracer = design.tracer(precision)
        self.T = self.tracer.T
        self.arr = self.system.arrays[spec.mla]
        if values is None:
            self.values0 = np.asarray(self.system.parameter_values(self.lam), dtype=np.float64)
        else:
            self.values0 = np.array(values, dtype=np.float64).reshape(self.tracer.n_params)
        self._powers = None if tunable_power_diopters is None else [float(p) for p in tunable_power_diopters]
        self.g = float(self.values0[self.tracer.index[GAP]])
        if not math.isfinite(self.g):
            raise DesignError(self.file, "object.distance", "inf", "the display (object) must be at a finite gap")
        self._nominal = self.tracer.vector.numpy_getter(self.values0.copy())
        frames = self.tracer.frames_numpy(self.tracer.params(values=self.values0))
        self.R_vw, self.o_vw = frames[spec.viewing_window]
        self.z_mla_back = float(frames[spec.mla_surfaces[-1]][1][2])
        M, N = self.arr.m, self.arr.n
        self.m_ref, self.n_ref = M // 2, N // 2
        self.c_ref = self.lenslet_center(self.m_ref, self.n_ref)
        stop = self.system.surfaces[spec.stop]
        if stop.aperture is not None and stop.aperture.kind == "rectangular":
            self.stop_half = np.array(stop.aperture.half_width)
        elif stop.aperture is not None:
            self.stop_half = np.array([stop.aperture.radius] * 2) / math.sqrt(2.0)
        else:
            self.stop_half = 0.5 * np.array(self.arr.pitch)
        self._lenslet_maps()
        self._solve_states()

    # ------------------------------------------------------------ geometry
    def lenslet_center(self, m, n) -> np.ndarray:
        """Eq. (1): lenslet axis (x, y) on the display side (0-based m, n; arrays allowed)."""
        m, n = np.asarray(m, dtype=np.float64), np.asarray(n, dtype=np.float64)
        get = self._nominal  # the design's lattice (linear views keep it)
        return np.stack(np.broadcast_arrays(*self.tracer.vector.lenslet_centre(self.arr.name, m, n, get)), axis=-1)

    def values(self, k: int | None = None) -> np.ndarray:
        """Parameter vector of CDP state ``k`` (all states stacked when None)."""
        if k is None:
            return np.concatenate([self.values(i) for i in range(len(self.depths))])
        v = self.values0.copy()
        if self.spec.tunable is not None:
            v[self.tracer.index[f"{self.system.surfaces[self.spec.tunable].name}.power"]] = self.tl_power[k]
        return v

    # ------------------------------------------------------- linearization
    def _linearize(self, *args, **kwargs):
        """Affine map of ray states about ``base`` through surfaces first..last.

        See :meth:`_linearize_lanes`; its few lanes compile as compact kernels.
        """
        with compact_kernels():
            return self._linearize_lanes(*args, **kwargs)

    def _linearize_lanes(self, blocks: np.ndarray, base: np.ndarray, z_in: float | None, first: int, last: int,
                         frame, on_surface: bool, lenslet=None):
        """Affine map of ray states about ``base`` through surfaces first..last.

        Input: state (x, y, tan_x, tan_y) on the global plane ``z = z_in``
        (None: the display plane z = −g of each block, g = ``object.distance``).
        Output: state on the plane of ``frame`` (R, o) (or, ``on_surface``, the
        hit point on the surface in that frame). Returns ``(F0, J)`` with shapes
        (B, 4) and (B, 4, 4), B = number of parameter blocks.
        """
        tr, T = self.tracer, self.T
        nb = blocks.shape[0]
        j = dr.arange(T.UInt32, 4 * nb)
        k = j % 4
        seed = dr.zeros(T.Float, 1)
        dr.enable_grad(seed)
        # Opaque (evaluated) scalars, not literals: a kernel compiled for one design is
        # reused for another whose axis point, display gap or frames differ.
        comp = [dr.opaque(T.Float, float(base[c])) + dr.select(k == c, seed, 0.0) for c in range(4)]
        P = tr.params(values=blocks.ravel())
        if z_in is None:
            z0 = -dr.gather(T.Float, P, (j // 4) * tr.const(tr.n_params, "UInt32") + tr.index[GAP])
        else:
            z0 = dr.opaque(T.Float, float(z_in)) + 0.0 * comp[0]
        o = T.Array3(comp[0], comp[1], z0)
        d = T.Array3(comp[2], comp[3], 1.0 + 0.0 * comp[0])
        lens = None
        if lenslet is not None:
            lens = (tr.const(lenslet[0], "Int32") + dr.zeros(T.Int32, 4 * nb),
                    tr.const(lenslet[1], "Int32") + dr.zeros(T.Int32, 4 * nb))
        out = tr.trace(P, RayState(o, d), block=j // 4, lenslet=lens, first=first, last=last)
        R, og = frame
        Rt = T.Matrix3(*(dr.opaque(T.Float, float(v)) for v in R.T.ravel()))
        pl = Rt @ (out.p - T.Array3(*(dr.opaque(T.Float, float(v)) for v in og)))
        dl = Rt @ out.d
        tx, ty = dl.x / dl.z, dl.y / dl.z
        if on_surface:
            x, y = pl.x, pl.y
        else:
            x, y = pl.x - tx * pl.z, pl.y - ty * pl.z
        outs = [x, y, tx, ty]
        dr.forward_from(seed, flags=dr.ADFlag.ClearNone)  # outputs share interior nodes
        grads = [dr.grad(v) for v in outs]
        # One kernel for the status, the values and their derivatives.
        status, failed_at, *res = to_numpy(out.status, out.failed_at, *outs, *grads)
        if np.any(status != 0):
            bad = int(failed_at[np.argmax(status != 0)])
            name = Status(int(status[status != 0][0])).name.lower()
            where = self.system.surfaces[bad].name if bad >= 0 else "?"
            raise IniModelError(f"{self.file}: the axis ray of the first-order model fails "
                                f"({name}) at surface {where!r}")
        vals = np.stack([np.asarray(v, dtype=np.float64).reshape(nb, 4)[:, 0] for v in res[:4]], axis=1)
        J = np.stack([np.asarray(v, dtype=np.float64).reshape(nb, 4) for v in res[4:]], axis=1)
        return vals, J

    def _lenslet_maps(self, blocks=None):
        """Display state → stop hit (S0, JS) and → state behind the MLA (L0, JL), reference
        lenslet; for the design (stored) or for parameter ``blocks`` (B, n) (returned)."""
        spec = self.spec
        base = np.array([self.c_ref[0], self.c_ref[1], 0.0, 0.0])
        store = blocks is None
        blocks = self.values0[None, :] if store else np.asarray(blocks)
        frames = self.tracer.frames_numpy()
        R_s, o_s = frames[spec.stop]
        o_s = o_s + np.array([self.c_ref[0], self.c_ref[1], 0.0])
        S0, JS = self._linearize(blocks, base, None, 0, spec.stop, (R_s, o_s), True,
                                 (self.m_ref, self.n_ref))
        back = (np.eye(3), np.array([0.0, 0.0, self.z_mla_back]))
        L0, JL = self._linearize(blocks, base, None, 0, spec.mla_surfaces[-1], back, False,
                                 (self.m_ref, self.n_ref))
        L0 = L0 - np.array([self.c_ref[0], self.c_ref[1], 0, 0])
        if not store:
            return S0[:, :2], JS[:, :2], L0, JL
        self.S0, self.JS = S0[0, :2], JS[0, :2]
        self.L0, self.JL = L0[0], JL[0]

    def linear_views(self, values) -> list[IniModel]:
        """First-order views of the design at other parameter values, in two launches.

        ``values``: (V, n_states, n_params) parameter vectors per CDP state (the
        tunable lens's power in each). Each view is a shallow copy of this
        model whose paraxial maps (S0, JS, L0, JL, G0, JG) are re-linearized at
        those values, so :meth:`aim`, :meth:`paraxial_vw`, :meth:`ei_centers`
        and :meth:`state` answer for the changed design (for finite
        differences of first-order quantities). Frames of the stop and the
        viewing window are this model's.
        """
        import copy

        values = np.asarray(values, dtype=np.float64)
        V, nd = values.shape[:2]
        S0, JS, L0, JL = self._lenslet_maps(values[:, 0])
        G0, JG = self._group_maps(values.reshape(V * nd, -1))
        G0, JG = G0.reshape(V, nd, 4), JG.reshape(V, nd, 4, 4)
        ip = None
        if self.spec.tunable is not None:
            ip = self.tracer.index[f"{self.system.surfaces[self.spec.tunable].name}.power"]
        views = []
        for v in range(V):
            w = copy.copy(self)
            w.values0 = values[v, 0].copy()
            if ip is not None:
                w.tl_power = [float(values[v, k, ip]) for k in range(nd)]
            w.S0, w.JS, w.L0, w.JL = S0[v], JS[v], L0[v], JL[v]
            w.G0, w.JG = G0[v], JG[v]
            views.append(w)
        return views

    def _group_maps(self, blocks):
        """State behind the MLA → viewing-window state, about the system axis, per block."""
        return self._linearize(blocks, np.zeros(4), self.z_mla_back, self.spec.mla_surfaces[-1] + 1,
                               self.spec.viewing_window, (self.R_vw, self.o_vw), False)

    # ------------------------------------------------------------ CDP states
    def _depth_of(self, JG):
        """Paraxial CDP depths (D) in x and y made by group maps JG (B, 4, 4)."""
        A = JG @ self.JL  # display (s, t) → VW state, about the lenslet axis
        Tp, Tt = A[:, 0:2, 2:4], A[:, 2:4, 2:4]
        # The image of a display point is at z_CDP where r = t − h/z_CDP does not depend on the pupil.
        return 1000.0 * Tt[:, 0, 0] / Tp[:, 0, 0], 1000.0 * Tt[:, 1, 1] / Tp[:, 1, 1], Tp, Tt

    def _solve_states(self):
        spec, tr = self.spec, self.tracer
        if spec.tunable is None:
            G0, JG = self._group_maps(self.values0[None, :])
            dx, dy, _, _ = self._depth_of(JG)
            D = 0.5 * (dx[0] + dy[0])
            if not D > -1e-9:
                raise DesignError(self.file, "ini", None, f"the display is imaged to a real point behind "
                                  f"the viewing window ({D:.4g} D): no virtual CDP")
            if spec.cdp_diopters is not None and abs(spec.cdp_diopters[0] - D) > 0.01:
                raise DesignError(self.file, "ini.cdp_diopters", spec.cdp_diopters,
                                  f"the geometry puts the CDP at {D:.4f} D")
            self.depths = [float(spec.cdp_diopters[0]) if spec.cdp_diopters else max(D, 0.0)]
            self.tl_power = [None]
            self.G0, self.JG = G0, JG
            return
        self.depths = list(spec.cdp_diopters)
        name = f"{self.system.surfaces[spec.tunable].name}.power"
        ip = tr.index[name]
        nd = len(self.depths)
        target = np.array(self.depths) / 1000.0

        def residual(phi):
            blocks = np.tile(self.values0, (nd, 1))
            blocks[:, ip] = phi
            G0, JG = self._group_maps(blocks)
            _, _, Tp, Tt = self._depth_of(JG)
            res = (Tt[:, 0, 0] + Tt[:, 1, 1]) - target * (Tp[:, 0, 0] + Tp[:, 1, 1])
            return res, G0, JG

        given = self._powers if self._powers is not None else spec.tunable_power_diopters
        if given is not None:
            phi = np.array(given) / 1000.0
            _, G0, JG = residual(phi)
        else:
            # Secant iteration (exact in one step when the axis ray crosses the lens centre).
            p0 = np.full(nd, self.values0[ip])
            p1 = p0 + 1e-3
            r0, _, _ = residual(p0)
            for it in range(30):
                r1, G0, JG = residual(p1)
                moving = (p1 != p0) & (r1 != 0)
                if not np.any(moving) or np.all(np.abs(p1 - p0) < 1e-13):
                    break
                slope = np.where(moving, (r1 - r0) / np.where(moving, p1 - p0, 1.0), 1.0)
                stuck = moving & (slope == 0)
                if it == 0 and np.any(stuck):
                    raise DesignError(self.file, "ini.tunable.surface", self.system.surfaces[spec.tunable].name,
                                      "its power does not change the CDP depth")
                moving &= ~stuck  # later: the residual no longer changes at this precision (float32)
                slope = np.where(moving, slope, 1.0)
                p0, r0, p1 = p1, r1, np.where(moving, p1 - r1 / slope, p1)
            phi = p1
            _, G0, JG = residual(phi)
        lo_hi = spec.tunable_range_diopters
        if lo_hi is not None:
            # Slack: the solve's rounding (measured at the range ends: 5e-15 D in float64, 6e-6 D in float32).
            tol = 1e-9 if self.tracer.precision == "float64" else 1e-4
            for D, p in zip(self.depths, phi):
                if not lo_hi[0] - tol <= 1000 * p <= lo_hi[1] + tol:
                    raise DesignError(self.file, "ini.tunable.range_diopters", list(lo_hi),
                                      f"CDP {D:g} D needs {1000 * p:.4f} D, outside the range")
        self.tl_power = [float(p) for p in phi]
        self.G0, self.JG = G0, JG

    # --------------------------------------------------------- paraxial rays
    def affine(self, k: int, c) -> tuple[np.ndarray, np.ndarray]:
        """Viewing-window state of lenslet centre ``c`` (..., 2) in CDP state ``k``:
        ``v = b + A·(s − c, t)`` with A (4, 4) and b (..., 4)."""
        c = np.asarray(c, dtype=np.float64)
        shift = np.zeros(c.shape[:-1] + (4,))
        shift[..., :2] = c - self.c_ref
        b = self.G0[k] + (self.L0 + shift) @ self.JG[k].T
        return self.JG[k] @ self.JL, b

    def aim(self, s, c, rho):
        """Paraxial slope of the ray from display point ``s`` through stop point ``rho``·half
        of lenslet ``c`` (arrays broadcast; rho in [−1, 1]²)."""
        s, c, rho = (np.asarray(a, dtype=np.float64) for a in (s, c, rho))
        target = rho * self.stop_half - self.S0 - (s - c) @ self.JS[:, :2].T
        return target @ np.linalg.inv(self.JS[:, 2:]).T

    def paraxial_vw(self, k: int, s, c, rho):
        """Paraxial viewing-window state (..., 4) of the ray (s, c, rho) in state k."""
        s, c = np.asarray(s, dtype=np.float64), np.asarray(c, dtype=np.float64)
        t = self.aim(s, c, rho)
        A, b = self.affine(k, c)
        u = np.concatenate([s - c, t], axis=-1)
        return b + u @ A.T

    def retinal(self, state, k: int):
        """Retinal angle (tan, x and y) of viewing-window states for the eye focused on CDP k."""
        state = np.asarray(state)
        return state[..., 2:4] - state[..., 0:2] * (self.depths[k] / 1000.0)

    def ei_centers(self, k: int, m, n) -> np.ndarray:
        """Display position (..., 2) of the centre of EI (m, n) in CDP state ``k``
        (Eqs. 2 and 4, generalized): its paraxial chief ray through the
        lenslet's stop centre crosses the viewing-window centre.

        With a tunable lens inside the eyepiece group the layout depends on the
        state (Eq. 2 through z'_xp), so EIs are laid out per state."""
        c = self.lenslet_center(m, n)
        # VW position of the chief ray is affine in s: pos = a0 + As·(s − c).
        zero = np.zeros_like(c)
        p0 = self.paraxial_vw(k, c, c, zero)[..., :2]
        cols = []
        for e in np.eye(2):
            cols.append(self.paraxial_vw(k, c + e, c, zero)[..., :2] - p0)
        As = np.stack(cols, axis=-1)
        return c - np.linalg.solve(As, p0[..., None])[..., 0]

    def ei_pitch(self, k: int = 0) -> np.ndarray:
        """EI pitch on the display (x, y), Eq. (2) generalized."""
        a = self.ei_centers(k, np.array([self.m_ref, self.m_ref + 1, self.m_ref]),
                            np.array([self.n_ref, self.n_ref, self.n_ref + 1]))
        return np.array([a[1, 0] - a[0, 0], a[2, 1] - a[0, 1]])

    def display_ei(self) -> tuple[np.ndarray, np.ndarray]:
        """(EIs per axis (2,), one EI's width on the display (2,), mm): the display holds
        ``M·pixels_per_ei·pixel_pitch`` by ``N·…``."""
        count = np.array([self.arr.m, self.arr.n], dtype=np.float64)
        return count, np.array(self.spec.pixels_per_ei, dtype=np.float64) * self.spec.pixel_pitch

    def display_mismatch(self, p_ei) -> np.ndarray:
        """How many EIs a layout of EI pitch ``p_ei`` (..., 2; Eq. 2) is wider or narrower than
        the display across the array, ``M·|p_EI − px·pitch| / |p_EI|`` per axis: the outer EIs are
        cut or widened by half of it at each edge (the renderer refuses more than 1:
        :func:`lfsim.render.display.check_display_size`)."""
        count, have = self.display_ei()
        q = np.abs(np.asarray(p_ei, dtype=np.float64))
        with np.errstate(divide="ignore", invalid="ignore"):  # p_EI 0: inf, refused
            return count * np.abs(q - have) / q

    def at_wavelength(self, wavelength_nm: float) -> IniModel:
        """The same design traced at ``wavelength_nm``, the tunable lens held at this model's
        powers (an ideal lens: no colour of its own), so that the two differ by the glasses'
        dispersion only (lateral colour, the polychromatic contrast, per-channel elemental
        images)."""
        powers = [self.state(k).tunable_power_diopters for k in range(len(self.depths))]
        return IniModel(self.design, wavelength_nm=wavelength_nm, precision=self.tracer.precision,
                        tunable_power_diopters=None if any(p is None for p in powers) else powers)

    # -------------------------------------------------------------- summary
    def state(self, k: int) -> DepthState:
        """First-order data (Eqs. 2–10, generalized) of CDP state k."""
        A, _ = self.affine(k, self.c_ref)
        dx, dy, _, _ = self._depth_of(self.JG[k:k + 1])
        c = self.c_ref
        s0 = self.ei_centers(k, self.m_ref, self.n_ref)
        pei = self.ei_pitch(k)
        z = np.zeros(2)
        dv, Dv, theta_ei, pix = [], [], [], []
        for ax in range(2):
            e = np.eye(2)[ax]
            plus = self.paraxial_vw(k, s0, c, e)
            minus = self.paraxial_vw(k, s0, c, -e)
            dv.append(abs(plus[ax] - minus[ax]))
            hp = 0.5 * pei[ax]
            ep = self.paraxial_vw(k, s0 + hp * e, c, z)
            em = self.paraxial_vw(k, s0 - hp * e, c, z)
            Dv.append(abs(ep[ax] - em[ax]))
            theta_ei.append(abs(self.retinal(ep, k)[ax] - self.retinal(em, k)[ax]))
            pix.append(theta_ei[-1] / pei[ax] * self.spec.pixel_pitch)
        # Eq. (7)/(9): virtual EI centres step by delta per lenslet.
        r0 = self.retinal(self.paraxial_vw(k, s0, c, z), k)
        s1 = self.ei_centers(k, self.m_ref + 1, self.n_ref + 1)
        r1 = self.retinal(self.paraxial_vw(k, s1, self.lenslet_center(self.m_ref + 1, self.n_ref + 1), z), k)
        delta = np.abs(r1 - r0)
        M, N = self.arr.m, self.arr.n
        fov_diag = 2.0 * math.degrees(math.atan(0.5 * math.hypot(M * delta[0], N * delta[1])))
        fov = tuple(2.0 * math.degrees(math.atan(0.5 * (nl - 1) * delta[i] + 0.5 * theta_ei[i]))
                    for i, nl in enumerate((M, N)))
        pix_deg = [math.degrees(math.atan(p)) for p in pix]
        tl = self.tl_power[k]
        return DepthState(
            diopters=self.depths[k],
            tunable_power_diopters=None if tl is None else 1000.0 * tl,
            cdp_diopters_x=float(dx[0]), cdp_diopters_y=float(dy[0]),
            p_ei=tuple(float(v) for v in pei), d_v=tuple(float(v) for v in dv),
            D_v=tuple(float(v) for v in Dv),
            delta_theta_eic_deg=tuple(_tan_deg(v) for v in delta),
            theta_eic_deg=tuple(_tan_deg(v) for v in theta_ei),
            fov_deg=fov, fov_diag_deg=fov_diag,
            pixel_arcmin=tuple(60.0 * p for p in pix_deg),
            nyquist_cpd=float(1.0 / (2.0 * max(pix_deg))),
        )


def model_at_depth(design, diopters: float, wavelength_nm: float | None = None,
                   precision: str = "float64") -> IniModel:
    """An :class:`IniModel` with the single CDP state ``diopters``.

    With a tunable lens, its power is the design's given powers interpolated
    linearly in diopters when the design lists them (the powers it was
    optimized with, at best focus), else solved paraxially. Without one, the
    geometry's own depth must match (as for any design).
    """
    import copy
    from dataclasses import replace

    spec = design.ini
    if spec is None:
        raise DesignError(design.path or "<dict>", "ini", None, "the design has no [ini] section")
    D = float(diopters)
    if not (math.isfinite(D) and D >= 0.0):
        raise DesignError(design.path or "<dict>", "cdp_diopters", diopters, "expected a depth >= 0 D")
    powers = None
    if spec.tunable is not None and spec.tunable_power_diopters is not None:
        if len(spec.cdp_diopters) == 1:
            powers = [float(spec.tunable_power_diopters[0])]
        else:
            from scipy.interpolate import interp1d

            # linear in diopters, extrapolated with the end segments' slopes
            f = interp1d(spec.cdp_diopters, spec.tunable_power_diopters, fill_value="extrapolate",
                         assume_sorted=False)
            powers = [float(f(D))]
    clone = copy.copy(design)
    if spec.tunable is None:
        if spec.cdp_diopters is not None and abs(spec.cdp_diopters[0] - D) > 1e-9:
            raise DesignError(design.path or "<dict>", "cdp_diopters", D,
                              f"the design has no tunable lens: its CDP is at {spec.cdp_diopters[0]:g} D")
        clone.ini = spec
    else:
        clone.ini = replace(spec, cdp_diopters=[D], tunable_power_diopters=powers)
    model = IniModel(clone, wavelength_nm=wavelength_nm, precision=precision)
    if spec.tunable is None and abs(model.depths[0] - D) > 0.01:
        raise DesignError(design.path or "<dict>", "cdp_diopters", D,
                          f"the design has no tunable lens: its CDP is at {model.depths[0]:.4g} D")
    return model
