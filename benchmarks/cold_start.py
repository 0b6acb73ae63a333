"""What a user waits for: every verb on the shipped designs, cold and warm.

Usage::

    .venv/bin/python benchmarks/cold_start.py                      # every case
    .venv/bin/python benchmarks/cold_start.py --only ini,analyze   # cases whose name starts so
    .venv/bin/python benchmarks/cold_start.py --out /tmp/cold.json --markdown /tmp/cold.md

Each case is one ``lfsim`` command run twice in a fresh process:

* **cold**: an empty Dr.Jit kernel cache and a new ``HOME`` (no matplotlib
  font cache either): a new user's first run;
* **warm**: the same command again with the cache the cold run left.

For each run it records the wall time (process start to exit), Dr.Jit's
kernel history (``dr.kernel_history()``: kernels launched, kernels compiled,
the LLVM codegen + backend seconds, i.e. the compile share of the wall, and
the IR op count of the largest kernel) and the peak resident memory
(``ru_maxrss``). Verbs run in-process through ``lfsim.cli.main`` inside a
small wrapper (``--child``) that writes these figures as JSON.

Output: a markdown table on stdout (and ``--markdown``) and a JSON file
(default ``benchmarks/results/cold_start.json``), written atomically.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def cases(tmp: Path) -> list[tuple[str, list[str]]]:
    """(name, lfsim arguments) of every case; outputs go under ``tmp``."""
    rays = tmp / "rays.csv"
    rays.write_text("x,y,z,dx,dy,dz\n" + "".join(f"0,{0.5 * i},-5,0,0,1\n" for i in range(9)))
    s = "scenes/"
    return [
        ("trace cooke_triplet", ["trace", s + "cooke_triplet.toml", "--rays", str(rays), "--json"]),
        ("first-order freeform_prism", ["first-order", s + "freeform_prism.toml", "--json"]),
        ("first-order cooke_triplet", ["first-order", s + "cooke_triplet.toml", "--json"]),
        ("params ini_freeform", ["params", s + "ini_freeform.toml", "--json"]),
        ("layout cooke_triplet", ["layout", s + "cooke_triplet.toml", "--out", str(tmp / "layout"), "--json"]),
        ("ini ini_coaxial", ["ini", s + "ini_coaxial.toml", "--json"]),
        ("ini ini_freeform_optimized", ["ini", s + "ini_freeform_optimized.toml", "--json"]),
        ("analyze ini_coaxial 4,2", ["analyze", s + "ini_coaxial.toml", "--stride", "4,2",
                                     "--out", str(tmp / "an_coax"), "--json"]),
        ("analyze ini_freeform_optimized 4,2", ["analyze", s + "ini_freeform_optimized.toml", "--stride", "4,2",
                                                "--out", str(tmp / "an_ff"), "--json"]),
        ("analyze ini_coaxial 1,1", ["analyze", s + "ini_coaxial.toml", "--stride", "1,1", "--no-plots",
                                     "--out", str(tmp / "an_coax11"), "--json"]),
        ("focal-stack (default: ini_ideal, 512x309, 64 spp)", ["focal-stack", "--out", str(tmp / "fs"), "--json"]),
        ("focal-stack (default) --optics mesh", ["focal-stack", "--optics", "mesh", "--resolution", "512,309",
                                                  "--spp", "64", "--out", str(tmp / "fs_mesh"), "--json"]),
        ("focal-stack ini_freeform analytic 512x309x64", ["focal-stack", s + "ini_freeform.toml", "--resolution",
                                                         "512,309", "--spp", "64", "--out", str(tmp / "fs_ff"),
                                                         "--json"]),
        ("focal-stack ini_freeform --optics mesh 512x309x64", ["focal-stack", s + "ini_freeform.toml", "--optics",
                                                              "mesh", "--resolution", "512,309", "--spp", "64",
                                                              "--out", str(tmp / "fs_ff_mesh"), "--json"]),
        ("gradcheck ini_coaxial", ["gradcheck", s + "ini_coaxial.toml", "--param", "mla.pitch_x",
                                   "--resolution", "48,27", "--spp", "4", "--focus-mm", "1000", "--json"]),
        ("optimize ini_freeform 1 iteration", ["optimize", s + "ini_freeform.toml", "--out", str(tmp / "opt"),
                                               "--stages", "coarse", "--iterations", "1", "--no-analyze",
                                               "--json"]),
    ]


def child(args: list[str], out: str) -> int:
    """Run ``lfsim args`` in this process with Dr.Jit's kernel history on; write figures to ``out``."""
    t0 = time.perf_counter()
    import drjit as dr

    dr.set_flag(dr.JitFlag.KernelHistory, True)
    from lfsim import cli

    code = 0
    try:
        code = cli.main(args) or 0
    except SystemExit as e:
        code = e.code if isinstance(e.code, int) else 1
    dr.sync_thread()
    wall = time.perf_counter() - t0
    hist = [k for k in dr.kernel_history() if k["type"] == dr.KernelType.JIT]
    compiled = [k for k in hist if not (k["cache_hit"] or k["cache_disk"])]
    doc = {
        "exit": code, "wall_s": wall,
        "kernels": len(hist), "compiled": len(compiled),
        "compile_s": sum(k["codegen_time"] + k["backend_time"] for k in hist) / 1000.0,
        "execution_s": sum(k["execution_time"] for k in hist) / 1000.0,
        "largest_kernel_ops": max((k["operation_count"] for k in hist), default=0),
        "largest_compiled_ops": max((k["operation_count"] for k in compiled), default=0),
        "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0,
    }
    Path(out).write_text(json.dumps(doc))
    return 0


def run_case(args: list[str], home: Path, timeout: float) -> dict:
    fd, out = tempfile.mkstemp(suffix=".json")
    os.close(fd)
    env = dict(os.environ, HOME=str(home), DRJIT_CACHE_DIR=str(home / ".drjit"), MPLBACKEND="Agg")
    t0 = time.perf_counter()
    try:
        p = subprocess.run([sys.executable, __file__, "--child", out, "--", *args], cwd=ROOT, env=env,
                           capture_output=True, text=True, timeout=timeout)
        doc = json.loads(Path(out).read_text() or "{}")
        if p.returncode or doc.get("exit"):
            doc["error"] = (p.stderr.strip().splitlines() or ["?"])[-1]
    except subprocess.TimeoutExpired:
        doc = {"error": f"timed out after {timeout:g} s"}
    finally:
        os.unlink(out)
    doc["process_s"] = time.perf_counter() - t0
    return doc


def table(rows: list[dict]) -> str:
    head = ("| case | cold s | warm s | cold/warm | compile share cold | kernels (compiled cold) "
            "| largest kernel ops | peak RSS MB |\n|---|---:|---:|---:|---:|---:|---:|---:|\n")
    lines = []
    for r in rows:
        c, w = r["cold"], r["warm"]
        if "error" in c or "error" in w:
            lines.append(f"| {r['name']} | error: {c.get('error') or w.get('error')} | | | | | | |")
            continue
        lines.append(f"| {r['name']} | {c['process_s']:.1f} | {w['process_s']:.1f} | "
                     f"{c['process_s'] / w['process_s']:.2f} | {100 * c['compile_s'] / c['process_s']:.0f}% | "
                     f"{c['kernels']} ({c['compiled']}) | {c['largest_kernel_ops']} | {c['peak_rss_mb']:.0f} |")
    return head + "\n".join(lines) + "\n"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--only", default="", help="comma-separated case-name prefixes")
    ap.add_argument("--out", default=str(ROOT / "benchmarks/results/cold_start.json"))
    ap.add_argument("--markdown", default=None)
    ap.add_argument("--timeout", type=float, default=1800.0, help="seconds per run")
    a = ap.parse_args(argv)
    tmp = Path(tempfile.mkdtemp(prefix="lfsim-cold-"))
    rows = []
    try:
        todo = cases(tmp)
        if a.only:
            pre = [p.strip() for p in a.only.split(",") if p.strip()]
            todo = [c for c in todo if any(c[0].startswith(p) for p in pre)]
        for name, args in todo:
            home = Path(tempfile.mkdtemp(prefix="home-", dir=tmp))
            cold = run_case(args, home, a.timeout)
            warm = run_case(args, home, a.timeout)
            rows.append({"name": name, "args": args, "cold": cold, "warm": warm})
            c, w = cold, warm
            print(f"{name}: cold {c['process_s']:.1f} s ({c.get('compiled', '?')} kernels compiled, "
                  f"{c.get('compile_s', 0):.1f} s compile), warm {w['process_s']:.1f} s"
                  + (f"  ERROR {c.get('error') or w.get('error')}" if 'error' in c or 'error' in w else ""),
                  flush=True)
            shutil.rmtree(home, ignore_errors=True)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    md = table(rows)
    print()
    print(md)
    import drjit as dr

    doc = {"machine": {"cpus": os.cpu_count(), "platform": platform.platform(), "python": platform.python_version(),
                       "drjit": dr.__version__}, "rows": rows}
    out = Path(a.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmpf = out.with_suffix(".tmp")
    tmpf.write_text(json.dumps(doc, indent=1))
    tmpf.replace(out)
    if a.markdown:
        Path(a.markdown).write_text(md)
    return 0


if __name__ == "__main__":
    if len(sys.argv) > 2 and sys.argv[1] == "--child":
        sys.exit(child(sys.argv[4:] if sys.argv[3] == "--" else sys.argv[3:], sys.argv[2]))
    sys.exit(main())
