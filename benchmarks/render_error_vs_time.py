"""Render error against run time: samples per pixel and mesh tessellation.

* spp: the analytic display path (eye rays traced back through the design)
  rendered by Mitsuba at 4 … 256 spp, against a 4096-spp render of the same
  path (the converged reference): relative RMSE (RMSE / mean) and seconds.
* tessellation: the mesh path (Mitsuba meshes of the optics at 1/8 … 2 ×
  the default segment counts, lfsim.render.meshes.tessellation) against the
  analytic path with the same eye rays (common random numbers, :mod:`lfsim.render.accuracy`), so only the
  geometric error is left; seconds include building and loading the meshes.

Scene: the Fig. 9 wall's elemental images on each design, CDP 750 mm, ideal
eye focused at 750 mm, 3 mm pupil. Prints tables and writes
``benchmarks/results/render_error_vs_time.json`` and
``docs/img/render_error_vs_time.png``.

    .venv/bin/python benchmarks/render_error_vs_time.py [--quick]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import lfsim  # noqa: E402
from lfsim.content import load_content  # noqa: E402
from lfsim.fileio import save_figure, write_json  # noqa: E402
from lfsim.render.accuracy import error_vs_time  # noqa: E402


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="smaller images and fewer settings")
    args = ap.parse_args(argv)
    res = (64, 37) if args.quick else (128, 74)
    spps = [4, 16, 64] if args.quick else [4, 16, 64, 256]
    ref_spp = 1024 if args.quick else 4096
    dens = [0.25, 0.5, 1.0] if args.quick else [0.125, 0.25, 0.5, 1.0, 2.0]
    pair_spp = 16 if args.quick else 64
    content = load_content(ROOT / "scenes" / "fig9_wall.toml")
    doc = {"resolution": list(res), "reference_spp": ref_spp, "pair_spp": pair_spp, "designs": {}}
    for name in ("ini_ideal", "ini_coaxial", "ini_freeform"):
        design = lfsim.load(ROOT / "scenes" / f"{name}.toml")
        d = error_vs_time(design, content, cdp_mm=750.0, resolution=res, spps=spps, reference_spp=ref_spp,
                          densities=dens, pair_spp=pair_spp)
        doc["designs"][name] = d
        rows_spp, rows_seg = d["spp"], d["tessellation"]
        t_ref, t_an = d["reference_seconds"], d["analytic_pair_seconds"]
        print(f"\n{name}: analytic path, {res[0]}x{res[1]} px, vs {ref_spp} spp ({t_ref:.1f} s)")
        print("  spp    rel. RMSE   seconds")
        for r in rows_spp:
            print(f"  {r['spp']:5d}  {r['rel_rmse']:9.4f}  {r['seconds']:8.2f}")
        print(f"  mesh path vs analytic, same eye rays ({pair_spp} spp; analytic {t_an:.2f} s)")
        print("  density  segments (lens/lenslet/prism)  rel. RMSE   seconds")
        for r in rows_seg:
            segs = f"{r['segments']}/{r['lenslet_segments']}/{r['prism_segments']}"
            print(f"  {r['density']:7.3f}  {segs:>29s}  {r['rel_rmse']:9.5f}  {r['seconds']:8.2f}")
    out = ROOT / "benchmarks" / "results" / "render_error_vs_time.json"
    write_json(out, doc)
    _plot(doc, ROOT / "docs" / "img" / "render_error_vs_time.png")
    print(f"\nwrote {out.relative_to(ROOT)} and docs/img/render_error_vs_time.png")
    return 0


def _plot(doc, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(10, 3.8))
    for name, d in doc["designs"].items():
        axes[0].loglog([r["seconds"] for r in d["spp"]], [r["rel_rmse"] for r in d["spp"]], "o-", label=name)
        for r in d["spp"]:
            axes[0].annotate(f"{r['spp']}", (r["seconds"], r["rel_rmse"]), fontsize=7)
        xs = [r["seconds"] for r in d["tessellation"]]
        ys = [max(r["rel_rmse"], 1e-6) for r in d["tessellation"]]
        axes[1].loglog(xs, ys, "s-", label=name)
        for r, x, y in zip(d["tessellation"], xs, ys):
            axes[1].annotate(f"×{r['density']:g}", (x, y), fontsize=7)
    axes[0].set_title(f"analytic path: spp vs {doc['reference_spp']}-spp reference")
    axes[1].set_title(f"mesh vs analytic, same rays ({doc['pair_spp']} spp); × default tessellation")
    for ax in axes:
        ax.set_xlabel("seconds")
        ax.set_ylabel("RMSE / mean")
        ax.grid(alpha=0.3, which="both")
        ax.legend(fontsize=8)
    fig.tight_layout()
    save_figure(fig, path, dpi=110)
    plt.close(fig)


if __name__ == "__main__":
    sys.exit(main())
