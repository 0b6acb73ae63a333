"""The lens data table of a prescription, as lens-design programs print it.

One row per surface (the object first): number and name, type, radius, thickness,
the medium after the surface with its nd and Vd (and its index at the table's
wavelength), semi-diameter, conic, the aspheric or XY terms in use, tilts and
decenters, lenslet-array membership and the stop. :func:`lens_table` returns the
rows as JSON-ready dicts; :func:`format_table` lays them out for a terminal.
"""

from __future__ import annotations

import math

from .materials import LAMBDA_D
from .prescription import Surface, System


def surface_type(s: Surface) -> str:
    """The row's type, as a lens-data editor names it."""
    if s.interaction == "break":
        return "coordinate break"
    if s.interaction == "paraxial":
        return "paraxial"
    if s.xy:
        kind = "XY polynomial"
    elif s.asphere:
        kind = "even asphere"
    elif s.curvature == 0.0:
        kind = "plane"
    else:
        kind = "conic" if s.conic else "sphere"
    return "dummy" if s.interaction == "none" and kind == "plane" else kind


def _finite(v: float) -> float | None:
    return float(v) if math.isfinite(v) else None


def _medium(s: Surface, before) -> str:
    if s.interaction == "reflect":
        return "MIRROR"
    if s.interaction == "tir":
        return f"TIR ({before.name})"
    return s.material.name


def semi_diameter(s: Surface) -> float | None:
    """The clear semi-diameter: ``semi_diameter``, else the largest reach of the aperture."""
    if s.semi_diameter is not None:
        return float(s.semi_diameter)
    return None if s.aperture is None else float(s.aperture.extent())


def lens_table(system: System, wavelength_nm: float | None = None) -> dict:
    """The table of ``system``: ``{wavelength_nm, object, surfaces: [...]}``.

    Each surface row: ``number`` (1-based), ``name``, ``type``, ``radius_mm`` (null: flat),
    ``curvature``, ``thickness_mm``, ``material`` (the medium after the surface;
    ``MIRROR`` for a mirror, ``TIR (medium)`` for a total-internal-reflection face),
    ``nd``, ``vd`` (null: non-dispersive), ``n`` (at ``wavelength_nm``, default the
    primary), ``semi_diameter_mm``, ``aperture`` (its kind and size, or null), ``conic``,
    ``asphere`` (``{"A4": ...}``), ``xy`` (``{"x2y0": ...}``, with ``norm_radius_mm``),
    ``power_diopters`` (paraxial), ``decenter_mm``, ``tilt_deg``, ``return_axis``,
    ``global_position_mm``, ``array`` (the lenslet grid or null), ``stop``.
    """
    lam = float(wavelength_nm if wavelength_nm is not None else system.primary_wavelength_nm)
    media = system.media()
    obj = system.object_material
    doc = {"wavelength_nm": lam,
           "object": {"thickness_mm": _finite(system.object_distance), "material": obj.name,
                      "nd": _finite(obj.nd), "vd": _finite(obj.vd), "n": float(obj.index(lam))}}
    rows = []
    for i, s in enumerate(system.surfaces):
        after = media[i + 1]
        arr = system.arrays.get(s.array) if s.array else None
        ap = s.aperture
        rows.append({
            "number": i + 1, "name": s.name, "type": surface_type(s),
            "radius_mm": None if s.curvature == 0.0 else 1.0 / s.curvature, "curvature": s.curvature,
            "thickness_mm": float(s.thickness), "material": _medium(s, media[i]),
            "nd": _finite(after.nd), "vd": _finite(after.vd), "n": float(after.index(lam)),
            "semi_diameter_mm": semi_diameter(s),
            "aperture": None if ap is None else (
                {"kind": "circular", "radius_mm": ap.radius, "decenter_mm": list(ap.decenter)}
                if ap.kind == "circular" else
                {"kind": "rectangular", "half_width_mm": list(ap.half_width), "decenter_mm": list(ap.decenter)}),
            "conic": s.conic,
            "asphere": {f"A{k}": v for k, v in sorted(s.asphere.items()) if v != 0.0},
            "xy": {f"x{i_}y{j}": v for (i_, j), v in sorted(s.xy.items()) if v != 0.0},
            "norm_radius_mm": s.norm_radius if s.xy else None,
            "power_diopters": 1000.0 * s.power if s.interaction == "paraxial" else None,
            "decenter_mm": list(s.decenter), "tilt_deg": list(s.tilt), "return_axis": s.return_axis,
            "global_position_mm": None if s.global_position is None else list(s.global_position),
            "same_as": None if s.same_as is None else system.surfaces[s.same_as].name,
            "array": None if arr is None else {"name": arr.name, "m": arr.m, "n": arr.n,
                                               "pitch_mm": list(arr.pitch), "center_mm": list(arr.center)},
            "stop": bool(s.stop),
        })
    doc["surfaces"] = rows
    return doc


def _g(v: float | None, width: int, spec: str = ".6g") -> str:
    return ("inf" if v is None else format(v, spec)).rjust(width)


def _notes(r: dict) -> str:
    out = []
    if r["asphere"]:
        out.append(" ".join(f"{k} {v:.6g}" for k, v in r["asphere"].items()))
    if r["xy"]:
        out.append(f"XY (R {r['norm_radius_mm']:g}): " + " ".join(f"{k} {v:.6g}" for k, v in r["xy"].items()))
    if r["power_diopters"] is not None:
        out.append(f"power {r['power_diopters']:.6g} D")
    if any(r["decenter_mm"]):
        out.append("decenter " + ", ".join(f"{v:g}" for v in r["decenter_mm"]) + " mm")
    if any(r["tilt_deg"]):
        out.append("tilt " + ", ".join(f"{v:g}" for v in r["tilt_deg"]) + " deg"
                   + ("" if r["return_axis"] else " (no return)"))
    if r["global_position_mm"] is not None:
        out.append("at " + ", ".join(f"{v:g}" for v in r["global_position_mm"]) + " mm (global)")
    if r["same_as"]:
        out.append(f"same as {r['same_as']}")
    a = r["aperture"]
    if a is not None and a["kind"] == "rectangular":
        out.append("rectangular {:g} x {:g} mm".format(*(2 * h for h in a["half_width_mm"])))
    if r["array"]:
        g = r["array"]
        out.append(f"array {g['name']} {g['m']}x{g['n']} @ {g['pitch_mm'][0]:g}x{g['pitch_mm'][1]:g} mm")
    if r["stop"]:
        out.append("STOP")
    return "; ".join(out)


def format_table(doc: dict, title: str = "") -> str:
    """The table as fixed-width text (one line per surface, the terms and placement last)."""
    head = (f"{'#':>3}  {'name':<8} {'type':<16} {'radius':>12} {'thickness':>12} {'material':<14} "
            f"{'nd':>8} {'vd':>6} {'semi-diam':>9} {'conic':>10}  terms, placement")
    lines = [f"# {title + ': ' if title else ''}{len(doc['surfaces'])} surfaces, mm; nd and Vd at the d line "
             f"({LAMBDA_D:g} nm); the material is the medium after each surface", head]
    o = doc["object"]
    glass = o["material"] != "air"
    lines.append(f"{'OBJ':>3}  {'object':<8} {'':<16} {'inf':>12} {_g(o['thickness_mm'], 12)} "
                 f"{o['material']:<14} {format(o['nd'], '.5f') if glass else '':>8} "
                 f"{format(o['vd'], '.2f') if glass and o['vd'] else '':>6}".rstrip())
    for r in doc["surfaces"]:
        vd = "" if r["vd"] is None else f"{r['vd']:.2f}"
        nd = "" if r["material"] in ("air", "MIRROR") else f"{r['nd']:.5f}"
        sd = "" if r["semi_diameter_mm"] is None else f"{r['semi_diameter_mm']:.4g}"
        conic = f"{r['conic']:.6g}" if r["conic"] else ""
        lines.append(f"{r['number']:>3}  {r['name']:<8} {r['type']:<16} {_g(r['radius_mm'], 12)} "
                     f"{r['thickness_mm']:>12.6g} {r['material']:<14} {nd:>8} "
                     f"{vd if nd else '':>6} {sd:>9} {conic:>10}  {_notes(r)}".rstrip())
    return "\n".join(lines)
