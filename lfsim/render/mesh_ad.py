"""Differentiable optics meshes: vertices and analytic normals in Dr.Jit from the design vector.

:mod:`lfsim.render.meshes` tessellates a design in numpy at one parameter
vector. This module keeps that tessellation's *topology* (the triangles, and
which surface and local (x, y) every vertex samples) and re-evaluates every
vertex and vertex normal in Dr.Jit from a design vector ``P`` with gradients
attached, by the same functions the tracer intersects:

* optical faces: ``z, ∂z/∂x, ∂z/∂y = lfsim.optics.surfaces.sag(x, y, shape(P))``,
  normal ``lfsim.optics.surfaces.normal``, and the global frame
  ``R_i(P) x + o_i(P)`` of :meth:`lfsim.optics.tracer.SequentialTracer.frames`
  (tilts, decenters, z-shifts, global positions). Lenslet faces sample the
  array lattice, whose local (x, y) are affine in the array's pitch and
  centre, so ``pitch_x/y`` and ``center_x/y`` are differentiable too; the
  seam welding of :func:`lfsim.render.meshes._lattice_z` is kept (a welded
  seam vertex takes its neighbour's value);
* rims, side walls, seam steps, prism bevels: their vertices are copies of
  face vertices (bit-identical in the numpy meshes) and follow them; mounts
  (and any other vertex that is no copy) move rigidly with their surface's
  frame; the rest (prism cap centres) stay fixed;
* BSDF parameters: ``int_ior`` / ``ext_ior`` of every ``lfsim_interface``
  from the index parameters of the media on either side, ``power`` / ``ior``
  of every ``lfsim_thinlens`` (summed over thin lenses merged in contact).

Nothing here re-implements surface math or a linearization: at the nominal
point the Dr.Jit vertices equal the numpy tessellation to rounding, and their
derivatives are exact derivatives of the tessellated surfaces
(``tests/test_mesh_ad.py`` checks both).

The design vector is the design's parameter table
(:mod:`lfsim.optics.vector`), whose ``object.distance`` is the display gap g
(the display is the plane z = −g).
"""

from __future__ import annotations

import weakref
from dataclasses import dataclass

import drjit as dr
import numpy as np

from .. import backend
from ..optics.surfaces import Shape, normal, sag
from ..optics.tracer import SequentialTracer
from . import bsdfs as _bsdfs
from . import meshes as _m
from . import optics_scene as _os


@dataclass
class _FaceRule:
    """How the vertices of one optical-face mesh follow ``P``."""

    surface: int
    x: object  # local x: T.Float (constant), or coefficients (a, b) for the lattice
    y: object
    lattice: tuple | None = None  # (array name, ax, bx, ay, by): X = cx + ax·px, U = bx·px, ...
    weld: tuple | None = None  # (src_x, src_y) UInt32 gathers of z (seam welding)


@dataclass
class _CopyRule:
    """Vertices of a non-face mesh: copies of face vertices, rigid, or constant."""

    kind: np.ndarray  # 0 copy, 1 rigid in the frame of ``surface``, 2 constant
    src: np.ndarray  # copy: index into the concatenated face vertices
    local: np.ndarray  # rigid: local coordinates; constant: global
    surface: int | None
    #: Rigid vertices that also follow design numbers linearly in their frame (an aperture
    #: array's mask follows its array's pitch and centre): ``[(index, P0, dlocal (V, 3))]``.
    linear: list | None = None
    normals: np.ndarray | None = None  # local unit normals (rigid), or None


class MeshGeometry:
    """The optics meshes of a design as differentiable functions of the design vector.

    Parameters
    ----------
    design : lfsim.Design
    values : array_like
        Parameter vector (``design.parameter_names()`` order, the display gap
        ``object.distance`` included) of the nominal state: it fixes the
        topology, the sides and which seams weld.
    wavelength_nm : float, optional
    tessellation : dict, optional
        ``segments``, ``lenslet_segments``, ``prism_segments``
        (:func:`lfsim.render.meshes.tessellation`).
    mounts : bool
        Absorbing mounts around lens faces and arrays (as ``optics_shapes``).
    fresnel : bool
        Interfaces refract with weight 1 − F instead of 1.
    tracer : SequentialTracer, optional
        The design's float64 forward tracer, when the caller has one already.
    """

    def __init__(self, design, values, wavelength_nm=None, tessellation=None, mounts: bool = True,
                 fresnel: bool = False, tracer=None):
        system = design.system
        self.system = system
        self.tracer = tracer if tracer is not None else SequentialTracer(system, "float64")
        self.T = self.tracer.T
        self.names = self.tracer.names
        self.index = self.tracer.index
        values = np.asarray(values, dtype=np.float64).ravel()
        self.values_fwd = values
        tess = dict(tessellation or {})
        self.parts = _os.optics_parts(design, values, wavelength_nm, mounts=mounts, **tess)
        self.model = model = _m.SurfaceModel(design, values, wavelength_nm)
        self.sides = _os.surface_sides(model)
        self.fresnel = bool(fresnel)
        if fresnel:
            for part in self.parts:
                if part.bsdf.get("type") == _bsdfs.INTERFACE:
                    part.bsdf["fresnel"] = True
        self.rules: list = []
        offsets, off = {}, 0
        for k, part in enumerate(self.parts):
            m = part.mesh
            if m.role in ("face", "paraxial") and m.surface is not None and m.normals is not None:
                self.rules.append(self._face_rule(m))
                offsets[k] = off
                off += len(m.vertices)
            else:
                self.rules.append(None)
        self._face_offsets = offsets
        lookup = {}
        for k, o in offsets.items():
            v = np.ascontiguousarray(self.parts[k].mesh.vertices) + 0.0
            for j, key in enumerate(map(bytes, v.view(np.dtype((np.void, 24))).ravel())):
                lookup.setdefault(key, o + j)
        for k, part in enumerate(self.parts):
            if self.rules[k] is None:
                self.rules[k] = self._copy_rule(part.mesh, lookup)
                if part.mesh.role == "mask":
                    self._mask_rule(self.rules[k], part.mesh, design, wavelength_nm)
        self._bsdf_src = [self._bsdf_sources(part) for part in self.parts]

    # ----------------------------------------------------------- set-up
    def _face_rule(self, m: _m.Mesh) -> _FaceRule:
        T, system = self.T, self.system
        i = m.surface
        s = system.surfaces[i]
        uv = np.asarray(m.uv, dtype=np.float64)
        if s.array is not None and m.role == "face":
            a = system.arrays[s.array]
            M, N = a.m, a.n
            per = len(uv) // (M * N)
            S = int(round(np.sqrt(per))) - 1
            v = np.arange(len(uv))
            cell, loc = v // per, v % per
            mm, nn = cell // N, cell % N
            j, kk = loc // (S + 1), loc % (S + 1)
            ax = (mm * S + kk) / S - 0.5 * M
            ay = (nn * S + j) / S - 0.5 * N
            bx = ax - (mm - 0.5 * (M - 1))
            by = ay - (nn - 0.5 * (N - 1))
            rule = _FaceRule(i, None, None, (s.array, *(T.Float(c) for c in (ax, bx, ay, by))))
            # Seam welding as _lattice_z: from the raw sags at the nominal point.
            with dr.suspend_grad():
                P0 = self.params_for(self.values_fwd)
                x, y, U, V = self._lattice_xy(rule, P0)
                z = np.asarray(sag(U, V, self._shape(P0, i))[0], dtype=np.float64)
            px, py = (self.values_fwd[self.tracer.index[f"{s.array}.pitch_{c}"]] for c in "xy")
            scale = 1e-12 * max(px, py)
            Z = z.reshape(M, N, S + 1, S + 1)
            idx = np.arange(len(z)).reshape(M, N, S + 1, S + 1)
            src_x = idx.copy()
            src_y = idx.copy()
            if M > 1:
                close = np.abs(Z[1:, :, :, 0] - Z[:-1, :, :, S]) <= scale
                src_x[1:, :, :, 0] = np.where(close, idx[:-1, :, :, S], idx[1:, :, :, 0])
            if N > 1:
                Zx = Z.ravel()[src_x.ravel()].reshape(Z.shape)
                close = np.abs(Zx[:, 1:, 0, :] - Zx[:, :-1, S, :]) <= scale
                src_y[:, 1:, 0, :] = np.where(close, idx[:, :-1, S, :], idx[:, 1:, 0, :])
            rule.weld = (T.UInt32(src_x.ravel().astype(np.uint32)), T.UInt32(src_y.ravel().astype(np.uint32)))
            return rule
        return _FaceRule(i, T.Float(uv[:, 0]), T.Float(uv[:, 1]))

    def _copy_rule(self, m: _m.Mesh, lookup: dict) -> _CopyRule:
        v = np.ascontiguousarray(m.vertices, dtype=np.float64) + 0.0
        keys = list(map(bytes, v.view(np.dtype((np.void, 24))).ravel()))
        src = np.array([lookup.get(k, -1) for k in keys], dtype=np.int64)
        kind = np.where(src >= 0, 0, 1 if m.surface is not None else 2)
        local = v.copy()
        if m.surface is not None:
            local = self.model.to_local(m.surface, v)
        return _CopyRule(kind, np.maximum(src, 0), local, m.surface)

    def _mask_rule(self, rule: _CopyRule, m: _m.Mesh, design, wavelength_nm) -> None:
        """An aperture array's mask: its vertices in the member's frame are affine in the
        array's pitch and centre (cell corners and clipped hole edges move with them); the
        slopes come from central differences of :func:`lfsim.render.meshes.aperture_mask`
        (exact for an affine map, up to rounding). Normals rotate with the frame."""
        i = m.surface
        array = self.system.surfaces[i].array
        if array is None or not np.all(rule.kind == 1):
            return
        linear = []
        for name in (f"{array}.{q}" for q in ("pitch_x", "pitch_y", "center_x", "center_y")):
            j = self.index[name]
            h = 1e-6 * max(1.0, abs(float(self.values_fwd[j])))
            loc = []
            for sgn in (-1.0, 1.0):
                v = self.values_fwd.copy()
                v[j] += sgn * h
                model = _m.SurfaceModel(design, v, wavelength_nm)
                mm = _m.aperture_mask(model, i, array)
                if mm.vertices.shape != m.vertices.shape:
                    return  # the mask's layout changes with this number: left rigid
                loc.append(model.to_local(i, mm.vertices))
            linear.append((j, float(self.values_fwd[j]), (loc[1] - loc[0]) / (2.0 * h)))
        rule.linear = linear
        if m.normals is not None:
            R = self.model.frames[i][0]
            rule.normals = np.asarray(m.normals, dtype=np.float64) @ R  # global -> local

    def _bsdf_sources(self, part) -> dict:
        """{bsdf parameter: [design-vector indices summed]} of one part."""
        b, m = part.bsdf, part.mesh
        t = b.get("type")
        media = self.tracer.vector.media
        if t == _bsdfs.INTERFACE:
            i = m.surface
            s = self.system.surfaces[i]
            n_in = media[i]
            n_out = f"{s.name}.index" if s.interaction in ("refract", "tir") else n_in
            a, c = (n_in, n_out) if self.sides[i] >= 0 else (n_out, n_in)
            return {"int_ior": [self.index[a]], "ext_ior": [self.index[c]]}
        if t == _bsdfs.THINLENS:
            i = m.surface
            names = [self.system.surfaces[i].name]
            # Thin lenses merged in contact: the mesh name lists them.
            rest = m.name[len(names[0]):].strip("_")
            by_name = {s.name: s for s in self.system.surfaces}
            while rest:
                for nm in sorted(by_name, key=len, reverse=True):
                    if rest.startswith(nm) and by_name[nm].interaction == "paraxial":
                        names.append(nm)
                        rest = rest[len(nm):].lstrip("_")
                        break
                else:
                    break
            return {"power": [self.index[f"{nm}.power"] for nm in names], "ior": [self.index[media[i]]]}
        return {}

    # -------------------------------------------------------- evaluation
    def params_for(self, values):
        """The design vector (``T.Float``) of numpy ``values``."""
        v = np.asarray(values, dtype=np.float64).ravel()
        if v.size != len(self.names):
            raise ValueError(f"expected {len(self.names)} design values, got {v.size}")
        return backend.from_numpy(self.T.Float, v)

    def _g(self, P, name):
        return dr.gather(self.T.Float, P, self.T.UInt32(self.index[name]))

    def _shape(self, P, i: int) -> Shape:
        return self.tracer.vector.shape(i, lambda name: self._g(P, name))

    def _lattice_xy(self, rule: _FaceRule, P):
        arr, ax, bx, ay, by = rule.lattice
        px, py = self._g(P, f"{arr}.pitch_x"), self._g(P, f"{arr}.pitch_y")
        cx, cy = self._g(P, f"{arr}.center_x"), self._g(P, f"{arr}.center_y")
        return cx + ax * px, cy + ay * py, bx * px, by * py

    def frames(self, P):
        """Forward frames (R, o) of every surface at design vector ``P`` (differentiable)."""
        from .diff_render import forward_frames

        return forward_frames(self.tracer, P)

    def geometry(self, P, frames=None):
        """Per part: (global vertices T.Array3, global unit normals T.Array3 or None)."""
        T = self.T
        Rs, os_ = frames if frames is not None else self.frames(P)
        out: list = [None] * len(self.parts)
        for k, rule in enumerate(self.rules):
            if not isinstance(rule, _FaceRule):
                continue
            i = rule.surface
            if rule.lattice is not None:
                x, y, U, V = self._lattice_xy(rule, P)
            else:
                x, y = rule.x, rule.y
                U, V = x, y
            z, zx, zy, _ = sag(U, V, self._shape(P, i))
            n = normal(zx, zy, T.Array3)
            if rule.weld is not None:
                z = dr.gather(T.Float, dr.gather(T.Float, z, rule.weld[0]), rule.weld[1])
            p = Rs[i] @ T.Array3(x, y, z) + os_[i]
            out[k] = (T.Array3(p), T.Array3(Rs[i] @ n))
        # Copies gather from each source face separately (no dr.concat: forward-mode
        # gradients through a concatenation of the faces came out partly zero).
        starts = sorted(self._face_offsets.items(), key=lambda kv: kv[1])
        for k, rule in enumerate(self.rules):
            if not isinstance(rule, _CopyRule):
                continue
            nv = len(rule.kind)
            if nv == 0:
                out[k] = (dr.zeros(T.Array3, 0), None)
                continue
            loc = T.Array3(*(T.Float(rule.local[:, c]) for c in range(3)))
            for j, p0, slope in rule.linear or ():
                dv = dr.gather(T.Float, P, T.UInt32(j)) - p0
                loc = loc + T.Array3(*(T.Float(slope[:, c]) for c in range(3))) * dv
            p = Rs[rule.surface] @ loc + os_[rule.surface] if rule.surface is not None else loc
            copy = rule.kind == 0
            for f, off in starts:
                n_f = len(self.parts[f].mesh.vertices)
                sel = copy & (rule.src >= off) & (rule.src < off + n_f)
                if not sel.any():
                    continue
                m = T.Bool(sel)
                idx = T.UInt32(np.where(sel, rule.src - off, 0).astype(np.uint32))
                p = dr.select(m, dr.gather(T.Array3, out[f][0], idx, m), p)
            nrm = None
            if rule.normals is not None:
                nrm = T.Array3(Rs[rule.surface] @ T.Array3(*(T.Float(rule.normals[:, c]) for c in range(3))))
            out[k] = (T.Array3(p), nrm)
        return out

    def bsdf_values(self, P) -> list[dict]:
        """Per part: {bsdf parameter: T.Float of width 1} (differentiable)."""
        out = []
        for src in self._bsdf_src:
            d = {}
            for key, idx in src.items():
                v = self._g(P, self.names[idx[0]])
                for j in idx[1:]:
                    v = v + self._g(P, self.names[j])
                d[key] = v
            out.append(d)
        return out

    def numpy_geometry(self, P) -> list[tuple[np.ndarray, np.ndarray | None]]:
        """:meth:`geometry` as numpy (V, 3) arrays (no gradients)."""
        with dr.suspend_grad():
            g = self.geometry(P)
            dr.eval(g)

            def np3(a):
                return np.stack([np.asarray(a[c], dtype=np.float64) for c in range(3)], axis=1)

            return [(np3(v), None if n is None else np3(n)) for v, n in g]


# ------------------------------------------------------------ the scene
#: Every MeshScene alive (see :meth:`MeshScene.release`).
_LIVE_SCENES: weakref.WeakSet = weakref.WeakSet()


def _flat32(v):
    """T.Array3 (float64) → Mitsuba's flat float32 buffer x0 y0 z0 x1 … (differentiable)."""
    from . import mitsuba

    mi = mitsuba()
    return mi.Float(dr.ravel(v))


class MeshScene:
    """A Mitsuba scene of the display and the optics meshes whose geometry and
    BSDF parameters are written from a design vector through ``mi.traverse``.

    The display is a two-triangle mesh at z = −g (``object.distance``) with the
    area emitter and bilinear texture of :meth:`DisplayLayout.emitter_dict`
    (same uv convention as its rectangle). Positions and analytic normals are
    written together in one update (positions alone would make Mitsuba
    recompute area-weighted normals).
    """

    def __init__(self, geom: MeshGeometry, layout, image, mesh_dir=None, max_depth: int | None = None):
        import hashlib

        from . import ad_integrator
        from .optics_scene import _mesh_dir, ply_bytes

        mi = ad_integrator.register()
        _bsdfs.register()
        self.geom, self.layout = geom, layout
        out_dir = _mesh_dir(mesh_dir)
        shapes, self.keys = {}, []

        def ply(mesh):
            blob = ply_bytes(mesh)
            path = out_dir / f"{mesh.name}-{hashlib.sha1(blob).hexdigest()[:16]}.ply"
            if not path.exists():
                tmp = path.with_suffix(f".{id(self)}.tmp")
                tmp.write_bytes(blob)
                tmp.replace(path)
            return str(path)

        self._parts = []  # (part index, shape key, has normals, bsdf keys)
        for k, part in enumerate(geom.parts):
            m = part.mesh
            if len(m.faces) == 0:
                continue
            if m.name in shapes:
                raise ValueError(f"two optics meshes named {m.name!r}")
            shapes[m.name] = {"type": "ply", "filename": ply(m), "face_normals": m.normals is None,
                              "bsdf": part.bsdf}
            self._parts.append((k, m.name, m.normals is not None, list(geom._bsdf_src[k])))
        em = layout.emitter_dict(np.asarray(image, dtype=np.float32))
        w, h = layout.size_mm
        cx, cy = layout.center
        self._display_xy = np.array([[cx - 0.5 * w, cy - 0.5 * h], [cx + 0.5 * w, cy - 0.5 * h],
                                     [cx + 0.5 * w, cy + 0.5 * h], [cx - 0.5 * w, cy + 0.5 * h]])
        disp = _m.Mesh("display", np.column_stack([self._display_xy, np.full(4, layout.z)]),
                       np.array([[0, 1, 2], [0, 2, 3]], np.int64), np.tile([0.0, 0.0, 1.0], (4, 1)),
                       np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]]), "display")
        shapes["display"] = {"type": "ply", "filename": ply(disp), "face_normals": False,
                             "bsdf": em["bsdf"], "emitter": em["emitter"]}
        n_faces = sum(1 for k, *_ in self._parts if isinstance(geom.rules[k], _FaceRule))
        self.max_depth = int(max_depth or 2 * n_faces + 8)
        # optimize=False: Mitsuba would merge meshes that share a BSDF and drop their ids.
        self.scene = mi.load_dict({"type": "scene", **shapes,
                                   "integrator": {"type": "lfsim_specular", "max_depth": self.max_depth}},
                                  optimize=False)
        self.params = mi.traverse(self.scene)
        for k, name, _, _ in self._parts:
            nv = dr.width(self.params[f"{name}.vertex_positions"]) // 3
            if nv != len(geom.parts[k].mesh.vertices):
                raise RuntimeError(f"mesh {name}: Mitsuba loaded {nv} vertices, lfsim wrote "
                                   f"{len(geom.parts[k].mesh.vertices)}")
        self.keys = [key for _, name, has_n, bk in self._parts
                     for key in ([f"{name}.vertex_positions"] + ([f"{name}.vertex_normals"] if has_n else [])
                                 + [f"{name}.bsdf.{b}" for b in bk])] + ["display.vertex_positions",
                                                                          "display.vertex_normals"]
        self._release_keys = list(self.keys)
        self._current = None
        _LIVE_SCENES.add(self)

    def values(self, P, frames=None) -> list:
        """The Mitsuba parameter values (``self.keys`` order) at design vector ``P``
        (mi.Float, attached to ``P`` where it has gradients)."""
        from . import mitsuba

        mi = mitsuba()
        g = self.geom
        T = g.T
        geo = g.geometry(P, frames)
        bs = g.bsdf_values(P)
        out = []
        for k, _, has_n, bk in self._parts:
            V, N = geo[k]
            out.append(_flat32(V))
            if has_n:
                out.append(_flat32(N))
            out += [mi.Float(bs[k][b]) for b in bk]
        z = -dr.gather(T.Float, P, T.UInt32(g.index["object.distance"]))
        zz = dr.gather(T.Float, z, dr.zeros(T.UInt32, 4))
        dv = T.Array3(T.Float(self._display_xy[:, 0]), T.Float(self._display_xy[:, 1]), zz)
        out.append(_flat32(dv))
        out.append(mi.Float(np.tile([0.0, 0.0, 1.0], 4).astype(np.float32)))
        return out

    def set(self, values) -> None:
        """Write parameter values (``self.keys`` order) into the scene (one update)."""
        if values is self._current:
            return
        for other in list(_LIVE_SCENES):
            if other is not self:
                other.release()
        for key, v in zip(self.keys, values):
            self.params[key] = v
        self.params.update()
        self._current = values

    def release(self) -> None:
        """Replace the AD-attached values in the scene by detached copies (same numbers).

        Dr.Jit differentiates a symbolic virtual call (``bsdf.sample``, the
        shapes' intersection) by replaying it, at propagation time, over
        *every* registered instance of the variant, those of other scenes
        included. A parameter that another scene still held attached to an
        earlier AD graph then entered this scene's derivative as an implicit
        input: forward mode failed with "... lies outside of the current
        dr.isolate_grad() scope" as soon as a second scene was differentiated
        in the same process (with or without ``fresnel``). :meth:`set` therefore
        releases every other live scene first: only the scene in use holds
        attached values. (Releasing a scene right after its own trace is wrong:
        the replay then sees detached parameters and the derivative is 0.)
        """
        changed = False
        for key in self._release_keys:
            v = self.params[key]
            if dr.grad_enabled(v):
                self.params[key] = dr.detach(v)
                changed = True
        if changed:
            self.params.update()
        self._current = None


# ------------------------------------------------------------ the renderer
def _analytic_base():
    from .diff_render import AnalyticRenderer

    return AnalyticRenderer


def flat_leaves(arrays: list, R_vw, o_vw) -> list:
    from .diff_render import flat_leaves as f

    return f(arrays, R_vw, o_vw)


class MeshRenderer(_analytic_base()):
    """Retinal images through the optics *meshes*, differentiable in the design vector.

    The same interface as :class:`~lfsim.render.diff_render.AnalyticRenderer`
    (same design vector, eye rays, display image, ``trace`` / ``image`` /
    ``backward``), so :mod:`lfsim.render.gradcheck` checks either. The eye
    rays (the same seeded samples as the analytic path, in the viewing-window
    frame) are moved to the viewing window's frame of ``P`` and followed
    through the scene of :class:`MeshScene` by
    :func:`lfsim.render.ad_integrator.specular_chain` (Mitsuba, float32):

        I_p(θ) = 1/spp Σ_s  Π_k w_k(θ) · E(uv_s(θ))

    Extra parameters: ``tessellation`` (dict of segment counts, default
    :func:`lfsim.render.meshes.tessellation` at 0.25), ``fresnel`` (interfaces
    refract with weight 1 − F), ``mounts``.
    """

    path = "mesh"

    def __init__(self, design, view, content=None, display=None, precision: str = "float64", channels: int = 1,
                 tessellation=None, fresnel: bool = False, mounts: bool = True):
        super().__init__(design, view, content=content, display=display, precision="float64",
                         channels=channels)
        tess = tessellation if tessellation is not None else _m.tessellation(0.25)
        self.tessellation = dict(tess)
        self.geom = MeshGeometry(design, self.model.values(0), self.model.lam, tess, mounts=mounts,
                                 fresnel=fresnel, tracer=self.map.fwd)
        if self.geom.names != self.names:
            raise RuntimeError("mesh geometry and renderer disagree on the design vector")
        img = self.display
        self.mscene = MeshScene(self.geom, self.layout, np.repeat(img[..., :1], 3, -1) if self.channels == 1 else img)
        self._cache = None

    def optics(self, P):
        """(Mitsuba parameter values, R_vw, o_vw) at design vector ``P`` (differentiable)."""
        if self._cache is not None and self._cache[0] is P:
            return self._cache[1]
        frames = self.geom.frames(P)
        Rs, os_ = frames
        out = (self.mscene.values(P, frames), Rs[self.map.vw], os_[self.map.vw])
        self._cache = (P, out)
        return out

    def trace(self, P, k: int = 0, optics=None):
        from . import mitsuba
        from .ad_integrator import specular_chain
        from .diff_render import RayBatch

        mi = mitsuba()
        T = self.T
        values, R_vw, o_vw = optics if optics is not None else self.optics(P)
        self.mscene.set(values)
        o_l, d_l, ok_eye = self._rays[k]
        n = dr.width(o_l)
        zero = dr.opaque(T.UInt32, 0, n)
        R = dr.gather(T.Matrix3, R_vw, zero)
        o = R @ o_l + dr.gather(T.Array3, o_vw, zero)
        d = R @ d_l
        ray = mi.Ray3f(mi.Point3f(mi.Float(o.x), mi.Float(o.y), mi.Float(o.z)),
                       mi.Vector3f(mi.Float(d.x), mi.Float(d.y), mi.Float(d.z)))
        c = specular_chain(self.mscene.scene, ray, mi.Bool(ok_eye), self.mscene.max_depth)
        valid = T.Bool(c.valid) & ok_eye
        value = [dr.select(valid, T.Float(c.L[ch]), 0.0) for ch in range(self.channels)]
        x = dr.select(valid, T.Float(c.p.x), 0.0)
        y = dr.select(valid, T.Float(c.p.y), 0.0)
        dr.eval(value, x, y, valid)
        return RayBatch(x, y, valid, T.UInt32(c.code), value)

    def backward(self, P, objective, wrt=None):
        """Reverse-mode gradient, mixed as :meth:`AnalyticRenderer.backward`: the render is
        differentiated in reverse with respect to the scene parameters and the eye frame
        (detached leaves), and the adjoints are pulled back through the map
        ``P → (vertices, normals, indices, powers, eye frame)`` by one forward pass per
        parameter in ``wrt``."""
        with dr.suspend_grad():
            vals, R_vw, o_vw = self.optics(P)
            leaves = ([dr.detach(v) for v in vals], dr.detach(R_vw), dr.detach(o_vw))
        for v in leaves[0]:
            dr.enable_grad(v)
        dr.enable_grad(leaves[1])
        dr.enable_grad(leaves[2])
        value = objective(leaves)
        dr.backward(value)
        adj = flat_leaves([dr.detach(dr.grad(v)) for v in leaves[0]], dr.detach(dr.grad(leaves[1])),
                           dr.detach(dr.grad(leaves[2])))
        self.mscene._current = None
        self._cache = None
        return float(value[0]), self._pull_back(P, adj, wrt)

    def _leaves(self, P) -> list:
        frames = self.geom.frames(P)
        vals = self.mscene.values(P, frames)
        return flat_leaves(vals, frames[0][self.map.vw], frames[1][self.map.vw])
