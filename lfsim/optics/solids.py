"""Thickness of a design's glass prisms, on the tracer's own surface model.

A prism (:func:`lfsim.optics.components.components`, kind ``"prism"``) is a
run of glass bounded by faces that refract and reflect. Its thickness at a
point P of one face is measured along that face's normal N, into the glass:
the distance from P to the first opposite face of the prism that the line
P + t·N (t > 0) meets inside that face's clear aperture. The glass side of a
face is the side on which the next face of the run lies (the previous one
for the exit face), judged from the centre of that face's clear aperture.
Two faces are opposite when, at the centres of their clear apertures, their
normals into the glass are more than 180° − ``OPPOSITE_DEG`` apart (the
faces are within ``OPPOSITE_DEG`` of parallel, like the front and back of a
prism eyepiece); faces that meet at a wider angle (the entrance face and the
faces it joins at an edge) bound a wedge whose thickness goes to zero at
that edge by construction, and are not measured against each other. Neither
are faces that are one physical face (``same_as``).

Each face with a clear aperture is sampled on a ``points × points`` grid over
its aperture (boundary included; points of a circular aperture outside the
circle are dropped). A sample point whose normal line meets no other face
inside its aperture has no thickness (``inf``): the prism's glass there ends
outside every modelled aperture.

Every surface, frame and intersection is the tracer's
(:meth:`~lfsim.optics.tracer.SequentialTracer.frames`,
:func:`~lfsim.optics.surfaces.sag`, :func:`~lfsim.optics.surfaces.intersect`),
evaluated for several parameter vectors in one launch (a block per vector,
e.g. the central differences of an optimization's Jacobian).
"""

from __future__ import annotations

import math

import drjit as dr
import numpy as np

from .. import backend
from .components import components
from .prescription import Aperture, System
from .surfaces import intersect, normal, sag
from .tracer import _rot_xyz as rot_xyz

#: Shortest distance counted as a hit (mm): the line's own start point is not one.
_T_MIN = 1e-9
#: Faces within this angle of parallel (at their aperture centres) are opposite faces.
OPPOSITE_DEG = 45.0


def _np_matrix(M) -> np.ndarray:
    """(B, 3, 3) of a Dr.Jit Matrix3 of width B."""
    return np.stack([np.stack([np.asarray(M[a][b], dtype=np.float64) for b in range(3)], -1) for a in range(3)], -2)


def _np_vector(v) -> np.ndarray:
    """(B, 3) of a Dr.Jit Array3 of width B."""
    return np.stack([np.asarray(v[a], dtype=np.float64) for a in range(3)], -1)


def prisms(system: System) -> list[list[int]]:
    """Surface indices of every prism of the optical path, in order."""
    return [c.surfaces for c in components(system) if c.kind == "prism"]


def _faces(system: System, run: list[int]) -> list[int]:
    return [i for i in run if system.surfaces[i].aperture is not None
            and system.surfaces[i].interaction in ("refract", "reflect", "tir")]


def aperture_grid(system: System, i: int, points: int) -> np.ndarray:
    """(Q, 2) local (x, y) sample points over surface ``i``'s clear aperture."""
    return _grid(system.surfaces[i].aperture, points)


def _inside(ap, x, y) -> np.ndarray:
    dx, dy = x - ap.decenter[0], y - ap.decenter[1]
    if ap.kind == "circular":
        return np.hypot(dx, dy) <= ap.radius
    return (np.abs(dx) <= ap.half_width[0]) & (np.abs(dy) <= ap.half_width[1])


def prism_thickness(tracer, values, points: int = 9) -> tuple[np.ndarray, list[tuple[int, np.ndarray]]]:
    """Thickness (B, Q) of every prism at every sample point, for B parameter vectors.

    ``values`` (B, n_params) or (n_params,): parameter vectors of the tracer's
    table. Returns the thickness in mm (``inf`` where the normal line meets
    no other face) and, per sampled face, ``(surface index, local xy (Q_i, 2))``
    in the order of the Q columns.
    """
    T = tracer.T
    system: System = tracer.system
    V = np.atleast_2d(np.asarray(values, dtype=np.float64))
    B = len(V)
    with dr.suspend_grad():
        packed = tracer.params(values=V.ravel())
        Rs, os_ = tracer.frames(packed)

        def shape(i, reps):  # surface i's shape, block b's coefficients on lanes b·reps … (b+1)·reps − 1
            return tracer.shape(packed, i, backend.from_numpy(T.UInt32, np.repeat(np.arange(B, dtype=np.uint32), reps)))

        R = [_np_matrix(Ri) for Ri in Rs]  # (B, 3, 3) each
        o = [_np_vector(oi) for oi in os_]  # (B, 3)

        def surface_points(i, xy):
            """Global points and unit normals (B, Q, 3) of surface i at local xy (Q, 2)."""
            Q = len(xy)
            X, Y = (backend.from_numpy(T.Float, np.tile(xy[:, k], B)) for k in (0, 1))
            z, zx, zy, ok = sag(X, Y, shape(i, Q))
            n = normal(zx, zy, T.Array3)
            dr.eval(z, n, ok)
            p = np.stack([np.tile(xy[:, 0], B), np.tile(xy[:, 1], B),
                          np.asarray(z, dtype=np.float64)], -1).reshape(B, Q, 3)
            nn = np.stack([np.asarray(n[k], dtype=np.float64) for k in range(3)], -1).reshape(B, Q, 3)
            okn = np.asarray(ok).reshape(B, Q)
            return (np.einsum("bij,bqj->bqi", R[i], p) + o[i][:, None],
                    np.einsum("bij,bqj->bqi", R[i], nn), okn)

        def centre(i):
            return surface_points(i, np.array([system.surfaces[i].aperture.decenter], dtype=np.float64))

        def into_glass(N, P, C):
            side = np.sign(np.einsum("bqi,bqi->bq", N, C - P))
            return N * np.where(side == 0, 1.0, side)[..., None]

        cols, sampled = [], []
        for run in prisms(system):
            faces = _faces(system, run)
            owner = {i: (system.surfaces[i].same_as if system.surfaces[i].same_as is not None else i)
                     for i in faces}
            nbr = {a: faces[j + 1] if j + 1 < len(faces) else faces[j - 1] for j, a in enumerate(faces)}
            cen = {a: centre(a) for a in faces}
            # Inward normals at the aperture centres (the nominal block decides which faces are opposite).
            inward = {a: into_glass(cen[a][1], cen[a][0], cen[nbr[a]][0])[0, 0] for a in faces}
            cos_opp = -np.cos(np.radians(OPPOSITE_DEG))
            for a in faces:
                xy = aperture_grid(system, a, points)
                P, N, ok_a = surface_points(a, xy)
                U = into_glass(N, P, cen[nbr[a]][0])
                best = np.full(P.shape[:2], np.inf)
                for b in faces:
                    if owner[b] == owner[a] or inward[a] @ inward[b] > cos_opp:
                        continue
                    Q = P.shape[1]
                    pl = np.einsum("bji,bqj->bqi", R[b], P - o[b][:, None])  # R^T (P − o)
                    dl = np.einsum("bji,bqj->bqi", R[b], U)
                    pa = T.Array3(*backend.from_numpy(T.Float, *(pl[..., k].ravel() for k in range(3))))
                    da = T.Array3(*backend.from_numpy(T.Float, *(dl[..., k].ravel() for k in range(3))))
                    t, hit, conv = intersect(pa, da, shape(b, Q), T, True,
                                             tracer.newton_tol, tracer.newton_max_iter)
                    dr.eval(t, hit, conv)
                    t = np.asarray(t, dtype=np.float64).reshape(B, Q)
                    good = np.asarray(hit & conv).reshape(B, Q) & (t > _T_MIN)
                    q = pl + t[..., None] * dl
                    good &= _inside(system.surfaces[b].aperture, q[..., 0], q[..., 1])
                    best = np.where(good & (t < best), t, best)
                cols.append(np.where(ok_a, best, np.inf))
                sampled.append((a, xy))
    if not cols:
        return np.zeros((B, 0)), []
    return np.concatenate(cols, axis=1), sampled


# ----------------------------------------------------------- crossing surfaces
#: Glass thinner than this (mm, relative to max(1, |centre thickness|)) counts as crossed.
CROSSING_TOL = 1e-9


def _pair_offsets(system: System, i: int) -> tuple[np.ndarray, np.ndarray] | None:
    """The vertices' offsets (x, y) of surfaces i and i + 1 from the axis surface i was
    placed on, when both sit on that axis untilted (decentred or not), ``thickness``
    apart; None otherwise (a tilt, a global position, a coordinate break, a copy)."""
    a, b = system.surfaces[i], system.surfaces[i + 1]
    if a.same_as is not None or b.same_as is not None or a.global_position is not None:
        return None
    if b.global_position is not None or any(a.tilt) or any(b.tilt) or b.interaction == "break":
        return None
    off_a = np.asarray(a.decenter, dtype=np.float64)
    # A decentred surface that returns the axis sends the next one back to the old axis.
    off_b = np.asarray(b.decenter, dtype=np.float64) + (0.0 if a.return_axis else off_a)
    return off_a, off_b


#: Surface interactions that are optical faces (a dummy plane, "none", is a reference that may
#: lie anywhere; a coordinate break has no face).
_FACES = ("refract", "reflect", "tir", "paraxial")


def crossings(system: System, points: int = 17) -> list[tuple[int, int, float, float, bool]]:
    """Neighbouring faces that cross: ``(i, i + 1, radial height mm, thickness mm, glass)``.

    For each refracting surface ``i`` into a medium denser than air (index >
    1.0001 at the primary wavelength: ``glass``) followed on its own axis by surface
    ``i + 1``, the glass thickness ``t(x, y) = d_i + z_{i+1}(x, y) − z_i(x, y)``
    (the tracer's sag model, :func:`~lfsim.optics.surfaces.sag`) is sampled on
    a ``points × points`` grid over the clear apertures both surfaces share (a
    lenslet array's surfaces: over the lenslet cell; no aperture: the vertex
    only). Where it is negative the surfaces cross inside their apertures (or
    the centre thickness itself is negative), which no lens can do; the
    worst point of each such element is returned (after an odd number of
    mirrors light runs toward −z and the thickness is counted that way). A
    decentred surface is sampled where it sits: its sag about its own vertex,
    over its aperture moved with it. Pairs with a surface marked ``virtual``,
    and pairs not on one axis (tilted or globally placed), are not checked.

    The same holds for the air between two optical faces (refracting, reflecting or
    ideal lenses; not dummy planes): a negative air gap puts the next face behind the
    light, which the tracer lets through only at ideal lenses and dummy planes (they
    are reached along the ray's line either way), so such a design would trace as if
    light ran backwards. The image surface may lie behind the last face (a virtual
    image) and is not checked against it.
    """
    from .vector import DesignVector

    vec = DesignVector(system)
    get = vec.numpy_getter(vec.values())
    out = []
    surfs = system.surfaces
    flips = 0  # reflections so far: after an odd number light runs toward -z, and so does the glass
    for i in range(len(surfs) - 1):
        a, b = surfs[i], surfs[i + 1]
        flips += a.interaction in ("reflect", "tir")
        if a.interaction not in _FACES or b.interaction not in _FACES or a.virtual or b.virtual:
            continue
        offsets = _pair_offsets(system, i)
        glass = a.interaction == "refract" and a.material.index(system.primary_wavelength_nm) > 1.0001
        if offsets is None or (not glass and i + 1 == len(surfs) - 1):
            continue
        off_a, off_b = offsets
        if (a.array is None) != (b.array is None) or a.array != b.array:
            continue
        aps = [(s.aperture, off) for s, off in ((a, off_a), (b, off_b)) if s.aperture is not None]
        if a.array is not None and not aps:
            arr = system.arrays[a.array]
            aps = [(Aperture("rectangular", half_width=(0.5 * arr.pitch[0], 0.5 * arr.pitch[1])), off_a)]
        if aps:  # points of the axis frame inside every aperture where it sits
            xy = _grid(aps[0][0], points) + aps[0][1]
            keep = np.ones(len(xy), bool)
            for ap, off in aps[1:]:
                keep &= _inside(ap, xy[:, 0] - off[0], xy[:, 1] - off[1])
            xy = np.vstack([xy[keep], [off_a]])
        else:
            xy = off_a[None]
        sa, sb = vec.shape(i, get), vec.shape(i + 1, get)
        d = float(get(f"{a.name}.thickness"))
        worst = None
        for x, y in xy:
            za, _, _, ina = sag(float(x - off_a[0]), float(y - off_a[1]), sa)
            zb, _, _, inb = sag(float(x - off_b[0]), float(y - off_b[1]), sb)
            if not (ina and inb):
                continue
            t = (d + zb - za) * (-1.0 if flips % 2 else 1.0)
            if worst is None or t < worst[1]:
                worst = (math.hypot(x, y), t)
        if worst is not None and worst[1] < -CROSSING_TOL * max(1.0, abs(d)):
            out.append((i, i + 1, worst[0], worst[1], glass))
    return out


def _grid(ap, points: int) -> np.ndarray:
    """``points × points`` samples over a clear aperture (boundary included)."""
    u = np.linspace(-1.0, 1.0, points)
    X, Y = np.meshgrid(u, u, indexing="xy")
    if ap.kind == "circular":
        keep = np.hypot(X, Y) <= 1.0 + 1e-12
        xy = np.stack([X[keep], Y[keep]], axis=1) * ap.radius
    else:
        xy = np.stack([X.ravel(), Y.ravel()], axis=1) * np.array(ap.half_width)
    return xy + np.array(ap.decenter)


# ---------------------------------------------------------- glass elements
def is_glass(system, names, values, i: int) -> bool:
    """Surface ``i`` refracts into a medium denser than air."""
    s = system.surfaces[i]
    return s.interaction in ("refract", "tir") and values[names.index(f"{s.name}.index")] > 1.0001


def glass_pairs(system, names, values, last: int) -> list[tuple[int, int, float]]:
    """(front, back, radius) of each glass element among surfaces ``0 … last − 1``
    outside a lenslet array: a refracting surface into glass followed by a
    refracting one, both axial (no ``global_position``), at the larger of their
    circular clear radii."""
    surf = system.surfaces
    out = []
    for i in range(last - 1):
        a, b = surf[i], surf[i + 1]
        if a.array is not None or b.array is not None or a.interaction != "refract":
            continue
        if b.interaction != "refract" or not is_glass(system, names, values, i):
            continue
        radii = [s.aperture.radius for s in (a, b) if s.aperture is not None and s.aperture.kind == "circular"]
        if radii and a.global_position is None and b.global_position is None:
            out.append((i, i + 1, max(radii)))
    return out


#: Points on a glass element's rim at which its edge thickness is measured.
EDGE_RIM_POINTS = 64


def _coaxial_element(system, V: np.ndarray, col, i: int, j: int) -> bool:
    """Whether surfaces i and j sit untilted and undecentred on one axis in every row of V."""
    for s in (system.surfaces[i], system.surfaces[j]):
        if s.aperture is not None and any(s.aperture.decenter):
            return False
        if any(np.any(col(f"{s.name}.{k}") != 0.0) for k in ("decenter_x", "decenter_y", "tilt_x", "tilt_y", "tilt_z")):
            return False
    return True


def _rim_radius(system, col, i: int, j: int, radius: float) -> np.ndarray:
    """(B,) radius of the circle about the element's axis that holds both surfaces'
    circular clear apertures where they sit (``radius`` where neither is circular)."""
    rim = np.zeros(len(col(f"{system.surfaces[i].name}.decenter_x")))
    for s in (system.surfaces[i], system.surfaces[j]):
        ap = s.aperture
        if ap is not None and ap.kind == "circular":
            dx = col(f"{s.name}.decenter_x") + ap.decenter[0]
            dy = col(f"{s.name}.decenter_y") + ap.decenter[1]
            rim = np.maximum(rim, ap.radius + np.hypot(dx, dy))
    return np.where(rim > 0.0, rim, radius)


def _axial_hits(tracer, V: np.ndarray, col, i: int, j: int, local: np.ndarray):
    """Where the lines through ``local`` (B, Q, 3) points of the element's axis frame
    (surface i's frame before its own decenter and tilt, to which both surfaces return),
    parallel to that axis, meet surfaces i and j: the points P (B, Q, 3), the axis
    direction D (B, Q, 3) and the parameters t_i, t_j (B, Q) along it (NaN where a
    line misses), global frame, for B parameter vectors in one launch."""
    T, system = tracer.T, tracer.system
    a = system.surfaces[i]
    B, Q = local.shape[:2]
    with dr.suspend_grad():
        packed = tracer.params(values=V.ravel())
        Rs, os_ = tracer.frames(packed)
        R = [_np_matrix(Rs[k]) for k in (i, j)]  # (B, 3, 3)
        o = [_np_vector(os_[k]) for k in (i, j)]  # (B, 3)
        deg = math.pi / 180.0
        tilt = _np_matrix(rot_xyz(*(backend.from_numpy(T.Float, col(f"{a.name}.tilt_{ax}") * deg)
                                    for ax in "xyz"), T))  # the tracer's own tilt
        R_ax = R[0] @ np.swapaxes(tilt, 1, 2)  # the frame surface i was placed from
        shift = np.stack([col(f"{a.name}.decenter_x"), col(f"{a.name}.decenter_y"), np.zeros(B)], -1)
        o_ax = o[0] - np.einsum("bij,bj->bi", R_ax, shift)
        P = np.einsum("bij,bqj->bqi", R_ax, local) + o_ax[:, None]  # (B, Q, 3), global
        D = np.broadcast_to(R_ax[:, :, 2][:, None], P.shape)  # the axis
        block = backend.from_numpy(T.UInt32, np.repeat(np.arange(B, dtype=np.uint32), Q))
        t = []
        for k, Rk, ok_ in ((i, R[0], o[0]), (j, R[1], o[1])):
            pl = np.einsum("bji,bqj->bqi", Rk, P - ok_[:, None])  # R^T (P − o)
            dl = np.einsum("bji,bqj->bqi", Rk, D)
            pa = T.Array3(*backend.from_numpy(T.Float, *(pl[..., c].ravel() for c in range(3))))
            da = T.Array3(*backend.from_numpy(T.Float, *(dl[..., c].ravel() for c in range(3))))
            tk, hit, conv = intersect(pa, da, tracer.shape(packed, k, block), T, True,
                                      tracer.newton_tol, tracer.newton_max_iter)
            dr.eval(tk, hit, conv)
            tk = np.asarray(tk, dtype=np.float64).reshape(B, Q)
            t.append(np.where(np.asarray(hit & conv).reshape(B, Q), tk, np.nan))
    return P, D, t[0], t[1]


def rim_thickness(tracer, values, i: int, j: int, radius: float, points: int = EDGE_RIM_POINTS) -> np.ndarray:
    """Glass thickness (B, points) at ``points`` equally spaced points of the rim of the
    element between surfaces i and j, for B parameter vectors ``values`` (B, n_params)
    or (n_params,), in one launch.

    The rim is the circle about the element's axis (surface i's frame before its
    own decenter and tilt, to which both surfaces return) that holds both
    surfaces' circular clear apertures where they sit: radius ``max(r_k +
    |d_k|)`` over the surfaces' clear radii r_k and the offsets d_k of their
    aperture centres from the axis (surface decenter plus aperture decenter),
    ``radius`` where neither aperture is circular. The thickness at a rim point
    is the distance between the two surfaces along the line through it parallel
    to the axis: the tracer's own intersection with each surface in its frame,
    so that tilted and decentred surfaces (a lens decentred or tilted as a whole,
    or wedged) are measured as they are built. −inf where the line misses a
    surface.
    """
    names = tracer.names
    V = np.atleast_2d(np.asarray(values, dtype=np.float64))

    def col(name):
        return V[:, names.index(name)]

    rim = _rim_radius(tracer.system, col, i, j, radius)
    phi = np.linspace(0.0, 2.0 * math.pi, points, endpoint=False)
    local = np.stack([np.cos(phi), np.sin(phi), np.zeros_like(phi)], -1)[None] * rim[:, None, None]
    _, _, t0, t1 = _axial_hits(tracer, V, col, i, j, local)
    e = t1 - t0
    return np.where(np.isfinite(e), e, -math.inf)


def element_section(tracer, values, i: int, j: int, radius: float, points: int = 65):
    """The y-z section of the glass element between surfaces i and j as it is built:
    ``(front, back)`` (points, 3) global points where the lines parallel to its axis,
    across the rim's diameter in the axis frame's y-z plane (:func:`rim_thickness`),
    meet each surface; NaN rows where a line misses. The lens's edge joins the two
    profiles' ends, along the axis."""
    names = tracer.names
    V = np.atleast_2d(np.asarray(values, dtype=np.float64))[:1]

    def col(name):
        return V[:, names.index(name)]

    rim = _rim_radius(tracer.system, col, i, j, radius)
    y = np.linspace(-1.0, 1.0, points)
    local = np.stack([np.zeros_like(y), y, np.zeros_like(y)], -1)[None] * rim[:, None, None]
    P, D, t0, t1 = _axial_hits(tracer, V, col, i, j, local)
    return P[0] + t0[0][:, None] * D[0], P[0] + t1[0][:, None] * D[0]


def edge_thickness(tracer, values, i: int, j: int, radius: float, points: int = EDGE_RIM_POINTS):
    """Least glass thickness on the rim of the element between surfaces i and j
    (:func:`rim_thickness`). On a coaxial element (no decenter or tilt on either
    surface) that is ``d + z_j(r) − z_i(r)`` at ``radius``, evaluated so from the sags.
    −inf where a sag or an intersection is undefined.

    ``values`` (n_params,) gives a float; (B, n_params) gives (B,) (e.g. the central
    differences of a Jacobian; off the axis in one launch).
    """
    T, names = tracer.T, tracer.names
    V = np.asarray(values, dtype=np.float64)
    single = V.ndim == 1
    V = np.atleast_2d(V)

    def col(name):
        return V[:, names.index(name)]

    if not _coaxial_element(tracer.system, V, col, i, j):
        e = np.min(rim_thickness(tracer, V, i, j, radius, points), axis=1)
        return float(e[0]) if single else e

    block = dr.zeros(T.UInt32, 1)
    out = []
    for v in V:
        P = tracer.params(values=v)

        def z(k):
            with dr.suspend_grad():
                zz, _, _, inside = sag(dr.opaque(T.Float, radius), T.Float(0.0), tracer.shape(P, k, block))
            return float(zz[0]) if bool(inside[0]) else math.nan

        thick = float(v[names.index(f"{tracer.system.surfaces[i].name}.thickness")])
        e = thick - z(i) + z(j)
        out.append(e if math.isfinite(e) else -math.inf)
    return out[0] if single else np.array(out)
