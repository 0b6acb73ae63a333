"""`lfsim lens`: the lens data table of every shipped design, row by row against its file."""

from __future__ import annotations

import json
import math
import tomllib

import pytest
from conftest import SCENES

from lfsim.cli import main

DESIGNS = sorted(p for p in SCENES.glob("*.toml") if "surfaces" in tomllib.loads(p.read_text()))

#: Schott catalog nd and Vd (Schott optical glass data sheets).
SCHOTT = {"N-BK7": (1.51680, 64.17), "N-LAK22": (1.65113, 55.89), "N-SF11": (1.78472, 25.68)}


@pytest.mark.parametrize("path", DESIGNS, ids=lambda p: p.stem)
def test_lens_table_rows_are_the_design_file(path, capsys):
    assert main(["lens", str(path), "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    raw = tomllib.loads(path.read_text())["surfaces"]
    rows = doc["surfaces"]
    assert [r["name"] for r in rows] == [s["name"] for s in raw]
    assert [r["number"] for r in rows] == list(range(1, len(raw) + 1))
    for r, s in zip(rows, raw):
        assert r["thickness_mm"] == pytest.approx(s.get("thickness", 0.0), abs=0.0), r["name"]
        if "radius" in s and math.isfinite(s["radius"]):
            assert r["radius_mm"] == pytest.approx(s["radius"], rel=1e-12), r["name"]
        elif s.get("curvature", 0.0):
            assert r["radius_mm"] == pytest.approx(1.0 / s["curvature"], rel=1e-12), r["name"]
        elif s.get("type") != "coordinate_break":  # flat (a radius of inf in the file)
            assert r["radius_mm"] is None, r["name"]
        assert r["conic"] == s.get("conic", 0.0)
        assert r["stop"] == s.get("stop", False)
        for k, v in s.get("asphere", {}).items():
            assert r["asphere"][k] == v
        for k, v in s.get("xy", {}).items():
            assert v == 0.0 or r["xy"][k] == v
        if s.get("mirror"):
            assert r["material"] == "MIRROR"
        elif isinstance(s.get("material"), str) and not s.get("tir"):
            assert r["material"].lower() == s["material"].lower()
        if r["material"] in SCHOTT:
            nd, vd = SCHOTT[r["material"]]
            assert r["nd"] == pytest.approx(nd, abs=2e-5) and r["vd"] == pytest.approx(vd, abs=0.01)
        assert all(v is None or math.isfinite(v) for v in (r["nd"], r["vd"], r["radius_mm"]))
    # The text table: a header, the object row, one line per surface.
    assert main(["lens", str(path)]) == 0
    text = capsys.readouterr().out.splitlines()
    assert len(text) == 3 + len(raw) and text[2].split()[0] == "OBJ"


def test_lens_table_of_the_prism_and_the_lenslets(capsys):
    assert main(["lens", str(SCENES / "ini_freeform_optimized.toml")]) == 0
    text = capsys.readouterr().out
    s3 = next(line for line in text.splitlines() if line.split()[1] == "S3")
    assert "XY polynomial" in s3 and "MIRROR" in s3 and "tilt" in s3 and "(global)" in s3
    assert "TIR (PMMA)" in next(line for line in text.splitlines() if line.split()[1] == "S2")
    l1 = next(line for line in text.splitlines() if line.split()[1] == "L1")
    assert "array mla 17x9 @ 1x1 mm" in l1 and "STOP" in l1 and "rectangular 1 x 1 mm" in l1


def test_lens_table_bad_input(tmp_path, capsys):
    assert main(["lens", str(tmp_path / "missing.toml")]) == 2
    assert main(["lens", str(SCENES / "fig9_wall.toml")]) == 2
    assert "content scene" in capsys.readouterr().err
