"""Verbs over many designs: `tolerance` (Monte Carlo) and `sweep` (a grid), on Dask."""

from __future__ import annotations

import sys

from .. import budget
from ..fileio import check_writable as _writable
from .common import (
    DEFAULT_CONTENT,
    InputError,
    _add_dask,
    _add_set,
    _dump,
    _int_pair,
    _load_design,
    _scheduler_args,
    content_path,
)


def _log(args):
    """Estimates and notes on standard error; nothing under --json."""
    return (lambda msg: None) if args.json else (lambda msg: print(msg, file=sys.stderr, flush=True))


def cmd_tolerance(args) -> int:
    from ..tolerance.monte_carlo import RunMismatch, run_tolerance

    design = _load_design(args)
    if design.ini is None:
        raise InputError(f"{args.design}: ini = missing: lfsim tolerance needs an [ini] section")
    for flag, v, lo in (("--trials", args.trials, 1), ("--seed", args.seed, 0), ("--batch", args.batch, 1)):
        if v is not None and v < lo:
            raise InputError(f"{flag} = {v}: must be >= {lo}")
    sched, workers, serial = _scheduler_args(args)
    try:
        doc = run_tolerance(design, args.out, trials=args.trials, seed=args.seed, scheduler=sched, workers=workers,
                            serial=serial, resume=args.resume, batch=args.batch,
                            sensitivity=not args.no_sensitivity, plots=not args.no_plots,
                            progress=not args.json, log=_log(args))
    except RunMismatch as e:
        raise InputError(str(e)) from None
    if args.json:
        print(_dump(doc))
        return 0
    ci = doc["yield_ci95"]
    print(f"{doc['design']}: {doc['trials']} trials in {doc['seconds']:.1f} s ({doc['execution']['mode']}, "
          f"{doc['execution']['workers']} workers); yield {100 * doc['yield']:.1f} % "
          f"(95 % CI {100 * ci[0]:.1f}-{100 * ci[1]:.1f} %)")
    for t, y in doc["yield_by_target"].items():
        print(f"  {t} {doc['targets'][t]:g}: {100 * y:.1f} % of trials")
    measured = [r for r in doc["sensitivity"] if r["margin_used"] is not None or r["margin_used_inf"]]
    if measured:
        print("  sensitivity (margin used at ± limit):")
    for r in measured:
        used = "inf" if r["margin_used_inf"] else f"{r['margin_used']:.3f}"
        print(f"    {r['rank']:2d}. {r['name']:28s} ±{r['limit']:g}  {used:>7s}  ({r['worst_target'] or '-'})")
    if len(measured) < len(doc["sensitivity"]):
        print(f"  sensitivity: {len(doc['sensitivity']) - len(measured)} tolerance(s) without ± limit runs "
              "(--no-sensitivity, or the run failed)")
    print(f"wrote {args.out}/summary.json, trials.jsonl, sensitivity.jsonl, sensitivity.csv"
          + (", " + ", ".join(doc.get("plots", [])) if doc.get("plots") else ""))
    return 0


def cmd_sweep(args) -> int:
    from ..design.overrides import load_with_overrides
    from ..tolerance.sweep import parse_axes, run_sweep

    if args.max_points < 1:
        raise InputError(f"--max-points = {args.max_points}: must be >= 1")
    _writable(args.out, "--out", folder=True)
    axes, fixed = parse_axes(args.set, max_points=args.max_points)
    if not axes:
        raise InputError("--set KEY=START:STOP:COUNT: give at least one axis to sweep")
    design = load_with_overrides(args.design)
    if design.ini is None:
        raise InputError(f"{args.design}: ini = missing: lfsim sweep needs an [ini] section")
    stride = _int_pair(args.stride, "--stride") if args.stride else None
    if args.batch < 1:
        raise InputError(f"--batch = {args.batch}: must be >= 1")
    sched, workers, serial = _scheduler_args(args)
    content = spec = None
    if args.render:
        from ..content import load_content
        from ..render.focal_stack import FocalStackSpec

        content = load_content(content_path(args.content))
        view = content.view
        if args.spp < 1:
            raise InputError(f"--spp = {args.spp}: must be >= 1")
        spec = FocalStackSpec(focus_mm=list(view.focus_mm), cdp_mm=view.cdp_mm,
                              pupil_diameter_mm=view.pupil_diameter_mm, spp=args.spp,
                              resolution=_int_pair(args.resolution, "--resolution"), focus_cues=False)
    doc = run_sweep(design, args.out, axes, fixed, stride=stride, reference=args.reference, render=args.render,
                    render_spec=spec, content=content, scheduler=sched, workers=workers, serial=serial,
                    batch=args.batch, progress=not args.json, log=_log(args))
    if args.json:
        print(_dump(doc))
        return 0
    keys = list(doc["axes"])
    print(f"{doc['design']}: {len(doc['points'])} points in {doc['seconds']:.1f} s ({doc['execution']['mode']})")
    for p in doc["points"]:
        vals = " ".join(f"{k}={p['values'][k]:.6g}{' ' + doc['units'][k] if doc['units'][k] else ''}" for k in keys)
        if p["error"]:
            print(f"  {vals}: {p['error']}")
            continue
        m = p["metrics"]
        fmt = lambda v, f: "-" if v is None else format(v, f)  # noqa: E731
        print(f"  {vals}: GD max {fmt(m['gd_max_deg'], '.4f')} deg, PA max {fmt(m['pa_max'], '.4f')}, "
              f"contrast min {fmt(m['contrast_nyquist_min'], '.3f')}, RMS {fmt(m['rms_spot_mean_arcmin'], '.3f')}'")
    print(f"wrote {args.out}/sweep.json, sweep.csv, sweep.png" + (", points/*/" if args.render else ""))
    return 0


def register(sub) -> None:
    """Add this module's verbs to the `lfsim` sub-command parser."""
    tol = sub.add_parser("tolerance", help="Monte Carlo tolerance analysis of the design's [tolerance] section "
                         "(with compensators), sensitivity table and yield, on Dask")
    tol.add_argument("design")
    tol.add_argument("--out", required=True, help="output directory (summary.json, trials.jsonl, plots)")
    tol.add_argument("--trials", type=int, help="Monte Carlo trials (default: tolerance.trials)")
    tol.add_argument("--seed", type=int, help="random seed (default: tolerance.seed)")
    tol.add_argument("--batch", type=int, help="trials per Dask task (default: tolerance.batch)")
    tol.add_argument("--resume", action="store_true", help="continue the run stored in --out")
    tol.add_argument("--no-sensitivity", action="store_true", help="skip the ± limit runs of each tolerance")
    tol.add_argument("--no-plots", action="store_true")
    _add_dask(tol)
    budget.add_flags(tol)
    _add_set(tol)
    tol.add_argument("--json", action="store_true")
    tol.set_defaults(func=cmd_tolerance)

    sw = sub.add_parser("sweep", help="InI metrics over a grid of design numbers (--set KEY=START:STOP:COUNT), "
                        "optionally with focal stacks, on Dask")
    sw.add_argument("design")
    sw.add_argument("--set", action="append", metavar="KEY=START:STOP:COUNT|KEY=VALUE",
                    help="an axis of the grid (numpy.linspace) or a fixed override (repeatable)")
    sw.add_argument("--out", required=True, help="output directory (sweep.json, sweep.csv, sweep.png)")
    sw.add_argument("--max-points", type=int, default=10_000,
                    help="refuse a grid of more points than this (default 10000; each point is a full analysis)")
    sw.add_argument("--stride", help="lenslet stride SX,SY of the metrics (default from [ini.analysis])")
    sw.add_argument("--reference", choices=("self", "nominal"), default="self",
                    help="GD/PA against each point's own paraxial rays (self) or the unswept design's")
    sw.add_argument("--render", action="store_true", help="render a focal stack of every point")
    sw.add_argument("--content", default=DEFAULT_CONTENT, help=f"content scene of --render ({DEFAULT_CONTENT})")
    sw.add_argument("--spp", type=int, default=16, help="samples per pixel of --render (16)")
    sw.add_argument("--resolution", default="160,84", help="W,H of the --render retinal images (160,84)")
    sw.add_argument("--batch", type=int, default=1, help="points per Dask task (1)")
    _add_dask(sw)
    budget.add_flags(sw)
    sw.add_argument("--json", action="store_true")
    sw.set_defaults(func=cmd_sweep)
