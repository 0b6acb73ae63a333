"""Compensators: numbers an assembly re-adjusts on each built unit, re-solved per trial.

Two merits, both solved with lfsim's damped least squares
(:func:`lfsim.optimize.solvers.levenberg_marquardt`, bounds from the tunable
lens's range):

``"focus"`` (default) — :class:`FocusProblem`
    residuals: the paraxial CDP depth (x and y meridians) that each CDP state
    makes, minus the nominal design's, in diopters. Restoring the nominal
    paraxial depths carries the nominal design's own focus setting over to the
    perturbed unit: where a design's tunable powers were optimized for best
    focus (aberrations move it from the paraxial CDP), the same offset from
    paraxial focus is kept. Derivatives: central differences of the
    first-order model (``IniModel.linear_views``, two launches per Jacobian).
``"spot"`` — :class:`lfsim.optimize.merit.IniMerit` restricted to the
    compensators with only its spot block weighted (the RMS spot about each
    sub-system's CDP): best focus of real rays, like a refocus by eye, about
    ten times the cost per trial.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from ..design.design import Design
from ..design.optimize_section import TUNABLE, OptimizeSpec, OptimizeTargets, OptimizeWeights, Variable
from ..design.writer import apply_values
from ..ini.model import IniModel
from ..optimize.merit import Column, IniMerit, columns
from ..optimize.solvers import Bounds, levenberg_marquardt


def compensator_columns(design: Design, names) -> list[Column]:
    """Columns (one per tunable state) of the compensators ``names``."""
    ini = design.ini
    rng = ini.tunable_range_diopters if ini is not None else None
    variables = []
    for n in names:
        if n == TUNABLE:
            lo, hi = rng if rng is not None else (-np.inf, np.inf)
            variables.append(Variable(TUNABLE, lo, hi))
        else:
            variables.append(Variable(n))
    return columns(design, OptimizeSpec(variables=tuple(variables)))


def paraxial_depths(model: IniModel) -> np.ndarray:
    """(K, 2) paraxial CDP depths (diopters) made in x and y by each CDP state of ``model``
    (from its first-order maps, as ``model.state(k).cdp_diopters_x/_y``)."""
    dx, dy, _, _ = model._depth_of(model.JG)
    return np.stack([dx, dy], axis=1)


def design_at(design: Design, cols: list[Column], x) -> Design:
    """``design`` with the compensator columns set to ``x`` (tunable powers in diopters)."""
    values = {c.name: float(v) for c, v in zip(cols, x) if c.state is None}
    powers = None
    if any(c.state is not None for c in cols):
        powers = list(design.ini.tunable_power_diopters or [])
        if len(powers) != len(design.ini.cdp_diopters):
            powers = [1000.0 * p for p in IniModel(design).tl_power]
        for c, v in zip(cols, x):
            if c.state is not None:
                powers[c.state] = float(v)
    raw = apply_values(design.raw, values, tunable_power_diopters=powers)
    return Design.from_dict(raw, design.path or "<dict>")


def start_values(model: IniModel, cols: list[Column]) -> np.ndarray:
    names = model.tracer.names
    return np.array([1000.0 * model.tl_power[c.state] if c.state is not None
                     else model.values0[names.index(c.name)] for c in cols])


class FocusProblem:
    """Paraxial refocus: residuals = depths made − ``target`` (K, 2), diopters (a solver Problem).

    The first-order model of the perturbed design is built once; at other
    compensator values it is re-linearized (``IniModel.linear_views``: the
    lenslet and eyepiece-group maps at the new parameter values, two launches
    for the residuals and all 2K central differences together). The frames of
    the stop and the viewing window stay the built model's, which is exact for
    compensators that do not move them (the tunable lens, the relay's
    spacings and shapes); the compensated design is then rebuilt in full.
    """

    def __init__(self, model: IniModel, cols: list[Column], target: np.ndarray):
        self.model0, self.cols, self.target = model, list(cols), np.asarray(target, dtype=np.float64)
        names = model.tracer.names
        self._index = [names.index(c.name) for c in self.cols]

    def _values(self, x, dx=None) -> np.ndarray:
        """Parameter vectors per CDP state (K_states, n) at compensator values ``x`` (+ ``dx``)."""
        x = np.asarray(x, dtype=np.float64) if dx is None else np.asarray(x, dtype=np.float64) + dx
        base = np.array([self.model0.values(k) for k in range(len(self.model0.depths))])
        for c, i, v in zip(self.cols, self._index, x):
            if c.state is None:
                base[:, i] = v
            else:
                base[c.state, i] = v / 1000.0  # diopters → 1/mm
        return base

    def residuals(self, x) -> np.ndarray:
        view = self.model0.linear_views(self._values(x)[None])[0]
        return (paraxial_depths(view) - self.target).ravel()

    def jacobian(self, x):
        x = np.asarray(x, dtype=np.float64)
        steps = np.array([1e-6 * max(1.0, abs(v)) for v in x])
        vals = [self._values(x)]
        for j, h in enumerate(steps):
            e = np.zeros(len(x))
            e[j] = h
            vals += [self._values(x, e), self._values(x, -e)]
        views = self.model0.linear_views(np.array(vals))
        r = (paraxial_depths(views[0]) - self.target).ravel()
        J = np.empty((r.size, len(self.cols)))
        for j, h in enumerate(steps):
            J[:, j] = (paraxial_depths(views[1 + 2 * j]) - paraxial_depths(views[2 + 2 * j])).ravel() / (2.0 * h)
        return r, J


@dataclass
class Compensation:
    design: Design
    values: dict  # column label → value
    cost0: float
    cost: float
    iterations: int
    status: str


def compensate(design: Design, names, method: str, target_depths: np.ndarray, iterations: int = 10,
               sampling: dict | None = None) -> Compensation:
    """Re-solve the compensators ``names`` of a perturbed ``design`` (see the module docstring)."""
    cols = compensator_columns(design, names)
    if not cols:
        return Compensation(design, {}, 0.0, 0.0, 0, "none")
    lower = np.array([c.lower for c in cols])
    upper = np.array([c.upper for c in cols])
    if method == "focus":
        model0 = IniModel(design)
        problem = FocusProblem(model0, cols, target_depths)
        x0 = start_values(model0, cols)
        res = levenberg_marquardt(problem, x0, Bounds(lower, upper), max_iterations=iterations,
                                  ftol=1e-10, xtol=1e-10, gtol=1e-12)
        out = design_at(design, cols, res.x)
    elif method == "spot":
        s = sampling or {}
        spec = OptimizeSpec(variables=(), targets=OptimizeTargets(local_distortion_max=None),
                            weights=OptimizeWeights(spot=1.0, gd=0.0, pa=0.0, distortion=0.0, crosstalk=0.0,
                                                    efl=0.0, thickness=0.0, tir=0.0))
        spec = replace(spec, stride=tuple(s.get("stride", (8, 4))), fields=int(s.get("fields", 3)),
                       pupil=int(s.get("pupil", 4)))
        problem = IniMerit(design, spec, cols=cols)
        res = levenberg_marquardt(problem, problem.x0, Bounds(lower, upper), max_iterations=iterations,
                                  ftol=1e-6, xtol=1e-10, gtol=1e-10)
        out = problem.design_at(res.x)
    else:
        raise ValueError(f"compensator method {method!r}: allowed focus, spot")
    return Compensation(out, {c.label: float(v) for c, v in zip(cols, res.x)}, float(res.cost0),
                        float(res.cost), int(res.iterations), res.status)
