"""lfsim regress: a reseeded render passes; an MLA moved by 20 µm or an eye defocused by 0.1 D fails.

One baseline of the ideal InI-HMD (Fig. 9 wall, eye focused at the CDP, 750
mm; 256x144 px, 16 spp, two seeds) serves every check here. Design metrics
on a lenslet stride of 4 at the 1 D CDP state, without the contrast search.
"""

import json
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest

from lfsim.cli import main
from lfsim.regression import baseline as bl
from lfsim.regression import check, update

SCENES = Path(__file__).resolve().parents[1] / "scenes"

DESIGN = str(SCENES / "ini_ideal.toml")
CONTENT = str(SCENES / "fig9_wall.toml")
FAST_METRICS = "ini.analysis.refine=0"
OPTIONS = {"content": CONTENT, "resolution": (256, 144), "spp": 16, "focus_mm": [750.0], "stride": (4, 4),
           "depths": [1.0], "set": [FAST_METRICS]}
#: The MLA moved 20 µm toward the eye: display gap 4.5 -> 4.52 mm, MLA to tunable lens 46.75 -> 46.73 mm.
MLA_20UM = ["object.distance=4.52", "MLA.thickness=46.73"]


@pytest.fixture(scope="module")
def base(tmp_path_factory):
    folder = tmp_path_factory.mktemp("regress") / "baseline"
    update(DESIGN, folder, OPTIONS)
    return folder


def _junit_cases(path):
    root = ET.parse(path).getroot()
    assert root.tag == "testsuites"
    suites = root.findall("testsuite")
    assert len(suites) == 1
    s = suites[0]
    cases = s.findall("testcase")
    assert int(s.get("tests")) == len(cases) == int(root.get("tests"))
    failed = {c.get("name"): c.find("failure").get("type") for c in cases if c.find("failure") is not None}
    assert int(s.get("failures")) == len(failed)
    return {c.get("name") for c in cases}, failed


def test_baseline_folder(base):
    doc = bl.read(base)
    assert doc["seeds"] == [0, 1] and doc["options"]["spp"] == 16 and doc["options"]["resolution"] == [256, 144]
    assert doc["options"]["focus_mm"] == [750.0] and doc["options"]["set"] == [FAST_METRICS]
    assert len(doc["images"]) == 4 and all((base / im["exr"]).is_file() for im in doc["images"])
    assert (base / "design.toml").is_file() and doc["design"]["sha256"]
    assert doc["tolerances"]["z_max"] == 4.0 and "summary.contrast_nyquist_min" in doc["metrics"]
    n = doc["noise"]["display 750 mm"]
    assert 0.05 < n["rms_noise"] < 0.5 and n["reseed_change_threshold"] > 0
    assert not list(base.parent.glob(".baseline.*"))  # no temporary folders left behind


def test_reseeded_render_passes(base, tmp_path):
    out = tmp_path / "out"
    r = check(DESIGN, base, {"seed": 7}, out_dir=out, junit=tmp_path / "junit.xml")
    assert r.doc["seeds"] == {"baseline": [0, 1], "candidate": [7, 8], "common_random_numbers": False}
    assert not r.failed, r.table()
    images = [c for c in r.checks if c.group == "image"]
    assert len(images) == 5  # display: image, detail, error vs natural; natural: image, detail
    for c in images:
        assert abs(c.z) < 4 and abs(c.change) <= c.tolerance, c
    names, failed = _junit_cases(tmp_path / "junit.xml")
    assert names == {c.name for c in r.checks} and not failed
    rep = json.loads((out / "report.json").read_text())
    assert rep["failed"] is False and len(rep["checks"]) == len(r.checks)
    assert "passed" in (out / "report.txt").read_text()
    assert (out / "heatmaps" / "display_750mm.png").is_file()


def test_mla_moved_20um_fails_with_the_right_rows(base, tmp_path, capsys):
    junit = tmp_path / "junit.xml"
    argv = ["regress", DESIGN, "--baseline", str(base), "--out", str(tmp_path / "out"), "--junit", str(junit)]
    for s in [FAST_METRICS, *MLA_20UM]:
        argv += ["--set", s]
    assert main(argv) == 1
    text = capsys.readouterr().out
    rep = json.loads((tmp_path / "out" / "report.json").read_text())
    status = {c["name"]: c["status"] for c in rep["checks"]}
    # what the eye sees changed (the field of view shrinks, so the natural view over it changes too) ...
    assert status["display 750 mm: image"] == "changed"
    assert status["render fov_deg[0]"] == "changed" and status["render tunable_power_diopters"] == "changed"
    # ... and the design metrics: Nyquist frequency, first-order data, and contrast at Nyquist got worse
    assert status["metric summary.nyquist_cpd"] == "changed"
    assert status["metric by_depth[1].first_order.pixel_arcmin[0]"] == "changed"
    assert status["metric summary.contrast_nyquist_min"] == "worse"
    # GD and PA are zero for ideal lenslets, moved or not
    assert status["metric summary.gd_max_deg"] == "ok" and status["metric summary.pa_max"] == "ok"
    for row in ("display 750 mm: image", "metric summary.contrast_nyquist_min", "WORSE", "CHANGED"):
        assert row in text
    assert rep["options_changed"]["set"]["candidate"] == [FAST_METRICS, *MLA_20UM]
    names, failed = _junit_cases(junit)
    assert names == set(status)
    assert failed == {n: s for n, s in status.items() if s in ("worse", "changed")}


def test_eye_defocused_by_0_1_diopter_fails(base, tmp_path):
    focus = 1000.0 / (1000.0 / 750.0 + 0.1)
    r = check(DESIGN, base, {"focus_mm": [focus]}, out_dir=tmp_path / "out")
    assert r.failed
    failed = {c.name: c for c in r.failing()}
    label = f"750 mm (candidate {focus:g} mm)"
    assert f"display {label}: image" in failed and f"natural {label}: image" in failed
    assert all(c.group == "image" for c in failed.values())  # the design is unchanged: metrics pass
    assert all(c.status == "ok" for c in r.checks if c.group != "image")
    c = failed[f"display {label}: image"]
    assert c.z > 4 and c.change > c.tolerance
    assert f"display {label}: image" in r.table()


def test_regress_bad_input_exits_2(base, tmp_path, capsys):
    out = tmp_path / "out"
    cases = [
        (["--baseline", str(tmp_path / "none")], "baseline.json: missing"),
        (["--baseline", str(base), "--spp", "32"], "--spp = 32"),
        (["--baseline", str(base), "--resolution", "128,72"], "--resolution = 128,72"),
        (["--baseline", str(base), "--focus-mm", "600,700"], "--focus-mm = 600,700"),
        (["--baseline", str(base), "--set", "MLA.nope=1"], "MLA.nope"),
        (["--baseline", str(base), "--spp", "0"], "--spp = 0"),
        (["--baseline", str(base), "--update", "--junit", str(tmp_path / "j.xml")], "--junit"),
        (["--baseline", str(tmp_path), "--update"], "not a previous output of this kind (no baseline.json)"),
    ]
    (tmp_path / "keep.txt").write_text("a file that --update must not delete")
    for args, fragment in cases:
        assert main(["regress", DESIGN, "--out", str(out), *args]) == 2, args
        err = capsys.readouterr().err
        assert err.startswith("lfsim: error: ") and err.count("\n") == 1 and fragment in err, (args, err)
    assert not out.exists() and (tmp_path / "keep.txt").is_file()
    broken = tmp_path / "broken"
    broken.mkdir()
    (broken / "baseline.json").write_text("{not json")
    assert main(["regress", DESIGN, "--baseline", str(broken)]) == 2
    assert "baseline.json: not a readable baseline" in capsys.readouterr().err
