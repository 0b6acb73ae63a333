"""Progress of long work: a tqdm bar on a terminal, periodic lines in a log.

A run whose standard error is a terminal gets tqdm's bar. Anywhere else (a CI
log, a batch job, ``2> run.log``) a bar's carriage returns would pile up into
one line, so the same calls print a plain line every ``interval`` seconds and
a last one when work of 2 s or more ends::

    sub-systems: 120/459 sub (26%), 12 s elapsed, ETA 34 s
"""

from __future__ import annotations

import sys
import time

#: Seconds between two progress lines in a log.
LOG_INTERVAL = 10.0
#: Work that took at least this long (s) ends with a line in a log.
LOG_CLOSE_AFTER = 2.0


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
            eta = f", ETA {el / frac - el:.0f} s" if 0 < frac < 1 else ""
            return (f"{self.desc}: {self.n}/{self.total} {self.unit} ({100 * frac:.0f}%), "
                    f"{el:.0f} s elapsed{eta}{post}")
        return f"{self.desc}: {self.n} {self.unit}, {el:.0f} s elapsed{post}"

    def set_postfix_str(self, text: str) -> None:
        self.postfix = str(text)

    def set_postfix(self, **kw) -> None:
        self.postfix = ", ".join(f"{k.rstrip('_')}={v}" for k, v in kw.items())

    def update(self, n: int = 1) -> None:
        self.n += int(n)
        now = time.monotonic()
        if not self.closed and now - self.last >= self.interval:
            self.last = now
            print(self._line(), file=self.stream, flush=True)

    def close(self) -> None:
        if not self.closed:
            self.closed = True
            if time.monotonic() - self.t0 >= min(self.interval, LOG_CLOSE_AFTER):  # a short task needs none
                print(self._line(), file=self.stream, flush=True)


def bar(iterable=None, **kw):
    """A tqdm bar when standard error is a terminal, else a :class:`LogBar` (same calls)."""
    if sys.stderr.isatty():
        from tqdm import tqdm

        return tqdm(iterable, **kw)
    kw.pop("leave", None)
    return LogBar(iterable, **kw)
