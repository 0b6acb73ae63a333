"""Random draws of the toleranced errors and the perturbed design tables they make.

Each trial's draw depends on (seed, trial index) only: its generator is
``numpy.random.default_rng(SeedSequence(seed, spawn_key=(index,)))``, and the
tolerances are drawn from it in the order of ``[[tolerance.parameters]]``. A
run on one process, on a local cluster or on any number of remote workers
therefore perturbs trial ``i`` identically.

Errors are offsets added to the nominal numbers (``relative``: offset =
fraction × |nominal|). ``keys`` tolerances go through
:func:`lfsim.design.overrides.apply_overrides` (so they are written in the
file's own words and validated); ``rigid`` tolerances move surfaces placed
with ``global_position`` as one body: a rotation ``G`` about ``pivot`` maps
each surface's position ``p`` to ``pivot + G (p − pivot)`` and its frame ``R``
to ``G R`` (the tracer's ``R = Rx·Ry·Rz`` convention, angles re-extracted),
a shift adds to every position.
"""

from __future__ import annotations

import math

import numpy as np

from ..design.errors import DesignError
from ..design.loader import system_from_dict
from ..design.optimize_section import TUNABLE
from ..design.overrides import apply_overrides
from ..design.tolerance_section import _TUNABLE_KEY, Tolerance, ToleranceSpec, nominal_value
from ..design.writer import apply_values


def trial_rng(seed: int, index: int) -> np.random.Generator:
    """The generator of trial ``index`` of a run with ``seed``."""
    return np.random.default_rng(np.random.SeedSequence(int(seed), spawn_key=(int(index),)))


def _draw_one(t: Tolerance, rng: np.random.Generator) -> float:
    if t.distribution == "uniform":
        return float(rng.uniform(-t.limit, t.limit))
    if t.distribution == "normal":
        return float(rng.normal(0.0, t.sigma))
    while True:  # truncated normal: rejection (acceptance >= 68 % for limit >= sigma)
        v = float(rng.normal(0.0, t.sigma))
        if abs(v) <= t.limit:
            return v


def draw(spec: ToleranceSpec, seed: int, index: int) -> dict[str, float]:
    """Offsets {tolerance name: offset (relative ones as fractions)} of Monte Carlo trial ``index``."""
    rng = trial_rng(seed, index)
    return {t.name: _draw_one(t, rng) for t in spec.parameters}


def is_setting_error(key: str, compensators) -> bool:
    """A key that a compensator sets: its error is applied after the compensator is solved."""
    if key in compensators:
        return True
    return TUNABLE in compensators and _TUNABLE_KEY.match(key) is not None


def _rot_xyz(ax: float, ay: float, az: float) -> np.ndarray:
    """R = Rx(ax)·Ry(ay)·Rz(az), radians (the tracer's frame convention)."""
    cx, sx, cy, sy, cz, sz = math.cos(ax), math.sin(ax), math.cos(ay), math.sin(ay), math.cos(az), math.sin(az)
    rx = np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]])
    ry = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
    rz = np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]])
    return rx @ ry @ rz


def _angles_xyz(R: np.ndarray) -> tuple[float, float, float]:
    """Angles (degrees) (a, b, c) with R = Rx(a)·Ry(b)·Rz(c)."""
    b = math.asin(max(-1.0, min(1.0, R[0, 2])))
    a = math.atan2(-R[1, 2], R[2, 2])
    c = math.atan2(-R[0, 1], R[0, 0])
    return math.degrees(a), math.degrees(b), math.degrees(c)


def rigid_values(raw: dict, t: Tolerance, amount: float) -> dict[str, float]:
    """Parameter-table values that move ``t.rigid`` by ``amount`` (degrees or mm) as one body."""
    system = system_from_dict(raw)
    table = {n: v for n, v, _ in system.parameter_table()}
    axis = "xyz".index(t.motion[-1])
    out: dict[str, float] = {}
    if t.motion.startswith("shift_"):
        for s in t.rigid:
            k = f"{s}.position_{'xyz'[axis]}"
            out[k] = table[k] + amount
        return out
    G = _rot_xyz(*(math.radians(amount) if j == axis else 0.0 for j in range(3)))
    q = np.array(t.pivot)
    for s in t.rigid:
        p = np.array([table[f"{s}.position_{c}"] for c in "xyz"])
        R = _rot_xyz(*(math.radians(table[f"{s}.tilt_{c}"]) for c in "xyz"))
        p2 = q + G @ (p - q)
        angles = _angles_xyz(G @ R)
        for j, c in enumerate("xyz"):
            out[f"{s}.position_{c}"] = float(p2[j])
            out[f"{s}.tilt_{c}"] = float(angles[j])
    return out


def _key_offsets(raw: dict, spec: ToleranceSpec, offsets: dict[str, float], post: bool) -> dict[str, float]:
    """{key: new value} of the keys tolerances, before (post=False) or after compensation."""
    system = system_from_dict(raw)
    acc: dict[str, float] = {}
    for t in spec.parameters:
        if t.is_rigid or t.name not in offsets:
            continue
        for k in t.keys:
            if is_setting_error(k, spec.compensators) != post:
                continue
            v0 = nominal_value(raw, system, k)
            d = offsets[t.name] * (abs(v0) if t.relative else 1.0)
            acc[k] = acc.get(k, 0.0) + d
    out = {}
    for k, d in acc.items():
        v0 = nominal_value(raw, system, k)
        out[k] = v0 + d
    return out


def perturb(raw: dict, spec: ToleranceSpec, offsets: dict[str, float], file: str = "<dict>") -> dict:
    """The raw table with the assembly/manufacturing errors (not the setting errors) applied."""
    out = raw
    values = _key_offsets(raw, spec, offsets, post=False)
    if values:
        out = apply_overrides(out, values, file)
    for t in spec.parameters:
        if t.is_rigid and offsets.get(t.name, 0.0) != 0.0:
            try:
                out = apply_values(out, rigid_values(out, t, offsets[t.name]))
            except DesignError:
                raise
            except ValueError as e:
                raise DesignError(file, f"tolerance {t.name}", offsets[t.name], str(e)) from None
    return out


def apply_setting_errors(raw: dict, spec: ToleranceSpec, offsets: dict[str, float],
                         file: str = "<dict>") -> dict:
    """The compensated table with the errors of compensator settings applied (tunable powers
    clipped to the lens's ``range_diopters``: the lens cannot go beyond it)."""
    values = _key_offsets(raw, spec, offsets, post=True)
    if not values:
        return raw
    rng = raw.get("ini", {}).get("tunable", {}).get("range_diopters")
    if rng:
        values = {k: (min(max(v, rng[0]), rng[1]) if _TUNABLE_KEY.match(k) else v) for k, v in values.items()}
    return apply_overrides(raw, values, file)
