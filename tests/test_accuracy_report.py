"""`benchmarks/accuracy_report.py --quick`: a table row and a plot per knob, figures measured, files atomic."""

import importlib.util
import json
import re
import sys
from pathlib import Path

import numpy as np

_PATH = Path(__file__).resolve().parents[1] / "benchmarks" / "accuracy_report.py"
_SPEC = importlib.util.spec_from_file_location("accuracy_report", _PATH)
accuracy_report = importlib.util.module_from_spec(_SPEC)
sys.modules["accuracy_report"] = accuracy_report  # dataclasses resolve their module by name
_SPEC.loader.exec_module(accuracy_report)

KNOBS = ["tracer_precision", "newton_tol", "newton_max_iter", "pupil", "mtf_grid", "fields", "refine", "stride", "spp",
         "tessellation", "wavelength_samples", "sampler", "ei_spp", "accommodation"]


def test_quick_report_has_a_row_and_a_plot_per_knob(tmp_path):
    out = tmp_path / "docs"
    doc = accuracy_report.report(out, quick=True)
    doc = json.loads(json.dumps(doc))  # JSON-ready
    assert [k["key"] for k in doc["knobs"]] == KNOBS
    md = (out / "accuracy.md").read_text()
    summary = md.split("## Summary", 1)[1].split("\n## ", 1)[0]
    for k in doc["knobs"]:
        # One summary row per knob, linking to its section, and a section with a table and a plot.
        assert len(re.findall(rf"^\| {k['stage']} \| \[[^]]+\]\(#{k['key']}\) \|", summary, re.M)) == 1, k["key"]
        assert f'<a id="{k["key"]}"></a>' in md and f"](img/accuracy_{k['key']}.png)" in md
        png = out / "img" / f"accuracy_{k['key']}.png"
        assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and png.stat().st_size > 10_000
        # Every row: a setting, finite errors (or none where every ray failed), a positive time.
        assert k["rows"], k["key"]
        for r in k["rows"]:
            assert r["seconds"] > 0 and all(e is None or (np.isfinite(e) and e >= 0) for e in r["errors"])
        assert any(r["setting"] == k["default"] for r in k["rows"]), k["key"]  # the default is measured
    assert "**Default and why.**" in md and md.count("**Default and why.**") == len(KNOBS)
    assert not list(out.rglob(".*"))  # no temporary files left behind
    by = {k["key"]: k for k in doc["knobs"]}
    # Physics the figures must show: float32 is farther from the reference than float64 …
    prec = {r["setting"]: r["errors"][0] for r in by["tracer_precision"]["rows"]}
    assert prec["float32"] > 1e3 * prec["float64"]
    # … one Newton iteration cannot converge (every ray flagged), the default can …
    cap = {r["setting"]: r["errors"][1] for r in by["newton_max_iter"]["rows"]}
    assert cap["1"] == 1.0 and cap["16"] == 0.0
    # … and Monte Carlo noise falls with the samples per pixel.
    spp = [r["errors"][0] for r in by["spp"]["rows"]]
    assert spp == sorted(spp, reverse=True)
    # … and the wavelength quadrature's error with its nodes (one node per primary: the worst).
    wav = {int(r["setting"]): r["errors"][0] for r in by["wavelength_samples"]["rows"]}
    assert wav[1] > wav[max(wav)] > 0
    # … and the jointly stratified sampler beats independent samples at the same spp.
    smp = {r["setting"]: r["errors"][0] for r in by["sampler"]["rows"]}
    assert smp["lfsim_sobol,16"] < 0.8 * smp["independent,16"], smp


def test_unwritable_out_is_refused_before_any_work(tmp_path, capsys):
    blocker = tmp_path / "file"
    blocker.write_text("x")
    assert accuracy_report.main(["--quick", "--out", str(blocker)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "--out" in err and "not a folder" in err
