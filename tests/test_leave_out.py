"""A design holds only what it declares: a direct-view InI display (display + MLA + eye, no relay,
no aperture array, no tunable lens, no eyepiece) builds, traces, exports and renders with none of
those parts in its tracer kernels or its Mitsuba scenes, and the analytic path exports no meshes."""

from __future__ import annotations

import tomllib
import xml.etree.ElementTree as ET

import numpy as np
import pytest

import lfsim
from lfsim.content import content_from_dict


@pytest.fixture(scope="module")
def direct_view(tmp_path_factory):
    """scenes/direct_view.toml with 5 × 3 lenslets (the same lenslet; a smaller display)."""
    from conftest import SCENES

    data = tomllib.loads((SCENES / "direct_view.toml").read_text())
    data["arrays"]["mla"].update(m=5, n=3)
    p = tmp_path_factory.mktemp("leave_out") / "direct_view_5x3.toml"
    from test_fuzz import to_toml

    p.write_text(to_toml(data))
    return lfsim.load(p)


WALL = {"objects": [{"corners": [[-300, -200, -324], [300, -200, -324], [-300, 200, -324]],
                     "texture": {"type": "checker", "period_mm": 20.0}}]}
MLA = {"L1", "L2"}


def test_builds_and_traces_with_only_the_declared_surfaces(direct_view):
    from lfsim.ini.model import IniModel
    from lfsim.ini.subsystems import sample, trace
    from lfsim.render.analytic import ReverseOptics

    d = direct_view
    assert [s.name for s in d.surfaces] == ["L1", "L2", "VW"]
    assert d.ini.tunable is None and d.ini.stop in d.ini.mla_surfaces  # no tunable lens, no aperture array
    model = IniModel(d)
    assert model.depths == [pytest.approx(3.0865)] and model.tl_power == [None]
    # The compiled tracers (metrics and the reversed render path) hold the MLA and the window only.
    tr = model.tracer
    assert [s.name for s in tr.system.surfaces] == ["L1", "L2", "VW"]
    assert {n.split(".")[0] for n in tr.names} == MLA | {"VW", "object", "mla"}  # no relay, TL or eyepiece numbers
    rev = ReverseOptics(model, 0)  # the render path: eye rays back to the display plane ("end")
    assert [(s.name, s.interaction) for s in rev.system.surfaces] == [
        ("L2", "refract"), ("L1", "refract"), ("end", "none")]
    subs = sample(model, lenslets=[(2, 1), (0, 0), (4, 2)])
    b = trace(model, subs, np.array([[0.0, 0.0], [0.9, 0.0], [0.0, -0.9]]))
    assert np.all(b.ok) and np.all(np.isfinite(b.pos)) and np.all(np.isfinite(b.dir))


def test_exports_only_the_lenslet_array(direct_view, tmp_path):
    from lfsim.render import meshes as M
    from lfsim.render.optics_scene import optics_shapes, write_scene_xml

    comps = M.components(direct_view.system)
    assert [(c.kind, c.surfaces) for c in comps] == [("lenslet_array", [0, 1])]
    shapes = optics_shapes(direct_view, mesh_dir=tmp_path / "ply", **M.tessellation(0.25))
    # The two lenslet faces, the seam walls between the cells and the array's holder: nothing else.
    assert sorted(shapes) == ["L1", "L1_L2_walls", "L1_mount", "L2"]
    assert {k for k, v in shapes.items() if v["bsdf"]["type"] != "diffuse"} == MLA
    xml = write_scene_xml(shapes, tmp_path / "export")
    ids = {e.get("id") for e in ET.parse(xml).getroot()}
    assert ids == set(shapes)
    assert {p.name.split("-")[0] for p in (tmp_path / "export" / "meshes").iterdir()} == set(shapes)


def test_renders_both_paths_with_nothing_else_in_the_scene(direct_view, tmp_path, monkeypatch):
    from lfsim.render import focal_stack as FS
    from lfsim.render import optics_scene
    from lfsim.render.focal_stack import FocalStackSpec, focal_stack

    scenes = []
    real_load = FS.load_scene

    def spy(scene_dict):
        scenes.append(scene_dict)
        return real_load(scene_dict)

    monkeypatch.setattr(FS, "load_scene", spy)
    content = content_from_dict(WALL, "wall")
    cdp_mm = 1000.0 / 3.0865

    def no_meshes(*a, **k):
        raise AssertionError("the analytic path built optics meshes")

    with monkeypatch.context() as m:
        m.setattr(optics_scene, "optics_parts", no_meshes)
        spec = FocalStackSpec(focus_mm=[cdp_mm], cdp_mm=cdp_mm, spp=2, resolution=(24, 16), natural=False)
        doc, stack = focal_stack(direct_view, content, tmp_path / "analytic", spec, log=lambda *a: None)
    # The display and its integrator only (the eye is each render's sensor).
    assert set(scenes[0]) == {"type", "display", "integrator"}
    assert sum("display" in sd for sd in scenes) == 1  # loaded once for the stack
    assert not list((tmp_path / "analytic").rglob("*.ply")) and not list((tmp_path / "analytic").rglob("*.xml"))
    img = stack["images"][("display", cdp_mm)]
    assert np.isfinite(img).all() and img.mean() > 0.05
    scenes.clear()
    spec = FocalStackSpec(focus_mm=[cdp_mm], cdp_mm=cdp_mm, spp=2, resolution=(24, 16), natural=False,
                          optics="mesh", tessellation=0.25)
    doc, stack = focal_stack(direct_view, content, tmp_path / "mesh", spec, log=lambda *a: None)
    extra = set(scenes[0]) - {"type", "display", "integrator"}
    assert sorted(extra) == ["L1", "L1_L2_walls", "L1_mount", "L2"]
    assert np.isfinite(stack["images"][("display", cdp_mm)]).all()
