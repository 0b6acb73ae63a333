"""How much of an InI design's contrast at Nyquist is lost to focus, and how much a display
that is refocused per lenslet, or tilted and curved, would give back.

From one through-focus sweep (:func:`lfsim.analysis.ini_analysis.through_focus`, the eye's
focus moved about the CDP with the tunable lens held) of every lenslet at one CDP state:

* ``nominal``: the eye at the CDP (the analysis's contrast mean);
* ``per_field`` / ``per_orientation``: each field (each orientation) at its own best focus,
  a bound that no single eye focus reaches;
* ``per_lenslet``: one focus shift per lenslet, the one that maximizes the mean over its
  fields: a lenslet array whose display gap is chosen per lenslet (a stepped display);
* ``focus_surface``: one smooth shift a + b·n + c·m² + d·n² over the lenslet indices (m, n
  about the array's centre; a design symmetric in x has no odd m terms), maximized by
  Nelder–Mead on the sweep's curves (linear interpolation): a tilted, cylindrically curved
  display.

Every figure is the mean over the lenslets × fields of the smaller orientation's contrast.

    python examples/focus_bounds.py scenes/ini_wearable_optimized.toml --depth 1 --out DIR
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
from scipy.optimize import minimize

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from lfsim import load  # noqa: E402
from lfsim.analysis import ini_analysis as A  # noqa: E402
from lfsim.fileio import write_json  # noqa: E402
from lfsim.ini.model import IniModel  # noqa: E402
from lfsim.ini.subsystems import sample  # noqa: E402


def _at(curves: np.ndarray, offsets: np.ndarray, shift: np.ndarray) -> np.ndarray:
    """``curves`` (T, S, F) read at a focus ``shift`` (S,) per sub-system, linearly between the
    sweep's foci (held at its ends)."""
    t = np.clip((shift - offsets[0]) / (offsets[1] - offsets[0]), 0.0, len(offsets) - 1.0)
    i = np.minimum(np.floor(t).astype(int), len(offsets) - 2)
    f = (t - i)[:, None]
    s = np.arange(curves.shape[1])
    return (1 - f) * curves[i, s] + f * curves[i + 1, s]


def bounds(design, diopters: float, half: float = 1.5, step: float = 0.05, stride=(1, 1)) -> dict:
    model = IniModel(design)
    hit = [k for k, v in enumerate(model.depths) if abs(v - diopters) < 1e-9]
    if not hit:
        raise SystemExit(f"{design.path}: {diopters:g} D is not a CDP depth ({model.depths})")
    subs = sample(model, stride=stride, depths=hit[:1])
    t0 = time.perf_counter()
    res = A.evaluate(model, subs, refine=0)
    tf = A.through_focus(res, A.focus_offsets(half, step))
    off = tf["offsets_d"]
    c = np.min(tf["contrast"], axis=-1)  # (T, S, F)
    per_lenslet = c[np.argmax(c.mean(axis=2), axis=0), np.arange(c.shape[1])]
    m = subs.m - (model.arr.m - 1) / 2.0
    n = subs.n - (model.arr.n - 1) / 2.0
    basis = np.stack([np.ones_like(m), n, m * m, n * n], axis=1)

    def loss(p):
        return -float(np.mean(_at(c, off, basis @ p)))

    # start: the least-squares surface through each lenslet's own best focus
    own = off[np.argmax(c.mean(axis=2), axis=0)]
    p0 = np.linalg.lstsq(basis, own, rcond=None)[0]
    best = min((minimize(loss, p, method="Nelder-Mead", options={"xatol": 1e-4, "fatol": 1e-6, "maxiter": 4000})
                for p in (p0, np.zeros(4))), key=lambda r: r.fun)
    return {
        "design": model.design.name, "file": model.file, "depth_diopters": model.depths[hit[0]],
        "lenslets": int(len(subs)), "fields": int(c.shape[2]), "focus_offsets_d": [float(off[0]), float(off[-1]), step],
        "nominal": float(np.mean(c[len(off) // 2])), "nominal_min": float(np.min(c[len(off) // 2])),
        "per_field": float(np.mean(tf["common_best"])), "per_field_min": float(np.min(tf["common_best"])),
        "per_orientation": float(np.mean(np.min(tf["peak"], axis=-1))),
        "per_lenslet": float(np.mean(per_lenslet)), "per_lenslet_min": float(np.min(per_lenslet)),
        "focus_surface": -float(best.fun),
        "focus_surface_d": dict(zip(("a", "b_n", "c_m2", "d_n2"), (float(v) for v in best.x))),
        "seconds": round(time.perf_counter() - t0, 2),
    }


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("design")
    ap.add_argument("--depth", type=float, default=1.0, help="CDP state, diopters (default 1)")
    ap.add_argument("--half", type=float, default=1.5, help="sweep half range, D (default 1.5)")
    ap.add_argument("--step", type=float, default=0.05, help="sweep step, D (default 0.05)")
    ap.add_argument("--stride", default="1,1", help="lenslet stride SX,SY (default every lenslet)")
    ap.add_argument("--out", help="folder for focus_bounds.json")
    args = ap.parse_args(argv)
    try:
        stride = tuple(int(v) for v in args.stride.split(","))
    except ValueError:
        stride = ()
    if len(stride) != 2 or min(stride) < 1:
        ap.error(f"--stride = {args.stride!r}: expected SX,SY, two integers >= 1")
    if not (args.half > 0 and args.step > 0 and 1 <= args.half / args.step <= 200):
        ap.error(f"--half = {args.half:g}, --step = {args.step:g}: expected both > 0, 1 to 200 steps either side")
    design = load(args.design)
    if design.ini is None:
        ap.error(f"{args.design}: ini = missing: the bounds need an InI design")
    depths = design.ini.cdp_diopters  # None: the one depth the geometry makes (bounds() checks it)
    if depths is not None and not any(abs(v - args.depth) < 1e-9 for v in depths):
        ap.error(f"--depth = {args.depth:g}: not a CDP depth of {args.design} ({depths})")
    doc = bounds(design, args.depth, args.half, args.step, stride)
    print(f"{doc['design']} at {doc['depth_diopters']:g} D, {doc['lenslets']} lenslets x {doc['fields']} fields: "
          f"contrast mean {doc['nominal']:.3f} at the CDP; {doc['per_lenslet']:.3f} refocused per lenslet, "
          f"{doc['focus_surface']:.3f} on the best tilted and curved display, {doc['per_field']:.3f} per field, "
          f"{doc['per_orientation']:.3f} per orientation ({doc['seconds']:.0f} s)")
    if args.out:
        Path(args.out).mkdir(parents=True, exist_ok=True)
        write_json(Path(args.out) / "focus_bounds.json", doc)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
