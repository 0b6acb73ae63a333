"""Error of a tolerance run's metric sampling against full sampling, on the same built units.

For the nominal design and the first Monte Carlo trials of its ``[tolerance]``
section, builds each unit exactly as ``lfsim tolerance`` does (perturbed,
compensated, setting errors) and measures it twice: with the run's
``[tolerance.sampling]`` and with full sampling (every lenslet, 3 × 3 fields,
8 × 8 pupil nodes, a 32² MTF grid, 2 levels of the worst-contrast search: the
``lfsim analyze --stride 1,1`` defaults). Prints both, their differences and
the times, and writes ``benchmarks/results/tolerance_sampling_error.json``.

    .venv/bin/python benchmarks/tolerance_sampling_error.py [--design D] [--trials N]
"""

from __future__ import annotations

import argparse
import copy
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import lfsim  # noqa: E402
from lfsim.design.design import Design  # noqa: E402
from lfsim.fileio import write_json  # noqa: E402
from lfsim.ini.model import IniModel  # noqa: E402
from lfsim.ini.subsystems import sample  # noqa: E402
from lfsim.tolerance.monte_carlo import spec_of  # noqa: E402
from lfsim.tolerance.perturb import draw  # noqa: E402
from lfsim.tolerance.trial import TrialEvaluator, metrics_of, with_sampling  # noqa: E402

FULL = {"stride": (1, 1), "fields": 3, "pupil": 8, "mtf_grid": 32, "refine": 2}
SHOWN = ("gd_max_deg", "pa_max", "contrast_nyquist_min", "rms_spot_mean_arcmin")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--design", default=str(ROOT / "scenes" / "ini_freeform_optimized.toml"))
    ap.add_argument("--trials", type=int, default=4)
    args = ap.parse_args(argv)
    design = lfsim.load(args.design)
    spec = spec_of(design)
    ev = TrialEvaluator(design.raw, args.design, spec)
    full_ref = IniModel(Design.from_dict(with_sampling(design.raw, FULL), args.design))
    full_subs = sample(full_ref)
    rows = []
    for uid, offsets in [("nominal", {})] + [(f"mc:{i}", draw(spec, spec.seed, i)) for i in range(args.trials)]:
        built, _ = ev.build(offsets)
        t0 = time.perf_counter()
        sampled = metrics_of(built, ev.ref, ev.subs)
        t1 = time.perf_counter()
        full = metrics_of(Design.from_dict(with_sampling(copy.deepcopy(built.raw), FULL), args.design),
                          full_ref, full_subs)
        t2 = time.perf_counter()
        row = {"id": uid, "sampled": sampled, "full": full, "sampled_s": t1 - t0, "full_s": t2 - t1,
               "difference": {k: (None if sampled[k] is None or full[k] is None else sampled[k] - full[k])
                              for k in SHOWN}}
        rows.append(row)
        print(f"{uid:8s} " + "  ".join(f"{k} {sampled[k]:.4f}/{full[k]:.4f}" for k in SHOWN)
              + f"  ({row['sampled_s']:.1f} s / {row['full_s']:.1f} s)", flush=True)
    worst = {k: max(abs(r["difference"][k]) for r in rows if r["difference"][k] is not None) for k in SHOWN}
    trial_rows = [r for r in rows if r["id"] != "nominal"]
    # Shifts of the trials relative to the nominal, sampled vs full: what a tolerance run reports.
    shift_err = {k: max(abs((r["sampled"][k] - rows[0]["sampled"][k]) - (r["full"][k] - rows[0]["full"][k]))
                        for r in trial_rows) for k in SHOWN} if trial_rows else None
    doc = {"design": args.design, "sampling": {k: list(v) if isinstance(v, tuple) else v
                                               for k, v in spec.sampling.items()},
           "full": {k: list(v) if isinstance(v, tuple) else v for k, v in FULL.items()}, "rows": rows,
           "max_abs_difference": worst, "max_abs_error_of_change_from_nominal": shift_err}
    out = ROOT / "benchmarks" / "results" / "tolerance_sampling_error.json"
    write_json(out, doc)
    print("max |sampled - full|: " + ", ".join(f"{k} {v:.4f}" for k, v in worst.items()))
    if shift_err:
        print("max error of the change from nominal: " + ", ".join(f"{k} {v:.4f}" for k, v in shift_err.items()))
    print(f"wrote {out.relative_to(ROOT)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
