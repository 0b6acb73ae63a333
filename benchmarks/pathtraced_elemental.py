"""Time and noise of path-traced elemental images (a Mitsuba-scene content), side by side.

For the shipped tabletop (``scenes/tabletop.toml`` on its ``[view]`` design,
the ideal InI-HMD: 2125 × 1125 display pixels) this times, in one process:

* the chief-ray tables alone (lfsim's tracer, every pixel's real chief ray: the
  part every content kind pays);
* the exact quad path on the Fig. 9 wall (one ray per pixel, first-hit
  emission) as the baseline;
* the path-traced tabletop at each ``--spp`` (chief rays), and with
  ``--bundle`` also integrated over the pixels' ray bundles;

and reports per case seconds, the ratio to the quad path, the noise the
render reports (standard error, RMS / mean) and its error against a reference
``--reference-spp`` render (RMS / mean, less the reference's own noise).
The first case of a process includes its kernel compiles; each case runs
twice and the warm (second) time is the figure.

    .venv/bin/python benchmarks/pathtraced_elemental.py [--spp 4,16,64] [--reference-spp 256] [--bundle]

Prints a table; writes ``benchmarks/results/pathtraced_elemental.json``.
"""

from __future__ import annotations

import argparse
import math
import platform
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--spp", default="4,16,64")
    ap.add_argument("--reference-spp", type=int, default=256)
    ap.add_argument("--bundle", action="store_true", help="also time --ei-bundle (a new trace per sample)")
    ap.add_argument("--out", default=str(ROOT / "benchmarks" / "results" / "pathtraced_elemental.json"))
    args = ap.parse_args()
    spps = [int(s) for s in args.spp.split(",")]

    import lfsim
    from lfsim import budget
    from lfsim.content import elemental_images, load_content, shade_display, visual_rays
    from lfsim.fileio import write_json
    from lfsim.ini.model import model_at_depth
    from lfsim.render.display import DisplayLayout

    table = load_content(ROOT / "scenes" / "tabletop.toml")
    wall = load_content(ROOT / "scenes" / "fig9_wall.toml")
    design = lfsim.load(table.view.design)
    model = model_at_depth(design, 1000.0 / table.view.cdp_mm)
    layout = DisplayLayout.from_model(model, 0)
    centres = layout.pixel_centers().reshape(-1, 2)

    def timed(fn):
        out = fn()  # the first call of a case compiles its kernels
        t0 = time.perf_counter()
        out = fn()
        return out, time.perf_counter() - t0

    rows = []
    _, t_rays = timed(lambda: visual_rays(model, layout, centres))
    rows.append({"case": "chief-ray tables (lfsim tracer)", "seconds": t_rays})
    wall_scene = wall.mitsuba_scene()
    _, t_quad = timed(lambda: elemental_images(model, wall_scene, layout, background=wall.background))
    rows.append({"case": "quads, Fig. 9 wall (baseline)", "seconds": t_quad})
    ref = shade_display(model, table, layout, spp=args.reference_spp, seed=101)
    has = ref.image.sum(axis=-1) > 0

    def error(img):
        e2 = np.mean((img - ref.image)[has] ** 2) / ref.image[has].mean() ** 2
        return math.sqrt(max(e2 - ref.noise_rel ** 2, 0.0))

    for bundle in ([False, True] if args.bundle else [False]):
        for spp in spps:
            r, secs = timed(lambda: shade_display(model, table, layout, spp=spp, seed=1, bundle=bundle))
            rows.append({"case": f"tabletop, {'ray bundles' if bundle else 'chief rays'}, {spp} spp",
                         "spp": spp, "bundle": bundle, "seconds": secs, "noise_rel": r.noise_rel,
                         "error_rel": None if bundle else error(r.image)})
    for r in rows:
        r["ratio_to_quads"] = r["seconds"] / t_quad
    print(f"display {layout.width}x{layout.height} px; reference {args.reference_spp} spp "
          f"(noise {100 * ref.noise_rel:.2f} %); Dr.Jit threads {budget.threads()}")
    print(f"{'case':44s} {'seconds':>8s} {'x quads':>8s} {'noise':>8s} {'error':>8s}")
    for r in rows:
        nz = "" if r.get("noise_rel") is None else f"{100 * r['noise_rel']:7.2f}%"
        er = "" if r.get("error_rel") is None else f"{100 * r['error_rel']:7.2f}%"
        print(f"{r['case']:44s} {r['seconds']:8.2f} {r['ratio_to_quads']:8.1f} {nz:>8s} {er:>8s}")
    doc = {"display_px": [layout.width, layout.height], "reference_spp": args.reference_spp,
           "reference_noise_rel": ref.noise_rel, "machine": platform.platform(), "rows": rows,
           "goal": "tabletop at 16 spp in <= 60 s on 2 cores"}
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    write_json(Path(args.out), doc)
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
