"""`lfsim export --mitsuba`: a scene plain Mitsuba loads and renders, matching lfsim's mesh path."""

import json
import xml.etree.ElementTree as ET

import numpy as np
import pytest

import lfsim
from lfsim.cli import main
from lfsim.render.export import plain_system, singlet


def test_the_exported_scene_renders_what_the_mesh_path_renders(scenes, tmp_path, capsys):
    """ini_coaxial (one ideal lens, the tunable TL) exported and rendered by Mitsuba alone: the
    same retinal image as lfsim's mesh path (lfsim's refraction BSDFs, no Fresnel) up to the
    Fresnel transmission of Mitsuba's dielectrics, which the mean brightness ratio matches
    (the product of the faces' normal-incidence transmissions) within 4 %."""
    from lfsim.render import mitsuba
    from lfsim.render.focal_stack import FocalStackSpec, focal_stack

    out = tmp_path / "ex"
    args = [str(scenes / "ini_coaxial.toml"), "--content", str(scenes / "fig9_wall.toml"), "--focus-mm", "750",
            "--resolution", "64,38"]
    assert main(["export", *args, "--mitsuba", str(out), "--spp", "256", "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert [s["surface"] for s in doc["paraxial_substitutions"]] == ["TL"]
    text = (out / "scene.xml").read_text()
    assert "lfsim" not in text  # built-in plugins only
    mi = mitsuba()
    img = np.array(mi.render(mi.load_file(str(out / "scene.xml"))), dtype=np.float64)[..., :3]
    T = 1.0
    for b in ET.fromstring(text).iter("bsdf"):
        if b.get("type") == "dielectric":
            f = {e.get("name"): float(e.get("value")) for e in b.findall("float")}
            T *= 1.0 - ((f["int_ior"] - f["ext_ior"]) / (f["int_ior"] + f["ext_ior"])) ** 2
    design = lfsim.load(scenes / "ini_coaxial.toml")
    from lfsim.content import load_content

    spec = FocalStackSpec(focus_mm=[750.0], spp=256, resolution=(64, 38), optics="mesh", natural=False,
                          wavelength_nm=design.system.primary_wavelength_nm, diffraction=False, focus_cues=False)
    _, stack = focal_stack(design, load_content(scenes / "fig9_wall.toml"), tmp_path / "fs", spec,
                           log=lambda m: None)
    ref = np.asarray(stack["images"][("display", 750.0)], dtype=np.float64)
    assert img.shape == ref.shape and np.isfinite(img).all()
    assert abs(img.mean() / ref.mean() / T - 1) < 0.04, (img.mean() / ref.mean(), T)

    def binned(a):
        y = a.mean(axis=-1)[: a.shape[0] // 2 * 2, : a.shape[1] // 2 * 2]
        return y.reshape(y.shape[0] // 2, 2, y.shape[1] // 2, 2).mean(axis=(1, 3)).ravel()

    assert np.corrcoef(binned(img), binned(ref))[0, 1] > 0.8


def test_an_ideal_lens_becomes_a_singlet_of_the_same_power(scenes):
    """The stand-in singlet's thick-lens power (lensmaker's formula, an independent
    evaluation) equals the ideal lens's; ideal lenses in contact become one singlet, and no
    ideal lens is left."""
    for P, n, r in ((1 / 31.0, 1.5168, 19.0), (-1.39e-3, 1.5168, 5.0), (1 / 3.5, 1.5168, 0.7)):
        c, t = singlet(P, n, r)
        got = (n - 1) * (c - (-c)) + (n - 1) ** 2 * t * c * (-c) / n
        assert abs(got / P - 1) < 1e-12 and t >= 0.2 - 1e-15
    design = lfsim.load(scenes / "ini_ideal.toml")
    system, subs = plain_system(design)
    assert [s["surface"] for s in subs] == ["MLA", "EP"]  # TL (0 D, in contact) joined EP
    assert not any(s.interaction == "paraxial" for s in system.surfaces)


@pytest.mark.parametrize("args,msg", [
    ([], "--mitsuba"),
    (["--mitsuba", "{out}", "--focus-mm", "600,900"], "one focus"),
    (["--mitsuba", "{out}", "--spp", "0"], "--spp"),
])
def test_export_bad_input(scenes, tmp_path, capsys, args, msg):
    out = tmp_path / "o"
    argv = ["export", str(scenes / "ini_coaxial.toml")] + [a.replace("{out}", str(out)) for a in args]
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert msg in err and "\n" not in err
    assert not out.exists()
