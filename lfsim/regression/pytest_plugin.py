"""pytest plugin (entry point ``pytest11: lfsim``): the ``lfsim_regression`` fixture.

    def test_my_design(lfsim_regression):
        lfsim_regression.check("design.toml", spp=16, resolution=(128, 72), focus_mm=[750])

``check`` renders the design's focal stack and computes its metrics like
``lfsim regress`` and fails the test, with the table of what got worse, when
the candidate regressed against its baseline. Baselines live in
``lfsim_baselines/<test name>`` next to the test file, or under
``--lfsim-baselines DIR`` (or the ini option ``lfsim_baselines``, relative to
the rootdir). ``pytest --lfsim-update-baselines`` (re-)creates them (the test
is then reported as skipped, naming the folder). Relative design and content
paths are looked up next to the test file first, then in the current folder.
A report (``report.txt``, ``report.json``, heat maps) of every check is
written to the test's ``tmp_path``.
"""

from __future__ import annotations

import re
from pathlib import Path

import pytest


def pytest_addoption(parser):
    group = parser.getgroup("lfsim", "lfsim image-quality regression tests")
    group.addoption("--lfsim-baselines", metavar="DIR", default=None,
                    help="folder of lfsim regression baselines (default: lfsim_baselines/ next to each test file)")
    group.addoption("--lfsim-update-baselines", action="store_true", default=False,
                    help="re-create the baselines of the lfsim_regression checks that run, instead of checking")
    parser.addini("lfsim_baselines", "folder of lfsim regression baselines, relative to the rootdir", default="")


class LfsimRegression:
    """The ``lfsim_regression`` fixture: :meth:`check` a design against its baseline."""

    def __init__(self, request, tmp_path: Path):
        self._request = request
        self._tmp = tmp_path
        self._test_dir = Path(str(request.node.fspath)).parent
        self.update = bool(request.config.getoption("--lfsim-update-baselines"))
        root = request.config.getoption("--lfsim-baselines") or request.config.getini("lfsim_baselines")
        if root:
            root = Path(root)
            self.root = root if root.is_absolute() else Path(str(request.config.rootpath)) / root
        else:
            self.root = self._test_dir / "lfsim_baselines"

    def _path(self, p) -> str:
        p = Path(p)
        if not p.is_absolute() and (self._test_dir / p).exists():
            return str(self._test_dir / p)
        return str(p)

    def baseline_dir(self, design, name: str | None = None) -> Path:
        """The baseline folder of a check: ``<root>/<test name>[-<name>]``."""
        stem = re.sub(r"[^A-Za-z0-9_.-]+", "_", self._request.node.name).strip("_")
        return self.root / (f"{stem}-{name}" if name else stem)

    def check(self, design, name: str | None = None, **options):
        """Check ``design`` against its baseline; fail the test on a regression.

        ``options``: the render and metric options of ``lfsim regress``
        (``spp``, ``resolution``, ``focus_mm``, ``content``, ``set``, ``seed``,
        ``stride``, ``depths``, ``metrics``, …), used to create the baseline
        and, for a check, replacing the baseline's. ``name`` tells apart
        several checks in one test. Returns the
        :class:`~lfsim.regression.run.RegressionResult`.
        """
        from . import BaselineError, RegressionInputError, check, update

        design = self._path(design)
        if options.get("content") is not None:
            options["content"] = self._path(options["content"])
        folder = self.baseline_dir(design, name)
        try:
            if self.update:
                update(design, folder, options)
                pytest.skip(f"lfsim baseline updated: {folder}")
            if not (folder / "baseline.json").is_file():
                pytest.fail(f"no lfsim baseline {folder}: create it with pytest --lfsim-update-baselines",
                            pytrace=False)
            out = self._tmp / f"lfsim-regress-{folder.name}"
            result = check(design, folder, options, out_dir=out)
        except (BaselineError, RegressionInputError) as e:
            pytest.fail(f"lfsim regression check of {design}: {e}", pytrace=False)
        if result.failed:
            pytest.fail(f"{design} regressed against {folder}: {result.summary()}\n"
                        f"{result.table(include_ok=False)}\nreport: {out}/report.txt", pytrace=False)
        return result


@pytest.fixture
def lfsim_regression(request, tmp_path) -> LfsimRegression:
    """Image-quality regression checks of lfsim designs (see :mod:`lfsim.regression.pytest_plugin`)."""
    return LfsimRegression(request, tmp_path)
