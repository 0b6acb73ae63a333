"""`lfsim focal-stack`: files, metadata, similarity and focus cues (small renders)."""

import json

import numpy as np
import pytest

from lfsim.cli import main
from lfsim.render.focal_stack import read_exr


def test_focal_stack_cli_writes_the_stack(scenes, tmp_path, capsys):
    out = tmp_path / "fs"
    rc = main(["focal-stack", str(scenes / "ini_ideal.toml"), "--content", str(scenes / "fig9_wall.toml"),
               "--focus-mm", "600,1400", "--spp", "4", "--resolution", "96,56", "--out", str(out), "--json"])
    assert rc == 0
    doc = json.loads(capsys.readouterr().out)
    on_disk = json.loads((out / "index.json").read_text())
    assert on_disk == doc
    assert [(i["kind"], i["focus_mm"]) for i in doc["images"]] == [
        ("display", 600.0), ("natural", 600.0), ("display", 1400.0), ("natural", 1400.0)]
    for im in doc["images"]:
        img, hdr = read_exr(out / im["exr"])
        assert img.shape == (56, 96, 3) and img.dtype == np.float32 and np.isfinite(img).all()
        assert hdr["lfsim_focus_mm"] == im["focus_mm"] and hdr["lfsim_spp"] == 4
        assert hdr["lfsim_kind"] == im["kind"] and "render_s" in im
        assert (out / im["png"]).stat().st_size > 0
        if im["kind"] == "display":
            assert -1 <= im["ssim_vs_natural"] <= 1 and im["psnr_vs_natural"] > 0
            assert img.mean() > 0.05  # the display shows the wall
    ei, hdr = read_exr(out / "elemental_images.exr")
    assert ei.shape == (9 * 125, 17 * 125, 3) and hdr["lfsim_kind"] == "elemental_images"
    assert (out / "contact_sheet.png").exists() and (out / "focus_cues.png").exists()
    assert doc["tunable_power_diopters"] is not None and doc["cdp_mm"] == 750.0
    assert len(doc["focus_cues"]["sharpest"]) == 4
    assert not list(out.glob(".*"))  # no temporary files left behind


@pytest.mark.parametrize("args,msg", [
    (["--focus-mm", "600,-1"], "--focus-mm"),
    (["--spp", "0"], "--spp"),
    (["--cdp-mm", "abc"], "--cdp-mm"),
    (["--content", "missing.toml"], "missing.toml"),
    (["--tessellation", "0"], "--tessellation"),
])
def test_focal_stack_bad_input(scenes, tmp_path, capsys, args, msg):
    base = ["focal-stack", str(scenes / "ini_ideal.toml"), "--content", str(scenes / "fig9_wall.toml"),
            "--out", str(tmp_path / "o")]
    assert main(base + args) == 2
    err = capsys.readouterr().err.strip()
    assert msg in err and "\n" not in err
    assert not (tmp_path / "o" / "index.json").exists()


def test_mesh_path_focal_stack_matches_the_analytic_path(scenes, tmp_path):
    """--optics mesh (display + optics meshes + eye at the viewing window, path-traced
    by Mitsuba) and the analytic path differ by Monte Carlo noise only."""
    import lfsim
    from lfsim.design.content import load_content
    from lfsim.render.accuracy import relative_rmse
    from lfsim.render.focal_stack import FocalStackSpec, focal_stack

    design = lfsim.load(scenes / "ini_coaxial.toml")
    content = load_content(scenes / "fig9_wall.toml")
    imgs = {}
    for optics, seed in (("mesh", 1), ("analytic", 2), ("analytic", 3)):
        spec = FocalStackSpec(focus_mm=[750.0], spp=16, resolution=(48, 28), seed=seed, natural=False,
                              optics=optics)
        doc, stack = focal_stack(design, content, tmp_path / f"{optics}{seed}", spec, log=lambda *a: None)
        assert doc["optics"] == optics
        imgs[(optics, seed)] = stack["images"][("display", 750.0)]
    mesh, a2, a3 = imgs[("mesh", 1)], imgs[("analytic", 2)], imgs[("analytic", 3)]
    noise = relative_rmse(a3, a2)
    assert np.isfinite(mesh).all() and mesh.mean() > 0.1
    assert relative_rmse(mesh, a2) < 1.25 * noise
    assert abs(mesh.mean() / a2.mean() - 1) < 0.03
