"""The mechanical package of an InI design (lfsim.ini.package) against closed forms and the tracer's path.

Small coaxial designs written here (an ideal MLA and eyepiece, then a real
biconvex lens W and a meniscus M before the viewing window) have every figure
by hand from their thicknesses, radii and semi-diameters; the shipped
ini_*.toml designs are checked for completeness, against their closed forms
(coaxial) and against an independent trace of the same rays with the tracer's
own recorded global path (tilted, globally placed prism faces).
"""

from __future__ import annotations

import json
import math
import tomllib

import numpy as np
import pytest
from conftest import SCENES
from helpers import SMALL
from helpers import small_ini as _small

import lfsim
from lfsim.ini.model import IniModel
from lfsim.ini.package import package, ray_set
from lfsim.optics.components import components

SHIPPED = sorted(SCENES.glob("ini_*.toml"))

KEYS = ("track_mm", "max_clear_diameter_mm", "clear_diameters_mm", "tunable_clear_aperture_mm",
        "tunable_footprint_mm", "bounding_box_mm", "bounding_box_min_mm", "bounding_box_max_mm", "prism_box_mm",
        "prism_footprint_box_mm", "min_center_thickness_mm", "min_edge_thickness_mm", "min_prism_thickness_mm",
        "eye_relief_mm")

G = SMALL["g"]  # display gap
T_VW = SMALL["t_vw"]  # M2 -> VW


def _design(text: str):
    return lfsim.Design.from_dict(tomllib.loads(text))


def sphere_sag(radius: float, r: float) -> float:
    """Sag of a sphere of (signed) radius at height r."""
    return radius - math.copysign(math.sqrt(radius * radius - r * r), radius)


@pytest.fixture(scope="module")
def small():
    model = IniModel(_design(_small()))
    return model, package(model)


# ------------------------------------------------------------------ shipped designs
def test_shipped_designs_are_discovered():
    names = {p.stem for p in SHIPPED}
    assert {"ini_ideal", "ini_coaxial", "ini_freeform", "ini_freeform_optimized"} <= names


@pytest.mark.parametrize("path", SHIPPED, ids=[p.stem for p in SHIPPED])
def test_keys_present_and_finite_on_shipped_designs(path):
    design = lfsim.load(path)
    model = IniModel(design)
    p = package(model)
    json.dumps(p, allow_nan=False)  # JSON-ready, no NaN or inf
    assert set(KEYS) <= set(p)
    has_prism = any(c.kind == "prism" for c in components(design.system))
    has_tunable = design.ini.tunable is not None
    optional = {  # key -> whether the figure applies to this design
        "tunable_clear_aperture_mm": has_tunable, "tunable_footprint_mm": has_tunable,
        "prism_box_mm": has_prism, "prism_footprint_box_mm": has_prism, "min_prism_thickness_mm": has_prism,
        "max_clear_diameter_mm": bool(p["clear_diameters_mm"]),
    }
    for key in KEYS:
        v = p[key]
        if key in optional and not optional[key]:
            assert v is None, key
            continue
        if key in ("min_center_thickness_mm", "min_edge_thickness_mm") and v is None:
            # only a design without any glass element (all ideal lenses)
            assert all(s.interaction != "refract" for s in design.system.surfaces), key
            continue
        assert v is not None, key
        vals = list(v.values()) if isinstance(v, dict) else (v if isinstance(v, list) else [v])
        assert all(isinstance(x, float) and math.isfinite(x) for x in vals), (key, v)
    assert p["rays_failed"] == 0 and p["rays_traced"] == 9 * 9 * 5 * len(model.depths)
    assert np.allclose(np.subtract(p["bounding_box_max_mm"], p["bounding_box_min_mm"]), p["bounding_box_mm"])
    assert p["eye_relief_mm"] > 0 and p["track_mm"] > 0
    # the display plane z = -g bounds the box from below (light travels +z from it)
    assert p["bounding_box_min_mm"][2] == pytest.approx(-model.g, abs=1e-12)
    if p["max_clear_diameter_mm"] is not None:
        assert p["max_clear_diameter_mm"] == max(p["clear_diameters_mm"].values())
    if p["prism_box_mm"] is not None:
        assert all(0 < a <= b + 1e-9 for a, b in zip(p["prism_box_mm"], p["bounding_box_mm"]))


# ------------------------------------------------------------------ closed forms
def test_track_of_coaxial_designs_is_the_axial_length():
    """On-axis chief ray of the central lenslet: display gap + every axial thickness up to the VW."""
    for text_or_path in (_small(), SCENES / "ini_coaxial.toml", SCENES / "ini_ideal.toml"):
        design = _design(text_or_path) if isinstance(text_or_path, str) else lfsim.load(text_or_path)
        model = IniModel(design)
        vw = design.ini.viewing_window
        raw = tomllib.loads(text_or_path if isinstance(text_or_path, str) else text_or_path.read_text())
        closed = raw["object"]["distance"] + sum(s.get("thickness", 0.0) for s in raw["surfaces"][:vw])
        assert package(model)["track_mm"] == pytest.approx(closed, abs=1e-9)
    assert closed == pytest.approx(4.5 + 46.75 + 31.0)  # ini_ideal


def test_edge_thickness_is_the_sphere_sag_closed_form(small):
    """W (R1 = +100, R2 = -100, 3 mm, semi-diameter 12) is the thinnest edge: 3 - 2 sag(12);
    M (R1 = 60, R2 = 80, 2 mm, semi-diameter 10) the thinnest centre."""
    _, p = small
    e_w = 3.0 - sphere_sag(100.0, 12.0) + sphere_sag(-100.0, 12.0)
    e_m = 2.0 - sphere_sag(60.0, 10.0) + sphere_sag(80.0, 10.0)
    assert e_w < e_m
    assert p["min_edge_thickness_mm"] == pytest.approx(e_w, abs=1e-12)
    assert p["min_center_thickness_mm"] == pytest.approx(2.0, abs=1e-12)
    assert p["min_prism_thickness_mm"] is None and p["prism_box_mm"] is None
    assert p["prism_footprint_box_mm"] is None


@pytest.mark.parametrize("l1_thickness", [None, 1.1])
def test_lenslet_edge_thickness_at_the_aperture_corner(l1_thickness):
    """ini_coaxial: the minimum over the relay's elements (sphere sags at the larger semi-diameter)
    and the aspheric lenslet (even-asphere sags at the corner of its 1 x 1 mm aperture); with the
    lenslet 1.1 mm thick its corner is the thinnest edge of the design."""
    raw = tomllib.loads((SCENES / "ini_coaxial.toml").read_text())
    if l1_thickness is not None:
        raw["surfaces"][0]["thickness"] = l1_thickness
    l1, l2 = raw["surfaces"][0], raw["surfaces"][1]

    def asag(s, r):
        c, k = s["curvature"], s["conic"]
        return (c * r * r / (1 + math.sqrt(1 - (1 + k) * c * c * r * r))
                + s["asphere"]["A4"] * r ** 4 + s["asphere"]["A6"] * r ** 6)

    r = math.hypot(0.5, 0.5)
    lenslet_edge = l1["thickness"] - asag(l1, r) + asag(l2, r)
    relay = []
    surf = raw["surfaces"]
    for a, b in zip(surf[:-1], surf[1:]):
        if "radius" in a and "radius" in b and a.get("material", "air") != "air":
            h = max(a["semi_diameter"], b["semi_diameter"])
            relay.append(a["thickness"] - sphere_sag(a["radius"], h) + sphere_sag(b["radius"], h))
    assert (lenslet_edge < min(relay)) == (l1_thickness is not None)
    p = package(IniModel(lfsim.Design.from_dict(raw)))
    assert p["min_edge_thickness_mm"] == pytest.approx(min([lenslet_edge] + relay), abs=1e-9)
    assert p["min_center_thickness_mm"] == pytest.approx(l1["thickness"], abs=1e-12)


def test_bounding_box_by_hand(small):
    """x, y: the largest semi-diameter (W, 12 mm); z: from the display (z = -g) to M2's rim,
    which bends toward the eye (R = +80: vertex + sag(10))."""
    _, p = small
    z_m2 = 46.75 + 0.0 + 10.0 + 3.0 + 4.0 + 2.0
    z_max = z_m2 + sphere_sag(80.0, 10.0)
    assert p["bounding_box_min_mm"] == pytest.approx([-12.0, -12.0, -G], abs=1e-9)
    assert p["bounding_box_max_mm"] == pytest.approx([12.0, 12.0, z_max], abs=1e-9)
    assert p["bounding_box_mm"] == pytest.approx([24.0, 24.0, z_max + G], abs=1e-9)
    assert p["clear_diameters_mm"] == {"W1": 24.0, "W2": 24.0, "M1": 20.0, "M2": 20.0}
    assert p["max_clear_diameter_mm"] == 24.0
    assert p["tunable_clear_aperture_mm"] == 20.0


@pytest.mark.parametrize("ratio", [0.8, 1.2])
def test_bounding_box_of_display_and_lenslet_array(ratio):
    """ini_ideal with 5 mm semi-diameters on TL and EP: in x the box is the wider of the display's
    EI grid (17 EIs of the Eq. (2) pitch, centred: 8.5 p_EI, the largest over the CDP states) and
    the lenslet array's outer apertures (8.5 mm); p_EI > 1 at z_xp = 0.8 f_ep, < 1 at 1.2 f_ep.
    In y the ideal lenses' 5 mm; in z the display plane and the flat ideal lenses at 46.75 mm."""
    from lfsim.ini import ini_first_order

    data = tomllib.loads((SCENES / "ini_ideal.toml").read_text())
    z_xp = ratio * 31.0
    data["surfaces"][2]["thickness"] = z_xp
    data["surfaces"][1]["semi_diameter"] = data["surfaces"][2]["semi_diameter"] = 5.0
    model = IniModel(lfsim.Design.from_dict(data))
    p_ei = max(ini_first_order(1.0, 4.5, 1.0 / (1.0 / 31.0 + phi), z_xp, 17, 9, f_mla=3.5, d_mla_ep=46.75).p_ei
               for phi in model.tl_power)
    assert (p_ei > 1.0) == (ratio < 1.0)
    half_x = max(8.5 * p_ei, 8.5)
    half_y = max(4.5 * p_ei, 4.5, 5.0)
    p = package(model)
    assert p["bounding_box_min_mm"] == pytest.approx([-half_x, -half_y, -4.5], abs=1e-9)
    assert p["bounding_box_max_mm"] == pytest.approx([half_x, half_y, 46.75], abs=1e-9)


def test_eye_relief_by_hand():
    """A flat last surface T_VW in front of the VW: the eye relief is T_VW for every ray. Curved
    toward the eye (R = +80), the rim comes closer: T_VW - sag(10) <= eye relief < T_VW."""
    flat = package(IniModel(_design(_small(None))))
    assert flat["eye_relief_mm"] == pytest.approx(T_VW, abs=1e-9)
    curved = package(IniModel(_design(_small(80.0))))
    assert T_VW - sphere_sag(80.0, 10.0) <= curved["eye_relief_mm"] < T_VW - 0.1
    assert package(IniModel(lfsim.load(SCENES / "ini_ideal.toml")))["eye_relief_mm"] == pytest.approx(31.0)


def test_figures_follow_the_model_values():
    """An optimizer's trial point (IniModel(values=...)): 0.5 mm more air after W moves M and the VW
    by 0.5 mm: the track and the box grow by 0.5 mm, the eye relief (flat M2) and the thicknesses
    stay; a more curved M1 thins M's edge (the thinnest, M2 being flat) by the sag difference."""
    model = IniModel(_design(_small(None)))
    p = package(model)
    v = model.values0.copy()
    v[model.tracer.index["W2.thickness"]] += 0.5
    q = package(IniModel(model.design, values=v))
    assert q["track_mm"] == pytest.approx(p["track_mm"] + 0.5, abs=1e-9)
    assert q["bounding_box_max_mm"][2] == pytest.approx(p["bounding_box_max_mm"][2] + 0.5, abs=1e-9)
    assert q["eye_relief_mm"] == pytest.approx(T_VW, abs=1e-9)
    assert p["min_edge_thickness_mm"] == pytest.approx(2.0 - sphere_sag(60.0, 10.0), abs=1e-12)
    assert q["min_edge_thickness_mm"] == pytest.approx(p["min_edge_thickness_mm"], abs=1e-12)
    v[model.tracer.index["M1.curvature"]] = 1.0 / 50.0
    r = package(IniModel(model.design, values=v))
    assert r["min_edge_thickness_mm"] == pytest.approx(2.0 - sphere_sag(50.0, 10.0), abs=1e-12)


@pytest.mark.parametrize("d", [0.8, -0.9])
def test_decentred_lens_edge_and_clear_diameter(d):
    """W (R = ±100, 3 mm, semi-diameter 12) decentred as a whole by d in y: its blank about the
    relay axis must hold the moved apertures, radius 12 + |d| (clear diameter 2(12 + |d|)), and
    its thinnest rim point lies 12 + 2|d| from the lens's own axis: 3 − 2 sag(12 + 2|d|) (or M's
    edge, 2 − sag_60(10), where that is thinner)."""
    model = IniModel(_design(_small(None)))
    v = model.values0.copy()
    for name in ("W1", "W2"):
        v[model.tracer.index[f"{name}.decenter_y"]] = d
    p = package(IniModel(model.design, values=v))
    r = 12.0 + 2.0 * abs(d)
    e_w = 3.0 - sphere_sag(100.0, r) + sphere_sag(-100.0, r)
    assert p["min_edge_thickness_mm"] == pytest.approx(min(e_w, 2.0 - sphere_sag(60.0, 10.0)), abs=1e-10)
    assert p["clear_diameters_mm"]["W1"] == pytest.approx(2.0 * (12.0 + abs(d)), abs=1e-12)
    assert p["clear_diameters_mm"]["W2"] == pytest.approx(2.0 * (12.0 + abs(d)), abs=1e-12)
    assert p["clear_diameters_mm"]["M1"] == 20.0


@pytest.mark.parametrize("tilt", [2.0, -3.0])
def test_wedged_lens_edge(tilt):
    """W's front face made flat and tilted about its vertex (a wedge): along the axis the flat face
    lies y·tan θ from its vertex plane, so the thinnest rim point (semi-diameter 12) is
    3 + sag_W2(12) − 12 tan|θ|. The back face alone decentred by 0.5 (a wedge again): the rim
    about the relay axis is 12.5, 13 from the back face's axis at its thinnest."""
    from lfsim.optics.solids import edge_thickness, glass_pairs

    model = IniModel(_design(_small(None)))
    tr, ix = model.tracer, model.tracer.index
    i, j, rad = glass_pairs(model.system, tr.names, model.values0, model.spec.viewing_window)[0]
    assert (model.system.surfaces[i].name, model.system.surfaces[j].name, rad) == ("W1", "W2", 12.0)
    v = model.values0.copy()
    v[ix["W1.curvature"]] = 0.0
    v[ix["W1.tilt_x"]] = tilt
    e = 3.0 + sphere_sag(-100.0, 12.0) - 12.0 * math.tan(math.radians(abs(tilt)))
    assert edge_thickness(tr, v, i, j, rad) == pytest.approx(e, abs=1e-10)
    w = model.values0.copy()
    w[ix["W1.curvature"]] = 0.0
    w[ix["W2.decenter_y"]] = 0.5
    assert edge_thickness(tr, w, i, j, rad) == pytest.approx(3.0 + sphere_sag(-100.0, 13.0), abs=1e-10)


@pytest.mark.parametrize("d", [0.0, 0.8])
def test_element_section_is_the_lens_as_built(d):
    """The layout's section of W (R = +-100, 3 mm, semi-diameter 12) decentred as a whole by d:
    its faces are the spheres about the moved vertex, sampled across the rim about the relay
    axis (radius 12 + |d|), and the ends are the rim thicknesses at +-90 deg (the edge)."""
    from lfsim.optics.solids import element_section, glass_pairs, rim_thickness

    model = IniModel(_design(_small(None)))
    tr = model.tracer
    v = model.values0.copy()
    for name in ("W1", "W2"):
        v[tr.index[f"{name}.decenter_y"]] = d
    i, j, rad = glass_pairs(model.system, tr.names, v, model.spec.viewing_window)[0]
    front, back = element_section(tr, v, i, j, rad, points=33)
    assert np.isfinite(front).all() and np.isfinite(back).all()
    R_rim = 12.0 + abs(d)
    np.testing.assert_allclose(front[:, 1], np.linspace(-R_rim, R_rim, 33), atol=1e-12)
    np.testing.assert_allclose(back[:, 1], front[:, 1], atol=1e-12)
    np.testing.assert_allclose(front[:, 0], 0.0, atol=1e-12)
    z0 = front[16, 2]  # the vertex plane of W1 (y = 0 is on the lens axis only when d = 0)
    h = front[:, 1] - d
    np.testing.assert_allclose(front[:, 2] - z0, [sphere_sag(100.0, y) - sphere_sag(100.0, d) for y in h],
                               atol=1e-9)
    np.testing.assert_allclose(back[:, 2] - front[:, 2],
                               [3.0 - sphere_sag(100.0, y) + sphere_sag(-100.0, y) for y in h], atol=1e-9)
    rim = rim_thickness(tr, v, i, j, rad, points=4)[0]  # at 0, 90, 180, 270 deg
    assert back[-1, 2] - front[-1, 2] == pytest.approx(rim[1], abs=1e-9)
    assert back[0, 2] - front[0, 2] == pytest.approx(rim[3], abs=1e-9)


def test_edge_thickness_batches_parameter_vectors():
    """(B, n) parameter vectors give the B edge thicknesses of one launch, each as alone."""
    from lfsim.optics.solids import edge_thickness, glass_pairs

    model = IniModel(_design(_small(None)))
    tr = model.tracer
    i, j, rad = glass_pairs(model.system, tr.names, model.values0, model.spec.viewing_window)[0]
    V = np.repeat(model.values0[None], 3, axis=0)
    V[1, tr.index["W1.decenter_y"]] = 0.3
    V[2, tr.index["W2.tilt_x"]] = 1.0
    batch = edge_thickness(tr, V, i, j, rad)
    assert batch.shape == (3,)
    for b in range(3):
        assert batch[b] == pytest.approx(edge_thickness(tr, V[b], i, j, rad), abs=1e-12)
    assert len(set(np.round(batch, 9))) == 3


# ------------------------------------------------------------ against the tracer's path
@pytest.mark.parametrize("name", ["ini_freeform", "ini_coaxial"])
def test_against_the_tracers_recorded_path(name):
    """The same aimed rays traced by the tracer (trace_numpy, record=True: global hit points):
    the chief ray's unfolded length, the nearest hit on the last optical surface along the VW
    axis, the tunable lens's footprint and the prism faces' hits inside the prism box."""
    from lfsim.ini.subsystems import _aim
    from lfsim.optics.solids import prisms

    design = lfsim.load(SCENES / f"{name}.toml")
    model = IniModel(design)
    p = package(model)
    surf, vw, ti = design.system.surfaces, design.ini.viewing_window, design.ini.tunable
    s, m, n, rho, k, lens = ray_set(model)
    s_r, m_r, n_r, k_r, t, _ = _aim(model, s, m, n, rho, k, 30)
    frames = model.tracer.frames_numpy(model.tracer.params(values=model.values0))
    R_vw, o_vw = frames[vw]
    R_t, o_t = frames[ti]
    last = max(i for i in range(vw) if surf[i].interaction not in ("none", "break"))
    real = [i for i in range(vw + 1) if surf[i].interaction not in ("none", "break") or i == vw]
    relief, foot, track = np.inf, 0.0, None
    faces = sorted({i for run in prisms(design.system) for i in run})
    lo, hi = np.full(3, np.inf), np.full(3, -np.inf)
    k_mid = len(model.depths) // 2
    for kk in range(len(model.depths)):
        q = np.nonzero(k_r == kk)[0]
        o = np.column_stack([s_r[q], np.full(len(q), -model.g)])
        d = np.column_stack([t[q], np.ones(len(q))])
        r = model.tracer.trace_numpy(o, d, lenslet=np.column_stack([m_r[q], n_r[q]]), record=True,
                                     values=model.values(kk))
        assert np.all(r["status"] == 0)
        path = r["path"]
        relief = min(relief, float(np.min(-(path[last] - o_vw) @ R_vw[:, 2])))
        loc = (path[ti] - o_t) @ R_t  # R^T (p - o)
        foot = max(foot, 2.0 * float(np.max(np.hypot(loc[:, 0], loc[:, 1]))))
        for i in faces:
            lo, hi = np.minimum(lo, path[i].min(axis=0)), np.maximum(hi, path[i].max(axis=0))
        if kk == k_mid:
            j = [a for a, i in enumerate(q) if m_r[i] == model.arr.m // 2 and n_r[i] == model.arr.n // 2
                 and not rho[i].any()][0]  # the first one: the EI-centre field
            pts = np.concatenate([[[*s_r[q[j]], -model.g]], path[real, j]])
            track = float(np.sum(np.linalg.norm(np.diff(pts, axis=0), axis=1)))
    assert p["track_mm"] == pytest.approx(track, abs=1e-9)
    assert p["eye_relief_mm"] == pytest.approx(relief, abs=1e-9)
    assert p["tunable_footprint_mm"] == pytest.approx(foot, abs=1e-9)
    if faces:  # every ray hit on a prism face lies inside the boxes (sampled apertures: 3 µm)
        assert np.all(hi - lo <= np.array(p["prism_box_mm"]) + 0.005)
        # the footprint box is exactly the extent of those hits
        assert np.allclose(p["prism_footprint_box_mm"], hi - lo, rtol=0, atol=1e-9)
        assert np.all(lo >= np.array(p["bounding_box_min_mm"]) - 0.005)
        assert np.all(hi <= np.array(p["bounding_box_max_mm"]) + 0.005)


# ------------------------------------------------------------------ lfsim analyze
def test_analyze_writes_package(tmp_path):
    from lfsim.analysis.ini_analysis import analyze

    design = _design(_small())
    doc = analyze(design, tmp_path / "out", stride=(4, 2), plots=False)
    written = json.loads((tmp_path / "out" / "metrics.json").read_text())
    assert written["package"] == doc["package"]
    expect = package(IniModel(design))
    assert written["package"].keys() == expect.keys()
    for key, v in expect.items():
        if isinstance(v, float):
            assert written["package"][key] == pytest.approx(v, abs=1e-9), key
        else:
            assert written["package"][key] == v, key


def test_analyze_prints_the_package_and_first_order(tmp_path, capsys):
    """The console shows what metrics.json holds: each state's FOV and pixel, and the package."""
    import re

    from lfsim.cli import main

    path = tmp_path / "small.toml"
    path.write_text(_small())
    out = tmp_path / "out"
    assert main(["analyze", str(path), "--out", str(out), "--stride", "4,2", "--no-plots"]) == 0
    text = capsys.readouterr().out
    doc = json.loads((out / "metrics.json").read_text())
    p = doc["package"]
    line = next(s for s in text.splitlines() if s.strip().startswith("package:"))
    assert f"track {p['track_mm']:.2f} mm" in line
    assert "box {:.1f} x {:.1f} x {:.1f} mm".format(*p["bounding_box_mm"]) in line
    assert f"eye relief {p['eye_relief_mm']:.2f} mm" in line
    assert f"glass edge >= {math.floor(p['min_edge_thickness_mm'] * 1000 + 1e-9) / 1000:.3f} mm" in line
    for D, b in doc["by_depth"].items():
        fo = b["first_order"]
        row = next(s for s in text.splitlines() if s.strip().startswith(f"CDP {D} D:"))
        fov = re.search(r"FOV ([\d.]+) x ([\d.]+) deg, pixel ([\d.]+) x ([\d.]+)'", row)
        assert fov, row
        assert [float(v) for v in fov.groups()[:2]] == [round(v, 1) for v in fo["fov_deg"]]
        assert [float(v) for v in fov.groups()[2:]] == [round(v, 2) for v in fo["pixel_arcmin"]]
        w = re.search(r"EI-centre chief rays meet the axis ([-+\d.]+) \(x\) / ([-+\d.]+) \(y\) mm from the window", row)
        assert w, row
        assert [float(v) for v in w.groups()] == [round(v, 2) for v in b["viewing_window_real"]["offset_mm"]]
    shape = re.search(r"footprint shape alone .*: max ([\d.]+), mean ([\d.]+)", text)
    assert shape and float(shape.group(1)) == round(doc["summary"]["pa_shape_max"], 4)


def test_the_shipped_wearable_shows_the_papers_field_inside_its_package():
    """scenes/ini_wearable_optimized.toml: 30 x 18 deg at its 1 D state (first order, Eqs. 8-10:
    (lenslets - 1) view steps plus one view of 125 pixels per axis), 17 x 9 lenslets of 125 x 125
    pixels of 8 um, and every package limit of its [optimize.targets]."""
    design = lfsim.load(SCENES / "ini_wearable_optimized.toml")
    model = IniModel(design)
    assert (model.arr.m, model.arr.n) == (17, 9)
    assert design.ini.pixels_per_ei == (125, 125) and design.ini.pixel_pitch == 0.008
    st = model.state(list(model.depths).index(1.0))
    np.testing.assert_allclose(st.fov_deg, (30.0, 18.0), atol=0.15)
    for ax, lenslets in enumerate((17, 9)):  # the field is the views laid side by side
        half = 0.5 * (lenslets - 1) * math.tan(math.radians(st.delta_theta_eic_deg[ax])) \
            + 0.5 * math.tan(math.radians(st.theta_eic_deg[ax]))
        assert st.fov_deg[ax] == pytest.approx(2 * math.degrees(math.atan(half)), abs=1e-9)
    p = package(model)
    t = design.optimize.targets
    assert p["track_mm"] <= t.track_max_mm and p["eye_relief_mm"] >= t.eye_relief_min_mm
    assert all(v <= lim for v, lim in zip(p["bounding_box_mm"], t.box_max_mm))
    assert all(v <= lim for v, lim in zip(p["prism_box_mm"], t.prism_box_max_mm))
    assert p["max_clear_diameter_mm"] <= t.clear_diameter_max_mm
    assert p["tunable_footprint_mm"] <= t.tunable_aperture_mm
    assert min(p["min_edge_thickness_mm"], p["min_center_thickness_mm"]) >= 1.0
