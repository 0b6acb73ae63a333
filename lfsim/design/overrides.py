"""Command-line overrides of design numbers: ``--set KEY=VALUE``.

A key is either

* a parameter-table name (:meth:`lfsim.optics.prescription.System.parameter_table`,
  e.g. ``MLA.curvature``, ``S3.x2y2``, ``S1.tilt_x``, ``mla.pitch_x``) —
  written back in the file's own words by :func:`lfsim.design.writer.apply_values`
  (a radius for a curvature, ``[arrays]`` pitch for ``pitch_x``, …); or
* ``ini.tunable.power_diopters[K]``, the tunable lens's power at CDP state K; or
* a dotted path to an existing number in the file's table, with ``[K]`` for a
  list element (``surfaces[3].thickness``, ``ini.cdp_diopters[1]``,
  ``ini.analysis.fields``).

The result is validated as a whole design, so an override the design cannot
take (a curvature its clear aperture cannot reach, a negative thickness) is
a :class:`DesignError` naming the file, the key and the value.
"""

from __future__ import annotations

import copy
import difflib
import math
import re
from collections.abc import Iterable
from pathlib import Path

from .design import Design
from .errors import DesignError
from .loader import read_toml, system_from_dict

_PATH_PART = re.compile(r"^([A-Za-z_][\w-]*)((?:\[\d+\])*)$")


def parse_assignment(text: str, flag: str = "--set") -> tuple[str, str]:
    """``"KEY=VALUE"`` → ``(KEY, VALUE)`` (both stripped); ValueError naming the flag."""
    key, sep, value = str(text).partition("=")
    key, value = key.strip(), value.strip()
    if not sep or not key or not value:
        raise ValueError(f"{flag} = {text!r}: expected KEY=VALUE, e.g. MLA.curvature=0.5")
    return key, value


def parse_number(text: str, key: str, flag: str = "--set") -> float:
    """A float (``inf`` allowed, e.g. a flat radius); NaN is refused."""
    try:
        v = float(text)
    except ValueError:
        raise ValueError(f"{flag} {key} = {text!r}: not a number") from None
    if math.isnan(v):
        raise ValueError(f"{flag} {key} = {text!r}: not a number")
    return v


def parse_sets(items: Iterable[str] | None, flag: str = "--set") -> dict[str, float]:
    """Parse repeated ``KEY=VALUE`` items into an ordered ``{key: value}``; a key given twice is an error."""
    out: dict[str, float] = {}
    for item in items or ():
        key, text = parse_assignment(item, flag)
        if key in out:
            raise ValueError(f"{flag} {key}: given twice")
        out[key] = parse_number(text, key, flag)
    return out


def _path_parts(key: str) -> list[str | int]:
    parts: list[str | int] = []
    for piece in key.split("."):
        m = _PATH_PART.match(piece)
        if not m:
            raise KeyError(key)
        parts.append(m.group(1))
        parts.extend(int(i) for i in re.findall(r"\[(\d+)\]", m.group(2)))
    return parts


def _set_path(raw: dict, key: str, value: float) -> bool:
    """Set the number at dotted ``key`` in ``raw``; False when the path does not fit the file.

    An existing number is replaced (an integer stays an integer when the value
    is whole). A missing key is created, with any missing tables on its way,
    only under a top-level table the file already has (``ini.analysis.fields``
    in a file with ``[ini]``); the design's validation then refuses keys it
    does not know.
    """
    value = float(value)
    try:
        parts = _path_parts(key)
    except KeyError:
        return False
    if len(parts) < 2 or not isinstance(raw.get(parts[0]), (dict, list)):  # [table] or [[array of tables]]
        return False
    node = raw
    for i, p in enumerate(parts[:-1]):
        nxt = parts[i + 1]
        if isinstance(node, dict) and p not in node and isinstance(p, str) and isinstance(nxt, str):
            node[p] = {}
        try:
            node = node[p]
        except (KeyError, IndexError, TypeError):
            return False
        if not isinstance(node, (dict, list)):
            return False
    last = parts[-1]
    if isinstance(node, dict) and isinstance(last, str) and last not in node:
        node[last] = int(value) if value.is_integer() else value
        return True
    try:
        old = node[last]
    except (KeyError, IndexError, TypeError):
        return False
    if isinstance(old, bool) or not isinstance(old, (int, float)):
        return False
    if isinstance(old, int) and value.is_integer():
        value = int(value)
    node[last] = value
    return True


_TUNABLE = re.compile(r"^ini\.tunable\.power_diopters\[(\d+)\]$")


def apply_overrides(raw: dict, overrides: dict[str, float], file: str = "<dict>") -> dict:
    """A copy of a design's raw table with ``overrides`` applied and validated.

    Raises
    ------
    DesignError
        An unknown key (with close matches), or a value the design cannot take.
    """
    from .writer import apply_values  # writer imports the loader; keep the import graph one-way

    if not overrides:
        return raw
    system = system_from_dict(raw, file)
    names = [n for n, _, _ in system.parameter_table()]
    table_values = {k: v for k, v in overrides.items() if k in names}
    out = raw
    if table_values:
        try:
            out = apply_values(raw, table_values)
        except DesignError as e:  # validated in memory: name the file the values came from
            raise DesignError(file, e.key, e.value, e.allowed, surface=e.surface) from None
        except ValueError as e:  # unknown / unwritable name or conflicting values
            k = next(iter(table_values))
            raise DesignError(file, k, table_values[k], str(e)) from None
    else:
        out = copy.deepcopy(raw)
    for key, value in overrides.items():
        if key in table_values:
            continue
        m = _TUNABLE.match(key)
        if m:
            ini = out.get("ini", {})
            tun = ini.get("tunable") if isinstance(ini, dict) else None
            depths = ini.get("cdp_diopters", []) if isinstance(ini, dict) else []
            k = int(m.group(1))
            if not isinstance(tun, dict) or k >= len(depths):
                raise DesignError(file, key, value, f"the design has no tunable lens state {k}")
            if not math.isfinite(value):
                raise DesignError(file, key, value, "a finite power in diopters")
            powers = tun.get("power_diopters")
            if not isinstance(powers, list) or len(powers) != len(depths):
                raise DesignError(file, key, value, "[ini.tunable] power_diopters must list every CDP state's "
                                                    "power (they are solved when omitted) before one is overridden")
            powers = list(powers)
            powers[k] = value
            tun["power_diopters"] = powers
            continue
        if not _set_path(out, key, value):
            close = difflib.get_close_matches(key, names, n=4, cutoff=0.6)
            hint = f" (close matches: {', '.join(close)})" if close else ""
            raise DesignError(file, key, value,
                              "a parameter name of the design (lfsim params DESIGN lists them) or the "
                              "dotted path of a number in the file" + hint)
    return out


def load_with_overrides(path: str | Path, overrides: dict[str, float] | None = None) -> Design:
    """:func:`lfsim.load` with ``--set`` overrides applied before validation."""
    raw = read_toml(path)
    if not overrides:
        return Design(system_from_dict(raw, str(path)), raw, str(path))
    out = apply_overrides(raw, overrides, str(path))
    return Design(system_from_dict(out, str(path)), out, str(path))
