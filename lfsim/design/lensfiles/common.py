"""Shared pieces of the lens-file readers and writers: errors, glass names, frames, angles.

No Dr.Jit, no Mitsuba: numpy and the material tables only.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from ...optics.materials import LAMBDA_C, LAMBDA_D, LAMBDA_F, MaterialError, lookup
from ..errors import DesignError

#: A source object/thickness at or beyond this is "at infinity" (CODE V writes 1e10 .. 1e14).
INFINITE_DISTANCE = 1e10


class LensFileError(DesignError):
    """A lens file that cannot be read: ``FILE: line N: what``, one line."""

    def __init__(self, file: str, line: int | None, what: str):
        where = f"line {line}: " if line else ""
        super().__init__(file, "", None, f"{where}{what}")
        self.line = line


def check_complete(text: str, file: str) -> None:
    """Refuse a file cut short: lens programs end every line, the last one too, so text that
    stops inside a line (a copy or download cut off mid-number) is not read."""
    if text and not text.endswith(("\n", "\r")):
        raise LensFileError(file, text.count("\n") + 1, "the file ends inside this line (cut short?): "
                            "lens files end with a line break")


def note_defaults(sysd: dict, notes: list[str], aperture_words: str, wavelength_words: str) -> None:
    """Say which system data the file lacked, so that a defaulted design is not taken as read."""
    if "aperture" not in sysd:
        notes.append(f"no {aperture_words}: the aperture is lfsim's default, an entrance pupil of 0 mm "
                     "(set [system] aperture before tracing ray bundles)")
    if not sysd.get("wavelengths_nm"):
        notes.append(f"no {wavelength_words}: the wavelength is lfsim's default, 587.5618 nm")


#: Length units of CODE V's DIM and Zemax's UNIT, in millimetres.
UNITS_MM = {"MM": 1.0, "M": 1.0, "CM": 10.0, "C": 10.0, "IN": 25.4, "I": 25.4, "METER": 1000.0, "METERS": 1000.0}


def scale_lengths(raw: dict, s: float) -> dict:
    """A design table read in a length unit of ``s`` mm, in millimetres: radii, thicknesses,
    placements, apertures, the EPD and height fields times ``s``; curvatures over ``s``;
    normalized XY terms (sags) times ``s``; even-asphere ``A2i`` times ``s**(1 - 2i)``."""
    if s == 1.0:
        return raw

    def vec(v):
        return [x * s for x in v]

    obj = raw.get("object", {})
    if "distance" in obj:
        obj["distance"] = obj["distance"] * s
    sysd = raw.get("system", {})
    ap = sysd.get("aperture")
    if ap and ap.get("type") == "epd":
        ap["value"] = ap["value"] * s
    fld = sysd.get("field")
    if fld and fld.get("type") == "height":
        fld["values"] = vec(fld["values"])
    for t in raw.get("surfaces", []):
        for k in ("radius", "thickness", "semi_diameter", "norm_radius", "focal_length"):
            if k in t:
                t[k] = t[k] * s
        if "curvature" in t:
            t["curvature"] = t["curvature"] / s
        for k in ("decenter", "global_position"):
            if k in t:
                t[k] = vec(t[k])
        for k in list(t.get("xy", {})):
            t["xy"][k] = t["xy"][k] * s
        for k in list(t.get("asphere", {})):
            t["asphere"][k] = t["asphere"][k] * s ** (1 - int(k[1:]))
        a = t.get("aperture")
        if a:
            for k in ("radius",):
                if k in a:
                    a[k] = a[k] * s
            for k in ("half_width", "decenter"):
                if k in a:
                    a[k] = vec(a[k])
    return raw


# ------------------------------------------------------------------ the model
@dataclass
class Entry:
    """One surface of the lfsim design being built (a ``[[surfaces]]`` table) and its source line."""

    table: dict
    line: int | None = None


@dataclass
class Imported:
    """What a reader found: the design table plus notes for the file's header comment."""

    raw: dict
    notes: list[str] = field(default_factory=list)


def material_value(file: str, line: int | None, name: str, catalogs: tuple[str, ...] = ()):
    """A glass name as a design-file material value, checked now (unknown names fail here).

    ``catalogs``: the vendors the source file names (Zemax ``GCAT``), in order: as in Zemax, the
    name is the glass of the first of them that holds it, spelled NAME_VENDOR unless the name
    alone (lfsim's built-in table first) gives the same indices at the d, F and C lines. A name
    none of them holds is looked up as it is.
    """
    from .export import same_index

    for cat in catalogs:
        try:
            lookup(f"{name}_{cat}")
        except MaterialError:
            continue
        return name if same_index(name, f"{name}_{cat}", (LAMBDA_F, LAMBDA_D, LAMBDA_C)) else f"{name}_{cat}"
    try:
        lookup(name)
        return name
    except MaterialError as first:
        raise LensFileError(file, line, f"glass {name!r}: {' '.join(str(first).split())}") from None


# ------------------------------------------------------------------- numbers
def number(file: str, line: int | None, text: str, what: str) -> float:
    try:
        v = float(text)
    except (TypeError, ValueError):
        raise LensFileError(file, line, f"{what} = {text!r}: expected a number") from None
    if math.isnan(v):
        raise LensFileError(file, line, f"{what} = {text!r}: expected a number")
    return v


def finite(file: str, line: int | None, text: str, what: str) -> float:
    v = number(file, line, text, what)
    if not math.isfinite(v) or abs(v) > 1e15:
        raise LensFileError(file, line, f"{what} = {text!r}: expected a finite number")
    return v


def fmt(v: float) -> str:
    """A float written so that it reads back bit for bit (shortest round-trip repr)."""
    v = float(v)
    if v == 0.0:
        return "0.0" if math.copysign(1.0, v) > 0 else "-0.0"
    return repr(v)


# -------------------------------------------------------------------- angles
def rot_xyz(tx: float, ty: float, tz: float) -> np.ndarray:
    """lfsim's R = Rx·Ry·Rz (degrees, right-handed, active; local → parent)."""
    ax, ay, az = (math.radians(v) for v in (tx, ty, tz))
    cx, sx, cy, sy, cz, sz = math.cos(ax), math.sin(ax), math.cos(ay), math.sin(ay), math.cos(az), math.sin(az)
    return np.array([[cy * cz, -cy * sz, sy],
                     [sx * sy * cz + cx * sz, cx * cz - sx * sy * sz, -sx * cy],
                     [sx * sz - cx * sy * cz, cx * sy * sz + sx * cz, cx * cy]])


def euler_xyz(R: np.ndarray) -> tuple[float, float, float]:
    """Degrees (tx, ty, tz) with ``rot_xyz(tx, ty, tz) == R`` (ty within ±90°)."""
    ty = math.degrees(math.atan2(R[0, 2], math.hypot(R[0, 0], R[0, 1])))
    if math.hypot(R[0, 0], R[0, 1]) < 1e-12:  # gimbal lock: put the whole x-z turn in tx
        tx = math.degrees(math.atan2(R[2, 1], R[1, 1]))
        return _clean(tx), _clean(ty), 0.0
    tx = math.degrees(math.atan2(-R[1, 2], R[2, 2]))
    tz = math.degrees(math.atan2(-R[0, 1], R[0, 0]))
    return _clean(tx), _clean(ty), _clean(tz)


def _clean(a: float) -> float:
    return 0.0 if a == 0.0 else a


# -------------------------------------------------------------------- frames
def surface_frames(system) -> list[tuple[np.ndarray, np.ndarray]]:
    """(R, o) of every surface in the global frame (the tracer's rules, in numpy), and the
    frame the chain continues from after each surface (before its thickness)."""
    R_cur, o_cur = np.eye(3), np.zeros(3)
    frames, after = [], []
    for s in system.surfaces:
        if s.same_as is not None:
            R_s, o_s = frames[s.same_as]
        else:
            T = rot_xyz(*s.tilt)
            shift = np.array([s.decenter[0], s.decenter[1], 0.0])
            if s.global_position is not None:
                R_s, o_s = T, np.asarray(s.global_position, float) + T @ shift
            else:
                R_s, o_s = R_cur @ T, o_cur + R_cur @ shift
        frames.append((R_s, o_s))
        if not s.return_axis or s.global_position is not None:
            R_cur, o_cur = R_s, o_s
        after.append((R_cur, o_cur))
        o_cur = o_cur + R_cur @ np.array([0.0, 0.0, s.thickness])
    return frames, after
