"""The checks of a regression run and their table.

A check compares one figure of the candidate with the baseline and has a
status:

* ``ok``      within tolerance;
* ``worse``   a figure with a direction (detail, error against the natural
  view, contrast, RMS spot, GD, PA, …) moved the wrong way beyond tolerance;
* ``changed`` a figure without a direction (the image itself, the field of
  view, a first-order quantity) moved beyond tolerance;
* ``better``  moved the right way beyond tolerance (does not fail).

``worse`` and ``changed`` fail the run (exit status 1).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

FAILING = ("worse", "changed")


@dataclass
class Check:
    """One figure, baseline against candidate.

    ``change``: the compared effect (a fraction for relative figures, see
    ``unit``); ``tolerance``: the largest ``|change|`` that passes; ``z``:
    the significance of a noisy figure (None for deterministic ones).
    """

    name: str
    group: str  # "image", "render" or "metric"
    statistic: str
    baseline: float | None
    candidate: float | None
    change: float | None
    tolerance: float | None
    status: str
    unit: str = ""
    z: float | None = None
    direction: str = "either"  # "lower" / "higher" is better, or "either"
    detail: str = ""
    value_unit: str = ""  # unit of baseline / candidate: "", "%" (a fraction shown in %) or "dB"

    @property
    def failed(self) -> bool:
        return self.status in FAILING

    def as_dict(self) -> dict:
        d = asdict(self)
        return {k: (None if isinstance(v, float) and not math.isfinite(v) else v) for k, v in d.items()}


def numeric_check(name: str, group: str, base, cand, direction: str, rel: float, abs_: float,
                  unit: str = "") -> Check:
    """A deterministic figure: fails when ``|cand - base| > abs_ + rel |base|`` in the bad direction.

    ``direction``: "lower" (lower is better), "higher", or "either" (any change
    beyond tolerance is ``changed``). A figure that appears or disappears
    (None on one side) is ``changed``.
    """
    if base is None or cand is None:
        same = base is None and cand is None
        return Check(name, group, "value", base, cand, None, None, "ok" if same else "changed", unit,
                     direction=direction, detail="" if same else "missing on one side")
    base, cand = float(base), float(cand)
    tol = abs_ + rel * abs(base)
    d = cand - base
    if not (math.isfinite(base) and math.isfinite(cand)):
        status = "ok" if base == cand else "changed"
    elif abs(d) <= tol:
        status = "ok"
    elif direction == "either":
        status = "changed"
    else:
        worse = d > 0 if direction == "lower" else d < 0
        status = "worse" if worse else "better"
    return Check(name, group, "value", base, cand, d, tol, status, unit, direction=direction)


def _value(v, unit: str) -> str:
    if v is None:
        return "-"
    if isinstance(v, float) and not math.isfinite(v):
        return str(v)
    if unit == "%":
        return f"{100 * v:.2f}%"
    if unit == "dB":
        return f"{v:.2f} dB"
    return f"{v:.6g}"


def table(checks: list[Check], include_ok: bool = True) -> str:
    """A fixed-width text table of ``checks``, failing ones first (``include_ok=False``: not the ok ones)."""
    order = {"worse": 0, "changed": 1, "better": 2, "ok": 3}
    rows = sorted((c for c in checks if include_ok or c.status != "ok"), key=lambda c: order.get(c.status, 9))
    head = ("check", "baseline", "candidate", "change", "tolerance", "z", "status")
    body = []
    for c in rows:
        pct = c.unit == "%"
        if c.change is None:
            change = "-"
        else:
            change = f"{100 * c.change:+.2f}%" if pct else f"{c.change:+.3g}"
        tol = "-" if c.tolerance is None else (f"±{100 * c.tolerance:.2f}%" if pct else f"±{c.tolerance:.3g}")
        z = "-" if c.z is None else f"{c.z:+.1f}"
        body.append((c.name, _value(c.baseline, c.value_unit), _value(c.candidate, c.value_unit), change, tol, z,
                     c.status.upper() if c.failed else c.status))
    widths = [max(len(r[i]) for r in [head, *body]) for i in range(len(head))]
    line = "  ".join(f"{{:{'<' if i == 0 else '>'}{w}}}" for i, w in enumerate(widths))
    out = [line.format(*head), line.format(*("-" * w for w in widths))]
    out += [line.format(*r) for r in body]
    return "\n".join(out)
