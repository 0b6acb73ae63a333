"""The ``[ini]`` section of a design file: what makes a sequential table an InI-HMD.

Schema (units mm, diopters)::

    [ini]
    mla = "mla"                     # the [arrays.NAME] of the lenslets (its surfaces
                                    # must come first in the table, untilted)
    pixel_pitch = 0.008             # display pixel pitch
    pixels_per_ei = [125, 125]      # pixels per elemental image (x, y)
    cdp_diopters = [0.0, 1.0, 3.0]  # virtual CDP depths (0 = infinity); without a
                                    # tunable lens: the one depth the geometry makes
    viewing_window = "VW"           # default: the last surface; its local +z is the
                                    # line of sight, (x, y) the viewing-window plane
    aperture_array = "AA"           # optional: a member surface of the MLA group whose
                                    # aperture is each sub-system's stop (default: the
                                    # group's first refracting surface, the lenslet face)
    [ini.tunable]                   # optional
    surface = "TL"                  # a type = "paraxial" surface
    power_diopters = [..]           # optional, one per depth; omitted: solved paraxially
    range_diopters = [-5.0, 5.0]    # optional: allowed power range
    [ini.eye]
    model = "ideal"                 # ideal lens at the viewing window, focused on the CDP
    pupil_diameter = 4.0
    [ini.analysis]                  # sampling of `lfsim analyze` (all optional)
    fields = 3                      # field points per EI axis (3 → 9 fields)
    field_fraction = 1.0            # outer fields at this fraction of the edge pixel
    refine = 2                      # levels of the search for each EI's worst contrast
                                    # around its worst grid field (0: the grid only)
    stride = [1, 1]                 # evaluate every k-th lenslet along x, y
    symmetry = "none"               # "x": mirror-symmetric in x (about the y-z plane)
                                    # → only lenslets with x >= 0; "y", "xy" likewise
    pupil = 8                       # Gauss–Legendre nodes per pupil axis (RMS, geometric MTF)
    mtf_grid = 32                   # pupil grid per axis of the diffraction MTF (FFT)
    pa_target = 0.3                 # Eq. (12) threshold counted in pa_within_target
    gd_target_deg = 0.75

The section is validated here (file, key, value, what is allowed); the InI model
itself lives in :mod:`lfsim.ini`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from ..optics.prescription import System
from .errors import MISSING
from .loader import MAX_ABS

INI_KEYS = {"mla", "pixel_pitch", "pixels_per_ei", "cdp_diopters", "viewing_window",
            "aperture_array", "tunable", "eye", "analysis"}
EYE_MODELS = ("ideal",)
SYMMETRIES = ("none", "x", "y", "xy")


@dataclass
class IniSpec:
    """Validated ``[ini]`` section (surface references resolved to indices)."""

    mla: str
    pixel_pitch: float
    pixels_per_ei: tuple[int, int]
    cdp_diopters: list[float] | None  # None: the geometry's own depth (no tunable lens)
    viewing_window: int
    stop: int  # surface index of each sub-system's stop (lenslet-relative aperture)
    mla_surfaces: list[int]
    tunable: int | None = None
    tunable_power_diopters: list[float] | None = None
    tunable_range_diopters: tuple[float, float] | None = None
    eye_model: str = "ideal"
    pupil_diameter: float = 4.0
    fields: int = 3
    refine: int = 2
    field_fraction: float = 1.0
    stride: tuple[int, int] = (1, 1)
    symmetry: str = "none"
    pupil: int = 8
    mtf_grid: int = 32
    pa_target: float = 0.3
    gd_target_deg: float = 0.75
    extra: dict = field(default_factory=dict)


def _surface_ref(ctx, tab, key, path, names, default=MISSING):
    v = tab.get(key, default)
    if v is MISSING:
        raise ctx.err(f"{path}.{key}", MISSING, "required: a surface name")
    if not isinstance(v, str) or v not in names:
        raise ctx.err(f"{path}.{key}", v, f"no such surface; surfaces: {', '.join(names)}")
    return names[v]


def parse_ini(ctx, data: dict, system: System) -> IniSpec | None:
    """Validate ``data['ini']`` against ``system``; None when the design has no [ini]."""
    if "ini" not in data:
        return None
    tab = ctx.table(data, "ini", "")
    ctx.no_unknown(tab, INI_KEYS, "ini")
    names = {s.name: i for i, s in enumerate(system.surfaces)}

    mla = tab.get("mla", MISSING)
    if not isinstance(mla, str) or mla not in system.arrays:
        raise ctx.err("ini.mla", mla, f"must name a lenslet array; defined: {', '.join(system.arrays) or 'none'}")
    members = system.array_groups()[mla]
    if members[0] != 0:
        raise ctx.err("ini.mla", mla, "the lenslet array must be the first surfaces of the table "
                      "(the display is the object)")
    for i in members:
        s = system.surfaces[i]
        if any(s.tilt) or any(s.decenter) or s.global_position is not None or s.interaction == "break":
            raise ctx.err(f"surfaces[{i}].tilt", list(s.tilt), "lenslet surfaces of the InI MLA must be "
                          "untilted and undecentered (move the array with arrays.NAME.center)")
    pixel = ctx.number(tab, "pixel_pitch", "ini", positive=True)
    ppe = tab.get("pixels_per_ei", MISSING)
    if (not isinstance(ppe, list) or len(ppe) != 2
            or any(isinstance(v, bool) or not isinstance(v, int) or v < 1 for v in ppe)):
        raise ctx.err("ini.pixels_per_ei", ppe, "expected [px, py], two integers >= 1")

    vw = _surface_ref(ctx, tab, "viewing_window", "ini", names, system.surfaces[-1].name)
    vws = system.surfaces[vw]
    if vws.curvature != 0 or vws.xy or vws.asphere or vws.interaction not in ("none", "refract"):
        raise ctx.err("ini.viewing_window", vws.name, "the viewing window must be a plane dummy surface")
    if vw <= members[-1]:
        raise ctx.err("ini.viewing_window", vws.name, "must come after the lenslet array")
    # Default stop: the lenslet's first face (the first member that refracts; an aperture
    # array on the display side, a dummy member, is then one more clipping aperture).
    stop = next((i for i in members if system.surfaces[i].interaction == "refract"), members[0])
    if "aperture_array" in tab:
        stop = _surface_ref(ctx, tab, "aperture_array", "ini", names)
        if stop not in members or system.surfaces[stop].aperture is None:
            raise ctx.err("ini.aperture_array", tab["aperture_array"],
                          f"must be a surface of array {mla!r} with an aperture")

    spec = IniSpec(mla=mla, pixel_pitch=pixel, pixels_per_ei=(ppe[0], ppe[1]), cdp_diopters=None,
                   viewing_window=vw, stop=stop, mla_surfaces=list(members))

    if "tunable" in tab:
        tt = ctx.table(tab, "tunable", "ini")
        ctx.no_unknown(tt, {"surface", "power_diopters", "range_diopters"}, "ini.tunable")
        spec.tunable = _surface_ref(ctx, tt, "surface", "ini.tunable", names)
        ts = system.surfaces[spec.tunable]
        if ts.interaction != "paraxial":
            raise ctx.err("ini.tunable.surface", ts.name, 'must be a type = "paraxial" surface')
        if not members[-1] < spec.tunable < vw:
            raise ctx.err("ini.tunable.surface", ts.name, "must lie between the MLA and the viewing window")
        if "range_diopters" in tt:
            lo, hi = ctx.vector(tt, "range_diopters", "ini.tunable", 2, MISSING)
            if not lo < hi:
                raise ctx.err("ini.tunable.range_diopters", [lo, hi], "expected [low, high] with low < high")
            spec.tunable_range_diopters = (lo, hi)

    depths = tab.get("cdp_diopters", None)
    if depths is not None:
        if (not isinstance(depths, list) or not depths
                or any(isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v < 0
                       or v > MAX_ABS for v in depths)):
            raise ctx.err("ini.cdp_diopters", depths, f"a non-empty list of depths in diopters, each >= 0 "
                          f"(and <= {MAX_ABS:g})")
        if len(set(depths)) != len(depths):
            raise ctx.err("ini.cdp_diopters", depths, "depths must be distinct")
        spec.cdp_diopters = [float(v) for v in depths]
    if spec.tunable is None and depths is not None and len(depths) != 1:
        raise ctx.err("ini.cdp_diopters", depths, "without [ini.tunable] the geometry fixes one CDP depth")
    if spec.tunable is not None and depths is None:
        raise ctx.err("ini.cdp_diopters", MISSING, "required with a tunable lens: the depths it serves")
    if spec.tunable is not None and "power_diopters" in tab["tunable"]:
        pw = tab["tunable"]["power_diopters"]
        if (not isinstance(pw, list) or len(pw) != len(spec.cdp_diopters)
                or any(isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v)
                       or abs(v) > MAX_ABS for v in pw)):
            raise ctx.err("ini.tunable.power_diopters", pw,
                          f"one finite power (diopters, |p| <= {MAX_ABS:g}) per CDP depth ({len(spec.cdp_diopters)})")
        spec.tunable_power_diopters = [float(v) for v in pw]

    eye = ctx.table(tab, "eye", "ini", {})
    ctx.no_unknown(eye, {"model", "pupil_diameter"}, "ini.eye")
    spec.eye_model = eye.get("model", "ideal")
    if spec.eye_model not in EYE_MODELS:
        raise ctx.err("ini.eye.model", spec.eye_model, f"allowed: {', '.join(EYE_MODELS)}")
    spec.pupil_diameter = ctx.number(eye, "pupil_diameter", "ini.eye", 4.0, positive=True)

    an = ctx.table(tab, "analysis", "ini", {})
    ctx.no_unknown(an, {"fields", "refine", "field_fraction", "stride", "symmetry", "pupil", "mtf_grid",
                        "pa_target", "gd_target_deg"}, "ini.analysis")
    if "fields" in an:
        spec.fields = ctx.integer(an, "fields", "ini.analysis", 1)
        if spec.fields % 2 == 0:
            raise ctx.err("ini.analysis.fields", spec.fields, "must be odd (the EI centre is a field)")
    if "refine" in an:
        spec.refine = ctx.integer(an, "refine", "ini.analysis", 0)
        if spec.refine > 12:
            raise ctx.err("ini.analysis.refine", spec.refine, "must be in 0..12 (level L halves the step L times)")
    spec.field_fraction = ctx.number(an, "field_fraction", "ini.analysis", 1.0, positive=True)
    if spec.field_fraction > 1:
        raise ctx.err("ini.analysis.field_fraction", spec.field_fraction, "must be in (0, 1]")
    if "stride" in an:
        st = an["stride"]
        if not isinstance(st, list) or len(st) != 2 or any(
                isinstance(v, bool) or not isinstance(v, int) or v < 1 for v in st):
            raise ctx.err("ini.analysis.stride", st, "expected [sx, sy], two integers >= 1")
        spec.stride = (st[0], st[1])
    spec.symmetry = an.get("symmetry", "none")
    if spec.symmetry not in SYMMETRIES:
        raise ctx.err("ini.analysis.symmetry", spec.symmetry, f"allowed: {', '.join(SYMMETRIES)}")
    if "pupil" in an:
        spec.pupil = ctx.integer(an, "pupil", "ini.analysis", 2)
    if "mtf_grid" in an:
        spec.mtf_grid = ctx.integer(an, "mtf_grid", "ini.analysis", 8)
    spec.pa_target = ctx.number(an, "pa_target", "ini.analysis", 0.3, positive=True)
    spec.gd_target_deg = ctx.number(an, "gd_target_deg", "ini.analysis", 0.75, positive=True)
    return spec
