"""The default focal stack's Monte Carlo error against its run time, as a user runs it.

For each spp, ``lfsim focal-stack --spp N --seed S`` (the README's main job:
the default design, content and view, colour, diffraction) is run twice in a
fresh process, with seeds 0 and 1, on a warm kernel cache (one untimed run
first). The error of each image is the relative RMSE of one render against
the converged image, estimated from the two seeds: ``RMS(a − b) / √2 /
mean`` (the estimators are unbiased, so no converged render is needed). The
wall time is the process's, start to exit.

Goal: every image of the stack at 2 % RMSE / mean in ≤ 60 s on 2 cores.

    .venv/bin/python benchmarks/focal_stack_noise.py [--spp 64,128,256] [--quick]

Prints a table; writes ``benchmarks/results/focal_stack_noise.json`` and
``docs/img/focal_stack_noise.png`` (error against wall time per image kind).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

GOAL_RMSE = 0.02
GOAL_SECONDS = 60.0


def run_stack(out: Path, spp: int, seed: int, extra=()) -> tuple[dict, float]:
    cmd = [sys.executable, "-m", "lfsim.cli", "focal-stack", "--spp", str(spp), "--seed", str(seed),
           "--out", str(out), "--json", *extra]
    t0 = time.perf_counter()
    subprocess.run(cmd, check=True, cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    wall = time.perf_counter() - t0
    return json.loads((out / "index.json").read_text()), wall


def image_errors(a: Path, b: Path, doc: dict) -> list[dict]:
    from lfsim.render.focal_stack import read_exr

    rows = []
    for rec in doc["images"] + [dict(doc["reference"], kind="reference", focus_mm=None)]:
        x, _ = read_exr(a / rec["exr"])
        y, _ = read_exr(b / rec["exr"])
        err = float(np.sqrt(np.mean((x.astype(np.float64) - y) ** 2) / 2.0) / np.mean(0.5 * (x + y)))
        rows.append({"kind": rec["kind"], "focus_mm": rec["focus_mm"], "rel_rmse": err})
    return rows


def _tag(row: dict) -> str:
    return row["kind"] if row["focus_mm"] is None else f"{row['kind']} {row['focus_mm']:g} mm"


def main(argv=None) -> int:
    from lfsim.fileio import save_figure, write_json

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--spp", default="64,128,256", help="samples per pixel to measure, comma separated")
    ap.add_argument("--quick", action="store_true", help="a 128-px stack at 16 and 64 spp")
    args = ap.parse_args(argv)
    spps = [16, 64] if args.quick else [int(v) for v in args.spp.split(",")]
    extra = ("--resolution", "128,77") if args.quick else ()
    doc = {"goal": {"rel_rmse": GOAL_RMSE, "seconds": GOAL_SECONDS}, "runs": []}
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        run_stack(tmp / "warm", spps[0], 2, extra)  # compiles the kernels (a user's second run)
        for spp in spps:
            da, wa = run_stack(tmp / "a", spp, 0, extra)
            _, wb = run_stack(tmp / "b", spp, 1, extra)
            rows = image_errors(tmp / "a", tmp / "b", da)
            worst = max(r["rel_rmse"] for r in rows if r["kind"] != "reference")
            doc["runs"].append({"spp": spp, "wall_s": wa, "wall_s_seed1": wb, "total_s": da["total_s"],
                                "resolution": da["resolution"], "images": rows, "worst_rel_rmse": worst,
                                "meets_goal": bool(worst <= GOAL_RMSE and wa <= GOAL_SECONDS)})
            print(f"spp {spp:5d}: wall {wa:6.1f} s ({da['total_s']:.1f} s in focal_stack), worst image "
                  f"{worst:.4f} RMSE/mean  " + "  ".join(f"{_tag(r)}: {r['rel_rmse']:.4f}" for r in rows),
                  flush=True)
    write_json(ROOT / "benchmarks" / "results" / ("focal_stack_noise_quick.json" if args.quick
                                                  else "focal_stack_noise.json"), doc)
    if not args.quick:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        fig, ax = plt.subplots(figsize=(5.6, 3.9))
        for kind in ("display", "natural", "reference"):
            xs = [r["wall_s"] for r in doc["runs"]]
            ys = [max(i["rel_rmse"] for i in r["images"] if i["kind"] == kind) for r in doc["runs"]]
            ax.loglog(xs, ys, "o-", label=f"{kind} (worst image)", ms=4)
            for r, x, y in zip(doc["runs"], xs, ys):
                ax.annotate(f"{r['spp']} spp", (x, y), fontsize=7, xytext=(3, 3), textcoords="offset points")
        ax.axhline(GOAL_RMSE, ls="--", color="0.4", lw=1, label="goal: 2 %")
        ax.axvline(GOAL_SECONDS, ls=":", color="0.4", lw=1, label="goal: 60 s")
        ax.set_xlabel("wall seconds of `lfsim focal-stack` (warm)")
        ax.set_ylabel("RMSE / mean")
        ax.grid(alpha=0.3, which="both")
        ax.legend(fontsize=7)
        ax.set_title("Default focal stack: error against run time", fontsize=10)
        fig.tight_layout()
        save_figure(fig, ROOT / "docs" / "img" / "focal_stack_noise.png", dpi=100)
        plt.close(fig)
    return 0


if __name__ == "__main__":
    sys.exit(main())
