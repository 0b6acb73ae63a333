"""Design-file loading: every bad value gets one line naming file, key, value."""

import math

import pytest

import lfsim
from lfsim import DesignError
from lfsim.cli import main

GOOD = """
[system]
aperture = { type = "epd", value = 4.0 }
[[surfaces]]
radius = 20.0
thickness = 3.0
material = "N-BK7"
semi_diameter = 5.0
[[surfaces]]
radius = -20.0
thickness = 18.0
[[surfaces]]
dummy = true
"""


def test_good_design_loads(make_design):
    d = make_design(GOOD)
    assert [s.name for s in d.surfaces] == ["S1", "S2", "S3"]
    assert d.surfaces[0].curvature == pytest.approx(0.05)
    assert math.isclose(d.surfaces[0].material.nd, 1.5168, abs_tol=1e-6)


BAD = [
    # (replacement of a line of GOOD or extra text, expected key, expected value fragment)
    ("radius = 20.0", "radius = 0", "surfaces[0].radius", "0"),
    ("radius = 20.0", 'radius = "big"', "surfaces[0].radius", "'big'"),
    ("radius = 20.0", "radius = nan", "surfaces[0].radius", "nan"),
    ('material = "N-BK7"', 'material = "UNOBTAINIUM"', "surfaces[0].material", "'UNOBTAINIUM'"),
    ('material = "N-BK7"', "material = -1.5", "surfaces[0].material", "-1.5"),
    ("semi_diameter = 5.0", "semi_diameter = -5.0", "surfaces[0].semi_diameter", "-5.0"),
    ("semi_diameter = 5.0", "semi_diameter = 25.0", "surfaces[0].semi_diameter", "25.0"),
    ("thickness = 3.0", "thickness = true", "surfaces[0].thickness", "True"),
    ("thickness = 3.0", "thicknes = 3.0", "surfaces[0].thicknes", "3.0"),
    ("radius = 20.0", "radius = 20.0\nasphere = { A3 = 1e-5 }", "surfaces[0].asphere.A3", "1e-05"),
    ("radius = 20.0", "radius = 20.0\nxy = { x6y6 = 1e-5 }", "surfaces[0].xy.x6y6", "1e-05"),
    ("radius = 20.0", "radius = 20.0\nxy = { x1y0 = 1e-5 }\nnorm_radius = 0", "surfaces[0].norm_radius", "0"),
    ("radius = 20.0", "radius = 20.0\ntilt = [1, 2]", "surfaces[0].tilt", "[1, 2]"),
    ("radius = 20.0", "radius = 20.0\nmirror = true\ntir = true", "surfaces[0].tir", "True"),
    ("radius = 20.0", 'radius = 20.0\nsame_as = "nowhere"', "surfaces[0].same_as", "'nowhere'"),
    ("radius = 20.0", 'radius = 20.0\narray = "mla"', "surfaces[0].array", "'mla'"),
    ('value = 4.0', 'value = -4.0', "system.aperture.value", "-4.0"),
    ('type = "epd"', 'type = "diameter"', "system.aperture.type", "'diameter'"),
    # F/0 would be an infinite pupil (first order took it as 0 mm); an NA at or above the object index
    ('aperture = { type = "epd", value = 4.0 }', 'aperture = { type = "fno", value = 0 }',
     "system.aperture.value", "0.0"),
    ('aperture = { type = "epd", value = 4.0 }', 'aperture = { type = "na", value = 1.0 }\n[object]\ndistance = 50.0',
     "system.aperture.value", "1.0"),
    ("[system]", "[system]\nwavelengths_nm = [50.0]", "system.wavelengths_nm", "[50.0]"),
    ("[system]", "[object]\ndistance = -5\n[system]", "object.distance", "-5.0"),
]


@pytest.mark.parametrize("old,new,key,value", BAD)
def test_bad_values_name_file_key_and_value(tmp_path, old, new, key, value):
    p = tmp_path / "bad.toml"
    assert old in GOOD
    p.write_text(GOOD.replace(old, new, 1))
    with pytest.raises(DesignError) as e:
        lfsim.load(p)
    msg = str(e.value)
    assert "\n" not in msg
    assert str(p) in msg and key in msg and value in msg, msg
    assert e.value.key == key


def test_array_pitch_and_size_are_validated(tmp_path):
    base = GOOD.replace("[[surfaces]]\nradius = 20.0",
                        '[arrays.mla]\nm = 3\nn = 2\npitch = 1.0\n[[surfaces]]\nradius = 20.0\narray = "mla"', 1)
    base = base.replace("semi_diameter = 5.0", "")
    p = tmp_path / "a.toml"
    p.write_text(base)
    lfsim.load(p)
    for old, new, key in [("pitch = 1.0", "pitch = 0.0", "arrays.mla.pitch"), ("m = 3", "m = 0", "arrays.mla.m"),
                          ("n = 2", "n = 2.5", "arrays.mla.n")]:
        p.write_text(base.replace(old, new))
        with pytest.raises(DesignError, match=key.replace(".", r"\.")):
            lfsim.load(p)


def test_malformed_toml_and_missing_file(tmp_path, capsys):
    p = tmp_path / "broken.toml"
    p.write_text("[[surfaces]\nradius = ")
    with pytest.raises(DesignError, match="invalid TOML"):
        lfsim.load(p)
    assert main(["first-order", str(p)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "broken.toml" in err and "Traceback" not in err
    assert main(["first-order", str(tmp_path / "nope.toml")]) == 2
    assert "file not found" in capsys.readouterr().err


@pytest.mark.parametrize("name, encoding", [("lens.seq", "utf-8"), ("lens.zmx", "utf-16")])
def test_a_lens_file_given_as_a_design_points_to_import(tmp_path, capsys, name, encoding):
    p = tmp_path / name
    p.write_text("RDM\nSO 0 1e11\nS 0.02 5 NBK7_SCHOTT\nSI\n", encoding=encoding)
    assert main(["first-order", str(p)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and f"lfsim import {name}" in err and "Traceback" not in err
    toml = tmp_path / "design.toml"
    toml.write_text("[[surfaces]\n")
    with pytest.raises(DesignError) as e:
        lfsim.load(toml)
    assert "lfsim import" not in str(e.value)


def test_material_kinds(make_design):
    d = make_design(GOOD.replace('material = "N-BK7"', "material = { nd = 1.5168, vd = 64.17 }"))
    m = d.surfaces[0].material
    assert abs(m.nd - 1.5168) < 1e-12 and abs(m.vd - 64.17) < 1e-9
    d = make_design(GOOD.replace('material = "N-BK7"', "material = 1.49"))
    assert d.surfaces[0].material.index(450.0) == 1.49


def _biconvex(R: float, h: float, thickness: float, decenter_a=None, decenter_b=None) -> str:
    """A design of one N-BK7 lens A|B (radii +-R, semi-diameter h), each face optionally
    decentred in y."""
    def dec(d):
        return "" if d is None else f"\ndecenter = [0.0, {d}]"

    return f"""
[system]
aperture = {{ type = "epd", value = 10.0 }}
[[surfaces]]
name = "A"
radius = {R}
thickness = {thickness}
material = "N-BK7"
semi_diameter = {h}{dec(decenter_a)}
[[surfaces]]
name = "B"
radius = {-R}
thickness = 40.0
semi_diameter = {h}{dec(decenter_b)}
[[surfaces]]
name = "image"
dummy = true
"""


@pytest.mark.parametrize("thickness", [-8.0, 0.1])
def test_glass_whose_faces_cross_is_refused(tmp_path, thickness):
    """A lens with a negative centre thickness, or with faces that cross inside their clear
    apertures (a negative edge thickness), is refused in one line naming both surfaces, the
    radial height and the glass thickness there (closed form for two spheres); marking a face
    ``virtual`` accepts it as deliberate geometry."""
    R, h = 20.0, 6.0
    text = _biconvex(R, h, thickness)
    p = tmp_path / "x.toml"
    p.write_text(text)
    with pytest.raises(DesignError) as e:
        lfsim.load(p)
    msg = str(e.value)
    sag = R - math.sqrt(R * R - h * h)
    edge = thickness - 2.0 * sag  # both faces bulge outwards by `sag` at the rim
    assert e.value.key == "surfaces[0].thickness" and "'A' and 'B'" in msg and "\n" not in msg
    assert f"{edge:.6g} mm thick at radial height {h:.4g} mm" in msg and "virtual = true" in msg
    p.write_text(text.replace('name = "B"', 'name = "B"\nvirtual = true'))
    assert lfsim.load(p).system.surfaces[1].virtual


def _air_spaced(gap: float, second: str = "lens", image_gap: float = 40.0) -> str:
    """Two N-BK7 menisci (faces R 20 / 30 mm, then 40 / 60 mm, all concave toward +z,
    semi-diameter 6) ``gap`` apart in air; ``second = "ideal"``: an ideal lens instead of the
    second meniscus."""
    lens_b = ("""[[surfaces]]
name = "C"
radius = 40.0
thickness = 2.0
material = "N-BK7"
semi_diameter = 6.0
[[surfaces]]
name = "D"
radius = 60.0
thickness = {image_gap}
semi_diameter = 6.0""" if second == "lens" else """[[surfaces]]
name = "C"
type = "paraxial"
focal_length = 50.0
thickness = {image_gap}""").format(image_gap=image_gap)
    return f"""
[system]
aperture = {{ type = "epd", value = 10.0 }}
[[surfaces]]
name = "A"
radius = 20.0
thickness = 3.0
material = "N-BK7"
semi_diameter = 6.0
[[surfaces]]
name = "B"
radius = 30.0
thickness = {gap}
semi_diameter = 6.0
{lens_b}
[[surfaces]]
name = "image"
dummy = true
"""


def test_air_gap_whose_faces_cross_is_refused(tmp_path, capsys):
    """An air gap is checked like glass: B (R 30) and C (R 40), both concave toward +z, close
    in by sag_B(6) − sag_C(6) at the rim, so a gap below that crosses inside the clear
    apertures (refused in one line naming B's thickness and "air gap") and one above it does
    not; an ideal lens (a plane) behind B is refused at a negative gap, where the tracer would
    let light run backwards to it; the image surface may lie behind the last face (a virtual
    image), and ``virtual = true`` accepts a deliberate crossing."""
    def sag(R, r):
        return R - math.sqrt(R * R - r * r)

    closing = sag(30.0, 6.0) - sag(40.0, 6.0)
    p = tmp_path / "x.toml"
    p.write_text(_air_spaced(closing - 0.01))
    with pytest.raises(DesignError) as e:
        lfsim.load(p)
    msg = str(e.value)
    assert e.value.key == "surfaces[1].thickness" and e.value.surface == "B" and "\n" not in msg
    assert "'B' and 'C' cross inside their clear apertures: the air gap between them is -0.01 mm" in msg, msg
    assert "radial height 6 mm" in msg
    p.write_text(_air_spaced(closing + 0.01))
    lfsim.load(p)
    p.write_text(_air_spaced(-1.0, "ideal"))
    with pytest.raises(DesignError) as e:  # the plane meets B's rim, sag_B(6) nearer still
        lfsim.load(p)
    assert f"'B' and 'C' cross inside their clear apertures: the air gap between them is {-1.0 - sag(30.0, 6.0):.6g}" \
        in str(e.value)
    p.write_text(_air_spaced(1.0, "ideal", image_gap=-30.0))  # a virtual image: allowed
    lfsim.load(p)
    p.write_text(_air_spaced(-1.0, "ideal").replace('name = "C"', 'name = "C"\nvirtual = true'))
    lfsim.load(p)
    # From the command line (--set), the same line and exit status 2, nothing written.
    good = tmp_path / "good.toml"
    good.write_text(_air_spaced(5.0))
    out = tmp_path / "lay"
    assert main(["layout", str(good), "--set", "B.thickness=-2", "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "surfaces[1].thickness = -2.0 (surface 'B')" in err and "air gap" in err, err
    assert not out.exists()


def test_content_scene_given_as_a_design_is_named_as_such(scenes):
    import lfsim

    with pytest.raises(DesignError, match=r"fig9_wall\.toml: objects .*content scene.*--content"):
        lfsim.load(scenes / "fig9_wall.toml")


@pytest.mark.parametrize("distance", ["distance = inf", 'distance = "inf"', ""])
def test_object_space_na_needs_a_finite_object(tmp_path, capsys, scenes, distance):
    """An object-space NA sets the pupil through the object distance: with the object at infinity
    (inf, "inf", or [object] distance left out) first order took it as an entrance pupil of 0 mm
    and every metric was meaningless. The loader refuses it in one line naming the file, the key
    system.aperture and its value (the lens-file importers and exporters refuse it too); at a
    finite distance the same NA loads with a pupil."""
    text = (scenes / "asphere_singlet.toml").read_text()
    assert 'aperture = { type = "epd", value = 10.0 }' in text and "\ndistance = inf\n" in text
    text = text.replace('aperture = { type = "epd", value = 10.0 }', 'aperture = { type = "na", value = 0.1 }')
    p = tmp_path / "na_at_infinity.toml"
    p.write_text(text.replace("distance = inf", distance, 1))
    with pytest.raises(DesignError) as e:
        lfsim.load(p)
    msg = str(e.value)
    assert e.value.key == "system.aperture" and e.value.value == {"type": "na", "value": 0.1}
    assert "\n" not in msg and msg.startswith(f"{p}: system.aperture = {{'type': 'na', 'value': 0.1}}: "), msg
    assert "object-space NA (0.1) needs a finite object" in msg and "epd or fno" in msg, msg
    assert main(["first-order", str(p)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and str(p) in err and "system.aperture" in err and "Traceback" not in err, err
    p.write_text(text.replace("distance = inf", "distance = 500.0", 1))
    fo = lfsim.load(p).first_order(method="paraxial")
    assert fo.entrance_pupil_diameter > 0


def test_a_surface_error_names_the_surface(tmp_path):
    """Past the index, the message names the surface a file knows it by; an unnamed surface
    is named by its index only; ``key`` stays the dotted path."""
    p = tmp_path / "bad.toml"
    p.write_text(GOOD.replace("radius = 20.0", 'name = "front"\nradius = 0', 1))
    with pytest.raises(DesignError) as e:
        lfsim.load(p)
    assert e.value.key == "surfaces[0].radius" and e.value.surface == "front"
    assert "surfaces[0].radius = 0.0 (surface 'front'): " in str(e.value)
    p.write_text(GOOD.replace("radius = 20.0", "radius = 0", 1))
    with pytest.raises(DesignError) as e:
        lfsim.load(p)
    assert e.value.surface is None and "(surface" not in str(e.value)


@pytest.mark.parametrize("d_b", [0.0, 1.5])
def test_decentred_glass_whose_faces_cross_is_refused(tmp_path, d_b):
    """Faces decentred where they sit (A by 1 mm, B by d_b, each aperture moved with its face):
    the glass is sampled about each face's own vertex over the apertures' overlap. A negative
    centre thickness is refused naming the surface. On the axis of symmetry A's rim point inside
    B's aperture lies 6 from A's vertex and 6 - |d_b - 1| from B's, so t below
    sag(6) + sag(6 - |d_b - 1|) crosses there; at t = 2 sag(6) + 0.01 no point of the overlap
    (each at most 6 from both vertices) is thinner than 0.01."""
    R, h = 20.0, 6.0

    def text(thickness):
        return _biconvex(R, h, thickness, decenter_a=1.0, decenter_b=d_b)

    def sag(r):
        return R - math.sqrt(R * R - r * r)

    p = tmp_path / "x.toml"
    p.write_text(text(-0.5))
    with pytest.raises(DesignError) as e:
        lfsim.load(p)
    assert e.value.key == "surfaces[0].thickness" and e.value.surface == "A"
    assert "'A' and 'B' cross inside their clear apertures" in str(e.value)
    p.write_text(text(sag(h) + sag(h - abs(d_b - 1.0)) - 0.01))
    with pytest.raises(DesignError, match="cross inside their clear apertures"):
        lfsim.load(p)
    p.write_text(text(2.0 * sag(h) + 0.01))
    lfsim.load(p)
