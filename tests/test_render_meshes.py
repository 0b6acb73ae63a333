"""Mitsuba geometry of a design's optics (lfsim.render.meshes / bsdfs / optics_scene).

References are lfsim's own tracer and surface functions (float64) or closed
forms; tolerances are physical (fractions of the design's pixel) or float32
rounding, never numbers taken from this implementation.
"""

import time

import numpy as np
import pytest

import lfsim
from lfsim.render import meshes as M
from lfsim.render import optics_scene as OS

EPS32 = 2.0**-24


@pytest.fixture(scope="module")
def mi():
    from lfsim.render import bsdfs

    return bsdfs.register()


@pytest.fixture(scope="module")
def coaxial(scenes):
    return lfsim.load(scenes / "ini_coaxial.toml")


@pytest.fixture(scope="module")
def scenes():
    from pathlib import Path

    return Path(__file__).resolve().parents[1] / "scenes"


def _np3(v):
    return np.column_stack([np.asarray(v.x), np.asarray(v.y), np.asarray(v.z)]).astype(np.float64)


def _lfsim_normals(tracer, i, x, y):
    """Analytic unit normals (+z local) by lfsim.optics.surfaces at the design values."""
    import drjit as dr

    from lfsim.optics.surfaces import Shape, normal, sag

    s = tracer.system.surfaces[i]
    o = tracer.system.surfaces[s.same_as] if s.same_as is not None else s
    T = tracer.T
    shape = Shape(T.Float(o.curvature), T.Float(o.conic), {k: T.Float(v) for k, v in o.asphere.items()},
                  {k: T.Float(v) for k, v in o.xy.items()}, 1.0 / o.norm_radius)
    with dr.suspend_grad():
        _, zx, zy, _ = sag(T.Float(x), T.Float(y), shape)
        return _np3(normal(zx, zy, T.Array3))


def _check_on_surface(tracer, mesh, i):
    R, o = tracer.frames_numpy()[i]
    loc = (mesh.vertices - o) @ R
    z_ref = tracer.sag_numpy(i, loc[:, 0], loc[:, 1])
    scale = 1.0 + np.abs(z_ref)
    assert np.max(np.abs(loc[:, 2] - z_ref) / scale) < 1e-9
    n_ref = _lfsim_normals(tracer, i, loc[:, 0], loc[:, 1]) @ R.T
    assert np.max(np.abs(mesh.normals - n_ref)) < 1e-9
    # Triangles are wound with the vertex normals.
    p = mesh.vertices[mesh.faces]
    fn = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    assert np.all(np.einsum("ij,ij->i", fn, mesh.normals[mesh.faces].sum(axis=1)) > 0)


# ----------------------------------------------------------- geometry
def test_vertices_and_normals_are_lfsim_surfaces(coaxial, scenes):
    tr = coaxial.tracer()
    model = M.SurfaceModel(coaxial)
    for i in (3, 7, 16):  # spheres, incl. a cemented interface
        _check_on_surface(tr, M.tessellate_surface(model, i, 12), i)
    for i in (0, 1):  # aspheric lenslets: per-lenslet normals, array lattice
        mesh = M.lenslet_faces(model, i, "mla", 6)
        R, o = tr.frames_numpy()[i]
        loc = (mesh.vertices - o) @ R
        xm, yn, _ = model.lenslet_centres("mla")
        # Vertex -> its lenslet (the lattice is per lenslet, 7x7 vertices each).
        lens = np.repeat(np.arange(17 * 9), 49)
        u = loc[:, 0] - xm[lens // 9]
        v = loc[:, 1] - yn[lens % 9]
        z_ref = tr.sag_numpy(i, u, v)
        assert np.max(np.abs(loc[:, 2] - z_ref) / (1 + np.abs(z_ref))) < 1e-9
        assert np.max(np.abs(mesh.normals - _lfsim_normals(tr, i, u, v) @ R.T)) < 1e-9
    ff = lfsim.load(scenes / "ini_freeform.toml")  # tilted XY-polynomial prism faces
    tf, mf = ff.tracer(), M.SurfaceModel(ff)
    for i in (15, 16, 17):
        _check_on_surface(tf, M.tessellate_surface(mf, i, 10), i)


def test_mesh_follows_parameter_vector(coaxial):
    """A per-state parameter vector moves the mesh (closed-form sphere)."""
    names = coaxial.parameter_names()
    vals = np.array(coaxial.system.parameter_values(587.5618))
    c = 1.0 / 40.0
    vals[names.index("A1a.curvature")] = c
    model = M.SurfaceModel(coaxial, values=vals)
    k = _index(coaxial, "A1a")
    mesh = M.tessellate_surface(model, k, 8)
    R, o = model.frames[k]
    loc = (mesh.vertices - o) @ R
    r2 = loc[:, 0] ** 2 + loc[:, 1] ** 2
    z = c * r2 / (1 + np.sqrt(1 - c * c * r2))
    assert np.max(np.abs(loc[:, 2] - z)) < 1e-12
    assert np.allclose(np.hypot(loc[:, 0], loc[:, 1]).max(), 22.5)  # the clear aperture


def test_watertight_solids(coaxial, scenes):
    model = M.SurfaceModel(coaxial)
    mla = M.lenslet_array_solid(model, [0, 1], "mla", 6)
    assert mla.is_watertight(), mla.open_edges()
    for comp in M.components(coaxial.system):
        if comp.kind == "lens":
            solid = M.lens_solid(model, comp.surfaces, 10)
            assert solid.is_watertight(), (comp.name, solid.open_edges())
            assert len(solid.pieces) == len(comp.surfaces) - 1  # one closed piece per glass
    # Negative control: without its rim band a lens is open.
    lens = M.lens_solid(model, [_index(coaxial, "F1a"), _index(coaxial, "F1b")], 10)
    assert M.open_edge_count(lens.meshes[:2]) > 0
    ff = lfsim.load(scenes / "ini_freeform.toml")
    mf = M.SurfaceModel(ff)
    prism = M.prism_solid(mf, [16, 17, 18, 19], 12, footprints=OS.footprints(ff, mf))
    assert prism.is_watertight()
    assert [m.name for m in prism.meshes if m.role == "face"].count("S2") == 1  # S4 = S2 emitted once


def test_components_only_what_is_declared(scenes):
    names = ("ini_coaxial", "ini_freeform", "ini_ideal", "direct_view", "cooke_triplet")
    kinds = {n: {c.kind for c in M.components(lfsim.load(scenes / f"{n}.toml").system)} for n in names}
    assert kinds["ini_coaxial"] == {"lenslet_array", "aperture_array", "lens", "paraxial"}
    assert kinds["ini_freeform"] == {"lenslet_array", "aperture_array", "lens", "paraxial", "prism"}
    assert kinds["ini_ideal"] == {"paraxial_array", "paraxial"}
    assert kinds["direct_view"] == {"lenslet_array"}
    assert kinds["cooke_triplet"] == {"lens"}


def test_prism_bsdfs(scenes):
    ff = lfsim.load(scenes / "ini_freeform.toml")
    parts = {p.mesh.name: p.bsdf for p in OS.optics_parts(ff, segments=8, lenslet_segments=4)}
    assert parts["S3"]["type"] == "twosided" and parts["S3"]["bsdf"]["type"] == "conductor"
    names = [s.name for s in ff.system.surfaces]
    n_pmma = ff.system.surfaces[names.index("S1")].material.index(587.5618)
    for face in ("S2", "S4"):  # TIR face and exit face: PMMA / air interfaces, four distinct surfaces
        assert parts[face]["type"] == "lfsim_interface"
        assert sorted([parts[face]["int_ior"], parts[face]["ext_ior"]]) == pytest.approx([1.0, n_pmma])
    assert all(s.same_as is None for s in ff.system.surfaces)


def test_aperture_array_mask(make_design):
    d = make_design("""
[object]
distance = 5.0
[arrays.mla]
m = 5
n = 3
pitch = [1.0, 0.8]
[[surfaces]]
name = "AA"
dummy = true
array = "mla"
aperture = { type = "rectangular", half_width = [0.3, 0.25] }
thickness = 0.5
[[surfaces]]
name = "L1"
array = "mla"
radius = 2.0
material = "N-BK7"
thickness = 1.0
[[surfaces]]
name = "L2"
array = "mla"
thickness = 5.0
[[surfaces]]
name = "IMG"
""")
    comps = M.components(d.system)
    assert [c.kind for c in comps] == ["lenslet_array", "aperture_array"]
    parts = {p.mesh.name: p for p in OS.optics_parts(d, lenslet_segments=4)}
    mask = parts["AA"].mesh
    assert parts["AA"].bsdf["type"] == "diffuse"
    p = mask.vertices[mask.faces]
    area = 0.5 * np.linalg.norm(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), axis=1).sum()
    assert area == pytest.approx(15 * (1.0 * 0.8 - 0.6 * 0.5), rel=1e-12)
    assert M.lenslet_array_solid(M.SurfaceModel(d), [1, 2], "mla", 4).is_watertight()


def test_mla_build_time():
    d = lfsim.load(__import__("pathlib").Path(__file__).resolve().parents[1] / "scenes" / "direct_view.toml")
    OS.optics_parts(d, lenslet_segments=4)  # warm the kernel cache
    t = time.perf_counter()
    parts = OS.optics_parts(d)  # 17 x 9 lenslets at the default density
    dt = time.perf_counter() - t
    assert dt < 5.0, dt
    assert sum(len(p.mesh.faces) for p in parts) > 2 * 153 * M.DEFAULT_LENSLET_SEGMENTS**2


# ------------------------------------------------------- ray agreement
def _display_bundle(design, k=12, seed=1):
    """Rays from the display through lenslets of the whole array (inside each cell)."""
    rng = np.random.default_rng(seed)
    mm, nn = [a.ravel() for a in np.meshgrid([0, 4, 8, 12, 16], [0, 4, 8])]
    mm, nn = np.repeat(mm, k), np.repeat(nn, k)
    xm, yn = mm - 8.0, nn - 4.0
    n = len(xm)
    o = np.column_stack([xm + rng.uniform(-.3, .3, n), yn + rng.uniform(-.3, .3, n),
                         np.full(n, -design.system.object_distance)])
    t = np.column_stack([xm + rng.uniform(-.35, .35, n), yn + rng.uniform(-.35, .35, n), np.zeros(n)])
    d = t - o
    return o, d / np.linalg.norm(d, axis=1, keepdims=True)


def _index(design, name: str) -> int:
    return [s.name for s in design.system.surfaces].index(name)


def _at_plane(p, d, z):
    return p + ((z - p[:, 2]) / d[:, 2])[:, None] * d


def _error_table(mi, coaxial, segs):
    """RMS / max position error (mm) vs lfsim in a plane 3 mm after the MLA and
    50 mm after the relay's last surface, per tessellation density."""
    o, d = _display_bundle(coaxial)
    tr = coaxial.tracer()
    frames = tr.frames_numpy()
    end = _index(coaxial, "C1b")  # the relay's last surface
    planes = {"after MLA": (1, frames[1][1][2] + 3.0), "end of relay": (end, frames[end][1][2] + 50.0)}
    refs = {}
    for label, (last, z) in planes.items():
        out = tr.trace(tr.params(), tr.rays(o, d), last=last)
        refs[label] = (np.asarray(out.status) == 0, _at_plane(_np3(out.p), _np3(out.d), z))
    rows = {label: [] for label in planes}
    for s in segs:
        shapes = OS.optics_shapes(coaxial, segments=s, lenslet_segments=s, span=(0, end))
        scene = mi.load_dict({"type": "scene", **shapes})
        for label, (last, z) in planes.items():
            # Through the MLA only: stop the walk after its two faces.
            res = OS.trace_scene(scene, o, d, max_depth=2) if last == 1 else OS.trace_scene(scene, o, d)
            ok0, ref = refs[label]
            valid = (res.interactions == 2) if last == 1 else res.valid
            ok = ok0 & valid
            e = np.linalg.norm((_at_plane(res.positions, res.directions, z) - ref)[ok, :2], axis=1)
            rows[label].append((ok.mean(), float(np.sqrt(np.mean(e**2))), float(e.max())))
    return rows


def test_mesh_trace_matches_lfsim_coaxial(mi, coaxial):
    """Display rays through the meshes agree with lfsim after the MLA and at the
    end of the relay; the error falls with tessellation and is small at the
    default density (display pixel 8 µm; intermediate image pixel ~20 µm)."""
    segs = (8, 16, 32)
    rows = _error_table(mi, coaxial, segs)
    for label, vals in rows.items():
        assert all(v[0] == 1.0 for v in vals), (label, vals)  # every ray valid in both
        rms = [v[1] for v in vals]
        assert rms[0] > rms[1] > rms[2], (label, rms)
        assert rms[0] / rms[2] > 8  # ~second-order convergence (16x ideal)
    # The defaults are at least this dense, so the bounds below hold for them too.
    assert segs[-1] <= min(M.DEFAULT_SEGMENTS, M.DEFAULT_LENSLET_SEGMENTS)
    # Bounds: 1/20 of the display pixel (8 µm) and of the intermediate image's (~20 µm). Their
    # noise floor is Mitsuba's float32 rounding of positions up to |z| ~ 262 mm from the origin,
    # about EPS32 · |z| (1.6e-5 mm at the end of the relay); each bound is above 16x that.
    z_end = abs(coaxial.tracer().frames_numpy()[_index(coaxial, "C1b")][1][2]) + 50.0
    assert 16 * EPS32 * z_end < 0.020 / 20, z_end
    assert rows["after MLA"][-1][1] < 0.008 / 20  # 1/20 display pixel
    assert rows["end of relay"][-1][1] < 0.020 / 20


@pytest.mark.slow
def test_mesh_trace_error_table(mi, coaxial, capsys):
    segs = (8, 16, 32, 64)
    rows = _error_table(mi, coaxial, segs)
    with capsys.disabled():
        for label, vals in rows.items():
            print(f"\n{label}: " + ", ".join(f"S={s}: rms {v[1] * 1e3:.3g} um max {v[2] * 1e3:.3g} um"
                                             for s, v in zip(segs, vals)))
    for vals in rows.values():
        rms = [v[1] for v in vals]
        assert all(a > b for a, b in zip(rms, rms[1:]))


def test_freeform_prism_scene_matches_lfsim(mi, scenes):
    ff = lfsim.load(scenes / "ini_freeform.toml")
    o, d = _display_bundle(ff, k=6, seed=3)
    tr = ff.tracer()
    out = tr.trace(tr.params(), tr.rays(o, d))
    ok0 = np.asarray(out.status) == 0
    res = OS.trace_scene(mi.load_dict({"type": "scene", **OS.optics_shapes(ff)}), o, d)
    assert np.all(res.valid[ok0])  # nothing blocked by walls/bevels, TIR at S2 works
    R, ov = tr.frames_numpy()[-1]
    ez = R[:, 2]
    t = ((ov - res.positions) @ ez) / (res.directions @ ez)
    q = res.positions + t[:, None] * res.directions
    e = np.linalg.norm(q - _np3(out.p), axis=1)[ok0]
    assert np.sqrt(np.mean(e**2)) < 0.02  # at the viewing window (mm), ~D_v/250
    assert np.max(np.abs(res.directions - _np3(out.d))[ok0]) < 1e-3


def test_thin_lens_bsdf_is_the_paraxial_surface(mi, scenes):
    """ini_ideal.toml (ideal MLA, tunable lens at a per-state power, eyepiece):
    forward and reverse agreement with the tracer to float32 rounding."""
    d = lfsim.load(scenes / "ini_ideal.toml")
    names = d.parameter_names()
    vals = np.array(d.system.parameter_values(587.5618))
    vals[names.index("TL.power")] = -1.03e-3
    scene = mi.load_dict({"type": "scene", **OS.optics_shapes(d, values=vals)})
    rng = np.random.default_rng(2)
    n = 300
    m, k = rng.integers(0, 17, n), rng.integers(0, 9, n)
    o = np.column_stack([m - 8 + rng.uniform(-.45, .45, n), k - 4 + rng.uniform(-.45, .45, n), np.full(n, -4.5)])
    t = np.column_stack([m - 8 + rng.uniform(-.45, .45, n), k - 4 + rng.uniform(-.45, .45, n), np.zeros(n)])
    dirs = (t - o) / np.linalg.norm(t - o, axis=1, keepdims=True)
    tr = d.tracer()
    P = tr.params(values=vals)
    out = tr.trace(P, tr.rays(o, dirs))
    ok = np.asarray(out.status) == 0
    assert ok.all()
    p0, d0 = _np3(out.p), _np3(out.d)
    scale = np.abs(p0).max() + 50.0
    res = OS.trace_scene(scene, o, dirs)
    assert res.valid.all()
    q = _at_plane(res.positions, res.directions, p0[0, 2])
    assert np.max(np.abs(q - p0)) < 64 * EPS32 * scale
    assert np.max(np.abs(res.directions - d0)) < 64 * EPS32
    back = OS.trace_scene(scene, p0, -d0)  # light going the other way
    assert back.valid.all()
    qb = _at_plane(back.positions, back.directions, -4.5)
    assert np.max(np.abs(qb - o)) < 64 * EPS32 * scale
    assert np.max(np.abs(back.directions + dirs)) < 64 * EPS32


def test_interface_bsdf_snell_and_tir(mi):
    """Closed forms: Snell's law both ways, TIR above the critical angle, weight 1."""
    from lfsim.render import bsdfs

    b = mi.load_dict(bsdfs.interface(int_ior=1.5, ext_ior=1.0))
    th = np.radians([10.0, 30.0, 60.0])
    si = mi.SurfaceInteraction3f()
    si.wi = mi.Vector3f(np.sin(th), 0 * th, np.cos(th))  # from outside (n = 1)
    bs, w = b.sample(mi.BSDFContext(), si, 0.5, mi.Point2f(0.5))
    wo = _np3(bs.wo)
    # Float32 directions: 16 EPS32 (1e-6), 50x the 0.3 EPS32 measured.
    assert np.allclose(np.sin(th) / 1.5, -wo[:, 0], rtol=0, atol=16 * EPS32) and np.all(wo[:, 2] < 0)
    assert np.allclose(np.asarray(w.x), 1.0)
    th = np.radians([20.0, 41.0, 42.0, 70.0])  # from inside; critical angle 41.81 deg
    si.wi = mi.Vector3f(np.sin(th), 0 * th, -np.cos(th))
    bs, w = b.sample(mi.BSDFContext(), si, 0.5, mi.Point2f(0.5))
    wo = _np3(bs.wo)
    tir = th > np.arcsin(1 / 1.5)
    assert np.all((wo[:, 2] < 0) == tir)  # reflected stays inside (z < 0)
    assert np.allclose(-wo[~tir, 0], 1.5 * np.sin(th[~tir]), rtol=0, atol=16 * EPS32)
    assert np.allclose(np.asarray(w.x), 1.0)


def test_xml_round_trip_renders_identically(mi, scenes, tmp_path):
    d = lfsim.load(scenes / "cooke_triplet.toml")
    T = mi.ScalarTransform4f

    def scene():
        return {
            "type": "scene",
            "integrator": {"type": "path", "max_depth": 16, "rr_depth": 32},
            "sensor": {"type": "perspective", "fov": 30.0,
                       "to_world": T().look_at(origin=[0, 0, -40], target=[0, 0, 0], up=[0, 1, 0]),
                       "film": {"type": "hdrfilm", "width": 24, "height": 24},
                       "sampler": {"type": "independent", "sample_count": 4}},
            "light": {"type": "rectangle", "to_world": T().translate([0, 0, 120]).scale([40, 40, 1]),
                      "flip_normals": True,
                      "emitter": {"type": "area", "radiance": {"type": "rgb", "value": [1.0, 0.5, 0.25]}}},
            **OS.optics_shapes(d, segments=12, mesh_dir=tmp_path / "cache"),
        }

    a = np.array(mi.render(mi.load_dict(scene()), seed=3))
    path = OS.write_scene_xml(scene(), tmp_path / "out")
    assert (tmp_path / "out" / "meshes").is_dir()
    b = np.array(mi.render(mi.load_file(str(path)), seed=3))
    assert a.mean() > 0.01  # the light is seen through the lens
    # Same samples; the meshes come back from the PLY files rounded to float32: 64 EPS32 of the
    # largest value, 32x the 2 EPS32 measured (one ray on another path would differ by ~1/spp).
    assert np.max(np.abs(a - b)) <= 64 * EPS32 * max(1.0, a.max())
