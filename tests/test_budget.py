"""Bounded work: estimates before long runs, limits with override flags (lfsim.budget)."""

import json
import math
import time

import pytest

from lfsim import budget
from lfsim.cli import main


def test_estimate_formatting_and_limits():
    assert budget.duration(45) == "45 s" and budget.duration(600) == "10 min"
    assert budget.duration(4 * 3600) == "4.0 h" and budget.duration(math.inf) == "unbounded"
    assert budget.count(66.1e6) == "66.1 M" and budget.count(3.58e11) == "358 G"
    est = budget.Estimate("job", 30.0, 2e9)
    assert est.text() == "job: about 30 s, peak memory about 2 GB"
    lines = []
    assert budget.check(est, budget.Limits(max_seconds=60.0, max_bytes=3e9), log=lines.append) is est
    assert lines == ["estimate: job: about 30 s, peak memory about 2 GB"]
    short = []
    budget.check(budget.Estimate("quick", 1.0), budget.Limits(), log=short.append)
    assert short == []  # a short run prints no estimate
    with pytest.raises(budget.BudgetError, match=r"longer than --max-hours 0.005.*raise --max-hours"):
        budget.check(est, budget.Limits(max_seconds=18.0, max_bytes=3e9))
    with pytest.raises(budget.BudgetError, match=r"more memory than 1 GB \(--max-memory-gb\)"):
        budget.check(est, budget.Limits(max_seconds=60.0, max_bytes=1e9))


def test_limits_from_flags_and_context():
    class A:
        max_hours, max_memory_gb = 2.0, 8.0

    lim = budget.Limits.from_args(A())
    assert lim.max_seconds == 7200.0 and lim.memory() == 8e9
    A.max_hours = math.inf
    assert budget.Limits.from_args(A()).max_seconds == math.inf  # inf lifts the limit
    for bad in (0.0, -1.0, math.nan):
        A.max_hours = bad
        with pytest.raises(budget.BudgetError, match="--max-hours"):
            budget.Limits.from_args(A())
    assert budget.Limits().memory() == pytest.approx(budget.MEMORY_SHARE * budget.usable_memory_bytes())
    assert 1e8 < budget.usable_memory_bytes() < 1e15
    with budget.use(budget.Limits(max_seconds=5.0)):
        assert budget.current().max_seconds == 5.0
    assert budget.current().max_seconds == budget.DEFAULT_MAX_HOURS * 3600


def test_focal_stack_estimate_scales_with_the_work():
    from lfsim.render.focal_stack import FocalStackSpec, estimate

    spec = FocalStackSpec(focus_mm=[600.0, 1000.0], spp=16)
    a = estimate(spec, (100, 50), 10_000)
    b = estimate(FocalStackSpec(focus_mm=[600.0, 1000.0], spp=64), (200, 100), 10_000)
    assert "5 images at 100x50 px x 16 spp" in a.text()
    # 16x the samples and 4x the pixels: all but the elemental images' time grows by 4x to 16x
    ei = 10_000 / (budget.threads() * budget.RATES["elemental_px"])
    assert 4 < (b.seconds - ei) / (a.seconds - ei) < 16
    assert b.bytes > a.bytes > budget.BASE_BYTES
    # Per sample the mesh path costs more (both monochrome: the mesh path renders one pass).
    mono = estimate(FocalStackSpec(focus_mm=[600.0, 1000.0], spp=16, wavelength_nm=550.0), (100, 50), 10_000)
    mesh = estimate(FocalStackSpec(focus_mm=[600.0, 1000.0], spp=16, optics="mesh"), (100, 50), 10_000)
    assert mesh.seconds > mono.seconds
    # A spectral render costs a pass per primary on the display path and, with diffraction,
    # in the natural view too.
    assert a.seconds - ei > 1.5 * (mono.seconds - ei)


def test_huge_render_is_refused_before_any_work(scenes, tmp_path, capsys):
    out = tmp_path / "fs"
    t0 = time.perf_counter()
    assert main(["focal-stack", str(scenes / "ini_ideal.toml"), "--resolution", "40000,20000",
                 "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "40000x20000 px" in err and "raise --max-memory-gb" in err and err.count("\n") == 1, err
    assert time.perf_counter() - t0 < 60 and not out.exists()
    assert not list(tmp_path.iterdir())  # no temporary folder left beside it
    # the override lifts the memory limit; the time limit still holds it back
    assert main(["focal-stack", str(scenes / "ini_ideal.toml"), "--resolution", "4000,2000", "--spp", "100000",
                 "--max-memory-gb", "inf", "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "longer than --max-hours 24" in err and not out.exists(), err
    assert main(["focal-stack", "--max-hours", "nan", "--out", str(out)]) == 2
    assert "--max-hours = nan" in capsys.readouterr().err


def test_gradcheck_estimate_is_checked(scenes, capsys):
    assert main(["gradcheck", str(scenes / "ini_ideal.toml"), "--param", "object.distance",
                 "--resolution", "4000,3000", "--spp", "64"]) == 2
    err = capsys.readouterr().err
    assert "gradient check of 1 parameter(s)" in err and "--max-memory-gb" in err, err


def test_tolerance_trials_bounded_by_memory(scenes, tmp_path, capsys):
    out = tmp_path / "tol"
    assert main(["tolerance", str(scenes / "ini_freeform_optimized.toml"), "--out", str(out), "--trials", str(10 ** 12),
                 "--scheduler", "serial"]) == 2
    err = capsys.readouterr().err
    assert "tolerance run of 1,000,000,000,000 trials" in err and "lower --trials" in err, err
    assert not out.exists()


def test_sweep_probe_refuses_a_long_run_and_leaves_the_folder(scenes, tmp_path, capsys):
    """A sweep of >= 8 points times two of them, then refuses a run beyond --max-hours; an
    earlier sweep in --out is left as it was."""
    out = tmp_path / "sw"
    out.mkdir()
    (out / "sweep.json").write_text(json.dumps({"points": []}))
    before = (out / "sweep.json").read_bytes()
    argv = ["sweep", str(scenes / "ini_ideal.toml"), "--set", "mla.pitch_x=0.95:1.05:8", "--stride", "8,8",
            "--scheduler", "serial", "--out", str(out)]
    assert main(argv + ["--max-hours", "1e-7"]) == 2
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert "sweep points: 6 more at" in err and "(measured on the second)" in err and "--max-hours" in err, err
    assert sorted(p.name for p in out.iterdir()) == ["sweep.json"] and (out / "sweep.json").read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["sw"]


def test_tolerance_refused_after_its_probe_leaves_nothing(scenes, tmp_path, capsys):
    out = tmp_path / "tol"
    assert main(["tolerance", str(scenes / "ini_freeform_optimized.toml"), "--out", str(out), "--trials", "4",
                 "--no-sensitivity", "--scheduler", "serial", "--max-hours", "1e-9"]) == 2
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert "tolerance trials and ±limit runs:" in err and "(measured on the second)" in err, err
    assert not out.exists()


def test_small_sweep_is_probed_too(scenes, tmp_path, capsys):
    out = tmp_path / "sw"
    assert main(["sweep", str(scenes / "ini_ideal.toml"), "--set", "mla.pitch_x=0.99:1.01:3", "--stride", "8,8",
                 "--scheduler", "serial", "--out", str(out), "--max-hours", "1e-9"]) == 2
    assert "sweep points: 1 more at" in capsys.readouterr().err and not out.exists()


def test_flag_type_errors_are_one_line_naming_the_verb(capsys):
    with pytest.raises(SystemExit) as e:
        main(["focal-stack", "--max-hours", "abc"])
    assert e.value.code == 2
    assert capsys.readouterr().err == "lfsim: error: focal-stack: argument --max-hours: invalid float value: 'abc'\n"
