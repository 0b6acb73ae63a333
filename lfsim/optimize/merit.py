"""The light-field merit of an InI-HMD design (Section 4) as weighted residuals.

The design variables ``x`` (names from the design's parameter table, plus
the tunable lens's power per CDP state) go into the packed parameter vector
of the start's InI model, whose first-order maps are re-linearized, and fused
traces carry every sampled sub-system (lenslet × CDP depth) × field × pupil
ray (:func:`lfsim.ini.subsystems.trace_rays_jacobian`), in chunks reduced
straight to residual rows (:class:`Rows`). The merit is the sum
of squares of the residuals below; each block is scaled so that a residual of
1 is "one unit of trouble":

============  ==============================================================
block         residuals
============  ==============================================================
spot          √w_j · (r_j − r̄) per Gauss–Legendre pupil ray, arcmin, over
              √(sub-systems × fields): the weighted mean square RMS spot
              (retinal tangents r = t − h·D/1000 about the CDP, as `analyze`)
spot_axis_max 10 × the excess of the RMS spot along x or y of a sub-system
              and field over ``spot_axis_max_arcmin`` (a contrast floor)
gd            Eq. (11) chief-ray error |r − r_par| in degrees (mean part),
              plus 10 × its excess over the GD target per sub-system, and
              10 × the excess of the mean GD over ``gd_mean_deg`` (the mean
              over the whole display: sampled lenslets weighted by the
              lenslets nearest to them)
pa            Eq. (12) marginal-ray footprint errors |v − v′|/(√2 d_v) (mean
              part); ``pa_hinge``: 10 × each field's PA over its target
distortion    local distortion of each elemental image beyond its target
crosstalk     marginal and pupil rays beyond (½ − margin) of the pitch on
              every MLA surface, µm
aperture      pupil rays beyond a clear aperture of the relay or eyepiece
              (less ``aperture_margin_mm``), µm (weighted like crosstalk; the
              analysis vignettes rays beyond the aperture itself)
efl           relay–eyepiece focal length per CDP state, % from its target
fov           full FOV per CDP state and axis, % from ``fov_deg``
pixel         one display pixel seen from the window per CDP state and axis, % from ``pixel_arcmin``
display       the EI layout (Eq. 2) wider or narrower than the display across the array, per CDP
              state and axis, beyond ``display_mismatch_max`` EIs, % of one EI (a hinge)
footprint     the footprint width d_v of a view on the viewing window (Eq. 5, the mean of its x
              and y widths, PA's reference) per CDP state beyond ``footprint_max_mm``, % of the
              limit (a hinge): pupil / d_v views fall in the eye pupil
thickness     centre thickness of glass / air gaps below their minimum, and
              edge thickness of glass elements at their clear radius, µm
package       the mechanical package (:mod:`lfsim.ini.package`) beyond its limits:
              track, extents of the optics and of the prism, eye relief, the
              relay's clear diameters, the rays through the tunable lens, µm
prism_        a prism's thickness between opposite faces below
thickness     ``min_prism_thickness`` at the faces' aperture grids, µm
              (:mod:`lfsim.optics.solids`)
tir           incidence below the critical angle + margin on TIR surfaces, °
colour        lateral colour (weight ``colour``, 0 by default: off): the
              retinal-tangent difference of each field's chief rays at the
              design's shortest and longest wavelengths (the same display
              point, the tunable lens at the primary's powers), arcmin over
              √(sub-systems × fields); ``colour_max``: 10 × its excess over
              ``lateral_colour_max_arcmin``. The tangent difference is within
              1/cos² of the field angle of `analyze`'s ``lateral_colour`` angle
lost          a ray lost to a failed refraction or intersection: a constant
              (steps that lose rays raise the merit and are rejected)
============  ==============================================================

Derivatives: the ray blocks are exact forward-mode Dr.Jit derivatives with
the re-aiming of every ray included; the paraxial references of GD and PA
and the EFL use the current design's first-order model, whose own change
(the display layout, the paraxial chief and marginal rays, d_v, the EFL) is
differentiated by central differences of the first-order maps; the prism
thickness by central differences of the geometry:
the package figures by central differences over the variables that move or
bend a surface (thicknesses, positions, tilts, curvatures), and only while a
package limit is exceeded;
the residuals themselves are always exact, so a damped least-squares step
is accepted only when the true merit falls.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from ..design.design import Design
from ..design.loader import curvature_limit
from ..ini.model import IniModel
from ..ini.subsystems import Subsystems, field_grid, sample, trace_rays_jacobian
from ..ini.views import StackedViews
from ..metrics import distortion, footprint, pupil, spot
from ..metrics.spot import ARCMIN
from ..optics.solids import prism_thickness, prisms
from . import constraints

LOST = 10.0  # residual of a lost ray (arcmin-equivalent)
#: Ray copies (rays × (variables + 2)) per launch of the merit's Jacobian: sub-systems are
#: traced and reduced to residual rows in chunks of this size, which bounds the memory.
MERIT_RAY_COPIES = 400_000
PRISM_POINTS = 9  # sample points per axis of a prism face's clear aperture (thickness)
DEG = 180.0 / math.pi
#: Parameter kinds that move or bend a surface: the package figures' variables.
_GEOMETRIC = {"thickness", "position_x", "position_y", "position_z", "tilt_x", "tilt_y", "tilt_z",
              "decenter_x", "decenter_y", "curvature"}


@dataclass
class Column:
    """One optimization variable: a parameter-table entry, or the tunable
    lens's power in one CDP state (``state`` set; value in diopters)."""

    name: str
    state: int | None
    lower: float
    upper: float

    @property
    def label(self) -> str:
        return self.name if self.state is None else f"tunable[{self.state}]"


@dataclass
class _Sample:
    """The traced rays of one merit evaluation, shared by its residual blocks.

    Shapes: S sampled sub-systems, F fields, R rays per field (chief, four
    marginal, the Gauss–Legendre pupil), K columns. ``r`` are retinal tangents
    about the CDP (S, F, R, 2), ``pos`` viewing-window positions, ``surf`` and
    ``cos_in`` the recorded hits (MLA surfaces, TIR surfaces, clear apertures in
    that order); the ``d*`` arrays are their derivatives (…, K).
    """

    model: IniModel
    x: np.ndarray
    derivatives: bool
    K: int
    subs: object
    ref: dict
    S: int
    F: int
    R: int
    S_all: int
    dense: bool
    ok: np.ndarray
    pos: np.ndarray
    r: np.ndarray
    surf: np.ndarray
    cos_in: np.ndarray
    nmla: int
    tirs: list
    apertures: list
    dr: np.ndarray | None = None
    dpos: np.ndarray | None = None
    dsurf: np.ndarray | None = None
    dcos: np.ndarray | None = None
    dpar_c: np.ndarray | None = None
    dpar_m: np.ndarray | None = None
    dd_v: np.ndarray | None = None
    defl: np.ndarray | None = None
    dfov: np.ndarray | None = None
    dpixel: np.ndarray | None = None
    dei_pitch: np.ndarray | None = None
    figures: dict = field(default_factory=dict)


class Rows:
    """Residual rows accumulated block by block (and chunk by chunk).

    ``add(name, residuals, jacobian)`` appends a block's rows; entries that are
    not finite count as 0 (no NaN reaches a solver). With ``compress`` the
    rows whose residual and Jacobian are both 0 are dropped as they come (an
    inactive hinge, a ray that has no derivative and no error): they add
    nothing to the merit, to ``JᵀJ`` or to ``Jᵀr``, so the damped least-squares
    step is the same. ``result()`` gives (residuals (M,), Jacobian (M, K) or
    None, the sum of squares per block, [(name, rows)]).
    """

    def __init__(self, K: int, derivatives: bool, compress: bool = True):
        self.K, self.derivatives, self.compress = K, derivatives, compress
        self.res, self.jac, self.sums, self.count = [], [], {}, {}
        self.h_g, self.h_j, self.h_count = [], [], {}

    def add(self, name: str, r, j) -> None:
        r = np.asarray(r, dtype=np.float64).ravel()
        r = np.where(np.isfinite(r), r, 0.0)
        if self.derivatives:
            j = np.asarray(j, dtype=np.float64).reshape(-1, self.K)
            j = np.where(np.isfinite(j), j, 0.0)
        if self.compress:
            keep = r != 0.0
            if self.derivatives:
                keep |= np.any(j != 0.0, axis=1)
            if not keep.all():
                r = r[keep]
                j = j[keep] if self.derivatives else j
        self.res.append(r)
        if self.derivatives:
            self.jac.append(j)
        self.sums[name] = self.sums.get(name, 0.0) + float(r @ r)
        self.count[name] = self.count.get(name, 0) + r.size

    def add_hinge(self, name: str, g, j) -> None:
        """A constraint block in the step model's own form: ``g`` the signed excess of each
        row over its limit (residual ``max(0, g)``), ``j`` its Jacobian whether or not the
        limit holds now. The rows go to the end of the residual vector, every one kept
        (:meth:`result`), and ``(g, j)`` to :attr:`hinges`."""
        g = np.asarray(g, dtype=np.float64).ravel()
        g = np.where(np.isfinite(g), g, -np.inf)  # not measurable: no residual, no pull
        self.h_g.append(g)
        if self.derivatives:
            j = np.asarray(j, dtype=np.float64).reshape(-1, self.K)
            self.h_j.append(np.where(np.isfinite(j) & np.isfinite(g)[:, None], j, 0.0))
        r = np.maximum(g, 0.0)
        self.sums[name] = self.sums.get(name, 0.0) + float(r @ r)
        self.h_count[name] = self.h_count.get(name, 0) + r.size

    @property
    def hinges(self):
        """``(g (H,), G (H, K) or None)`` of the :meth:`add_hinge` rows."""
        g = np.concatenate(self.h_g) if self.h_g else np.zeros(0)
        G = (np.concatenate(self.h_j) if self.h_j else np.zeros((0, self.K))) if self.derivatives else None
        return g, G

    def result(self):
        r = np.concatenate(self.res) if self.res else np.zeros(0)
        J = (np.concatenate(self.jac) if self.jac else np.zeros((0, self.K))) if self.derivatives else None
        layout = list(self.count.items())
        if self.h_g:  # hinge rows last, every one (their count is fixed): max(0, g), G where g > 0
            g, G = self.hinges
            r = np.concatenate([r, np.maximum(g, 0.0)])
            if self.derivatives:
                J = np.concatenate([J, np.where((g > 0.0)[:, None], G, 0.0)])
            layout += list(self.h_count.items())
        return r, J, dict(self.sums), layout


def _hinge(st, over, excess, jac):
    """Rows of a hinge block: ``excess`` where ``over`` (else 0) and ``jac(index)``, the
    Jacobian rows of the entries at ``index``. Dense: every entry (``index`` = ``...``);
    otherwise only the entries over their limit, gathered (the others are 0 rows)."""
    if st.dense:
        r = np.where(over, excess, 0.0)
        return r, (np.where(over[..., None], jac(...), 0.0) if st.derivatives else None)
    ix = np.nonzero(over)
    return excess[ix], (jac(ix) if st.derivatives else None)


def columns(design: Design, spec) -> list[Column]:
    """Expand the ``[optimize]`` variables into columns ("tunable" → one per state)."""
    out = []
    ini = design.ini
    for v in spec.variables:
        if v.name == "tunable":
            tl = design.system.surfaces[ini.tunable].name
            for k in range(len(ini.cdp_diopters)):
                out.append(Column(f"{tl}.power", k, v.lower, v.upper))
        else:
            lo, hi = v.lower, v.upper
            surf, _, key = v.name.partition(".")
            if key == "curvature":  # the surface must keep reaching its clear aperture (the loader's rule)
                names = [s.name for s in design.system.surfaces]
                if surf in names:
                    lim = curvature_limit(design.system.surfaces, names.index(surf), design.system.arrays)
                    lo, hi = max(lo, -lim * (1.0 - 1e-9)), min(hi, lim * (1.0 - 1e-9))
            out.append(Column(v.name, None, lo, hi))
    return out


def _retinal(J, shape, D, K: int, derivatives: bool, dsx=None):
    """``(pos, r, dpos, dr)`` of traced rays ``J`` reshaped to ``shape``: viewing-window
    positions and retinal tangents ``r = t − h·D/1000`` (``D`` broadcasts against ``shape``),
    with their derivatives (…, K) when ``derivatives``; ``dsx`` (shape + (2, K)): the
    display-point derivatives to chain in numpy (the dense evaluation), else None."""
    pos = J.pos.reshape(shape + (2,))
    dirs = J.dir.reshape(shape + (3,))
    slope = dirs[..., :2] / dirs[..., 2:3]
    r = slope - pos * (D[..., None] / 1000.0)
    if not derivatives:
        return pos, r, None, None
    dpos = J.d_pos.reshape(shape + (2, K))
    ddir = J.d_dir.reshape(shape + (3, K))
    if dsx is not None:
        dpos = dpos + np.einsum("...ab,...bk->...ak", J.ds_pos.reshape(shape + (2, 2)), dsx)
        ddir = ddir + np.einsum("...ab,...bk->...ak", J.ds_dir.reshape(shape + (3, 2)), dsx)
    dslope = (ddir[..., :2, :] - slope[..., None] * ddir[..., 2:3, :]) / dirs[..., 2:3, None]
    return pos, r, dpos, dslope - dpos * (D[..., None, None] / 1000.0)


class IniMerit:
    """Residuals and Jacobian of the light-field merit (a solver ``Problem``).

    Parameters
    ----------
    design : Design
        The starting design (with ``[ini]``; its ``[optimize]`` section or
        ``spec`` gives variables, targets and weights).
    spec : OptimizeSpec
    cols : list of Column
        The active variables (default: all of ``spec``).
    stride : (int, int), optional
        Lenslet sampling (default: ``spec.stride``; (1, 1) = all lenslets).
    """

    def __init__(self, design: Design, spec, cols: list[Column] | None = None, stride=None,
                 fields: int | None = None, pupil_nodes: int | None = None, efl_target=None,
                 hinge_model: bool = False):
        if design.ini is None:
            raise ValueError(f"{design.path}: the design has no [ini] section")
        self.design0 = design
        self.spec = spec
        #: The mechanical constraints (glass and air thickness, prism thickness, package) as
        #: signed hinges with their Jacobian at every row, whether or not the limit holds
        #: (:meth:`Rows.add_hinge`), for the ``lm-hinge`` solver's step model.
        self.hinge_model = bool(hinge_model)
        self.hinges = (np.zeros(0), None)
        self.cols = list(cols) if cols is not None else columns(design, spec)
        self.stride = tuple(stride or spec.stride)
        self.fields = int(fields or spec.fields)
        self.nodes = int(pupil_nodes or spec.pupil)
        model0 = IniModel(design)
        self.model0 = model0
        names = model0.tracer.names
        self.x0 = np.array([1000.0 * model0.tl_power[c.state] if c.state is not None
                            else model0.values0[names.index(c.name)] for c in self.cols])
        t = spec.targets
        self.efl0 = self._references(model0)[1]["efl"]
        if efl_target is not None:  # e.g. an earlier stage's start, so that stages do not drift
            self.efl_target = np.array(efl_target, dtype=np.float64).reshape(self.efl0.shape)
        elif t.efl_mm is not None and math.isfinite(t.efl_mm):
            self.efl_target = np.full_like(self.efl0, t.efl_mm)
        else:
            self.efl_target = self.efl0.copy()
        self.details: dict = {}
        self.layout: list[tuple[str, int]] = []
        self.rays = 0
        gl, wgl = pupil.gauss_legendre_square(self.nodes)
        self.rho = np.concatenate([np.zeros((1, 2)), pupil.MARGINAL, gl])
        self.w_gl = wgl
        self.sl_marg = slice(1, 5)
        self.sl_gl = slice(5, 5 + len(gl))
        self.evaluations = 0
        self._has_prism = bool(prisms(design.system))
        self._model = None  # (x bytes, IniModel) of the last design built
        self._colour_models = None  # (x bytes, [IniModel, IniModel]) at the colour wavelengths
        waves = sorted(float(w) for w in design.system.wavelengths_nm)
        self.colour_wavelengths = (waves[0], waves[-1]) if waves[0] < waves[-1] else None
        if spec.weights.colour > 0 and self.colour_wavelengths is None:
            raise ValueError(f"{design.path}: optimize.weights.colour = {spec.weights.colour:g} needs two or "
                             f"more [system] wavelengths_nm (the design has {waves})")
        # The tunable lens held at the primary's powers: solved again at 486 nm, a start's 3 D
        # state can need a power outside the lens's range and refuse the design.
        self._colour0 = ([model0.at_wavelength(w) for w in self.colour_wavelengths]
                         if spec.weights.colour > 0 else None)

    # ------------------------------------------------------------ designs
    @property
    def bounds(self):
        return (np.array([c.lower for c in self.cols]), np.array([c.upper for c in self.cols]))

    def _powers(self, x):
        """The tunable lens's power per CDP state (D) at ``x``: the start's where it is not a
        variable. Held, not solved again for each design (a design file without
        ``power_diopters`` has its powers solved for the CDP depths when it loads): the
        merit's derivatives hold it, and the written design says what the merit saw. None
        without a tunable lens."""
        if self.design0.ini.tunable is None:
            return None
        powers = [1000.0 * p for p in self.model0.tl_power]
        for c, v in zip(self.cols, x):
            if c.state is not None:
                powers[c.state] = float(v)
        return powers

    def design_at(self, x) -> Design:
        """The design with the variables set to ``x`` (validated like a file)."""
        from ..design.writer import apply_values

        x = np.asarray(x, dtype=np.float64)
        values = {c.name: float(v) for c, v in zip(self.cols, x) if c.state is None}
        raw = apply_values(self.design0.raw, values, tunable_power_diopters=self._powers(x))
        return Design.from_dict(raw, self.design0.path or "<dict>")

    def model_at(self, x) -> IniModel:
        """The InI model at ``x``; the last one is kept, since a damped least-squares
        step evaluates the residuals at a trial point and then, once accepted, the
        Jacobian at the same point.

        The variables go straight into the packed parameter vector of the start's
        model (its tracer and kernels are reused; nothing is written or re-validated),
        except for a lenslet array's pitch, which the model also reads from the
        array's table (then the design is rebuilt, :meth:`design_at`)."""
        key = np.asarray(x, dtype=np.float64).tobytes()
        if self._model is None or self._model[0] != key:
            self._model = (key, self._build_model(np.asarray(x, dtype=np.float64)))
        return self._model[1]

    def _build_model(self, x, base: IniModel | None = None, powers=None) -> IniModel:
        """The model at ``x`` at ``base``'s wavelength (default the start's model), the tunable
        lens at ``powers`` (diopters; default the variables', else solved)."""
        m0 = self.model0 if base is None else base
        powers = self._powers(x) if powers is None else powers
        arrays = self.design0.system.arrays
        if any(c.state is None and c.name.split(".")[0] in arrays for c in self.cols):
            return IniModel(self.design_at(x), wavelength_nm=m0.lam, tunable_power_diopters=powers)
        v = m0.values0.copy()
        for c, val in zip(self.cols, x):
            if c.state is None:
                v[m0.tracer.index[c.name]] = val
        return IniModel(self.design0, wavelength_nm=m0.lam, values=v, tunable_power_diopters=powers)

    def colour_models_at(self, x) -> list[IniModel]:
        """The InI models at ``x`` for the shortest and longest wavelengths (the last pair is
        kept), their tunable lens at the primary model's powers."""
        x = np.asarray(x, dtype=np.float64)
        key = x.tobytes()
        if self._colour_models is None or self._colour_models[0] != key:
            primary = self.model_at(x)
            powers = None if primary.tl_power[0] is None else [1000.0 * p for p in primary.tl_power]
            self._colour_models = (key, [self._build_model(x, m0, powers) for m0 in self._colour0])
        return self._colour_models[1]

    # ------------------------------------------------------------ pieces
    def _subs(self, model: IniModel):
        return sample(model, stride=self.stride, symmetry="none",
                      fields=field_grid(self.fields, model.spec.field_fraction))

    def _references(self, model: IniModel):
        """The sampled sub-systems and their first-order references (:mod:`lfsim.ini.views`):
        display points (S, F, 2), paraxial retinal tangents of the chief rays (S, F, 2),
        paraxial VW positions of the marginal rays (S, F, 4, 2), footprint widths d_v
        (S,), EFL per state."""
        subs = self._subs(model)
        ref = StackedViews(model, [model]).references(subs, display=subs.display[None])
        return subs, {key: v[0] for key, v in ref.items()}

    def _reference_derivatives(self, model: IniModel, x, subs=None):
        """Central differences (K columns) of :meth:`_references` from first-order views,
        all 2K views in two launches and one stacked evaluation."""
        nd = len(model.depths)
        names = model.tracer.names
        base = np.array([model.values(k) for k in range(nd)])
        steps = np.array([1e-6 * max(1.0, abs(v)) for v in np.asarray(x, dtype=np.float64)])
        vals = []
        for c, h in zip(self.cols, steps):
            for sgn in (1.0, -1.0):
                b = base.copy()
                if c.state is None:
                    b[:, names.index(c.name)] += sgn * h
                else:
                    b[c.state, names.index(c.name)] += sgn * h / 1000.0
                vals.append(b)
        if not vals:
            return {}
        subs = subs if subs is not None else self._subs(model)
        ref = StackedViews(model, model.linear_views(np.array(vals))).references(subs)
        return {key: np.moveaxis(v[0::2] - v[1::2], 0, -1) / (2.0 * steps) for key, v in ref.items()}

    @staticmethod
    def _grid_weights(model: IniModel, subs) -> np.ndarray:
        """(S,) the number of the array's lenslets nearest to each sampled one (ties
        shared), so that a weighted mean over the sample estimates the mean over
        every lenslet of the display; 1 for every sub-system at stride 1."""
        def axis(count, used):
            used = np.unique(used)
            d = np.abs(np.arange(count)[:, None] - used[None, :])
            near = d == d.min(axis=1, keepdims=True)
            share = (near / near.sum(axis=1, keepdims=True)).sum(axis=0)
            return dict(zip(used.tolist(), share))

        wx, wy = axis(model.arr.m, subs.m), axis(model.arr.n, subs.n)
        return np.array([wx[int(a)] * wy[int(b)] for a, b in zip(subs.m, subs.n)])

    def _rays(self, model: IniModel, subs, derivatives: bool, ds=None, rho=None, record=None):
        """Trace ``subs`` × fields × pupil points ``rho`` (default the merit's) with the
        Jacobian; ``record`` (default :meth:`_record`): the surfaces whose hits come back."""
        rho = self.rho if rho is None else rho
        S, F, R = len(subs), subs.display.shape[1], len(rho)
        shape = (S, F, R)
        s = np.broadcast_to(subs.display[:, :, None, :], shape + (2,)).reshape(-1, 2)
        rho = np.broadcast_to(rho[None, None], shape + (2,)).reshape(-1, 2)
        m = np.broadcast_to(subs.m[:, None, None], shape).ravel()
        n = np.broadcast_to(subs.n[:, None, None], shape).ravel()
        k = np.broadcast_to(subs.k[:, None, None], shape).ravel()
        own = record is None
        record = self._record(model) if own else record
        cols = [(c.name, c.state) for c in self.cols]
        # tunable-lens columns: the tracer's power is in 1/mm, the variable in diopters
        conv = np.array([1e-3 if c.state is not None else 1.0 for c in self.cols])
        if ds is not None:  # lean: the chain rule, the re-aiming and the units inside the trace
            J = trace_rays_jacobian(model, s, m, n, rho, k, cols, record=record, derivatives=derivatives,
                                    ds=ds / conv, max_ray_copies=MERIT_RAY_COPIES,
                                    select=self._select(model) if own else None, column_scale=conv)
        else:
            J = trace_rays_jacobian(model, s, m, n, rho, k, cols, record=record, derivatives=derivatives)
            if derivatives:
                J.d_pos, J.d_dir, J.d_surf, J.d_cos_in = (J.d_pos * conv, J.d_dir * conv, J.d_surf * conv,
                                                          J.d_cos_in * conv)
        return shape, J

    def _record(self, model: IniModel) -> list[int]:
        """Surfaces whose hits the merit needs: MLA (crosstalk), TIR, clear apertures."""
        return self._crosstalk_surfaces(model) + self._tir_surfaces(model) + self._aperture_surfaces(model)

    @staticmethod
    def _aperture_surfaces(model: IniModel) -> list[int]:
        """Surfaces of the display path with a clear aperture (outside the lenslet array)."""
        last = model.spec.viewing_window
        return [i for i, s in enumerate(model.system.surfaces[:last])
                if s.aperture is not None and s.array is None and s.interaction != "break"]

    @staticmethod
    def _crosstalk_surfaces(model: IniModel) -> list[int]:
        """MLA surfaces other than the stop (on the stop the pupil edge is the cell edge)."""
        return [i for i in model.spec.mla_surfaces if i != model.spec.stop]

    @staticmethod
    def _tir_surfaces(model: IniModel) -> list[int]:
        last = model.spec.viewing_window
        return [i for i, s in enumerate(model.system.surfaces[:last + 1]) if s.interaction == "tir"]

    # ------------------------------------------------------------ residuals
    def evaluate(self, x, derivatives: bool = True, dense: bool = False):
        """(residuals (M,), Jacobian (M, K) or None, details dict).

        The sub-systems are traced and reduced to residual rows in chunks of at
        most :data:`MERIT_RAY_COPIES` ray copies, and rows that are 0 with a 0
        Jacobian (inactive hinges) are dropped, so memory is bounded by the
        chunk and by the active rows (:class:`Rows`). ``dense``: one chunk, every
        row, and the re-aiming and display-layout chain rule in numpy (the
        reference the lean evaluation is tested against; same merit, ``JᵀJ``
        and ``Jᵀr``).
        """
        self.evaluations += 1
        x = np.asarray(x, dtype=np.float64)
        model = self.model_at(x)
        K = len(self.cols)
        subs, ref = self._references(model)
        dref = self._reference_derivatives(model, x, subs) if derivatives and K else {}
        S, F, R = len(subs), subs.display.shape[1], len(self.rho)
        per = S if dense else max(1, MERIT_RAY_COPIES // ((K + 2 if derivatives else 1) * F * R))
        rows = Rows(K, derivatives, compress=not dense)
        parts = []
        for a in range(0, S, per):
            part = slice(a, min(S, a + per))
            st = self._sample(model, x, subs, ref, dref, part, derivatives, dense)
            for block in (self._lost, self._spot, self._gd, self._pa, self._distortion, self._recorded):
                for name, r, j in block(st):
                    rows.add(name, r, j)
            if self._colour0 is not None:
                for name, r, j in self._colour(st, dref, part):
                    rows.add(name, r, j)
            parts.append(st.figures)
        fig = {key: np.concatenate([p_[key] for p_ in parts]) for key in parts[0]}
        st.figures = fig
        gw = self._grid_weights(model, subs)
        for name, r, j in self._gd_mean(st, gw):
            rows.add(name, r, j)
        for block in (self._efl, self._fov, self._pixel):
            for name, r, j in block(st):
                rows.add(name, r, j)
        def footprint_block(_st):
            return self._footprint(subs, ref, dref, derivatives, K)

        for block in (self._thickness, self._edge_thickness, self._prism_thickness_block, self._package,
                      self._display, footprint_block):
            for name, r, j in block(st):
                if self.hinge_model:  # signed excess with its Jacobian everywhere (the step model's)
                    rows.add_hinge(name, r, j)
                else:
                    rows.add(name, r, j)
        r_all, J_all, details, self.layout = rows.result()
        #: The constraint rows of the last evaluation in the step model's form, the last
        #: ``len(g)`` entries of the residuals (``hinge_model``; else empty): see :meth:`Rows.add_hinge`.
        self.hinges = rows.hinges
        self.rays = S * F * R
        okc, pa_ok, spot_ok = fig["gd_ok"], fig["pa_ok"], fig["spot_ok"]
        gd, pa_f, rms = fig["gd"], fig["pa"], fig["rms"]
        #: The last evaluation's figures per sampled sub-system (S) and field (F), as
        #: `lfsim analyze` defines them (metrics.distortion, .footprint, .spot).
        self.figures = {"subs": subs, "gd_deg": np.where(okc, gd, np.nan),
                        "pa": np.where(pa_ok, pa_f, np.nan),
                        "rms_spot_arcmin": np.where(spot_ok, rms * ARCMIN, np.nan)}
        details.update(gd_max_deg=float(np.max(gd[okc])) if okc.any() else None,
                       pa_max=float(np.max(pa_f[pa_ok])) if pa_ok.any() else None,
                       rms_spot_mean_arcmin=float(np.mean(rms[spot_ok]) * ARCMIN) if spot_ok.any() else None,
                       gd_mean_deg=float(gw[okc] @ gd[okc] / gw[okc].sum()) if okc.any() else None,
                       **self._colour_details(fig),
                       rays=self.rays, rays_lost=int(fig["lost"].sum()),
                       efl_mm=[float(v) for v in ref["efl"]], fov_deg=ref["fov"].tolist(),
                       pixel_arcmin=ref["pixel"].tolist(),
                       display_mismatch_ei=model.display_mismatch(ref["ei_pitch"]).tolist(),
                       footprint_mm=self._footprint_widths(subs, ref)[0].tolist())
        self.details = details
        return r_all, J_all, details

    def _sample(self, model, x, subs, ref, dref, sl: slice, derivatives: bool, dense: bool) -> _Sample:
        """Trace the sampled rays of sub-systems ``sl`` at ``x``: their retinal tangents,
        VW positions and recorded hits, with total derivatives (the display layout's
        change included)."""
        K = len(self.cols)
        part = Subsystems(subs.m[sl], subs.n[sl], subs.k[sl], subs.fields, subs.center[sl], subs.display[sl])
        S, F, R = len(part), part.display.shape[1], len(self.rho)
        ds = None
        if derivatives:  # rays move with the display layout too: d/dx += ∂/∂s · ds/dx
            dd = dref["display"][sl] if dref else np.zeros((S, F, 2, K))
            ds = np.broadcast_to(dd[:, :, None], (S, F, R, 2, K)).reshape(-1, 2, K)
        (S, F, R), J = self._rays(model, part, derivatives, None if dense else ds)
        ok = (J.status == 0).reshape(S, F, R)
        D = np.array(model.depths)[part.k][:, None, None]
        dsx = ds.reshape(S, F, R, 2, K) if dense and derivatives else None
        pos, r, dpos, dr = _retinal(J, (S, F, R), D, K, derivatives, dsx)
        nrec = J.surf.shape[1]
        per_state = ("efl", "fov", "pixel", "ei_pitch")  # references per CDP state, not per sub-system
        cut = {key: (v if key in per_state else v[sl]) for key, v in ref.items()}
        st = _Sample(model=model, x=x, derivatives=derivatives, K=K, subs=part, ref=cut, S=S, F=F, R=R,
                     S_all=len(subs), dense=dense, ok=ok, pos=pos, r=r, surf=J.surf.reshape(S, F, R, nrec, 2),
                     cos_in=J.cos_in.reshape(S, F, R, nrec), nmla=len(self._crosstalk_surfaces(model)),
                     tirs=self._tir_surfaces(model), apertures=self._aperture_surfaces(model))
        st.figures["lost"] = (~ok).reshape(S, -1).sum(axis=1)
        if derivatives:
            dsurf = J.d_surf.reshape(S, F, R, nrec, 2, K)
            dcos = J.d_cos_in.reshape(S, F, R, nrec, K)
            if dense:  # the chain rule in numpy, from the display-point derivatives (dsx above)
                dsurf = dsurf + np.einsum("sfrjab,sfrbk->sfrjak", J.ds_surf.reshape(S, F, R, nrec, 2, 2), dsx)
                dcos = dcos + np.einsum("sfrjb,sfrbk->sfrjk", J.ds_cos_in.reshape(S, F, R, nrec, 2), dsx)
            st.dpos, st.dsurf, st.dcos, st.dr = dpos, dsurf, dcos, dr
            st.dpar_c = dref["par_c"][sl] if dref else np.zeros((S, F, 2, K))
            st.dpar_m = dref["par_m"][sl] if dref else np.zeros((S, F, 4, 2, K))
            st.dd_v = dref["d_v"][sl] if dref else np.zeros((S, K))
            st.defl, st.dfov, st.dpixel = dref.get("efl"), dref.get("fov"), dref.get("pixel")
            st.dei_pitch = dref.get("ei_pitch")
        else:  # no columns: the derivative variants of lfsim.metrics run with K = 0
            st.dr, st.dpos = np.zeros(r.shape + (0,)), np.zeros(pos.shape + (0,))
            st.dpar_c, st.dpar_m, st.dd_v = np.zeros((S, F, 2, 0)), np.zeros((S, F, 4, 2, 0)), np.zeros((S, 0))
        return st

    # One method per residual block: each yields (name, residuals, Jacobian rows or None).
    def _lost(self, st: _Sample):
        """A constant per ray lost to a failed refraction or intersection (no derivative)."""
        lost = (~st.ok).reshape(-1).astype(np.float64) * LOST
        yield "lost", lost, np.zeros((lost.size, st.K)) if st.derivatives else None

    def _spot(self, st: _Sample):
        """RMS spot over the Gauss–Legendre pupil: the angular offsets about the spot's
        centroid direction of metrics.spot (the figure `lfsim analyze` reports), with
        their exact derivatives; then the per-axis RMS beyond its limit."""
        t, w = self.spec.targets, self.spec.weights
        g = self.sl_gl
        okg = st.ok[:, :, g]
        rms, _, off, doff, wn = spot.rms_spot_jvp(st.r[:, :, g], st.dr[:, :, g], self.w_gl, okg)
        st.figures.update(rms=rms, spot_ok=okg.any(-1))
        scale = w.spot * ARCMIN / math.sqrt(st.S_all * st.F)
        yield ("spot", np.sqrt(wn)[..., None] * off * scale,
               np.sqrt(wn)[..., None, None] * doff * scale if st.derivatives else None)
        if t.spot_axis_max_arcmin is None:
            return
        rms_a = np.sqrt(np.sum(wn[..., None] * off ** 2, axis=2)) * ARCMIN  # (S, F, 2)
        over = (rms_a > t.spot_axis_max_arcmin) & okg.any(-1)[..., None]

        def jac(ix):  # rows (S, F, axis) of d rms_a
            om = np.moveaxis(off, 2, -1)  # (S, F, 2, Q)
            o_, w_ = om[ix], np.broadcast_to(wn[:, :, None, :], om.shape)[ix]
            do_ = np.moveaxis(doff, 2, -2)[ix]  # (..., Q, K)
            return (np.sum((w_ * o_)[..., None] * do_, axis=-2) * ARCMIN ** 2
                    / np.maximum(rms_a[ix], 1e-300)[..., None]) * 10.0 * w.spot

        yield ("spot_axis_max", *_hinge(st, over, (rms_a - t.spot_axis_max_arcmin) * 10.0 * w.spot, jac))

    def _gd(self, st: _Sample):
        """GD (Eq. 11, metrics.distortion) on the centre field's chief ray against the
        paraxial chief ray (the residual vector has |v| = GD in degrees); the mean over
        the whole display and the per-sub-system maximum as hinges."""
        t, w, S = self.spec.targets, self.spec.weights, st.S_all
        e = st.r[:, 0, 0] - st.ref["par_c"][:, 0]  # (S, 2)
        okc = st.ok[:, 0, 0]
        gd, dgd, gv, dgv = distortion.gd_deg_jvp(e, st.dr[:, 0, 0] - st.dpar_c[:, 0])
        st.figures.update(gd=gd, gd_ok=okc)
        if st.derivatives:
            st.figures["dgd"] = dgd
        yield ("gd", np.where(okc[:, None], gv, 0.0) * w.gd / math.sqrt(S),
               np.where(okc[:, None, None], dgv, 0.0) * w.gd / math.sqrt(S) if st.derivatives else None)
        if t.gd_max_deg is not None:
            over = okc & (gd > t.gd_max_deg)
            yield ("gd_max", *_hinge(st, over, (gd - t.gd_max_deg) * 10.0 * w.gd, lambda ix: dgd[ix] * 10.0 * w.gd))

    def _gd_mean(self, st: _Sample, grid_weights):
        """The mean GD over the whole display beyond ``gd_mean_deg``: each sampled
        lenslet stands for the lenslets nearest to it (all weights equal at stride 1);
        ``st.figures`` holds every chunk's GD."""
        t, w, fig = self.spec.targets, self.spec.weights, st.figures
        okc, gd = fig["gd_ok"], fig["gd"]
        if t.gd_mean_deg is None or not okc.any():
            return
        wm = np.where(okc, grid_weights, 0.0)
        wm = wm / wm.sum()
        mean = float(wm @ gd)
        hit = mean > t.gd_mean_deg
        jac = (wm @ fig["dgd"] * 10.0 * w.gd * hit)[None] if st.derivatives else None
        yield "gd_mean", np.array([(mean - t.gd_mean_deg) * 10.0 * w.gd if hit else 0.0]), jac

    def _pa(self, st: _Sample):
        """PA (Eq. 12, metrics.footprint): the marginal rays' footprint errors, and each
        field's PA (the mean over its four marginal rays) beyond its maximum."""
        t, w = self.spec.targets, self.spec.weights
        d_v = st.ref["d_v"][:, None, None, None]
        m_ = self.sl_marg
        okm = st.ok[:, :, m_]
        dev = (st.pos[:, :, m_] - st.ref["par_m"]) / (math.sqrt(2.0) * d_v)  # (S, F, 4, 2)
        ddev = ((st.dpos[:, :, m_] - st.dpar_m) / (math.sqrt(2.0) * d_v[..., None])
                - dev[..., None] * (st.dd_v[:, None, None, None, :] / d_v[..., None]))
        n_m = math.sqrt(st.S_all * st.F * 4)
        yield ("pa", np.where(okm[..., None], dev, 0.0) * w.pa / n_m,
               np.where(okm[..., None, None], ddev, 0.0) * w.pa / n_m if st.derivatives else None)
        pa_f, dpa_f = footprint.pa_jvp(dev, ddev)
        pa_ok = okm.all(-1)
        st.figures.update(pa=pa_f, pa_ok=pa_ok)
        if t.pa_max is not None:
            over = pa_ok & (pa_f > t.pa_max)
            yield ("pa_hinge", *_hinge(st, over, (pa_f - t.pa_max) * 10.0 * w.pa, lambda ix: dpa_f[ix] * 10.0 * w.pa))

    def _colour(self, st: _Sample, dref, part: slice):
        """Lateral colour: each field's chief rays at the shortest and longest wavelengths
        (:meth:`colour_models_at`), their retinal-tangent difference in arcmin, with exact
        derivatives (the display layout's change included); ``colour_max`` hinges each
        field's |difference| over ``lateral_colour_max_arcmin``."""
        t, w, S, F, K = self.spec.targets, self.spec.weights, st.S, st.F, st.K
        dd = None
        if st.derivatives:
            dd = dref["display"][part] if dref else np.zeros((S, F, 2, K))
        D = np.array(st.model.depths)[st.subs.k][:, None, None]
        ends = []
        for m in self.colour_models_at(st.x):
            ds = None if dd is None or st.dense else dd.reshape(-1, 2, K)
            _, J = self._rays(m, st.subs, st.derivatives, ds, rho=np.zeros((1, 2)), record=[])
            dsx = dd[:, :, None] if st.dense and dd is not None else None
            _, r, _, dr = _retinal(J, (S, F, 1), D, K, st.derivatives, dsx)
            ends.append(((J.status == 0).reshape(S, F), r[:, :, 0], None if dr is None else dr[:, :, 0]))
        (ok_a, ra, dra), (ok_b, rb, drb) = ends
        ok = ok_a & ok_b
        e = np.where(ok[..., None], (ra - rb) * ARCMIN, 0.0)  # (S, F, 2)
        de = np.where(ok[..., None, None], (dra - drb) * ARCMIN, 0.0) if st.derivatives else None
        mag = np.linalg.norm(e, axis=-1)
        st.figures.update(colour=mag, colour_ok=ok)
        scale = w.colour / math.sqrt(st.S_all * F)
        yield "colour", e * scale, de * scale if st.derivatives else None
        if t.lateral_colour_max_arcmin is not None:
            over = ok & (mag > t.lateral_colour_max_arcmin)

            def jac(ix):
                return (np.einsum("...a,...ak->...k", e[ix], de[ix]) / np.maximum(mag[ix], 1e-300)[..., None]
                        * 10.0 * w.colour)

            yield ("colour_max", *_hinge(st, over, (mag - t.lateral_colour_max_arcmin) * 10.0 * w.colour, jac))

    def _colour_details(self, fig: dict) -> dict:
        if "colour" not in fig:
            return {}
        ok, mag = fig["colour_ok"], fig["colour"]
        return {"lateral_colour_max_arcmin": float(np.max(mag[ok])) if ok.any() else None,
                "lateral_colour_mean_arcmin": float(np.mean(mag[ok])) if ok.any() else None}

    def _distortion(self, st: _Sample):
        """Local distortion of each EI beyond its maximum (metrics.distortion: chief rays
        of every field against the paraxial ones, about the EI's centre field)."""
        t, w = self.spec.targets, self.spec.weights
        if t.local_distortion_max is None or st.F <= 1:
            return
        ld, dld = distortion.local_distortion_jvp(st.r[:, :, 0], st.dr[:, :, 0], st.ref["par_c"], st.dpar_c)
        over = st.ok[:, :, 0] & st.ok[:, :1, 0] & (ld > t.local_distortion_max)
        over[:, 0] = False
        yield ("distortion", *_hinge(st, over, (ld - t.local_distortion_max) * 100.0 * w.distortion,
                                     lambda ix: dld[ix] * 100.0 * w.distortion))

    def _limits(self, model: IniModel, surf, cos_in, ok):
        """The constraint of every recorded hit, for hits of any leading shape (…):
        ``surf`` (…, nrec, 2), ``cos_in`` (…, nrec), ``ok`` (…). Yields ``(block, j,
        kind, excess, over, aux)`` per recorded surface j: ``kind`` "axes" (excess and
        over per axis (…, 2), aux the hit), "tir" (…; aux the incidence cosine) or
        "radial" (…; aux (hit, radius)). One definition for the residual blocks and
        for choosing which derivatives the trace returns (:meth:`_select`)."""
        t = self.spec.targets
        nmla = len(self._crosstalk_surfaces(model))
        tirs, aps = self._tir_surfaces(model), self._aperture_surfaces(model)
        lim = (0.5 - (t.crosstalk_margin or 0.0)) * np.array(model.arr.pitch)
        for j in range(nmla):  # pupil and marginal rays beyond (½ − margin) of the cell, per MLA surface
            hs = surf[..., j, :]
            ex = np.abs(hs) - lim
            yield "crosstalk", j, "axes", ex, (ex > 0) & ok[..., None], hs
        if t.tir_margin_deg is not None:
            vals, names = model.values(0), model.tracer.names
            for q, i in enumerate(tirs):
                j = nmla + q
                n1 = vals[names.index(model.tracer.vector.media[i])]
                n2 = vals[names.index(f"{model.system.surfaces[i].name}.index")]
                need = math.degrees(math.asin(min(1.0, n2 / n1))) + t.tir_margin_deg
                cosv = np.clip(cos_in[..., j], -1.0, 1.0)
                ex = need - np.degrees(np.arccos(cosv))
                yield f"tir_{model.system.surfaces[i].name}", j, "tir", ex, ok & (ex > 0), cosv
        margin = t.aperture_margin_mm
        for q, i in enumerate(aps):
            j = nmla + len(tirs) + q
            ap = model.system.surfaces[i].aperture
            name = f"aperture_{model.system.surfaces[i].name}"
            h = surf[..., j, :] - np.array(ap.decenter)
            if ap.kind == "circular":
                rad = np.hypot(h[..., 0], h[..., 1])
                ex = rad - (ap.radius - margin)
                yield name, j, "radial", ex, ok & (ex > 0), (h, rad)
            else:
                ex = np.abs(h) - (np.array(ap.half_width) - margin)
                yield name, j, "axes", ex, (ex > 0) & ok[..., None], h

    def _select(self, model: IniModel):
        """The trace's ``select``: the recorded hits beyond their limit (their hinge rows
        are the only ones that use their derivatives)."""
        nrec = len(self._record(model))

        def select(v):
            need = np.zeros((len(v.status), nrec), dtype=bool)
            for _, j, kind, _, over, _ in self._limits(model, v.surf, v.cos_in, v.status == 0):
                need[:, j] |= over.any(axis=-1) if kind == "axes" else over
            return need

        return select

    def _recorded(self, st: _Sample):
        """Hinges on the recorded hits (:meth:`_limits`): rays beyond (½ − margin) of the
        cell on every MLA surface and pupil rays beyond a clear aperture of the relay or
        eyepiece less ``aperture_margin_mm`` (the analysis vignettes them there), µm;
        incidence below the critical angle + margin on surfaces that rely on TIR, °."""
        w = self.spec.weights
        um = 1000.0 * w.crosstalk
        for name, j, kind, ex, over, aux in self._limits(st.model, st.surf, st.cos_in, st.ok):
            dsj = st.dsurf[:, :, :, j] if st.derivatives else None
            if kind == "axes":
                yield name, *_hinge(st, over, ex * um, lambda ix, h=aux, d=dsj: np.sign(h[ix])[..., None] * d[ix] * um)
            elif kind == "radial":
                def jac(ix, h=aux[0], rad=aux[1], d=dsj):
                    u = h[ix] / np.maximum(rad[ix], 1e-300)[..., None]
                    return np.einsum("...a,...ak->...k", u, d[ix]) * um

                yield name, *_hinge(st, over, ex * um, jac)
            else:
                def jac(ix, cosv=aux, j=j):
                    sin = np.maximum(np.sqrt(1.0 - cosv[ix] ** 2), 1e-12)
                    return st.dcos[:, :, :, j][ix] / sin[..., None] * DEG * w.tir

                yield name, *_hinge(st, over, ex * w.tir, jac)

    def _efl(self, st: _Sample):
        """Relay–eyepiece focal length per CDP state, % from its target (derivatives:
        central differences of the first-order maps)."""
        w = self.spec.weights
        f = st.ref["efl"]
        tgt = self.efl_target[:len(f)]
        jac = st.defl / tgt[:, None] * 100.0 * w.efl if st.derivatives and st.K else None
        yield "efl", (f - tgt) / tgt * 100.0 * w.efl, jac

    def _fov(self, st: _Sample):
        """Full FOV per CDP state and axis (first-order model, as `lfsim ini` reports it),
        % from ``fov_deg`` (derivatives: central differences of the first-order maps)."""
        t, w = self.spec.targets, self.spec.weights
        if t.fov_deg is None:
            return
        tgt = np.array(t.fov_deg, dtype=np.float64)
        f = st.ref["fov"]  # (states, 2)
        jac = st.dfov / tgt[None, :, None] * 100.0 * w.fov if st.derivatives and st.K else None
        yield "fov", (f - tgt) / tgt * 100.0 * w.fov, jac

    def _pixel(self, st: _Sample):
        """One display pixel seen from the viewing window per CDP state and axis (first-order
        model, as `lfsim ini` reports it), % from ``pixel_arcmin``: with ``fov_deg`` it fixes
        both the view of one elemental image and the step between views (Eqs. 7–10)."""
        t, w = self.spec.targets, self.spec.weights
        if t.pixel_arcmin is None:
            return
        tgt = np.array(t.pixel_arcmin, dtype=np.float64)
        f = st.ref["pixel"]  # (states, 2)
        jac = st.dpixel / tgt[None, :, None] * 100.0 * w.pixel if st.derivatives and st.K else None
        yield "pixel", (f - tgt) / tgt * 100.0 * w.pixel, jac

    def _display(self, st: _Sample):
        """The EI layout against the display per CDP state and axis (first-order model):
        :meth:`IniModel.display_mismatch` beyond ``display_mismatch_max``, % of one EI. Its
        derivative: ``M·h·sign(|p| − h)/p²`` times that of ``|p_EI|`` (``h`` the display's EI width)."""
        t, w, m = self.spec.targets, self.spec.weights, st.model
        if t.display_mismatch_max is None:
            return
        p = np.asarray(st.ref["ei_pitch"], dtype=np.float64)  # (states, 2)
        q = np.abs(p)
        count, have = m.display_ei()
        g = (m.display_mismatch(p) - t.display_mismatch_max) * 100.0 * w.display
        jac = np.zeros(g.shape + (st.K,)) if st.derivatives else None
        if st.derivatives and st.K:
            dq = np.sign(p)[..., None] * st.dei_pitch  # (states, 2, K)
            jac = (count * have * np.sign(q - have) / q ** 2)[..., None] * dq * 100.0 * w.display
        if self.hinge_model:
            yield "display", g, jac
            return
        over = g > 0.0
        yield "display", np.where(over, g, 0.0), (np.where(over[..., None], jac, 0.0) if jac is not None else None)

    @staticmethod
    def _footprint_widths(subs, ref):
        """(d_v per CDP state (states,), the first sampled sub-system of each state): every
        sub-system of a state has its state's d_v."""
        _, first = np.unique(np.asarray(subs.k), return_index=True)
        return np.asarray(ref["d_v"], dtype=np.float64)[first], first

    def _footprint(self, subs, ref, dref, derivatives: bool, K: int):
        """The footprint width d_v (Eq. 5; the mean of x and y, PA's reference) per CDP state
        beyond ``footprint_max_mm``, % of the limit: with a pupil of diameter P about P / d_v
        views fall in it, and fewer than two no longer give a focus cue (Section 5). Its
        derivative is the first-order model's (central differences, as PA's reference)."""
        t, w = self.spec.targets, self.spec.weights
        if t.footprint_max_mm is None:
            return
        d, first = self._footprint_widths(subs, ref)
        unit = 100.0 * w.footprint / t.footprint_max_mm
        g = (d - t.footprint_max_mm) * unit
        jac = None
        if derivatives:
            jac = (np.asarray(dref["d_v"], dtype=np.float64)[first] if K else np.zeros((d.size, 0))) * unit
        if self.hinge_model:
            yield "footprint", g, jac
            return
        over = g > 0.0
        yield "footprint", np.where(over, g, 0.0), (np.where(over[:, None], jac, 0.0) if jac is not None else None)

    def _thickness(self, st: _Sample):
        """Centre thickness of variable glass thicknesses and air gaps below their minimum, µm."""
        m = st.model
        yield from constraints.center_thickness(self.cols, st.x, m.system, m.tracer.names, m.values0,
                                                self.spec.targets, self.spec.weights, st.K, st.derivatives,
                                                signed=self.hinge_model)

    def _edge_thickness(self, st: _Sample):
        """Edge thickness of glass elements (display path, outside the lenslet array) at
        their larger clear radius below its minimum, µm."""
        m = st.model
        pairs = constraints.glass_pairs(m.system, m.tracer.names, m.values0, m.spec.viewing_window)
        yield from constraints.edge_thickness_block(self.cols, st.x, m.tracer, m.values0, pairs, self.spec.targets,
                                                    self.spec.weights, st.K, st.derivatives, signed=self.hinge_model)

    def _prism_thickness_block(self, st: _Sample):
        """A prism's thickness between opposite faces (lfsim.optics.solids) below its
        minimum at the faces' aperture grids, µm (derivatives by central differences of
        the geometry)."""
        t, w, model, x = self.spec.targets, self.spec.weights, st.model, st.x
        if t.min_prism_thickness is None or not self._has_prism:
            return
        vals = model.values0
        th = prism_thickness(model.tracer, vals, PRISM_POINTS)[0][0]
        over = np.isfinite(th) & ((th < t.min_prism_thickness) | self.hinge_model)
        jac = None
        if st.derivatives:
            jac = np.zeros((th.size, st.K))
            geo = [j_ for j_, c in enumerate(self.cols) if c.state is None]
            if over.any() and geo:
                names = model.tracer.names
                hs = np.array([1e-7 * max(1.0, abs(x[j_])) for j_ in geo])
                V = np.repeat(vals[None], 2 * len(geo), axis=0)
                for q, (j_, h) in enumerate(zip(geo, hs)):
                    V[2 * q, names.index(self.cols[j_].name)] += h
                    V[2 * q + 1, names.index(self.cols[j_].name)] -= h
                tv = prism_thickness(model.tracer, V, PRISM_POINTS)[0]
                with np.errstate(invalid="ignore"):  # a point whose line misses at x ± h: no slope
                    d_th = (tv[0::2] - tv[1::2]) / (2.0 * hs[:, None])  # (len(geo), Q)
                jac[:, geo] = np.where(over[:, None] & np.isfinite(d_th.T), -d_th.T, 0.0)
            jac *= 1000.0 * w.thickness
        g = t.min_prism_thickness - th if self.hinge_model else np.where(over, t.min_prism_thickness - th, 0.0)
        yield "prism_thickness", g * 1000.0 * w.thickness, jac

    @staticmethod
    def _package_excess(fig: dict, t, signed: bool = False) -> np.ndarray:
        """Each package limit's excess (mm, >= 0 inside the limit is 0): track, the box and
        the prism box per axis, eye relief, the relay's largest clear diameter, the
        tunable lens's footprint; a figure that cannot be measured (no ray reached its
        surface) counts as 0 here: the lost-ray block already carries it. ``signed``:
        the signed excess (negative inside the limit), −inf for a limit that is off or a
        figure that cannot be measured."""
        def over(v, lim, sign=1.0):
            if signed:
                return -np.inf if v is None or lim is None else sign * (v - lim)
            return 0.0 if v is None or lim is None else max(0.0, sign * (v - lim))

        box, pbox = fig["bounding_box_mm"], fig["prism_box_mm"]
        out = [over(fig["track_mm"], t.track_max_mm)]
        out += [over(None if box is None else box[a], None if t.box_max_mm is None else t.box_max_mm[a])
                for a in range(3)]
        out += [over(None if pbox is None else pbox[a],
                     None if t.prism_box_max_mm is None else t.prism_box_max_mm[a]) for a in range(3)]
        out.append(over(fig["eye_relief_mm"], t.eye_relief_min_mm, -1.0))
        out.append(over(fig["max_clear_diameter_mm"], t.clear_diameter_max_mm))
        out.append(over(fig["tunable_footprint_mm"], t.tunable_aperture_mm))
        return np.array(out)

    def _package(self, st: _Sample):
        """Package limits (:mod:`lfsim.ini.package`) exceeded, µm: track, the optics' and the
        prism's extents, eye relief, the relay's clear diameters, the tunable lens's
        footprint (derivatives: central differences of the package figures over the
        geometric variables, computed only while a limit is exceeded)."""
        from ..ini.package import package

        t, w = self.spec.targets, self.spec.weights
        if not t.package_limits:
            return
        um = 1000.0 * w.package
        if self.hinge_model:
            yield "package", *self._package_signed(st, t, um)
            return
        e0 = self._package_excess(package(st.model), t)
        jac = None
        if st.derivatives:
            jac = np.zeros((e0.size, st.K))
            active = e0 > 0
            geo = [j_ for j_, c in enumerate(self.cols) if c.state is None and c.name.split(".")[-1] in _GEOMETRIC]
            if active.any():
                for j_ in geo:
                    h = 1e-5 * max(1.0, abs(st.x[j_]))
                    xp, xm = st.x.copy(), st.x.copy()
                    xp[j_] += h
                    xm[j_] -= h
                    ep = self._package_excess(package(self._build_model(xp)), t)
                    em = self._package_excess(package(self._build_model(xm)), t)
                    jac[:, j_] = np.where(active, (ep - em) / (2.0 * h), 0.0)
            jac *= um
        yield "package", e0 * um, jac

    def _package_signed(self, st: _Sample, t, um: float):
        """The package rows in the step model's form: each limit's signed excess (µm × the
        weight) and its derivatives over every variable of the design (central
        differences of the figures, rebuilt at x ± h; only for limits that are on and
        measurable), the tunable powers included: the display gap, the lenslets and the
        prism's XY terms move the track, the eye relief and the prism's extent too."""
        from ..ini.package import package

        g0 = self._package_excess(package(st.model, solids=False), t, signed=True)
        jac = None
        if st.derivatives:
            jac = np.zeros((g0.size, st.K))
            live = np.isfinite(g0)
            if live.any():
                for j_ in range(st.K):
                    h = 1e-6 * max(1.0, abs(st.x[j_]))
                    xp, xm = st.x.copy(), st.x.copy()
                    xp[j_] += h
                    xm[j_] -= h
                    ep = self._package_excess(package(self._build_model(xp), solids=False), t, signed=True)
                    em = self._package_excess(package(self._build_model(xm), solids=False), t, signed=True)
                    with np.errstate(invalid="ignore"):
                        d = (ep - em) / (2.0 * h)
                    jac[:, j_] = np.where(live & np.isfinite(d), d, 0.0)
            jac *= um
        return g0 * um, jac

    @staticmethod
    def describe(details: dict) -> str:
        """One line of the evaluation's figures for the run's log."""
        gd, mean = details.get("gd_max_deg"), details.get("gd_mean_deg")
        fov = details.get("fov_deg")
        fov = f"; FOV {fov[len(fov) // 2][0]:.2f} x {fov[len(fov) // 2][1]:.2f} deg (middle CDP)" if fov else ""
        return (f"GD max {'undefined' if gd is None else f'{gd:.3f} deg'}, "
                f"mean {'undefined' if mean is None else f'{mean:.3f} deg'} over the display (the merit's sample){fov}")

    # Problem protocol
    def residuals(self, x) -> np.ndarray:
        return self.evaluate(x, derivatives=False)[0]

    def jacobian(self, x):
        r, J, _ = self.evaluate(x, derivatives=True)
        return r, J
