"""From a loaded design to a format-neutral list of surfaces and coordinate breaks.

Every surface keeps its shape; its placement is rebuilt from the global frames the
tracer uses (:func:`surface_frames`): where a surface's frame is not the one the
running chain reaches, a coordinate break (Zemax ``COORDBRK``; a decentred dummy
surface in CODE V) moves the chain there, with the z offset put into the thickness
before it. A chain that needs no break keeps the design's thickness values as they
are, so coaxial designs are written number for number.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from ...optics.materials import AIR, lookup
from ...optics.prescription import Aperture
from .common import euler_xyz, surface_frames


@dataclass
class Out:
    name: str
    kind: str = "surface"  # "surface", "break", "paraxial"
    curvature: float = 0.0
    conic: float = 0.0
    asphere: dict = field(default_factory=dict)
    xy: dict = field(default_factory=dict)
    norm_radius: float = 1.0
    thickness: float = 0.0
    glass: object = None  # the medium after: None (air), a name, {nd, vd} or {n}
    mirror: bool = False
    stop: bool = False
    aperture: Aperture | None = None
    semi_diameter: float | None = None
    decenter: tuple | None = None  # (dx, dy, dz, tx, ty, tz), lfsim tilt convention
    dar: bool = False
    image: bool = False
    focal_length: float = math.inf
    notes: list = field(default_factory=list)


@dataclass
class Plan:
    system: object
    entries: list
    object_glass: object
    notes: list


def _material_value(raw_value, material):
    """The design file's own spelling of a medium (None for air)."""
    if material is AIR or material.name == "air":
        return None
    if isinstance(raw_value, bool) or raw_value is None:
        return material.name
    if isinstance(raw_value, (int, float)):
        return {"n": float(raw_value)}
    if isinstance(raw_value, dict):
        return {k: float(v) for k, v in raw_value.items()}
    if isinstance(raw_value, str) and raw_value.strip().lower() == "air":
        return None
    return str(raw_value)


def lenslet_offset(system, name: str, lenslet) -> tuple[float, float]:
    a = system.arrays[name]
    m, n = lenslet
    return (a.center[0] + (m - (a.m - 1) / 2) * a.pitch[0], a.center[1] + (n - (a.n - 1) / 2) * a.pitch[1])


def plan(design, lenslet: tuple[int, int] | None = None) -> Plan:
    """The export plan of ``design`` (lenslet (m, n), 0-based, selects one sub-system of an array)."""
    system = design.system
    raw_surfaces = design.raw.get("surfaces", [])
    if system.arrays and lenslet is None:
        names = ", ".join(sorted(system.arrays))
        raise ValueError(f"{design.path}: the design has lenslet arrays ({names}): export one sub-system with "
                         "--lenslet M,N (0-based lenslet indices)")
    if lenslet is not None:
        if not system.arrays:
            raise ValueError(f"--lenslet {lenslet[0]},{lenslet[1]}: {design.path} has no lenslet array")
        for a in system.arrays.values():
            if not (0 <= lenslet[0] < a.m and 0 <= lenslet[1] < a.n):
                raise ValueError(f"--lenslet {lenslet[0]},{lenslet[1]}: array {a.name!r} has lenslets "
                                 f"0..{a.m - 1}, 0..{a.n - 1}")
    if system.aperture_type == "na" and math.isinf(system.object_distance):
        raise ValueError(f"{design.path}: [system] aperture is an object-space NA ({system.aperture_value:g}) and "
                         "[object] distance = inf: an object at infinity has no NA (lfsim takes it as an entrance "
                         "pupil of 0 mm) and lfsim's import refuses CODE V NAO and Zemax OBNA so; give the "
                         "aperture as epd or fno")
    frames, after = surface_frames(system)
    obj_raw = design.raw.get("object", {})
    object_glass = _material_value(obj_raw.get("material"), system.object_material)
    medium = object_glass
    E_R, E_o = np.eye(3), np.zeros(3)  # where the written chain stands (after the pending thickness)
    entries: list[Out] = []
    notes: list[str] = []
    ini = getattr(design, "ini", None)
    if ini is not None and ini.tunable is not None:
        s_t = system.surfaces[ini.tunable]
        power = f" ({1000.0 * s_t.power:.6g} D)" if s_t.interaction == "paraxial" else ""
        notes.append(f"the tunable lens is written at the design file's own setting{power}; each CDP state "
                     "has its own power (lfsim ini DESIGN lists them)")
    last = len(system.surfaces) - 1
    for i, s in enumerate(system.surfaces):
        if getattr(s, "virtual", False):
            raise ValueError(f"{design.path}: surfaces[{i}] ({s.name}) is virtual (rays may meet it behind "
                             "their start): neither lens-file format has that; export the design without it")
        if s.interaction == "break":
            continue
        G_R, G_o = frames[i]
        ap = s.aperture
        sd = s.semi_diameter
        if s.array is not None and lenslet is not None:
            ox, oy = lenslet_offset(system, s.array, lenslet)
            G_o = G_o + G_R @ np.array([ox, oy, 0.0])
            a = system.arrays[s.array]
            if ap is None:
                ap = Aperture("rectangular", half_width=(a.pitch[0] / 2, a.pitch[1] / 2))
                sd = None
        if not (np.array_equal(G_R, E_R) and np.array_equal(G_o, E_o)):
            rel_R = E_R.T @ G_R
            rel_t = E_R.T @ (G_o - E_o)
            if entries:
                entries[-1].thickness += rel_t[2]
            elif abs(rel_t[2]) > 0:
                raise ValueError(f"{design.path}: surfaces[{i}] ({s.name}) is not at the first vertex: the "
                                 "object distance cannot move it")
            tx, ty, tz = euler_xyz(rel_R)
            brk = Out(f"{s.name}_place", kind="break", glass=medium,
                      decenter=(float(rel_t[0]), float(rel_t[1]), 0.0, tx, ty, tz))
            entries.append(brk)
            E_R, E_o = G_R, G_o
        shape = system.surfaces[s.same_as] if s.same_as is not None else s
        e = Out(s.name, curvature=shape.curvature, conic=shape.conic, asphere=dict(shape.asphere),
                xy=dict(shape.xy), norm_radius=shape.norm_radius, stop=s.stop, aperture=ap, semi_diameter=sd,
                image=(i == last))
        raw_s = raw_surfaces[i] if i < len(raw_surfaces) and isinstance(raw_surfaces[i], dict) else {}
        if s.interaction == "paraxial":
            e.kind = "paraxial"
            e.focal_length = math.inf if s.power == 0 else 1.0 / s.power
            e.glass = medium
        elif s.interaction in ("reflect", "tir"):
            e.mirror = True
            e.glass = medium
            if s.interaction == "tir":
                e.notes.append("total internal reflection, written as a mirror")
                notes.append(f"{s.name}: total internal reflection written as a mirror")
        elif s.interaction == "none":
            e.glass = medium
        else:
            medium = _material_value(raw_s.get("material"), s.material)
            e.glass = medium
        entries.append(e)
        A_R, A_o = after[i]
        e.thickness = 0.0
        if not (np.array_equal(A_R, G_R) and np.array_equal(A_o, G_o)):
            rel_R = G_R.T @ A_R
            rel_t = G_R.T @ (A_o - G_o)
            e.thickness = float(rel_t[2])
            tx, ty, tz = euler_xyz(rel_R)
            entries.append(Out(f"{s.name}_return", kind="break", glass=medium,
                               decenter=(float(rel_t[0]), float(rel_t[1]), 0.0, tx, ty, tz)))
        entries[-1].thickness = s.thickness
        E_R, E_o = A_R, A_o + A_R @ np.array([0.0, 0.0, s.thickness])
    for e in entries:
        if e.decenter is not None and not any(e.decenter):
            e.decenter = None
    return Plan(system, entries, object_glass, notes)


def same_index(a, b, wavelengths) -> bool:
    """Whether two material values give the same index at every wavelength, to 1e-12: one catalog
    formula evaluated two ways differs by rounding (N-BK7: 2e-16), glasses of one name in two
    vendor catalogs by 1e-6 and more."""
    try:
        ma, mb = lookup(a), lookup(b)
    except Exception:
        return False
    return all(abs(ma.index(w) - mb.index(w)) <= 1e-12 for w in wavelengths)
