"""Content from Mitsuba scenes and RGB-D images: elemental images, natural views, focus."""

import json
import math

import numpy as np
import pytest

import lfsim
from lfsim.cli import main
from lfsim.content import from_mitsuba, load_content, shade_display
from lfsim.render.focal_stack import FocalStackSpec, focal_stack, read_exr

TWO_OBJECTS = """<scene version="3.0.0">
  <emitter type="constant"><rgb name="radiance" value="1.0"/></emitter>
  <!-- near: a checkered card 500 mm (2 D) away, left of the line of sight -->
  <shape type="rectangle">
    <transform name="to_world"><scale x="70" y="80" z="1"/><translate x="-75" y="0" z="-500"/></transform>
    <bsdf type="diffuse"><texture type="checkerboard" name="reflectance">
      <rgb name="color0" value="0.05"/><rgb name="color1" value="0.9"/>
      <transform name="to_uv"><scale x="14" y="16"/></transform></texture></bsdf>
  </shape>
  <!-- far: a checkered wall 2000 mm (0.5 D) away, right of the line of sight -->
  <shape type="rectangle">
    <transform name="to_world"><scale x="280" y="320" z="1"/><translate x="300" y="0" z="-2000"/></transform>
    <bsdf type="diffuse"><texture type="checkerboard" name="reflectance">
      <rgb name="color0" value="0.05"/><rgb name="color1" value="0.9"/>
      <transform name="to_uv"><scale x="14" y="16"/></transform></texture></bsdf>
  </shape>
</scene>
"""


def _sharpness(img, cols):
    """Mean squared Laplacian (luma) inside a column range, away from the top and bottom."""
    from scipy.ndimage import laplace

    y = img[..., :3] @ np.array([0.2126, 0.7152, 0.0722])
    h = y.shape[0]
    return float(np.mean(laplace(y)[h // 4:3 * h // 4, cols[0]:cols[1]] ** 2))


def test_a_mitsuba_scene_is_sharp_where_the_eye_focuses(scenes, tmp_path):
    """Two lit objects at 2 D and 0.5 D (a Mitsuba XML scene, path-traced elemental images):
    seen through the display with the eye at near focus the near object is the sharper, at far
    focus the far one; likewise the natural view."""
    xml = tmp_path / "two.xml"
    xml.write_text(TWO_OBJECTS)
    content = load_content(xml)
    assert content.path_traced
    design = lfsim.load(scenes / "ini_ideal.toml")
    spec = FocalStackSpec(focus_mm=[500.0, 2000.0], cdp_mm=1000.0, spp=32, resolution=(192, 116), ei_spp=4,
                          wavelength_nm=550.0, diffraction=False, focus_cues=False)
    doc, stack = focal_stack(design, content, tmp_path / "fs", spec, log=lambda m: None)
    assert doc["display"]["path_traced"] and doc["display"]["spp"] == 4
    assert 0 < doc["display"]["noise_rel"] < 0.2
    W = doc["resolution"][0]
    near, far = (8, W // 2 - 8), (W // 2 + 8, W - 8)
    for kind in ("display", "natural"):
        a, b = stack["images"][(kind, 500.0)], stack["images"][(kind, 2000.0)]
        assert np.isfinite(a).all() and a.mean() > 0.05
        ratio_near = _sharpness(a, near) / _sharpness(b, near)
        ratio_far = _sharpness(b, far) / _sharpness(a, far)
        assert ratio_near > 1.5 and ratio_far > 1.5, (kind, ratio_near, ratio_far)


def _wall_in_metres(tmp_path, scenes):
    """The Fig. 9 wall written as a Mitsuba scene: the same texture (an EXR) on a rectangle
    with an area emitter, modelled in metres in a frame turned 90 deg about y, placed by a
    content TOML's [scene]."""
    from lfsim.content import texture_image
    from lfsim.render.focal_stack import write_exr

    wall = load_content(scenes / "fig9_wall.toml")
    q = wall.objects[0]
    # Mitsuba's rectangle maps bitmap row 0 to local y = -1 (the quad path flips the same way).
    write_exr(tmp_path / "wall.exr", np.ascontiguousarray(texture_image(q)[::-1]), {})
    # Visual space -> scene frame: x_s = R^T (x_v - t) / 1000, R = rotation of +90 deg about y.
    R = np.array([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]])
    t = np.array([10.0, -20.0, 30.0])
    u, v = q.u, q.v
    n = np.cross(u, v) / np.linalg.norm(np.cross(u, v))
    c = q.corners[0] + 0.5 * (u + v)
    M = np.eye(4)
    M[:3, 0], M[:3, 1], M[:3, 2], M[:3, 3] = R.T @ (0.5 * u), R.T @ (0.5 * v), R.T @ n, R.T @ (c - t)
    M[:3, :] /= 1000.0
    M[:3, 2] *= 1000.0  # the normal column stays a unit vector
    rows = " ".join(f"{x:.17g}" for x in M.ravel())
    (tmp_path / "wall.xml").write_text(f"""<scene version="3.0.0">
  <shape type="rectangle">
    <transform name="to_world"><matrix value="{rows}"/></transform>
    <bsdf type="diffuse"><rgb name="reflectance" value="0"/></bsdf>
    <emitter type="area"><texture type="bitmap" name="radiance"><string name="filename" value="wall.exr"/>
      <boolean name="raw" value="true"/><string name="filter_type" value="bilinear"/>
      <string name="wrap_mode" value="clamp"/></texture></emitter>
  </shape>
</scene>
""")
    view = (scenes / "fig9_wall.toml").read_text()
    view = view[view.index("[view]"):view.index("[[objects]]")].replace('"ini_ideal.toml"',
                                                                        json.dumps(str(scenes / "ini_ideal.toml")))
    (tmp_path / "wall.toml").write_text(f"""name = "Fig. 9 wall as a Mitsuba scene"
[scene]
file = "wall.xml"
units = "m"
rotate_deg = [0.0, 90.0, 0.0]
translate_mm = [10.0, -20.0, 30.0]
{view}""")
    return wall, load_content(tmp_path / "wall.toml")


def test_the_fig9_wall_as_a_mitsuba_scene_matches_the_quad_path(scenes, tmp_path):
    """The quad wall and the same wall as a Mitsuba scene in metres, in a turned and shifted
    frame: the same elemental images (float32 rounding of the texture lookup only), depth
    AOVs and retinal images (display and natural) within their noise."""
    from lfsim.render.accuracy import relative_rmse

    quad, mts = _wall_in_metres(tmp_path, scenes)
    assert mts.path_traced and not quad.path_traced and mts.scene.scale == 1000.0
    design = lfsim.load(scenes / "ini_ideal.toml")
    imgs = {}
    for name, c in (("quad", quad), ("mitsuba", mts)):
        spec = FocalStackSpec(focus_mm=[1000.0], spp=16, resolution=(128, 77), ei_spp=2, wavelength_nm=550.0,
                              diffraction=False, focus_cues=False, seed=3)
        doc, stack = focal_stack(design, c, tmp_path / name, spec, log=lambda m: None)
        ei, _ = read_exr(tmp_path / name / "elemental_images.exr")
        import OpenEXR

        with OpenEXR.File(str(tmp_path / name / "elemental_images.exr")) as f:
            depth = np.array(f.channels()["depth.Z"].pixels)
        imgs[name] = (ei, depth, stack["images"][("display", 1000.0)], stack["images"][("natural", 1000.0)], doc)
    (e0, d0, r0, n0, doc0), (e1, d1, r1, n1, doc1) = imgs["quad"], imgs["mitsuba"]
    assert doc0["display"]["noise_rel"] is None  # the quad path is exact
    # An emitter with a black BSDF: path tracing adds nothing, so the estimate has no noise.
    assert doc1["display"]["noise_rel"] is not None and doc1["display"]["noise_rel"] < 1e-6
    assert np.mean(np.abs(e1 - e0)) < 2e-3 * e0.mean() and np.mean(np.abs(e1 - e0) > 0.05) < 2e-3
    hit = np.isfinite(d0) & (d0 > 0)
    assert hit.mean() > 0.9 and np.array_equal(hit, np.isfinite(d1) & (d1 > 0))
    assert np.max(np.abs(d1[hit] - d0[hit]) / d0[hit]) < 1e-5  # float32 distances, 500-1700 mm
    # Retinal images: the same eye samples (same seed) through the same optics.
    assert relative_rmse(r1, r0) < 0.01 and relative_rmse(n1, n0) < 0.01


def test_path_traced_noise_is_the_error_against_a_converged_render(scenes, tmp_path):
    """The reported noise (standard error from two independent halves) matches the actual RMS
    error against a 16x longer render within 25 %, and falls as 1/sqrt(spp)."""
    xml = tmp_path / "two.xml"
    xml.write_text(TWO_OBJECTS.replace("</scene>", """  <shape type="sphere"><point name="center" x="0" y="300"
      z="-700"/><float name="radius" value="60"/><emitter type="area"><rgb name="radiance" value="6"/></emitter>
  </shape>
</scene>"""))
    content = load_content(xml)
    design = lfsim.load(scenes / "ini_ideal.toml")
    from lfsim.ini.model import model_at_depth
    from lfsim.render.display import DisplayLayout

    model = model_at_depth(design, 1.0)
    layout = DisplayLayout.from_model(model, 0)
    ref = shade_display(model, content, layout, spp=64, seed=11)
    runs = [shade_display(model, content, layout, spp=s, seed=1) for s in (4, 16)]
    has = ref.image.sum(axis=-1) > 0
    for r in runs:
        err = math.sqrt(np.mean((r.image - ref.image)[has] ** 2 - 0.0)) / ref.image[has].mean()
        err = math.sqrt(max(err ** 2 - ref.noise_rel ** 2, 0.0))  # less the reference's own noise
        assert abs(r.noise_rel / err - 1) < 0.25, (r.spp, r.noise_rel, err)
    assert 1.6 < runs[0].noise_rel / runs[1].noise_rel < 2.4


def test_rgbd_content_is_the_image_at_its_depths(tmp_path):
    """An RGB-D image: rays from the eye a quarter pixel off the pixel centres see the image's
    bilinear interpolation there and meet the height field at the stored depth (both
    conventions); between the two columns of a depth jump there is no skin."""
    from scipy.ndimage import map_coordinates
    from skimage import data
    from skimage.io import imsave

    from lfsim.content import shade
    from lfsim.content.pathtrace import surface_aovs
    from lfsim.content.rgbd import pixel_directions
    from lfsim.render.focal_stack import write_exr

    img = data.astronaut()[::8, ::8]  # 64 x 64, sRGB
    H, W = img.shape[:2]
    imsave(tmp_path / "rgb.png", img, check_contrast=False)
    z = np.full((H, W), 1000.0)
    z[:, W // 2:] = 2500.0  # a step: the right half 2.5 m away
    write_exr(tmp_path / "depth.exr", np.repeat(z[..., None], 3, axis=-1), {})
    # Rays through (column + 0.25, row + 0.25): pixel_directions of a grid shifted by a quarter pixel.
    t = math.tan(math.radians(20.0))
    X, Y = np.meshgrid(((np.arange(W) + 0.75) / W * 2 - 1) * t, (1 - (np.arange(H) + 0.75) / H * 2) * t * H / W)
    dirs = np.stack([X, Y, -np.ones_like(X)], axis=-1).reshape(-1, 3)
    assert np.allclose(pixel_directions(W, H, 40.0)[0, 0], [-t * (1 - 1 / W), t * (1 - 1 / H), -1])
    unit = dirs / np.linalg.norm(dirs, axis=1, keepdims=True)
    col = np.tile(np.arange(W), H)
    inner = np.zeros((H, W), dtype=bool)
    inner[1:-2, 1:-2] = True
    inner[:, W // 2 - 1] = False  # the rays past the last near column cross the jump
    sel = inner.ravel()
    for conv in ("z", "range"):
        (tmp_path / "c.toml").write_text(f"""[[objects]]
type = "rgbd"
image = "rgb.png"
depth = "depth.exr"
depth_convention = "{conv}"
fov_deg = 40.0
""")
        content = load_content(tmp_path / "c.toml")
        lin = content.objects[0].image()
        scene = content.mitsuba_scene()
        o = np.zeros_like(dirs)
        L = shade(scene, o, dirs)
        rr, cc = np.meshgrid(np.arange(H) + 0.25, np.arange(W) + 0.25, indexing="ij")
        want = np.stack([map_coordinates(lin[..., k], [rr, cc], order=1) for k in range(3)], -1).reshape(-1, 3)
        if conv == "z":  # planar depth: the two planes are flat, uv is linear across the screen
            assert np.max(np.abs(L[sel] - want[sel])) < 2e-4
        depth, _ = surface_aovs(scene, o, dirs, np.ones(len(dirs), dtype=bool))
        if conv == "z":
            expect = z.ravel() / (-unit[:, 2])
            assert np.max(np.abs(depth[sel] / expect[sel] - 1)) < 1e-5
        else:  # spheres about the eye: between vertices the flat triangles lie a little inside
            expect = z.ravel()
            assert np.all(np.abs(depth[sel] / expect[sel] - 1) < 2e-4)
        gap = col == W // 2 - 1
        assert np.all(np.isinf(depth[gap]))  # nothing between 1 m and 2.5 m


def test_python_api_takes_a_loaded_scene(scenes):
    from lfsim.render import mitsuba

    mi = mitsuba()
    scene = mi.load_string(TWO_OBJECTS)
    c = from_mitsuba(scene, name="two", units="cm", translate_mm=(0.0, 0.0, -100.0))
    assert c.path_traced and c.mitsuba_scene() is scene and c.scene.scale == 10.0
    o, d = c.scene.rays_to_scene(np.array([[0.0, 0.0, 0.0]]), np.array([[0.0, 0.0, -1.0]]))
    assert np.allclose(o, [[0.0, 0.0, 10.0]]) and np.allclose(d, [[0.0, 0.0, -1.0]])


@pytest.mark.parametrize("xml,toml,msg", [
    ("<scene version='3.0.0'><shape type='sphere'/></scene>", None, "no emitter"),
    ("<scene version='3.0.0'><emitter type='constant'/><shape type='sphere'><point name='center' x='0' y='0' "
     "z='500'/></shape></scene>", None, "behind the eye"),
    ("<scene version='3.0.0'><shape type='nosuchshape'/></scene>", None, "cannot load"),
    ("<scene version='3.0.0'><emitter type='constant'/></scene>", "[scene]\nfile = 's.xml'\nunits = 'furlong'\n",
     "unknown units"),
    ("<scene version='3.0.0'><emitter type='constant'/></scene>",
     "[scene]\nfile = 's.xml'\n[[objects]]\ntype = 'quad'\n", "not both"),
])
def test_bad_scenes_get_one_line_and_exit_2(scenes, tmp_path, capsys, xml, toml, msg):
    (tmp_path / "s.xml").write_text(xml)
    path = tmp_path / "s.xml"
    if toml is not None:
        path = tmp_path / "s.toml"
        path.write_text(toml)
    out = tmp_path / "o"
    assert main(["focal-stack", str(scenes / "ini_ideal.toml"), "--content", str(path), "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert msg in err and "\n" not in err and str(path.name) in err
    assert not out.exists()


def test_ray_bundles_average_over_the_rays_that_reach_the_window(scenes):
    """--ei-bundle: a uniform quad filling the view gives its radiance exactly on every pixel
    with rays (vignetted rays do not dilute the mean); on the Fig. 9 wall the bundle image
    keeps the chief-ray image's mean and is smoother (anti-aliased)."""
    from lfsim.content import content_from_dict
    from lfsim.ini.model import model_at_depth
    from lfsim.render.display import DisplayLayout

    design = lfsim.load(scenes / "ini_ideal.toml")
    model = model_at_depth(design, 1.0)
    layout = DisplayLayout.from_model(model, 0)
    flat = content_from_dict({"objects": [{"type": "quad", "texture": {"type": "constant"}, "radiance": 0.7,
                                           "corners": [[-5000, -5000, -1000], [5000, -5000, -1000],
                                                       [-5000, 5000, -1000]]}]})
    b = shade_display(model, flat, layout, spp=4, bundle=True, seed=2)
    lit = b.image[..., 0] > 0
    assert b.bundle and lit.mean() > 0.95
    assert np.max(np.abs(b.image[lit] - 0.7)) < 1e-6
    wall = load_content(scenes / "fig9_wall.toml")
    chief = shade_display(model, wall, layout)
    bundle = shade_display(model, wall, layout, spp=8, bundle=True, seed=2)
    assert chief.noise_rel is None and bundle.noise_rel > 0
    assert abs(bundle.image.mean() / chief.image.mean() - 1) < 0.01

    def rough(img):
        y = img[..., 1]
        return float(np.mean(np.diff(y, axis=1) ** 2))

    assert rough(bundle.image) < rough(chief.image)


def test_a_content_file_alone_is_a_focal_stack_and_stacks_compare(scenes, tmp_path, capsys):
    """`lfsim focal-stack CONTENT.toml` takes the design from the content's [view]; `lfsim compare`
    of two stacks compares their images (RGB), not the elemental images' depth/normal AOVs."""
    out = tmp_path / "fs"
    small = ["--focus-mm", "1000", "--spp", "1", "--resolution", "48,27", "--out", str(out)]
    assert main(["focal-stack", str(scenes / "fig9_wall.toml"), *small]) == 0
    doc = json.loads((out / "index.json").read_text())
    assert doc["design"].endswith("ini_ideal.toml") and doc["content"].endswith("fig9_wall.toml")
    capsys.readouterr()
    assert main(["compare", str(out), str(out), "--json"]) == 0
    assert "unexpected shape" not in capsys.readouterr().err


def _rb_correlation(img) -> float:
    r, b = img[..., 0] - img[..., 0].mean(), img[..., 2] - img[..., 2].mean()
    return float(np.sum(r * b) / np.sqrt(np.sum(r * r) * np.sum(b * b)))


def test_per_channel_elemental_images_pre_correct_lateral_colour(scenes, tmp_path):
    """--ei-colour: each colour channel of the display shaded along rays traced at its primary's
    median wavelength. On a design without colour (ini_ideal: ideal lenses) it is the plain
    display image, bit for bit; through ini_freeform_optimized (6.5' of lateral colour) the
    retinal image's red and blue channels of the grey Fig. 9 wall come back into register: their
    correlation rises toward the natural view's (0.998)."""
    from lfsim.ini.model import IniModel, model_at_depth
    from lfsim.render.display import DisplayLayout

    wall = load_content(scenes / "fig9_wall.toml")
    model = model_at_depth(lfsim.load(scenes / "ini_ideal.toml"), 1.0)
    layout = DisplayLayout.from_model(model, 0)
    power = [model.state(0).tunable_power_diopters]
    ch = [IniModel(model.design, wavelength_nm=x, tunable_power_diopters=power) for x in (620.0, 530.0, 460.0)]
    plain, per = shade_display(model, wall, layout), shade_display(model, wall, layout, channel_models=ch)
    assert np.array_equal(per.image, plain.image) and np.array_equal(per.depth, plain.depth)

    design = lfsim.load(scenes / "ini_freeform_optimized.toml")
    corr = {}
    for ec in (False, True):
        spec = FocalStackSpec(focus_mm=[750.0], cdp_mm=750.0, spp=8, resolution=(128, 72), ei_colour=ec,
                              focus_cues=False, natural=False)
        doc, _ = focal_stack(design, wall, tmp_path / f"fs{int(ec)}", spec, progress=False, log=lambda *a, **k: None)
        img = read_exr(tmp_path / f"fs{int(ec)}" / doc["images"][0]["exr"])
        corr[ec] = _rb_correlation(img[0] if isinstance(img, tuple) else img)
        assert doc["display"]["channel_wavelengths_nm"] == (pytest.approx([620.0, 530.0, 460.0]) if ec else None)
    # (at 192 x 108 px and 16 spp: 0.838 -> 0.916; here 128 x 72 px at 8 spp, the same seed)
    assert corr[False] < 0.85 and corr[True] > corr[False] + 0.04, corr


def test_per_channel_elemental_images_need_a_spectral_render(scenes, tmp_path, capsys):
    for extra in (["--wavelength-nm", "550"], ["--optics", "mesh"]):
        out = tmp_path / "fs"
        assert main(["focal-stack", str(scenes / "ini_ideal.toml"), "--out", str(out), "--ei-colour", *extra]) == 2
        err = capsys.readouterr().err.strip()
        assert "\n" not in err and err.startswith("lfsim: error: --ei-colour with ") and "spectral render" in err, err
        assert not out.exists()
