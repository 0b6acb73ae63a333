"""Mesh path against the analytic path with the same eye rays (common random numbers)."""

import numpy as np
import pytest

import lfsim
from lfsim.design.content import content_from_dict
from lfsim.ini.model import model_at_depth
from lfsim.render import mitsuba
from lfsim.render.accuracy import paired_renders, relative_rmse
from lfsim.render.content import scene_dict
from lfsim.render.display import DisplayLayout
from lfsim.render.elemental import elemental_images
from lfsim.render.eye import EyeSpec

WALL = {"objects": [{"corners": [[-400, -300, -600], [400, -300, -600], [-400, 300, -600]],
                     "texture": {"type": "checker", "period_mm": 20.0}}]}


def _pairs(scenes, name, densities, res=(48, 28), spp=8):
    mi = mitsuba()
    model = model_at_depth(lfsim.load(scenes / f"{name}.toml"), 1.0)
    layout = DisplayLayout.from_model(model)
    display = elemental_images(model, mi.load_dict(scene_dict(content_from_dict(WALL))), layout)
    fx, fy = model.state(0).fov_deg
    eye = EyeSpec("ideal", 3.0, 1000.0, (fx, fy), res)
    return paired_renders(model, layout, display, eye, spp=spp, densities=densities)


def test_thin_lens_meshes_equal_the_analytic_path(scenes):
    """Ideal elements: the thin-lens BSDF and the tracer's paraxial surface are the same map."""
    out = _pairs(scenes, "ini_ideal", (0.125,))
    ref = out["analytic"][0]
    assert ref.mean() > 0.1
    assert relative_rmse(out[0.125][0], ref) < 1e-4


def test_mesh_error_falls_with_tessellation(scenes):
    dens = (0.125, 0.25, 1.0)
    out = _pairs(scenes, "ini_coaxial", dens)
    ref = out["analytic"][0]
    e = [relative_rmse(out[S][0], ref) for S in dens]
    assert e[0] > e[1] > e[2]
    assert np.isfinite(e).all()
    # The default tessellation is within 1 % of the analytic path (RMSE / mean).
    assert e[2] < 0.01


def test_tessellation_scales_the_defaults():
    from lfsim.render import meshes

    assert meshes.tessellation() == {"segments": meshes.DEFAULT_SEGMENTS,
                                     "lenslet_segments": meshes.DEFAULT_LENSLET_SEGMENTS,
                                     "prism_segments": meshes.DEFAULT_PRISM_SEGMENTS}
    assert meshes.tessellation(0.5)["segments"] == meshes.DEFAULT_SEGMENTS // 2
    with pytest.raises(ValueError, match="density"):
        meshes.tessellation(0.0)
