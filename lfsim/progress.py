"""Progress of long work: a tqdm bar on a terminal, periodic lines in a log.

A run whose standard error is a terminal gets tqdm's bar. Anywhere else (a CI
log, a batch job, ``2> run.log``) a bar's carriage returns would pile up into
one line, so the same calls print a plain line every ``interval`` seconds and
a last one when work of 2 s or more ends::

    sub-systems: 120/459 sub (26%), 12 s elapsed, ETA 34 s

Between bars, :func:`heartbeat` (around every ``lfsim`` command) speaks for
work that shows no progress of its own for 2 s: Dr.Jit compiling the kernels
of a design it has not met before (seen as new files in its kernel cache,
``~/.drjit``), or any other long step::

    compiling kernels for this design (14 so far; cached for later runs), 12 s elapsed
"""

from __future__ import annotations

import os
import sys
import threading
import time
from contextlib import contextmanager
from pathlib import Path

#: Seconds between two progress lines in a log.
LOG_INTERVAL = 10.0
#: Work that took at least this long (s) ends with a line in a log.
LOG_CLOSE_AFTER = 2.0
#: Seconds without progress output before the heartbeat speaks, then between its lines.
HEARTBEAT_AFTER = 2.0
_last = [time.monotonic()]  # the last time a bar moved or printed
_phase: list[str | None] = [None]  # what the command is doing now, for the heartbeat


@contextmanager
def phase(text: str):
    """Name the step under way: the heartbeat's lines say it (``lfsim analyze: searching the
    worst contrast, 20 s elapsed``) instead of "working"."""
    prev = _phase[0]
    _phase[0] = text
    try:
        yield
    finally:
        _phase[0] = prev


def touch() -> None:
    """A bar moved or a line was printed: the heartbeat stays quiet for a while."""
    _last[0] = time.monotonic()


def kernel_cache() -> Path:
    """Dr.Jit's on-disk kernel cache (``$HOME/.drjit``): one file per compiled kernel."""
    return Path(os.path.expanduser("~")) / ".drjit"


class _KernelCounter:
    """Counts kernels written to Dr.Jit's cache since it was made: the file names then and now
    (listed only when the folder's mtime changed, so a poll is one stat)."""

    def __init__(self):
        self.dir = kernel_cache()
        self.mtime = self._mtime()
        self.start = self._names()
        self.new = 0

    def _mtime(self) -> float:
        try:
            return self.dir.stat().st_mtime
        except OSError:
            return 0.0

    def _names(self) -> set[str]:
        try:
            return set(os.listdir(self.dir))
        except OSError:
            return set()

    def poll(self) -> bool:
        """Whether kernels were written since the last poll (updates :attr:`new`)."""
        m = self._mtime()
        if m == self.mtime:
            return False
        self.mtime = m
        self.new = len(self._names() - self.start)
        return True


_EMIT = threading.Lock()


def _emit(msg: str) -> None:
    """One whole line on standard error (one write, so it never merges with another thread's)."""
    with _EMIT:
        if sys.stderr.isatty():
            from tqdm import tqdm

            tqdm.write(msg, file=sys.stderr)
        else:
            sys.stderr.write(msg + "\n")
            sys.stderr.flush()
    touch()


def line(msg: str) -> None:
    """Print one progress line on standard error (above a bar on a terminal)."""
    _emit(msg)


@contextmanager
def heartbeat(what: str, after: float | None = None, interval: float | None = None, enabled: bool = True):
    """Around a command: a line whenever ``after`` s (then ``interval`` s) pass with no progress output.

    The line says "compiling kernels for this design" while Dr.Jit writes new
    kernels to its cache, else that ``what`` is still working (on the :func:`phase`
    named, if any); at the end, a
    run that compiled kernels for 2 s or more says how many it compiled.
    """
    if not enabled:
        yield
        return
    interval = LOG_INTERVAL if interval is None else float(interval)
    if after is None:  # LFSIM_HEARTBEAT_AFTER: seconds before the first line (default HEARTBEAT_AFTER)
        try:
            after = float(os.environ.get("LFSIM_HEARTBEAT_AFTER", HEARTBEAT_AFTER))
        except ValueError:
            after = HEARTBEAT_AFTER
    counter = _KernelCounter()
    stop = threading.Event()
    t0 = time.monotonic()
    touch()
    spoke = [False]

    def run():
        wait = after
        while not stop.wait(0.25):
            now = time.monotonic()
            compiling = counter.poll()
            if now - _last[0] < wait:
                continue
            el = now - t0
            if compiling or (counter.new and not spoke[0]):
                _emit(f"compiling kernels for this design ({counter.new} so far; cached for later runs), "
                      f"{el:.0f} s elapsed")
            else:
                _emit(f"{what}: {_phase[0] or 'working'}, {el:.0f} s elapsed")
            spoke[0] = True
            wait = interval

    th = threading.Thread(target=run, name="lfsim-heartbeat", daemon=True)
    th.start()
    try:
        yield
    finally:
        stop.set()
        th.join()
        counter.poll()
        if spoke[0] and counter.new:
            _emit(f"{counter.new} kernels compiled this run (Dr.Jit keeps them in {counter.dir})")


class LogBar:
    """The part of tqdm's interface lfsim uses (``update``, ``close``, ``n``, ``total``,
    iteration), printing lines to a stream instead of redrawing a bar."""

    def __init__(self, iterable=None, total=None, desc: str = "", unit: str = "it", initial: int = 0,
                 stream=None, interval: float = LOG_INTERVAL, disable: bool = False, **_):
        self.iterable = iterable
        self.total = total if total is not None else (len(iterable) if hasattr(iterable, "__len__") else None)
        self.desc, self.unit, self.n = desc, unit, int(initial)
        self.stream = stream or sys.stderr
        self.interval = float(interval)
        self.t0 = self.last = time.monotonic()
        self.closed = bool(disable)
        self.postfix = ""
        self._shown = None  # the count of the last line printed
        self._first = None  # (time, count) of the first update

    def __iter__(self):
        for item in self.iterable:
            yield item
            self.update(1)
        self.close()

    def _line(self) -> str:
        el = time.monotonic() - self.t0
        post = f", {self.postfix}" if self.postfix else ""
        if self.total:
            frac = min(1.0, self.n / self.total)
            eta = ""
            if 0 < frac < 1:
                # The rate since the first update, once there is one: the time before it holds
                # the set-up (kernel compiles, first loads) that the remaining items do not repeat.
                first = self._first
                if first is not None and self.n > first[1]:
                    left = (time.monotonic() - first[0]) / (self.n - first[1]) * (self.total - self.n)
                else:
                    left = el / frac - el
                eta = f", ETA {left:.0f} s"
            return (f"{self.desc}: {self.n}/{self.total} {self.unit} ({100 * frac:.0f}%), "
                    f"{el:.0f} s elapsed{eta}{post}")
        return f"{self.desc}: {self.n} {self.unit}, {el:.0f} s elapsed{post}"

    def set_postfix_str(self, text: str) -> None:
        self.postfix = str(text)

    def set_postfix(self, **kw) -> None:
        self.postfix = ", ".join(f"{k.rstrip('_')}={v}" for k, v in kw.items())

    def update(self, n: int = 1) -> None:
        self.n += int(n)
        if self._first is None:
            self._first = (time.monotonic(), self.n)
        touch()
        now = time.monotonic()
        if not self.closed and now - self.last >= self.interval:
            self.last, self._shown = now, self.n
            print(self._line(), file=self.stream, flush=True)

    def close(self) -> None:
        if not self.closed:
            self.closed = True
            # a short task needs no closing line, nor one that repeats the last
            if time.monotonic() - self.t0 >= min(self.interval, LOG_CLOSE_AFTER) and self._shown != self.n:
                print(self._line(), file=self.stream, flush=True)
            touch()


def bar(iterable=None, **kw):
    """A tqdm bar when standard error is a terminal, else a :class:`LogBar` (same calls)."""
    touch()
    if sys.stderr.isatty():
        from tqdm import tqdm

        class _Bar(tqdm):
            def update(self, n=1):
                touch()
                return super().update(n)

            def __iter__(self):
                for item in super().__iter__():
                    touch()
                    yield item

        return _Bar(iterable, **kw)
    kw.pop("leave", None)
    return LogBar(iterable, **kw)
