"""Error against run time of every approximation knob (the accuracy report).

Runs :func:`lfsim.analysis.accuracy_report.report` — the same as
``lfsim report accuracy`` — which regenerates ``docs/accuracy.md`` and
``docs/img/accuracy_*.png``, and writes the measured figures to
``benchmarks/results/accuracy_report.json``.

    .venv/bin/python benchmarks/accuracy_report.py [--quick] [--out DIR]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from lfsim.analysis.accuracy_report import report  # noqa: E402
from lfsim.fileio import write_json  # noqa: E402


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="a small version (fewer settings, rays and pixels)")
    ap.add_argument("--out", default=str(ROOT / "docs"), help="where accuracy.md and img/ go (default docs/)")
    args = ap.parse_args(argv)
    t0 = time.perf_counter()
    doc = report(args.out, quick=args.quick, log=lambda msg: print(f"{time.perf_counter() - t0:7.1f} s  {msg}",
                                                                   flush=True))
    name = "accuracy_report_quick.json" if args.quick else "accuracy_report.json"
    out = ROOT / "benchmarks" / "results" / name
    write_json(out, doc)
    for k, v in zip(doc["knobs"], doc["verdicts"]):
        err = " / ".join("-" if e is None else f"{e:.3g}" for e in v["error_at_default"] or [None])
        secs = ", ".join(f"{s:.3g}" for s in v["seconds_at_default"])
        print(f"{k['stage']:8s} {k['key']:17s} default {v['default']:>14s}  error {err:>9s}  s {secs:>24s}  "
              f"meets target: {v['meets_target']}")
    print(f"wrote {Path(args.out) / 'accuracy.md'} and {out.relative_to(ROOT)} in {doc['total_seconds']:.0f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
