"""Differentiable mesh path: Dr.Jit mesh vertices against the numpy tessellation
(values and parameter derivatives), the specular-chain AD integrator against
central differences (common random numbers), forward = reverse mode, no NaN,
the Fresnel-weighted interface and `lfsim gradcheck --optics mesh`."""

import json
import subprocess
import sys

import drjit as dr
import numpy as np
import pytest
from conftest import ROOT

SMALL = {"arrays.mla.m": 5, "arrays.mla.n": 3}
SETS = [a for k, v in SMALL.items() for a in ("--set", f"{k}={v}")]
TESS = {"segments": 8, "lenslet_segments": 4, "prism_segments": 16}
EPS64, EPS32 = np.finfo(np.float64).eps, 2.0**-24  # float64 machine epsilon; float32 unit roundoff
# Lenslet index, curvature and conic, and the display gap (a z-shift). AD is compared over
# the samples the difference keeps (ad_kept), at steps capped to move hits by 0.25 px.
# F1b.thickness (a relay z-shift, 366 flagged samples) is not here: 4.2 % at these sample
# counts (docs/differentiable-rendering.md).
INTERIOR = ["L1.index", "L1.curvature", "L1.conic", "object.distance"]
#: The default run checks a surface shape and the display gap (the float32 case whose
#: difference is noisiest); ``-m slow`` checks every parameter above.
INTERIOR_DEFAULT = ["L1.curvature", "object.distance"]


@pytest.fixture(scope="module")
def coaxial():
    from lfsim.design.overrides import load_with_overrides

    return load_with_overrides(ROOT / "scenes/ini_coaxial.toml", SMALL)


@pytest.fixture(scope="module")
def geometry(coaxial):
    from lfsim.render.mesh_ad import MeshGeometry

    v = coaxial.system.parameter_values(coaxial.system.primary_wavelength_nm)
    return MeshGeometry(coaxial, v, tessellation=TESS), v


@pytest.fixture(scope="module")
def mesh_setup(coaxial):
    from scipy.ndimage import gaussian_filter

    from lfsim.content import load_content
    from lfsim.render import gradcheck as gc
    from lfsim.render.diff_render import AnalyticRenderer, ViewSpec
    from lfsim.render.mesh_ad import MeshRenderer

    content = load_content(ROOT / "scenes/fig9_wall.toml")
    view = ViewSpec(resolution=(64, 36), spp=8, focus_mm=[1000.0])
    ei = AnalyticRenderer(coaxial, view, content=content).display
    # As `lfsim gradcheck --optics mesh`: elemental images blurred by 2 px (float32 steps).
    s = gc.MESH_DISPLAY_BLUR
    r = MeshRenderer(coaxial, view, display=gaussian_filter(ei, (s, s, 0), mode="nearest"))
    targets = gc.natural_targets(r, content, spp=32)
    return r, gc.RenderLoss(r, targets)


def _with_gap(g, v, gap):
    """The vector ``v`` with another display gap (the display plane does not enter the optics meshes)."""
    v = np.array(v, dtype=np.float64)
    v[g.index["object.distance"]] = gap
    return v


def test_drjit_vertices_equal_the_numpy_tessellation(geometry):
    g, v = geometry
    P = g.params_for(_with_gap(g, v, 7.0))
    checked = 0
    for part, (V, N) in zip(g.parts, g.numpy_geometry(P)):
        np.testing.assert_allclose(V, part.mesh.vertices, rtol=0, atol=1e-9, err_msg=part.mesh.name)
        if part.mesh.normals is not None:
            np.testing.assert_allclose(N, part.mesh.normals, rtol=0, atol=1e-12, err_msg=part.mesh.name)
            checked += 1
    assert checked >= 20  # every lens and lenslet face


@pytest.mark.parametrize("name,h", [("L1.curvature", 1e-6), ("L1.conic", 1e-6), ("L2.A4", 1e-6),
                                    ("F1b.thickness", 1e-6), ("A1a.tilt_x", 1e-5), ("E1a.decenter_y", 1e-6),
                                    ("mla.pitch_x", 1e-7)])
def test_vertex_derivatives_match_numpy_central_differences(geometry, coaxial, name, h):
    from lfsim.render.optics_scene import optics_parts

    g, v = geometry
    i = g.index[name]
    T = g.T
    t = dr.zeros(T.Float, 1)
    dr.enable_grad(t)
    e = np.zeros(len(g.names))
    e[i] = 1.0
    P = g.params_for(_with_gap(g, v, 7.0)) + t * T.Float(e)
    geo = g.geometry(P)
    # Mounts (absorbing rings outside the clear apertures) move rigidly with their
    # surface's frame; their inner edge keeps the nominal sag, so they are left out.
    keep = [k for k, p in enumerate(g.parts) if p.mesh.role != "mount"]
    flat = [c for k in keep for c in ([geo[k][0]] + ([geo[k][1]] if geo[k][1] is not None else []))]
    dr.forward_from(t, dr.ADFlag.ClearNone)  # keep the gradients of interior nodes (vertices feed copies)
    ad = [np.stack([np.asarray(dr.grad(a[c]), dtype=np.float64) for c in range(3)], 1) for a in flat]
    parts = {}
    for s in (-1, 1):
        vv = v.copy()
        vv[i] += s * h
        parts[s] = optics_parts(coaxial, vv, **TESS)
    fd = []
    for k in keep:
        pm, pp = parts[-1][k], parts[1][k]
        fd.append((pp.mesh.vertices - pm.mesh.vertices) / (2 * h))
        if pp.mesh.normals is not None:
            fd.append((pp.mesh.normals - pm.mesh.normals) / (2 * h))
    assert len(fd) == len(ad)
    scale = max(np.abs(f).max() for f in fd)
    assert scale > 0, name
    # Noise of the difference: float64 rounding of vertices as large as vmax (~345 mm), about
    # EPS64 · vmax / h; truncation (h² times the third derivative) is far below it (a second
    # step 2h moves the difference by < 5e-9 of the largest derivative). Bound 4x that (measured
    # errors: <= 0.06 of the rounding estimate), at most the 1e-5 of the largest derivative
    # (+ 1e-7) that a wrong derivative must exceed.
    vmax = max(np.abs(parts[sgn][k].mesh.vertices).max() for sgn in (-1, 1) for k in keep)
    atol = 4.0 * EPS64 * vmax / h
    assert atol <= 1e-5 * scale + 1e-7, (name, atol, scale)
    for a, f in zip(ad, fd):
        assert np.all(np.isfinite(a))
        np.testing.assert_allclose(a, f, rtol=0, atol=atol, err_msg=name)


#: Render seeds the AD-against-difference check is averaged over. One 64×36, 8-spp render's
#: discrepancy scatters from seed to seed far beyond the spread of its own difference steps
#: (object.distance: 1 % to 11 % over seeds 0-6; L1.curvature: 0.2 % to 2.6 %): every hit
#: moves across the bilinear kinks of the display image, and where the samples fall against
#: the texel grid is the seed's. The mean over seeds, with its own standard error, is the check.
AD_SEEDS = (0, 1, 2, 3)


@pytest.mark.parametrize("names", [pytest.param(INTERIOR_DEFAULT, id="default"),
                                   pytest.param(INTERIOR, id="all", marks=pytest.mark.slow)])
def test_render_ad_matches_central_differences(coaxial, mesh_setup, names):
    from dataclasses import replace

    from lfsim.render import gradcheck as gc
    from lfsim.render.mesh_ad import MeshRenderer

    r0, loss0 = mesh_setup
    rows = {n: [] for n in names}
    for seed in AD_SEEDS:
        r = r0 if seed == r0.view.seed else MeshRenderer(coaxial, replace(r0.view, seed=seed), display=r0.display)
        targets = [t.reshape(r.H, r.W, -1) for t in loss0.targets_np]
        doc = gc.gradcheck(r, targets, names, rel_step=gc.MESH_REL_STEP, edge_rel_step=gc.MESH_EDGE_REL_STEP,
                           fd_points=gc.MESH_FD_POINTS)
        print(gc.table(doc))
        for p in doc["params"]:
            assert p["fd_step"] <= gc.fd_step(p["name"], p["value"], p["unit"], gc.MESH_REL_STEP), p
            assert np.isfinite(p["ad"]) and p["ad"] != 0.0, p
            assert p["forward_reverse_rel"] <= gc.FORWARD_REVERSE_TOL["mesh"], p
            rows[p["name"]].append((p["ad_kept"], p["fd_interior"]))
    for name, vals in rows.items():
        ad, fd = np.array(vals).T
        diff = ad - fd
        # 2 % for AD's float32 arithmetic and the slope's truncation, plus three standard errors
        # of the mean discrepancy over the seeds (from their own scatter).
        sem = diff.std(ddof=1) / np.sqrt(len(diff))
        err = abs(diff.mean()) / abs(fd.mean())
        assert err <= 0.02 + 3.0 * sem / abs(fd.mean()), (name, err, sem / abs(fd.mean()), vals)
        assert sem / abs(fd.mean()) < 0.05, (name, vals)  # the check is not drowned in its scatter


def test_forward_and_reverse_mode_agree_and_no_nan(mesh_setup):
    from lfsim.render import gradcheck as gc

    r, loss = mesh_setup
    names = ["L1.index", "L1.curvature", "L2.A4", "F1b.thickness", "A1a.tilt_x", "E1a.decenter_y",
             "TL.power", "object.distance", "mla.pitch_x", "VW.tilt_y"]
    idx = [r.index[n] for n in names]
    _, g = gc.gradient(loss, wrt=idx)
    assert np.all(np.isfinite(g))
    rng = np.random.default_rng(5)
    v = np.zeros(len(r.names))
    v[idx] = rng.standard_normal(len(idx)) * 1e-3
    rev = float(g @ v)
    fwd = gc.directional(loss, v)
    assert np.isfinite(fwd) and fwd != 0.0
    # Float32 (Mitsuba) renders: the two modes sum the same terms in another order, a rounding
    # random walk of about EPS32 · sqrt(samples) of the result (136 EPS32 here; measured 13 EPS32).
    # Bound 4x that, at most gradcheck's forward/reverse tolerance for the mesh path (1e-4).
    tol = 4.0 * EPS32 * np.sqrt(r.n_pixels * r.spp)
    assert tol <= gc.FORWARD_REVERSE_TOL["mesh"], tol
    assert abs(rev - fwd) <= tol * abs(fwd), (rev, fwd, tol)


def _fresnel_unpolarized(n1, n2, cos_i):
    """Closed-form unpolarized Fresnel reflectance from medium n1 into n2 (numpy; 1 on TIR)."""
    cos_i = np.abs(cos_i)
    sin2_t = (n1 / n2) ** 2 * (1.0 - cos_i ** 2)
    cos_t = np.sqrt(np.maximum(1.0 - sin2_t, 0.0))
    rs = (n1 * cos_i - n2 * cos_t) / (n1 * cos_i + n2 * cos_t)
    rp = (n2 * cos_i - n1 * cos_t) / (n2 * cos_i + n1 * cos_t)
    return np.where(sin2_t >= 1.0, 1.0, 0.5 * (rs ** 2 + rp ** 2))


def test_fresnel_weight_is_the_unpolarized_transmittance():
    """``fresnel = true``: refraction weight 1 − F (closed form), weight 1 and reflection on TIR."""
    from lfsim.render import bsdfs

    mi = bsdfs.register()
    n_int, n_ext = 1.65113, 1.0
    b = mi.load_dict({"type": "lfsim_interface", "int_ior": n_int, "ext_ior": n_ext, "fresnel": True})
    # From outside (cos > 0, ext → int) and from inside (cos < 0), up to and past TIR (37.3°).
    ang = np.radians([0.0, 20.0, 45.0, 70.0, 85.0, 0.0, 20.0, 30.0, 36.0, 50.0])
    side = np.array([1, 1, 1, 1, 1, -1, -1, -1, -1, -1], dtype=np.float64)
    cos = side * np.cos(ang)
    si = dr.zeros(mi.SurfaceInteraction3f, len(cos))
    si.wi = mi.Vector3f(mi.Float(np.sin(ang).astype(np.float32)), mi.Float(0.0), mi.Float(cos.astype(np.float32)))
    si.sh_frame = mi.Frame3f(mi.Vector3f(0.0, 0.0, 1.0))
    bs, w = b.sample(mi.BSDFContext(), si, mi.Float(0.5), mi.Point2f(0.5, 0.5))
    w = np.asarray(w[0], dtype=np.float64)
    n1 = np.where(side > 0, n_ext, n_int)
    n2 = np.where(side > 0, n_int, n_ext)
    F = _fresnel_unpolarized(n1, n2, cos)
    tir = F == 1.0
    assert tir.sum() == 1 and tir[-1]
    # Float32 weights <= 1: 32 EPS32 (2e-6), 10x the 3 EPS32 measured next to TIR (36°), where
    # the rounding of cos θ is amplified most.
    np.testing.assert_allclose(w[~tir], 1.0 - F[~tir], rtol=0, atol=32 * EPS32)
    assert w[tir][0] == 1.0
    wo_z = np.asarray(bs.wo.z, dtype=np.float64)
    assert np.all(np.sign(wo_z[~tir]) == -side[~tir]) and wo_z[tir][0] < 0  # refracted through / reflected back


@pytest.fixture(scope="module")
def fresnel_setup(coaxial, mesh_setup):
    from lfsim.render import gradcheck as gc
    from lfsim.render.mesh_ad import MeshRenderer

    r0, loss0 = mesh_setup
    r = MeshRenderer(coaxial, r0.view, display=r0.display, fresnel=True)
    return r, gc.RenderLoss(r, [t.reshape(r.H, r.W, -1) for t in loss0.targets_np])


def test_fresnel_interface_darkens_the_image(mesh_setup, fresnel_setup):
    """Weight 1 − F: about 4-6 % lost per air-glass face."""
    r0, _ = mesh_setup
    r, _ = fresnel_setup
    img, img1 = r.image_numpy(), r0.image_numpy()
    assert np.all(np.isfinite(img))
    ratio = img.mean() / img1.mean()
    # Noise of the ratio: both means' standard errors from their pixels' spread (an upper bound:
    # the spread includes the image's structure; ~0.011 here). The ratio is inside (0.2, 0.8) by
    # more than 4x that.
    noise = ratio * np.hypot(*(np.std(x) / (np.sqrt(x.size) * x.mean()) for x in (img, img1)))
    assert 0.2 + 4.0 * noise < ratio < 0.8 - 4.0 * noise, (ratio, noise)


@pytest.mark.slow
def test_fresnel_index_gradient_forward_reverse_and_central_differences(mesh_setup, fresnel_setup):
    """With fresnel on, d(loss)/d(index) goes through the refraction and the 1 − F weight:
    forward = reverse mode, and both match the interior central difference (AD over the
    samples the difference keeps). A second scene in the process (``mesh_setup``, already
    differentiated) used to break forward mode (isolate_grad error, see MeshScene.release)."""
    from lfsim.render import gradcheck as gc

    mesh_setup[0].image_numpy()  # the other scene was used last
    r, loss = fresnel_setup
    doc = gc.gradcheck(r, [t.reshape(r.H, r.W, -1) for t in loss.targets_np], ["L1.index"],
                       rel_step=gc.MESH_REL_STEP, edge_rel_step=gc.MESH_EDGE_REL_STEP, fd_points=gc.MESH_FD_POINTS)
    print(gc.table(doc))
    p = doc["params"][0]
    assert np.isfinite(p["ad"]) and p["ad"] != 0.0, p
    assert p["forward_reverse_rel"] <= gc.FORWARD_REVERSE_TOL["mesh"], p
    assert p["interior_rel_err"] <= 0.02 + 3.0 * p["interior_noise_rel"], p


def test_gradcheck_cli_mesh_path(tmp_path):
    cmd = [sys.executable, "-m", "lfsim.cli", "gradcheck", "scenes/ini_coaxial.toml", "--optics", "mesh",
           "--param", "L1.index", "--resolution", "24,14", "--spp", "4", "--focus-mm", "1000", *SETS, "--json"]
    out = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert out.returncode in (0, 1), out.stderr
    doc = json.loads(out.stdout)
    assert doc["path"] == "mesh" and doc["fd_points"] == 4 and doc["precision"] == "float32"
    p = doc["params"][0]
    assert {"name", "value", "ad", "fd", "rel_err", "boundary", "fd_interior", "edge_samples"} <= set(p)
    assert isinstance(p["boundary"], bool) and np.isfinite(p["ad"])
