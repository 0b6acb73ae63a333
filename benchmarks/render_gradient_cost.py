"""Cost of a render gradient with and without its boundary term, side by side, cold and warm.

For each design, at the default settings of ``lfsim gradcheck`` (the content's
``[view]``: Fig. 9 wall, eye focused at 600 / 1000 / 1400 mm, CDP 750 mm, 3 mm
pupil; 96×54 px at 16 spp, float64), one process builds the renderer and the
loss (``Σ_focus mean (I − R)²`` against the natural view) and then times, in
this order:

* the interior gradient (``lfsim.render.gradcheck.gradient``, reverse mode,
  AD along fixed samples) and the total gradient (``total=True``, with the
  boundary term of :mod:`lfsim.render.boundary`), each called twice: the first
  call includes the kernel compiles of that process, the second is warm;
* the per-pixel Jacobian of the inverse-design problem
  (:class:`lfsim.render.inverse.FocalStackProblem`, 2 parameters), interior
  against total, once each after a warm-up call.

Each design runs in a fresh process twice: **cold** (an empty Dr.Jit kernel
cache and a new ``HOME``: a user's first run) and **warm** (the cache the cold
run left). Reported per case: seconds and the ratio total / interior (the goal
is ≤ 3×), plus Dr.Jit's kernels compiled.

    .venv/bin/python benchmarks/render_gradient_cost.py [--designs ini_ideal,ini_freeform_optimized]

Prints a table; writes ``benchmarks/results/render_gradient_cost.json``.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

GOAL_RATIO = 3.0
#: Parameters differentiated per design: the tables of docs/differentiable-rendering.md.
PARAMS = {
    "ini_ideal": "MLA.power,EP.power,TL.power,object.distance,MLA.thickness,EP.thickness,MLA.tilt_x,EP.tilt_x,"
                 "MLA.decenter_x,EP.decenter_y,mla.pitch_x,mla.center_y",
    "ini_freeform_optimized": "L1.index,L1.curvature,L1.conic,L2.curvature,L2.A4,S3.x2y0,S4.x0y3,S1.x2y2,"
                              "S2.x0y2,F1b.thickness,S3.position_z,S3.tilt_x,TL.power,object.distance",
}
JACOBIAN_PARAMS = {"ini_ideal": ["TL.power", "MLA.thickness"],
                   "ini_freeform_optimized": ["TL.power", "L1.curvature"]}


def _compiles() -> int:
    """Kernels compiled (not found in the in-memory or on-disk cache) since the last call."""
    import drjit as dr

    return sum(1 for k in dr.kernel_history()
               if k["type"] == dr.KernelType.JIT and not (k["cache_hit"] or k["cache_disk"]))


def child(design_name: str, resolution=(96, 54), spp: int = 16) -> dict:
    """Timings of one design in this process (see the module docstring)."""
    import drjit as dr

    from lfsim.content import load_content
    from lfsim.design.design import load as load_design
    from lfsim.render import gradcheck as gc
    from lfsim.render.diff_render import AnalyticRenderer, ViewSpec
    from lfsim.render.inverse import FocalStackProblem

    dr.set_flag(dr.JitFlag.KernelHistory, True)
    content = load_content(ROOT / "scenes/fig9_wall.toml")
    v = content.view
    design = load_design(ROOT / f"scenes/{design_name}.toml")
    view = ViewSpec(focus_mm=list(v.focus_mm), cdp_mm=v.cdp_mm, pupil_diameter_mm=v.pupil_diameter_mm,
                    resolution=tuple(resolution), spp=int(spp), seed=0)
    t0 = time.perf_counter()
    r = AnalyticRenderer(design, view, content=content)
    targets = gc.natural_targets(r, content, spp=4 * spp, seed=1)
    loss = gc.RenderLoss(r, targets)
    setup = time.perf_counter() - t0
    wrt = [r.index[n] for n in PARAMS[design_name].split(",")]
    out = {"design": design_name, "resolution": list(resolution), "spp": int(spp),
           "samples": r.n_pixels * r.spp * len(view.focus_mm), "parameters": len(wrt), "setup_s": setup}
    dr.kernel_history()  # clear
    for kind, total in (("interior", False), ("total", True)):
        for call in ("first", "second"):
            t0 = time.perf_counter()
            gc.gradient(loss, None, wrt, total=total)
            out[f"gradient_{kind}_{call}_s"] = time.perf_counter() - t0
            out[f"gradient_{kind}_{call}_compiles"] = _compiles()
    names = JACOBIAN_PARAMS[design_name]
    for kind, total in (("interior", False), ("total", True)):
        p = FocalStackProblem(r, targets, names, total=total)
        x = r.values0[[r.index[n] for n in names]]
        p.jacobian(x)  # warm-up
        t0 = time.perf_counter()
        p.jacobian(x)
        out[f"jacobian_{kind}_s"] = time.perf_counter() - t0
    for call in ("first", "second"):
        out[f"gradient_ratio_{call}"] = out[f"gradient_total_{call}_s"] / out[f"gradient_interior_{call}_s"]
    out["jacobian_ratio"] = out["jacobian_total_s"] / out["jacobian_interior_s"]
    return out


def run_case(design: str, env: dict, resolution: str, spp: int) -> dict:
    cmd = [sys.executable, __file__, "--child", design, "--resolution", resolution, "--spp", str(spp)]
    t0 = time.perf_counter()
    res = subprocess.run(cmd, cwd=ROOT, env=env, capture_output=True, text=True, check=True)
    doc = json.loads(res.stdout.strip().splitlines()[-1])
    doc["wall_s"] = time.perf_counter() - t0
    return doc


def main(argv=None) -> int:
    from lfsim.fileio import write_json

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--designs", default="ini_ideal,ini_freeform_optimized")
    ap.add_argument("--resolution", default="96,54")
    ap.add_argument("--spp", type=int, default=16)
    ap.add_argument("--child", help=argparse.SUPPRESS)
    ap.add_argument("--out", default=str(ROOT / "benchmarks/results/render_gradient_cost.json"))
    args = ap.parse_args(argv)
    res = tuple(int(v) for v in args.resolution.split(","))
    if args.child:
        print(json.dumps(child(args.child, res, args.spp)))
        return 0
    rows = []
    for design in args.designs.split(","):
        with tempfile.TemporaryDirectory() as home:
            env = {**os.environ, "HOME": home}
            for state in ("cold", "warm"):
                doc = run_case(design, env, args.resolution, args.spp)
                doc["state"] = state
                rows.append(doc)
                print(f"{design:24s} {state:4s}  gradient interior {doc['gradient_interior_first_s']:6.2f} s "
                      f"/ total {doc['gradient_total_first_s']:6.2f} s  (x{doc['gradient_ratio_first']:.2f}; "
                      f"second call {doc['gradient_interior_second_s']:.2f} / {doc['gradient_total_second_s']:.2f} s, "
                      f"x{doc['gradient_ratio_second']:.2f})  per-pixel Jacobian {doc['jacobian_interior_s']:.2f} / "
                      f"{doc['jacobian_total_s']:.2f} s (x{doc['jacobian_ratio']:.2f})", flush=True)
    worst = max(r["gradient_ratio_second"] for r in rows)
    doc = {"goal_ratio": GOAL_RATIO, "machine": {"cpus": os.cpu_count(), "platform": platform.platform()},
           "runs": rows, "worst_warm_ratio": worst}
    write_json(args.out, doc)
    print(f"worst warm gradient ratio total / interior: x{worst:.2f} (goal <= x{GOAL_RATIO:g}); wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
