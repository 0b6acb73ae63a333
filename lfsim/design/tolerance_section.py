"""The ``[tolerance]`` section of a design file: manufacturing and assembly errors, compensators, targets.

Schema (units: each key's own — mm, degrees, 1/mm, diopters)::

    [tolerance]
    trials = 1000              # default of `lfsim tolerance --trials`
    seed = 1                   # default of --seed (integer >= 0)
    batch = 8                  # trials per Dask task (integer >= 1)
    compensators = ["tunable"] # re-solved per trial: parameter-table names
                               # (design.parameter_names()) and/or "tunable" (the
                               # tunable lens's power at every CDP state); default none
    compensator_method = "focus"   # "focus": restore the nominal design's paraxial CDP
                                   # depths (x and y, every state); "spot": minimise the
                                   # RMS spot (light-field merit, spot block only)
    compensator_iterations = 10    # damped least-squares iterations, >= 1

    [tolerance.sampling]       # metric sampling of each trial ([ini.analysis] keys)
    stride = [8, 4]            # every k-th lenslet along x, y (both ends included)
    fields = 3                 # field points per EI axis (odd)
    pupil = 4                  # Gauss–Legendre nodes per pupil axis
    mtf_grid = 16              # FFT pupil grid of the diffraction MTF
    refine = 0                 # levels of the worst-contrast search

    [tolerance.targets]        # a trial passes when every given target holds
    gd_max_deg = 1.0           # Eq. (11), max over sub-systems, <=
    pa_max = 0.35              # Eq. (12), <=
    contrast_nyquist_min = 0.2 # >=
    rms_spot_mean_arcmin = 1.0 # <=
                               # default: [ini.analysis] gd_target_deg and pa_target

    [[tolerance.parameters]]   # one per toleranced error
    name = "mla_decenter_x"    # label (default: the key); unique
    key = "mla.center_x"       # a --set key: parameter-table name (object.distance is
                               # the display gap), dotted path of a number in the
                               # file, or ini.tunable.power_diopters[K]
    # keys = ["F1a.decenter_y", "F1b.decenter_y"]   # instead of key: the same offset to each
    # rigid = ["S1", "S2", "S3", "S4"]              # instead of key(s): surfaces placed with
    # motion = "tilt_x"        # global_position, moved as one body: tilt_x|tilt_y|tilt_z
    # pivot = [0.0, -10.0, 285.0]                   # (deg, about pivot) or shift_x|shift_y|shift_z (mm)
    limit = 0.015              # > 0: the ± tolerance (uniform: the half-width; truncated_normal:
                               # the truncation; every kind: the ± of the sensitivity table)
    distribution = "normal"    # "uniform" | "normal" | "truncated_normal"
    sigma = 0.005              # normal kinds: standard deviation (default limit / 2)
    relative = false           # true: limit and sigma are fractions of the nominal value

An error is an offset added to the nominal value. A key that is also a
compensator (``ini.tunable.power_diopters[K]`` with ``"tunable"``, or a
parameter in ``compensators``) is a setting error: it is applied after the
compensator is solved. The section is validated here (file, key, value, what is
allowed); the Monte Carlo engine is :mod:`lfsim.tolerance`.
"""

from __future__ import annotations

import difflib
import re
from dataclasses import dataclass, field

from ..optics.prescription import System
from .errors import MISSING
from .optimize_section import TUNABLE, fixed_parameter_reason

TOLERANCE_KEYS = {"trials", "seed", "batch", "compensators", "compensator_method", "compensator_iterations",
                  "sampling", "targets", "parameters"}
PARAMETER_KEYS = {"name", "key", "keys", "rigid", "motion", "pivot", "limit", "distribution", "sigma", "relative"}
SAMPLING_KEYS = {"stride", "fields", "pupil", "mtf_grid", "refine"}
DISTRIBUTIONS = ("uniform", "normal", "truncated_normal")
METHODS = ("focus", "spot")
MOTIONS = ("tilt_x", "tilt_y", "tilt_z", "shift_x", "shift_y", "shift_z")
_TUNABLE_KEY = re.compile(r"^ini\.tunable\.power_diopters\[(\d+)\]$")

#: Targets: name → (comparison, metric of the trial record).
TARGETS = {
    "gd_max_deg": ("max", "gd_max_deg"),
    "pa_max": ("max", "pa_max"),
    "contrast_nyquist_min": ("min", "contrast_nyquist_min"),
    "rms_spot_mean_arcmin": ("max", "rms_spot_mean_arcmin"),
}


@dataclass(frozen=True)
class Tolerance:
    """One toleranced error: what moves, and how its offset is drawn."""

    name: str
    keys: tuple[str, ...] = ()  # --set keys that all receive the offset
    rigid: tuple[str, ...] = ()  # surfaces moved as one body (global_position)
    motion: str | None = None
    pivot: tuple[float, float, float] = (0.0, 0.0, 0.0)
    limit: float = 0.0
    distribution: str = "uniform"
    sigma: float | None = None
    relative: bool = False

    @property
    def is_rigid(self) -> bool:
        return bool(self.rigid)


@dataclass(frozen=True)
class ToleranceSpec:
    """Validated ``[tolerance]`` section."""

    parameters: tuple[Tolerance, ...] = ()
    trials: int = 100
    seed: int = 0
    batch: int = 8
    compensators: tuple[str, ...] = ()
    compensator_method: str = "focus"
    compensator_iterations: int = 10
    sampling: dict = field(default_factory=lambda: {"stride": (8, 4), "fields": 3, "pupil": 4,
                                                    "mtf_grid": 16, "refine": 0})
    targets: dict = field(default_factory=dict)

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(p.name for p in self.parameters)


def nominal_value(raw: dict, system: System, key: str):
    """The nominal number a ``--set`` key names, or None when the key names none."""
    from .overrides import _path_parts

    table = {n: v for n, v, _ in system.parameter_table()}
    if key in table:
        return float(table[key])
    m = _TUNABLE_KEY.match(key)
    if m:
        tun = raw.get("ini", {}).get("tunable") if isinstance(raw.get("ini"), dict) else None
        powers = tun.get("power_diopters") if isinstance(tun, dict) else None
        k = int(m.group(1))
        return float(powers[k]) if isinstance(powers, list) and k < len(powers) else None
    try:
        parts = _path_parts(key)
    except KeyError:
        return None
    node = raw
    for p in parts:
        try:
            node = node[p]
        except (KeyError, IndexError, TypeError):
            return None
    if isinstance(node, bool) or not isinstance(node, (int, float)):
        return None
    return float(node)


def _keys(ctx, tab, path, raw, system, ini=None, compensators=()) -> tuple[str, ...]:
    if "key" in tab and "keys" in tab:
        raise ctx.err(f"{path}.keys", tab["keys"], "give key or keys, not both")
    if "key" in tab:
        keys, kpath = [tab["key"]], f"{path}.key"
    else:
        keys, kpath = tab["keys"], f"{path}.keys"
        if not isinstance(keys, list) or not keys:
            raise ctx.err(kpath, keys, "a non-empty list of --set keys")
    names = system.parameter_names()
    for j, k in enumerate(keys):
        where = kpath if "key" in tab else f"{kpath}[{j}]"
        if not isinstance(k, str):
            raise ctx.err(where, k, "a --set key (string)")
        m = _TUNABLE_KEY.match(k)
        if m and TUNABLE in compensators and ini is not None and ini.tunable is not None:
            if int(m.group(1)) >= len(ini.cdp_diopters):
                raise ctx.err(where, k, f"the design has {len(ini.cdp_diopters)} CDP states")
        elif nominal_value(raw, system, k) is None:
            close = difflib.get_close_matches(k, names, n=4, cutoff=0.6)
            hint = f" (close matches: {', '.join(close)})" if close else ""
            raise ctx.err(where, k, "a parameter name of the design, ini.tunable.power_diopters[K] with the powers "
                                    "listed, or the dotted path of a number in the file" + hint)
        if k in keys[:j]:
            raise ctx.err(where, k, "listed twice")
    return tuple(keys)


def _rigid(ctx, tab, path, system) -> tuple[tuple[str, ...], str, tuple[float, float, float]]:
    surfs = tab["rigid"]
    if not isinstance(surfs, list) or not surfs or any(not isinstance(s, str) for s in surfs):
        raise ctx.err(f"{path}.rigid", surfs, "a non-empty list of surface names")
    by_name = {s.name: s for s in system.surfaces}
    for j, s in enumerate(surfs):
        if s not in by_name:
            close = difflib.get_close_matches(s, list(by_name), n=3)
            hint = f" (close matches: {', '.join(close)})" if close else ""
            raise ctx.err(f"{path}.rigid[{j}]", s, "a surface name of the design" + hint)
        if by_name[s].global_position is None:
            raise ctx.err(f"{path}.rigid[{j}]", s, "rigid groups move surfaces placed with global_position "
                                                   "(move sequential surfaces with keys = [...decenter/tilt...])")
        if s in surfs[:j]:
            raise ctx.err(f"{path}.rigid[{j}]", s, "listed twice")
    motion = tab.get("motion", MISSING)
    if motion not in MOTIONS:
        raise ctx.err(f"{path}.motion", motion, f"allowed: {', '.join(MOTIONS)}")
    pivot = ctx.vector(tab, "pivot", path, 3, (0.0, 0.0, 0.0))
    return tuple(surfs), motion, pivot


def _parameter(ctx, tab, i: int, raw, system, ini=None, compensators=()) -> Tolerance:
    path = f"tolerance.parameters[{i}]"
    if not isinstance(tab, dict):
        raise ctx.err(path, tab, "a table { key = ..., limit = ..., distribution = ... }")
    ctx.no_unknown(tab, PARAMETER_KEYS, path)
    given = [k for k in ("key", "keys", "rigid") if k in tab]
    if not given:
        raise ctx.err(f"{path}.key", MISSING, "required: key, keys or rigid")
    if "rigid" in tab and len(given) > 1:
        raise ctx.err(f"{path}.rigid", tab["rigid"], "give rigid or key(s), not both")
    kw: dict = {}
    if "rigid" in tab:
        kw["rigid"], kw["motion"], kw["pivot"] = _rigid(ctx, tab, path, system)
        default_name = f"{'+'.join(kw['rigid'])}.{kw['motion']}"
    else:
        if "motion" in tab or "pivot" in tab:
            bad = "motion" if "motion" in tab else "pivot"
            raise ctx.err(f"{path}.{bad}", tab[bad], "only with rigid = [...]")
        kw["keys"] = _keys(ctx, tab, path, raw, system, ini, compensators)
        default_name = kw["keys"][0] if len(kw["keys"]) == 1 else "+".join(kw["keys"])
    name = tab.get("name", default_name)
    if not isinstance(name, str) or not name.strip():
        raise ctx.err(f"{path}.name", name, "a non-empty label")
    kw["name"] = name
    kw["limit"] = ctx.number(tab, "limit", path, positive=True)
    dist = tab.get("distribution", "uniform")
    if dist not in DISTRIBUTIONS:
        raise ctx.err(f"{path}.distribution", dist, f"allowed: {', '.join(DISTRIBUTIONS)}")
    kw["distribution"] = dist
    if "sigma" in tab:
        if dist == "uniform":
            raise ctx.err(f"{path}.sigma", tab["sigma"], "only for normal and truncated_normal")
        kw["sigma"] = ctx.number(tab, "sigma", path, positive=True)
    elif dist != "uniform":
        kw["sigma"] = kw["limit"] / 2.0
    kw["relative"] = ctx.boolean(tab, "relative", path, False)
    if kw["relative"] and "rigid" in tab:
        raise ctx.err(f"{path}.relative", True, "a rigid motion is absolute (mm or degrees)")
    if kw["relative"]:
        for k in kw["keys"]:
            if nominal_value(raw, system, k) in (0.0, None):
                raise ctx.err(f"{path}.relative", True, f"{k} is 0 at nominal: give an absolute limit")
    return Tolerance(**kw)


def _compensators(ctx, tab, system, ini) -> tuple[str, ...]:
    comps = tab.get("compensators", [])
    if not isinstance(comps, list) or any(not isinstance(c, str) for c in comps):
        raise ctx.err("tolerance.compensators", comps, 'a list of parameter names and/or "tunable"')
    names = set(system.parameter_names())
    for j, c in enumerate(comps):
        key = f"tolerance.compensators[{j}]"
        if c == TUNABLE:
            if ini is None or ini.tunable is None:
                raise ctx.err(key, c, "needs a tunable lens ([ini.tunable])")
        elif c not in names:
            close = difflib.get_close_matches(c, sorted(names | {TUNABLE}), n=4, cutoff=0.6)
            hint = f"; close matches: {', '.join(close)}" if close else ""
            raise ctx.err(key, c, "a parameter name of the design or \"tunable\"" + hint)
        else:
            reason = fixed_parameter_reason(system, c, ini)
            if reason:
                raise ctx.err(key, c, reason)
        if c in comps[:j]:
            raise ctx.err(key, c, "listed twice")
    return tuple(comps)


def _sampling(ctx, tab) -> dict:
    ctx.no_unknown(tab, SAMPLING_KEYS, "tolerance.sampling")
    out = dict(ToleranceSpec().sampling)
    p = "tolerance.sampling"
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
    if "mtf_grid" in tab:
        out["mtf_grid"] = ctx.integer(tab, "mtf_grid", p, 4)
    if "refine" in tab:
        out["refine"] = ctx.integer(tab, "refine", p, 0)
    return out


def _targets(ctx, tab, ini) -> dict:
    ctx.no_unknown(tab, set(TARGETS), "tolerance.targets")
    out = {}
    if ini is not None:
        out = {"gd_max_deg": ini.gd_target_deg, "pa_max": ini.pa_target}
    for k in TARGETS:
        if k in tab:
            out[k] = ctx.number(tab, k, "tolerance.targets", positive=True)
    return out


def parse_tolerance(ctx, data: dict, system: System, ini=None) -> ToleranceSpec | None:
    """Validate ``data['tolerance']`` against ``system`` and its ``[ini]`` spec; None when absent."""
    if "tolerance" not in data:
        return None
    tab = data["tolerance"]
    if not isinstance(tab, dict):
        raise ctx.err("tolerance", tab, "expected a table ([tolerance])")
    if ini is None:
        raise ctx.err("tolerance", "...", "a tolerance analysis needs an InI design ([ini])")
    ctx.no_unknown(tab, TOLERANCE_KEYS, "tolerance")
    kw: dict = {}
    kw["compensators"] = _compensators(ctx, tab, system, ini)
    raw_params = tab.get("parameters", [])
    if not isinstance(raw_params, list):
        raise ctx.err("tolerance.parameters", raw_params, "a list of [[tolerance.parameters]] tables")
    params = []
    for i, p in enumerate(raw_params):
        t = _parameter(ctx, p, i, data, system, ini, kw["compensators"])
        if t.name in [q.name for q in params]:
            raise ctx.err(f"tolerance.parameters[{i}].name", t.name, "duplicate name")
        params.append(t)
    kw["parameters"] = tuple(params)
    if "trials" in tab:
        kw["trials"] = ctx.integer(tab, "trials", "tolerance", 1)
    if "seed" in tab:
        kw["seed"] = ctx.integer(tab, "seed", "tolerance", 0)
    if "batch" in tab:
        kw["batch"] = ctx.integer(tab, "batch", "tolerance", 1)
    method = tab.get("compensator_method", "focus")
    if method not in METHODS:
        raise ctx.err("tolerance.compensator_method", method, f"allowed: {', '.join(METHODS)}")
    kw["compensator_method"] = method
    if "compensator_iterations" in tab:
        kw["compensator_iterations"] = ctx.integer(tab, "compensator_iterations", "tolerance", 1)
    kw["sampling"] = _sampling(ctx, ctx.table(tab, "sampling", "tolerance", {}))
    kw["targets"] = _targets(ctx, ctx.table(tab, "targets", "tolerance", {}), ini)
    return ToleranceSpec(**kw)


def tolerance_from_design(design) -> ToleranceSpec | None:
    """The validated ``[tolerance]`` section of a loaded :class:`~lfsim.design.design.Design`."""
    from .loader import _Ctx

    return parse_tolerance(_Ctx(design.path or "<dict>"), design.raw, design.system, design.ini)


def default_spec(design) -> ToleranceSpec:
    """Settings of a design without ``[tolerance]`` (no parameters; targets from ``[ini.analysis]``)."""
    ini = design.ini
    targets = {"gd_max_deg": ini.gd_target_deg, "pa_max": ini.pa_target} if ini is not None else {}
    return ToleranceSpec(targets=targets)
