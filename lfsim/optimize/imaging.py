"""The merit of a conventional imaging lens (a design without ``[ini]``) as weighted residuals.

For a camera lens, a relay or an eyepiece on its own, ``lfsim optimize``
minimizes the polychromatic RMS spot at the image surface with the focal
length held, under the same thickness limits as the light-field merit:

==============  ============================================================
block           residuals
==============  ============================================================
spot            √w_q · (p_q − p_chief) per pupil ray, µm at the image surface,
                over √(fields × wavelengths): the mean square RMS spot radius
                about the primary wavelength's chief ray of each field (so
                lateral colour counts), w_q the pupil quadrature weights
efl             focal length, % from its target (``[optimize.targets]
                efl_mm``; default the start's)
thickness       centre thickness of variable glass thicknesses and air gaps
                below their minimum, µm (:mod:`lfsim.optimize.constraints`)
edge_thickness  glass elements' edge thickness at their larger clear radius
                below its minimum, µm
lost            a constant per ray lost to a clear aperture or a failed
                refraction (steps that lose rays raise the merit)
==============  ============================================================

Pupil: the paraxial entrance pupil of the current design (position and
diameter from its first-order model, :func:`lfsim.optics.sampling.field_rays`),
sampled by a polar product rule (Gauss–Legendre in ρ², equally spaced
azimuths), which integrates the RMS of a polynomial aberration exactly up to
its degree. Derivatives: one forward-mode Dr.Jit launch replicates the rays
once per variable; copy k carries the variable's seed in the surface
parameters *and* in the ray starts, whose change with the entrance pupil
(first-order) is taken by central differences; the focal length by central
differences of the first-order model. The image surface's orientation is
held (its tilts are not variables of this merit); its position drops out,
since every ray is measured from its field's chief ray.

References
----------
Kingslake, R. & Johnson, R. B., *Lens Design Fundamentals*, 2nd ed.,
Academic Press, 2010, ch. 15 (damped least squares on spot residuals).
"""

from __future__ import annotations

import math

import numpy as np

from ..design.design import Design
from ..optics.sampling import field_rays
from . import constraints
from .merit import LOST, Rows, columns

FD_STEP = 1e-6  # relative central-difference step of the first-order dependences


def polar_pupil(rings: int) -> tuple[np.ndarray, np.ndarray]:
    """Points (Q, 2) in the unit disc and weights (Q,) summing to 1.

    Gauss–Legendre in ρ² with ``rings`` nodes, ``4·rings`` equally spaced
    azimuths (offset by half a step from the axes): a product rule that
    integrates ρ^(2a)·cos(bθ) exactly for a < 2·rings and b < 4·rings.
    """
    u, wu = np.polynomial.legendre.leggauss(rings)
    rho2, w_r = 0.5 * (u + 1.0), 0.5 * wu
    n_a = 4 * rings
    th = (np.arange(n_a) + 0.5) * 2.0 * math.pi / n_a
    r = np.sqrt(rho2)[:, None]
    pts = np.stack([(r * np.cos(th)).ravel(), (r * np.sin(th)).ravel()], axis=1)
    w = (w_r[:, None] * np.full(n_a, 1.0 / n_a)).ravel()
    return pts, w


class ImagingMerit:
    """Residuals and Jacobian of the imaging merit (a solver ``Problem``).

    Parameters
    ----------
    design : Design
        The starting design (no ``[ini]``); its ``[optimize]`` section or
        ``spec`` gives variables, targets and weights.
    spec : OptimizeSpec
    cols : list of Column
        The active variables (default: all of ``spec``).
    pupil_rings : int, optional
        Rings of the pupil rule (default ``[optimize.sampling] pupil``).
    """

    def __init__(self, design: Design, spec, cols=None, stride=None, pupil_rings: int | None = None,
                 hinge_model: bool = False):
        self.design0, self.spec = design, spec
        self.hinge_model = bool(hinge_model)  # glass thickness as the lm-hinge solver's signed hinges
        self.hinges = (np.zeros(0), None)
        self.cols = list(cols) if cols is not None else columns(design, spec)
        if any(c.state is not None for c in self.cols):
            raise ValueError(f"{design.path}: tunable-lens variables need an InI design ([ini])")
        self.stride = (1, 1)
        self.tracer = design.tracer("float64")
        self.names = self.tracer.names
        self.col_index = [self.names.index(c.name) for c in self.cols]
        sysm = design.system
        self.wavelengths = list(sysm.wavelengths_nm)
        w0 = sysm.primary_wavelength_nm
        self.primary = int(np.argmin([abs(w - w0) for w in self.wavelengths]))
        from ..optics.vector import DesignVector

        vec = DesignVector(sysm)
        self.base = np.array([vec.values(w) for w in self.wavelengths])  # (W, n_params)
        self.x0 = self.base[self.primary, self.col_index].copy()
        pts, self.w_pupil = polar_pupil(int(pupil_rings or spec.pupil))
        self.rho = np.concatenate([np.zeros((1, 2)), pts])  # the chief ray first
        self.fields = list(sysm.fields)
        self.efl0 = self._starts(design)[2]  # the same (paraxial) focal length the merit evaluates
        t = spec.targets
        self.efl_target = t.efl_mm if t.efl_mm is not None and math.isfinite(t.efl_mm) else self.efl0
        if self.efl_target is None or not math.isfinite(self.efl_target):
            self.efl_target = None  # afocal start: no focal-length block
        R_img, _ = self.tracer.frames_numpy()[-1]
        self.R_img = R_img[:, :2]
        self.pairs = constraints.glass_pairs(sysm, self.names, self.base[self.primary], len(sysm.surfaces))
        self.evaluations = 0
        self._design = None  # (x bytes, Design) of the last point
        self.layout: list[tuple[str, int]] = []

    # ------------------------------------------------------------ designs
    @property
    def bounds(self):
        return (np.array([c.lower for c in self.cols]), np.array([c.upper for c in self.cols]))

    def design_at(self, x) -> Design:
        """The design with the variables set to ``x`` (validated like a file). The last
        one is kept: a damped least-squares step evaluates a trial point and then, once
        accepted, its Jacobian."""
        key = np.asarray(x, dtype=np.float64).tobytes()
        if self._design is None or self._design[0] != key:
            self._design = (key, self._build(x))
        return self._design[1]

    def _build(self, x) -> Design:
        from ..design.writer import apply_values

        raw = apply_values(self.design0.raw, {c.name: float(v) for c, v in zip(self.cols, np.asarray(x, float))})
        return Design.from_dict(raw, self.design0.path or "<dict>")

    def _values(self, x) -> np.ndarray:
        v = self.base.copy()
        v[:, self.col_index] = np.asarray(x, dtype=np.float64)
        return v

    def _starts(self, design: Design):
        """Ray starts (F, R, 3) and directions (F, R, 3) through the design's paraxial
        entrance pupil, and its focal length."""
        fo = design.first_order(method="paraxial")
        O, D = zip(*(field_rays(design.system, fo, f, self.rho) for f in self.fields))
        return np.array(O), np.array(D), fo.efl

    # ------------------------------------------------------------ residuals
    def evaluate(self, x, derivatives: bool = True):
        """(residuals (M,), Jacobian (M, K) or None, details dict)."""
        self.evaluations += 1
        x = np.asarray(x, dtype=np.float64)
        K = len(self.cols) if derivatives else 0
        O, D, efl = self._starts(self.design_at(x))
        dO = dD = None
        defl = np.zeros(K)
        if K:
            steps = FD_STEP * np.maximum(1.0, np.abs(x))
            dO, dD = np.empty((K,) + O.shape), np.empty((K,) + D.shape)
            for k in range(K):
                e = np.zeros_like(x)
                e[k] = steps[k]
                Op, Dp, fp = self._starts(self._build(x + e))  # first-order only: not kept
                Om, Dm, fm = self._starts(self._build(x - e))
                dO[k], dD[k] = (Op - Om) / (2 * steps[k]), (Dp - Dm) / (2 * steps[k])
                defl[k] = (fp - fm) / (2 * steps[k]) if efl is not None and math.isfinite(efl) else 0.0
        xy, dxy, ok = self._trace(self._values(x), O, D, dO, dD, K)
        t, w = self.spec.targets, self.spec.weights
        Fn, W, R = ok.shape
        blocks = []
        add = blocks.append
        add(("lost", (~ok).astype(np.float64) * LOST, np.zeros((ok.size, K)) if derivatives else None))
        chief_ok = ok[:, self.primary, 0]  # (F,)
        rel = xy[:, :, 1:] - xy[:, self.primary, 0][:, None, None]  # (F, W, Q, 2) mm
        use = ok[:, :, 1:] & chief_ok[:, None, None]
        scale = 1000.0 * w.spot / math.sqrt(Fn * W)
        sw = np.sqrt(self.w_pupil)[None, None, :, None]
        jac = None
        if derivatives:
            drel = dxy[:, :, 1:] - dxy[:, self.primary, 0][:, None, None]
            jac = np.where(use[..., None, None], sw[..., None] * drel * scale, 0.0)
        add(("spot", np.where(use[..., None], sw * rel * scale, 0.0), jac))
        if self.efl_target is not None and efl is not None and math.isfinite(efl):
            tgt = self.efl_target
            add(("efl", np.array([(efl - tgt) / tgt * 100.0 * w.efl]),
                 (defl / tgt * 100.0 * w.efl)[None] if derivatives else None))
        values = self._values(x)[self.primary]
        hinge = self.hinge_model
        limits = [*constraints.center_thickness(self.cols, x, self.design0.system, self.names, values, t, w, K,
                                                derivatives, signed=hinge),
                  *constraints.edge_thickness_block(self.cols, x, self.tracer, values, self.pairs, t, w, K,
                                                    derivatives, signed=hinge)]
        rows = Rows(K, derivatives, compress=False)
        for name, r, j in blocks:
            rows.add(name, r, j)
        for name, r, j in limits:  # the step model's signed hinges for lm-hinge (see IniMerit)
            (rows.add_hinge if hinge else rows.add)(name, r, j)
        r_all, J_all, details, self.layout = rows.result()
        self.hinges = rows.hinges
        self.rays = int(ok.size)
        # RMS spot radius per field (µm), polychromatic, about the primary chief ray.
        wq = self.w_pupil[None, None, :] * use
        ms = np.sum(wq * np.sum(rel ** 2, axis=-1), axis=(1, 2)) / np.maximum(np.sum(wq, axis=(1, 2)), 1e-300)
        rms = np.where(chief_ok & use.any(axis=(1, 2)), 1000.0 * np.sqrt(ms), np.nan)
        self.figures = {"rms_spot_um": rms}
        details.update(rms_spot_um=[None if not np.isfinite(v) else float(v) for v in rms],
                       rms_spot_mean_um=float(np.nanmean(rms)) if np.isfinite(rms).any() else None,
                       efl_mm=None if efl is None or not math.isfinite(efl) else float(efl),
                       rays=int(ok.size), rays_lost=int((~ok).sum()))
        self.details = details
        return r_all, J_all, details

    def _trace(self, values, O, D, dO, dD, K: int):
        """Image-surface positions (F, W, R, 2) in its frame, their derivatives
        (F, W, R, 2, K) and the ray status (F, W, R) == 0, in one launch of
        (K + 1) copies × wavelengths × rays."""
        import drjit as dr

        from ..backend import to_numpy

        tr, T = self.tracer, self.tracer.T
        Fn, R = O.shape[:2]
        W = len(self.wavelengths)
        C = K + 1
        N = Fn * W * R  # rays per copy, ordered (field, wavelength, ray)
        o = np.broadcast_to(O[:, None], (Fn, W, R, 3)).reshape(N, 3)
        d = np.broadcast_to(D[:, None], (Fn, W, R, 3)).reshape(N, 3)
        do = np.zeros((C, N, 3))
        dd = np.zeros((C, N, 3))
        mask = np.zeros((C, W, tr.n_params))
        for k in range(K):
            do[k] = np.broadcast_to(dO[k][:, None], (Fn, W, R, 3)).reshape(N, 3)
            dd[k] = np.broadcast_to(dD[k][:, None], (Fn, W, R, 3)).reshape(N, 3)
            mask[k, :, self.col_index[k]] = 1.0
        seed = dr.opaque(T.Float, 0.0, 1)  # opaque: a literal would be widened in place by its first use
        if K:
            dr.enable_grad(seed)
        P = T.Float(np.tile(values.ravel(), C)) + seed * T.Float(mask.ravel())
        lanes = C * N
        oo = np.tile(o, (C, 1))
        dirs = np.tile(d, (C, 1))
        rays = tr.rays(oo, dirs)
        if K:
            g = tr.rays(do.reshape(-1, 3), dd.reshape(-1, 3))
            rays.p = rays.p + seed * g.p
            rays.d = rays.d + seed * g.d
        j = np.arange(lanes)
        w_of = (j % N) // R % W
        block = T.UInt32(((j // N) * W + w_of).astype(np.uint32))
        out = tr.trace(P, rays, block=block)
        if K:
            dr.forward_from(seed)
            st, p, gp = to_numpy(out.status, out.p, dr.grad(out.p))
        else:
            st, p = to_numpy(out.status, out.p)
        p = np.asarray(p, dtype=np.float64)
        xy = (p[:N] @ self.R_img).reshape(Fn, W, R, 2)
        ok = (np.asarray(st)[:N] == 0).reshape(Fn, W, R)
        dxy = None
        if K:
            gp = np.asarray(gp, dtype=np.float64).reshape(C, N, 3)[:K]
            dxy = np.moveaxis(gp @ self.R_img, 0, -1).reshape(Fn, W, R, 2, K)
        return xy, dxy, ok

    # Problem protocol
    def residuals(self, x) -> np.ndarray:
        return self.evaluate(x, derivatives=False)[0]

    def jacobian(self, x):
        r, J, _ = self.evaluate(x, derivatives=True)
        return r, J

    @staticmethod
    def describe(details: dict) -> str:
        """One line of the evaluation's figures for the run's log."""
        rms = details.get("rms_spot_mean_um")
        efl = details.get("efl_mm")
        return (f"RMS spot {'undefined' if rms is None else f'{rms:.3f} µm'} (mean over fields), "
                f"EFL {'undefined' if efl is None else f'{efl:.4f} mm'}")
