"""How does pupil aberration grow with the eye relief? A sweep on a design that meets PA.

PA (Eq. 12) of a freeform InI-HMD is mostly the footprints' *shift* on the
viewing window: the EI centres' real chief rays cross the axis in front of the
window (pupil spherical aberration of the relay and eyepiece imaging the
relay's stop onto the window), and the outer lenslets' views land beside the
inner ones. This script measures how that grows when the eye is moved back
from the eyepiece, with and without letting the optimizer answer.

For each eye relief of ``--eye-relief`` (mm):

1. the design's viewing window is moved along its line of sight (its local z)
   so that ``lfsim analyze``'s ``package.eye_relief_mm`` becomes that value;
   the elemental-image layout follows, as it always does, from the paraxial
   model (Eq. 2), and the tunable lens is re-solved for each CDP;
2. the clear apertures named by ``--open`` (default: the prism's four faces
   and the tunable lens) are scaled by ``--open-factor`` (default 1.6), so that
   the beams of a window farther out are not cut off. Without this, the outer
   fields lose a marginal ray, Eq. 12 is undefined for them and they drop out
   of PA: PA then looks flat while the image loses its edge;
3. the moved design is analysed (``start``), optimized by one stage of the
   design's own merit (the targets and weights of its stage ``--like``,
   default ``balance``, with the eye relief held by the package block; solver
   ``lm-hinge``; ``--iterations`` at the design's sampling stride; the tunable
   lens's range widened by 2 D each side, since a CDP state may sit at its limit)
   and analysed again (``reoptimized``), both at
   ``--stride`` and the CDP ``--depth``.

Writes ``OUT/sweep.json`` (every figure of both analyses, each point's files
under ``OUT/er_<mm>/``) and ``OUT/eye_relief_sweep.png`` (PA max and mean,
contrast mean and the real window's offset against the eye relief). A design
scaled as a whole by s, its window at s·E, has the original's PA at E (Eq. 12
is a ratio of lengths): the sweep reads an eye relief in units of the prism's
size. The wearable design's prism is the bench one scaled by 0.6, so its 18.3 mm
eye relief is 30.5 mm on the bench design's scale (its beams and window are not
scaled with it, so this is a comparison of prisms, not of whole designs).

    python examples/eye_relief_sweep.py --out DIR \\
        --eye-relief 17.56,20,22.5,25,28.2,30.5 --iterations 30

(9 to 12 minutes per point on 2 cores; most of it the package block's derivatives.)
"""

from __future__ import annotations

import argparse
import copy
import math
import sys
import time
from pathlib import Path

import numpy as np

from lfsim.cli import OneLineParser
from lfsim.design import Design, load
from lfsim.design.errors import DesignError
from lfsim.design.writer import write_design
from lfsim.fileio import atomic_path, write_json

ROOT = Path(__file__).resolve().parents[1]


def _numbers(text: str, flag: str) -> list[float]:
    try:
        vals = [float(v) for v in text.split(",") if v.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(f"{flag} = {text!r}: expected numbers separated by commas") from None
    if not vals or not all(math.isfinite(v) and v > 0 for v in vals):
        raise argparse.ArgumentTypeError(f"{flag} = {text!r}: expected positive numbers")
    return vals


def _stride(text: str) -> list[int]:
    vals = _numbers(text, "--stride")
    if len(vals) != 2 or any(v != int(v) for v in vals):
        raise argparse.ArgumentTypeError(f"--stride = {text!r}: expected two whole numbers, e.g. 4,2")
    return [int(v) for v in vals]


def _surface_index(raw: dict, name: str, path: str, flag: str = "--open") -> int:
    for i, s in enumerate(raw.get("surfaces", [])):
        if s.get("name") == name:
            return i
    raise ValueError(f"{flag} {name!r}: {path} has no surface of that name")


def _reach(ap: dict, f: float) -> float:
    """Largest distance from the surface's axis of an aperture scaled by ``f`` about its decenter."""
    dx, dy = (abs(float(v)) for v in ap.get("decenter", (0.0, 0.0)))
    if "radius" in ap:
        return f * float(ap["radius"]) + math.hypot(dx, dy)
    hx, hy = (float(v) for v in ap["half_width"])
    return math.hypot(f * hx + dx, f * hy + dy)


def _reach_factor(ap: dict, lim: float) -> float:
    """The scale ``f`` at which :func:`_reach` equals ``lim`` (closed form)."""
    dx, dy = (abs(float(v)) for v in ap.get("decenter", (0.0, 0.0)))
    if "radius" in ap:
        return (lim - math.hypot(dx, dy)) / float(ap["radius"])
    hx, hy = (float(v) for v in ap["half_width"])
    # (f hx + dx)^2 + (f hy + dy)^2 = lim^2, the positive root
    a, b, c = hx * hx + hy * hy, 2.0 * (hx * dx + hy * dy), dx * dx + dy * dy - lim * lim
    return (-b + math.sqrt(b * b - 4.0 * a * c)) / (2.0 * a)


def _open(raw: dict, names: list[str], factor: float, path: str) -> dict[str, float]:
    """Scale the clear apertures of ``names`` by ``factor`` about their decenters.

    A sphere-based surface reaches only |R| from its axis: an aperture is opened at
    most to 98 % of that. Returns the factor each surface got.
    """
    got = {}
    for name in names:
        s = raw["surfaces"][_surface_index(raw, name, path)]
        ap = s.get("aperture")
        if ap is None:
            if "semi_diameter" not in s:
                raise ValueError(f"--open {name!r}: {path}: the surface has no aperture or semi_diameter to open")
            ap = {"radius": float(s["semi_diameter"])}
        f = factor
        radius = s.get("radius")
        if radius is not None and math.isfinite(float(radius)) and s.get("conic", 0.0) >= -1e-12:
            lim = 0.98 * abs(float(radius))
            if _reach(ap, f) > lim:
                f = max(1.0, _reach_factor(ap, lim))
        if "semi_diameter" in s and s.get("aperture") is None:
            s["semi_diameter"] = float(s["semi_diameter"]) * f
        elif "radius" in ap:
            ap["radius"] = float(ap["radius"]) * f
        else:
            ap["half_width"] = [float(v) * f for v in ap["half_width"]]
        got[name] = f
    return got


def _stage(raw: dict, like: str, path: str) -> dict:
    """The design's optimization stage named ``like`` (``--like``)."""
    stages = raw.get("optimize", {}).get("stages", [])
    for st in stages:
        if st.get("name") == like:
            return st
    raise ValueError(f"--like {like!r}: {path} has no optimization stage of that name "
                     f"(it has {', '.join(str(st.get('name')) for st in stages) or 'none'})")


def moved(design, eye_relief_mm: float, open_names: list[str], open_factor: float, like: str,
          iterations: int) -> tuple[dict, dict[str, float]]:
    """The design's table with the window moved to ``eye_relief_mm``, apertures opened, one stage
    added; and the factor each named aperture was opened by."""
    from lfsim.ini.model import IniModel
    from lfsim.ini.package import package

    raw = copy.deepcopy(design.raw)
    vw_name = raw["ini"]["viewing_window"]
    vw = _surface_index(raw, vw_name, design.path, "ini.viewing_window")
    if "global_position" not in raw["surfaces"][vw]:
        raise DesignError(design.path, f"surfaces[{vw}].global_position", None,
                          "the viewing window needs a global position to be moved", surface=vw_name)
    opened = _open(raw, open_names, open_factor, design.path)
    # A CDP state may sit at the tunable lens's range limit (the bench design's 0 D state
    # does): the package block's differences step past it. The range is not what is swept.
    tun = raw["ini"].get("tunable", {})
    if "range_diopters" in tun:
        lo, hi = (float(v) for v in tun["range_diopters"])
        tun["range_diopters"] = [lo - 2.0, hi + 2.0]
    # The eye relief is measured to the nearest ray hit on the last surface, and the hits
    # follow the EI layout, which follows the window: a few fixed-point steps.
    cur = Design.from_dict(raw, design.path)
    for _ in range(6):
        model = IniModel(cur)
        e = package(model, solids=False)["eye_relief_mm"]
        if abs(e - eye_relief_mm) < 0.005:
            break
        R, o = model.tracer.frames_numpy(model.tracer.params(values=model.values0))[vw]
        raw["surfaces"][vw]["global_position"] = [float(v) for v in o + (eye_relief_mm - e) * R[:, 2]]
        cur = Design.from_dict(raw, design.path)

    stages = raw["optimize"].get("stages", [])
    base = _stage(raw, like, design.path)
    stage = {"name": "sweep", "solver": "lm-hinge", "iterations": int(iterations)}
    for key in ("targets", "weights", "variables"):
        if key in base:
            stage[key] = copy.deepcopy(base[key])
    # The stage holds the eye relief where the sweep put it (the package block's soft limit).
    stage.setdefault("targets", {})["eye_relief_min_mm"] = float(eye_relief_mm)
    stage.setdefault("weights", {}).setdefault("package", 40.0)
    raw["optimize"]["stages"] = stages + [stage]
    return raw, opened


def figures(doc: dict, depth: str) -> dict:
    """The figures a point of the sweep is judged by (one CDP state)."""
    s, b, pk = doc["summary"], doc["by_depth"][depth], doc["package"]
    vwr = b.get("viewing_window_real") or {}
    fo = b["first_order"]
    return {
        "eye_relief_mm": pk["eye_relief_mm"],
        "pa_max": b["pa_max"], "pa_mean": b["pa_mean"], "pa_shape_max": b["pa_shape_max"],
        "pa_fields_failed": s["pa_fields_failed"],
        "gd_max_deg": b["gd_max_deg"], "gd_mean_deg": b["gd_mean_deg"],
        "contrast_nyquist_mean": b["contrast_nyquist_mean"], "contrast_nyquist_min": b["contrast_nyquist_min"],
        "rms_spot_mean_arcmin": b["rms_spot_mean_arcmin"],
        "fov_deg": fo["fov_deg"], "d_v_mm": fo["d_v"],
        "window_crossing_mm": vwr.get("offset_mm"),
        "prism_box_mm": pk["prism_box_mm"],
        "prism_footprint_box_mm": pk.get("prism_footprint_box_mm"),
    }


def plot(points: list[dict], path: Path, title: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    e = [p["start"]["eye_relief_mm"] for p in points]
    fig, ax = plt.subplots(1, 3, figsize=(13, 3.8))
    for key, lab in (("start", "window moved"), ("reoptimized", "then one stage")):
        er = [p[key]["eye_relief_mm"] for p in points]
        ax[0].plot(er, [p[key]["pa_max"] for p in points], "o-", label=f"PA max, {lab}")
        ax[0].plot(er, [p[key]["pa_mean"] for p in points], "s--", label=f"PA mean, {lab}")
        for x, p in zip(er, points):  # fields that lost a marginal ray have no PA (Eq. 12)
            if p[key]["pa_fields_failed"]:
                ax[0].annotate(f"{p[key]['pa_fields_failed']} fields\nwithout PA", (x, p[key]["pa_max"]),
                               fontsize=6, textcoords="offset points", xytext=(-40, 6))
        ax[1].plot(er, [p[key]["contrast_nyquist_mean"] for p in points], "o-", label=lab)
        ax[2].plot(er, [-(p[key]["window_crossing_mm"] or [np.nan] * 2)[1] for p in points], "o-",
                   label=f"y, {lab}")
    ax[0].axhline(0.3, color="k", lw=0.8)
    ax[0].axhline(0.145, color="k", lw=0.8, ls=":")
    ax[0].set_ylabel("PA (Eq. 12)")
    ax[1].set_ylabel("contrast at Nyquist, mean")
    ax[2].set_ylabel("EI-centre chief rays cross the axis,\nmm in front of the window")
    for a in ax:
        a.set_xlabel("eye relief (mm)")
        a.grid(alpha=0.3)
        a.legend(fontsize=7)
    ax[0].set_xlim(min(e) - 1, max(e) + 1)
    fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=110, format="png")
    plt.close(fig)


def main(argv=None) -> int:
    ap = OneLineParser(description=__doc__.split("\n")[0])
    ap.add_argument("--design", default=str(ROOT / "scenes" / "ini_freeform_optimized.toml"))
    ap.add_argument("--out", required=True)
    ap.add_argument("--eye-relief", default="17.56,20,22.5,25,28.2,30.5",
                    type=lambda t: _numbers(t, "--eye-relief"), help="eye reliefs to sweep, mm")
    ap.add_argument("--open", default="S1,S2,S3,S4,TL", help="surfaces whose clear apertures are opened")
    ap.add_argument("--open-factor", type=float, default=1.6)
    ap.add_argument("--like", default="balance", help="the design's stage whose targets and weights are used")
    ap.add_argument("--iterations", type=int, default=30)
    ap.add_argument("--stride", default="4,2", type=_stride)
    ap.add_argument("--depth", type=float, default=1.0, help="CDP state analysed (diopters)")
    args = ap.parse_args(argv)
    if not (math.isfinite(args.open_factor) and args.open_factor >= 1.0):
        ap.error(f"--open-factor = {args.open_factor}: expected a number >= 1")
    if args.iterations < 1:
        ap.error(f"--iterations = {args.iterations}: expected at least 1")

    from lfsim.analysis.ini_analysis import analyze
    from lfsim.optimize.workflow import optimize

    try:
        design = load(args.design)
    except (DesignError, OSError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    depth = f"{args.depth:g}"
    names = [n.strip() for n in args.open.split(",") if n.strip()]
    try:  # every name checked before anything is written
        if design.ini is None:
            raise ValueError(f"--design {design.path}: not an InI design (no [ini] section)")
        for name in names:
            _surface_index(design.raw, name, design.path)
        _stage(design.raw, args.like, design.path)
        if args.depth not in [float(v) for v in design.raw["ini"]["cdp_diopters"]]:
            raise ValueError(f"--depth {args.depth:g}: {design.path} has CDP states "
                             f"{', '.join(f'{float(v):g}' for v in design.raw['ini']['cdp_diopters'])} D only")
    except ValueError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    points = []
    for er in args.eye_relief:
        t0 = time.perf_counter()
        try:
            raw, opened = moved(design, er, names, args.open_factor, args.like, args.iterations)
        except ValueError as e:  # DesignError included
            print(f"error: {e}", file=sys.stderr)
            return 2
        d = out / f"er_{er:g}"
        d.mkdir(exist_ok=True)
        start_path = d / f"er_{er:g}.toml"
        write_design(start_path, raw, [f"{design.path} with its window at {er:g} mm eye relief, "
                                       "apertures opened " + ", ".join(f"{k} x{v:.3g}" for k, v in opened.items())
                                       + " (examples/eye_relief_sweep.py)"])
        start = load(start_path)
        a0 = analyze(start, d / "start", stride=args.stride, depths_diopters=[args.depth], plots=False)
        optimize(start, d / "opt", stages=["sweep"], analyze_stride=None, log=lambda *a, **k: None)
        result = load(d / "opt" / f"{start_path.stem}_optimized.toml")
        a1 = analyze(result, d / "reoptimized", stride=args.stride, depths_diopters=[args.depth], plots=False)
        p = {"target_eye_relief_mm": er, "opened": opened, "start": figures(a0, depth),
             "reoptimized": figures(a1, depth), "seconds": time.perf_counter() - t0}
        points.append(p)
        f0, f1 = p["start"], p["reoptimized"]
        print(f"eye relief {f0['eye_relief_mm']:.2f} mm: PA max {f0['pa_max']:.3f} -> {f1['pa_max']:.3f} "
              f"(eye relief {f1['eye_relief_mm']:.2f} mm), mean {f0['pa_mean']:.3f} -> {f1['pa_mean']:.3f}, "
              f"contrast mean {f0['contrast_nyquist_mean']:.3f} -> {f1['contrast_nyquist_mean']:.3f}, "
              f"fields without PA {f0['pa_fields_failed']} -> {f1['pa_fields_failed']}, "
              f"FOV {f1['fov_deg'][0]:.1f} x {f1['fov_deg'][1]:.1f} deg ({p['seconds']:.0f} s)", flush=True)
        doc = {"design": str(design.path), "depth_diopters": args.depth, "stride": args.stride,
               "open": names, "open_factor": args.open_factor, "like": args.like,
               "iterations": args.iterations, "points": points}
        write_json(out / "sweep.json", doc)
    opened = ", ".join(f"{k} x{v:.3g}" for k, v in points[0]["opened"].items())
    plot(points, out / "eye_relief_sweep.png",
         f"{Path(design.path).name}: window moved along the line of sight, apertures opened ({opened}), "
         f"then {args.iterations} lm-hinge iterations ({args.like} merit); "
         f"CDP {args.depth:g} D, stride {args.stride[0]}x{args.stride[1]}")
    print(f"wrote {out / 'sweep.json'} and {out / 'eye_relief_sweep.png'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
