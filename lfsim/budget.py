"""Work estimates and limits: what a long run will cost, checked before it starts.

A verb that can be asked for unbounded work (a render's resolution and
samples, a sweep's grid, a tolerance run's trials) builds an :class:`Estimate`
of its run time and peak memory before it starts, prints it when the run will
take a while, and refuses, with exit status 2 and the flag that lifts the
limit, a run beyond :class:`Limits`:

* memory: ``--max-memory-gb`` (default 80 % of the memory this process may use:
  the physical memory, or a cgroup's limit where one is set);
* time: ``--max-hours`` (default 24 h).

Render estimates come from throughputs measured on a 2-core AVX-512 machine
(:data:`RATES`, samples per second per Dr.Jit thread), scaled by the thread
count; sweeps and tolerance runs time one unit of their own work first and
extrapolate. An estimate is a planning figure (within a factor of about 2),
not a promise; a progress bar with an ETA follows it.
"""

from __future__ import annotations

import math
import os
from contextlib import contextmanager
from contextvars import ContextVar
from dataclasses import dataclass

#: Default time limit of one run (``--max-hours``).
DEFAULT_MAX_HOURS = 24.0
#: Share of the usable memory a run may plan to use by default (``--max-memory-gb``).
MEMORY_SHARE = 0.8
#: Runs estimated to take at least this long (s) print their estimate first.
ANNOUNCE_AFTER_S = 10.0

#: Measured throughput, samples per second per Dr.Jit thread (2-core AMD EPYC, AVX-512,
#: ``lfsim focal-stack`` at 256x144 to 1024x576 px, 16 to 256 spp; benchmarks/work_estimates.py compares):
#: retinal images through the analytic display path, through the path-traced optics meshes,
#: of the content seen directly; display pixels of the elemental images (real chief rays).
RATES = {"display_analytic": 4.5e6, "display_mesh": 1.2e6, "natural": 5.5e6, "elemental_px": 0.8e6}
#: Seconds per retinal pixel of what follows each render (EXR/PNG writing, SSIM, focus cues).
POST_S_PER_PX = 2e-6
#: Process memory (bytes) before any image: Python, Mitsuba, Dr.Jit and their kernels.
BASE_BYTES = 1.2e9
#: Bytes per retinal pixel held at the peak of a focal stack (film, images kept for the focus cues).
BYTES_PER_PX = 400.0
#: Bytes per display pixel (elemental images: RGB float32, EXR and PNG copies).
BYTES_PER_DISPLAY_PX = 64.0


class BudgetError(ValueError):
    """A run whose estimate exceeds a limit (one line: the estimate and the flag that lifts it)."""


def usable_memory_bytes() -> float:
    """Memory this process may use: physical memory, or a smaller cgroup (v2 or v1) limit."""
    try:
        total = float(os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES"))
    except (ValueError, OSError, AttributeError):  # pragma: no cover - not POSIX
        total = math.inf
    for path in ("/sys/fs/cgroup/memory.max", "/sys/fs/cgroup/memory/memory.limit_in_bytes"):
        try:
            with open(path, encoding="ascii") as f:
                text = f.read().strip()
        except OSError:
            continue
        if text.isdigit():
            total = min(total, float(text))
    return total


def threads() -> int:
    """Dr.Jit's CPU worker threads (after ``lfsim.backend.init``), at least 1."""
    try:
        import drjit as dr

        return max(1, int(dr.thread_count()))
    except Exception:  # pragma: no cover - Dr.Jit not initialised yet
        return max(1, os.cpu_count() or 1)


def duration(seconds: float) -> str:
    """``"45 s"``, ``"12 min"``, ``"3.5 h"``, ``"12 days"``."""
    if not math.isfinite(seconds):
        return "unbounded"
    if seconds < 90:
        return f"{seconds:.0f} s"
    if seconds < 5400:
        return f"{seconds / 60:.0f} min"
    if seconds < 3 * 86400:
        return f"{seconds / 3600:.1f} h"
    return f"{seconds / 86400:.3g} days"


def count(n: float) -> str:
    """``"66.1 M"``, ``"358 G"``: a large count in SI units."""
    return f"{n / 1e6:.3g} M" if n < 1e9 else f"{n / 1e9:.3g} G"


def gigabytes(nbytes: float) -> str:
    return f"{nbytes / 1e9:.2g} GB" if nbytes < 1e11 else f"{nbytes / 1e9:.3g} GB"


@dataclass(frozen=True)
class Estimate:
    """A run's planned cost: ``what`` it is (counts of its work), ``seconds``, peak ``bytes``."""

    what: str
    seconds: float
    bytes: float = 0.0
    note: str = ""  # e.g. what the time leaves out

    def text(self) -> str:
        mem = f", peak memory about {gigabytes(self.bytes)}" if self.bytes else ""
        note = f" ({self.note})" if self.note else ""
        return f"{self.what}: about {duration(self.seconds)}{note}{mem}"


@dataclass(frozen=True)
class Limits:
    """The largest run allowed: ``max_seconds`` (``--max-hours``), ``max_bytes`` (``--max-memory-gb``)."""

    max_seconds: float = DEFAULT_MAX_HOURS * 3600.0
    max_bytes: float | None = None  # None: MEMORY_SHARE of usable_memory_bytes()

    @classmethod
    def from_args(cls, args) -> Limits:
        """The limits of a parsed command line (its ``max_hours`` / ``max_memory_gb``, where given)."""
        hours = getattr(args, "max_hours", None)
        gb = getattr(args, "max_memory_gb", None)
        for flag, v in (("--max-hours", hours), ("--max-memory-gb", gb)):
            if v is not None and not v > 0:  # nan fails too; inf lifts the limit
                raise BudgetError(f"{flag} = {v!r}: must be > 0 (inf: no limit)")
        return cls(max_seconds=DEFAULT_MAX_HOURS * 3600.0 if hours is None else hours * 3600.0,
                   max_bytes=None if gb is None else gb * 1e9)

    def memory(self) -> float:
        return self.max_bytes if self.max_bytes is not None else MEMORY_SHARE * usable_memory_bytes()


_CURRENT: ContextVar[Limits | None] = ContextVar("lfsim_budget_limits", default=None)


def current() -> Limits:
    """The limits in force: those of :func:`use`, else the defaults."""
    return _CURRENT.get() or Limits()


@contextmanager
def use(limits: Limits):
    """Make ``limits`` the ones :func:`check` applies inside the block (a command's flags)."""
    token = _CURRENT.set(limits)
    try:
        yield limits
    finally:
        _CURRENT.reset(token)


def check(est: Estimate, limits: Limits | None = None, log=None, hint: str = "") -> Estimate:
    """Refuse a run beyond ``limits`` (default :func:`current`) with a :class:`BudgetError`;
    print the estimate of a long one to ``log``.

    ``hint`` names what would make the run smaller (e.g. ``"lower --spp or --resolution"``).
    """
    limits = limits or current()
    tail = f" ({hint})" if hint else ""
    mem = limits.memory()
    if est.bytes > mem:
        src = "--max-memory-gb" if limits.max_bytes is not None else \
            f"the default {MEMORY_SHARE:.0%} of this machine's {gigabytes(usable_memory_bytes())}"
        raise BudgetError(f"{est.text()}: more memory than {gigabytes(mem)} ({src}): raise --max-memory-gb "
                          f"to run it anyway{tail}")
    if est.seconds > limits.max_seconds:
        raise BudgetError(f"{est.text()}: longer than --max-hours {limits.max_seconds / 3600:g}: raise "
                          f"--max-hours to run it anyway{tail}")
    if log is not None and est.seconds >= ANNOUNCE_AFTER_S:
        log(f"estimate: {est.text()}")
    return est


def add_flags(parser, memory: bool = True) -> None:
    """``--max-hours`` (and ``--max-memory-gb``) on a verb's parser."""
    parser.add_argument("--max-hours", type=float, metavar="H",
                        help=f"refuse a run estimated to take longer (default {DEFAULT_MAX_HOURS:g}; inf: no limit)")
    if memory:
        parser.add_argument("--max-memory-gb", type=float, metavar="GB",
                            help=f"refuse a run estimated to need more memory (default {100 * MEMORY_SHARE:.0f}%% of "
                                 "this machine's memory; inf: no limit)")
