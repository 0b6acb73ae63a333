"""Design files (TOML): parsing and validation into an optics ``System``.

Schema (units: mm, degrees, nm)::

    name = "Cooke triplet"
    [system]
    aperture = { type = "epd", value = 10.0 }     # epd (mm) | fno | na
    field = { type = "angle", values = [0, 14, 20] }   # angle (deg) | height (mm)
    wavelengths_nm = [486.1327, 587.5618, 656.2725]
    primary_wavelength_nm = 587.5618
    [object]
    distance = inf                                # object to first vertex
    material = "air"
    [[surfaces]]                                  # in sequence; the last is the image
    name = "L1a"            radius = 22.01359    thickness = 3.25896
    material = "SK16"       semi_diameter = 8.0  conic = 0.0
    # asphere = { A4 = ..., ..., A16 = ... }
    # xy = { x2y0 = ..., x0y2 = ..., ... }  with norm_radius = R (total order ≤ 10)
    # mirror = true | tir = true | dummy = true | type = "coordinate_break"
    # type = "paraxial" with focal_length = f: an ideal thin lens (plane, same medium)
    # aperture = { type = "circular", radius = r, decenter = [x, y] }
    #          | { type = "rectangular", half_width = [hx, hy], decenter = [x, y] }
    # stop = true, decenter = [dx, dy], tilt = [tx, ty, tz], return_axis = false,
    # global_position = [x, y, z], same_as = "name", array = "mla"
    [arrays.mla]
    m = 17  n = 9  pitch = [1.0, 1.0]  center = [0.0, 0.0]

Every problem raises :class:`DesignError` naming the file, the key, the
value and what is allowed.
"""

from __future__ import annotations

import math
import re
import tomllib
from pathlib import Path

from ..optics.materials import AIR, MaterialError, lookup
from ..optics.prescription import (
    ASPHERE_ORDERS,
    XY_MAX_ORDER,
    Aperture,
    LensletArray,
    Surface,
    System,
)
from .errors import MISSING, DesignError, surface_names

_NAME_RE = re.compile(r"^[A-Za-z_][A-Za-z0-9_\-]*$")
_XY_RE = re.compile(r"^x(\d+)y(\d+)$")

SURFACE_KEYS = {
    "name", "type", "radius", "curvature", "conic", "asphere", "xy", "norm_radius",
    "thickness", "material", "mirror", "tir", "dummy", "semi_diameter", "aperture",
    "stop", "decenter", "tilt", "return_axis", "global_position", "same_as", "array",
    "comment", "focal_length", "virtual",
}
SURFACE_TYPES = ("standard", "even_asphere", "xy_polynomial", "coordinate_break", "paraxial")
TOP_KEYS = {"name", "description", "system", "object", "surfaces", "arrays", "ini", "render", "optimize",
            "tolerance"}
#: Largest magnitude of a finite design number (mm, 1/mm, degrees, ...): 1e15 mm is 1e9 km,
#: and the tracer's squares of such numbers stay finite in float32 (max 3.4e38).
MAX_ABS = 1e15


class _Ctx:
    """Carries the file name so every check can raise a complete error."""

    def __init__(self, file: str):
        self.file = file

    def err(self, key, value, allowed):
        return DesignError(self.file, key, value, allowed)

    # -- scalar readers -----------------------------------------------------
    def number(self, tab, key, path, default=MISSING, *, finite=True, positive=False,
               nonneg=False, allow_inf=False):
        v = tab.get(key, default)
        if v is MISSING:
            raise self.err(f"{path}.{key}", MISSING, "required: a number")
        if isinstance(v, str) and allow_inf and v.strip().lower() in ("inf", "infinity", "+inf"):
            v = math.inf
        if isinstance(v, bool) or not isinstance(v, (int, float)):
            raise self.err(f"{path}.{key}", v, "expected a number" + (" or inf" if allow_inf else ""))
        v = float(v)
        if math.isnan(v) or (math.isinf(v) and not allow_inf) or (finite and not allow_inf and not math.isfinite(v)):
            raise self.err(f"{path}.{key}", v, "expected a finite number" + (" or inf" if allow_inf else ""))
        if math.isfinite(v) and abs(v) > MAX_ABS:
            raise self.err(f"{path}.{key}", v, f"|value| must be <= {MAX_ABS:g}" + (" (or inf)" if allow_inf else ""))
        if positive and not v > 0:
            raise self.err(f"{path}.{key}", v, "must be > 0")
        if nonneg and not v >= 0:
            raise self.err(f"{path}.{key}", v, "must be >= 0")
        return v

    def vector(self, tab, key, path, length, default):
        v = tab.get(key, default)
        if isinstance(v, (int, float)) and not isinstance(v, bool) and length == 2 and key == "pitch":
            v = [v, v]
        if not isinstance(v, (list, tuple)) or len(v) != length or any(
            isinstance(x, bool) or not isinstance(x, (int, float)) or not math.isfinite(x) or abs(x) > MAX_ABS
            for x in v
        ):
            raise self.err(f"{path}.{key}", v, f"expected a list of {length} finite numbers (|x| <= {MAX_ABS:g})")
        return tuple(float(x) for x in v)

    def boolean(self, tab, key, path, default=False):
        v = tab.get(key, default)
        if not isinstance(v, bool):
            raise self.err(f"{path}.{key}", v, "expected true or false")
        return v

    def integer(self, tab, key, path, minimum=1):
        v = tab.get(key, MISSING)
        if isinstance(v, bool) or not isinstance(v, int):
            raise self.err(f"{path}.{key}", v, f"expected an integer >= {minimum}")
        if v < minimum:
            raise self.err(f"{path}.{key}", v, f"must be an integer >= {minimum}")
        return v

    def table(self, tab, key, path, default=MISSING):
        v = tab.get(key, default)
        if v is MISSING:
            raise self.err(f"{path}.{key}", MISSING, "required: a table")
        if not isinstance(v, dict):
            raise self.err(f"{path}.{key}", v, "expected a table")
        return v

    def no_unknown(self, tab, allowed, path):
        for k in tab:
            if k not in allowed:
                raise self.err(f"{path}.{k}" if path else k, tab[k],
                               f"unknown key; allowed: {', '.join(sorted(allowed))}")


def read_toml(path: str | Path) -> dict:
    """Parse a TOML file, turning I/O and syntax problems into :class:`DesignError`."""
    p = Path(path)
    # a CODE V or Zemax file given where a design is expected: say how to make one of it
    hint = (f" ({p.suffix} is a lens file: `lfsim import {p.name} --out DESIGN.toml` makes a design of it)"
            if p.suffix.lower() in (".seq", ".zmx") else "")
    try:
        text = p.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise DesignError(str(p), "", MISSING, "file not found") from None
    except (OSError, UnicodeDecodeError) as e:
        raise DesignError(str(p), "", MISSING, f"cannot read file ({e.__class__.__name__}: {e}){hint}") from None
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as e:
        raise DesignError(str(p), "", MISSING, f"invalid TOML: {e}{hint}") from None


def load_system(path: str | Path) -> tuple[System, dict]:
    """Load and validate a design file; return the optics ``System`` and the raw table."""
    data = read_toml(path)
    return system_from_dict(data, str(path)), data


def _material(ctx, tab, key, path, default):
    if key not in tab:
        return default
    try:
        return lookup(tab[key])
    except MaterialError as e:
        raise ctx.err(f"{path}.{key}", tab[key], str(e).split(": ", 1)[-1]) from None


def _surface(ctx: _Ctx, raw, i: int, names: dict, arrays: dict) -> Surface:
    path = f"surfaces[{i}]"
    if not isinstance(raw, dict):
        raise ctx.err(path, raw, "each [[surfaces]] entry must be a table")
    ctx.no_unknown(raw, SURFACE_KEYS, path)
    name = raw.get("name", f"S{i + 1}")
    if not isinstance(name, str) or not _NAME_RE.match(name) or name in ("object",):
        raise ctx.err(f"{path}.name", name, "a name made of letters, digits, '_' or '-', not 'object'")
    if name in names:
        raise ctx.err(f"{path}.name", name, f"duplicate surface name (also surfaces[{names[name]}])")
    stype = raw.get("type", None)
    if stype is not None and stype not in SURFACE_TYPES:
        raise ctx.err(f"{path}.type", stype, f"allowed: {', '.join(SURFACE_TYPES)}")
    s = Surface(name=name)

    if stype == "coordinate_break":
        extra = set(raw) - {"name", "type", "decenter", "tilt", "thickness", "return_axis", "comment"}
        if extra:
            k = sorted(extra)[0]
            raise ctx.err(f"{path}.{k}", raw[k],
                          "a coordinate break takes only decenter, tilt, thickness, return_axis")
        s.interaction = "break"
        s.return_axis = ctx.boolean(raw, "return_axis", path, False)
    if stype == "paraxial":
        bad = {"radius", "curvature", "conic", "asphere", "xy", "norm_radius", "material", "mirror",
               "tir", "dummy", "same_as"} & set(raw)
        if bad:
            k = sorted(bad)[0]
            raise ctx.err(f"{path}.{k}", raw[k], "a paraxial (ideal) lens is a plane in one medium: "
                          "give focal_length, thickness, apertures and placement only")
        f = ctx.number(raw, "focal_length", path, allow_inf=True)
        if abs(f) < 1.0 / MAX_ABS:
            raise ctx.err(f"{path}.focal_length", f, f"|value| must be >= {1 / MAX_ABS:g} (inf for no power)")
        s.interaction = "paraxial"
        s.power = 0.0 if math.isinf(f) else 1.0 / f
    elif "focal_length" in raw:
        raise ctx.err(f"{path}.focal_length", raw["focal_length"], 'only for type = "paraxial"')
    # Shape.
    if "radius" in raw and "curvature" in raw:
        raise ctx.err(f"{path}.curvature", raw["curvature"], "give radius or curvature, not both")
    if "radius" in raw:
        r = ctx.number(raw, "radius", path, allow_inf=True)
        if abs(r) < 1.0 / MAX_ABS:  # its reciprocal, the curvature, must stay within MAX_ABS
            raise ctx.err(f"{path}.radius", r, f"|value| must be >= {1 / MAX_ABS:g} (use inf for a flat surface)")
        s.curvature = 0.0 if math.isinf(r) else 1.0 / r
    elif "curvature" in raw:
        s.curvature = ctx.number(raw, "curvature", path)
    s.conic = ctx.number(raw, "conic", path, 0.0)
    if "asphere" in raw:
        tab = ctx.table(raw, "asphere", path)
        for k, v in tab.items():
            m = re.match(r"^A(\d+)$", k)
            if not m or int(m.group(1)) not in ASPHERE_ORDERS:
                raise ctx.err(f"{path}.asphere.{k}", v, "allowed keys A4, A6, A8, A10, A12, A14, A16")
            s.asphere[int(m.group(1))] = ctx.number(tab, k, f"{path}.asphere")
        if stype not in (None, "even_asphere"):
            raise ctx.err(f"{path}.asphere", tab, f"not allowed on a surface of type {stype!r}")
    if "xy" in raw:
        tab = ctx.table(raw, "xy", path)
        for k, v in tab.items():
            m = _XY_RE.match(k)
            if not m:
                raise ctx.err(f"{path}.xy.{k}", v, "keys are x<i>y<j>, e.g. x2y0, x0y3")
            ij = (int(m.group(1)), int(m.group(2)))
            if not 1 <= sum(ij) <= XY_MAX_ORDER:
                raise ctx.err(f"{path}.xy.{k}", v, f"total order i+j must be 1..{XY_MAX_ORDER}")
            s.xy[ij] = ctx.number(tab, k, f"{path}.xy")
        if stype not in (None, "xy_polynomial"):
            raise ctx.err(f"{path}.xy", tab, f"not allowed on a surface of type {stype!r}")
    if "norm_radius" in raw:
        if not s.xy:
            raise ctx.err(f"{path}.norm_radius", raw["norm_radius"], "only used with xy coefficients")
        s.norm_radius = ctx.number(raw, "norm_radius", path, positive=True)
        if s.norm_radius < 1.0 / MAX_ABS:
            raise ctx.err(f"{path}.norm_radius", s.norm_radius, f"must be >= {1 / MAX_ABS:g}")
    s.thickness = ctx.number(raw, "thickness", path, 0.0)

    # Interaction and media.
    flags = [k for k in ("mirror", "tir", "dummy") if ctx.boolean(raw, k, path)]
    if len(flags) > 1:
        raise ctx.err(f"{path}.{flags[1]}", True, f"conflicts with {flags[0]} = true")
    if flags and s.interaction == "break":
        raise ctx.err(f"{path}.{flags[0]}", True, "not allowed on a coordinate break")
    if flags:
        s.interaction = {"mirror": "reflect", "tir": "tir", "dummy": "none"}[flags[0]]
    if s.interaction == "reflect" and "material" in raw:
        raise ctx.err(f"{path}.material", raw["material"], "a mirror keeps the medium; remove material")
    if s.interaction != "paraxial":
        s.material = _material(ctx, raw, "material", path, AIR)

    # Apertures.
    if "semi_diameter" in raw:
        s.semi_diameter = ctx.number(raw, "semi_diameter", path, positive=True)
    if "aperture" in raw:
        tab = ctx.table(raw, "aperture", path)
        ap_path = f"{path}.aperture"
        kind = tab.get("type", MISSING)
        if kind == "circular":
            ctx.no_unknown(tab, {"type", "radius", "decenter"}, ap_path)
            s.aperture = Aperture("circular", radius=ctx.number(tab, "radius", ap_path, positive=True),
                                  decenter=ctx.vector(tab, "decenter", ap_path, 2, (0.0, 0.0)))
        elif kind == "rectangular":
            ctx.no_unknown(tab, {"type", "half_width", "decenter"}, ap_path)
            hw = ctx.vector(tab, "half_width", ap_path, 2, MISSING)
            if min(hw) <= 0:
                raise ctx.err(f"{ap_path}.half_width", list(hw), "both half-widths must be > 0")
            s.aperture = Aperture("rectangular", half_width=hw,
                                  decenter=ctx.vector(tab, "decenter", ap_path, 2, (0.0, 0.0)))
        else:
            raise ctx.err(f"{ap_path}.type", kind, "allowed: 'circular', 'rectangular'")
    elif s.semi_diameter is not None:
        s.aperture = Aperture("circular", radius=s.semi_diameter)
    s.stop = ctx.boolean(raw, "stop", path)
    s.virtual = ctx.boolean(raw, "virtual", path)

    # Placement.
    s.decenter = ctx.vector(raw, "decenter", path, 2, (0.0, 0.0))
    s.tilt = ctx.vector(raw, "tilt", path, 3, (0.0, 0.0, 0.0))
    if any(abs(t) > 360.0 for t in s.tilt):
        raise ctx.err(f"{path}.tilt", list(s.tilt), "tilt angles are degrees within [-360, 360]")
    if s.interaction != "break":
        s.return_axis = ctx.boolean(raw, "return_axis", path, True)
    if "global_position" in raw:
        s.global_position = ctx.vector(raw, "global_position", path, 3, MISSING)
    if "same_as" in raw:
        ref = raw["same_as"]
        if not isinstance(ref, str) or ref not in names:
            raise ctx.err(f"{path}.same_as", ref, "must name an earlier surface")
        j = names[ref]
        shape_keys = {"radius", "curvature", "conic", "asphere", "xy", "norm_radius", "decenter",
                      "tilt", "global_position", "type"} & set(raw)
        if shape_keys:
            k = sorted(shape_keys)[0]
            raise ctx.err(f"{path}.{k}", raw[k], "a same_as surface takes its shape and frame from the original")
        s.same_as = j
    if "array" in raw:
        if not isinstance(raw["array"], str) or raw["array"] not in arrays:
            raise ctx.err(f"{path}.array", raw["array"],
                          f"no such lenslet array; defined: {', '.join(sorted(arrays)) or 'none'}")
        s.array = raw["array"]
    return s


def clear_extent(s: Surface, arrays) -> tuple[float | None, str | None]:
    """(largest distance from the axis a ray may meet ``s`` at, the key that sets it): its
    clear aperture's (or semi-diameter's) reach, within one lenslet cell on an array; None
    where nothing bounds it."""
    extent = None
    key = None
    if s.aperture is not None:
        extent, key = s.aperture.extent(), "aperture" if s.semi_diameter is None else "semi_diameter"
    if s.array is not None:
        a = arrays[s.array]
        cell = 0.5 * math.hypot(*a.pitch)
        extent = cell if extent is None else min(extent, cell)
        key = key or "array"
    return extent, key


def curvature_limit(surfaces, i: int, arrays) -> float:
    """The largest |curvature| surface ``i``'s base conic may take and still reach the clear
    extent of ``i`` and of every surface that shares its shape (``same_as``):
    ``1 / (extent·√(1 + k))``; inf where nothing bounds it (no extent, or 1 + k ≤ 0)."""
    lim = math.inf
    k = surfaces[i].conic
    for j, s in enumerate(surfaces):
        if j != i and s.same_as != i:
            continue
        extent, _ = clear_extent(s, arrays)
        if extent and 1.0 + k > 0.0:
            lim = min(lim, 1.0 / (extent * math.sqrt(1.0 + k)))
    return lim


def _check_reach(ctx: _Ctx, s: Surface, shape: Surface, i: int, arrays):
    """A clear aperture must lie inside the domain of the base conic."""
    extent, key = clear_extent(s, arrays)
    if extent is None or shape.curvature == 0.0:
        return
    ce = shape.curvature * extent  # products, not powers: huge values give inf, not OverflowError
    lim = 1.0 - (1.0 + shape.conic) * ce * ce
    if lim < 0.0:
        reach = 1.0 / (abs(shape.curvature) * math.sqrt(1.0 + shape.conic))
        value = s.semi_diameter if key == "semi_diameter" else round(extent, 9)
        raise ctx.err(f"surfaces[{i}].{key}", value,
                      f"the surface (radius {1 / shape.curvature:g}, conic {shape.conic:g}) "
                      f"reaches only {reach:.6g} mm from its axis")


def ini_from_dict(data: dict, system: System, file: str = "<dict>"):
    """The validated ``[ini]`` section (:class:`~lfsim.design.ini_section.IniSpec`) or None."""
    from .ini_section import parse_ini

    return parse_ini(_Ctx(file), data, system)


def optimize_from_dict(data: dict, system: System, ini=None, file: str = "<dict>"):
    """The validated ``[optimize]`` section (:class:`~lfsim.design.optimize_section.OptimizeSpec`) or None."""
    from .optimize_section import parse_optimize

    return parse_optimize(_Ctx(file), data, system, ini)


def system_from_dict(data: dict, file: str = "<dict>") -> System:
    """Validate a parsed design table and build the optics ``System``."""
    with surface_names(data):
        return _system_from_dict(data, file)


def _system_from_dict(data: dict, file: str) -> System:
    ctx = _Ctx(file)
    if not isinstance(data, dict):
        raise ctx.err("", data, "a design file must be a TOML table")
    if "surfaces" not in data and ("objects" in data or "view" in data or "scene" in data):
        key = next(k for k in ("objects", "scene", "view") if k in data)
        raise ctx.err(key, "[...]", "this is a content scene ([[objects]] or [scene], with [view]), not a "
                      "design: pass it as --content, and a design file (with [[surfaces]]) as DESIGN")
    ctx.no_unknown(data, TOP_KEYS, "")

    arrays: dict[str, LensletArray] = {}
    for aname, tab in ctx.table(data, "arrays", "", {}).items():
        path = f"arrays.{aname}"
        if not isinstance(tab, dict):
            raise ctx.err(path, tab, "expected a table")
        if not _NAME_RE.match(aname):
            raise ctx.err(path, aname, "array names are letters, digits, '_' or '-'")
        ctx.no_unknown(tab, {"m", "n", "pitch", "center"}, path)
        pitch = ctx.vector(tab, "pitch", path, 2, MISSING)
        if min(pitch) <= 0:
            raise ctx.err(f"{path}.pitch", tab.get("pitch"), "pitch must be > 0")
        arrays[aname] = LensletArray(aname, ctx.integer(tab, "m", path), ctx.integer(tab, "n", path),
                                     pitch, ctx.vector(tab, "center", path, 2, (0.0, 0.0)))

    raw_surfaces = data.get("surfaces", MISSING)
    if not isinstance(raw_surfaces, list) or len(raw_surfaces) < 1:
        raise ctx.err("surfaces", raw_surfaces, "need at least one [[surfaces]] entry (the last is the image)")
    names: dict[str, int] = {}
    surfaces: list[Surface] = []
    for i, raw in enumerate(raw_surfaces):
        s = _surface(ctx, raw, i, names, arrays)
        names[s.name] = i
        surfaces.append(s)
    if array_names := {s.array for s in surfaces if s.array}:
        for a in array_names:
            idx = [i for i, s in enumerate(surfaces) if s.array == a]
            if idx != list(range(idx[0], idx[-1] + 1)):
                raise ctx.err(f"surfaces[{idx[0]}].array", a, "the surfaces of an array must be consecutive")
    for a in arrays:
        if a not in array_names:
            raise ctx.err(f"arrays.{a}", a, "declared but used by no surface")
    stops = [i for i, s in enumerate(surfaces) if s.stop]
    if len(stops) > 1:
        raise ctx.err(f"surfaces[{stops[1]}].stop", True, f"only one stop allowed (also surfaces[{stops[0]}])")
    if surfaces[-1].interaction == "break":
        raise ctx.err(f"surfaces[{len(surfaces) - 1}].type", "coordinate_break", "the last surface is the image")
    for i, s in enumerate(surfaces):
        _check_reach(ctx, s, surfaces[s.same_as] if s.same_as is not None else s, i, arrays)

    # Object space and system data.
    obj = ctx.table(data, "object", "", {})
    ctx.no_unknown(obj, {"distance", "material"}, "object")
    sysd = ctx.table(data, "system", "", {})
    ctx.no_unknown(sysd, {"aperture", "field", "wavelengths_nm", "primary_wavelength_nm"}, "system")
    system = System(surfaces=surfaces, arrays=arrays, name=str(data.get("name", Path(file).stem)))
    system.object_distance = ctx.number(obj, "distance", "object", math.inf, allow_inf=True, positive=True)
    system.object_material = _material(ctx, obj, "material", "object", AIR)

    ap = ctx.table(sysd, "aperture", "system", {"type": "epd", "value": 0.0})
    ctx.no_unknown(ap, {"type", "value"}, "system.aperture")
    if ap.get("type") not in ("epd", "fno", "na"):
        raise ctx.err("system.aperture.type", ap.get("type", MISSING), "allowed: 'epd', 'fno', 'na'")
    system.aperture_type = ap["type"]
    system.aperture_value = ctx.number(ap, "value", "system.aperture", nonneg=True)
    if system.aperture_type == "na" and not system.aperture_value < 1.0 * system.object_material.nd:
        raise ctx.err("system.aperture.value", system.aperture_value, "an NA must be below the object index")
    if system.aperture_type == "fno" and not system.aperture_value > 0:
        # F/0 is an infinite pupil; first order would take it as an entrance pupil of 0 mm
        raise ctx.err("system.aperture.value", system.aperture_value, "an f-number must be > 0")
    if system.aperture_type == "na" and math.isinf(system.object_distance):
        # the NA sets the pupil through the object distance: first order would take 0 mm
        raise ctx.err("system.aperture", ap, f"an object-space NA ({system.aperture_value:g}) needs a finite "
                      "object, and [object] distance = inf (the default when absent) would give an entrance "
                      "pupil of 0 mm; give the aperture as epd or fno, or put the object at a finite distance")

    fld = ctx.table(sysd, "field", "system", {"type": "angle", "values": [0.0]})
    ctx.no_unknown(fld, {"type", "values"}, "system.field")
    if fld.get("type") not in ("angle", "height"):
        raise ctx.err("system.field.type", fld.get("type", MISSING), "allowed: 'angle', 'height'")
    vals = fld.get("values", MISSING)
    if not isinstance(vals, list) or not vals or any(
        isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) for v in vals
    ):
        raise ctx.err("system.field.values", vals, "a non-empty list of finite numbers")
    if fld["type"] == "angle" and any(abs(v) >= 90 for v in vals):
        raise ctx.err("system.field.values", vals, "field angles must be within (-90, 90) degrees")
    if fld["type"] == "height" and math.isinf(system.object_distance):
        raise ctx.err("system.field.type", "height", "an object at infinity needs field type 'angle'")
    system.field_type, system.fields = fld["type"], [float(v) for v in vals]

    wl = sysd.get("wavelengths_nm", [587.5618])
    if not isinstance(wl, list) or not wl or any(
        isinstance(v, bool) or not isinstance(v, (int, float)) or not (200.0 <= v <= 20000.0) for v in wl
    ):
        raise ctx.err("system.wavelengths_nm", wl, "a non-empty list of wavelengths in nm (200..20000)")
    system.wavelengths_nm = [float(v) for v in wl]
    system.primary_wavelength_nm = ctx.number(sysd, "primary_wavelength_nm", "system",
                                              system.wavelengths_nm[len(wl) // 2], positive=True)
    if not 200.0 <= system.primary_wavelength_nm <= 20000.0:
        raise ctx.err("system.primary_wavelength_nm", system.primary_wavelength_nm, "a wavelength in nm (200..20000)")
    lams = system.wavelengths_nm + [system.primary_wavelength_nm]
    media = [("object.material", system.object_material)] + [(f"surfaces[{i}].material", s.material)
                                                              for i, s in enumerate(surfaces)]
    for key, m in media:
        for lam in lams:
            if not m.in_range(lam):
                raise ctx.err(key, m.name, f"its dispersion data cover {m.range_nm[0]:g}-{m.range_nm[1]:g} nm, "
                              f"not {lam:g} nm")
            n = m.index(lam)
            if not (math.isfinite(n) and n > 0):
                raise ctx.err(key, m.name, f"its index at {lam:g} nm is {n!r}: must be a finite number > 0")
    _check_crossings(ctx, system)
    return system


def _check_crossings(ctx, system: System) -> None:
    """Refuse neighbouring faces (a glass element, or an air gap) that cross inside their clear
    apertures."""
    from ..optics.solids import crossings

    for i, j, r, t, glass in crossings(system)[:1]:
        a, b = system.surfaces[i], system.surfaces[j]
        what = "the glass between them is" if glass else "the air gap between them is"
        raise ctx.err(f"surfaces[{i}].thickness", a.thickness,
                      f"surfaces {a.name!r} and {b.name!r} cross inside their clear apertures: {what} "
                      f"{t:.6g} mm thick at radial height {round(r, 3) + 0.0:.4g} mm (set virtual = true on "
                      f"one of them if this geometry is deliberate)")
