"""The mechanical package of an InI-HMD's display path: length, diameters, box, glass, eye relief.

:func:`package` measures, in the design's global frame (mm; z along the relay
axis, light travelling +z from the microdisplay):

* ``track_mm``: the unfolded length of the central chief ray, display point →
  viewing window, as the sum of its segments between successive surface hits;
* ``max_clear_diameter_mm`` / ``clear_diameters_mm``: the relay's lenses;
* ``tunable_clear_aperture_mm`` / ``tunable_footprint_mm``: the tunable lens;
* ``bounding_box_mm`` (with ``_min_`` / ``_max_`` corners) of the whole optics
  and ``prism_box_mm`` of the prism faces;
* ``min_center_thickness_mm``, ``min_edge_thickness_mm`` (relay elements and
  the lenslet array) and ``min_prism_thickness_mm`` (:mod:`lfsim.optics.solids`);
* ``eye_relief_mm``: viewing-window centre → nearest ray hit on the last
  optical surface, along the line of sight.

Definitions: ``docs/contracts.md``. The ray set (:func:`ray_set`) is the
lenslets {0, M//2, M−1} × {0, N//2, N−1}, 9 EI field points (centre, corners,
edge midpoints) and 5 pupil rays (chief + the 4 marginal rays at the lenslet
aperture's edge midpoints) at every CDP state, aimed and traced by
:func:`lfsim.ini.subsystems.trace_rays_jacobian` (the merit's trace, without
derivatives: apertures are not applied, so the figures are smooth in the
design's parameters); rays that fail are left out. Hits come back as local
(x, y) on each surface; their z is the tracer's sag and their global position
the tracer's frames. Nothing here traces rays itself.
"""

from __future__ import annotations

import math

import drjit as dr
import numpy as np

from ..backend import from_numpy
from ..optics.surfaces import sag
from .model import IniModel

#: EI field points in units of the EI half-size (±1: the centre of the edge pixel):
#: the centre, the 4 corners, the 4 edge midpoints.
FIELDS = np.array([[0.0, 0.0], [1.0, 1.0], [-1.0, 1.0], [1.0, -1.0], [-1.0, -1.0],
                   [1.0, 0.0], [-1.0, 0.0], [0.0, 1.0], [0.0, -1.0]])
#: Pupil points in units of the stop half-widths: the chief ray and the 4 marginal rays.
PUPIL = np.array([[0.0, 0.0], [1.0, 0.0], [-1.0, 0.0], [0.0, 1.0], [0.0, -1.0]])
#: Samples of a clear aperture for the boxes: points on a circular outline, per rectangle
#: edge, and per axis of the interior grid. A tilted curved face (the prism's mirror) has
#: its extreme inside the aperture, where its normal is along a global axis: with these
#: counts the shipped designs' boxes are within 3 µm of a 201 × 201 grid and 720-point
#: outline (0.12 mm with a 5 × 5 grid); the coaxial ones are exact (rim or vertex).
OUTLINE_POINTS = 128
EDGE_POINTS = 17
GRID_POINTS = 17
#: Sample points per axis of a prism face for its thickness (as the merit's constraint).
PRISM_POINTS = 9

_DUMMY = ("none", "break")


def ray_set(model: IniModel):
    """The flat ray lists of the package figures: ``(s, m, n, rho, k)`` and the
    lenslet table (L, 2); ray order (state, lenslet, field, pupil), pupil fastest."""
    from .subsystems import sample

    M, N = model.arr.m, model.arr.n
    lens = np.array([(a, b) for b in sorted({0, N // 2, N - 1}) for a in sorted({0, M // 2, M - 1})])
    subs = sample(model, lenslets=lens, fields=FIELDS)
    S, F, R = len(subs), len(FIELDS), len(PUPIL)
    shape = (S, F, R)
    s = np.broadcast_to(subs.display[:, :, None, :], shape + (2,)).reshape(-1, 2)
    rho = np.broadcast_to(PUPIL[None, None], shape + (2,)).reshape(-1, 2)
    m, n, k = (np.broadcast_to(a[:, None, None], shape).ravel() for a in (subs.m, subs.n, subs.k))
    return s, m, n, rho, k, lens


def _f(v) -> float | None:
    v = float(v)
    return v if math.isfinite(v) else None


def _min_finite(values) -> float | None:
    v = [float(x) for x in values if math.isfinite(x)]
    return min(v) if v else None


def _declared_diameter(ap, shift=(0.0, 0.0)) -> float:
    """Diameter of the circle about the axis that holds a clear aperture: 2 × its radius
    (a rectangle: its half-diagonal) plus its centre's offset from the axis (the
    aperture's own decenter plus ``shift``, the surface's decenter)."""
    off = math.hypot(ap.decenter[0] + shift[0], ap.decenter[1] + shift[1])
    if ap.kind == "circular":
        return 2.0 * (ap.radius + off)
    dx, dy = abs(ap.decenter[0] + shift[0]), abs(ap.decenter[1] + shift[1])
    return 2.0 * math.hypot(ap.half_width[0] + dx, ap.half_width[1] + dy)


def _outline(kind: str, size, decenter=(0.0, 0.0)) -> np.ndarray:
    """(Q, 2) samples of a clear aperture: its outline and an interior grid."""
    u = np.linspace(-1.0, 1.0, GRID_POINTS)
    X, Y = np.meshgrid(u, u, indexing="xy")
    grid = np.stack([X.ravel(), Y.ravel()], axis=1)
    if kind == "circular":
        a = np.linspace(0.0, 2.0 * math.pi, OUTLINE_POINTS, endpoint=False)
        edge = np.stack([np.cos(a), np.sin(a)], axis=1)
        grid = grid[np.hypot(grid[:, 0], grid[:, 1]) <= 1.0 + 1e-12]
        xy = np.concatenate([edge, grid]) * float(size)
    else:
        t = np.linspace(-1.0, 1.0, EDGE_POINTS)
        one = np.ones_like(t)
        edge = np.concatenate([np.stack(p, axis=1) for p in ((t, one), (t, -one), (one, t), (-one, t))])
        xy = np.concatenate([edge, grid]) * np.asarray(size, dtype=np.float64)
    return xy + np.asarray(decenter, dtype=np.float64)


class _Geometry:
    """Local (x, y) on a surface → global points, with the tracer's sag and frames."""

    def __init__(self, model: IniModel):
        self.model = model
        tr = self.tracer = model.tracer
        self.P = tr.params(values=model.values0)
        self.frames = tr.frames_numpy(self.P)

    def sags(self, items):
        """Local sag z (Q,) of each ``(surface i, local xy (Q, 2))`` (NaN outside the surface's
        domain; 0 on an ideal lens, a plane), all evaluated together (a kernel per point count)."""
        tr, T = self.tracer, self.tracer.T
        lazy = []
        with dr.suspend_grad():
            for i, xy in items:
                if len(xy) == 0:
                    lazy.append(None)
                    continue
                X, Y = from_numpy(T.Float, np.ascontiguousarray(xy[:, 0]), np.ascontiguousarray(xy[:, 1]))
                z, _, _, inside = sag(X, Y, tr.shape(self.P, i, dr.zeros(T.UInt32, len(xy))))
                lazy.append((z, inside))
            dr.eval([v for v in lazy if v is not None])
        out = []
        for (i, _xy), v in zip(items, lazy):
            if v is None:
                out.append(np.zeros(0))
                continue
            z = np.asarray(v[0], dtype=np.float64).reshape(-1)
            z = np.where(np.asarray(v[1], dtype=bool).reshape(-1), z, np.nan)
            if tr.system.surfaces[i].interaction == "paraxial":
                z = np.zeros_like(z)
            out.append(z)
        return out

    def to_global(self, items):
        """``items``: list of (surface i, local xy (Q, 2), lenslet axes (Q, 2) or None: the
        points' lenslets on an array surface, xy relative to them). Returns per item the
        global points (Q', 3) where the sag is defined."""
        zs = self.sags([(i, xy) for i, xy, _ in items])
        out = []
        for (i, xy, off), z in zip(items, zs):
            q = np.column_stack([xy if off is None else xy + off, z])[np.isfinite(z)]
            R, o = self.frames[i]
            out.append(q @ R.T + o)
        return out


def _lenslet_corner(system, i: int, j: int) -> tuple[float, float]:
    """The corner (x, y) of a lenslet's aperture (lenslet-relative), the larger of
    surfaces i and j (a circle: (radius, 0); none: the lenslet cell)."""
    best = None
    for q in (i, j):
        ap = system.surfaces[q].aperture
        if ap is None:
            continue
        c = ((abs(ap.decenter[0]) + ap.radius, abs(ap.decenter[1])) if ap.kind == "circular"
             else (abs(ap.decenter[0]) + ap.half_width[0], abs(ap.decenter[1]) + ap.half_width[1]))
        if best is None or math.hypot(*c) > math.hypot(*best):
            best = c
    if best is None:
        arr = system.arrays[system.surfaces[i].array]
        best = (0.5 * arr.pitch[0], 0.5 * arr.pitch[1])
    return float(best[0]), float(best[1])


def _box(points) -> tuple[np.ndarray, np.ndarray] | None:
    pts = [p for p in points if len(p)]
    if not pts:
        return None
    p = np.concatenate(pts)
    return p.min(axis=0), p.max(axis=0)


def package(model: IniModel, solids: bool = True) -> dict:
    """The mechanical package of ``model``'s display path (mm, global frame; JSON-ready).

    ``solids=False`` leaves out the glass and prism thicknesses (None), which the
    merit measures in blocks of their own.

    Keys (``docs/contracts.md``): ``track_mm``, ``max_clear_diameter_mm``,
    ``clear_diameters_mm``, ``tunable_clear_aperture_mm``,
    ``tunable_footprint_mm``, ``bounding_box_mm``, ``bounding_box_min_mm``,
    ``bounding_box_max_mm``, ``prism_box_mm``, ``prism_footprint_box_mm``, ``min_center_thickness_mm``,
    ``min_edge_thickness_mm``, ``min_prism_thickness_mm``, ``eye_relief_mm``,
    and the ray counts ``rays_traced``, ``rays_failed``. None where a figure
    does not apply (no tunable lens, no prism, no glass element) or no ray of
    the set reaches the surface it needs.
    """
    from ..optics.solids import edge_thickness, glass_pairs, is_glass, prism_thickness, prisms
    from .subsystems import trace_rays_jacobian

    system, spec, tr = model.system, model.spec, model.tracer
    surf = system.surfaces
    vw = spec.viewing_window
    names, values = tr.names, model.values0
    geo = _Geometry(model)

    # ---------------------------------------------------------------- rays
    s, m, n, rho, k, lens = ray_set(model)
    record = [i for i in range(vw + 1) if surf[i].interaction != "break"]
    col = {i: c for c, i in enumerate(record)}
    J = trace_rays_jacobian(model, s, m, n, rho, k, [], record=record, derivatives=False)
    ok = J.status == 0
    hits = J.surf  # (rays, surfaces, 2), local; on an array surface relative to the ray's lenslet axis

    def radial(i):
        h = hits[ok, col[i]]
        return float(np.max(np.hypot(h[:, 0], h[:, 1]))) if len(h) else math.nan

    # --------------------------------------------------------------- track
    nl, F, R = len(lens), len(FIELDS), len(PUPIL)
    k_mid = len(model.depths) // 2
    j_lens = int(np.nonzero((lens[:, 0] == model.arr.m // 2) & (lens[:, 1] == model.arr.n // 2))[0][0])
    chief = ((k_mid * nl + j_lens) * F + 0) * R + 0
    track = math.nan
    if ok[chief]:
        path = [i for i in record if surf[i].interaction not in _DUMMY or i == vw]
        c_chief = model.lenslet_center(m[chief], n[chief])
        items = [(i, hits[chief:chief + 1, col[i]],
                  c_chief[None] if surf[i].array is not None else None) for i in path]
        pts = np.concatenate([[[s[chief, 0], s[chief, 1], -model.g]], *geo.to_global(items)])
        if len(pts) == len(path) + 1:  # every hit on its surface's domain
            track = float(np.sum(np.linalg.norm(np.diff(pts, axis=0), axis=1)))

    # ------------------------------------------------- relay clear diameters
    def rotational(i):
        return not surf[tr.vector.owner(i)].xy

    relay = [i for i in range(vw) if surf[i].interaction == "refract" and surf[i].array is None
              and surf[i].global_position is None and rotational(i)]
    clear = {}
    for i in relay:
        ap = surf[i].aperture
        shift = (values[tr.index[f"{surf[i].name}.decenter_x"]], values[tr.index[f"{surf[i].name}.decenter_y"]])
        clear[surf[i].name] = _f(_declared_diameter(ap, shift) if ap is not None
                                 else 2.0 * (radial(i) + math.hypot(*shift)))
    diam = [v for v in clear.values() if v is not None]

    # --------------------------------------------------------- tunable lens
    t_ap = t_fp = None
    if spec.tunable is not None:
        ti = spec.tunable
        t_fp = _f(2.0 * radial(ti)) if ti in col else None
        ap = surf[ti].aperture
        t_ap = _f(_declared_diameter(ap)) if ap is not None else t_fp

    # ------------------------------------------------------ bounding boxes
    items = []
    for i in range(vw + (0 if surf[vw].interaction in _DUMMY else 1)):
        si = surf[i]
        if si.interaction in _DUMMY:
            continue
        ap = si.aperture
        if si.array is not None:
            arr = system.arrays[si.array]
            xy = (_outline(ap.kind, ap.radius if ap.kind == "circular" else ap.half_width, ap.decenter)
                  if ap is not None else _outline("rectangular", (0.5 * arr.pitch[0], 0.5 * arr.pitch[1])))
            # Global points are affine in the lenslet axis: the corner lenslets bound the array.
            for a in (0, arr.m - 1):
                for b in (0, arr.n - 1):
                    items.append((i, xy, np.broadcast_to(model.lenslet_center(a, b), xy.shape)))
            continue
        if ap is not None:
            xy = _outline(ap.kind, ap.radius if ap.kind == "circular" else ap.half_width, ap.decenter)
        else:
            h = hits[ok, col[i]]
            if not len(h):
                continue
            if rotational(i):  # a lens blank: the disc of the footprint's radius
                xy = _outline("circular", float(np.max(np.hypot(h[:, 0], h[:, 1]))))
            else:  # the footprint's rectangle
                lo, hi = h.min(axis=0), h.max(axis=0)
                xy = _outline("rectangular", 0.5 * (hi - lo), 0.5 * (hi + lo))
        items.append((i, xy, None))
    pts = geo.to_global(items)
    # The display's active area: the EI grid on the plane z = −g, every CDP state.
    M, N = model.arr.m, model.arr.n
    corners_m, corners_n = np.array([0, M - 1, 0, M - 1]), np.array([0, 0, N - 1, N - 1])
    disp = []
    for kk in range(len(model.depths)):
        c = model.ei_centers(kk, corners_m, corners_n)
        half = 0.5 * np.abs(model.ei_pitch(kk))
        for sx in (-1.0, 1.0):
            for sy in (-1.0, 1.0):
                disp.append(np.column_stack([c + half * np.array([sx, sy]), np.full(4, -model.g)]))
    box = _box(pts + disp)
    prism_faces = {i for run in prisms(system) if max(run) < vw for i in run
                   if surf[i].interaction in ("refract", "reflect", "tir")}
    pbox = _box([p for (i, _, _), p in zip(items, pts) if i in prism_faces]) if prism_faces else None
    # The light's own extent in the prism: the ray set's hits on its faces (a prism can be no
    # smaller; its clear apertures, above, are what is built).
    fbox = (_box(geo.to_global([(i, hits[ok, col[i]], None) for i in sorted(prism_faces) if i in col]))
            if prism_faces else None)

    # ----------------------------------------------------------- thickness
    centre, edge = [], []
    for i, j, rad in (glass_pairs(system, names, values, vw) if solids else ()):
        centre.append(float(values[tr.index[f"{surf[i].name}.thickness"]]))
        edge.append(edge_thickness(tr, values, i, j, rad))
    mla = list(spec.mla_surfaces)
    for i, j in (zip(mla[:-1], mla[1:]) if solids else ()):
        if (j != i + 1 or surf[i].interaction != "refract" or surf[j].interaction != "refract"
                or not is_glass(system, names, values, i)):
            continue
        corner = np.array([_lenslet_corner(system, i, j)])
        zi, zj = geo.sags([(i, corner), (j, corner)])  # both surfaces share the lenslet axis
        centre.append(float(values[tr.index[f"{surf[i].name}.thickness"]]))
        e = centre[-1] + float(zj[0]) - float(zi[0])
        edge.append(e if math.isfinite(e) else -math.inf)
    p_min = None
    if solids and prisms(system):
        th = prism_thickness(tr, values, PRISM_POINTS)[0]
        th = th[np.isfinite(th)]
        p_min = _f(np.min(th)) if th.size else None

    # ---------------------------------------------------------- eye relief
    relief = math.nan
    last = max((i for i in range(vw) if surf[i].interaction not in _DUMMY), default=None)
    if last is not None and np.any(ok):
        off = model.lenslet_center(m[ok], n[ok]) if surf[last].array is not None else None
        p = geo.to_global([(last, hits[ok, col[last]], off)])[0]
        R_vw, o_vw = geo.frames[vw]
        if len(p):
            relief = float(np.min(-(p - o_vw) @ R_vw[:, 2]))

    return {
        "track_mm": _f(track),
        "max_clear_diameter_mm": max(diam) if diam else None,
        "clear_diameters_mm": clear,
        "tunable_clear_aperture_mm": t_ap,
        "tunable_footprint_mm": t_fp,
        "bounding_box_mm": None if box is None else [float(v) for v in box[1] - box[0]],
        "bounding_box_min_mm": None if box is None else [float(v) for v in box[0]],
        "bounding_box_max_mm": None if box is None else [float(v) for v in box[1]],
        "prism_box_mm": None if pbox is None else [float(v) for v in pbox[1] - pbox[0]],
        "prism_footprint_box_mm": None if fbox is None else [float(v) for v in fbox[1] - fbox[0]],
        "min_center_thickness_mm": _min_finite(centre),
        "min_edge_thickness_mm": _min_finite(edge),
        "min_prism_thickness_mm": p_min,
        "eye_relief_mm": _f(relief),
        "rays_traced": int(len(ok)),
        "rays_failed": int(np.sum(~ok)),
    }
