"""Triangle meshes of a design's optics: tessellations of lfsim's own surfaces.

Every vertex and every vertex normal is evaluated by
:func:`lfsim.optics.surfaces.sag` / :func:`lfsim.optics.surfaces.normal` (the
functions the tracer intersects), in the frames of
:meth:`lfsim.optics.tracer.SequentialTracer.frames` for a parameter vector
``values`` (:meth:`System.parameter_table` order). A per-state vector (e.g. a
tunable-lens power, a moved MLA) therefore gives the meshes of that state.
Nothing here re-implements surface math; this module only chooses where to
sample and how to connect the samples.

Conventions (numpy, float64, millimetres, design global frame):

* :class:`Mesh` ``vertices`` (V, 3) and ``normals`` (V, 3) are global.
  Optical faces carry the analytic unit normal of their surface oriented
  along **+z of the surface's local frame**, and every triangle is wound
  counter-clockwise seen from that side (its geometric normal agrees with the
  vertex normals). ``uv`` holds the local (x, y) of each vertex (lenslet
  arrays: the surface's local x, y, not lenslet-relative).
* Rim bands, side walls, bevels and caps have no vertex normals (flat
  shading) and are wound with their geometric normal pointing out of the
  glass.
* A :class:`Solid` is a set of meshes whose ``pieces`` each close a volume of
  one medium: after welding vertices with bit-identical positions every edge
  of a piece is shared by exactly two of its triangles (seams between meshes
  reuse the very same coordinates, so this weld is exact). A cemented
  interface belongs to the two pieces on either side of it.

Densities: ``segments`` per semi-diameter of a circular (or per larger
half-width of a rectangular) clear aperture; ``lenslet_segments`` per lenslet
pitch. A disk with S segments has S rings with 6k vertices on ring k, so its
rim polygon has 6S sides.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from functools import lru_cache

import drjit as dr
import numpy as np

from .. import backend
from ..optics.components import Component, components  # noqa: F401  (re-exported)
from ..optics.prescription import Aperture, System
from ..optics.surfaces import Shape, normal, sag

#: Default tessellation: segments per semi-diameter of an ordinary surface,
#: per lenslet pitch, and per half-width of a freeform prism's largest face.
#: Flat triangles with interpolated analytic normals converge as 1/S²; the
#: prism is denser because its faces are the largest and its mirror doubles
#: any normal error. Measured with benchmarks/render_error_vs_time.py (mesh
#: path vs analytic path, same eye rays, Fig. 9 wall): relative RMSE 0.7 % on
#: scenes/ini_coaxial.toml and 0.7 % on scenes/ini_freeform.toml at these
#: values; the 17 × 9 MLA builds in under a second.
DEFAULT_SEGMENTS = 64
DEFAULT_LENSLET_SEGMENTS = 32
DEFAULT_PRISM_SEGMENTS = 128


def tessellation(density: float = 1.0) -> dict[str, int]:
    """Segment counts at ``density`` × the defaults (keyword arguments of
    :func:`lfsim.render.optics_scene.optics_shapes`)."""
    if not density > 0:
        raise ValueError(f"tessellation density = {density!r}: expected > 0")
    return {"segments": max(2, round(density * DEFAULT_SEGMENTS)),
            "lenslet_segments": max(2, round(density * DEFAULT_LENSLET_SEGMENTS)),
            "prism_segments": max(2, round(density * DEFAULT_PRISM_SEGMENTS))}


_TWO_PI = 2.0 * math.pi


# ---------------------------------------------------------------- data
@dataclass
class Mesh:
    """One triangle mesh (see the module docstring for frames and orientation).

    Attributes
    ----------
    name : str
    vertices : (V, 3) float64, global frame, mm
    faces : (F, 3) int64
    normals : (V, 3) float64 or None (flat shading)
    uv : (V, 2) float64 or None, the surface-local (x, y) of each vertex
    role : str
        ``"face"`` (an optical surface), ``"paraxial"`` (the plane of an ideal
        lens), ``"mask"`` (an absorbing aperture mask), ``"rim"``, ``"wall"``.
    surface : int or None
        Index into ``system.surfaces`` of an optical face.
    loop : (L,) int64 or None
        Boundary loop of a face (indices into ``vertices``), counter-clockwise
        about the aperture centre in the local frame.
    loop_angle : (L,) float64 or None
        Polar angle of each loop vertex about the aperture centre (local).
    """

    name: str
    vertices: np.ndarray
    faces: np.ndarray
    normals: np.ndarray | None = None
    uv: np.ndarray | None = None
    role: str = "face"
    surface: int | None = None
    loop: np.ndarray | None = None
    loop_angle: np.ndarray | None = None


@dataclass
class Solid:
    """Meshes bounding one optical element; ``pieces`` lists the closed volumes."""

    name: str
    meshes: list[Mesh]
    pieces: list[list[int]] = field(default_factory=list)

    def open_edges(self) -> list[int]:
        """Number of edges not shared by exactly two triangles, per piece."""
        return [open_edge_count([self.meshes[k] for k in piece]) for piece in self.pieces]

    def is_watertight(self) -> bool:
        return bool(self.pieces) and all(n == 0 for n in self.open_edges())


# ------------------------------------------------------- topology checks
def weld(vertices: np.ndarray) -> np.ndarray:
    """Ids of vertices after merging bit-identical positions: (V,) int64."""
    v = np.ascontiguousarray(vertices, dtype=np.float64) + 0.0  # −0.0 → +0.0
    _, inv = np.unique(v.view(np.dtype((np.void, 24))).ravel(), return_inverse=True)
    return inv.ravel()


def open_edge_count(meshes: list[Mesh]) -> int:
    """Edges (after :func:`weld`) not shared by exactly two triangles."""
    verts = np.concatenate([m.vertices for m in meshes])
    offs = np.cumsum([0] + [len(m.vertices) for m in meshes[:-1]])
    faces = np.concatenate([m.faces + o for m, o in zip(meshes, offs)])
    ids = weld(verts)[faces]
    ids = ids[(ids[:, 0] != ids[:, 1]) & (ids[:, 1] != ids[:, 2]) & (ids[:, 0] != ids[:, 2])]
    e = np.sort(np.concatenate([ids[:, [0, 1]], ids[:, [1, 2]], ids[:, [2, 0]]]), axis=1)
    _, counts = np.unique(e, axis=0, return_counts=True)
    return int(np.count_nonzero(counts != 2))


# ------------------------------------------------------ analytic surfaces
class SurfaceModel:
    """The analytic surfaces of a system at one parameter vector (float64).

    Parameters
    ----------
    design : Design or System
    values : array_like, optional
        Parameter vector (``system.parameter_names()`` order); default: the
        design values with indices at ``wavelength_nm``.
    wavelength_nm : float, optional
        Default: the system's primary wavelength.
    """

    def __init__(self, design, values=None, wavelength_nm=None):
        from ..optics.tracer import SequentialTracer

        system: System = getattr(design, "system", design)
        self.system = system
        self.tracer = design.tracer("float64") if hasattr(design, "tracer") else SequentialTracer(system, "float64")
        self.T = self.tracer.T
        lam = system.primary_wavelength_nm if wavelength_nm is None else float(wavelength_nm)
        self.wavelength_nm = lam
        if values is None:
            values = system.parameter_values(lam)
        values = np.asarray(values, dtype=np.float64).ravel()
        if values.size != self.tracer.n_params:
            raise ValueError(f"values has {values.size} entries; the design has {self.tracer.n_params} "
                             "parameters (see parameter_names())")
        self.values = values
        with dr.suspend_grad():
            self.frames = self.tracer.frames_numpy(self.tracer.params(values=values))
        self.vector = self.tracer.vector
        self._media = self.vector.media  # index parameter of the medium before each surface

    # -- parameters
    def value(self, name: str) -> float:
        return float(self.values[self.tracer.index[name]])

    def owner(self, i: int) -> int:
        return self.vector.owner(i)

    def index_before(self, i: int) -> float:
        """Index of the medium a ray is in when it meets surface ``i``."""
        return self.value(self._media[i])

    def index_other(self, i: int) -> float:
        """Index on the far side of surface ``i`` (refract: after it; tir: its material)."""
        s = self.system.surfaces[i]
        if s.interaction in ("refract", "tir"):
            return self.value(f"{s.name}.index")
        return self.index_before(i)

    def power(self, i: int) -> float:
        return self.value(f"{self.system.surfaces[i].name}.power")

    def lenslet_centres(self, array: str) -> tuple[np.ndarray, np.ndarray, tuple[float, float]]:
        """Lenslet axis positions x_m (M,), y_n (N,) and the pitch, in each member's local frame."""
        a = self.system.arrays[array]
        xm, yn = self.vector.lenslet_centre(array, np.arange(a.m), np.arange(a.n), self.value)
        return xm, yn, (self.value(f"{array}.pitch_x"), self.value(f"{array}.pitch_y"))

    def shape(self, i: int) -> Shape:
        """The :class:`~lfsim.optics.surfaces.Shape` of surface ``i`` from ``values``."""
        def op(v):
            return dr.opaque(self.T.Float, float(v))

        return self.vector.shape(i, lambda name: op(self.value(name)), const=op)

    def sag(self, i: int, x, y) -> tuple[np.ndarray, np.ndarray]:
        """Sag z and unit normal (+z local) of surface ``i`` at local (x, y).

        Evaluated by :func:`lfsim.optics.surfaces.sag` and
        :func:`~lfsim.optics.surfaces.normal`. Raises ``ValueError`` where
        (x, y) is outside the domain of the base conic.
        """
        T = self.T
        x = np.asarray(x, dtype=np.float64)
        y = np.asarray(y, dtype=np.float64)
        shp = x.shape
        if x.size == 0:
            return np.zeros(shp), np.zeros(shp + (3,))
        with dr.suspend_grad():
            X, Y = backend.from_numpy(T.Float, x.ravel(), y.ravel())
            z, zx, zy, inside = sag(X, Y, self.shape(i))
            n = normal(zx, zy, T.Array3)
            dr.eval(z, n, inside)
            inside = np.asarray(inside)
            if not inside.all():
                name = self.system.surfaces[i].name
                raise ValueError(f"surface {name}: {np.count_nonzero(~inside)} mesh vertices lie outside "
                                 "the domain of its base conic (aperture too large for its curvature)")
            zn = np.asarray(z, dtype=np.float64).reshape(shp)
            nn = np.stack([np.asarray(n.x), np.asarray(n.y), np.asarray(n.z)], axis=-1).astype(np.float64)
        return zn, nn.reshape(shp + (3,))

    # -- frames
    def to_global(self, i: int, p: np.ndarray) -> np.ndarray:
        """Local points (..., 3) of surface ``i`` → global (elementwise, bit-reproducible)."""
        R, o = self.frames[i]
        return np.stack([R[k, 0] * p[..., 0] + R[k, 1] * p[..., 1] + R[k, 2] * p[..., 2] + o[k]
                         for k in range(3)], axis=-1)

    def dir_to_global(self, i: int, v: np.ndarray) -> np.ndarray:
        R, _ = self.frames[i]
        return np.stack([R[k, 0] * v[..., 0] + R[k, 1] * v[..., 1] + R[k, 2] * v[..., 2]
                         for k in range(3)], axis=-1)

    def to_local(self, i: int, p: np.ndarray) -> np.ndarray:
        R, o = self.frames[i]
        return (np.asarray(p, dtype=np.float64) - o) @ R


# ------------------------------------------------------------ primitives
def _zipper(a_idx, a_ang, b_idx, b_ang) -> np.ndarray:
    """Triangles joining two closed loops A and B, merged by polar angle.

    Both loops are sorted by angle here (star-shaped about the same centre).
    Triangles are (a_i, b_j, a_i+1) and (a_i, b_j, b_j+1): counter-clockwise
    seen from +z when A is the inner loop. Degenerate triangles (a loop of
    one vertex) are dropped.
    """
    oa, ob = np.argsort(a_ang, kind="stable"), np.argsort(b_ang, kind="stable")
    a, aa = np.asarray(a_idx)[oa], np.asarray(a_ang, dtype=np.float64)[oa]
    b, ba = np.asarray(b_idx)[ob], np.asarray(b_ang, dtype=np.float64)[ob]
    na, nb = len(a), len(b)
    ev = np.concatenate([np.append(aa[1:], aa[0] + _TWO_PI), np.append(ba[1:], ba[0] + _TWO_PI)])
    which_b = np.concatenate([np.zeros(na, bool), np.ones(nb, bool)])
    order = np.argsort(ev, kind="stable")
    wb = which_b[order]
    ia = np.cumsum(~wb) - (~wb)
    jb = np.cumsum(wb) - wb
    ia_n, jb_n = (ia + 1) % na, (jb + 1) % nb
    ia, jb = ia % na, jb % nb
    t = np.where(wb[:, None],
                 np.stack([a[ia], b[jb], b[jb_n]], axis=1),
                 np.stack([a[ia], b[jb], a[ia_n]], axis=1))
    keep = (t[:, 0] != t[:, 1]) & (t[:, 1] != t[:, 2]) & (t[:, 0] != t[:, 2])
    return t[keep].astype(np.int64)


@lru_cache(maxsize=32)
def _unit_disk(S: int):
    """Unit disk: S rings, 6k vertices on ring k. Returns (uv, faces, loop, loop_angle)."""
    S = max(int(S), 1)
    k = np.arange(1, S + 1)
    counts = 6 * k
    starts = 1 + np.concatenate([[0], np.cumsum(counts)[:-1]])
    total = int(counts.sum())
    ring = np.repeat(k, counts)
    j = np.arange(total) - np.repeat(starts - 1, counts)
    th = _TWO_PI * j / np.repeat(counts, counts)
    r = ring / S
    uv = np.concatenate([[[0.0, 0.0]], np.stack([r * np.cos(th), r * np.sin(th), ], axis=1)])
    ang = np.concatenate([[0.0], th])
    faces = []
    prev = np.array([0])
    for kk in range(S):  # one zipper per ring (S ≤ a few hundred), not per vertex
        cur = np.arange(starts[kk], starts[kk] + counts[kk])
        faces.append(_zipper(prev, ang[prev], cur, ang[cur]))
        prev = cur
    uv[np.abs(uv) < 1e-15] = 0.0
    return uv, np.concatenate(faces), prev.copy(), ang[prev].copy()


@lru_cache(maxsize=32)
def _unit_rect(nx: int, ny: int):
    """Square [-1, 1]² grid with nx × ny cells. Returns (uv, faces, loop, loop_angle)."""
    u = np.linspace(-1.0, 1.0, nx + 1)
    v = np.linspace(-1.0, 1.0, ny + 1)
    U, V = np.meshgrid(u, v)  # (ny+1, nx+1), index = j*(nx+1) + i
    uv = np.stack([U.ravel(), V.ravel()], axis=1)
    faces = _grid_faces(nx, ny)
    idx = np.arange((nx + 1) * (ny + 1)).reshape(ny + 1, nx + 1)
    loop = np.concatenate([idx[0, :-1], idx[:-1, -1], idx[-1, :0:-1], idx[:0:-1, 0]])
    return uv, faces, loop, np.arctan2(uv[loop, 1], uv[loop, 0])


def _grid_faces(nx: int, ny: int) -> np.ndarray:
    """Triangles of an (ny+1) × (nx+1) row-major vertex grid, counter-clockwise in (x, y)."""
    j, i = np.meshgrid(np.arange(ny), np.arange(nx), indexing="ij")
    a = (j * (nx + 1) + i).ravel()
    b, c, d = a + 1, a + nx + 2, a + nx + 1
    return np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)]).astype(np.int64)


def _orient(faces: np.ndarray, vertices: np.ndarray, ref: np.ndarray) -> np.ndarray:
    """Flip triangles whose geometric normal points against ``ref`` (per-face or (3,))."""
    p = vertices[faces]
    n = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    ref = np.broadcast_to(ref, n.shape)
    flip = np.einsum("ij,ij->i", n, ref) < 0.0
    out = faces.copy()
    out[flip] = out[flip][:, [0, 2, 1]]
    return out


def _drop_degenerate(faces: np.ndarray, vertices: np.ndarray) -> np.ndarray:
    ids = weld(vertices)[faces]
    keep = (ids[:, 0] != ids[:, 1]) & (ids[:, 1] != ids[:, 2]) & (ids[:, 0] != ids[:, 2])
    return faces[keep]


def _outward(faces, vertices, centre) -> np.ndarray:
    return _orient(faces, vertices, vertices[faces].mean(axis=1) - centre)


# -------------------------------------------------------------- regions
def clear_region(system: System, i: int, default_radius: float) -> Aperture:
    """The region to tessellate for surface ``i``: its aperture, or the union
    (bounding circle / rectangle) of the apertures of every use of a
    ``same_as`` face, or a disk of ``default_radius`` when none is given."""
    uses = [j for j, s in enumerate(system.surfaces) if j == i or s.same_as == i]
    aps = [system.surfaces[j].aperture for j in uses if system.surfaces[j].aperture is not None]
    if not aps:
        return Aperture("circular", radius=float(default_radius))
    if len(aps) == 1:
        return aps[0]
    if all(a.kind == "circular" for a in aps):
        # Smallest circle centred on the line of the two extreme circles enclosing all.
        c = np.array([a.decenter for a in aps])
        r = np.array([a.radius for a in aps])
        lo = (c - r[:, None]).min(axis=0)
        hi = (c + r[:, None]).max(axis=0)
        centre = 0.5 * (lo + hi)
        rad = float(np.max(np.hypot(*(c - centre).T) + r))
        return Aperture("circular", radius=rad, decenter=(float(centre[0]), float(centre[1])))
    lo = np.min([np.subtract(a.decenter, _half(a)) for a in aps], axis=0)
    hi = np.max([np.add(a.decenter, _half(a)) for a in aps], axis=0)
    return Aperture("rectangular", half_width=tuple(0.5 * (hi - lo)), decenter=tuple(0.5 * (hi + lo)))


def _half(a: Aperture) -> tuple[float, float]:
    return (a.radius, a.radius) if a.kind == "circular" else a.half_width


def default_extent(system: System) -> float:
    """Radius given to surfaces without an aperture: twice the largest aperture
    reach of the system (lenslet arrays count with their half-diagonal), ≥ 10 mm."""
    reach = [s.aperture.extent() for s in system.surfaces if s.aperture is not None and s.array is None]
    for a in system.arrays.values():
        reach.append(math.hypot(abs(a.center[0]) + 0.5 * a.m * a.pitch[0], abs(a.center[1]) + 0.5 * a.n * a.pitch[1]))
    return max(10.0, 2.0 * max(reach, default=0.0))


def _region_grid(region: Aperture, segments: int):
    """Local (x, y), faces, loop and loop angles of a tessellated region."""
    dx, dy = region.decenter
    if region.kind == "circular":
        uv, faces, loop, ang = _unit_disk(segments)
        xy = uv * region.radius
    else:
        hx, hy = region.half_width
        h = max(hx, hy)
        nx = max(1, int(round(segments * hx / h)))
        ny = max(1, int(round(segments * hy / h)))
        uv, faces, loop, _ = _unit_rect(nx, ny)
        xy = uv * np.array([hx, hy])
        ang = np.arctan2(xy[loop, 1], xy[loop, 0])
    return xy + np.array([dx, dy]), faces, loop, ang


# --------------------------------------------------------- tessellation
def tessellate_surface(model: SurfaceModel, i: int, segments: int = DEFAULT_SEGMENTS,
                       region: Aperture | None = None, name: str | None = None,
                       role: str | None = None) -> Mesh:
    """Mesh of surface ``i`` over its clear aperture (or ``region``).

    Vertices are on the analytic surface, normals analytic (+z local), uv =
    local (x, y). Paraxial surfaces are their plane.
    """
    system = model.system
    s = system.surfaces[i]
    if region is None:
        region = clear_region(system, model.owner(i), default_extent(system))
    xy, faces, loop, ang = _region_grid(region, segments)
    z, n = model.sag(i, xy[:, 0], xy[:, 1])
    V = model.to_global(i, np.column_stack([xy, z]))
    N = model.dir_to_global(i, n)
    faces = _orient(faces, V, N[faces].sum(axis=1))
    return Mesh(name or s.name, V, faces, N, xy.copy(), role or ("paraxial" if s.interaction == "paraxial" else "face"),
                i, loop, ang)


def band(a: Mesh, b: Mesh, name: str, centre: np.ndarray | None = None, role: str = "rim") -> Mesh:
    """Rim band joining the boundary loops of faces ``a`` and ``b`` (flat shaded,
    wound outward from ``centre``, default: the centroid of both faces)."""
    va, vb = a.vertices[a.loop], b.vertices[b.loop]
    V = np.concatenate([va, vb])
    la, lb = len(va), len(vb)
    faces = _zipper(np.arange(la), a.loop_angle, la + np.arange(lb), b.loop_angle)
    if centre is None:
        centre = 0.5 * (a.vertices.mean(axis=0) + b.vertices.mean(axis=0))
    faces = _outward(_drop_degenerate(faces, V), V, centre)
    return Mesh(name, V, faces, None, None, role)


def lens_solid(model: SurfaceModel, surfaces: list[int], segments: int = DEFAULT_SEGMENTS,
               name: str | None = None) -> Solid:
    """A lens element (or cemented group): its faces plus a rim band between
    each pair of consecutive faces; one closed piece per glass."""
    sysf = model.system.surfaces
    name = name or f"{sysf[surfaces[0]].name}_{sysf[surfaces[-1]].name}"
    faces = [tessellate_surface(model, i, segments) for i in surfaces]
    rims = [band(faces[k], faces[k + 1], f"{faces[k].name}_{faces[k + 1].name}_rim")
            for k in range(len(faces) - 1)]
    nf = len(faces)
    return Solid(name, faces + rims, [[k, k + 1, nf + k] for k in range(nf - 1)])


# --------------------------------------------------------- lenslet arrays
def _lattice_z(model: SurfaceModel, i: int, array: str, S: int):
    """Local lattice (X (M,N,S+1,S+1), Y, Z, normals) of array member ``i``.

    Lenslet (m, n) is sampled on its cell; vertex (j, k) of it sits on the
    array-wide lattice column m·S + k, row n·S + j, so neighbouring lenslets
    share seam coordinates exactly. Where two lenslets' sags agree on a seam
    to rounding (symmetric lenslets) the seam vertex takes one value, so the
    faces meet without a crack; elsewhere a step wall is added.
    """
    a = model.system.arrays[array]
    xm, yn, (px, py) = model.lenslet_centres(array)
    cx, cy = model.value(f"{array}.center_x"), model.value(f"{array}.center_y")
    M, N = a.m, a.n
    gx = cx + (np.arange(M * S + 1) / S - 0.5 * M) * px
    gy = cy + (np.arange(N * S + 1) / S - 0.5 * N) * py
    ix = np.arange(M)[:, None] * S + np.arange(S + 1)[None, :]  # (M, S+1)
    iy = np.arange(N)[:, None] * S + np.arange(S + 1)[None, :]  # (N, S+1)
    X = np.broadcast_to(gx[ix][:, None, None, :], (M, N, S + 1, S + 1))
    Y = np.broadcast_to(gy[iy][None, :, :, None], (M, N, S + 1, S + 1))
    U = X - xm[:, None, None, None]
    Vv = Y - yn[None, :, None, None]
    Z, Nrm = model.sag(i, U, Vv)
    scale = 1e-12 * max(px, py)
    # Weld seams: x seams (column S of m == column 0 of m+1), then y seams.
    if M > 1:
        close = np.abs(Z[1:, :, :, 0] - Z[:-1, :, :, S]) <= scale
        Z[1:, :, :, 0] = np.where(close, Z[:-1, :, :, S], Z[1:, :, :, 0])
    if N > 1:
        close = np.abs(Z[:, 1:, 0, :] - Z[:, :-1, S, :]) <= scale
        Z[:, 1:, 0, :] = np.where(close, Z[:, :-1, S, :], Z[:, 1:, 0, :])
    return np.array(X), np.array(Y), Z, Nrm


def lenslet_faces(model: SurfaceModel, i: int, array: str, S: int, name: str | None = None) -> Mesh:
    """All lenslets of array member ``i`` as one mesh (per-lenslet analytic normals)."""
    X, Y, Z, Nl = _lattice_z(model, i, array, S)
    M, N = X.shape[:2]
    P = model.to_global(i, np.stack([X, Y, Z], axis=-1)).reshape(-1, 3)
    Ng = model.dir_to_global(i, Nl).reshape(-1, 3)
    per = (S + 1) ** 2
    base = (np.arange(M * N) * per)[:, None, None]
    faces = (base + _grid_faces(S, S)[None]).reshape(-1, 3)
    faces = _orient(faces, P, Ng[faces].sum(axis=1))
    uv = np.stack([X, Y], axis=-1).reshape(-1, 2)
    return Mesh(name or model.system.surfaces[i].name, P, faces, Ng, uv, "face", i)


def _lattice_index(M, N, S):
    """Vertex index of lenslet (m, n), local (row j, column k) in a lenslet_faces mesh."""
    per = (S + 1) ** 2

    def idx(m, n, j, k):
        return ((np.asarray(m) * N + np.asarray(n)) * per + np.asarray(j) * (S + 1) + np.asarray(k))

    return idx


def _seam_walls(face: Mesh, M, N, S) -> np.ndarray:
    """Step walls between neighbouring lenslets whose seam vertices differ."""
    idx = _lattice_index(M, N, S)
    quads = []
    if M > 1:
        m, n, j = np.meshgrid(np.arange(M - 1), np.arange(N), np.arange(S), indexing="ij")
        quads.append(np.stack([idx(m, n, j, S), idx(m, n, j + 1, S), idx(m + 1, n, j + 1, 0), idx(m + 1, n, j, 0)],
                              axis=-1).reshape(-1, 4))
    if N > 1:
        m, n, k = np.meshgrid(np.arange(M), np.arange(N - 1), np.arange(S), indexing="ij")
        quads.append(np.stack([idx(m, n, S, k), idx(m, n, S, k + 1), idx(m, n + 1, 0, k + 1), idx(m, n + 1, 0, k)],
                              axis=-1).reshape(-1, 4))
    if not quads:
        return np.zeros((0, 3), np.int64)
    q = np.concatenate(quads)
    tri = np.concatenate([q[:, [0, 1, 2]], q[:, [0, 2, 3]]])
    return _drop_degenerate(tri, face.vertices)


def _perimeter(M, N, S) -> np.ndarray:
    """The outer boundary of a lenslet_faces mesh as a closed loop (seam
    duplicates included, so a stepped seam is walked across)."""
    idx = _lattice_index(M, N, S)
    ks = np.arange(S + 1)
    bottom = idx(np.repeat(np.arange(M), S + 1), 0, 0, np.tile(ks, M))
    right = idx(M - 1, np.repeat(np.arange(N), S + 1), np.tile(ks, N), S)
    top = idx(np.repeat(np.arange(M), S + 1), N - 1, S, np.tile(ks, M))[::-1]
    left = idx(0, np.repeat(np.arange(N), S + 1), np.tile(ks, N), 0)[::-1]
    return np.concatenate([bottom, right, top, left])


def lenslet_array_solid(model: SurfaceModel, surfaces: list[int], array: str,
                        lenslet_segments: int = DEFAULT_LENSLET_SEGMENTS, name: str | None = None) -> Solid:
    """The refracting members of a lenslet array as one solid.

    Every lenslet's faces on every member surface (per-lenslet analytic
    normals), step walls where neighbouring lenslets' sags differ on a seam,
    and the outer side walls joining consecutive members' perimeters (one
    ``walls`` mesh). One closed piece per glass between consecutive members.
    """
    a = model.system.arrays[array]
    M, N, S = a.m, a.n, int(lenslet_segments)
    faces = [lenslet_faces(model, i, array, S) for i in surfaces]
    centre = np.mean([f.vertices.mean(axis=0) for f in faces], axis=0)
    per_piece_walls = []
    loop = _perimeter(M, N, S)
    for k in range(len(faces) - 1):
        fa, fb = faces[k], faces[k + 1]
        va, vb = fa.vertices[loop], fb.vertices[loop]
        L = len(loop)
        V = np.concatenate([va, vb])
        i0 = np.arange(L)
        i1 = (i0 + 1) % L
        tri = np.concatenate([np.stack([i0, i1, L + i1], 1), np.stack([i0, L + i1, L + i0], 1)])
        tri = _outward(_drop_degenerate(tri, V), V, centre)
        per_piece_walls.append(Mesh(f"{fa.name}_{fb.name}_walls", V, tri, None, None, "wall"))
    steps = {}  # face position -> index of its step-wall mesh
    meshes = faces + per_piece_walls
    for k, f in enumerate(faces):
        st = _seam_walls(f, M, N, S)
        if len(st):
            steps[k] = len(meshes)
            meshes.append(Mesh(f"{f.name}_steps", f.vertices, _outward(st, f.vertices, centre), None, None, "wall"))
    nf = len(faces)
    pieces = [[k, k + 1, nf + k] + [steps[j] for j in (k, k + 1) if j in steps] for k in range(nf - 1)]
    return Solid(name or array, meshes, pieces)


def paraxial_array(model: SurfaceModel, i: int, array: str, name: str | None = None) -> Mesh:
    """The plane of an ideal-lens array: one rectangle per lenslet (cell ∩ aperture)."""
    s = model.system.surfaces[i]
    xm, yn, (px, py) = model.lenslet_centres(array)
    hx, hy, dx, dy = 0.5 * px, 0.5 * py, 0.0, 0.0
    if s.aperture is not None:
        ax, ay = _half(s.aperture)
        ddx, ddy = s.aperture.decenter
        lo = np.maximum([-hx, -hy], [ddx - ax, ddy - ay])
        hi = np.minimum([hx, hy], [ddx + ax, ddy + ay])
        hx, hy = 0.5 * (hi - lo)
        dx, dy = 0.5 * (hi + lo)
    corners = np.array([[-hx, -hy], [hx, -hy], [hx, hy], [-hx, hy]]) + [dx, dy]
    X = xm[:, None, None] + corners[None, None, :, 0]
    Y = yn[None, :, None] + corners[None, None, :, 1]
    X, Y = np.broadcast_arrays(X, Y)
    Z, Nl = model.sag(i, X, Y)  # a plane for a paraxial surface: z = 0, n = +z
    P = model.to_global(i, np.stack([X, Y, Z], axis=-1)).reshape(-1, 3)
    Ng = model.dir_to_global(i, Nl).reshape(-1, 3)
    base = (np.arange(X.shape[0] * X.shape[1]) * 4)[:, None, None]
    faces = (base + np.array([[0, 1, 2], [0, 2, 3]])[None]).reshape(-1, 3)
    faces = _orient(faces, P, Ng[faces].sum(axis=1))
    return Mesh(name or s.name, P, faces, Ng, np.stack([X, Y], -1).reshape(-1, 2), "paraxial", i)


#: Thinnest mask of an aperture array, as a fraction of the cell's area (1e-6: walls of 0.25 nm
#: at 1 mm pitch).
MASK_MIN_WALL = 1e-6


def aperture_mask(model: SurfaceModel, i: int, array: str, holes: int = 8, name: str | None = None) -> Mesh:
    """An absorbing mask on array member ``i``: every cell minus its aperture
    (a rectangular hole, or a polygon of ``4·holes`` sides for a circle), on
    the member's surface. Empty when the aperture fills the cells."""
    s = model.system.surfaces[i]
    xm, yn, (px, py) = model.lenslet_centres(array)
    ap = s.aperture
    q = max(1, int(holes))
    # Outer loop: the cell border with q points per side; inner: the hole.
    t = np.arange(q) / q
    hx, hy = 0.5 * px, 0.5 * py
    outer = np.concatenate([
        np.stack([-hx + 2 * hx * t, np.full(q, -hy)], 1), np.stack([np.full(q, hx), -hy + 2 * hy * t], 1),
        np.stack([hx - 2 * hx * t, np.full(q, hy)], 1), np.stack([np.full(q, -hx), hy - 2 * hy * t], 1)])
    if ap.kind == "circular":
        th = _TWO_PI * np.arange(4 * q) / (4 * q) - 0.75 * math.pi
        inner = ap.radius * np.stack([np.cos(th), np.sin(th)], 1)
    else:
        ax, ay = ap.half_width
        inner = np.concatenate([
            np.stack([-ax + 2 * ax * t, np.full(q, -ay)], 1), np.stack([np.full(q, ax), -ay + 2 * ay * t], 1),
            np.stack([ax - 2 * ax * t, np.full(q, ay)], 1), np.stack([np.full(q, -ax), ay - 2 * ay * t], 1)])
    inner = inner + np.array(ap.decenter)
    inner = np.clip(inner, [-hx, -hy], [hx, hy])
    # An opening that fills its cell but for walls thinner than MASK_MIN_WALL leaves no mask:
    # it stays empty when the pitch moves by a rounding step or a derivative's step.
    x, y = inner[:, 0], inner[:, 1]
    area = 0.5 * abs(float(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1))))
    if area >= 4.0 * hx * hy * (1.0 - MASK_MIN_WALL):
        empty = np.zeros((0, 3))
        return Mesh(name or s.name, empty, np.zeros((0, 3), np.int64), empty.copy(), np.zeros((0, 2)), "mask", i)
    cell = np.concatenate([inner, outer])
    ni = len(inner)
    ca = np.arctan2(cell[:, 1] - ap.decenter[1], cell[:, 0] - ap.decenter[0])
    tri = _zipper(np.arange(ni), ca[:ni], ni + np.arange(len(outer)), ca[ni:])
    X = xm[:, None, None] + cell[None, None, :, 0]
    Y = yn[None, :, None] + cell[None, None, :, 1]
    X, Y = np.broadcast_arrays(X, Y)
    Z, Nl = model.sag(i, X, Y)
    P = model.to_global(i, np.stack([X, Y, Z], -1)).reshape(-1, 3)
    Ng = model.dir_to_global(i, Nl).reshape(-1, 3)
    base = (np.arange(X.shape[0] * X.shape[1]) * len(cell))[:, None, None]
    faces = (base + tri[None]).reshape(-1, 3)
    faces = _drop_degenerate(faces, P)
    faces = _orient(faces, P, Ng[faces].sum(axis=1))
    return Mesh(name or s.name, P, faces, Ng, np.stack([X, Y], -1).reshape(-1, 2), "mask", i)


def mount(model: SurfaceModel, i: int, region: Aperture, array: str | None = None, points: int = 256,
          name: str | None = None) -> Mesh:
    """An absorbing mount around surface ``i``: a flat ring in its local frame
    from the edge of ``region`` (circle or rectangle, decentred) out to
    max(2·reach, reach + 10 mm), at the sag of the edge (so it meets the rim).

    The tracer vignettes a ray outside a clear aperture (or outside a lenslet
    array); in a scene of meshes the lens barrel or the array's holder does.
    The inner loop passes through the rectangle's corners exactly, so the ring
    never covers the clear aperture. For an array the sag is taken on the
    edge lenslets (lenslet-relative coordinates)."""
    dx, dy = region.decenter
    if region.kind == "circular":
        th = _TWO_PI * np.arange(points) / points
        ix, iy = region.radius * np.cos(th), region.radius * np.sin(th)
        reach = region.radius
    else:
        a, b = region.half_width
        corners = np.arctan2([b, b, -b, -b], [a, -a, -a, a]) % _TWO_PI
        th = np.unique(np.concatenate([_TWO_PI * np.arange(points) / points, corners]))
        c, sn = np.cos(th), np.sin(th)
        t = np.minimum(a / np.maximum(np.abs(c), 1e-300), b / np.maximum(np.abs(sn), 1e-300))
        ix, iy = t * c, t * sn
        reach = math.hypot(a, b)
    ix, iy = ix + dx, iy + dy
    R_out = max(2.0 * reach, reach + 10.0)
    ox, oy = dx + R_out * np.cos(th), dy + R_out * np.sin(th)
    if array is None:
        z, _ = model.sag(i, ix, iy)
    else:
        xm, yn, (px, py) = model.lenslet_centres(array)
        # the edge point relative to its own (nearest edge) lenslet
        mx = xm[np.clip(np.searchsorted(xm, ix), 0, len(xm) - 1)]
        ny = yn[np.clip(np.searchsorted(yn, iy), 0, len(yn) - 1)]
        lx = np.clip(ix - mx, -0.5 * px, 0.5 * px)
        ly = np.clip(iy - ny, -0.5 * py, 0.5 * py)
        z, _ = model.sag(i, lx, ly)
    z = np.where(np.isfinite(z), z, 0.0)
    n = len(th)
    local = np.concatenate([np.stack([ix, iy, z], 1), np.stack([ox, oy, z], 1)])
    P = model.to_global(i, local)
    k = np.arange(n)
    k1 = (k + 1) % n
    faces = np.concatenate([np.stack([k, k1, n + k1], 1), np.stack([k, n + k1, n + k], 1)]).astype(np.int64)
    faces = _drop_degenerate(faces, P)
    return Mesh(name or f"{model.system.surfaces[i].name}_mount", P, faces, None,
                np.concatenate([np.stack([ix, iy], 1), np.stack([ox, oy], 1)]), "mount", i)


# ---------------------------------------------------------------- prisms
def prism_solid(model: SurfaceModel, surfaces: list[int], segments: int = DEFAULT_PRISM_SEGMENTS,
                name: str | None = None, footprints: dict | None = None, margin: float = 0.1) -> Solid:
    """A freeform prism: its physical faces (a ``same_as`` face once, over the
    union of its uses' apertures) closed by bevels and two side caps.

    Each face is tessellated on the rectangle bounding its apertures, with the
    same number of columns along the common extrusion axis (the mean local x
    axis of the faces, e.g. the normal of a plane of symmetry). Faces are
    ordered around that axis; each face's two edges across the axis are
    joined to its neighbours' by ruled bevels, and the two ends are closed by
    fans (caps). The result is closed (watertight by construction); it is a
    faithful prism only where neighbouring faces' rectangles end near where
    the real faces would meet.

    ``footprints`` ({surface index: (lo (2,), hi (2,)) local x, y}) narrows
    each face across the axis to the region rays use (plus ``margin`` of its
    width on each side), inside the aperture: oversized apertures would
    otherwise make faces cross each other and bevels cut the beam.
    """
    system = model.system
    phys = []
    for i in surfaces:
        o = model.owner(i)
        if o not in phys and system.surfaces[o].interaction in ("refract", "reflect", "tir"):
            phys.append(o)
    name = name or f"{system.surfaces[surfaces[0]].name}_{system.surfaces[surfaces[-1]].name}"
    axes = np.array([model.frames[o][0][:, 0] for o in phys])
    ref = axes[0]
    signs = np.where(axes @ ref < 0, -1.0, 1.0)
    ext = (axes * signs[:, None]).sum(axis=0)
    ext /= np.linalg.norm(ext)
    regions = []
    for o in phys:
        reg = clear_region(system, o, default_extent(system))
        c, hw = np.array(reg.decenter, dtype=float), np.array(_half(reg), dtype=float)
        if footprints is not None and o in footprints:
            flo, fhi = (np.asarray(v, dtype=float) for v in footprints[o])
            pad = margin * (fhi[1] - flo[1]) + 1e-3 * hw[1]
            ylo, yhi = max(c[1] - hw[1], flo[1] - pad), min(c[1] + hw[1], fhi[1] + pad)
            if yhi > ylo:
                c[1], hw[1] = 0.5 * (ylo + yhi), 0.5 * (yhi - ylo)
        regions.append((c, hw))
    hmax = max(max(h) for _, h in regions)
    nx = max(2, int(round(2 * segments * max(h[0] for _, h in regions) / hmax)))
    faces = []
    for o, (c, h), sg in zip(phys, regions, signs):
        ny = max(2, int(round(2 * segments * h[1] / hmax)))
        uv, tri, _, _ = _unit_rect(nx, ny)
        xy = uv * h + c
        if sg < 0:  # run columns along +ext
            xy[:, 0] = (-uv[:, 0]) * h[0] + c[0]
        z, n = model.sag(o, xy[:, 0], xy[:, 1])
        V = model.to_global(o, np.column_stack([xy, z]))
        Nn = model.dir_to_global(o, n)
        tri = _orient(tri, V, Nn[tri].sum(axis=1))
        m = Mesh(system.surfaces[o].name, V, tri, Nn, xy.copy(), "face", o)
        m.grid = (nx, ny)  # type: ignore[attr-defined]
        faces.append(m)
    centre = np.mean([f.vertices.mean(axis=0) for f in faces], axis=0)
    # Order faces around the extrusion axis.
    e1 = np.cross(ext, [1.0, 0.0, 0.0] if abs(ext[0]) < 0.9 else [0.0, 1.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(ext, e1)
    fc = np.array([f.vertices.mean(axis=0) - centre for f in faces])
    order = np.argsort(np.arctan2(fc @ e2, fc @ e1))
    faces = [faces[k] for k in order]
    nfc = len(faces)

    def rows(f):
        nx_, ny_ = f.grid
        idx = np.arange((nx_ + 1) * (ny_ + 1)).reshape(ny_ + 1, nx_ + 1)
        return idx

    # Which across-axis edge (row 0 / row ny) of each face meets the next
    # face: the assignment with the shortest bevels over the whole cycle.
    import itertools

    ends = [(f.vertices[rows(f)[0]].mean(axis=0), f.vertices[rows(f)[-1]].mean(axis=0)) for f in faces]
    best, choice = np.inf, None
    for bits in itertools.product((0, 1), repeat=nfc):
        cost = sum(np.linalg.norm(ends[k][bits[k]] - ends[(k + 1) % nfc][1 - bits[(k + 1) % nfc]])
                   for k in range(nfc))
        if cost < best:
            best, choice = cost, bits
    edge_next, edge_prev = [], []
    for k, f in enumerate(faces):
        idx = rows(f)
        en, ep = (idx[0], idx[-1]) if choice[k] == 0 else (idx[-1], idx[0])
        edge_next.append(en)
        edge_prev.append(ep)
    walls_v, walls_f, off = [], [], 0
    for k, f in enumerate(faces):
        g = faces[(k + 1) % nfc]
        va, vb = f.vertices[edge_next[k]], g.vertices[edge_prev[(k + 1) % nfc]]
        L = len(va)
        i0 = np.arange(L - 1)
        tri = np.concatenate([np.stack([i0, i0 + 1, L + i0 + 1], 1), np.stack([i0, L + i0 + 1, L + i0], 1)])
        V = np.concatenate([va, vb])
        walls_v.append(V)
        walls_f.append(_drop_degenerate(tri, V) + off)
        off += len(V)
    # Caps: walk each end around the faces (prev edge → next edge along the end column).
    for col in (0, -1):
        loop = []
        for k, f in enumerate(faces):
            idx = rows(f)
            column = idx[:, col]
            start_prev = edge_prev[k][col]
            if column[0] != start_prev:
                column = column[::-1]
            loop.append(f.vertices[column])
        loop = np.concatenate(loop)
        c = loop.mean(axis=0)
        V = np.concatenate([loop, c[None]])
        L = len(loop)
        i0 = np.arange(L)
        tri = np.stack([np.full(L, L), i0, (i0 + 1) % L], 1)
        walls_v.append(V)
        walls_f.append(_drop_degenerate(tri, V) + off)
        off += len(V)
    V = np.concatenate(walls_v)
    W = _outward(np.concatenate(walls_f), V, centre)
    walls = Mesh(f"{name}_walls", V, W, None, None, "wall")
    for f in faces:
        f.__dict__.pop("grid", None)
    return Solid(name, faces + [walls], [list(range(nfc + 1))])
