"""Tolerance analysis and sweeps (lfsim.tolerance): schema, draws, rigid motions, the record
store, compensators, and runs serially, on a local Dask cluster and on a Dask cluster of two
worker processes started here on loopback (identical records; a worker killed mid-run)."""

from __future__ import annotations

import json
import math
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

import lfsim
from lfsim.cli import main
from lfsim.design.errors import DesignError
from lfsim.design.tolerance_section import tolerance_from_design

ROOT = Path(__file__).resolve().parents[1]
VENV_BIN = Path(sys.executable).parent

# The ideal 17x9 InI-HMD with small tolerances and a coarse metric sampling (fast trials).
TOL = """
[tolerance]
trials = 6
seed = 3
batch = 2
compensators = ["tunable"]

[tolerance.sampling]
stride = [16, 8]
fields = 1
pupil = 2
mtf_grid = 8

[tolerance.targets]
gd_max_deg = 0.05
pa_max = 0.05
contrast_nyquist_min = 0.5

[[tolerance.parameters]]
key = "mla.center_x"
limit = 0.01
distribution = "normal"
sigma = 0.005

[[tolerance.parameters]]
name = "gap"
key = "object.distance"
limit = 0.01

[[tolerance.parameters]]
key = "EP.power"
limit = 0.002
relative = true
distribution = "truncated_normal"

[[tolerance.parameters]]
key = "ini.tunable.power_diopters[1]"
limit = 0.05
"""


@pytest.fixture(scope="module")
def design_file(tmp_path_factory):
    p = tmp_path_factory.mktemp("tol") / "ideal_tol.toml"
    p.write_text((ROOT / "scenes" / "ini_ideal.toml").read_text() + TOL)
    return p


def _variant(tmp_path, text):
    p = tmp_path / "bad.toml"
    p.write_text((ROOT / "scenes" / "ini_ideal.toml").read_text() + text)
    return p


# ------------------------------------------------------------------ schema
def test_section_parses(design_file):
    spec = tolerance_from_design(lfsim.load(design_file))
    assert spec.names == ("mla.center_x", "gap", "EP.power", "ini.tunable.power_diopters[1]")
    assert spec.parameters[2].sigma == pytest.approx(0.001)  # default limit / 2
    assert spec.targets == {"gd_max_deg": 0.05, "pa_max": 0.05, "contrast_nyquist_min": 0.5}
    assert spec.sampling["stride"] == (16, 8) and spec.compensators == ("tunable",)


@pytest.mark.parametrize("text, key", [
    ('[[tolerance.parameters]]\nkey = "MLA.curvatur"\nlimit = 0.1\n', "tolerance.parameters[0].key"),
    ('[[tolerance.parameters]]\nkey = "mla.center_x"\nlimit = -0.1\n', "tolerance.parameters[0].limit"),
    ('[[tolerance.parameters]]\nkey = "mla.center_x"\nlimit = 0.1\ndistribution = "gauss"\n',
     "tolerance.parameters[0].distribution"),
    ('[[tolerance.parameters]]\nrigid = ["EP"]\nmotion = "tilt_x"\nlimit = 0.1\n', "tolerance.parameters[0].rigid[0]"),
    ('compensators = ["EP.powr"]\n', "tolerance.compensators[0]"),
    ('[tolerance.targets]\ngd_max = 1.0\n', "tolerance.targets"),
])
def test_bad_section_is_one_line_naming_key(tmp_path, capsys, text, key):
    bad = _variant(tmp_path, "\n[tolerance]\n" + text.replace("[tolerance.targets]\n", "[tolerance.targets]\n"))
    with pytest.raises(DesignError) as e:
        tolerance_from_design(lfsim.load(bad))
    assert key in str(e.value)
    assert main(["tolerance", str(bad), "--out", str(tmp_path / "o"), "--scheduler", "serial"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and key in err and "Traceback" not in err
    assert not (tmp_path / "o" / "summary.json").exists()


def test_limit_the_design_cannot_take_is_refused(tmp_path, capsys):
    bad = _variant(tmp_path, '\n[tolerance]\n[[tolerance.parameters]]\nkey = "object.distance"\nlimit = 10.0\n')
    assert main(["tolerance", str(bad), "--out", str(tmp_path / "o"), "--scheduler", "serial"]) == 2
    assert "tolerance.parameters[0].limit" in capsys.readouterr().err


# ------------------------------------------------------------------ draws and design changes
def test_draws_depend_on_seed_and_index_only(design_file):
    from lfsim.tolerance.perturb import draw

    spec = tolerance_from_design(lfsim.load(design_file))
    a = [draw(spec, 5, i) for i in range(200)]
    assert draw(spec, 5, 17) == a[17]  # order of evaluation does not matter
    assert draw(spec, 6, 17) != a[17]
    u = np.array([d["gap"] for d in a])
    t = np.array([d["EP.power"] for d in a])
    assert np.all(np.abs(u) <= 0.01) and np.all(np.abs(t) <= 0.002)
    assert u.std() == pytest.approx(0.01 / math.sqrt(3), rel=0.2)


def test_rigid_motion_of_a_prism(tmp_path):
    from lfsim.design.tolerance_section import Tolerance
    from lfsim.tolerance.perturb import rigid_values

    d = lfsim.load(ROOT / "scenes" / "ini_freeform_optimized.toml")
    table = {n: v for n, v, _ in d.system.parameter_table()}
    t = Tolerance("p", rigid=("S1", "S2", "S3", "S4"), motion="tilt_x", pivot=(0.0, -11.0, 279.0), limit=0.05)
    v = rigid_values(d.raw, t, 0.05)
    for s in ("S1", "S2", "S3", "S4"):
        assert v[f"{s}.tilt_x"] == pytest.approx(table[f"{s}.tilt_x"] + 0.05, abs=1e-12)
        assert v[f"{s}.tilt_y"] == pytest.approx(0.0, abs=1e-12)
        p = np.array([table[f"{s}.position_{c}"] for c in "xyz"]) - np.array(t.pivot)
        q = np.array([v[f"{s}.position_{c}"] for c in "xyz"]) - np.array(t.pivot)
        assert np.linalg.norm(q) == pytest.approx(np.linalg.norm(p), rel=1e-12)  # a rotation about the pivot
        assert math.degrees(math.atan2(q[2], q[1]) - math.atan2(p[2], p[1])) == pytest.approx(0.05, abs=1e-9)
    s = rigid_values(d.raw, Tolerance("s", rigid=("S1", "S3"), motion="shift_z", limit=0.02), 0.02)
    assert s == {"S1.position_z": table["S1.position_z"] + 0.02, "S3.position_z": table["S3.position_z"] + 0.02}


def test_setting_error_applies_after_compensation(design_file):
    from lfsim.tolerance.perturb import apply_setting_errors, perturb

    d = lfsim.load(design_file)
    spec = tolerance_from_design(d)
    offs = {"ini.tunable.power_diopters[1]": 0.04}
    assert perturb(d.raw, spec, offs) is d.raw  # nothing before compensation
    raw = {**d.raw, "ini": {**d.raw["ini"], "tunable": {**d.raw["ini"]["tunable"],
                                                         "power_diopters": [0.0, -1.0, -3.0]}}}
    out = apply_setting_errors(raw, spec, offs)
    assert out["ini"]["tunable"]["power_diopters"] == pytest.approx([0.0, -0.96, -3.0])


def test_store_keeps_each_record_once_and_survives_a_torn_line(tmp_path):
    from lfsim.tolerance.store import RecordStore

    s = RecordStore(tmp_path / "r.jsonl")
    assert [r["id"] for r in s.add([{"id": "a", "v": 1}, {"id": "b", "v": 2}, {"id": "a", "v": 3}])] == ["a", "b"]
    with open(tmp_path / "r.jsonl", "a") as f:
        f.write('{"id": "c", "v"')  # interrupted mid-write
    s2 = RecordStore(tmp_path / "r.jsonl").load()
    assert sorted(s2.records) == ["a", "b"] and s2.records["a"]["v"] == 1
    s2.add([{"id": "c", "v": 4}])
    assert sorted(RecordStore(tmp_path / "r.jsonl").load().records) == ["a", "b", "c"]


def test_focus_compensator_restores_the_paraxial_depths():
    from lfsim.design.design import Design
    from lfsim.design.overrides import apply_overrides
    from lfsim.ini.model import IniModel
    from lfsim.tolerance.compensate import compensate, paraxial_depths

    path = str(ROOT / "scenes" / "ini_freeform_optimized.toml")
    d = lfsim.load(path)
    target = paraxial_depths(IniModel(d))
    bad = Design.from_dict(apply_overrides(d.raw, {"L2.thickness": d.raw["surfaces"][1]["thickness"] + 0.05}, path),
                           path)
    before = np.abs(paraxial_depths(IniModel(bad)) - target).max()
    c = compensate(bad, ["tunable"], "focus", target)
    after = np.abs(paraxial_depths(IniModel(c.design)) - target)
    assert before > 0.015  # 50 um of MLA-relay spacing defocuses by 0.02 D
    assert after.max() < 1e-6 * before  # refocused in x and y at every CDP state
    assert c.values["tunable[0]"] < 5.0  # within the lens's range (0 D is at its 5 D limit nominally)
    assert c.cost < 1e-12 * c.cost0


# ------------------------------------------------------------------ runs
def _records(out: Path, name="trials.jsonl"):
    return {r["id"]: r for r in map(json.loads, (out / name).read_text().splitlines())}


def _same(a, b):
    assert sorted(a) == sorted(b)
    for k in a:
        for f in ("offsets", "metrics", "compensators", "pass", "failed", "error"):
            assert a[k][f] == b[k][f], (k, f)


@pytest.fixture(scope="module")
def serial_run(design_file, tmp_path_factory):
    out = tmp_path_factory.mktemp("serial")
    assert main(["tolerance", str(design_file), "--out", str(out), "--scheduler", "serial", "--no-plots"]) == 0
    return out


def test_serial_run_writes_the_contract(serial_run):
    doc = json.loads((serial_run / "summary.json").read_text())
    assert doc["trials"] == 6 and len(_records(serial_run)) == 6
    assert 0.0 <= doc["yield"] <= 1.0
    assert doc["yield"] == sum(r["pass"] for r in _records(serial_run).values()) / 6
    assert [r["name"] for r in doc["sensitivity"]][:1] == ["mla.center_x"]  # registration dominates GD
    assert len(_records(serial_run, "sensitivity.jsonl")) == 1 + 2 * 4
    for r in _records(serial_run).values():
        assert r["error"] is None and set(r["compensators"]) == {"tunable[0]", "tunable[1]", "tunable[2]"}


def test_resume_extends_a_run_and_matches(serial_run, design_file, tmp_path, capsys):
    out = tmp_path / "r"
    assert main(["tolerance", str(design_file), "--out", str(out), "--scheduler", "serial", "--trials", "3",
                 "--no-plots", "--no-sensitivity"]) == 0
    assert main(["tolerance", str(design_file), "--out", str(out), "--scheduler", "serial",
                 "--no-plots"]) == 2  # a run is there: refuse without --resume
    assert "--resume" in capsys.readouterr().err
    lines = (out / "trials.jsonl").read_text().splitlines()
    (out / "trials.jsonl").write_text("\n".join(lines[:2]) + "\n" + lines[2][:25])  # interrupted mid-record
    assert main(["tolerance", str(design_file), "--out", str(out), "--scheduler", "serial", "--resume",
                 "--no-plots", "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["units_evaluated"] == 4 + 8  # trial 2 (torn) and 3..5, plus the ± runs (nominal was done)
    _same(_records(out), _records(serial_run))
    assert main(["tolerance", str(design_file), "--out", str(out), "--scheduler", "serial", "--resume",
                 "--seed", "4", "--no-plots"]) == 2  # another seed is another run


def test_local_cluster_matches_serial(serial_run, design_file, tmp_path):
    out = tmp_path / "local"
    assert main(["tolerance", str(design_file), "--out", str(out), "--workers", "2", "--no-plots"]) == 0
    _same(_records(out), _records(serial_run))
    _same(_records(out, "sensitivity.jsonl"), _records(serial_run, "sensitivity.jsonl"))
    doc = json.loads((out / "summary.json").read_text())
    assert doc["execution"]["mode"] == "local" and doc["execution"]["workers"] == 2
    assert len({r["worker"] for r in _records(out).values()}) >= 1


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture
def cluster():
    """A dask.distributed scheduler and two worker processes (no nanny) on 127.0.0.1."""
    port = _free_port()
    env = {**os.environ, "LFSIM_THREADS": "1"}
    dask = str(VENV_BIN / "dask")
    procs = [subprocess.Popen([dask, "scheduler", "--host", "127.0.0.1", "--port", str(port), "--no-dashboard"],
                              env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)]
    address = f"tcp://127.0.0.1:{port}"
    workers = []
    try:
        for _ in range(2):
            workers.append(subprocess.Popen(
                [dask, "worker", address, "--nthreads", "1", "--no-nanny", "--no-dashboard", "--host", "127.0.0.1"],
                env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL))
        from dask.distributed import Client

        with Client(address, timeout="60s") as c:
            c.wait_for_workers(2, timeout=120)
        yield address, workers
    finally:
        for p in workers + procs:
            if p.poll() is None:
                p.terminate()
        for p in workers + procs:
            try:
                p.wait(timeout=20)
            except subprocess.TimeoutExpired:
                p.kill()


def test_two_worker_cluster_matches_serial_and_survives_a_killed_worker(serial_run, design_file, tmp_path,
                                                                         cluster):
    from lfsim.tolerance.monte_carlo import run_tolerance

    address, workers = cluster
    out = tmp_path / "cluster"
    assert main(["tolerance", str(design_file), "--out", str(out), "--scheduler", address, "--no-plots"]) == 0
    _same(_records(out), _records(serial_run))
    # Both workers take trials: checked over this run's 3 tasks and the 40 below, since under
    # pytest-xdist a worker starved of CPU can see the first run's few tasks all go to the other.
    workers_seen = {r["worker"] for r in _records(out).values()}

    # 40 trials, one per task; kill a worker once the first records are stored.
    out2 = tmp_path / "killed"
    design = lfsim.load(design_file)
    result = {}
    th = threading.Thread(target=lambda: result.update(doc=run_tolerance(
        design, out2, trials=40, scheduler=address, batch=1, sensitivity=False, plots=False)))
    th.start()
    t0 = time.time()
    while time.time() - t0 < 120:
        f = out2 / "trials.jsonl"
        if f.exists() and len(f.read_text().splitlines()) >= 3:
            break
        time.sleep(0.05)
    n_at_kill = len((out2 / "trials.jsonl").read_text().splitlines())
    workers[0].send_signal(signal.SIGKILL)
    th.join(timeout=300)
    assert not th.is_alive()
    assert n_at_kill < 40
    lines = (out2 / "trials.jsonl").read_text().splitlines()
    ids = [json.loads(x)["id"] for x in lines]
    assert sorted(ids) == sorted(f"mc:{i}" for i in range(40))  # every trial, once
    assert result["doc"]["trials"] == 40
    ref = _records(serial_run)
    recs = _records(out2)
    for k in ref:  # the first six trials are the serial run's
        assert recs[k]["metrics"] == ref[k]["metrics"]
    assert len(workers_seen | {r["worker"] for r in recs.values()}) >= 2  # both workers took trials


# ------------------------------------------------------------------ sweep
def test_sweep_grid_and_outputs(tmp_path, capsys):
    out = tmp_path / "sw"
    assert main(["sweep", str(ROOT / "scenes" / "ini_ideal.toml"), "--out", str(out), "--scheduler", "serial",
                 "--set", "EP.power=0.0322:0.0324:2", "--set", "mla.center_x=0:0.01:2",
                 "--set", "ini.analysis.fields=1", "--set", "ini.analysis.mtf_grid=8", "--set", "ini.analysis.pupil=2",
                 "--set", "ini.analysis.refine=0", "--stride", "16,8", "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert [p["values"] for p in doc["points"]] == [
        {"EP.power": 0.0322, "mla.center_x": 0.0}, {"EP.power": 0.0322, "mla.center_x": 0.01},
        {"EP.power": 0.0324, "mla.center_x": 0.0}, {"EP.power": 0.0324, "mla.center_x": 0.01}]
    assert all(p["error"] is None for p in doc["points"])
    gd = [p["metrics"]["gd_max_deg"] for p in doc["points"]]
    assert gd[0] < 1e-9 and gd[2] < 1e-9  # the ideal design, centred: no distortion
    assert gd[1] > 1e-3 and gd[3] > 1e-3  # a decentred array moves the virtual EIs
    for f in ("sweep.json", "sweep.csv", "sweep.png"):
        assert (out / f).exists()
    assert len((out / "sweep.csv").read_text().splitlines()) == 5


@pytest.mark.parametrize("args, text", [
    (["--set", "EP.power=1:2"], "START:STOP:COUNT"),
    (["--set", "EP.power=1:2:x"], "COUNT"),
    (["--set", "EP.powr=0.03:0.04:2"], "EP.powr"),
    (["--set", "EP.power=0.03"], "at least one axis"),
])
def test_sweep_bad_input(tmp_path, capsys, args, text):
    assert main(["sweep", str(ROOT / "scenes" / "ini_ideal.toml"), "--out", str(tmp_path / "o"),
                 "--scheduler", "serial", *args]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and text in err


# ------------------------------------------------------------------ fused launches
def test_trials_traced_together_are_bit_identical_to_trials_traced_alone(tmp_path):
    """run_many traces a batch's rays in shared launches; each trial's rays, metrics and record
    are exactly those it gets alone (freeform prism: real Newton aiming, per-trial stop frames)."""
    from lfsim.analysis.ini_analysis import PupilSets
    from lfsim.ini.model import IniModel
    from lfsim.ini.subsystems import trace, trace_many
    from lfsim.tolerance.monte_carlo import spec_of
    from lfsim.tolerance.perturb import draw
    from lfsim.tolerance.trial import TrialEvaluator

    text = (ROOT / "scenes" / "ini_freeform_optimized.toml").read_text()
    i = text.index("[tolerance.sampling]")
    j = text.index("[tolerance.targets]")
    sampling = "[tolerance.sampling]\nstride = [16, 8]\nfields = 1\npupil = 3\nmtf_grid = 8\nrefine = 0\n\n"
    text = text[:i] + sampling + text[j:]
    p = tmp_path / "ff.toml"
    p.write_text(text)
    design = lfsim.load(p)
    spec = spec_of(design)
    ev = TrialEvaluator(design.raw, str(p), spec)
    units = [(f"mc:{n}", draw(spec, 5, n)) for n in range(3)]
    models = [IniModel(ev.build(off)[0]) for _, off in units]
    rho = PupilSets.build(ev.nominal.ini.pupil, ev.nominal.ini.mtf_grid).rho
    fused = trace_many(models, ev.subs, rho, max_rays=20_000)  # several chunks, all trials in each
    for model, b in zip(models, fused):
        a = trace(model, ev.subs, rho)
        assert np.any(a.pos != 0) and np.any(a.status == 0)
        for f in ("pos", "dir", "opl", "status"):
            assert np.array_equal(getattr(a, f), getattr(b, f)), f
        assert a.aim_error == b.aim_error
    alone = [ev.run(uid, off) for uid, off in units]
    together = ev.run_many(units)
    for a, b in zip(alone, together):
        assert a["error"] is None and b["error"] is None
        assert a["metrics"] == b["metrics"] and a["offsets"] == b["offsets"]
        assert a["compensators"] == b["compensators"] and a["pass"] == b["pass"]
    # designs with other parameter tables cannot share a launch
    with pytest.raises(ValueError, match="cannot share launches"):
        trace_many([models[0], IniModel(lfsim.load(ROOT / "scenes" / "ini_ideal.toml"))], ev.subs, rho)
