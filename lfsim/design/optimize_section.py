"""The ``[optimize]`` section of a design file: what an optimization run varies and aims at.

Schema (units mm, degrees, diopters)::

    [optimize]
    # Variables: parameter names of the design's parameter table
    # (design.parameter_names()), a bare string (unbounded) or a table with
    # optional bounds; "tunable" = the tunable lens's power at every CDP state
    # (one variable per state, diopters; needs [ini.tunable]; its bounds default
    # to [ini.tunable] range_diopters and must lie inside it).
    variables = ["S3.x2y0", { name = "S1.curvature", min = -0.05, max = 0.05 },
                 { name = "tunable", min = -2.0, max = 4.5 }]     # default: none
    solver = "lm"            # "lm" (damped least squares) | "lm-hinge" (the same, with the
                             # glass, prism and package limits as hinges in its step model) | "adam"
    iterations = 30          # > 0, per stage
    full_iterations = 3      # > 0, the "full" stage's (default: iterations)
    stages = ["mla", "relay_eyepiece", "integrated", "full"]
                             # the workflow stages to run: any non-empty subset,
                             # in this order; all four by default with [ini],
                             # only "full" without (the others need [ini])
    [optimize.sampling]      # sub-systems of the integrated stage
    stride = [4, 2]          # every k-th lenslet along x, y (integers >= 1)
    fields = 3               # field points per EI axis (odd: the EI centre is one)
    pupil = 4                # Gauss–Legendre nodes per pupil axis (>= 2) for the RMS spot
    [optimize.targets]       # all optional
    gd_max_deg = 0.75        # Eq. (11) target, > 0 (default: [ini.analysis] gd_target_deg)
    gd_mean_deg = 0.22       # optional: the mean GD over the display at most this, > 0
    pa_max = 0.3             # Eq. (12) target, > 0 (default: [ini.analysis] pa_target)
    spot_axis_max_arcmin = 1.0    # optional: RMS spot along x and along y of every
                                  # sub-system and field at most this (a contrast
                                  # floor: the MTF at Nyquist falls with the larger axis)
    local_distortion_max = 0.05   # per elemental image (fraction), > 0
    crosstalk_margin = 0.02  # marginal rays stay this fraction of the pitch inside
                             # their lenslet cell, in [0, 0.5)
    aperture_margin_mm = 0.0 # pupil rays stay this far (mm) inside every clear aperture
                             # of the relay and eyepiece, >= 0 (the penalty is met from
                             # outside: a margin keeps the rays inside the real edge)
    efl_mm = nan             # eyepiece focal length target (nonzero; signed, an
                             # inverting group has a negative EFL); nan or
                             # absent: keep the starting design's
    fov_deg = [30.0, 18.0]   # optional: full FOV (x, y) of every CDP state, as `lfsim ini`
                             # reports it (first-order); absent: off
    pixel_arcmin = [3.0, 3.0]  # optional: one display pixel (x, y) seen from the window in
                             # every CDP state, as `lfsim ini` reports it; absent: off
    display_mismatch_max = 0.5  # optional: how many EIs the layout of Eq. 2 (M EIs of p_EI) may
                             # differ from the display (M x pixels_per_ei x pixel_pitch) across it,
                             # per CDP state and axis; the renderer refuses more than 1; absent: off
    footprint_max_mm = 1.5   # optional: the footprint d_v (Eq. 5, the mean of its x and y widths)
                             # of a view on the window in every CDP state at most this, so that
                             # pupil / d_v views fall in the eye pupil (2 in a 3 mm pupil at 1.5 mm);
                             # absent: off
    min_center_thickness = 0.3    # mm, glass, >= 0
    min_edge_thickness = 0.3      # mm, glass, >= 0
    min_air_gap = 0.1             # mm, >= 0
    min_prism_thickness = 1.0     # mm, >= 0: between opposite prism faces (lfsim.optics.solids)
    track_max_mm = 150.0          # optional package limits (lfsim.ini.package; absent: off):
                                  # the central chief ray's unfolded length, display → window
    box_max_mm = [50.0, 50.0, 160.0]   # extents (x, y, z) of the whole optics, global frame
    prism_box_max_mm = [40.0, 40.0, 40.0]  # extents (x, y, z) of the prism's faces
    eye_relief_min_mm = 18.0      # window centre → nearest ray on the last surface
    clear_diameter_max_mm = 25.4  # the relay lenses' clear diameters
    tunable_aperture_mm = 10.0    # rays through the tunable lens within this diameter
    lateral_colour_max_arcmin = 5.0  # optional: each field's lateral colour (the chief
                                  # rays at the shortest and longest wavelengths) at most this
    tir_margin_deg = 1.0          # TIR surfaces: incidence at least this far beyond
                                  # the critical angle, in [0, 90)
    [optimize.weights]       # all optional, finite and >= 0
    spot = 1.0
    gd = 1.0
    pa = 1.0
    distortion = 1.0
    crosstalk = 1.0
    efl = 10.0
    fov = 10.0               # per % of the FOV target
    pixel = 10.0             # per % of the pixel target
    display = 10.0           # per % of one EI beyond display_mismatch_max
    footprint = 10.0         # per % of d_v beyond footprint_max_mm
    thickness = 1.0
    tir = 1.0
    package = 1.0            # per µm beyond a package limit
    colour = 0.0             # per arcmin of lateral colour (off by default; needs
                             # two or more [system] wavelengths)

A schedule instead of ``stages = [...]``: ``[[optimize.stages]]`` tables run
in the order written, each from the design the one before it ended with; every
key but ``name`` is optional and falls back on the section's own::

    [[optimize.stages]]
    name = "coarse"          # unique; letters, digits, '_' and '-' (checkpoints/<name>.npz)
    variables = [...]        # as [optimize] variables; a bare name listed there keeps its bounds
    solver = "lm"
    iterations = 40          # the stage's iteration cap
    stride = [4, 2]          # lenslet sampling ([1, 1]: every sub-system)
    fields = 3
    pupil = 3
    [optimize.stages.targets]    # replace the section's targets of the same name
    gd_mean_deg = 0.2
    [optimize.stages.weights]    # replace the section's weights of the same name
    gd = 32.0

Targets taken from the starting design: ``gd_max_deg`` and ``pa_max`` left out
of the file are filled from ``[ini.analysis]`` when the section is parsed (they
stay ``None`` without ``[ini]``, and in :meth:`OptimizeSpec.default`, where
:meth:`OptimizeTargets.resolve` fills them); ``efl_mm`` left out (or ``nan``) is
``None``: keep the starting design's focal length.

Parameters the file cannot carry are refused as variables: refractive indices
(``*.index``, ``object.index``: they come from materials), the shape of a
paraxial lens or a coordinate break, the tilt and decenter of the InI lenslet
surfaces (move the array with ``NAME.center_x``), the viewing window's shape,
and the tunable surface's ``power`` (vary ``"tunable"``).

The section is validated here (file, key, value, what is allowed); the merit
functions and solvers live in :mod:`lfsim.optimize`.
"""

from __future__ import annotations

import difflib
import math
import re
from dataclasses import dataclass, field, replace

from ..optics.prescription import System
from .errors import MISSING

OPTIMIZE_KEYS = {"variables", "solver", "iterations", "full_iterations", "stages", "sampling", "targets",
                 "weights"}
STAGE_KEYS = {"name", "variables", "solver", "iterations", "stride", "fields", "pupil", "targets", "weights"}
_STAGE_NAME_RE = re.compile(r"^[A-Za-z0-9_-]{1,64}$")
SOLVERS = ("lm", "lm-hinge", "adam")
#: Workflow stages in the order they run.
STAGES = ("mla", "relay_eyepiece", "integrated", "full")
#: The variable name standing for the tunable lens's power at every CDP state.
TUNABLE = "tunable"
SAMPLING_KEYS = {"stride", "fields", "pupil"}
_COEFF_RE = re.compile(r"^(A\d+|x\d+y\d+)$")


@dataclass(frozen=True)
class Variable:
    """One optimization variable: a parameter-table name (or ``"tunable"``) and its bounds.

    ``lower`` / ``upper`` are ``-inf`` / ``+inf`` when not given. For
    ``"tunable"`` they are in diopters and apply to the power at every CDP state.
    """

    name: str
    lower: float = -math.inf
    upper: float = math.inf

    @property
    def is_tunable(self) -> bool:
        return self.name == TUNABLE

    @property
    def bounded(self) -> bool:
        return math.isfinite(self.lower) or math.isfinite(self.upper)


@dataclass(frozen=True)
class OptimizeTargets:
    """Targets and constraint limits; ``None`` = taken from the starting design."""

    gd_max_deg: float | None = None
    gd_mean_deg: float | None = None
    pa_max: float | None = None
    spot_axis_max_arcmin: float | None = None
    local_distortion_max: float = 0.05
    crosstalk_margin: float = 0.02
    aperture_margin_mm: float = 0.0
    efl_mm: float | None = None
    fov_deg: tuple[float, float] | None = None
    pixel_arcmin: tuple[float, float] | None = None
    display_mismatch_max: float | None = None
    footprint_max_mm: float | None = None
    min_center_thickness: float = 0.3
    min_edge_thickness: float = 0.3
    min_air_gap: float = 0.1
    min_prism_thickness: float = 1.0
    tir_margin_deg: float = 1.0
    track_max_mm: float | None = None
    box_max_mm: tuple[float, float, float] | None = None
    prism_box_max_mm: tuple[float, float, float] | None = None
    eye_relief_min_mm: float | None = None
    clear_diameter_max_mm: float | None = None
    tunable_aperture_mm: float | None = None
    lateral_colour_max_arcmin: float | None = None

    @property
    def package_limits(self) -> bool:
        """Any package limit set (the ``package`` merit block is on)."""
        return any(v is not None for v in (self.track_max_mm, self.box_max_mm, self.prism_box_max_mm,
                                           self.eye_relief_min_mm, self.clear_diameter_max_mm,
                                           self.tunable_aperture_mm))

    def resolve(self, ini) -> OptimizeTargets:
        """A copy with ``gd_max_deg`` / ``pa_max`` taken from an :class:`IniSpec` where unset."""
        if ini is None:
            return self
        return replace(
            self,
            gd_max_deg=ini.gd_target_deg if self.gd_max_deg is None else self.gd_max_deg,
            pa_max=ini.pa_target if self.pa_max is None else self.pa_max,
        )


@dataclass(frozen=True)
class OptimizeWeights:
    """Weights of the merit-function terms (each >= 0)."""

    spot: float = 1.0
    gd: float = 1.0
    pa: float = 1.0
    distortion: float = 1.0
    crosstalk: float = 1.0
    efl: float = 10.0
    fov: float = 10.0
    pixel: float = 10.0
    display: float = 10.0
    footprint: float = 10.0
    thickness: float = 1.0
    tir: float = 1.0
    package: float = 1.0
    colour: float = 0.0


TARGET_DEFAULTS = OptimizeTargets()
WEIGHT_DEFAULTS = OptimizeWeights()
TARGET_KEYS = set(OptimizeTargets.__dataclass_fields__)
WEIGHT_KEYS = set(OptimizeWeights.__dataclass_fields__)


@dataclass(frozen=True)
class StageSpec:
    """One ``[[optimize.stages]]`` entry, with the section's settings filled in."""

    name: str
    variables: tuple[Variable, ...]
    solver: str
    iterations: int
    stride: tuple[int, int]
    fields: int
    pupil: int
    targets: OptimizeTargets
    weights: OptimizeWeights


@dataclass(frozen=True)
class OptimizeSpec:
    """Validated ``[optimize]`` section (``schedule``: its ``[[optimize.stages]]``, or None)."""

    variables: tuple[Variable, ...] = ()
    solver: str = "lm"
    iterations: int = 30
    full_iterations: int | None = None  # iterations of the "full" stage (default: iterations)
    stages: tuple[str, ...] = STAGES
    stride: tuple[int, int] = (4, 2)
    fields: int = 3
    pupil: int = 4
    targets: OptimizeTargets = field(default_factory=OptimizeTargets)
    weights: OptimizeWeights = field(default_factory=OptimizeWeights)
    schedule: tuple[StageSpec, ...] | None = None

    def for_stage(self, stage: StageSpec) -> OptimizeSpec:
        """This section with one scheduled stage's settings in place of its own."""
        return replace(self, variables=stage.variables, solver=stage.solver, iterations=stage.iterations,
                       stride=stage.stride, fields=stage.fields, pupil=stage.pupil, targets=stage.targets,
                       weights=stage.weights, schedule=None, stages=("integrated",))

    @classmethod
    def default(cls, *, ini: bool = True) -> OptimizeSpec:
        """The settings of a design without ``[optimize]``: no variables, default
        solver, sampling, targets and weights; all stages for an InI design
        (``ini=True``), only ``"full"`` otherwise."""
        return cls(stages=STAGES if ini else ("full",))

    @property
    def varies_anything(self) -> bool:
        """The section or one of its scheduled stages names a variable."""
        return bool(self.variables) or any(st.variables for st in self.schedule or ())

    @property
    def variable_names(self) -> tuple[str, ...]:
        return tuple(v.name for v in self.variables)


# ----------------------------------------------------------------- validation
def fixed_parameter_reason(system: System, name: str, ini=None) -> str | None:
    """Why parameter ``name`` cannot be an optimization variable, or None if it can.

    ``name`` must be in ``system.parameter_names()``; ``ini`` is the design's
    :class:`IniSpec` (or None).
    """
    if name == "object.index" or name.endswith(".index"):
        return "refractive indices come from materials and cannot be varied; change the material instead"
    owner, attr = name.rsplit(".", 1)
    surf = {s.name: (i, s) for i, s in enumerate(system.surfaces)}
    if owner not in surf or (attr.startswith(("pitch_", "center_")) and owner in system.arrays):
        return None
    i, s = surf[owner]
    shape = attr in ("curvature", "conic") or _COEFF_RE.match(attr) is not None
    if shape and s.interaction == "paraxial":
        return "a paraxial (ideal) lens is a plane: vary its power instead"
    if shape and s.interaction == "break":
        return "a coordinate break has no shape; vary its decenter, tilt or thickness"
    if ini is not None:
        if attr == "power" and ini.tunable == i:
            return f"{owner} is the tunable lens: vary \"{TUNABLE}\" (its power at every CDP state)"
        if i in ini.mla_surfaces and attr.startswith(("decenter_", "tilt_")):
            return (f"the InI lenslet surfaces stay untilted and undecentered; "
                    f"move the array with {ini.mla}.center_x / {ini.mla}.center_y")
        if i == ini.viewing_window and shape:
            return "the viewing window must stay a plane"
    return None


def _bound(ctx, tab, key, path):
    if key not in tab:
        return None
    v = tab[key]
    if isinstance(v, bool) or not isinstance(v, (int, float)) or math.isnan(v):
        raise ctx.err(f"{path}.{key}", v, "expected a number (leave it out for no bound)")
    return float(v)


def _variable(ctx, raw, i: int, names: set[str], system: System, ini, base="optimize.variables") -> Variable:
    path = f"{base}[{i}]"
    if isinstance(raw, str):
        name, name_key, tab = raw, path, {}
    elif isinstance(raw, dict):
        ctx.no_unknown(raw, {"name", "min", "max"}, path)
        name, name_key, tab = raw.get("name", MISSING), f"{path}.name", raw
        if not isinstance(name, str):
            raise ctx.err(name_key, name, "required: a parameter name (string)")
    else:
        raise ctx.err(path, raw, 'a parameter name or a table { name = "...", min = ..., max = ... }')

    if name == TUNABLE:
        if ini is None or ini.tunable is None:
            raise ctx.err(name_key, name, "needs a tunable lens ([ini.tunable])")
    elif name not in names:
        close = difflib.get_close_matches(name, sorted(names | {TUNABLE}), n=4, cutoff=0.6)
        hint = f"close matches: {', '.join(close)}" if close else "see design.parameter_names()"
        raise ctx.err(name_key, name, f"not a parameter of this design; {hint}")
    else:
        reason = fixed_parameter_reason(system, name, ini)
        if reason:
            raise ctx.err(name_key, name, reason)

    lo, hi = _bound(ctx, tab, "min", path), _bound(ctx, tab, "max", path)
    if lo is not None and hi is not None and not lo < hi:
        raise ctx.err(f"{path}.max", hi, f"must be > min (= {lo:g})")
    if name == TUNABLE and ini.tunable_range_diopters is not None:
        r_lo, r_hi = ini.tunable_range_diopters
        if lo is not None and lo < r_lo:
            raise ctx.err(f"{path}.min", lo, f"outside the tunable lens's range [{r_lo:g}, {r_hi:g}] D")
        if hi is not None and hi > r_hi:
            raise ctx.err(f"{path}.max", hi, f"outside the tunable lens's range [{r_lo:g}, {r_hi:g}] D")
        lo = r_lo if lo is None else lo
        hi = r_hi if hi is None else hi
        if not lo < hi:
            raise ctx.err(f"{path}.max" if "max" in tab else f"{path}.min", hi if "max" in tab else lo,
                          f"leaves no room inside the tunable lens's range [{r_lo:g}, {r_hi:g}] D")
    return Variable(name, -math.inf if lo is None else lo, math.inf if hi is None else hi)


def _sampling(ctx, tab, p="optimize.sampling", allowed=SAMPLING_KEYS) -> dict:
    ctx.no_unknown(tab, allowed, p)
    out = {}
    if "stride" in tab:
        st = tab["stride"]
        if not isinstance(st, list) or len(st) != 2 or any(
                isinstance(v, bool) or not isinstance(v, int) or v < 1 for v in st):
            raise ctx.err(f"{p}.stride", st, "expected [sx, sy], two integers >= 1")
        out["stride"] = (st[0], st[1])
    if "fields" in tab:
        out["fields"] = ctx.integer(tab, "fields", p, 1)
        if out["fields"] % 2 == 0:
            raise ctx.err(f"{p}.fields", out["fields"], "must be odd (the EI centre is a field)")
    if "pupil" in tab:
        out["pupil"] = ctx.integer(tab, "pupil", p, 2)
    return out


def _targets(ctx, tab, p="optimize.targets") -> OptimizeTargets:
    ctx.no_unknown(tab, TARGET_KEYS, p)
    kw = {}
    for key in ("gd_max_deg", "gd_mean_deg", "pa_max", "local_distortion_max", "spot_axis_max_arcmin",
                "lateral_colour_max_arcmin", "footprint_max_mm"):
        if key in tab:
            kw[key] = ctx.number(tab, key, p, positive=True)
    for key, top, allowed in (("crosstalk_margin", 0.5, "a fraction of the lenslet pitch in [0, 0.5)"),
                              ("tir_margin_deg", 90.0, "an angle in degrees in [0, 90)")):
        if key in tab:
            v = ctx.number(tab, key, p, nonneg=True)
            if not v < top:
                raise ctx.err(f"{p}.{key}", v, allowed)
            kw[key] = v
    if "fov_deg" in tab:
        v = tab["fov_deg"]
        if (not isinstance(v, list) or len(v) != 2 or any(isinstance(a, bool) or not isinstance(a, (int, float))
                                                           or not 0.0 < a < 180.0 for a in v)):
            raise ctx.err(f"{p}.fov_deg", v, "expected [x, y], two full field angles in degrees in (0, 180)")
        kw["fov_deg"] = (float(v[0]), float(v[1]))
    if "pixel_arcmin" in tab:
        v = tab["pixel_arcmin"]
        if (not isinstance(v, list) or len(v) != 2 or any(isinstance(a, bool) or not isinstance(a, (int, float))
                                                           or not 0.0 < a < 600.0 for a in v)):
            raise ctx.err(f"{p}.pixel_arcmin", v, "expected [x, y], two pixel angles in arcmin in (0, 600)")
        kw["pixel_arcmin"] = (float(v[0]), float(v[1]))
    if "display_mismatch_max" in tab:
        v = tab["display_mismatch_max"]
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not 0.0 <= v <= 1.0:
            raise ctx.err(f"{p}.display_mismatch_max", v, "expected a number of elemental images in [0, 1]")
        kw["display_mismatch_max"] = float(v)
    if "efl_mm" in tab:
        v = tab["efl_mm"]
        if isinstance(v, float) and math.isnan(v):
            kw["efl_mm"] = None
        else:
            v = ctx.number(tab, "efl_mm", p)
            if v == 0:
                raise ctx.err(f"{p}.efl_mm", v, "a nonzero focal length in mm (nan or absent: keep the start's)")
            kw["efl_mm"] = v
    for key in ("min_center_thickness", "min_edge_thickness", "min_air_gap", "min_prism_thickness",
                "aperture_margin_mm"):
        if key in tab:
            kw[key] = ctx.number(tab, key, p, nonneg=True)
    for key in ("track_max_mm", "eye_relief_min_mm", "clear_diameter_max_mm", "tunable_aperture_mm"):
        if key in tab:
            kw[key] = ctx.number(tab, key, p, positive=True)
    for key in ("box_max_mm", "prism_box_max_mm"):
        if key in tab:
            v = tab[key]
            if (not isinstance(v, list) or len(v) != 3
                    or any(isinstance(a, bool) or not isinstance(a, (int, float)) or not 0.0 < a < math.inf
                           for a in v)):
                raise ctx.err(f"{p}.{key}", v, "expected [x, y, z], three positive extents in mm")
            kw[key] = tuple(float(a) for a in v)
    return OptimizeTargets(**kw)


def _weights(ctx, tab, p="optimize.weights") -> OptimizeWeights:
    ctx.no_unknown(tab, WEIGHT_KEYS, p)
    return OptimizeWeights(**{k: ctx.number(tab, k, p, nonneg=True) for k in tab})


def _stages(ctx, raw, ini) -> tuple[str, ...]:
    key = "optimize.stages"
    if not isinstance(raw, list) or not raw or any(not isinstance(s, str) for s in raw):
        raise ctx.err(key, raw, f"a non-empty list of stage names from: {', '.join(STAGES)}")
    for j, s in enumerate(raw):
        if s not in STAGES:
            close = difflib.get_close_matches(s, STAGES, n=1)
            hint = f" (did you mean {close[0]!r}?)" if close else ""
            raise ctx.err(f"{key}[{j}]", s, f"allowed: {', '.join(STAGES)}{hint}")
        if s in raw[:j]:
            raise ctx.err(f"{key}[{j}]", s, "duplicate stage")
        if ini is None and s != "full":
            raise ctx.err(f"{key}[{j}]", s, 'needs an InI design ([ini]); a plain lens has only "full"')
    if [STAGES.index(s) for s in raw] != sorted(STAGES.index(s) for s in raw):
        raise ctx.err(key, raw, f"stages run in this order: {', '.join(STAGES)}")
    return tuple(raw)


def _variables(ctx, raw_vars, system: System, ini, base: str, inherit=None) -> tuple[Variable, ...]:
    """A variables list; with ``inherit`` (the section's variables), a bare name listed
    there keeps its bounds."""
    if not isinstance(raw_vars, list):
        raise ctx.err(base, raw_vars, "a list of parameter names or { name, min, max } tables")
    names = set(system.parameter_names())
    known = {v.name: v for v in inherit or ()}
    seen: dict[str, int] = {}
    variables = []
    for i, raw in enumerate(raw_vars):
        v = _variable(ctx, raw, i, names, system, ini, base)
        if isinstance(raw, str) and raw in known:
            v = known[raw]
        if v.name in seen:
            key = f"{base}[{i}]" + (".name" if isinstance(raw, dict) else "")
            raise ctx.err(key, v.name, f"duplicate variable (also {base}[{seen[v.name]}])")
        seen[v.name] = i
        variables.append(v)
    return tuple(variables)


def _schedule(ctx, raw, tab, system: System, ini, sec: dict) -> tuple[StageSpec, ...]:
    """The ``[[optimize.stages]]`` tables, each filled in from the section ``sec``."""
    stages, seen = [], {}
    for j, st in enumerate(raw):
        p = f"optimize.stages[{j}]"
        if not isinstance(st, dict):
            raise ctx.err(p, st, "every entry a table ([[optimize.stages]]) or every entry a stage name")
        ctx.no_unknown(st, STAGE_KEYS, p)
        name = st.get("name", MISSING)
        if not isinstance(name, str) or not _STAGE_NAME_RE.match(name):
            raise ctx.err(f"{p}.name", name, "required: a name of letters, digits, '_' or '-' (at most 64)")
        if name in seen:
            raise ctx.err(f"{p}.name", name, f"duplicate stage name (also optimize.stages[{seen[name]}])")
        seen[name] = j
        variables = (_variables(ctx, st["variables"], system, ini, f"{p}.variables", sec["variables"])
                     if "variables" in st else sec["variables"])
        if not variables:
            raise ctx.err(f"{p}.variables", st.get("variables", []), "no variables: the stage would vary nothing")
        solver = st.get("solver", sec["solver"])
        if solver not in SOLVERS:
            raise ctx.err(f"{p}.solver", solver, f"allowed: {', '.join(SOLVERS)}")
        iterations = ctx.integer(st, "iterations", p, 1) if "iterations" in st else sec["iterations"]
        samp = {k: sec[k] for k in ("stride", "fields", "pupil")}
        samp.update(_sampling(ctx, {k: st[k] for k in ("stride", "fields", "pupil") if k in st}, p))
        targets = _targets(ctx, {**ctx.table(tab, "targets", "optimize", {}), **ctx.table(st, "targets", p, {})},
                           f"{p}.targets").resolve(ini)
        weights = _weights(ctx, {**ctx.table(tab, "weights", "optimize", {}), **ctx.table(st, "weights", p, {})},
                           f"{p}.weights")
        stages.append(StageSpec(name, variables, solver, iterations, samp["stride"], samp["fields"], samp["pupil"],
                                targets, weights))
    return tuple(stages)


def parse_optimize(ctx, data: dict, system: System, ini=None) -> OptimizeSpec | None:
    """Validate ``data['optimize']`` against ``system`` and its ``[ini]`` spec; None when absent."""
    if "optimize" not in data:
        return None
    tab = data["optimize"]
    if not isinstance(tab, dict):
        raise ctx.err("optimize", tab, "expected a table ([optimize])")
    ctx.no_unknown(tab, OPTIMIZE_KEYS, "optimize")
    kw: dict = {}

    kw["variables"] = _variables(ctx, tab.get("variables", []), system, ini, "optimize.variables")

    solver = tab.get("solver", "lm")
    if solver not in SOLVERS:
        raise ctx.err("optimize.solver", solver, f"allowed: {', '.join(SOLVERS)}")
    kw["solver"] = solver
    if "iterations" in tab:
        kw["iterations"] = ctx.integer(tab, "iterations", "optimize", 1)
    if "full_iterations" in tab:
        kw["full_iterations"] = ctx.integer(tab, "full_iterations", "optimize", 1)
    raw_stages = tab.get("stages")
    scheduled = isinstance(raw_stages, list) and bool(raw_stages) and isinstance(raw_stages[0], dict)
    if not scheduled:
        kw["stages"] = _stages(ctx, raw_stages, ini) if "stages" in tab else (
            STAGES if ini is not None else ("full",))
    kw.update(_sampling(ctx, ctx.table(tab, "sampling", "optimize", {})))
    kw["targets"] = _targets(ctx, ctx.table(tab, "targets", "optimize", {})).resolve(ini)
    kw["weights"] = _weights(ctx, ctx.table(tab, "weights", "optimize", {}))
    spec = OptimizeSpec(**kw)
    if scheduled:
        if "full_iterations" in tab:
            raise ctx.err("optimize.full_iterations", tab["full_iterations"],
                          "belongs to a stages = [...] list; a [[optimize.stages]] schedule sets iterations per stage")
        sec = {k: getattr(spec, k) for k in ("variables", "solver", "iterations", "stride", "fields", "pupil")}
        schedule = _schedule(ctx, raw_stages, tab, system, ini, sec)
        spec = replace(spec, schedule=schedule, stages=tuple(st.name for st in schedule))
    if len(set(system.wavelengths_nm)) < 2:  # lateral colour needs two wavelengths
        where = [("optimize.weights.colour", spec.weights)]
        where += [(f"optimize.stages[{j}].weights.colour", st.weights) for j, st in enumerate(spec.schedule or ())]
        for key, w in where:
            if w.colour > 0:
                raise ctx.err(key, w.colour, "lateral colour needs two or more [system] wavelengths_nm")
    return spec
