"""`lfsim optimize`: the design method's workflow, stage by stage, with checkpoints.

Stages (the ``[optimize] stages`` of the design file, in this order):

``mla``
    the lenslet array alone: only the variables of the MLA's surfaces and of
    the array itself move, under the full light-field merit at the sampled
    sub-systems (a starting point for the lenslets with the relay and
    eyepiece held);
``relay_eyepiece``
    the relay, tunable lens and eyepiece alone: every other variable;
``integrated``
    every variable, sampled sub-systems (``[optimize.sampling] stride``) at
    every CDP depth;
``full``
    every variable, all M × N sub-systems at every CDP depth.

Each stage is a damped least-squares (or Adam) run of
:class:`~lfsim.optimize.merit.IniMerit` from the previous stage's design; its
solver state is checkpointed after every accepted iteration in
``OUT/checkpoints/<stage>.npz`` so an interrupted run resumes where it
stopped (``resume=True``) and ends bit for bit where an uninterrupted run
would.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from ..design.design import Design
from ..fileio import save_figure, write_json
from .imaging import ImagingMerit
from .merit import IniMerit, columns
from .solvers import Bounds, CheckpointMismatch, adam, levenberg_marquardt


def stage_columns(design: Design, cols, stage: str):
    """The variables a stage moves (see the module docstring)."""
    if stage in ("integrated", "full"):
        return list(cols)
    ini = design.ini
    if ini is None:
        raise ValueError(f"stage {stage!r} needs an InI design ([ini]); a plain lens has only \"full\"")
    mla_names = {design.system.surfaces[i].name for i in ini.mla_surfaces} | {ini.mla}

    def in_mla(c):
        return c.state is None and c.name.split(".")[0] in mla_names

    if stage == "mla":
        return [c for c in cols if in_mla(c)]
    if stage == "relay_eyepiece":
        return [c for c in cols if not in_mla(c)]
    raise ValueError(f"unknown stage {stage!r}")


def _summary(details: dict) -> dict:
    return {k: (round(v, 6) if isinstance(v, float) else v) for k, v in details.items()}


def optimize(design: Design, out_dir, stages=None, iterations: int | None = None, solver: str | None = None,
             resume: bool = False, progress: bool = False, log=print, analyze_stride=(4, 2)) -> dict:
    """Run the stages; write the optimized design, the merit history and plots.

    Returns the ``history.json`` document. ``OUT/<stem>_optimized.toml`` is the
    result (the input file's table with the variables' values, and the merit
    figures in its header). With ``analyze_stride`` (lenslet stride, default
    (4, 2); None: skip), the start and the result are analysed as by
    ``lfsim analyze`` into ``OUT/before`` and ``OUT/after``, compared in
    ``before_after.png`` and in the document's ``before_after`` — what
    ``lfsim optimize`` writes.
    """
    if analyze_stride is not None:
        analyze_stride = tuple(int(v) for v in analyze_stride)
        if len(analyze_stride) != 2 or min(analyze_stride) < 1:
            raise ValueError(f"analyze_stride = {analyze_stride!r}: expected two integers >= 1")
    from ..design.writer import write_design

    spec = design.optimize
    if spec is None:
        raise ValueError(f"{design.path}: the design has no [optimize] section")
    if not spec.variables:
        raise ValueError(f"{design.path}: optimize.variables is empty: nothing to vary")
    out = Path(out_dir)
    (out / "checkpoints").mkdir(parents=True, exist_ok=True)
    stages = list(stages or spec.stages)
    override = iterations
    iterations = int(iterations or spec.iterations)
    solver = solver or spec.solver
    all_cols = columns(design, spec)
    current = design
    doc = {"design": design.path, "solver": solver, "iterations_per_stage": iterations,
           "variables": [c.label for c in all_cols], "stages": []}
    t_all = time.perf_counter()
    for stage in stages:
        cols = stage_columns(design, all_cols, stage)
        if not cols:
            log(f"stage {stage}: no variables, skipped")
            continue
        stride = (1, 1) if stage == "full" else None
        t0 = time.perf_counter()
        merit = (IniMerit(current, spec, cols=cols, stride=stride) if current.ini is not None
                 else ImagingMerit(current, spec, cols=cols))
        lo, hi = merit.bounds
        x0 = np.clip(merit.x0, lo, hi)
        r0, _, det0 = merit.evaluate(x0, derivatives=False)
        ckpt = out / "checkpoints" / f"{stage}.npz"
        log(f"stage {stage}: {len(cols)} variables, {merit.rays} rays, merit {float(r0 @ r0):.6g}")
        scale = np.maximum(np.abs(x0), 1e-3)
        n_it = iterations
        if stage == "full" and spec.full_iterations is not None and override is None:
            n_it = spec.full_iterations
        def solve(resume_stage):
            if solver == "lm":
                return levenberg_marquardt(merit, x0, Bounds(lo, hi), max_iterations=n_it, scale=scale,
                                           checkpoint=ckpt, resume=resume_stage, progress=progress)
            return adam(merit, x0, Bounds(lo, hi), iterations=n_it, scale=scale, checkpoint=ckpt,
                        resume=resume_stage, progress=progress)

        try:
            res = solve(resume)
        except CheckpointMismatch as e:
            # A later stage whose start moved (an earlier stage resumed with more iterations
            # ended elsewhere): its checkpoint is stale, so the stage starts afresh. A first
            # stage whose start moved means the input changed: that is still refused.
            if not doc["stages"] or not set(e.keys) <= {"x0", "scale"}:
                raise
            log(f"stage {stage}: the earlier stages ended elsewhere than when {ckpt.name} was written; "
                "starting this stage afresh")
            ckpt.unlink()
            res = solve(False)
        r1, _, det1 = merit.evaluate(res.x, derivatives=False)
        current = merit.design_at(res.x)
        secs = time.perf_counter() - t0
        rec = {"stage": stage, "variables": [c.label for c in cols], "stride": list(merit.stride),
               "rays": merit.rays, "status": res.status, "iterations": res.iterations,
               "evaluations": res.evaluations, "merit_start": float(r0 @ r0), "merit_end": float(r1 @ r1),
               "blocks_start": _summary(det0), "blocks_end": _summary(det1),
               "x_start": [float(v) for v in x0], "x_end": [float(v) for v in res.x],
               "history": res.history, "seconds": round(secs, 2)}
        doc["stages"].append(rec)
        log(f"stage {stage}: merit {rec['merit_start']:.6g} -> {rec['merit_end']:.6g} "
            f"({res.status}, {res.iterations} iterations, {secs:.1f} s); {merit.describe(det1)}")
    doc["seconds"] = round(time.perf_counter() - t_all, 2)
    stem = Path(design.path or "design").stem
    path = out / f"{stem}_optimized.toml"
    header = [f"{design.name}: optimized by `lfsim optimize` from {Path(design.path or '').name}",
              f"solver {solver}, stages {', '.join(r['stage'] for r in doc['stages'])}, "
              f"{doc['seconds']:.0f} s"]
    for r in doc["stages"]:
        header.append(f"  {r['stage']}: merit {r['merit_start']:.6g} -> {r['merit_end']:.6g} "
                      f"({r['iterations']} iterations, {r['status']}, stride {r['stride'][0]}x{r['stride'][1]})")
    header.append("Evaluate with: lfsim analyze THIS_FILE --out DIR --stride 1,1")
    raw = dict(current.raw)
    raw["name"] = design.name if "optimized" in design.name.lower() else f"{design.name} (optimized)"
    write_design(path, raw, header)
    doc["optimized_design"] = path.name
    plot_history(doc, out / "merit_history.png")
    doc["plots"] = ["merit_history.png"]
    if analyze_stride is not None and design.ini is not None:
        from ..analysis.ini_analysis import analyze
        from ..design import load

        before = analyze(design, out / "before", stride=analyze_stride, plots=True)
        after = analyze(load(path), out / "after", stride=analyze_stride, plots=True)
        doc["before_after"] = compare(before, after, out / "before_after.png")
        doc["before_after_stride"] = list(analyze_stride)
        doc["plots"].append("before_after.png")
    elif analyze_stride is not None:  # a plain lens: its layout and spot report before and after
        from ..analysis.layout import layout_report
        from ..design import load

        before = layout_report(design, out / "before")
        after = layout_report(load(path), out / "after")
        unit = "°" if design.system.field_type == "angle" else " mm"
        doc["before_after"] = compare_spots(before, after, out / "before_after.png", unit)
        doc["plots"].append("before_after.png")
    write_json(out / "history.json", doc)
    return doc


def plot_history(doc: dict, path) -> None:
    """Merit per accepted iteration, stage after stage (log scale)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 3.6))
    start = 0
    for rec in doc["stages"]:
        costs = [rec["merit_start"]] + [h["cost"] for h in rec["history"]]
        xs = np.arange(start, start + len(costs))
        ax.semilogy(xs, costs, "o-", ms=3, label=f"{rec['stage']} ({rec['stride'][0]}x{rec['stride'][1]})")
        start = xs[-1] + 1
    ax.set_xlabel("accepted iteration")
    ax.set_ylabel("merit (sum of squared residuals)")
    ax.set_title(f"{Path(doc['design'] or '').name}: {doc['solver']}")
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=8)
    fig.tight_layout()
    save_figure(fig, path, dpi=110)
    plt.close(fig)


def compare_spots(before: dict, after: dict, path, field_unit: str = "°") -> dict:
    """Before/after RMS spot radius per field (µm) of two ``lfsim layout`` summaries, with a bar plot."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    def rms(doc):
        return [r["rms_um"] for r in doc["spots"]]

    fields = [r["field"] for r in before["spots"]]
    b, a = rms(before), rms(after)
    fig, ax = plt.subplots(figsize=(6, 3.4))
    xs = np.arange(len(fields))
    ax.bar(xs - 0.2, [v or 0.0 for v in b], 0.4, label="before")
    ax.bar(xs + 0.2, [v or 0.0 for v in a], 0.4, label="after")
    ax.set_xticks(xs, [f"{f:g}{field_unit}" for f in fields])
    ax.set_xlabel("field")
    ax.set_ylabel("RMS spot (µm, primary λ)")
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3, axis="y")
    fig.tight_layout()
    save_figure(fig, path, dpi=110)
    plt.close(fig)
    return {"rms_spot_um": {"fields": fields, "before": b, "after": a},
            "efl_mm": {"before": before["first_order"].get("efl"), "after": after["first_order"].get("efl")}}


def compare(before: dict, after: dict, path) -> dict:
    """Before/after table and bar plots of two ``lfsim analyze`` documents: one panel per
    quantity and unit (GD in degrees, PA, contrast at Nyquist, RMS spot in arcmin),
    with the design's targets where it has them."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    panels = [("GD (Eq. 11), deg", [("gd_max_deg", "max"), ("gd_mean_deg", "mean")], "gd_target_deg"),
              ("PA (Eq. 12)", [("pa_max", "max"), ("pa_mean", "mean")], "pa_target"),
              ("contrast at Nyquist", [("contrast_nyquist_min", "min"), ("contrast_nyquist_mean", "mean")], None),
              ("RMS spot, arcmin", [("rms_spot_mean_arcmin", "mean")], None)]
    keys = [k for _, ks, _ in panels for k, _ in ks]
    rows = {k: (before["summary"].get(k), after["summary"].get(k)) for k in keys}
    fig, axes = plt.subplots(1, len(panels), figsize=(11, 3.4))
    for ax, (title, ks, target) in zip(axes, panels):
        xs = np.arange(len(ks))
        for dx, j, lbl in ((-0.2, 0, "before"), (0.2, 1, "after")):
            vals = [rows[k][j] for k, _ in ks]
            bars = ax.bar(xs + dx, [np.nan if v is None else v for v in vals], 0.4, label=lbl)
            ax.bar_label(bars, labels=["-" if v is None else f"{v:.3g}" for v in vals], fontsize=7)
        t = before["summary"].get(target) if target else None
        if t is not None:
            ax.axhline(t, color="k", ls="--", lw=0.8, label=f"target {t:g}")
        ax.set_xticks(xs, [lbl for _, lbl in ks], fontsize=8)
        ax.set_xlim(-0.6, len(ks) - 0.4)
        ax.set_ylabel(title, fontsize=9)
        ax.margins(y=0.15)
        ax.grid(alpha=0.3, axis="y")
    axes[0].legend(fontsize=7)
    fig.tight_layout()
    save_figure(fig, path, dpi=110)
    plt.close(fig)
    return {k: {"before": v[0], "after": v[1]} for k, v in rows.items()}

