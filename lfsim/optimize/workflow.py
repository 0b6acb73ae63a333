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

import re
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


def block_shares(details: dict, layout) -> dict:
    """Each residual block's share of the merit (aperture_* and tir_* blocks summed)."""
    sums: dict = {}
    for name, _ in layout:
        key = "aperture" if name.startswith("aperture_") else "tir" if name.startswith("tir_") else name
        sums[key] = sums.get(key, 0.0) + float(details.get(name, 0.0))
    total = sum(sums.values())
    return {k: v / total for k, v in sums.items()} if total > 0 else {k: 0.0 for k in sums}


def _release() -> None:
    """Hand the memory of a finished stage or analysis back: Python's cycles, then the
    blocks Dr.Jit keeps for reuse (otherwise each phase's peak adds to the next's)."""
    import gc

    import drjit as dr

    gc.collect()
    dr.flush_malloc_cache()
    try:  # glibc keeps freed heap pages mapped unless asked
        import ctypes

        ctypes.CDLL("libc.so.6").malloc_trim(0)
    except (OSError, AttributeError):
        pass


def _peak_rss_gb() -> float:
    """This process's peak resident memory so far (GB; Linux reports kB)."""
    import resource
    import sys

    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return peak / (1e9 if sys.platform == "darwin" else 1e6)


def _duration(seconds: float) -> str:
    s = int(round(seconds))
    return f"{s // 60}:{s % 60:02d}"


class _Plan:
    """One stage to run: its name, merit settings, variables, sampling, cap and solver."""

    def __init__(self, name, spec, cols, stride, iterations, solver):
        self.name, self.spec, self.cols, self.stride = name, spec, cols, stride
        self.iterations, self.solver = iterations, solver


def plans(design: Design, stages=None, iterations: int | None = None, solver: str | None = None) -> list[_Plan]:
    """The stages a run goes through: the design's ``[[optimize.stages]]`` schedule (or
    the named subset of it), or the workflow stages of a ``stages = [...]`` list.
    ``iterations`` and ``solver`` override every stage's."""
    spec = design.optimize
    if spec.schedule is not None:
        chosen = list(stages or spec.stages)
        by_name = {st.name: st for st in spec.schedule}
        bad = [n for n in chosen if n not in by_name]
        if bad:
            raise ValueError(f"{design.path}: no stage {bad[0]!r} in [[optimize.stages]] "
                             f"(the schedule has {', '.join(by_name)})")
        out = []
        for st in spec.schedule:
            if st.name not in chosen:
                continue
            sub = spec.for_stage(st)
            out.append(_Plan(st.name, sub, columns(design, sub), st.stride, int(iterations or st.iterations),
                             solver or st.solver))
        return out
    all_cols = columns(design, spec)
    out = []
    for stage in list(stages or spec.stages):
        n_it = int(iterations or spec.iterations)
        if stage == "full" and spec.full_iterations is not None and iterations is None:
            n_it = spec.full_iterations
        out.append(_Plan(stage, spec, stage_columns(design, all_cols, stage), (1, 1) if stage == "full" else None,
                         n_it, solver or spec.solver))
    return out


#: A start's name ends in what marks it as one: ", starting point", " (optimization start)", " start".
_START = re.compile(r"(?:(?P<sep>[,;:])\s*|\s*(?P<open>\(\s*))(?:optimi[sz]ation\s+)?(?:starting\s+point|start)"
                    r"(?(open)\s*\))\s*$", re.IGNORECASE)


def _base_name(name: str) -> str:
    """``name`` without the words that mark it as an optimization's start."""
    m = _START.search(name)
    return name[:m.start()] if m else name


def optimized_name(name: str) -> str:
    """The name of an optimized design: the start's, its "starting point" / "(optimization start)"
    replaced (``"X, starting point"`` → ``"X, optimized"``, ``"X (optimization start)"`` →
    ``"X (optimized)"``), else ``"X (optimized)"``; a name that already says it is left as it is."""
    if "optimized" in name.lower():
        return name
    m = _START.search(name)
    if m is None:
        return f"{name} (optimized)"
    return name[:m.start()] + (" (optimized)" if m.group("open") else f"{m.group('sep')} optimized")


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
    if not spec.varies_anything:
        raise ValueError(f"{design.path}: optimize.variables is empty: nothing to vary")
    todo = plans(design, stages, iterations, solver)
    out = Path(out_dir)
    current = design
    solvers = sorted({p.solver for p in todo})
    doc = {"design": design.path, "solver": solvers[0] if len(solvers) == 1 else ",".join(solvers),
           "iterations_per_stage": todo[0].iterations if todo else 0,
           "schedule": spec.schedule is not None,
           "variables": [c.label for c in columns(design, spec)], "stages": []}
    efl_target = None  # a schedule keeps the input design's focal length through every stage
    t_all = time.perf_counter()
    for plan in todo:
        stage, cols, n_it = plan.name, plan.cols, plan.iterations
        if not cols:
            log(f"stage {stage}: no variables, skipped")
            continue
        t0 = time.perf_counter()
        if current.ini is not None:
            merit = IniMerit(current, plan.spec, cols=cols, stride=plan.stride, efl_target=efl_target,
                             hinge_model=plan.solver == "lm-hinge")
            if spec.schedule is not None and efl_target is None:
                efl_target = merit.efl_target
        else:
            merit = ImagingMerit(current, plan.spec, cols=cols, hinge_model=plan.solver == "lm-hinge")
        lo, hi = merit.bounds
        x0 = np.clip(merit.x0, lo, hi)
        r0, _, det0 = merit.evaluate(x0, derivatives=False)
        ckpt = out / "checkpoints" / f"{stage}.npz"
        ckpt.parent.mkdir(parents=True, exist_ok=True)  # once the stage's merit stands: a refusal writes nothing
        log(f"stage {stage}: {len(cols)} variables, {merit.rays} rays, stride "
            f"{merit.stride[0]}x{merit.stride[1]}, up to {n_it} iterations ({plan.solver}), merit {float(r0 @ r0):.6g}")
        scale = np.maximum(np.abs(x0), 1e-3)
        lap = {"t": time.perf_counter(), "times": []}

        def report(rec, stage=stage, merit=merit, n_it=n_it, lap=lap):
            now = time.perf_counter()
            lap["times"].append(now - lap["t"])
            lap["t"] = now
            shares = block_shares(merit.details, merit.layout)
            top = ", ".join(f"{k} {100 * v:.0f}%" for k, v in sorted(shares.items(), key=lambda kv: -kv[1])
                            if v >= 0.01)
            damp = f"lambda {rec['lambda']:.3g}" if "lambda" in rec else f"lr {rec['lr']:.3g}"
            eta = float(np.mean(lap["times"][-5:])) * (n_it - rec["iteration"])
            log(f"  {stage} {rec['iteration']}/{n_it}: merit {rec['cost']:.6g} ({top}); {damp}, step "
                f"{rec['step_norm']:.3g}, {lap['times'][-1]:.1f} s; stage ETA {_duration(eta)} at most")

        def solve(resume_stage, plan=plan, merit=merit, x0=x0, lo=lo, hi=hi, ckpt=ckpt, scale=scale,
                  n_it=n_it, report=report):
            kw = dict(scale=scale, checkpoint=ckpt, resume=resume_stage, progress=progress, on_iteration=report)
            if plan.solver in ("lm", "lm-hinge"):
                return levenberg_marquardt(merit, x0, Bounds(lo, hi), max_iterations=n_it,
                                           hinges=plan.solver == "lm-hinge", **kw)
            return adam(merit, x0, Bounds(lo, hi), iterations=n_it, **kw)

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
               "solver": plan.solver, "rays": merit.rays, "status": res.status, "iterations": res.iterations,
               "max_iterations": n_it, "evaluations": res.evaluations, "merit_start": float(r0 @ r0),
               "merit_end": float(r1 @ r1), "blocks_start": _summary(det0), "blocks_end": _summary(det1),
               "x_start": [float(v) for v in x0], "x_end": [float(v) for v in res.x],
               "history": res.history, "seconds": round(secs, 2)}
        doc["stages"].append(rec)
        said = merit.describe(det1)
        del merit, res, solve, report
        _release()
        rec["peak_rss_gb"] = round(_peak_rss_gb(), 3)
        log(f"stage {stage}: merit {rec['merit_start']:.6g} -> {rec['merit_end']:.6g} "
            f"({rec['status']}, {rec['iterations']} iterations, {secs:.1f} s, peak memory so far "
            f"{rec['peak_rss_gb']:.2f} GB); {said}")
    doc["seconds"] = round(time.perf_counter() - t_all, 2)
    stem = Path(design.path or "design").stem
    path = out / f"{stem}_optimized.toml"
    src = Path(design.path or "design.toml")
    try:
        shown = src.resolve().relative_to(Path.cwd().resolve())
    except ValueError:
        shown = src
    header = [f"{_base_name(design.name)}: optimized from {src.name} by one run of",
              f"  lfsim optimize {shown} --out DIR",
              f"solver {doc['solver']}, stages {', '.join(r['stage'] for r in doc['stages'])}, "
              f"{doc['seconds']:.0f} s"]
    for r in doc["stages"]:
        header.append(f"  {r['stage']}: merit {r['merit_start']:.6g} -> {r['merit_end']:.6g} "
                      f"({r['iterations']} of at most {r['max_iterations']} iterations, {r['status']}, "
                      f"stride {r['stride'][0]}x{r['stride'][1]}, {len(r['variables'])} variables, "
                      f"{r['seconds']:.0f} s)")
    header.append("Evaluate with: lfsim analyze THIS_FILE --out DIR --stride 1,1" if design.ini is not None
                  else "Evaluate with: lfsim layout THIS_FILE --out DIR")
    raw = dict(current.raw)
    raw["name"] = optimized_name(design.name)
    write_design(path, raw, header)
    doc["optimized_design"] = path.name
    plot_history(doc, out / "merit_history.png")
    doc["plots"] = ["merit_history.png"]
    if analyze_stride is not None and design.ini is not None:
        from ..analysis.ini_analysis import analyze
        from ..design import load

        before = analyze(design, out / "before", stride=analyze_stride, plots=True)
        _release()
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

