"""A design's optics as Mitsuba shapes; XML + PLY export; a specular ray walker.

:func:`optics_shapes` turns everything in a design's optical path except the
display (object) and the eye / image (last surface) into Mitsuba shape dicts,
meshed by :mod:`lfsim.render.meshes` from lfsim's own surfaces:

=====================  ==========================================  =====================
component              shapes (keys)                               BSDF
=====================  ==========================================  =====================
lens / cemented group  one per face (surface name), one rim band   ``lfsim_interface``;
                       per glass (``<a>_<b>_rim``)                 rims absorb
lenslet array          front / back faces of all lenslets          ``lfsim_interface``;
                       (surface names), ``<a>_<b>_walls``,         walls absorb
                       ``<name>_steps`` where seams step
freeform prism         one per physical face (a ``same_as`` face   interface (refract,
                       once), ``<first>_<last>_walls``             tir), mirror (reflect)
paraxial surface       a flat disk / rectangle (surface name)      ``lfsim_thinlens``
paraxial lenslet array one rectangle per lenslet                   ``lfsim_thinlens``
aperture array         absorbing mask with the lenslet holes       absorber
mirror in air          the face                                    two-sided mirror
=====================  ==========================================  =====================

Indices come from the parameter vector (``values``), i.e. from the design's
materials at ``wavelength_nm``; which side of a face is which medium comes
from a reference ray traced by lfsim. Shapes are PLY files (float32, with
analytic vertex normals and the surface-local (x, y) as UVs) written to
``mesh_dir`` (a temporary folder by default), so the same dicts load with
``mi.load_dict`` and serialize with :func:`write_scene_xml`.
"""

from __future__ import annotations

import hashlib
import math
import shutil
import tempfile
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..backend import from_numpy, to_numpy
from ..optics.prescription import Aperture
from . import bsdfs as _bsdfs
from . import meshes as _m

_MESH_DIR: Path | None = None


# ------------------------------------------------------------------ sides
def surface_sides(model: _m.SurfaceModel) -> np.ndarray:
    """Per surface: +1 if light of the design crosses it along its local +z,
    −1 if along −z (from lfsim reference rays near the axis; +1 when none
    reaches it). Fixes which index lies on the side of the mesh normals."""
    import drjit as dr

    system, tr = model.system, model.tracer
    n_s = len(system.surfaces)
    g = np.linspace(-1.0, 1.0, 5)
    gx, gy = [a.ravel() for a in np.meshgrid(g, g)]
    first = system.surfaces[0]
    r0 = 0.05 * (first.aperture.extent() if first.aperture is not None and first.array is None else 1.0)
    if system.array_groups():
        r0 = min(r0, 0.2 * min(min(a.pitch) for a in system.arrays.values()))
    if math.isinf(system.object_distance):
        o = np.column_stack([gx * r0, gy * r0, np.full_like(gx, -1.0)])
        d = np.tile([0.0, 0.0, 1.0], (len(gx), 1))
    else:
        o = np.tile([0.0, 0.0, -system.object_distance], (len(gx), 1))
        d = np.column_stack([gx * r0, gy * r0, np.zeros_like(gx)]) - o
    with dr.suspend_grad():
        out = tr.trace(tr.params(values=model.values), tr.rays(o, d), record=True)
        # One kernel for every surface's directions (read one by one, each would re-trace).
        failed, *dirs = to_numpy(out.failed_at, *(q for _, q in out.path))
    d_in = [d / np.linalg.norm(d, axis=1, keepdims=True)] + dirs[:-1]
    sides = np.ones(n_s)
    for i in range(n_s):
        ok = (failed < 0) | (failed > i)
        if ok.any():
            ez = model.frames[i][0][:, 2]
            sides[i] = 1.0 if np.sum(d_in[i][ok] @ ez) >= 0.0 else -1.0
    return sides


def reference_bundle(design, model: _m.SurfaceModel) -> tuple[np.ndarray, np.ndarray]:
    """Rays that fill the design's light path (global origins, directions).

    With a lenslet array: from a 3×3 grid over each lenslet's elemental image
    on the display (the object plane) to a 3×3 grid over that lenslet on the
    array's first surface. Otherwise: the system's fields (±) through a
    hexapolar pupil (lfsim.optics.sampling).
    """
    system = model.system
    if system.arrays:
        name = next(iter(system.arrays))
        first = system.array_groups()[name][0]
        xm, yn, (px, py) = model.lenslet_centres(name)
        ini = getattr(design, "ini", None)
        ex, ey = (0.5 * px, 0.5 * py)
        if ini is not None:
            ex, ey = 0.5 * ini.pixel_pitch * ini.pixels_per_ei[0], 0.5 * ini.pixel_pitch * ini.pixels_per_ei[1]
        g = np.array([-0.9, 0.0, 0.9])
        u, v = [a.ravel() for a in np.meshgrid(g, g)]
        X, Y = [a.ravel() for a in np.meshgrid(xm, yn)]
        R, o0 = model.frames[first]
        src = np.stack([X[:, None, None] + ex * u[None, :, None] + 0 * u[None, None, :],
                        Y[:, None, None] + ey * v[None, :, None] + 0 * v[None, None, :]], -1)
        dst = np.stack([X[:, None, None] + 0.45 * px * u[None, None, :] + 0 * u[None, :, None],
                        Y[:, None, None] + 0.45 * py * v[None, None, :] + 0 * v[None, :, None]], -1)
        src, dst = src.reshape(-1, 2), dst.reshape(-1, 2)
        zo = -system.object_distance if math.isfinite(system.object_distance) else -1.0
        o = model.to_global(first, np.column_stack([src, np.full(len(src), zo)]))
        t = model.to_global(first, np.column_stack([dst, np.zeros(len(dst))]))
        if not math.isfinite(system.object_distance):
            o = t - model.dir_to_global(first, np.array([0.0, 0.0, 1.0]))[None, :]
        return o, t - o
    from ..optics.sampling import field_rays, pupil_grid

    if not hasattr(design, "first_order"):
        return np.zeros((0, 3)), np.zeros((0, 3))
    fo = design.first_order(model.wavelength_nm)
    os_, ds = [], []
    for f in sorted({float(v) for f0 in system.fields for v in (f0, -f0)}):
        o, d = field_rays(system, fo, f, pupil_grid(4))
        os_.append(o)
        ds.append(d)
    return np.concatenate(os_), np.concatenate(ds)


def footprints(design, model: _m.SurfaceModel) -> dict[int, tuple[np.ndarray, np.ndarray]]:
    """Local (x, y) bounding box of the :func:`reference_bundle` on every
    physical surface ({index: (lo, hi)}; ``same_as`` uses are merged)."""
    import drjit as dr

    o, d = reference_bundle(design, model)
    if len(o) == 0:
        return {}
    tr = model.tracer
    with dr.suspend_grad():
        out = tr.trace(tr.params(values=model.values), tr.rays(o, d), record=True)
        failed, *pts = to_numpy(out.failed_at, *(p for p, _ in out.path))
    boxes: dict[int, tuple[np.ndarray, np.ndarray]] = {}
    for i, s in enumerate(model.system.surfaces):
        ok = (failed < 0) | (failed > i)
        if s.interaction == "break" or not ok.any():
            continue
        loc = model.to_local(i, pts[i][ok])[:, :2]
        lo, hi = loc.min(axis=0), loc.max(axis=0)
        j = model.owner(i)
        if j in boxes:
            lo, hi = np.minimum(lo, boxes[j][0]), np.maximum(hi, boxes[j][1])
        boxes[j] = (lo, hi)
    return boxes


# ------------------------------------------------------------- assembly
@dataclass
class OpticsPart:
    """One mesh of the optics with its BSDF (a Mitsuba dict) and component."""

    mesh: _m.Mesh
    bsdf: dict
    component: str


def _face_bsdf(model, sides, i) -> dict:
    s = model.system.surfaces[i]
    if s.interaction == "reflect":
        return _bsdfs.mirror()
    n_in, n_out = model.index_before(i), model.index_other(i)
    if sides[i] >= 0:  # normals (+z local) point into the medium after the surface
        return _bsdfs.interface(int_ior=n_in, ext_ior=n_out)
    return _bsdfs.interface(int_ior=n_out, ext_ior=n_in)


def _same_plane(model, i: int, j: int) -> bool:
    (Ri, oi), (Rj, oj) = model.frames[i], model.frames[j]
    return bool(np.allclose(Ri, Rj, rtol=0, atol=1e-12) and np.allclose(oi, oj, rtol=0, atol=1e-9)
                and model.index_before(i) == model.index_before(j))


def _resolve(system, ref) -> int:
    if isinstance(ref, str):
        names = [s.name for s in system.surfaces]
        if ref not in names:
            raise ValueError(f"no surface named {ref!r}; surfaces: {', '.join(names)}")
        return names.index(ref)
    return int(ref) % len(system.surfaces)


def optics_parts(design, values=None, wavelength_nm=None, segments: int = _m.DEFAULT_SEGMENTS,
                 lenslet_segments: int = _m.DEFAULT_LENSLET_SEGMENTS, span=None,
                 mounts: bool = True, prism_segments: int = _m.DEFAULT_PRISM_SEGMENTS) -> list[OpticsPart]:
    """The meshes and BSDFs of :func:`optics_shapes` (numpy, before export).

    ``mounts``: absorbing rings around every lens face with a clear aperture
    and around each lenslet array (barrels and holders), so a ray the tracer
    vignettes is stopped in the scene too instead of passing beside the glass.
    """
    model = _m.SurfaceModel(design, values, wavelength_nm)
    system = model.system
    sides = surface_sides(model)
    lo, hi = (0, len(system.surfaces) - 1) if span is None else (_resolve(system, span[0]), _resolve(system, span[1]))
    parts: list[OpticsPart] = []
    absorb = _bsdfs.absorber()
    for comp in _m.components(system):
        if min(comp.surfaces) < lo or max(comp.surfaces) > hi:
            continue
        kind, idx = comp.kind, comp.surfaces
        if kind in ("lens", "lenslet_array", "prism"):
            if kind == "lens":
                solid = _m.lens_solid(model, idx, segments, comp.name)
            elif kind == "prism":
                solid = _m.prism_solid(model, idx, prism_segments, comp.name, footprints=footprints(design, model))
            else:
                solid = _m.lenslet_array_solid(model, idx, comp.name, lenslet_segments)
            for mesh in solid.meshes:
                b = _face_bsdf(model, sides, mesh.surface) if mesh.role == "face" else absorb
                parts.append(OpticsPart(mesh, b, comp.name))
            if mounts and kind == "lens":
                for i in idx:
                    if system.surfaces[i].aperture is not None:
                        parts.append(OpticsPart(_m.mount(model, i, system.surfaces[i].aperture), absorb, comp.name))
            elif mounts and kind == "lenslet_array":
                parts.append(OpticsPart(_array_mount(model, idx[0]), absorb, comp.name))
        elif kind in ("face", "mirror"):
            mesh = _m.tessellate_surface(model, idx[0], segments)
            parts.append(OpticsPart(mesh, _face_bsdf(model, sides, idx[0]), comp.name))
        elif kind == "paraxial":
            i = idx[0]
            prev = parts[-1] if parts else None
            if (prev is not None and prev.bsdf.get("type") == _bsdfs.THINLENS and "array_m" not in prev.bsdf
                    and _same_plane(model, prev.mesh.surface, i)):
                # Thin lenses in contact (same plane and axis) are one lens of
                # the summed power: coincident meshes would hide one another.
                prev.bsdf["power"] += model.power(i)
                prev.mesh.name = f"{prev.mesh.name}_{system.surfaces[i].name}"
                continue
            mesh = _m.tessellate_surface(model, i, segments)
            b = _bsdfs.thin_lens(model.power(i), model.index_before(i), model.frames[i][0])
            parts.append(OpticsPart(mesh, b, comp.name))
        elif kind == "paraxial_array":
            i = idx[0]
            arr = system.surfaces[i].array
            mesh = _m.paraxial_array(model, i, arr)
            a = system.arrays[arr]
            _, _, pitch = model.lenslet_centres(arr)
            centre = (model.value(f"{arr}.center_x"), model.value(f"{arr}.center_y"))
            b = _bsdfs.thin_lens(model.power(i), model.index_before(i), model.frames[i][0],
                                 array=(a.m, a.n, pitch, centre))
            parts.append(OpticsPart(mesh, b, comp.name))
            if mounts:
                parts.append(OpticsPart(_array_mount(model, i), absorb, comp.name))
        elif kind == "aperture_array":
            mesh = _m.aperture_mask(model, idx[0], system.surfaces[idx[0]].array)
            if len(mesh.faces):
                parts.append(OpticsPart(mesh, absorb, comp.name))
    return parts


def _array_mount(model, i: int) -> _m.Mesh:
    """The holder around lenslet array member ``i`` (its M×N cells are the clear area)."""
    arr = model.system.surfaces[i].array
    a = model.system.arrays[arr]
    _, _, (px, py) = model.lenslet_centres(arr)
    cx, cy = model.value(f"{arr}.center_x"), model.value(f"{arr}.center_y")
    region = Aperture("rectangular", half_width=(0.5 * a.m * px, 0.5 * a.n * py), decenter=(cx, cy))
    return _m.mount(model, i, region, array=arr)


def _mesh_dir(mesh_dir) -> Path:
    global _MESH_DIR
    if mesh_dir is not None:
        p = Path(mesh_dir)
        p.mkdir(parents=True, exist_ok=True)
        return p
    if _MESH_DIR is None or not _MESH_DIR.exists():
        _MESH_DIR = Path(tempfile.mkdtemp(prefix="lfsim_meshes_"))
    return _MESH_DIR


def optics_shapes(design, values=None, wavelength_nm=None, segments: int = _m.DEFAULT_SEGMENTS,
                  lenslet_segments: int = _m.DEFAULT_LENSLET_SEGMENTS, span=None,
                  mesh_dir=None, mounts: bool = True,
                  prism_segments: int = _m.DEFAULT_PRISM_SEGMENTS) -> dict[str, dict]:
    """Mitsuba shape dicts of a design's optics (display and eye excluded).

    Parameters
    ----------
    design : Design or System
    values : array_like, optional
        Parameter vector (``design.parameter_names()`` order) of the state to
        export, e.g. with a tunable-lens power per CDP depth; indices are
        taken from it. Default: the design at ``wavelength_nm``.
    wavelength_nm : float, optional
        Render wavelength for the indices (default: primary).
    segments : int
        Segments per semi-diameter of ordinary surfaces.
    lenslet_segments : int
        Segments per lenslet pitch.
    span : (first, last), optional
        Only components whose surfaces lie within these surfaces (names or
        indices, inclusive).
    prism_segments : int
        Segments per half-width of a freeform prism's largest face
        (:func:`lfsim.render.meshes.tessellation` scales all three together).
    mesh_dir : path, optional
        Where the PLY files go (default: one temporary folder per process);
        files are named by content hash.

    Returns
    -------
    dict
        ``{key: {"type": "ply", "filename": ..., "bsdf": {...}, ...}}`` with
        keys = surface names for optical faces and ``<a>_<b>_rim`` /
        ``_walls`` for the rest; ready for ``mi.load_dict({"type": "scene", **shapes, ...})``.
    """
    _bsdfs.register()
    out_dir = _mesh_dir(mesh_dir)
    shapes: dict[str, dict] = {}
    for part in optics_parts(design, values, wavelength_nm, segments, lenslet_segments, span, mounts,
                             prism_segments):
        m = part.mesh
        blob = ply_bytes(m)
        path = out_dir / f"{m.name}-{hashlib.sha1(blob).hexdigest()[:16]}.ply"
        if not path.exists():
            tmp = path.with_suffix(".tmp")
            tmp.write_bytes(blob)
            tmp.replace(path)
        shapes[m.name] = {"type": "ply", "filename": str(path), "face_normals": m.normals is None,
                          "bsdf": part.bsdf}
    return shapes


# ------------------------------------------------------------------ PLY
def ply_bytes(mesh: _m.Mesh) -> bytes:
    """Binary little-endian PLY of a mesh: float32 x y z [nx ny nz] [u v], int32 faces."""
    props = ["x", "y", "z"]
    cols = [mesh.vertices]
    if mesh.normals is not None:
        props += ["nx", "ny", "nz"]
        cols.append(mesh.normals)
    if mesh.uv is not None:
        props += ["u", "v"]
        cols.append(mesh.uv)
    data = np.ascontiguousarray(np.concatenate(cols, axis=1), dtype="<f4")
    faces = np.empty(len(mesh.faces), dtype=[("n", "u1"), ("i", "<i4", (3,))])
    faces["n"] = 3
    faces["i"] = mesh.faces
    head = ("ply\nformat binary_little_endian 1.0\n"
            f"element vertex {len(data)}\n" + "".join(f"property float {p}\n" for p in props)
            + f"element face {len(faces)}\nproperty list uchar int vertex_indices\nend_header\n")
    return head.encode("ascii") + data.tobytes() + faces.tobytes()


def write_ply(path, mesh: _m.Mesh) -> Path:
    p = Path(path)
    p.write_bytes(ply_bytes(mesh))
    return p


# ------------------------------------------------------------------ XML
_CATEGORY_BY_KEY = {"bsdf": "bsdf", "emitter": "emitter", "sensor": "sensor", "film": "film",
                    "sampler": "sampler", "integrator": "integrator", "rfilter": "rfilter",
                    "medium": "medium", "interior": "medium", "exterior": "medium"}
_CATEGORY_BY_TYPE = {
    **{t: "shape" for t in ("ply", "obj", "serialized", "rectangle", "disk", "sphere", "cylinder", "cube",
                            "shapegroup", "instance", "bsplinecurve", "linearcurve", "sdfgrid", "ellipsoids")},
    **{t: "bsdf" for t in ("diffuse", "conductor", "roughconductor", "dielectric", "roughdielectric",
                           "thindielectric", "twosided", "plastic", "roughplastic", "null", "mask",
                           "blendbsdf", "principled", "measured", "normalmap", "bumpmap", "pplastic",
                           _bsdfs.INTERFACE, _bsdfs.THINLENS)},
    **{t: "emitter" for t in ("area", "point", "constant", "envmap", "spot", "directional", "projector",
                              "directionalarea")},
    **{t: "sensor" for t in ("perspective", "thinlens", "orthographic", "radiancemeter",
                             "irradiancemeter", "distant", "batch")},
    **{t: "texture" for t in ("bitmap", "checkerboard", "mesh_attribute", "volume")},
    **{t: "film" for t in ("hdrfilm", "specfilm")},
    **{t: "sampler" for t in ("independent", "stratified", "multijitter", "orthogonal", "ldsampler", "lfsim_sobol")},
    **{t: "rfilter" for t in ("box", "gaussian", "tent", "lanczos", "mitchell", "catmullrom")},
    **{t: "integrator" for t in ("path", "direct", "volpath", "volpathmis", "prb", "prb_basic",
                                 "direct_projective", "prb_projective", "aov", "moment", "depth",
                                 "stokes", "ptracer")},
}


def _fmt(v) -> str:
    return repr(float(v))


def _add(parent, key, value, out_dir: Path, categories: dict, top: bool):
    import mitsuba as mi

    if isinstance(value, dict):
        t = value.get("type")
        if t == "rgb":
            vals = value["value"]
            vals = [vals] * 3 if np.isscalar(vals) else vals
            ET.SubElement(parent, "rgb", name=key, value=", ".join(_fmt(v) for v in vals))
            return
        if t == "spectrum":
            ET.SubElement(parent, "spectrum", name=key, value=str(value["value"]))
            return
        cat = categories.get(t) or _CATEGORY_BY_TYPE.get(t) or _CATEGORY_BY_KEY.get(key)
        if cat is None:
            raise ValueError(f"write_scene_xml: cannot tell the XML tag of {key!r} (type {t!r}); "
                             "pass categories={type: 'shape'|'bsdf'|'emitter'|...}")
        el = ET.SubElement(parent, cat, type=t, **({"id": key} if top else {"name": key}))
        for k, v in value.items():
            if k != "type":
                _add(el, k, v, out_dir, categories, False)
        return
    if isinstance(value, bool):
        ET.SubElement(parent, "boolean", name=key, value="true" if value else "false")
    elif isinstance(value, (int, np.integer)):
        ET.SubElement(parent, "integer", name=key, value=str(int(value)))
    elif isinstance(value, (float, np.floating)):
        ET.SubElement(parent, "float", name=key, value=_fmt(value))
    elif isinstance(value, str):
        if key == "filename" and Path(value).is_file():
            src = Path(value)
            (out_dir / "meshes").mkdir(exist_ok=True)
            dst = out_dir / "meshes" / src.name
            if src.resolve() != dst.resolve():
                shutil.copyfile(src, dst)
            value = f"meshes/{src.name}"
        ET.SubElement(parent, "string", name=key, value=value)
    elif isinstance(value, (mi.ScalarTransform4f, mi.ScalarTransform4d)):
        el = ET.SubElement(parent, "transform", name=key)
        M = np.array(value.matrix, dtype=np.float64).reshape(4, 4)
        ET.SubElement(el, "matrix", value=" ".join(_fmt(v) for v in M.ravel()))
    elif isinstance(value, (list, tuple)) and len(value) == 3 and all(np.isscalar(v) for v in value):
        ET.SubElement(parent, "point", name=key, x=_fmt(value[0]), y=_fmt(value[1]), z=_fmt(value[2]))
    else:
        raise TypeError(f"write_scene_xml: {key!r} holds a {type(value).__name__}, which has no XML form "
                        "(use files, e.g. a bitmap 'filename', instead of in-memory objects)")


def write_scene_xml(scene_dict: dict, out_dir, name: str = "scene.xml", categories: dict | None = None) -> Path:
    """Write a scene dict as Mitsuba XML plus its PLY files into ``out_dir``.

    Referenced files (``filename`` entries) are copied to ``out_dir/meshes``
    and named relative to the XML, so the folder is self-contained and
    ``mi.load_file(path)`` gives the same scene (register lfsim's BSDFs first:
    :func:`lfsim.render.bsdfs.register`). ``scene_dict`` may be a full scene
    (``{"type": "scene", ...}``) or just shapes. Floats are written with full
    precision. Returns the XML path.
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    root = ET.Element("scene", version="3.0.0")
    for k, v in scene_dict.items():
        if k == "type":
            continue
        _add(root, k, v, out, categories or {}, True)
    ET.indent(root)
    path = out / name
    ET.ElementTree(root).write(path, encoding="utf-8", xml_declaration=True)
    return path


# ------------------------------------------------------------ ray walker
@dataclass
class SceneTrace:
    """Result of :func:`trace_scene` (numpy).

    positions : (N, 3) last interaction point (the origin if nothing was hit)
    directions : (N, 3) direction leaving it
    valid : (N,) bool, the ray left the scene (no absorption, no zero
        weight, fewer than ``max_depth`` interactions)
    interactions : (N,) number of surfaces met
    """

    positions: np.ndarray
    directions: np.ndarray
    valid: np.ndarray
    interactions: np.ndarray


def trace_scene(scene, origins, directions, max_depth: int = 64, along_ray: bool = True) -> SceneTrace:
    """Follow rays through a specular chain: ray_intersect → bsdf.sample → spawn_ray.

    A deterministic walk (sample values 0.5) for delta BSDFs; a ray ends when
    it misses everything (it escaped: valid) or a BSDF returns zero weight
    (absorbed: invalid). Float32 Mitsuba arithmetic; inputs numpy (N, 3) in
    the scene's frame (mm).

    ``along_ray``: Mitsuba's ``spawn_ray`` lifts the new origin off the
    surface along the normal by ~1e-4·(1 + |p|) mm, which shifts the ray
    sideways (≈1 µm per surface 200 mm from the origin). By default the same
    clearance is taken along the new direction instead (no lateral shift),
    so the walk measures the tessellation; ``False`` reproduces exactly what
    Mitsuba's integrators do.
    """
    import drjit as dr

    mi = _bsdfs.register()
    o = np.asarray(origins, dtype=np.float32).reshape(-1, 3)
    d = np.asarray(directions, dtype=np.float64).reshape(-1, 3)
    d = (d / np.linalg.norm(d, axis=1, keepdims=True)).astype(np.float32)
    n = len(o)
    ray = mi.Ray3f(mi.Point3f(*from_numpy(mi.Float, *(o[:, k] for k in range(3)))),
                   mi.Vector3f(*from_numpy(mi.Float, *(d[:, k] for k in range(3)))))
    pos, dirn = mi.Point3f(ray.o), mi.Vector3f(ray.d)
    active = dr.full(mi.Bool, True, n)
    absorbed = dr.full(mi.Bool, False, n)
    count = dr.zeros(mi.UInt32, n)
    ctx = mi.BSDFContext()
    with dr.suspend_grad():
        for _ in range(int(max_depth)):
            si = scene.ray_intersect(ray, active)
            hit = active & si.is_valid()
            bs, w = si.bsdf(ray).sample(ctx, si, 0.5, mi.Point2f(0.5, 0.5), hit)
            ok = hit & (w.x > 0.0)
            wo = si.to_world(bs.wo)
            absorbed |= hit & ~ok
            pos = dr.select(ok, si.p, pos)
            dirn = dr.select(ok, wo, dirn)
            count = dr.select(ok, count + 1, count)
            if along_ray:
                # Mitsuba's offset (∝ |p|, along the normal) moved onto the ray's own line.
                off = dr.norm(si.spawn_ray(wo).o - si.p)
                cos_n = dr.maximum(dr.abs(dr.dot(si.n, wo)), 1e-3)
                nxt = mi.Ray3f(si.p + wo * (off / cos_n), wo)
            else:
                nxt = si.spawn_ray(wo)
            ray = dr.select(ok, nxt, ray)
            active = ok
            dr.eval(pos, dirn, count, absorbed, active, ray)
            if not dr.any(active):
                break
        valid = ~absorbed & ~active

    def np3(v):
        return np.column_stack([np.asarray(v.x), np.asarray(v.y), np.asarray(v.z)]).astype(np.float64)

    return SceneTrace(np3(pos), np3(dirn), np.asarray(valid, dtype=bool), np.asarray(count).astype(np.int64))
