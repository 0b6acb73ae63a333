"""The lfsim command: trace, first-order, layout; exit codes and outputs."""

import argparse
import json

import numpy as np
import pytest

from lfsim.cli import main, read_rays_csv


def test_trace_csv_and_json(scenes, tmp_path, capsys):
    rays = tmp_path / "rays.csv"
    rays.write_text("x,y,z,dx,dy,dz\n0,0,-5,0,0,1\n0,2,-5,0,0,1\n0,30,-5,0,0,1\n")
    out = tmp_path / "out.csv"
    assert main(["trace", str(scenes / "cooke_triplet.toml"), "--rays", str(rays), "--out", str(out)]) == 0
    lines = out.read_text().strip().splitlines()
    assert lines[0].startswith("# Cooke triplet") and "x,y,z in mm" in lines[0] and "7 behind" in lines[0]
    rows = [line.split(",") for line in lines[1:]]
    assert rows[0] == ["x", "y", "z", "dx", "dy", "dz", "status", "status_name", "opl"]
    assert float(rows[1][2]) == 60.17675 and rows[1][6:8] == ["0", "ok"] and rows[3][6:8] == ["1", "missed"]
    o, d = read_rays_csv(str(out))  # the output reads back as rays (the comment line is skipped)
    assert o.shape == (3, 3) and float(o[0, 2]) == 60.17675
    assert main(["trace", str(scenes / "cooke_triplet.toml"), "--rays", str(rays), "--json",
                 "--precision", "float32", "--wavelength-nm", "486.1327"]) == 0
    data = json.loads(capsys.readouterr().out)
    assert data["precision"] == "float32" and len(data["rays"]) == 3
    assert abs(data["rays"][1]["position"][2] - 60.17675) < 1e-4


def test_trace_bad_rays_file_exits_2(scenes, tmp_path, capsys):
    design = str(scenes / "cooke_triplet.toml")
    cases = {
        "x,y,z,dx,dy\n0,0,0,0,1\n": "column 'dz' missing",
        "x,y,z,dx,dy,dz\n0,0,abc,0,0,1\n": "line 2 column 'z' = 'abc'",
        "x,y,z,dx,dy,dz\n0,0,0,0,0,0\n": "must be nonzero",
        "x,y,z,dx,dy,dz\n0,0,inf,0,0,1\n": "finite",
    }
    for text, fragment in cases.items():
        p = tmp_path / "r.csv"
        p.write_text(text)
        out = tmp_path / "never.csv"
        assert main(["trace", design, "--rays", str(p), "--out", str(out)]) == 2
        err = capsys.readouterr().err
        assert fragment in err and str(p) in err and err.count("\n") == 1, err
        assert not out.exists()
    assert main(["trace", design, "--rays", str(tmp_path / "missing.csv")]) == 2
    assert main(["trace", design, "--rays", str(p), "--wavelength-nm", "-3"]) == 2


def test_first_order_json(scenes, capsys):
    assert main(["first-order", str(scenes / "cooke_triplet.toml"), "--json"]) == 0
    d = json.loads(capsys.readouterr().out)
    assert abs(d["efl"] - 50.0216) < 1e-3 and d["method"] == "paraxial"
    assert abs(d["entrance_pupil_diameter"] - 10.0) < 1e-12


def test_layout_of_an_ini_design_draws_its_sub_systems(scenes, tmp_path, capsys):
    """An InI design's layout: the InI first order of every CDP state and the package
    (what `lfsim ini` and `analyze` report), no conventional focal lengths or spots; its
    rays are aimed sub-system rays, which end where :func:`trace_rays` puts them on the
    viewing window, and the EI centres' chief rays of the ideal design all pass through the
    window's centre (Eq. 2)."""
    import lfsim
    from lfsim.analysis.layout import ini_ray_sets
    from lfsim.ini.model import IniModel
    from lfsim.ini.package import package
    from lfsim.ini.subsystems import sample, trace_rays

    out = tmp_path / "lay"
    assert main(["layout", str(scenes / "ini_ideal.toml"), "--out", str(out)]) == 0
    text = capsys.readouterr().out
    assert sorted(p.name for p in out.iterdir()) == ["layout.png", "summary.json"]
    s = json.loads((out / "summary.json").read_text())
    model = IniModel(lfsim.load(scenes / "ini_ideal.toml"))
    assert s["ini"]["lenslets"] == [17, 9] and s["ini"]["display_gap_mm"] == pytest.approx(4.5, rel=1e-12)
    for k, D in enumerate(model.depths):
        fo = model.state(k).as_dict()
        assert s["ini"]["first_order"][f"{D:g}"]["fov_deg"] == pytest.approx(fo["fov_deg"], rel=1e-12)
        assert f"CDP {D:g} D: FOV {fo['fov_deg'][0]:.1f} x {fo['fov_deg'][1]:.1f} deg" in text
    assert s["package"]["track_mm"] == pytest.approx(package(model)["track_mm"], rel=1e-12)
    assert "EFL" not in text and "package: track" in text
    sets = ini_ray_sets(model, 1)
    assert [label for label, _, _ in sets] == ["(9, 1)", "(9, 5)", "(9, 9)"]
    R, o = model.tracer.frames_numpy()[model.spec.viewing_window]
    subs = sample(model, lenslets=[(8, 0), (8, 4), (8, 8)], depths=[1], fields=[[0.0, 0.0], [0.0, 0.9], [0.0, -0.9]])
    for i, (_, pts, ok) in enumerate(sets):
        assert ok.all() and pts.shape == (len(model.system.surfaces) + 1, 9, 3)
        np.testing.assert_allclose(pts[0, :, :2], np.repeat(subs.display[i], 3, axis=0), atol=1e-12)
        rho = np.tile([[0.0, 0.0], [0.0, 1.0], [0.0, -1.0]], (3, 1))
        pos, _, _, status, _ = trace_rays(model, np.repeat(subs.display[i], 3, axis=0), subs.m[i], subs.n[i], rho, 1)
        assert np.all(status == 0)
        local = (pts[-1] - o) @ R  # the window frame
        np.testing.assert_allclose(local[:, :2], pos, atol=1e-9)
        np.testing.assert_allclose(local[:, 2], 0.0, atol=1e-9)
        np.testing.assert_allclose(pos[0], [0.0, 0.0], atol=1e-9)  # EI centre, chief ray: the window centre
    assert "paraxial CDP" not in text  # the ideal design's CDPs are stigmatic
    # The wearable's prism makes its paraxial CDPs astigmatic: each state shows its x and y.
    assert main(["layout", str(scenes / "ini_wearable_optimized.toml"), "--out", str(tmp_path / "w")]) == 0
    text = capsys.readouterr().out
    wear = IniModel(lfsim.load(scenes / "ini_wearable_optimized.toml"))
    for k, D in enumerate(wear.depths):
        fo = wear.state(k).as_dict()
        assert f"CDP {D:g} D: FOV" in text and \
            f"paraxial CDP x {fo['cdp_diopters_x']:.2f} y {fo['cdp_diopters_y']:.2f} D" in text


def test_layout_writes_pictures_and_summary(scenes, tmp_path, capsys):
    out = tmp_path / "lay"
    assert main(["layout", str(scenes / "cooke_triplet.toml"), "--out", str(out)]) == 0
    for f in ("layout.png", "spots.png", "summary.json"):
        assert (out / f).stat().st_size > 1000 or f == "summary.json"
    s = json.loads((out / "summary.json").read_text())
    rms = [row["rms_um"] for row in s["spots"]]
    assert len(rms) == 3 and all(0 < v < 50 for v in rms)
    assert not list(out.glob(".*"))  # no temporary files left behind
    assert np.isfinite(s["first_order"]["efl"])
    # The spot diagrams' Airy circle: radius 1.22 λ F/# at the primary wavelength (µm).
    assert s["airy_radius_um"] == pytest.approx(1.22 * 0.5875618 * s["first_order"]["fno"], rel=1e-12)


def test_trace_reports_lenslets_for_arrays(tmp_path, capsys):
    d = tmp_path / "mla.toml"
    d.write_text("""
[arrays.mla]
m = 3
n = 3
pitch = 1.0
[[surfaces]]
radius = 1.5
thickness = 1.0
material = 1.5
array = "mla"
[[surfaces]]
thickness = 2.0
array = "mla"
[[surfaces]]
dummy = true
""")
    rays = tmp_path / "r.csv"
    rays.write_text("x,y,z,dx,dy,dz\n1,-1,-1,0,0,1\n0.45,0,-0.01,0.5,0,1\n")
    assert main(["trace", str(d), "--rays", str(rays), "--json"]) == 0
    out = json.loads(capsys.readouterr().out)["rays"]
    assert out[0]["lenslet"] == [2, 0] and out[0]["status_name"] == "ok"
    assert out[1]["status_name"] == "wrong_lenslet"
    assert main(["trace", str(d), "--rays", str(rays)]) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    assert lines[0].startswith("# ") and lines[1].endswith("status,status_name,opl,m,n")
    assert lines[2].endswith(",2,0") and ",ok," in lines[2]


def test_ini_first_order_verb(capsys):
    args = ["ini", "--p-mla", "1", "--g", "3.5", "--f-mla", "3", "--z-xp", "25", "--f-ep", "25",
            "--m", "17", "--n", "9"]
    assert main(args + ["--cdp-diopters", "0", "--json"]) == 0
    d = json.loads(capsys.readouterr().out)
    for key in ("p_mla", "g", "l", "z_ic", "z_xp", "f_ep", "z_cdp", "m", "n", "p_ei", "z_xp_image",
                "d_v", "D_v", "delta_p_eic", "p_eic", "fov_diag_deg"):
        assert key in d
    assert d["z_cdp"] is None and d["z_xp_image"] is None and d["p_ei"] == 1.0  # 0 D, telecentric
    assert abs(d["fov_diag_deg"] - 2 * np.degrees(np.arctan(np.hypot(17, 9) / 2 / 25))) < 1e-9
    assert main(args + ["--z-ic", "19", "--cdp-diopters", "3"]) == 2
    assert "disagrees" in capsys.readouterr().err
    assert main(["ini", "--p-mla", "0", "--g", "3.5", "--f-mla", "3", "--z-xp", "25", "--f-ep", "25",
                 "--m", "17", "--n", "9", "--z-ic", "19"]) == 2
    assert "p_mla = 0.0" in capsys.readouterr().err


def _blocked(tmp_path):
    """A path under a regular file: no output can be written there."""
    f = tmp_path / "a_file"
    f.write_text("x")
    return f / "sub"


def _fails_fast(capsys, argv, needle):
    import time

    t0 = time.perf_counter()
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert needle in err and "\n" not in err and "Traceback" not in err, err
    assert time.perf_counter() - t0 < 60.0  # refused before the work (which takes minutes), not after
    return err


def test_options_are_checked_before_any_work(scenes, tmp_path, capsys):
    """Unwritable outputs, unbounded sweeps, a NaN limit, an empty --resume folder and a zero
    resolution are refused with one line and exit 2 before any work, and leave nothing behind."""
    blocked = _blocked(tmp_path)
    _fails_fast(capsys, ["regress", str(scenes / "ini_ideal.toml"), "--baseline",
                         str(scenes.parent / "tests/lfsim_baselines/test_ini_ideal_fig9_wall"),
                         "--junit", str(blocked / "x.xml")], "--junit")
    sweep_out = tmp_path / "sweep"
    err = _fails_fast(capsys, ["sweep", str(scenes / "ini_ideal.toml"), "--out", str(sweep_out),
                               "--set", "mla.pitch_x=0.9:1.1:100000000"], "--max-points")
    assert "100,000,000 points" in err and not sweep_out.exists()
    _fails_fast(capsys, ["sweep", str(scenes / "ini_ideal.toml"), "--out", str(blocked),
                         "--set", "mla.pitch_x=0.9:1.1:3"], "--out")
    a = tmp_path / "a.exr"
    from lfsim.render.focal_stack import write_exr

    write_exr(a, np.zeros((4, 4, 3), np.float32), {})
    for flag, v in (("--min-psnr", "nan"), ("--min-ssim", "1.5"), ("--max-abs", "-1")):
        _fails_fast(capsys, ["compare", str(a), str(a), flag, v], flag)
    empty = tmp_path / "empty"
    empty.mkdir()
    _fails_fast(capsys, ["tolerance", str(scenes / "ini_freeform_optimized.toml"), "--out", str(empty),
                         "--resume", "--trials", "2"], "holds no tolerance run")
    assert not any(empty.iterdir())
    _fails_fast(capsys, ["tolerance", str(scenes / "ini_freeform_optimized.toml"), "--out", str(tmp_path / "tol"),
                         "--scheduler", "tcp://127.0.0.1:1", "--trials", "2"], "no scheduler answers")
    assert not (tmp_path / "tol").exists()
    _fails_fast(capsys, ["focal-stack", "--resolution", "0,0", "--out", str(tmp_path / "fs")],
                "both values must be >= 1")
    assert not (tmp_path / "fs").exists()


def test_text_output_has_units_and_no_python_values(scenes, tmp_path, capsys):
    """first-order prints each quantity with its unit, and a design without an entrance
    pupil (EPD 0, the documented default) reports its F-number as undefined, in
    first-order and in layout (which used to crash on it after writing its files)."""
    text = (scenes / "cooke_triplet.toml").read_text()
    assert 'aperture = { type = "epd", value = 10.0 }' in text
    p = tmp_path / "epd0.toml"
    p.write_text(text.replace('aperture = { type = "epd", value = 10.0 }', 'aperture = { type = "epd", value = 0.0 }'))
    assert main(["first-order", str(scenes / "cooke_triplet.toml")]) == 0
    out = capsys.readouterr().out
    assert "efl                        50.02159651 mm" in out and "fno                        5.002159651\n" in out
    assert main(["first-order", str(p)]) == 0
    out = capsys.readouterr().out
    assert "fno                        undefined" in out and "None" not in out
    assert main(["layout", str(p), "--out", str(tmp_path / "lay")]) == 0
    out = capsys.readouterr().out
    assert "F/# undefined" in out and "None" not in out and (tmp_path / "lay" / "summary.json").exists()
    assert main(["ini", str(scenes / "ini_coaxial.toml")]) == 0
    out = capsys.readouterr().out
    assert "(" not in out.split("\n", 1)[1] and "None" not in out  # no tuple reprs below the title
    assert "    fov_deg                34.2368 x 19.7648 deg" in out
    assert "    nyquist_cpd            13.4894 cycles/deg" in out


def test_progress_prints_lines_in_a_log():
    """Without a terminal, progress comes as periodic plain lines with a count, the
    percentage and an ETA (a tqdm bar's carriage returns would pile up in a log)."""
    import io

    from lfsim.progress import LogBar

    out = io.StringIO()
    b = LogBar(total=4, desc="sub-systems", unit="sub", stream=out, interval=0.0)
    for _ in range(2):
        b.update(1)
    b.set_postfix_str("cost=1.5")
    b.update(2)
    b.close()
    lines = out.getvalue().splitlines()
    assert lines[0].startswith("sub-systems: 1/4 sub (25%), ") and "ETA" in lines[0]
    assert lines[2].startswith("sub-systems: 4/4 sub (100%)") and lines[2].endswith("cost=1.5")
    assert len(lines) == 3  # the closing line does not repeat the last update's
    assert "\r" not in out.getvalue()
    # The ETA counts the rate after the first item: the set-up before it (compiles) is not
    # repeated, so 10 s to the first of 10 items, then 1 s per item, leaves 8 s, not 80 s.
    import lfsim.progress as prog

    now = [0.0]
    real = prog.time.monotonic
    prog.time.monotonic = lambda: now[0]
    try:
        eta_out = io.StringIO()
        e = LogBar(total=10, desc="images", stream=eta_out, interval=0.0)  # t0 = 0
        now[0] = 10.0
        e.update(1)  # the first item, set-up included
        now[0] = 11.0
        e.update(1)  # the second, 1 s later
    finally:
        prog.time.monotonic = real
    assert eta_out.getvalue().splitlines()[-1].endswith("ETA 8 s"), eta_out.getvalue()
    quiet = io.StringIO()
    LogBar(total=3, stream=quiet, interval=0.0, disable=True).update(3)
    assert quiet.getvalue() == ""


def test_folder_outputs_never_replace_a_foreign_folder(scenes, tmp_path, capsys):
    """Every verb whose --out is a folder replaces that folder as a whole, so a folder that is
    not a previous output of the verb (here: one holding a user's file) is refused with one
    line and exit 2, before any work, and left exactly as it was."""
    foreign = tmp_path / "mine"
    foreign.mkdir()
    (foreign / "precious.txt").write_text("keep me")
    exr = tmp_path / "a.exr"
    from lfsim.render.focal_stack import write_exr

    write_exr(exr, np.zeros((4, 4, 3), np.float32), {})
    cases = {
        "layout": ["layout", str(scenes / "cooke_triplet.toml"), "--out", str(foreign)],
        "analyze": ["analyze", str(scenes / "ini_ideal.toml"), "--out", str(foreign), "--stride", "8,4"],
        "focal-stack": ["focal-stack", str(scenes / "ini_ideal.toml"), "--out", str(foreign),
                        "--resolution", "16,9", "--spp", "1"],
        "compare": ["compare", str(exr), str(exr), "--out", str(foreign)],
        "sweep": ["sweep", str(scenes / "ini_ideal.toml"), "--set", "mla.pitch_x=0.9:1.0:2", "--out", str(foreign),
                  "--scheduler", "serial"],
    }
    for verb, argv in cases.items():
        err = _fails_fast(capsys, argv, "--out")
        assert "not a previous output" in err, (verb, err)
        assert sorted(p.name for p in tmp_path.iterdir()) == ["a.exr", "mine"], verb  # no temporary folders
        assert [p.name for p in foreign.iterdir()] == ["precious.txt"], verb
        assert (foreign / "precious.txt").read_text() == "keep me"


def test_folder_output_is_replaced_whole_on_a_rerun(scenes, tmp_path, capsys):
    out = tmp_path / "lay"
    for _ in range(2):
        assert main(["layout", str(scenes / "cooke_triplet.toml"), "--out", str(out)]) == 0
    capsys.readouterr()
    assert sorted(p.name for p in out.iterdir()) == ["layout.png", "spots.png", "summary.json"]
    assert [p.name for p in tmp_path.iterdir()] == ["lay"]
    # An empty folder is fine too.
    empty = tmp_path / "empty"
    empty.mkdir()
    assert main(["layout", str(scenes / "cooke_triplet.toml"), "--out", str(empty)]) == 0


def test_folder_outputs_name_the_folder_given_when_it_cannot_be_written(scenes, tmp_path, capsys, monkeypatch):
    """A folder output is made beside --out and then swapped in: a parent that refuses the new
    folder (a read-only file system) is named with the option and the folder given, not the
    temporary name; a mount point, which no swap can replace, is refused before any work."""
    import errno
    import os
    import tempfile
    from pathlib import Path

    out = tmp_path / "ro" / "x"
    out.parent.mkdir()
    real = tempfile.mkdtemp

    def read_only(*a, dir=None, **kw):
        if dir is not None and Path(dir) == out.parent:
            raise OSError(errno.EROFS, os.strerror(errno.EROFS), str(Path(dir) / ".x.abc123.tmp"))
        return real(*a, dir=dir, **kw)

    monkeypatch.setattr(tempfile, "mkdtemp", read_only)
    argv = ["focal-stack", str(scenes / "ini_ideal.toml"), "--out", str(out), "--resolution", "16,9", "--spp", "1"]
    err = _fails_fast(capsys, argv, "--out")
    assert err == f"lfsim: error: --out = {str(out)!r}: cannot write in {out.parent} ({os.strerror(errno.EROFS)})"
    assert list(out.parent.iterdir()) == []
    monkeypatch.setattr(tempfile, "mkdtemp", real)

    mount = tmp_path / "mnt"
    mount.mkdir()
    real_ismount = os.path.ismount
    monkeypatch.setattr(os.path, "ismount", lambda p: Path(p) == mount or real_ismount(p))
    for argv in (["layout", str(scenes / "cooke_triplet.toml"), "--out", str(mount)],
                 ["focal-stack", str(scenes / "ini_ideal.toml"), "--out", str(mount), "--resolution", "16,9",
                  "--spp", "1"]):
        err = _fails_fast(capsys, argv, "--out")
        assert "a mount point cannot be replaced" in err, err
        assert list(mount.iterdir()) == [] and sorted(p.name for p in tmp_path.iterdir()) == ["mnt", "ro"]
    # A path that climbs out of a folder that does not exist names the folder above it, which
    # holds a user's files here: refused before any work, and the missing folder is not made.
    (tmp_path / "mnt" / "keep.txt").write_text("mine")
    argv = ["layout", str(scenes / "cooke_triplet.toml"), "--out", str(tmp_path / "mnt" / "nope" / "..")]
    err = _fails_fast(capsys, argv, "--out")
    assert "a mount point cannot be replaced" in err or "not a previous output" in err, err
    assert sorted(p.name for p in (tmp_path / "mnt").iterdir()) == ["keep.txt"]


def test_human_output_has_units_and_no_python_reprs(scenes, tmp_path, capsys):
    """Printed numbers carry units; no None, tuple reprs or float rounding noise about zero."""
    import re

    from lfsim.ini.first_order import IniFirstOrder

    runs = [["first-order", str(scenes / "cooke_triplet.toml")],
            ["ini", "--p-mla", "1", "--g", "4.5", "--f-mla", "3.5", "--cdp-diopters", "1", "--z-xp", "31",
             "--f-ep", "31", "--m", "17", "--n", "9"],
            ["ini", str(scenes / "ini_ideal.toml")],
            ["layout", str(scenes / "cooke_triplet.toml"), "--out", str(tmp_path / "lay")]]
    for argv in runs:
        assert main(argv) == 0
        out = capsys.readouterr().out
        body = "\n".join(out.splitlines()[1:])  # below the title line
        assert "None" not in body and not re.search(r"\(\d|\d\)|e-1[0-9]", body), (argv, out)
        for line in out.splitlines()[1:]:
            m = re.match(r"\s+(\w+)\s+(-?[\d.]+(?:e[+-]?\d+)?)(.*)$", line)
            if m and m.group(1) not in ("m", "n", "n_object", "n_image", "fno", "working_fno", "magnification"):
                assert m.group(3).strip(), f"{' '.join(argv)}: no unit on {line!r}"
    assert set(IniFirstOrder.UNITS) == {f for f in IniFirstOrder.__dataclass_fields__}
    assert main(["layout", str(scenes / "cooke_triplet.toml"), "--out", str(tmp_path / "lay")]) == 0
    assert "field 14°: RMS spot" in capsys.readouterr().out


def test_every_verb_prints_its_help():
    """`lfsim VERB --help` formats for every verb (a bare '%' in a help string made
    argparse raise instead of printing the help of five verbs)."""
    from lfsim.cli import build_parser

    parser = build_parser()
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    for name, sp in sub.choices.items():
        assert f"usage: lfsim {name}" in sp.format_help(), name
    assert "usage: lfsim" in parser.format_help()


def test_the_default_content_is_found_outside_the_checkout(tmp_path, monkeypatch):
    from lfsim.cli.common import DEFAULT_CONTENT, content_path
    from lfsim.content import load_content

    monkeypatch.chdir(tmp_path)
    path = content_path(DEFAULT_CONTENT)
    assert path != DEFAULT_CONTENT and load_content(path).view.design
    assert content_path("other.toml") == "other.toml"  # a file the user names is theirs to find


def test_optimize_says_when_the_renderer_will_refuse_its_output(scenes, tmp_path):
    """``lfsim optimize`` checks the design it wrote against the renderer's display rule and
    warns in one line naming the key (a stage can grow the EI layout past the display)."""
    import tomllib

    import tomli_w

    from lfsim.cli.ini import _render_refusal

    raw = tomllib.loads((scenes / "ini_wearable_optimized.toml").read_text())
    assert _render_refusal(scenes / "ini_wearable_optimized.toml") is None
    raw["ini"]["pixels_per_ei"] = [121, 121]  # 17 x 121 px of 8 µm: 16.5 mm under a 17.6 mm layout
    p = tmp_path / "narrow.toml"
    p.write_text(tomli_w.dumps(raw))
    msg = _render_refusal(p)
    assert msg is not None and "\n" not in msg and "ini.pixels_per_ei" in msg and str(p) in msg
