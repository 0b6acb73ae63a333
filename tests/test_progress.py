"""The heartbeat: long work with no progress of its own is reported, kernel compiles by name."""

import time

from lfsim import progress


def _lines(capsys):
    return [line for line in capsys.readouterr().err.splitlines() if line]


def test_heartbeat_names_kernel_compiles(tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("HOME", str(tmp_path))
    cache = tmp_path / ".drjit"
    cache.mkdir()
    (cache / "old.llvm.v6.bin").write_bytes(b"x")  # cached before the run: not counted
    time.sleep(0.05)
    with progress.heartbeat("lfsim analyze", after=0.4, interval=0.4):
        for k in range(3):  # Dr.Jit writes one file per compiled kernel
            (cache / f"k{k}.llvm.v6.bin").write_bytes(b"x")
            time.sleep(0.3)
        time.sleep(0.6)
    lines = _lines(capsys)
    assert any(line.startswith("compiling kernels for this design (") and "so far; cached for later runs" in line
               for line in lines), lines
    assert lines[-1] == f"3 kernels compiled this run (Dr.Jit keeps them in {cache})"


def test_heartbeat_reports_other_long_work_and_stays_quiet_when_bars_move(tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("HOME", str(tmp_path))
    with progress.heartbeat("lfsim sweep", after=0.3, interval=0.3):
        time.sleep(1.0)
    lines = _lines(capsys)
    assert lines and all(line.startswith("lfsim sweep: working, ") and line.endswith(" s elapsed") for line in lines)
    with progress.heartbeat("lfsim sweep", after=0.3, interval=0.3):
        bar = progress.LogBar(total=20, desc="points", interval=60.0)
        for _ in range(10):  # a bar that moves keeps the heartbeat quiet
            bar.update(1)
            time.sleep(0.1)
    assert _lines(capsys) == []
    with progress.heartbeat("quick", after=0.3):  # a short command prints nothing
        pass
    assert _lines(capsys) == []


def test_heartbeat_names_the_phase_under_way(tmp_path, monkeypatch, capsys):
    """A named step replaces "working" while it runs, and the name goes with it."""
    monkeypatch.setenv("HOME", str(tmp_path))
    with progress.heartbeat("lfsim analyze", after=0.3, interval=0.3):
        with progress.phase("searching each sub-system's worst contrast"):
            time.sleep(0.8)
        progress.touch()
        time.sleep(0.8)
    lines = _lines(capsys)
    named = [line for line in lines if line.startswith("lfsim analyze: searching each sub-system's worst contrast, ")]
    assert named and lines[-1].startswith("lfsim analyze: working, "), lines
