"""`lfsim sweep`: the InI metrics over a grid of design numbers, optionally with focal stacks.

``--set KEY=START:STOP:COUNT`` gives an axis (``numpy.linspace(START, STOP,
COUNT)``), ``--set KEY=VALUE`` a fixed override; the grid is the product of
the axes (the first axis varies slowest). Keys are those of ``--set``
(:mod:`lfsim.design.overrides`). Each point is the design with its overrides,
validated like a file, and measured like ``lfsim analyze`` (its own paraxial
reference, the ``[ini.analysis]`` sampling); a point the design cannot take is
recorded with its error. Points are evaluated on Dask like tolerance trials
(:mod:`lfsim.tolerance.execute`). With ``render``, a focal stack of every valid
point is rendered afterwards in this process (Mitsuba), into
``DIR/points/<index>/``.
"""

from __future__ import annotations

import csv
import io
import itertools
import math
import os
import socket
import time
from pathlib import Path

import numpy as np

from ..design.design import Design
from ..design.errors import DesignError
from ..design.overrides import apply_overrides, parse_assignment, parse_number
from ..fileio import write_json, write_text
from ..ini.model import IniModelError
from . import execute
from .trial import METRICS, metrics_of

#: Grid points a sweep evaluates unless told otherwise (``--max-points``): each is a full
#: sub-system analysis of the design (~0.1-1 s), so 10,000 points are hours of work.
MAX_POINTS = 10_000


def parse_axes(items, flag: str = "--set", max_points: int | None = MAX_POINTS
               ) -> tuple[dict[str, np.ndarray], dict[str, float]]:
    """``KEY=START:STOP:COUNT`` items → axes {key: values}; ``KEY=VALUE`` → fixed {key: value}.

    Refuses (before allocating anything) a grid of more than ``max_points`` points
    (None: no limit)."""
    axes: dict[str, np.ndarray] = {}
    fixed: dict[str, float] = {}
    points = 1
    for item in items or ():
        key, text = parse_assignment(item, flag)
        if key in axes or key in fixed:
            raise ValueError(f"{flag} {key}: given twice")
        if ":" in text:
            parts = text.split(":")
            if len(parts) != 3:
                raise ValueError(f"{flag} {key} = {text!r}: expected START:STOP:COUNT, e.g. 0:0.02:5")
            start, stop = (parse_number(p, key, flag) for p in parts[:2])
            try:
                count = int(parts[2])
            except ValueError:
                raise ValueError(f"{flag} {key} = {text!r}: COUNT must be an integer >= 1") from None
            if count < 1 or not (math.isfinite(start) and math.isfinite(stop)):
                raise ValueError(f"{flag} {key} = {text!r}: finite START, STOP and an integer COUNT >= 1")
            points *= count
            if max_points is not None and points > max_points:
                raise ValueError(f"{flag} {key} = {text!r}: the grid would have {points:,} points, more than "
                                 f"--max-points {max_points:,} (each is a full analysis of the design)")
            axes[key] = np.linspace(start, stop, count)
        else:
            fixed[key] = parse_number(text, key, flag)
    return axes, fixed


def grid(axes: dict[str, np.ndarray]) -> list[dict[str, float]]:
    keys = list(axes)
    return [dict(zip(keys, (float(v) for v in combo))) for combo in itertools.product(*(axes[k] for k in keys))]


class PointEvaluator:
    """Evaluates sweep points of one design (built once per worker process)."""

    def __init__(self, raw: dict, path: str, reference: str | None = None):
        self.raw, self.path = raw, path
        self.reference = None
        if reference == "nominal":
            from ..ini.model import IniModel

            self.reference = IniModel(Design.from_dict(raw, path))

    def run(self, uid: str, overrides: dict[str, float]) -> dict:
        t0 = time.perf_counter()
        rec = {"id": uid, "values": dict(overrides), "metrics": None, "error": None}
        try:
            design = Design.from_dict(apply_overrides(self.raw, overrides, self.path), self.path)
            rec["metrics"] = metrics_of(design, self.reference)
        except (DesignError, IniModelError, ValueError, FloatingPointError) as e:
            rec["error"] = " ".join(str(e).split())[:300]
        rec["seconds"] = round(time.perf_counter() - t0, 4)
        rec["worker"] = f"{socket.gethostname()}:{os.getpid()}"
        return rec


def _table_csv(keys, points) -> str:
    buf = io.StringIO()
    w = csv.writer(buf)
    w.writerow(["index", *keys, *METRICS, "error"])
    for p in points:
        m = p["metrics"] or {}
        w.writerow([p["index"], *(p["values"][k] for k in keys), *(m.get(k) for k in METRICS), p["error"] or ""])
    return buf.getvalue()


#: Axis labels of the plotted metrics, with their units.
LABELS = {"gd_max_deg": "GD max (Eq. 11), deg", "pa_max": "PA max (Eq. 12)",
          "contrast_nyquist_min": "contrast at Nyquist, min", "rms_spot_mean_arcmin": "RMS spot mean, arcmin"}
#: Units of sweepable keys by their last name (dotted paths); parameter names take the design's own.
_KEY_UNITS = (("power_diopters", "D"), ("curvature", "1/mm"), ("tilt", "deg"), ("pitch", "mm"), ("thickness", "mm"),
              ("distance", "mm"), ("gap", "mm"), ("semi_diameter", "mm"), ("radius", "mm"), ("decenter", "mm"),
              ("position", "mm"), ("diameter", "mm"), ("wavelength", "nm"))
#: Spread below which a curve is drawn as constant (float rounding, not a trend): relative to its
#: value, or absolute (the plotted metrics are of order 0.01 to 10 in their units).
FLAT_REL, FLAT_ABS = 1e-9, 1e-9


def unit_of(design: Design, key: str) -> str:
    """The unit of a sweep key: the design vector's for a parameter name, else by the key's last name."""
    for name, _, unit in design.parameters(design.wavelength(None)):
        if name == key:
            return unit
    last = key.rsplit(".", 1)[-1].split("[", 1)[0]
    return next((u for k, u in _KEY_UNITS if k in last), "")


def _flatten(ax, ys) -> bool:
    """Draw a curve that is constant to float rounding as constant: y limits ±1 % (or ±1e-3) about it."""
    ys = np.asarray([y for y in ys if np.isfinite(y)], float)
    if ys.size < 2:
        return False
    mid, spread = float(np.mean(ys)), float(np.ptp(ys))
    if spread > max(FLAT_REL * abs(mid), FLAT_ABS):
        return False
    half = max(0.01 * abs(mid), 1e-3)
    ax.set_ylim(mid - half, mid + half)
    ax.ticklabel_format(axis="y", useOffset=False, style="plain")
    ax.text(0.5, 0.92, f"constant ({mid:.3g}; spread {spread:.1e})", transform=ax.transAxes, ha="center",
            fontsize=7, color="0.3")
    return True


def _plot(keys, points, path: Path, x_label: str | None = None) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from ..fileio import save_figure

    shown = ("gd_max_deg", "pa_max", "contrast_nyquist_min", "rms_spot_mean_arcmin")
    fig, axes = plt.subplots(1, len(shown), figsize=(4.0 * len(shown), 3.3))
    x_key, rest = keys[0], keys[1:]
    groups: dict = {}
    for p in points:
        groups.setdefault(tuple(p["values"][k] for k in rest), []).append(p)
    for ax, metric in zip(axes, shown):
        every = []
        for g, pts in groups.items():
            xs = [p["values"][x_key] for p in pts]
            ys = [np.nan if not p["metrics"] or p["metrics"].get(metric) is None else p["metrics"][metric]
                  for p in pts]
            every += ys
            label = ", ".join(f"{k}={v:g}" for k, v in zip(rest, g)) or None
            ax.plot(xs, ys, "o-", ms=3, label=label)
        _flatten(ax, every)
        ax.set_xlabel(x_label or x_key)
        ax.set_ylabel(LABELS.get(metric, metric))
        ax.grid(alpha=0.3)
        if rest and len(groups) <= 8:
            ax.legend(fontsize=6)
    fig.tight_layout()
    save_figure(fig, path, dpi=110)
    plt.close(fig)


def run_sweep(design: Design, out_dir, axes: dict[str, np.ndarray], fixed: dict[str, float] | None = None,
              stride=None, reference: str | None = None, render: bool = False, render_spec=None,
              content=None, scheduler: str | None = None, workers: int | None = None, serial: bool = False,
              batch: int = 1, progress: bool = False, log=None) -> dict:
    """Evaluate the grid; write ``sweep.json``, ``sweep.csv``, ``sweep.png`` (and focal stacks)
    into ``out_dir``, a folder replaced as a whole on success (see :func:`lfsim.fileio.atomic_dir`)."""
    from ..fileio import atomic_dir, check_replaceable

    check_replaceable(out_dir, "sweep.json")
    if not axes:
        raise ValueError("--set KEY=START:STOP:COUNT: give at least one axis to sweep")
    if design.ini is None:
        raise DesignError(design.path or "<dict>", "ini", None, "lfsim sweep needs an [ini] section")
    path = design.path or "<dict>"
    raw = apply_overrides(design.raw, dict(fixed or {}), path)
    if stride is not None:
        raw = dict(raw)
        raw["ini"] = dict(raw["ini"])
        raw["ini"]["analysis"] = {**raw["ini"].get("analysis", {}), "stride": list(stride), "symmetry": "none"}
    Design.from_dict(raw, path)
    from .. import budget
    from .execute import BYTES_PER_RECORD

    n_pts = int(np.prod([len(v) for v in axes.values()]))
    per_stack = None
    if render and render_spec is not None and render_spec.resolution:
        from ..render.focal_stack import estimate

        per_stack = estimate(render_spec, render_spec.resolution, 0)
    budget.check(budget.Estimate(
        f"sweep of {n_pts:,} points" + (f", each a {per_stack.what}" if per_stack else ""),
        n_pts * per_stack.seconds if per_stack else 0.0,
        budget.BASE_BYTES + BYTES_PER_RECORD * n_pts + (per_stack.bytes if per_stack else 0.0)),
        log=log, hint="fewer points")
    pts = grid(axes)
    Design.from_dict(apply_overrides(raw, pts[0], path), path)  # an unknown key is bad input, not a bad point
    units = [(f"pt:{i}", p) for i, p in enumerate(pts)]
    records: dict[str, dict] = {}
    bar = None
    if progress:
        from ..progress import bar as tqdm

        bar = tqdm(total=len(units), desc="points", unit="pt")

    def on_records(recs):
        for r in recs:
            records.setdefault(r["id"], r)
        if bar:
            bar.update(len(recs))

    import hashlib
    import json

    key = hashlib.sha256(json.dumps({"raw": raw, "ref": reference}, sort_keys=True, default=str).encode()).hexdigest()
    job = {"kind": "sweep", "key": key[:16], "raw": raw, "path": path, "reference": reference, "threads": None}
    t0 = time.perf_counter()
    try:
        where = execute.run(job, units, batch=batch, scheduler=scheduler, workers=workers, serial=serial,
                            on_records=on_records, estimate="sweep points", log=log)
    finally:
        if bar:
            bar.close()
    seconds = time.perf_counter() - t0
    keys = list(axes)
    points = []
    for i, p in enumerate(pts):
        r = records[f"pt:{i}"]
        points.append({"index": i, "values": p, "metrics": r["metrics"], "error": r["error"],
                       "seconds": r["seconds"]})
    with atomic_dir(out_dir, "sweep.json") as out:
        return _write(design, out, raw, path, axes, keys, fixed, reference, points, seconds, where, render,
                      render_spec, content)


def _write(design, out, raw, path, axes, keys, fixed, reference, points, seconds, where, render, render_spec,
           content) -> dict:
    if render:
        from ..vision.focus_cues import focal_stack

        for p in points:
            if p["error"]:
                continue
            d = Design.from_dict(apply_overrides(raw, p["values"], path), path)
            sub = out / "points" / f"{p['index']:04d}"
            index, _ = focal_stack(d, content, sub, render_spec, progress=False, log=lambda *a, **k: None)
            p["focal_stack"] = {"dir": str(sub.relative_to(out)), "images": [
                {k: im.get(k) for k in ("kind", "focus_mm", "png", "ssim_vs_natural", "psnr_vs_natural",
                                           "exposure_vs_natural", "ssim_vs_natural_matched")}
                for im in index["images"]]}
    units = {k: unit_of(design, k) for k in keys}
    doc = {"design": design.name, "file": design.path, "axes": {k: [float(v) for v in axes[k]] for k in keys},
           "units": units,
           "fixed": dict(fixed or {}), "reference": reference or "self", "points": points,
           "seconds": round(seconds, 2), "execution": where}
    write_text(out / "sweep.csv", _table_csv(keys, points))
    _plot(keys, points, out / "sweep.png", x_label=f"{keys[0]}, {units[keys[0]]}".rstrip(", "))
    doc["plots"] = ["sweep.png"]
    write_json(out / "sweep.json", doc)
    return doc
