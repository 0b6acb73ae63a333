"""Writing design files back: parameter values into the raw TOML table, then to disk.

:func:`apply_values` sets parameter-table values (the names of
:meth:`lfsim.optics.prescription.System.parameter_table`, e.g. ``L1.curvature``,
``S3.x2y0``, ``S1.tilt_x``, ``TL.power``, ``mla.pitch_x``) in a copy of a
design file's raw table (as read with ``tomllib``), in the words the file
already uses:

=====================  =====================================================
parameter              written as
=====================  =====================================================
``S.curvature``        ``radius = 1/c`` (``inf`` for c = 0) when the surface
                       gives ``radius`` or neither; ``curvature = c`` when it
                       gives ``curvature``
``S.conic``            ``conic``
``S.A4`` … ``S.A16``   ``asphere = {A4 = …}``
``S.x2y0`` …           ``xy = {x2y0 = …}``
``S.decenter_x|y``     ``decenter = [dx, dy]`` (created as zeros when absent)
``S.tilt_x|y|z``       ``tilt = [tx, ty, tz]`` (likewise)
``S.position_x|y|z``   ``global_position = [x, y, z]``
``S.thickness``        ``thickness``
``S.power``            ``focal_length = 1/power`` (``inf`` for 0) of a
                       ``type = "paraxial"`` surface
``A.pitch_x|y``        ``[arrays.A] pitch = [px, py]``
``A.center_x|y``       ``[arrays.A] center = [cx, cy]`` (created when absent)
=====================  =====================================================

The shape and frame of a ``same_as`` surface are those of its original: a name
such as ``S1_tir.curvature`` is written to the original's entry. Tunable-lens
powers per CDP state go to ``[ini.tunable] power_diopters`` (diopters). A value
equal to the design's current one leaves the file's entry untouched, so numbers
that were not changed keep their exact text value.

:func:`write_design` writes such a table atomically with ``tomli-w`` (floats as
their shortest round-trip ``repr``; infinity as TOML's ``inf``) under a comment
header.
"""

from __future__ import annotations

import copy
import difflib
import math
import re
import tomllib
from pathlib import Path

import tomli_w

from ..fileio import write_text
from ..optics.vector import GAP
from .loader import ini_from_dict, system_from_dict
from .optimize_section import fixed_parameter_reason

_XY_RE = re.compile(r"^x(\d+)y(\d+)$")
_A_RE = re.compile(r"^A(\d+)$")
#: Attributes of a ``same_as`` surface that belong to its original.
_SHARED = re.compile(r"^(curvature|conic|A\d+|x\d+y\d+|decenter_[xy]|tilt_[xyz]|position_[xyz])$")
_AXIS = {"x": 0, "y": 1, "z": 2}


def _surface_names(raw_surfaces: list) -> dict[str, int]:
    return {s.get("name", f"S{i + 1}"): i for i, s in enumerate(raw_surfaces)}


def _set_component(tab: dict, key: str, length: int, axis: int, value: float) -> None:
    vec = tab.get(key)
    if isinstance(vec, (int, float)) and not isinstance(vec, bool):  # scalar pitch = [p, p]
        vec = [vec] * length
    vec = list(vec) if vec is not None else [0.0] * length
    vec[axis] = value
    tab[key] = vec


def _reciprocal(v: float) -> float:
    return math.inf if v == 0 else 1.0 / v


def _coefficient_key(tab: dict, pattern: re.Pattern, wanted: tuple[int, ...]) -> str:
    """The key of ``tab`` spelling the coefficient ``wanted`` (e.g. "A4" or "x2y0")."""
    for k in tab:
        m = pattern.match(k)
        if m and tuple(int(g) for g in m.groups()) == wanted:
            return k
    raise KeyError(wanted)  # unreachable for names taken from the parameter table


def _write_surface(s: dict, attr: str, value: float) -> None:
    if attr == "curvature":
        if "curvature" in s:
            s["curvature"] = value
        else:
            s["radius"] = _reciprocal(value)
    elif attr in ("conic", "thickness"):
        s[attr] = value
    elif attr == "power":
        s["focal_length"] = _reciprocal(value)
    elif m := _A_RE.match(attr):
        tab = s["asphere"]
        tab[_coefficient_key(tab, _A_RE, (int(m.group(1)),))] = value
    elif m := _XY_RE.match(attr):
        tab = s["xy"]
        tab[_coefficient_key(tab, _XY_RE, (int(m.group(1)), int(m.group(2))))] = value
    elif attr.startswith("decenter_"):
        _set_component(s, "decenter", 2, _AXIS[attr[-1]], value)
    elif attr.startswith("tilt_"):
        _set_component(s, "tilt", 3, _AXIS[attr[-1]], value)
    elif attr.startswith("position_"):
        _set_component(s, "global_position", 3, _AXIS[attr[-1]], value)
    else:  # unreachable for names taken from the parameter table
        raise ValueError(f"cannot write parameter attribute {attr!r}")


def apply_values(raw: dict, values: dict[str, float],
                 tunable_power_diopters: list[float] | None = None) -> dict:
    """A deep copy of a design's raw table with parameter values set.

    Parameters
    ----------
    raw : dict
        A design file's table as read with ``tomllib`` (not modified).
    values : dict[str, float]
        Parameter-table names → new values, in the table's units (curvature
        1/mm, lengths mm, tilts degrees, ``power`` 1/mm).
    tunable_power_diopters : list of float, optional
        The tunable lens's power at each CDP state (diopters), written to
        ``[ini.tunable] power_diopters``.

    Returns
    -------
    dict
        The new raw table; it is validated as a design (and ``[ini]``) before
        it is returned.

    Raises
    ------
    ValueError
        An unknown or non-writable name (indices come from materials; a
        paraxial lens or coordinate break has no shape), a non-finite value,
        conflicting values for one physical surface, or tunable powers without
        ``[ini.tunable]`` or of the wrong count.
    lfsim.DesignError
        (a ``ValueError``) when ``raw`` or the result is not a valid design,
        e.g. a curvature too strong for the surface's clear aperture.
    """
    system = system_from_dict(raw)
    current = {n: v for n, v, _ in system.parameter_table()}
    out = copy.deepcopy(raw)
    surfaces = out["surfaces"]
    index_of = _surface_names(surfaces)

    resolved: dict[str, float] = {}
    given_as: dict[str, str] = {}
    for name, value in values.items():
        try:
            value = float(value)
        except (TypeError, ValueError):
            raise ValueError(f"parameter {name!r}: value {value!r} is not a number") from None
        if not math.isfinite(value):
            raise ValueError(f"parameter {name!r}: value {value!r} is not finite")
        target = name
        owner, _, attr = name.rpartition(".")
        if owner in index_of and _SHARED.match(attr):
            j = system.surfaces[index_of[owner]].same_as
            if j is not None:
                target = f"{system.surfaces[j].name}.{attr}"
        if target not in current:
            close = difflib.get_close_matches(name, list(current), n=4, cutoff=0.6)
            hint = f"; close matches: {', '.join(close)}" if close else ""
            raise ValueError(f"unknown parameter {name!r}{hint}")
        if target in resolved and resolved[target] != value:
            raise ValueError(f"parameters {given_as[target]!r} and {name!r} are one physical surface "
                             f"but were given different values ({resolved[target]!r}, {value!r})")
        reason = fixed_parameter_reason(system, target)
        if reason and value != current[target]:
            raise ValueError(f"parameter {name!r} cannot be written: {reason}")
        resolved[target], given_as[target] = value, name

    for name, value in resolved.items():
        if value == current[name]:
            continue  # unchanged: keep the file's own spelling of the number
        owner, _, attr = name.rpartition(".")
        if name == GAP:
            obj = out.setdefault("object", {})
            if not isinstance(obj, dict):
                raise ValueError(f"parameter {name!r}: the design's [object] is not a table")
            obj["distance"] = value
        elif attr.startswith(("pitch_", "center_")) and owner in system.arrays:
            _set_component(out["arrays"][owner], attr.split("_")[0], 2, _AXIS[attr[-1]], value)
        else:
            _write_surface(surfaces[index_of[owner]], attr, value)

    if tunable_power_diopters is not None:
        tun = out.get("ini", {}).get("tunable") if isinstance(out.get("ini"), dict) else None
        if not isinstance(tun, dict):
            raise ValueError("tunable powers given but the design has no [ini.tunable]")
        powers = [float(p) for p in tunable_power_diopters]
        depths = out["ini"].get("cdp_diopters", [])
        if len(powers) != len(depths) or not all(math.isfinite(p) for p in powers):
            raise ValueError(f"tunable powers {powers!r}: need one finite power (diopters) per CDP depth "
                             f"({len(depths)})")
        tun["power_diopters"] = powers

    ini_from_dict(out, system_from_dict(out))
    return out


#: A flat array as tomli-w writes it, one item a line (strings are single-line).
#: Each item line is indentation, then a non-blank character, then the rest of the line:
#: no two parts of the pattern can take the same character, so a long array that is
#: not flat (an inline table on its 80th line) fails in linear time, not exponential.
_FLAT_ARRAY = re.compile(r"\[\n((?:[ ]+[^\s\[\]{}][^\n\[\]{}]*,\n)+)[ ]*\]")


def _compact_arrays(text: str) -> str:
    """Put each flat array (numbers, strings) on one line: ``tilt = [0.0, 5.0, 0.0]``."""
    compact = _FLAT_ARRAY.sub(
        lambda m: "[" + ", ".join(item.strip().rstrip(",") for item in m.group(1).splitlines()) + "]", text)
    # Guard: the compact text must mean the same table (repr compares nan equal).
    return compact if repr(tomllib.loads(compact)) == repr(tomllib.loads(text)) else text


def design_text(raw: dict, header_lines: list[str]) -> str:
    """TOML text of a design table under a ``#`` comment header."""
    header = []
    for line in header_lines:
        for part in str(line).splitlines() or [""]:
            header.append(f"# {part}".rstrip())
    body = _compact_arrays(tomli_w.dumps(raw))
    return ("\n".join(header) + "\n\n" if header else "") + body


def write_design(path: str | Path, raw: dict, header_lines: list[str]) -> None:
    """Write a design table as TOML atomically (a reader never sees a partial file)."""
    write_text(path, design_text(raw, header_lines))
