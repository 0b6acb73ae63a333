"""Glass and air thickness constraints shared by the merit functions.

Each block yields ``(name, residuals, Jacobian rows or None)`` like the
residual blocks of :class:`lfsim.optimize.merit.IniMerit`: a hinge in µm
(× the ``thickness`` weight) that is zero while the limit holds.
"""

from __future__ import annotations

import numpy as np

from ..optics.solids import edge_thickness, glass_pairs, is_glass, rim_thickness

__all__ = ["center_thickness", "edge_thickness", "edge_thickness_block", "glass_pairs", "is_glass"]


def center_thickness(cols, x, system, names, values, targets, weights, K: int, derivatives: bool,
                     signed: bool = False):
    """Variable centre thicknesses below ``min_center_thickness`` (glass) or
    ``min_air_gap`` (air), µm. ``signed``: the signed excess (negative while the limit
    holds) with its Jacobian at every row (:meth:`lfsim.optimize.merit.Rows.add_hinge`)."""
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
        res_t.append((lo - v if signed else max(0.0, lo - v)) * 1000.0 * weights.thickness)
        row = np.zeros(K)
        if v < lo or signed:
            row[j_] = -1000.0 * weights.thickness
        jac_t.append(row)
    if res_t:
        yield "thickness", np.array(res_t), np.array(jac_t) if derivatives else None


_OFF_AXIS = ("decenter_x", "decenter_y", "tilt_x", "tilt_y", "tilt_z")


def edge_thickness_block(cols, x, tracer, values, pairs, targets, weights, K: int, derivatives: bool,
                         signed: bool = False):
    """Edge thickness of the glass elements ``pairs`` below ``min_edge_thickness``, µm;
    derivatives by central differences (one launch per element). ``signed``: the signed
    excess with its Jacobian at every row (:meth:`lfsim.optimize.merit.Rows.add_hinge`).

    An element whose own decenter or tilt is a variable gives a row per rim point
    (:func:`~lfsim.optics.solids.rim_thickness`): the least thickness over the rim
    has a kink wherever the thinnest point moves (at a coaxial start every rim point
    is thinnest at once), and a least-squares step cannot see it; each point's
    hinge is smooth. Every other element gives one row, its least rim thickness."""
    if targets.min_edge_thickness is None or not pairs:
        return
    system, names = tracer.system, tracer.names
    lim, scale = targets.min_edge_thickness, 1000.0 * weights.thickness
    res, rows = [], []
    for i, j, rad in pairs:
        own = {system.surfaces[i].name, system.surfaces[j].name}
        use = [c_ for c_, col in enumerate(cols) if col.state is None and col.name.split(".")[0] in own]
        per_point = any(cols[c_].name.split(".")[-1] in _OFF_AXIS for c_ in use)

        def thickness(V, i=i, j=j, rad=rad, per_point=per_point):  # (B, rows of this element)
            if per_point:
                return rim_thickness(tracer, V, i, j, rad)
            return np.atleast_1d(edge_thickness(tracer, V, i, j, rad)).reshape(-1, 1)

        et = thickness(values[None])[0]
        over = (et < lim) | (signed & np.isfinite(et))
        res.append(((lim - et) if signed else np.where(over, lim - et, 0.0)) * 1000.0 * weights.thickness)
        jac = np.zeros((et.size, K)) if derivatives else None
        if derivatives and over.any() and use:
            hs = np.array([1e-7 * max(1.0, abs(x[c_])) for c_ in use])
            V = np.repeat(values[None], 2 * len(use), axis=0)
            for k, (c_, h) in enumerate(zip(use, hs)):
                V[2 * k, names.index(cols[c_].name)] += h
                V[2 * k + 1, names.index(cols[c_].name)] -= h
            e = thickness(V)  # one launch for every ± step
            d = (e[0::2] - e[1::2]) / (2 * hs[:, None])  # (len(use), rows)
            with np.errstate(invalid="ignore"):  # a rim point whose line misses at x ± h: no slope
                jac[:, use] = np.where(over[:, None] & np.isfinite(d.T), -d.T, 0.0) * scale
        rows.append(jac)
    yield ("edge_thickness", np.concatenate(res), np.concatenate(rows) if derivatives else None)
