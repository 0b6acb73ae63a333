"""The step model's hinges, measured: ``lm`` and ``lm-hinge`` side by side.

Usage::

    .venv/bin/python benchmarks/solver_hinges.py                       # the wearable's gd stage
    .venv/bin/python benchmarks/solver_hinges.py --design D --stage S --iterations N [--solvers a,b]

From the same start (the design's numbers, the stage's variables, targets, weights and
sampling), each solver takes N damped least-squares steps in this process, one after
another, so that both share the machine and the compiled kernels (the first solver
also pays the kernel compiles: name it twice in ``--solvers`` for a warm ratio).
Recorded per solver: the merit after every accepted step, the seconds, the residual and
Jacobian evaluations, and the figures of the merit's last evaluation (GD max and mean,
PA max, the mean RMS spot, the rays lost). The ratio that matters is the merit's decrease
per iteration and per second against ``lm``'s.

* ``lm``: every limit (the glass, package and display limits, and the per-field spot, GD,
  PA and colour limits) is a penalty row that exists only while the limit is broken, so
  the step's linear model cannot see a step break a limit that holds;
* ``lm-hinge``: the mechanical limits enter the step model as hinges max(0, g + G h), with
  their Jacobian whether or not they hold.

Output: a table on stdout, ``benchmarks/results/solver_hinges.json`` (or ``--json``) and
a plot of the merit against iterations and seconds beside it, both written atomically.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from lfsim import load  # noqa: E402
from lfsim.design.errors import DesignError  # noqa: E402
from lfsim.fileio import save_figure, write_json  # noqa: E402
from lfsim.optimize.merit import IniMerit  # noqa: E402
from lfsim.optimize.solvers import Bounds, levenberg_marquardt  # noqa: E402
from lfsim.optimize.workflow import plans  # noqa: E402

SOLVERS = ("lm", "lm-hinge")


def run(design, stage: str, solver: str, iterations: int) -> dict:
    plan = plans(design, [stage])[0]
    merit = IniMerit(design, plan.spec, cols=plan.cols, stride=plan.stride, hinge_model=solver == "lm-hinge")
    lo, hi = merit.bounds
    x0 = np.clip(merit.x0, lo, hi)
    t0 = time.perf_counter()
    trail = []

    def seen(rec):
        trail.append({"iteration": rec["iteration"], "merit": rec["cost"], "lambda": rec["lambda"],
                      "seconds": round(time.perf_counter() - t0, 2)})
        print(f"  {solver} {rec['iteration']}/{iterations}: merit {rec['cost']:.6g}, lambda {rec['lambda']:.3g}, "
              f"{trail[-1]['seconds']:.0f} s", flush=True)

    res = levenberg_marquardt(merit, x0, Bounds(lo, hi), max_iterations=iterations, scale=np.maximum(np.abs(x0), 1e-3),
                              hinges=solver == "lm-hinge", on_iteration=seen)
    secs = time.perf_counter() - t0
    _, _, det = merit.evaluate(res.x, derivatives=False)
    keys = ("gd_max_deg", "gd_mean_deg", "pa_max", "rms_spot_mean_arcmin", "rays_lost")
    return {"solver": solver, "status": res.status, "iterations": res.iterations, "evaluations": res.evaluations,
            "merit_start": res.cost0, "merit_end": res.cost, "decrease": 1.0 - res.cost / res.cost0,
            "seconds": round(secs, 2), "trail": trail, "figures_end": {k: det.get(k) for k in keys},
            "variables": len(plan.cols), "rays": merit.rays}


def plot(doc: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(10, 3.8))
    for r in doc["runs"]:
        it = [0] + [t["iteration"] for t in r["trail"]]
        f = [r["merit_start"]] + [t["merit"] for t in r["trail"]]
        s = [0.0] + [t["seconds"] for t in r["trail"]]
        axes[0].plot(it, f, marker="o", ms=3, label=r["solver"])
        axes[1].plot(s, f, marker="o", ms=3, label=r["solver"])
    axes[0].set_xlabel("accepted step")
    axes[1].set_xlabel("seconds (2 cores)")
    for a in axes:
        a.set_ylabel("merit")
        a.grid(alpha=0.3)
    axes[0].legend()
    fig.suptitle(f"{Path(doc['design']).name}, stage {doc['stage']}: merit per step and per second")
    fig.tight_layout()
    save_figure(fig, path, dpi=110)
    plt.close(fig)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0],
                                 formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    ap.add_argument("--design", default=str(ROOT / "scenes" / "ini_wearable_optimized.toml"),
                    help="an [ini] design file with an [[optimize.stages]] schedule")
    ap.add_argument("--stage", default="gd", help="the schedule's stage whose merit both solvers minimize")
    ap.add_argument("--iterations", type=int, default=10, help="accepted steps per solver")
    ap.add_argument("--solvers", default=",".join(SOLVERS),
                    help=f"comma-separated, from {', '.join(SOLVERS)}; a name given twice runs twice (warm)")
    ap.add_argument("--json", default=str(ROOT / "benchmarks" / "results" / "solver_hinges.json"),
                    help="the JSON written (the plot beside it, .png)")
    a = ap.parse_args(argv)
    solvers = [s for s in a.solvers.split(",") if s]  # a name given twice runs twice (warm)
    bad = [s for s in solvers if s not in SOLVERS]
    if bad or a.iterations < 1:
        print(f"solver_hinges.py: --solvers {a.solvers!r} / --iterations {a.iterations}: solvers from "
              f"{', '.join(SOLVERS)}, at least one iteration", file=sys.stderr)
        return 2
    try:
        design = load(a.design)
    except DesignError as e:
        print(f"solver_hinges.py: {e}", file=sys.stderr)
        return 2
    names = [st.name for st in (design.optimize.schedule or [])] if design.optimize else []
    if a.stage not in names:
        print(f"solver_hinges.py: {a.design}: no stage {a.stage!r} in [[optimize.stages]] ({', '.join(names)})",
              file=sys.stderr)
        return 2
    runs = []
    for s in solvers:
        print(f"{s}:", flush=True)
        runs.append(run(design, a.stage, s, a.iterations))
    base = next((r for r in runs if r["solver"] == "lm"), runs[0])
    print(f"\n{'solver':14s} {'merit start':>12s} {'merit end':>12s} {'decrease':>9s} {'s':>6s} "
          f"{'x lm /step':>10s} {'x lm /s':>8s}  GD max, PA max, spot")
    for r in runs:
        per_it = r["decrease"] / max(base["decrease"], 1e-300)
        per_s = per_it * base["seconds"] / r["seconds"]
        r["decrease_vs_lm"], r["decrease_per_second_vs_lm"] = per_it, per_s
        f = r["figures_end"]
        print(f"{r['solver']:14s} {r['merit_start']:12.6g} {r['merit_end']:12.6g} {100 * r['decrease']:8.2f}% "
              f"{r['seconds']:6.0f} {per_it:10.2f} {per_s:8.2f}  {f['gd_max_deg']:.3f} deg, {f['pa_max']:.3f}, "
              f"{f['rms_spot_mean_arcmin']:.3f}'")
    doc = {"design": a.design, "stage": a.stage, "iterations": a.iterations, "runs": runs}
    out = Path(a.json)
    out.parent.mkdir(parents=True, exist_ok=True)
    write_json(out, doc)
    plot(doc, out.with_suffix(".png"))
    print(f"wrote {out} and {out.with_suffix('.png').name}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
