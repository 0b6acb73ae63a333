"""benchmarks/solver_hinges.py refuses bad input in one line, exit status 2, writing nothing."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def _script():
    spec = importlib.util.spec_from_file_location("solver_hinges", ROOT / "benchmarks" / "solver_hinges.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


@pytest.mark.parametrize("args, words", [
    (["--design", "{tmp}/missing.toml"], "missing.toml: file not found"),
    (["--solvers", "lm,bogus"], "'lm,bogus'"),
    (["--iterations", "0"], "--iterations 0"),
    (["--stage", "nonsense"], "no stage 'nonsense'"),
])
def test_bad_input_is_one_line_and_exit_2(tmp_path, capsys, args, words):
    out = tmp_path / "res" / "solver_hinges.json"
    argv = [a.format(tmp=tmp_path) for a in args] + ["--json", str(out)]
    assert _script().main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert words in err and "\n" not in err and "Traceback" not in err
    assert not out.parent.exists()
