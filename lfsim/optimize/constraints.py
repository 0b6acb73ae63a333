"""Glass and air thickness constraints shared by the merit functions.

Each block yields ``(name, residuals, Jacobian rows or None)`` like the
residual blocks of :class:`lfsim.optimize.merit.IniMerit`: a hinge in µm
(× the ``thickness`` weight) that is zero while the limit holds.
"""

from __future__ import annotations

import numpy as np

from ..optics.solids import edge_thickness, glass_pairs, is_glass

__all__ = ["center_thickness", "edge_thickness", "edge_thickness_block", "glass_pairs", "is_glass"]


def center_thickness(cols, x, system, names, values, targets, weights, K: int, derivatives: bool):
    """Variable centre thicknesses below ``min_center_thickness`` (glass) or
    ``min_air_gap`` (air), µm."""
    res_t, jac_t = [], []
    surf_names = [s.name for s in system.surfaces]
    for j_, c in enumerate(cols):
        if c.state is not None or not c.name.endswith(".thickness"):
            continue
        i = surf_names.index(c.name[: -len(".thickness")])
        lo = targets.min_center_thickness if is_glass(system, names, values, i) else targets.min_air_gap
        if lo is None:
            continue
        v = float(x[j_])
        res_t.append(max(0.0, lo - v) * 1000.0 * weights.thickness)
        row = np.zeros(K)
        if v < lo:
            row[j_] = -1000.0 * weights.thickness
        jac_t.append(row)
    if res_t:
        yield "thickness", np.array(res_t), np.array(jac_t) if derivatives else None


def edge_thickness_block(cols, x, tracer, values, pairs, targets, weights, K: int, derivatives: bool):
    """Edge thickness of the glass elements ``pairs`` below ``min_edge_thickness``,
    µm; derivatives by central differences of the sags."""
    if targets.min_edge_thickness is None or not pairs:
        return
    system, names = tracer.system, tracer.names
    et = np.array([edge_thickness(tracer, values, i, j, rad) for i, j, rad in pairs])
    over = et < targets.min_edge_thickness
    jac = None
    if derivatives:
        jac = np.zeros((len(pairs), K))
        for q, (i, j, rad) in enumerate(pairs):
            if not over[q]:
                continue
            own = {system.surfaces[i].name, system.surfaces[j].name}
            for c_, col in enumerate(cols):
                if col.state is not None or col.name.split(".")[0] not in own:
                    continue
                h = 1e-7 * max(1.0, abs(x[c_]))
                vp, vm = values.copy(), values.copy()
                vp[names.index(col.name)] += h
                vm[names.index(col.name)] -= h
                jac[q, c_] = -(edge_thickness(tracer, vp, i, j, rad) - edge_thickness(tracer, vm, i, j, rad)) / (2 * h)
        jac *= 1000.0 * weights.thickness
    yield ("edge_thickness", np.where(over, targets.min_edge_thickness - et, 0.0) * 1000.0 * weights.thickness,
           jac)
