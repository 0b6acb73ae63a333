"""`lfsim focal-stack`: files, metadata, similarity and focus cues (small renders)."""

import json

import numpy as np
import pytest

import lfsim
from lfsim.analysis.compare import compare_images
from lfsim.cli import main
from lfsim.content import load_content
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
            # One SSIM/PSNR convention: index.json says what `lfsim compare` says of the same pair.
            nat = next(n for n in doc["images"] if n["kind"] == "natural" and n["focus_mm"] == im["focus_mm"])
            cmp = compare_images(read_exr(out / nat["exr"])[0], img)
            assert abs(cmp["ssim"] - im["ssim_vs_natural"]) <= 1e-12
            assert abs(cmp["psnr"] - im["psnr_vs_natural"]) <= 1e-9
            # Exposure: the mean light against the natural view's; the matched SSIM compares
            # the display scaled to it (the ideal design's views have about 0.78 of the light).
            nat_img = read_exr(out / nat["exr"])[0]
            assert im["exposure_vs_natural"] == pytest.approx(img.mean() / nat_img.mean(), rel=1e-6)
            assert 0.3 < im["exposure_vs_natural"] < 1.5 and -1 <= im["ssim_vs_natural_matched"] <= 1
    ei, hdr = read_exr(out / "elemental_images.exr")
    assert ei.shape == (9 * 125, 17 * 125, 3) and hdr["lfsim_kind"] == "elemental_images"
    assert (out / "contact_sheet.png").exists() and (out / "focus_cues.png").exists()
    assert doc["tunable_power_diopters"] is not None and doc["cdp_mm"] == 750.0
    assert len(doc["focus_cues"]["sharpest"]) == 4
    for r in doc["focus_cues"]["sharpest"]:  # a second peak, or none, with its height over the peak's
        assert (r["runner_up_diopters"] is None) == (r["runner_up_ratio"] is None)
        assert r["runner_up_ratio"] is None or 0 < r["runner_up_ratio"] <= 1
    # Colour by default: 8 nodes per primary, and the primaries they came from.
    assert doc["spectral"] and [len(w) for w in doc["wavelengths_nm"]] == [8, 8, 8]
    assert doc["primaries"]["source"] == "default" and doc["primaries"]["G"]["peak_nm"] == 530.0
    # The natural view: the real wall's broadband light, the same node count, other nodes.
    nat_nm = doc["natural_wavelengths_nm"]
    assert [len(w) for w in nat_nm] == [8, 8, 8] and nat_nm != doc["wavelengths_nm"]
    assert read_exr(out / "natural_600mm.exr")[1]["lfsim_wavelengths_nm"].startswith(f"{nat_nm[0][0]:.2f}")
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
    from lfsim.content import load_content
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
    noise = relative_rmse(a3, a2)  # per pixel and channel, of a difference of two seeds
    assert np.isfinite(mesh).all() and mesh.mean() > 0.1
    assert relative_rmse(mesh, a2) < 1.25 * noise
    # Means: 3 % (a brightness error) or 4 standard errors of a difference of two means
    # (noise / sqrt(pixels): box pixels are independent, their RGB values are not; 1.1 % here,
    # so 4.5 %), whichever is larger; ceiling 6 %.
    tol = max(0.03, 4.0 * noise / np.sqrt(mesh.shape[0] * mesh.shape[1]))
    assert tol <= 0.06, (tol, noise)
    assert abs(mesh.mean() / a2.mean() - 1) < tol


def test_view_defaults_have_one_owner(scenes, tmp_path, capsys):
    """FocalStackSpec, ViewSpec and the render verbs take a [view] without keys from
    ContentView's defaults (the CDP at 750 mm, focus 600/1000/1400 mm, a 3 mm pupil)."""
    from lfsim.content import VIEW_DEFAULTS, load_content
    from lfsim.render.diff_render import ViewSpec
    from lfsim.render.focal_stack import FocalStackSpec

    for spec in (FocalStackSpec(), ViewSpec()):
        assert spec.cdp_mm == VIEW_DEFAULTS.cdp_mm == 750.0
        assert tuple(spec.focus_mm) == VIEW_DEFAULTS.focus_mm == (600.0, 1000.0, 1400.0)
        assert spec.pupil_diameter_mm == VIEW_DEFAULTS.pupil_diameter_mm == 3.0
    text = (scenes / "fig9_wall.toml").read_text()
    bare = tmp_path / "bare.toml"
    i, j = text.index("[view]"), text.index("[[objects]]")
    bare.write_text(text[:i] + text[j:])
    assert load_content(bare).view == VIEW_DEFAULTS
    out = tmp_path / "fs"
    assert main(["focal-stack", str(scenes / "ini_ideal.toml"), "--content", str(bare), "--focus-mm", "1000",
                 "--spp", "1", "--resolution", "96,56", "--out", str(out), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["cdp_mm"] == VIEW_DEFAULTS.cdp_mm


def test_python_api_writes_what_the_verb_writes_even_at_a_small_resolution(scenes, tmp_path):
    """vision.focus_cues.focal_stack() runs the focus-cue analysis and writes index.json with it,
    as `lfsim focal-stack` does; a 48x27 image (fewer columns than 24 bands of 3)
    gets fewer bands instead of failing."""
    import lfsim
    from lfsim.content import load_content
    from lfsim.render.focal_stack import FocalStackSpec
    from lfsim.vision.focus_cues import focal_stack

    design = lfsim.load(scenes / "ini_ideal.toml")
    content = load_content(scenes / "fig9_wall.toml")
    out = tmp_path / "api"
    doc, _ = focal_stack(design, content, out, FocalStackSpec(focus_mm=[1000.0], spp=1, resolution=(48, 27)),
                         log=lambda m: None)
    on_disk = json.loads((out / "index.json").read_text())
    assert on_disk == json.loads(json.dumps(doc)) and "focus_cues" in on_disk
    cues = json.loads((out / "focus_cues.json").read_text())
    assert (out / "focus_cues.png").stat().st_size > 0
    assert 1 <= cues["bands"] and all(r["sharpest_diopters"] is not None for r in cues["results"])


def test_a_failed_render_leaves_an_existing_stack_as_it_was(scenes, tmp_path, capsys, monkeypatch):
    """A bad --seed is refused before any work, and a render that fails midway (here: its
    natural view raises) leaves the folder of an earlier stack byte for byte as it was."""
    out = tmp_path / "fs"
    args = ["focal-stack", "--focus-mm", "1000", "--spp", "1", "--resolution", "48,27", "--out", str(out), "--json"]
    assert main(args) == 0
    capsys.readouterr()
    before = {p.name: p.read_bytes() for p in out.iterdir()}
    assert main(args + ["--seed", "-1"]) == 2 and "--seed" in capsys.readouterr().err
    import lfsim.render.focal_stack as fs

    def broken(*a, **k):
        raise RuntimeError("render failed midway")

    monkeypatch.setattr(fs, "write_png", broken)
    with pytest.raises(RuntimeError, match="midway"):
        fs.focal_stack(lfsim.load(scenes / "ini_ideal.toml"), load_content(scenes / "fig9_wall.toml"), out,
                       fs.FocalStackSpec(focus_mm=[1000.0], spp=1, resolution=(48, 27)), log=lambda m: None)
    assert {p.name: p.read_bytes() for p in out.iterdir()} == before
    assert [p.name for p in tmp_path.iterdir()] == ["fs"]  # no temporary folder left behind


def test_the_runner_up_peak_of_a_sharpness_profile():
    """Two Gaussian bumps: the sharpest band is the higher one's centre (parabola-refined on the
    three-band smoothed profile), the runner-up the lower one's, with the ratio of their smoothed
    heights; one bump has no runner-up, and a shoulder within 0.15 D of the peak is not one."""
    from lfsim.vision.focus_cues import _smoothed, peak_diopters, runner_up

    D = np.linspace(0.6, 2.0, 57)
    rng = np.random.default_rng(1)
    order = rng.permutation(len(D))  # the profile's bands come in image-column order, not by depth

    def bump(c, h, w=0.08):
        return h * np.exp(-0.5 * ((D - c) / w) ** 2)

    S = 0.1 + bump(1.3, 1.0) + bump(0.9, 0.8)
    assert peak_diopters(D[order], S[order]) == pytest.approx(1.3, abs=0.01)
    second = runner_up(D[order], S[order])
    Ds, Ss = _smoothed(D, S)
    assert second[0] == pytest.approx(0.9, abs=0.01)
    assert second[1] == pytest.approx(Ss[np.argmin(abs(Ds - 0.9))] / Ss.max(), rel=1e-3)
    assert 0.7 < second[1] < 0.9
    # Equal bumps: the ratio reaches 1, whichever is called the peak.
    S2 = 0.1 + bump(1.3, 1.0) + bump(0.9, 1.0)
    assert runner_up(D, S2)[1] == pytest.approx(1.0, abs=1e-9)
    assert runner_up(D, 0.1 + bump(1.3, 1.0)) is None
    assert runner_up(D, 0.1 + bump(1.3, 1.0) + bump(1.4, 0.9, w=0.02)) is None  # a shoulder, not a peak
    assert runner_up(D[:2], S[:2]) is None and runner_up(D, np.zeros_like(D)) is None
