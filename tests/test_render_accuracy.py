"""Mesh path against the analytic path with the same eye rays (common random numbers)."""

import numpy as np
import pytest

import lfsim
from lfsim.content import content_from_dict, elemental_images, scene_dict
from lfsim.ini.model import model_at_depth
from lfsim.render import mitsuba
from lfsim.render.accuracy import paired_renders, relative_rmse
from lfsim.render.display import DisplayLayout
from lfsim.render.eye import EyeSpec

EPS32 = 2.0**-24  # float32 unit roundoff (Mitsuba's mesh path traces in float32)

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
    # Same rays: only the mesh path's float32 rounding differs (measured: 6e-6 of the mean,
    # ~100 EPS32). Bound 1024 EPS32 (6e-5): 10x that rounding noise.
    assert relative_rmse(out[0.125][0], ref) < 1024 * EPS32


def test_mesh_error_falls_with_tessellation(scenes):
    dens = (0.125, 0.25, 1.0)
    out = _pairs(scenes, "ini_coaxial", dens)
    ref = out["analytic"][0]
    e = [relative_rmse(out[S][0], ref) for S in dens]
    assert np.isfinite(e).all()
    # Noise of each e (a mean over pixels of independent squared differences): its standard
    # error from the pixels' spread, se(e) = e · std(d²) / (2 mean(d²) sqrt(n)) (~0.0014 at S = 1).
    se = [e_ * np.std(d2) / (2 * np.mean(d2) * np.sqrt(d2.size))
          for e_, d2 in ((e_, ((out[S][0] - ref) ** 2).ravel()) for e_, S in zip(e, dens))]
    # Falls by more than 4 x the noise of both errors compared.
    assert all(e[i] - e[i + 1] > 4 * np.hypot(se[i], se[i + 1]) for i in range(2)), (e, se)
    # The default tessellation is within 1 % of the analytic path (RMSE / mean), a bound
    # above 4 x the estimate's noise (ceiling 2 %).
    tol = max(0.01, 4 * se[2])
    assert tol <= 0.02, (tol, se)
    assert e[2] < tol, (e, se)


def test_tessellation_scales_the_defaults():
    from lfsim.render import meshes

    assert meshes.tessellation() == {"segments": meshes.DEFAULT_SEGMENTS,
                                     "lenslet_segments": meshes.DEFAULT_LENSLET_SEGMENTS,
                                     "prism_segments": meshes.DEFAULT_PRISM_SEGMENTS}
    assert meshes.tessellation(0.5)["segments"] == meshes.DEFAULT_SEGMENTS // 2
    with pytest.raises(ValueError, match="density"):
        meshes.tessellation(0.0)
