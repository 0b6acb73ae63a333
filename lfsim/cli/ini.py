"""Verbs of the InI-HMD design stage: `ini`, `analyze`, `optimize`."""

from __future__ import annotations

import math
import sys

from ..design import load
from .common import InputError, _add_set, _dump, _float_list, _int_pair, _load_design


def cmd_ini_design(args) -> int:
    from ..ini.model import IniModel

    model = IniModel(_load_design(args))
    states = [model.state(k).as_dict() for k in range(len(model.depths))]
    doc = {"design": model.design.name, "file": args.design, "p_mla": list(model.arr.pitch),
           "g": model.g, "m": model.arr.m, "n": model.arr.n, "states": states}
    if args.json:
        print(_dump(doc))
        return 0
    print(f"{model.design.name}: InI first-order model (Eqs. 1-10 from the design's own maps)")
    print(f"  {model.arr.m} x {model.arr.n} lenslets, pitch {model.arr.pitch[0]:g} mm, display gap {model.g:g} mm")
    units = type(model.state(0)).UNITS

    def num(v: float) -> str:  # 6 significant digits; float rounding about zero (|v| < 1e-9) is 0
        return f"{0.0 if abs(v) < 1e-9 else v:.6g}"

    for st in states:
        print(f"  CDP {st['diopters']:g} D:")
        for k, v in st.items():
            if k == "diopters":
                continue
            if v is None:
                text = "none (no tunable lens)" if k == "tunable_power_diopters" else "undefined"
            elif isinstance(v, (tuple, list)):  # x, y
                text = " x ".join(num(c) for c in v) + f" {units.get(k, '')}"
            else:
                text = f"{num(v)} {units.get(k, '')}"
            print(f"    {k:22s} {text.rstrip()}")
    return 0


def cmd_ini(args) -> int:
    from ..ini.first_order import IniInputError, ini_first_order

    if args.design is not None:
        return cmd_ini_design(args)
    missing = [f"--{k.replace('_', '-')}" for k in ("p_mla", "g", "z_xp", "f_ep", "m", "n")
               if getattr(args, k) is None]
    if args.l is None and args.f_mla is None:
        missing.append("--l or --f-mla")
    if missing:
        raise InputError(f"lfsim ini: give a design file or the inputs {', '.join(missing)}")

    if args.z_ic is not None and args.cdp_diopters is not None:
        ref = ini_first_order(args.p_mla, args.g, args.f_ep, args.z_xp, args.m, args.n,
                              l=args.l, f_mla=args.f_mla, z_ic=args.z_ic)
        if abs(ref.cdp_diopters - args.cdp_diopters) > 1e-9 * max(1.0, args.cdp_diopters):
            raise InputError(f"--cdp-diopters = {args.cdp_diopters!r} disagrees with --z-ic = {args.z_ic!r}, "
                             f"which puts the CDP at {ref.cdp_diopters:.9g} D: give one of them")
        z_ic, cdp = args.z_ic, None
    else:
        z_ic, cdp = args.z_ic, args.cdp_diopters
    try:
        fo = ini_first_order(args.p_mla, args.g, args.f_ep, args.z_xp, args.m, args.n,
                             l=args.l, f_mla=args.f_mla, z_ic=z_ic, cdp_diopters=cdp,
                             d_mla_ep=args.d_mla_ep)
    except IniInputError as e:
        raise InputError(str(e)) from None
    d = fo.as_dict()
    if args.json:
        print(_dump(d))
    else:
        print("InI-HMD first-order model (Eqs. 1-10)")
        for k, v in d.items():
            unit = fo.UNITS.get(k, "")
            print(f"  {k:22s} {'inf' if v is None else (f'{v:.10g}' if isinstance(v, float) else v)} {unit}".rstrip())
    return 0


def cmd_analyze(args) -> int:
    from ..analysis.ini_analysis import analyze

    design = _load_design(args)
    if design.ini is None:
        raise InputError(f"{args.design}: ini = missing: lfsim analyze needs an [ini] section")
    stride = _int_pair(args.stride, "--stride") if args.stride else None
    depths = _float_list(args.depths, "--depths") if args.depths else None
    reference = None
    if args.reference:
        reference = load(args.reference)
        if reference.ini is None:
            raise InputError(f"{args.reference}: ini = missing: a --reference design needs an [ini] section")
    sweep = _focus_sweep(args.through_focus) if args.through_focus else None
    doc = analyze(design, args.out, stride=stride, symmetry=args.symmetry, depths_diopters=depths,
                  progress=not args.json, plots=not args.no_plots,
                  reference=reference, polychromatic=args.polychromatic, through_focus_d=sweep)
    if args.json:
        print(_dump(doc))
        return 0
    s = doc["summary"]
    print(f"{doc['design']}: {s['subsystems_evaluated']} sub-systems x {s['fields_per_subsystem']} fields "
          f"({s['rays_traced']} rays) in {s['wall_s']:.1f} s (trace {s['trace_s']:.1f} s)")
    print(f"  GD (Eq. 11)  max {_num(s['gd_max_deg'], '.4f')} deg, mean {_num(s['gd_mean_deg'], '.4f')} deg "
          f"({s['gd_within_target']} within {s['gd_target_deg']:g} deg"
          + (f"; {s['gd_failed']} chief rays failed)" if s.get("gd_failed") else ")"))
    print(f"  PA (Eq. 12)  max {_num(s['pa_max'], '.4f')}, mean {_num(s['pa_mean'], '.4f')} "
          f"({s['pa_within_target']} sub-systems within {s['pa_target']:g}"
          + (f"; {s['pa_fields_failed']} fields' marginal rays failed)" if s.get("pa_fields_failed") else ")"))
    if s.get("pa_shape_max") is not None:
        print(f"    footprint shape alone (each footprint's own shift removed): max {s['pa_shape_max']:.4f}, "
              f"mean {_num(s.get('pa_shape_mean'), '.4f')}")
    print(f"  contrast at Nyquist {s['nyquist_cpd']:.2f} cpd (the highest state's): "
          f"min {_low(s['contrast_nyquist_min'])}, "
          f"mean {_num(s['contrast_nyquist_mean'], '.3f')}")
    if s.get("lateral_colour_wavelengths_nm"):
        lo, hi = s["lateral_colour_wavelengths_nm"]
        print(f"  lateral colour {lo:.1f}-{hi:.1f} nm: max {_num(s['lateral_colour_max_arcmin'], '.3f')}', "
              f"mean {_num(s['lateral_colour_mean_arcmin'], '.3f')}' (chief rays; every other figure"
              + (" but the polychromatic contrast" if s.get("contrast_poly_wavelengths_nm") else "")
              + f" is at {doc['wavelength_nm']:g} nm)")
    if s.get("contrast_poly_wavelengths_nm"):
        waves = "/".join(f"{v:.1f}" for v in s["contrast_poly_wavelengths_nm"])
        per_depth = " / ".join(_num(b["contrast_nyquist_poly_mean"], ".3f") for b in doc["by_depth"].values())
        print(f"  polychromatic contrast at Nyquist ({waves} nm, equal weights): min "
              f"{_num(s['contrast_nyquist_poly_min'], '.3f')}, mean {_num(s['contrast_nyquist_poly_mean'], '.3f')}"
              f" ({per_depth} at {' / '.join(doc['by_depth'])} D)")
    for D, b in doc["by_depth"].items():
        print(f"  CDP {D} D: contrast min {_low(b['contrast_nyquist_min'])} "
              f"mean {_num(b['contrast_nyquist_mean'], '.3f')}, "
              f"RMS spot mean {_num(b['rms_spot_mean_arcmin'], '.3f')}' max {_num(b['rms_spot_max_arcmin'], '.3f')}', "
              f"GD max {_num(b['gd_max_deg'], '.3f')} deg, PA max {_num(b['pa_max'], '.3f')}"
              + _first_order_line(b.get("first_order")) + _window_line(b.get("viewing_window_real")))
    for D, b in doc["by_depth"].items():
        if b.get("gd_terms"):
            print(f"  GD terms at {D} D: " + _gd_terms_line(b["gd_terms"]))
    for D, b in doc["by_depth"].items():
        if b.get("through_focus"):
            print(f"  through focus at {D} D: " + _through_focus_line(b["through_focus"]))
    if doc.get("package"):
        print("  " + _package_line(doc["package"]))
    print(f"wrote {args.out}/metrics.json" + (", " + ", ".join(doc.get("plots", [])) if doc.get("plots") else ""))
    return 0


def _first_order_line(fo: dict | None) -> str:
    """``, FOV 29.5 x 16.6 deg, pixel 1.91 x 1.83'``: the state's first order (Eqs. 8-10), x and y,
    for the console; where the paraxial CDP is astigmatic (x or y more than 0.005 D from the
    state's depth, which the tunable lens sets for their mean), both."""
    if not fo:
        return ""
    (fx, fy), (px, py) = fo["fov_deg"], fo["pixel_arcmin"]
    line = f", FOV {fx:.1f} x {fy:.1f} deg, pixel {px:.2f} x {py:.2f}'"
    cx, cy, D = fo.get("cdp_diopters_x"), fo.get("cdp_diopters_y"), fo.get("diopters")
    if None not in (cx, cy, D) and max(abs(cx - D), abs(cy - D)) > 0.005:  # an astigmatic CDP
        line += f", paraxial CDP x {cx:.2f} y {cy:.2f} D"
    return line


def _focus_sweep(text: str) -> tuple[float, float]:
    """``--through-focus HALF,STEP``: a half range and a step in diopters, 3 to 401 foci."""
    vals = _float_list(text, "--through-focus")
    if len(vals) != 2 or not (vals[0] > 0 and vals[1] > 0) or not 1 <= vals[0] / vals[1] <= 200:
        raise InputError(f"--through-focus = {text!r}: expected HALF,STEP in diopters, both > 0, "
                         f"with at most 200 steps either side (e.g. 1,0.05)")
    return vals[0], vals[1]


def _through_focus_line(t: dict) -> str:
    fc, ast = t["field_curvature_d"], t["astigmatism_d"]
    nominal = t["contrast_mean"][t["focus_offsets_d"].index(0.0)] if 0.0 in t["focus_offsets_d"] else None
    return (f"best focus - CDP mean {_num(fc and fc['mean'], '+.3f')} D (std {_num(fc and fc['std'], '.3f')}), "
            f"astigmatism x - y mean {_num(ast and ast['mean'], '+.3f')} D (rms {_num(ast and ast['rms'], '.3f')}); "
            f"contrast mean {_num(nominal, '.3f')} at the CDP, {_num(t['contrast_at_best_focus']['mean'], '.3f')} "
            f"with each field at its best focus, {_num(t['contrast_each_axis_at_best_focus']['mean'], '.3f')} "
            f"with each orientation at its own"
            + (f"; {t['peaks_at_sweep_edge']} peaks on the sweep's edge: widen it" if t["peaks_at_sweep_edge"] else ""))


def _gd_terms_line(t: dict, count: int = 3) -> str:
    """``dy·x2 -1.279 (0.57 RMS), dx·xy +0.426 (0.16), … deg at the edge of the 15.1 x 9.0 deg
    grid; residual RMS 0.011 deg``: the largest terms of GD's displacement field
    (``metrics.json`` ``gd_terms``), for the console."""
    parts = []
    for key, rms in list(t["rms_deg"].items())[:count]:
        axis, name = key.split("_")
        parts.append(f"{axis}·{name} {t[axis][name]:+.3f} ({rms:.3f} RMS)")
    hx, hy = t["normalization_deg"]
    return (", ".join(parts) + f" deg at the edge of the {hx:.1f} x {hy:.1f} deg grid; "
            f"residual RMS {t['residual_rms_deg']:.3f} deg")


def _window_line(w: dict | None) -> str:
    """``, EI-centre chief rays meet the axis -4.36 (x) / -7.37 (y) mm from the window (+ toward
    the eye)``: where the real viewing window lies along the line of sight relative to the
    design's, per section, for the console."""
    if not w:
        return ""
    zs = [f"{_num(None if z is None else round(z, 2) + 0.0, '+.2f')} ({a})" for a, z in zip("xy", w["offset_mm"])]
    return f", EI-centre chief rays meet the axis {' / '.join(zs)} mm from the window (+ toward the eye)"


def _package_line(p: dict) -> str:
    """One console line of ``metrics.json`` ``package`` (the figures the package limits name)."""
    parts = [f"package: track {_num(p.get('track_mm'), '.2f')} mm"]
    if p.get("bounding_box_mm"):
        parts.append("box {:.1f} x {:.1f} x {:.1f} mm".format(*p["bounding_box_mm"]))
    if p.get("prism_box_mm"):
        parts.append("prism {:.1f} x {:.1f} x {:.1f} mm".format(*p["prism_box_mm"]))
    parts.append(f"eye relief {_num(p.get('eye_relief_mm'), '.2f')} mm")
    if p.get("max_clear_diameter_mm") is not None:
        parts.append(f"largest clear diameter {p['max_clear_diameter_mm']:.2f} mm")
    if p.get("tunable_footprint_mm") is not None:
        parts.append(f"tunable lens footprint {p['tunable_footprint_mm']:.2f} of "
                     f"{_num(p.get('tunable_clear_aperture_mm'), '.1f')} mm")
    if p.get("min_edge_thickness_mm") is None and p.get("min_center_thickness_mm") is None:
        parts.append("no glass elements")
    else:
        parts.append(f"glass edge >= {_floor3(p.get('min_edge_thickness_mm'))} mm, "
                     f"centre >= {_floor3(p.get('min_center_thickness_mm'))} mm")
    if p.get("rays_failed"):
        parts.append(f"{p['rays_failed']} of {p['rays_traced']} package rays failed")
    return ", ".join(parts)


def _floor3(v) -> str:
    """A least value after ">=", rounded down to 1 µm so that the bound printed holds."""
    return "n/a" if v is None else f"{math.floor(v * 1000.0 + 1e-9) / 1000.0:.3f}"


def _low(v) -> str:
    """A least contrast: three decimals, or two significant digits from 0.00005 to 0.01 (a floor
    of 0.00047 is not 0)."""
    return _num(v, ".3f" if v is None or not 5e-5 <= abs(v) < 0.00995 else ".2g")


def _num(v, fmt: str) -> str:
    """A figure for the terminal; "n/a" where every ray it needs failed (metrics.json: null)."""
    return "n/a" if v is None else format(v, fmt)


def cmd_optimize(args) -> int:
    from pathlib import Path

    from ..optimize.workflow import optimize

    design = _load_design(args)
    if design.optimize is None or not design.optimize.varies_anything:
        raise InputError(f"{args.design}: optimize.variables = missing: mark the variables in an [optimize] section")
    stages = None
    if args.stages:
        from ..design.optimize_section import STAGES

        stages = [s.strip() for s in args.stages.split(",") if s.strip()]
        allowed = design.optimize.stages if design.optimize.schedule is not None else STAGES
        bad = [s for s in stages if s not in allowed]
        if bad or not stages or len(set(stages)) != len(stages):
            what = "stages of its [[optimize.stages]] schedule" if design.optimize.schedule is not None else "stages"
            raise InputError(f"--stages = {args.stages!r}: expected a comma-separated subset of the {what}: "
                             f"{', '.join(allowed)}")
        if design.ini is None and design.optimize.schedule is None and stages != ["full"]:
            raise InputError(f"--stages = {args.stages!r}: {args.design} has no [ini]: a plain lens has only \"full\"")
    if args.iterations is not None and args.iterations < 1:
        raise InputError(f"--iterations = {args.iterations}: must be >= 1")
    stride = None if args.no_analyze else _int_pair(args.analyze_stride, "--analyze-stride")
    # progress: one line per iteration (merit, block shares, damping, step, time, ETA) on
    # standard error, in a log as on a terminal; a bar as well on a terminal
    from .. import progress

    log = (lambda *a, **k: None) if args.json else progress.line
    doc = optimize(design, args.out, stages=stages, iterations=args.iterations, solver=args.solver,
                   resume=args.resume, progress=not args.json and sys.stderr.isatty(), log=log,
                   analyze_stride=stride)
    out = Path(args.out)
    refused = _render_refusal(out / doc["optimized_design"]) if design.ini is not None else None
    if refused:  # written, as optimized, but the renderer will not take it: say so, and how to hold it
        doc["render_refused"] = refused
        print(f"lfsim optimize: warning: {refused} (lfsim focal-stack refuses this design; "
              "[optimize.targets] display_mismatch_max holds the layout to the display)", file=sys.stderr)
    if args.json:
        print(_dump(doc))
        return 0
    for r in doc["stages"]:
        print(f"{r['stage']:15s} {len(r['variables']):3d} variables  merit {r['merit_start']:.6g} -> "
              f"{r['merit_end']:.6g}  ({r['iterations']} iterations, {r['status']}, {r['seconds']:.1f} s)")
    ba = doc.get("before_after", {})
    for k, v in ba.items():
        if isinstance(v.get("before"), float) and isinstance(v.get("after"), float):
            print(f"  {k:24s} {v['before']:10.4f} -> {v['after']:10.4f}")
    if "rms_spot_um" in ba:  # a plain lens: RMS spot per field (primary wavelength)
        s = ba["rms_spot_um"]
        for f, b, a in zip(s["fields"], s["before"], s["after"]):
            shown = [("undefined" if v is None else f"{v:.3f} µm") for v in (b, a)]
            print(f"  RMS spot at field {f:g}: {shown[0]} -> {shown[1]}")
    print(f"wrote {out / doc['optimized_design']}, history.json, " + ", ".join(doc["plots"]))
    return 0


def _render_refusal(path) -> str | None:
    """The renderer's one-line refusal of the written design's EI layout against its display
    (:func:`lfsim.render.display.check_display_size`, every CDP state), or None."""
    from ..design import DesignError
    from ..ini.model import IniModel
    from ..render.display import check_display_size

    model = IniModel(load(path))
    try:
        for k in range(len(model.depths)):
            check_display_size(model, k, model.ei_pitch(k))
    except DesignError as e:
        return str(e)
    return None


def register(sub) -> None:
    """Add this module's verbs to the `lfsim` sub-command parser."""
    ini = sub.add_parser("ini", help="InI-HMD first-order model (Eqs. 1-10) of a design or explicit inputs")
    ini.add_argument("design", nargs="?", help="design file with an [ini] section")
    ini.add_argument("--p-mla", type=float, help="lenslet pitch (mm)")
    ini.add_argument("--g", type=float, help="display to MLA gap (mm)")
    mla = ini.add_mutually_exclusive_group()
    mla.add_argument("--l", type=float, help="MLA to intermediate CDP (mm; inf allowed)")
    mla.add_argument("--f-mla", type=float, help="lenslet focal length (mm): l from 1/g + 1/l = 1/f")
    ini.add_argument("--z-ic", type=float, help="intermediate CDP to eyepiece (mm)")
    ini.add_argument("--d-mla-ep", type=float, help="MLA to eyepiece (mm), instead of --z-ic")
    ini.add_argument("--cdp-diopters", type=float, help="virtual CDP depth (D; 0 = infinity), instead of --z-ic")
    ini.add_argument("--z-xp", type=float, help="eyepiece to viewing window (mm)")
    ini.add_argument("--f-ep", type=float, help="eyepiece focal length (mm)")
    ini.add_argument("--m", type=int, help="lenslets along x")
    ini.add_argument("--n", type=int, help="lenslets along y")
    _add_set(ini)
    ini.add_argument("--json", action="store_true")
    ini.set_defaults(func=cmd_ini)

    an = sub.add_parser("analyze", help="InI metrics (RMS, MTF, contrast, GD, PA, footprints) with plots")
    an.add_argument("design")
    an.add_argument("--out", required=True, help="output directory (metrics.json and PNGs)")
    an.add_argument("--stride", help="evaluate every k-th lenslet: SX,SY (default from [ini.analysis])")
    an.add_argument("--symmetry", choices=("none", "x", "y", "xy"), help="skip mirror-image lenslets")
    an.add_argument("--depths", help="CDP depths to evaluate, diopters, comma separated (default all)")
    an.add_argument("--reference", help="nominal design: GD and PA against its display layout and paraxial rays")
    an.add_argument("--polychromatic", action="store_true",
                    help="also the contrast at Nyquist of the polychromatic MTF (every [system] wavelength, "
                         "equal weights, one image point: lateral colour lowers it); traces each wavelength, "
                         "about twice the run time")
    an.add_argument("--through-focus", metavar="HALF,STEP",
                    help="also sweep the eye's focus about each CDP, HALF diopters either side in steps of "
                         "STEP (e.g. 1.5,0.05), each state's tunable-lens power kept: every field's best focus "
                         "per orientation, the field curvature and astigmatism, the contrast there "
                         "(by_depth.through_focus, through_focus.png); about 2 s per focus at stride 1 on 2 cores")
    an.add_argument("--no-plots", action="store_true")
    _add_set(an)
    an.add_argument("--json", action="store_true")
    an.set_defaults(func=cmd_analyze)

    op = sub.add_parser("optimize", help="optimize a design's [optimize] variables against the light-field merit")
    op.add_argument("design")
    op.add_argument("--out", required=True, help="output directory (optimized design, history, plots, checkpoints)")
    op.add_argument("--stages", help="comma-separated stages (default: the design's [optimize] stages)")
    op.add_argument("--iterations", type=int, help="iterations per stage (default: the design's)")
    op.add_argument("--solver", choices=("lm", "lm-hinge", "adam"), help="default: the design's")
    op.add_argument("--resume", action="store_true", help="continue from the checkpoints in --out")
    op.add_argument("--no-analyze", action="store_true", help="skip the before/after `analyze` runs")
    op.add_argument("--analyze-stride", default="4,2",
                    help="lenslet stride of the before/after analysis (4,2; 1,1 = every sub-system, "
                         "about 3.5 GB on the freeform design)")
    _add_set(op)
    op.add_argument("--json", action="store_true")
    op.set_defaults(func=cmd_optimize)
