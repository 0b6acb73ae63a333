"""Display layout, content scenes, elemental images and the analytic reverse path."""


import numpy as np
import pytest

import lfsim
from lfsim.content import content_from_dict, load_content
from lfsim.design.errors import DesignError
from lfsim.ini.model import IniModel, model_at_depth
from lfsim.ini.subsystems import trace_rays
from lfsim.render.analytic import ReverseOptics
from lfsim.render.display import DisplayLayout


@pytest.fixture
def coaxial(scenes):
    return model_at_depth(lfsim.load(scenes / "ini_coaxial.toml"), 1.0)


def test_layout_assigns_pixels_to_the_nearest_elemental_image(scenes):
    model = IniModel(lfsim.load(scenes / "ini_ideal.toml"))
    lay = DisplayLayout.from_model(model, 0)
    assert (lay.width, lay.height) == (17 * 125, 9 * 125)
    c = model.ei_centers(0, np.arange(17)[:, None] + 0 * np.arange(9), 0 * np.arange(17)[:, None] + np.arange(9))
    m, n = lay.lenslet_of(c.reshape(-1, 2))
    np.testing.assert_array_equal(m.reshape(17, 9), np.arange(17)[:, None] + 0 * np.arange(9))
    np.testing.assert_array_equal(n.reshape(17, 9), 0 * np.arange(17)[:, None] + np.arange(9))
    px = lay.pixel_centers()
    assert px[0, 0, 0] < px[0, -1, 0] and px[0, 0, 1] > px[-1, 0, 1]  # row 0 top, column 0 left
    assert np.mean(px[..., 0]) == pytest.approx(0.0, abs=1e-12)


@pytest.mark.parametrize("precision", ["float64", "float32"])
def test_reverse_path_returns_forward_rays_to_their_pixel(coaxial, precision):
    """Display pixel → (forward, aimed) → viewing window → (reversed) → the same pixel."""
    lay = DisplayLayout.from_model(coaxial)
    # Rounding noise of the round trip: coordinates as far as the viewing window (z ~ 374 mm)
    # rounded to the precision's machine epsilon, eps · z (float32 4.5e-5 mm, measured 0.17 of it;
    # float64 8.3e-14 mm, measured 0.25). Bound 2 eps · z, at most 1/50 of a display pixel.
    tol = 2 * np.finfo(precision).eps * abs(coaxial.o_vw[2])
    assert tol < lay.pixel_pitch / 50, tol
    xy = lay.pixel_centers().reshape(-1, 2)[::1499]
    m, n = lay.lenslet_of(xy)
    rev = ReverseOptics(coaxial, 0, precision)
    for rho in (np.zeros(2), np.array([0.6, -0.4])):
        pos, d, _, st, _ = trace_rays(coaxial, xy, m, n, rho, 0)
        ok = st == 0
        assert ok.mean() > 0.99
        p, _, valid = rev.to_display_numpy(np.column_stack([pos, 0 * pos[:, 0]])[ok], -d[ok])
        assert valid.all()
        assert np.max(np.hypot(*(p[:, :2] - xy[ok]).T)) < tol
        np.testing.assert_allclose(p[:, 2], -coaxial.g, atol=tol)


def test_model_at_depth_interpolates_given_tunable_powers(scenes):
    design = lfsim.load(scenes / "ini_coaxial.toml")
    given = dict(zip(design.ini.cdp_diopters, design.ini.tunable_power_diopters))
    for D in (0.0, 1.0, 3.0):
        assert 1000 * model_at_depth(design, D).tl_power[0] == pytest.approx(given[D], abs=1e-12)
    mid = model_at_depth(design, 2.0).tl_power[0] * 1000
    assert mid == pytest.approx(0.5 * (given[1.0] + given[3.0]), abs=1e-12)
    with pytest.raises(DesignError, match="cdp_diopters"):
        model_at_depth(design, -1.0)


def test_content_file_and_errors(scenes, tmp_path):
    c = load_content(scenes / "fig9_wall.toml")
    assert c.view.cdp_mm == 750.0 and c.view.focus_mm == (600.0, 1000.0, 1400.0)
    q = c.objects[0]
    assert -q.corners[0, 2] == pytest.approx(500.0) and -q.corners[1, 2] == pytest.approx(1667.0)
    ok = {"objects": [{"corners": [[-1, -1, -100], [1, -1, -100], [-1, 1, -100]]}]}
    content_from_dict(ok)
    bad = {"objects": [{"corners": [[-1, -1, -100], [-1, 1, -100], [1, -1, -100]]}]}
    with pytest.raises(DesignError, match=r"objects\[0\].corners.*faces away"):
        content_from_dict(bad, "c.toml")
    bad = {"objects": [dict(ok["objects"][0], texture={"type": "plaid"})]}
    with pytest.raises(DesignError, match=r"c.toml: objects\[0\].texture.type = 'plaid'"):
        content_from_dict(bad, "c.toml")
    bad = {"objects": [dict(ok["objects"][0], texture={"type": "image", "path": "nope.png"})]}
    with pytest.raises(DesignError, match="no such file"):
        content_from_dict(bad, "c.toml", tmp_path)


def test_elemental_images_show_the_content_seen_along_each_pixel_ray(scenes):
    """A luminous quad over the left half of visual space at 1 m lights exactly
    the display pixels whose visual-space ray meets it (both methods)."""
    from lfsim.content import elemental_images, scene_dict, visual_rays
    from lfsim.render import mitsuba

    mi = mitsuba()
    model = IniModel(lfsim.load(scenes / "ini_ideal.toml"))
    lay = DisplayLayout.from_model(model, 0)
    left = content_from_dict({"objects": [{
        "corners": [[-2000, -2000, -1000], [0, -2000, -1000], [-2000, 2000, -1000]],
        "texture": {"type": "constant"}, "radiance": [0.25, 0.5, 1.0]}]})
    sc = mi.load_dict(scene_dict(left))
    for method in ("real", "pinhole"):
        img = elemental_images(model, sc, lay, method=method).reshape(-1, 3)
        o, d, ok = visual_rays(model, lay, lay.pixel_centers().reshape(-1, 2), method)
        assert ok.all()
        x_at = o[:, 0] + d[:, 0] * (-1000 - o[:, 2]) / d[:, 2]
        clear = np.abs(x_at) > 1.0
        lit = x_at < 0
        assert 0.2 < lit.mean() < 0.8
        np.testing.assert_allclose(img[clear & lit], np.broadcast_to([0.25, 0.5, 1.0], img[clear & lit].shape),
                                   rtol=1e-6)
        assert np.all(img[clear & ~lit] == 0.0)


def test_image_texture_is_decoded_from_srgb_to_linear(tmp_path):
    """An 8-bit sRGB value 188 is linear 0.5029 (the sRGB transfer function, IEC 61966-2-1)."""
    from skimage import io

    from lfsim.content import texture_image

    io.imsave(tmp_path / "t.png", np.full((4, 6, 3), 188, dtype=np.uint8), check_contrast=False)
    c = content_from_dict({"objects": [{"corners": [[-1, -1, -100], [1, -1, -100], [-1, 1, -100]],
                                        "texture": {"type": "image", "path": "t.png"}}]}, "c.toml", tmp_path)
    img = texture_image(c.objects[0])
    assert img.shape == (4, 6, 3)
    expect = ((188 / 255 + 0.055) / 1.055) ** 2.4
    np.testing.assert_allclose(img, expect, rtol=1e-3)
