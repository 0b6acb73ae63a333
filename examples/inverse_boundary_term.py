"""Inverse design on parameters with a large boundary term: the tunable-lens power and the MLA position.

Setup (defaults): the default design (``scenes/ini_ideal.toml``, 17 x 9 ideal
lenslets) showing the Fig. 9 wall (``scenes/fig9_wall.toml``), CDP 750 mm;
retinal images through the ideal eye (3 mm pupil) focused at 600, 1000 and
1400 mm, 96 x 54 px at 16 spp. Unknowns: the tunable lens's power
(``TL.power``) and the MLA's distance to the tunable lens
(``MLA.thickness``). Both move the lenslet edges across the eye's pupil, so
their render derivatives carry a large boundary term
(``lfsim gradcheck``: AD along fixed samples misses 84 % and 55 % of them
against the natural view).

Solver: L-BFGS-B (scipy) on ``L = Σ_focus mean (I − T)²`` with reverse-mode
gradients (stop: the loss changes by less than ``ftol`` = 1e-12 per iteration),
run twice from the same start: with the **total** derivative
(:mod:`lfsim.render.boundary`) and with the **interior** term alone. The
iterates use one set of eye samples (common random numbers).

Two problems (``--problem``):

* ``recover``: the targets are retinal images rendered at the true design
  with *other* samples (``--target-seed``; independent Monte Carlo noise),
  and the start is ``--perturbation`` away from the truth (default +10 %,
  −10 %). The answer is the truth.
* ``natural``: the targets are the natural views of the wall through the same
  eye (what a perfect display would show), which no design matches exactly.
  The answer is the minimum of the expected loss, found without derivatives:
  Nelder–Mead (:func:`lfsim.render.inverse.minimize_loss_reference`) on the
  mean loss of ``reference_seeds`` renderers with independent samples (seeds
  100, 101, …; the solver's own samples are seed 0). The start is
  ``--perturbation`` away from it.

Run: ``.venv/bin/python examples/inverse_boundary_term.py [--problem recover,natural]
[--resolution 96,54] [--spp 16] [--json]``. It prints, per problem and
gradient, the recovered values, their errors, the evaluations and the time.
"""

from __future__ import annotations

import json
import math
import sys
import time
from pathlib import Path

import numpy as np

from lfsim.cli import OneLineParser

ROOT = Path(__file__).resolve().parents[1]
PARAMS = ("TL.power", "MLA.thickness")
PROBLEMS = ("recover", "natural")


def run(problem: str = "natural", design_path=ROOT / "scenes/ini_ideal.toml",
        content_path=ROOT / "scenes/fig9_wall.toml", names=PARAMS, resolution=(96, 54), spp=16,
        focus_mm=(600.0, 1000.0, 1400.0), cdp_mm=750.0, pupil_mm=3.0, perturbation=(0.10, -0.10), seed=0,
        target_seed=1, reference_seeds=4, kinds=("total", "interior"), overrides=None, iterations=40,
        ftol=1e-12, log=None) -> dict:
    """One problem (see the module docstring), solved with total and with interior gradients."""
    from lfsim.content import load_content
    from lfsim.design.overrides import load_with_overrides
    from lfsim.render.diff_render import AnalyticRenderer, ViewSpec
    from lfsim.render.gradcheck import RenderLoss, natural_targets
    from lfsim.render.inverse import minimize_loss, minimize_loss_reference

    if problem not in PROBLEMS:
        raise ValueError(f"problem = {problem!r}: expected one of {', '.join(PROBLEMS)}")
    t_all = time.perf_counter()
    design = load_with_overrides(design_path, overrides or {})
    content = load_content(content_path)
    view = ViewSpec(focus_mm=[float(f) for f in focus_mm], cdp_mm=cdp_mm, pupil_diameter_mm=pupil_mm,
                    resolution=tuple(resolution), spp=int(spp), seed=int(seed))
    r = AnalyticRenderer(design, view, content=content)
    idx = [r.index[n] for n in names]
    if problem == "recover":
        other = AnalyticRenderer(design, ViewSpec(**{**view.__dict__, "seed": int(target_seed)}), display=r.display)
        targets = [other.image_numpy(None, k) for k in range(len(focus_mm))]
    else:
        targets = natural_targets(r, content, spp=4 * int(spp), seed=int(target_seed))
    loss = RenderLoss(r, targets)
    t_setup = time.perf_counter() - t_all
    reference = None
    if problem == "recover":
        answer = r.values0[idx].copy()
    else:
        # The loss's minimum over independent samples (reference_seeds renderers of the
        # same spp): that of the expected loss, which the solver's gradients estimate.
        refs = [RenderLoss(AnalyticRenderer(design, ViewSpec(**{**view.__dict__, "seed": 100 + j}),
                                            display=r.display), targets) for j in range(int(reference_seeds))]
        reference = minimize_loss_reference(refs, names, r.values0[idx])
        answer = reference["x"]
    x0 = answer * (1.0 + np.asarray(perturbation, dtype=np.float64)[:len(names)])
    at_answer = r.values0.copy()
    at_answer[idx] = answer
    out = {"problem": problem, "design": str(design_path), "content": str(content_path),
           "resolution": list(resolution), "spp": int(spp), "focus_mm": list(focus_mm), "cdp_mm": cdp_mm,
           "seed": int(seed), "target_seed": int(target_seed), "names": list(names),
           "answer": [float(v) for v in answer], "start": [float(v) for v in x0],
           "loss_at_answer": loss.value(at_answer), "runs": {}}
    if reference is not None:
        out["reference"] = {k: (v.tolist() if isinstance(v, np.ndarray) else v) for k, v in reference.items()}
    for kind in kinds:
        res = minimize_loss(loss, names, x0, total=kind == "total", max_iterations=iterations, ftol=ftol)
        err = (res["x"] - answer) / np.abs(answer)
        out["runs"][kind] = {"recovered": [float(v) for v in res["x"]], "rel_err": [float(e) for e in err],
                             "max_rel_err": float(np.max(np.abs(err))), "loss": res["loss"],
                             "evaluations": res["evaluations"], "message": res["message"],
                             "seconds": round(res["seconds"], 2)}
    out["seconds"] = {"setup": round(t_setup, 2), "total": round(time.perf_counter() - t_all, 2)}
    if log:
        what = ("truth" if problem == "recover"
                else f"expected-loss minimum (Nelder-Mead over {reference_seeds} independent sample sets)")
        log(f"{problem}: {', '.join(names)} (design units: mm^-1, mm); answer = {what} "
            + ", ".join(f"{v:.6g}" for v in answer) + "; start " + ", ".join(f"{v:.6g}" for v in x0))
        for kind, run_ in out["runs"].items():
            log(f"  with {kind:8s} gradients, recovered: "
                + ", ".join(f"{n} {x:.6g} ({100 * e:+.3f} % from the answer)"
                            for n, x, e in zip(names, run_["recovered"], run_["rel_err"]))
                + f"; loss {run_['loss']:.6g} (answer {out['loss_at_answer']:.6g}); {run_['evaluations']} "
                  f"evaluations, {run_['seconds']:.1f} s")
    return out


def main(argv=None) -> int:
    ap = OneLineParser(description=__doc__.split("\n")[0])
    ap.add_argument("--problem", default=",".join(PROBLEMS), help="recover, natural, or both (comma separated)")
    ap.add_argument("--design", default=str(ROOT / "scenes/ini_ideal.toml"))
    ap.add_argument("--content", default=str(ROOT / "scenes/fig9_wall.toml"))
    ap.add_argument("--resolution", default="96,54")
    ap.add_argument("--spp", type=int, default=16)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--target-seed", type=int, default=1)
    ap.add_argument("--perturbation", default="0.1,-0.1", help="relative error of the start (TL power, MLA position)")
    ap.add_argument("--json", action="store_true")
    a = ap.parse_args(argv)
    problems = [p.strip() for p in a.problem.split(",") if p.strip()]
    bad = [p for p in problems if p not in PROBLEMS]
    if bad or not problems:
        ap.error(f"--problem {a.problem!r}: expected {' or '.join(PROBLEMS)} (comma separated)")
    try:
        res = tuple(int(v) for v in a.resolution.split(","))
        pert = tuple(float(v) for v in a.perturbation.split(","))
    except ValueError as e:
        ap.error(f"--resolution {a.resolution!r} / --perturbation {a.perturbation!r}: {e}")
    docs = [run(p, a.design, a.content, resolution=res, spp=a.spp, perturbation=pert, seed=a.seed,
                target_seed=a.target_seed, log=None if a.json else print) for p in problems]
    if a.json:
        print(json.dumps(docs, indent=2))
    return 0 if all(math.isfinite(d["runs"]["total"]["max_rel_err"]) for d in docs) else 1


if __name__ == "__main__":
    sys.exit(main())
