"""How good are the work estimates printed before a long render? Estimate against measurement.

Usage::

    .venv/bin/python benchmarks/work_estimates.py            # every case
    .venv/bin/python benchmarks/work_estimates.py --quick    # the two smallest

Each case is one ``lfsim focal-stack`` of the default design in a fresh
process (warm kernel cache: the estimate covers rendering, not compiling).
For each it records :func:`lfsim.render.focal_stack.estimate` (seconds, peak
bytes) next to the measured ``index.json`` ``total_s`` and the process's peak
resident memory, and the ratios measured / estimated. ``lfsim.budget.RATES``
are the throughputs this figure calibrates: a ratio far from 1 on another
machine says by how much its estimates are off there.

Output: a table on stdout and ``benchmarks/results/work_estimates.json`` (atomic).
"""

from __future__ import annotations

import argparse
import json
import platform
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
CASES = [("256,144", 16, "analytic"), ("512,288", 64, "analytic"), ("256,144", 256, "analytic"),
         ("1024,576", 64, "analytic"), ("256,144", 64, "mesh")]

CHILD = """
import json, resource, sys
from lfsim.cli import main
rc = main(sys.argv[1:])
print(json.dumps({"rc": rc, "maxrss_kb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss}))
"""


def estimate_for(res: str, spp: int, optics: str) -> dict:
    from lfsim import load
    from lfsim.content import load_content
    from lfsim.ini.model import model_at_depth
    from lfsim.render.display import DisplayLayout
    from lfsim.render.focal_stack import FocalStackSpec, estimate

    content = load_content(ROOT / "scenes" / "fig9_wall.toml")
    design = load(ROOT / "scenes" / "ini_ideal.toml")
    view = content.view
    spec = FocalStackSpec(focus_mm=list(view.focus_mm), cdp_mm=view.cdp_mm, spp=spp, optics=optics)
    layout = DisplayLayout.from_model(model_at_depth(design, 1000.0 / view.cdp_mm), 0)
    w, h = (int(v) for v in res.split(","))
    est = estimate(spec, (w, h), layout.width * layout.height)
    return {"seconds": est.seconds, "bytes": est.bytes, "what": est.what}


def run_case(res: str, spp: int, optics: str, tmp: Path) -> dict:
    out = tmp / f"fs_{res.replace(',', 'x')}_{spp}_{optics}"
    argv = ["focal-stack", "--resolution", res, "--spp", str(spp), "--optics", optics, "--out", str(out),
            "--json"]
    subprocess.run([sys.executable, "-c", CHILD, *argv], cwd=ROOT, capture_output=True, text=True)  # warm up
    p = subprocess.run([sys.executable, "-c", CHILD, *argv], cwd=ROOT, capture_output=True, text=True)
    lines = p.stdout.strip().splitlines()
    child = json.loads(lines[-1])
    index = json.loads((out / "index.json").read_text())
    est = estimate_for(res, spp, optics)
    return {"resolution": res, "spp": spp, "optics": optics, "estimate_s": est["seconds"],
            "measured_s": index["total_s"], "time_ratio": index["total_s"] / est["seconds"],
            "estimate_gb": est["bytes"] / 1e9, "peak_rss_gb": child["maxrss_kb"] * 1024 / 1e9,
            "memory_ratio": child["maxrss_kb"] * 1024 / est["bytes"]}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="only the two smallest cases")
    ap.add_argument("--out", default=str(ROOT / "benchmarks" / "results" / "work_estimates.json"))
    a = ap.parse_args(argv)
    from lfsim.fileio import check_writable, write_json

    check_writable(a.out, "--out")
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for res, spp, optics in (CASES[:2] if a.quick else CASES):
            r = run_case(res, spp, optics, Path(tmp))
            rows.append(r)
            print(f"{res:>9s} {spp:4d} spp {optics:8s}: estimate {r['estimate_s']:6.1f} s, measured "
                  f"{r['measured_s']:6.1f} s (x{r['time_ratio']:.2f}); memory estimate {r['estimate_gb']:.2f} GB, "
                  f"peak {r['peak_rss_gb']:.2f} GB (x{r['memory_ratio']:.2f})", flush=True)
    write_json(a.out, {"machine": platform.processor() or platform.machine(), "cases": rows})
    print(f"wrote {a.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
