"""Tolerance trials per second: serially in one process, and on a local Dask cluster of 1 and 2 workers.

Runs :func:`lfsim.tolerance.monte_carlo.run_tolerance` (the same as
``lfsim tolerance``) on the same trials of a design's ``[tolerance]`` section
four ways — ``serial`` (this process, Dr.Jit on every core), a local cluster
of 1 worker process (Dr.Jit on every core) and of 2 worker processes (one
Dr.Jit thread each), each with the trials of a batch traced together, and
``serial, unfused`` (batch 1: one trial per launch) — checks that all four
give identical records, prints trials per second, the ratio local cluster /
serial, the scaling from 1 to 2 workers and the gain of tracing a batch
together, and writes ``benchmarks/results/tolerance_throughput.json``.

Two rates per run: *wall* counts everything from the call to the last record
(cluster start-up, each worker's imports and kernel compilation), *steady*
is trials / (sum of the trials' own seconds / workers): the rate once every
worker is warm.

    .venv/bin/python benchmarks/tolerance_throughput.py [--design D] [--trials N] [--batch B]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import lfsim  # noqa: E402
from lfsim.fileio import write_json  # noqa: E402
from lfsim.tolerance.monte_carlo import run_tolerance  # noqa: E402


def _records(out: Path) -> dict:
    return {r["id"]: r for r in map(json.loads, (out / "trials.jsonl").read_text().splitlines())}


def measure(design, trials: int, batch: int, **where) -> tuple[dict, dict]:
    out = Path(tempfile.mkdtemp(prefix="lfsim_tol_bench_"))
    try:
        t0 = time.perf_counter()
        doc = run_tolerance(design, out, trials=trials, batch=batch, sensitivity=False, plots=False, **where)
        wall = time.perf_counter() - t0
        recs = _records(out)
    finally:
        shutil.rmtree(out, ignore_errors=True)
    workers = doc["execution"]["workers"]
    busy = sum(r["seconds"] for r in recs.values())
    row = {"mode": doc["execution"]["mode"], "workers": workers, "trials": len(recs), "wall_s": round(wall, 2),
           "trials_per_s_wall": len(recs) / wall, "trial_s_mean": busy / len(recs),
           "trials_per_s_steady": len(recs) / (busy / workers), "yield": doc["yield"]}
    return row, recs


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--design", default=str(ROOT / "scenes" / "ini_freeform_optimized.toml"))
    ap.add_argument("--trials", type=int, default=40)
    ap.add_argument("--batch", type=int, default=5)
    args = ap.parse_args(argv)
    design = lfsim.load(args.design)
    rows, recs = [], []
    for label, where, batch in (("serial", {"serial": True}, args.batch),
                                ("local, 1 worker", {"workers": 1}, args.batch),
                                ("local, 2 workers", {"workers": 2}, args.batch),
                                ("serial, unfused", {"serial": True}, 1)):
        row, rec = measure(design, args.trials, batch, **where)
        row["batch"] = batch
        row["label"] = label
        rows.append(row)
        recs.append(rec)
        print(f"{label:18s} {row['trials']} trials  wall {row['wall_s']:7.1f} s  "
              f"{row['trials_per_s_wall']:.3f} trials/s (wall)  {row['trials_per_s_steady']:.3f} trials/s (steady)  "
              f"{row['trial_s_mean']:.2f} s/trial/worker", flush=True)
    fields = ("offsets", "metrics", "compensators", "pass")
    identical = all(recs[0][k][f] == r[k][f] for r in recs[1:] for k in recs[0] for f in fields)
    s, l1, l2, s1 = rows
    doc = {
        "design": args.design, "trials": args.trials, "batch": args.batch, "runs": rows,
        "identical_records": identical,
        "ratio_local2_over_serial_wall": l2["trials_per_s_wall"] / s["trials_per_s_wall"],
        "ratio_local2_over_serial_steady": l2["trials_per_s_steady"] / s["trials_per_s_steady"],
        "scaling_2_over_1_workers_wall": l2["trials_per_s_wall"] / l1["trials_per_s_wall"],
        "scaling_2_over_1_workers_steady": l2["trials_per_s_steady"] / l1["trials_per_s_steady"],
        "fused_over_unfused_serial_wall": s["trials_per_s_wall"] / s1["trials_per_s_wall"],
        "machine": {"cpus": os.cpu_count(), "python": platform.python_version(), "platform": platform.platform()},
    }
    out = ROOT / "benchmarks" / "results" / "tolerance_throughput.json"
    write_json(out, doc)
    print(f"local cluster (2 workers) / serial: {doc['ratio_local2_over_serial_wall']:.2f} (wall), "
          f"{doc['ratio_local2_over_serial_steady']:.2f} (steady)")
    print(f"2 workers / 1 worker: {doc['scaling_2_over_1_workers_wall']:.2f} (wall), "
          f"{doc['scaling_2_over_1_workers_steady']:.2f} (steady)")
    print(f"batch of {args.batch} traced together / one trial per launch (serial): "
          f"{doc['fused_over_unfused_serial_wall']:.2f} (wall)")
    print(f"identical records in all four runs: {identical}; wrote {out.relative_to(ROOT)}")
    return 0 if identical else 1


if __name__ == "__main__":
    sys.exit(main())
