"""The ``lfsim`` command. Thin: parse arguments, call the packages, print.

Exit status: 0 success, 1 a check failed, 2 bad input (one line on stderr
naming the file, key and value; never a traceback).
"""

from __future__ import annotations

import argparse
import csv
import io
import json
import math
import sys

import numpy as np

from . import __version__
from .backend import BackendError
from .design import DesignError, load
from .fileio import check_writable as _writable
from .fileio import write_text


class InputError(Exception):
    """Bad command-line input (already formatted as one line)."""


def _load_design(args, path=None):
    """The verb's design, with its ``--set KEY=VALUE`` overrides applied (lfsim.design.overrides)."""
    from .design.overrides import load_with_overrides, parse_sets

    return load_with_overrides(path or args.design, parse_sets(getattr(args, "set", None)))


def _add_set(parser) -> None:
    parser.add_argument("--set", action="append", metavar="KEY=VALUE",
                        help="override a design number before the run (repeatable): a parameter name "
                             "such as MLA.curvature, S3.x2y2, TL.power, mla.pitch_x, or a dotted path "
                             "such as surfaces[2].thickness")


def _json_default(o):
    if isinstance(o, (np.integer,)):
        return int(o)
    if isinstance(o, (np.floating,)):
        return float(o)
    raise TypeError(type(o).__name__)


def _dump(obj) -> str:
    return json.dumps(obj, indent=2, default=_json_default, allow_nan=False)


# ------------------------------------------------------------------- trace
RAY_COLUMNS = ("x", "y", "z", "dx", "dy", "dz")


def read_rays_csv(path: str) -> tuple[np.ndarray, np.ndarray]:
    """Rays from a CSV with columns x,y,z,dx,dy,dz (header required)."""
    try:
        with open(path, newline="", encoding="utf-8") as f:
            rows = list(csv.reader(f))
    except OSError as e:
        raise InputError(f"{path}: cannot read rays file ({e.strerror or e})") from None
    rows = [r for r in rows if r and not r[0].lstrip().startswith("#")]
    if not rows:
        raise InputError(f"{path}: empty rays file: expected a header x,y,z,dx,dy,dz and rows")
    header = [h.strip() for h in rows[0]]
    for c in RAY_COLUMNS:
        if c not in header:
            raise InputError(f"{path}: column {c!r} missing: the header must name x,y,z,dx,dy,dz")
    idx = [header.index(c) for c in RAY_COLUMNS]
    data = np.empty((len(rows) - 1, 6))
    for r, row in enumerate(rows[1:], start=2):
        for k, (c, j) in enumerate(zip(RAY_COLUMNS, idx)):
            try:
                v = float(row[j])
            except (IndexError, ValueError):
                val = row[j] if j < len(row) else ""
                raise InputError(f"{path}: line {r} column {c!r} = {val!r}: expected a number") from None
            if not (math.isfinite(v) and abs(v) <= 1e15):  # the design files' bound (lfsim.design.loader.MAX_ABS)
                raise InputError(f"{path}: line {r} column {c!r} = {row[j]!r}: expected a finite number, |x| <= 1e15")
            data[r - 2, k] = v
    if len(data) == 0:
        raise InputError(f"{path}: no rays after the header")
    zero = np.where(np.linalg.norm(data[:, 3:], axis=1) == 0)[0]
    if len(zero):
        raise InputError(f"{path}: line {zero[0] + 2} direction (dx,dy,dz) = (0,0,0): must be nonzero")
    return data[:, :3], data[:, 3:]


def cmd_trace(args) -> int:
    from .optics.tracer import Status

    design = _load_design(args)
    o, d = read_rays_csv(args.rays)
    r = design.trace(o, d, wavelength_nm=args.wavelength_nm, precision=args.precision)
    arrays = bool(design.system.arrays)  # lenslet (m, n) columns only where there is an array
    if args.json:
        rows = []
        for i in range(len(o)):
            row = {"position": r.positions[i].tolist(), "direction": r.directions[i].tolist(),
                   "status": int(r.status[i]), "status_name": Status(int(r.status[i])).name.lower(),
                   "opl": float(r.opl[i])}
            if arrays:
                row["lenslet"] = r.lenslet[i].tolist()
            rows.append(row)
        print(_dump({
            "design": design.path, "wavelength_nm": args.wavelength_nm or design.system.primary_wavelength_nm,
            "precision": args.precision, "rays": rows,
        }))
    else:
        buf = io.StringIO()
        w = csv.writer(buf)
        w.writerow(["x", "y", "z", "dx", "dy", "dz", "status", "opl"] + (["m", "n"] if arrays else []))
        for i in range(len(o)):
            w.writerow([f"{v:.15g}" for v in (*r.positions[i], *r.directions[i])]
                       + [int(r.status[i]), f"{r.opl[i]:.15g}"]
                       + (r.lenslet[i].tolist() if arrays else []))
        if args.out:
            write_text(args.out, buf.getvalue())
        else:
            sys.stdout.write(buf.getvalue())
    return 0


def cmd_first_order(args) -> int:
    design = _load_design(args)
    fo = design.first_order(args.wavelength_nm, method=args.method)
    d = fo.as_dict()
    if args.json:
        print(_dump({"design": design.path, **d}))
    else:
        print(f"{design.name} ({design.path}) at {fo.wavelength_nm:g} nm, {fo.method}")
        for k, v in d.items():
            if k in ("wavelength_nm", "method"):
                continue
            # None: not finite (an afocal system's EFL, an F-number without an entrance pupil)
            text = _fmt(v, ".10g", fo.UNITS.get(k, "")) if v is None or isinstance(v, float) else str(v)
            print(f"  {k:26s} {text}")
    return 0


def cmd_layout(args) -> int:
    from .analysis.layout import layout_report

    design = _load_design(args)
    summary = layout_report(design, args.out)
    if args.json:
        print(_dump(summary))
    else:
        fo = summary["first_order"]
        print(f"{design.name}: EFL {_fmt(fo['efl'], '.6f', 'mm')}, BFL {_fmt(fo['bfl'], '.6f', 'mm')}, "
              f"F/# {_fmt(fo['fno'], '.4f')}")
        for row in summary["spots"]:
            rms = "vignetted" if row["rms_um"] is None else f"RMS spot {row['rms_um']:.3f} µm"
            print(f"  field {row['field']:g}: {rms}")
        print(f"wrote {args.out}/layout.png, spots.png, summary.json")
    return 0


def cmd_params(args) -> int:
    design = _load_design(args)
    lam = design.wavelength(None)
    rows = [{"name": n, "value": v, "unit": u} for n, v, u in design.parameters(lam)]
    if args.json:  # JSON has no NaN/inf: such a value (none is expected) is written as null
        rows = [{**r, "value": r["value"] if math.isfinite(r["value"]) else None} for r in rows]
        print(_dump({"design": design.name, "file": args.design, "wavelength_nm": lam, "params": rows}))
        return 0
    print(f"# {design.name}: design vector, indices at {lam:g} nm")
    for r in rows:
        print(f"{r['name']:28s} {r['value']: .12g} {r['unit']}")
    return 0


def cmd_ini_design(args) -> int:
    from .ini.model import IniModel

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
    for st in states:
        print(f"  CDP {st['diopters']:g} D:")
        for k, v in st.items():
            if k == "diopters":
                continue
            if v is None:
                text = "none (no tunable lens)" if k == "tunable_power_diopters" else "undefined"
            elif isinstance(v, (tuple, list)):  # x, y
                text = " x ".join(f"{c:.6g}" for c in v) + f" {units.get(k, '')}"
            else:
                text = f"{v:.6g} {units.get(k, '')}"
            print(f"    {k:22s} {text.rstrip()}")
    return 0


def cmd_ini(args) -> int:
    from .ini.first_order import IniInputError, ini_first_order

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
        print("InI-HMD first-order model (Eqs. 1-10; mm, deg, diopters)")
        for k, v in d.items():
            print(f"  {k:22s} {'inf' if v is None else (f'{v:.10g}' if isinstance(v, float) else v)}")
    return 0


def _check_seed(seed: int, end: int = 2 ** 32) -> None:
    """Mitsuba's samplers take 32-bit unsigned seeds."""
    if not 0 <= seed < end:
        raise InputError(f"--seed = {seed}: must be an integer in [0, {end})")


def _fmt(v, spec: str, unit: str = "") -> str:
    """A number with its unit, or "undefined" for a quantity that is not finite (None)."""
    return "undefined" if v is None else f"{format(v, spec)} {unit}".rstrip()


def _int_pair(text, flag):
    try:
        a, b = (int(v) for v in text.split(","))
    except ValueError:
        raise InputError(f"{flag} = {text!r}: expected two integers A,B") from None
    if a < 1 or b < 1:
        raise InputError(f"{flag} = {text!r}: both values must be >= 1")
    return a, b


def _float_list(text, flag):
    try:
        vals = [float(v) for v in text.split(",")]
    except ValueError:
        raise InputError(f"{flag} = {text!r}: expected numbers separated by commas") from None
    if not all(math.isfinite(v) for v in vals):
        raise InputError(f"{flag} = {text!r}: expected finite numbers")
    return vals


def cmd_analyze(args) -> int:
    from .analysis.ini_analysis import analyze

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
    doc = analyze(design, args.out, stride=stride, symmetry=args.symmetry, depths_diopters=depths,
                  progress=not args.json, plots=not args.no_plots,
                  reference=reference)
    if args.json:
        print(_dump(doc))
        return 0
    s = doc["summary"]
    print(f"{doc['design']}: {s['subsystems_evaluated']} sub-systems x {s['fields_per_subsystem']} fields "
          f"({s['rays_traced']} rays) in {s['wall_s']:.1f} s (trace {s['trace_s']:.1f} s)")
    print(f"  GD (Eq. 11)  max {s['gd_max_deg']:.4f} deg, mean {s['gd_mean_deg']:.4f} deg "
          f"({s['gd_within_target']} within {s['gd_target_deg']:g} deg)")
    print(f"  PA (Eq. 12)  max {s['pa_max']:.4f}, mean {s['pa_mean']:.4f} "
          f"({s['pa_within_target']} sub-systems within {s['pa_target']:g})")
    print(f"  contrast at Nyquist {s['nyquist_cpd']:.2f} cpd: min {s['contrast_nyquist_min']:.3f}, "
          f"mean {s['contrast_nyquist_mean']:.3f}")
    for D, b in doc["by_depth"].items():
        print(f"  CDP {D} D: contrast min {b['contrast_nyquist_min']:.3f} mean {b['contrast_nyquist_mean']:.3f}, "
              f"RMS spot mean {b['rms_spot_mean_arcmin']:.3f}' max {b['rms_spot_max_arcmin']:.3f}', "
              f"GD max {b['gd_max_deg']:.3f} deg, PA max {b['pa_max']:.3f}")
    print(f"wrote {args.out}/metrics.json" + (", " + ", ".join(doc.get("plots", [])) if doc.get("plots") else ""))
    return 0


def cmd_optimize(args) -> int:
    from pathlib import Path

    from .optimize.workflow import optimize

    design = _load_design(args)
    if design.ini is None:
        raise InputError(f"{args.design}: ini = missing: lfsim optimize needs an [ini] section")
    if design.optimize is None or not design.optimize.variables:
        raise InputError(f"{args.design}: optimize.variables = missing: mark the variables in an [optimize] section")
    stages = None
    if args.stages:
        from .design.optimize_section import STAGES

        stages = [s.strip() for s in args.stages.split(",") if s.strip()]
        bad = [s for s in stages if s not in STAGES]
        if bad or not stages:
            raise InputError(f"--stages = {args.stages!r}: expected a comma-separated subset of {', '.join(STAGES)}")
    if args.iterations is not None and args.iterations < 1:
        raise InputError(f"--iterations = {args.iterations}: must be >= 1")
    stride = None if args.no_analyze else _int_pair(args.analyze_stride, "--analyze-stride")
    quiet = args.json  # progress: a bar on a terminal, periodic lines in a log
    log = (lambda *a, **k: None) if args.json else (lambda msg: print(msg, file=sys.stderr))
    doc = optimize(design, args.out, stages=stages, iterations=args.iterations, solver=args.solver,
                   resume=args.resume, progress=not quiet, log=log, analyze_stride=stride)
    out = Path(args.out)
    if args.json:
        print(_dump(doc))
        return 0
    for r in doc["stages"]:
        print(f"{r['stage']:15s} {len(r['variables']):3d} variables  merit {r['merit_start']:.6g} -> "
              f"{r['merit_end']:.6g}  ({r['iterations']} iterations, {r['status']}, {r['seconds']:.1f} s)")
    for k, v in doc.get("before_after", {}).items():
        if v["before"] is not None and v["after"] is not None:
            print(f"  {k:24s} {v['before']:10.4f} -> {v['after']:10.4f}")
    print(f"wrote {out / doc['optimized_design']}, history.json, " + ", ".join(doc["plots"]))
    return 0


DEFAULT_CONTENT = "scenes/fig9_wall.toml"


def _view_of(args, verb: str):
    """The content, design and eye view of a render verb: ``(content, design_path, design, focus_mm,
    cdp_mm, pupil_mm)``, from the arguments or else the content file's ``[view]``."""
    from .design.content import load_content

    content = load_content(args.content)
    view = content.view
    design_path = args.design or view.design
    if design_path is None:
        raise InputError(f"{args.content}: view.design = missing: give a DESIGN argument")
    design = _load_design(args, design_path)
    if design.ini is None:
        raise InputError(f"{design_path}: ini = missing: {verb} renders an InI design ([ini] section)")
    focus = _float_list(args.focus_mm, "--focus-mm") if args.focus_mm else list(view.focus_mm)
    if any(not f > 0 for f in focus):
        raise InputError(f"--focus-mm = {args.focus_mm!r}: distances must be > 0")
    if args.cdp_mm is not None:
        try:
            cdp = float(args.cdp_mm)
        except ValueError:
            raise InputError(f"--cdp-mm = {args.cdp_mm!r}: expected a distance in mm or inf") from None
        if not cdp > 0 or math.isnan(cdp):
            raise InputError(f"--cdp-mm = {args.cdp_mm!r}: must be > 0 (inf allowed)")
    else:
        cdp = view.cdp_mm
    pupil = args.pupil_mm if args.pupil_mm is not None else view.pupil_diameter_mm
    if not (math.isfinite(pupil) and pupil > 0):
        raise InputError(f"--pupil-mm = {pupil!r}: must be > 0")
    return content, design_path, design, focus, cdp, pupil


def cmd_focal_stack(args) -> int:
    from pathlib import Path

    from .render.focal_stack import FocalStackSpec, focal_stack

    content, design_path, design, focus, cdp, pupil = _view_of(args, "lfsim focal-stack")
    if args.spp < 1:
        raise InputError(f"--spp = {args.spp}: must be >= 1")
    _check_seed(args.seed)
    if not (math.isfinite(args.tessellation) and args.tessellation > 0):
        raise InputError(f"--tessellation = {args.tessellation!r}: must be > 0")
    res = _int_pair(args.resolution, "--resolution") if args.resolution else None
    spec = FocalStackSpec(focus_mm=[float(f) for f in focus], cdp_mm=cdp, pupil_diameter_mm=float(pupil),
                          spp=args.spp, resolution=res, seed=args.seed, eye_model=args.eye,
                          mla_cells=args.mla_cells, optics=args.optics, tessellation=args.tessellation)
    quiet = args.json  # progress: a bar on a terminal, periodic lines in a log
    log = (lambda *a, **k: None) if args.json else (lambda msg: print(msg, file=sys.stderr))
    doc, _ = focal_stack(design, content, args.out, spec, progress=not quiet, log=log)
    if args.json:
        print(_dump(doc))
        return 0
    print(f"{Path(design_path).name} + {Path(args.content).name}: CDP {cdp:g} mm "
          f"(tunable lens {doc['tunable_power_diopters']}), {pupil:g} mm pupil, {spec.spp} spp, "
          f"{doc['resolution'][0]}x{doc['resolution'][1]} px, {doc['total_s']:.1f} s -> {args.out}")
    for im in doc["images"]:
        ssim = (f"SSIM {im['ssim_vs_natural']:.3f}, PSNR {im['psnr_vs_natural']:.1f} dB"
                if im["kind"] == "display" else "")
        print(f"  {im['kind']:8s} focus {im['focus_mm']:7.1f} mm  {im['render_s']:6.1f} s  {ssim}")
    for r in doc["focus_cues"]["sharpest"]:
        print(f"  sharpest band ({r['kind']}, focus {r['focus_diopters']:.2f} D): {r['sharpest_diopters']:.2f} D "
              f"(offset {r['offset_diopters']:+.2f} D)")
    return 0


def cmd_gradcheck(args) -> int:
    from .render.diff_render import ViewSpec
    from .render.gradcheck import run, table

    content, design_path, design, focus, cdp, pupil = _view_of(args, "lfsim gradcheck")
    names = [n.strip() for n in ",".join(args.param).split(",") if n.strip()]
    if not names:
        raise InputError("--param: give at least one parameter name")
    known = set(design.parameter_names())
    unknown = [n for n in names if n not in known]
    if unknown:
        raise InputError(f"--param {','.join(unknown)}: not a parameter of {design_path} "
                         "(lfsim params DESIGN lists them)")
    res = _int_pair(args.resolution, "--resolution")
    _check_seed(args.seed)
    for flag, v in (("--spp", args.spp), ("--rel-step", args.rel_step), ("--edge-rel-step", args.edge_rel_step),
                    ("--tessellation", args.tessellation),
                    ("--fd-points", args.fd_points)):
        if v is None and flag in ("--rel-step", "--edge-rel-step", "--fd-points"):
            continue
        if not (v > 0 and math.isfinite(v) or (flag == "--cdp-mm" and v == math.inf)):
            raise InputError(f"{flag} = {v!r}: must be > 0")
    if args.motion_px is not None and not (args.motion_px >= 0 and math.isfinite(args.motion_px)):
        raise InputError(f"--motion-px = {args.motion_px!r}: must be >= 0")
    if args.display_blur is not None and not (args.display_blur >= 0 and math.isfinite(args.display_blur)):
        raise InputError(f"--display-blur = {args.display_blur!r}: must be >= 0")
    sweep = tuple(_float_list(args.sweep, "--sweep")) if args.sweep else ()
    view_spec = ViewSpec(focus_mm=[float(f) for f in focus], cdp_mm=cdp, pupil_diameter_mm=float(pupil),
                         resolution=res, spp=args.spp, seed=args.seed, cells=args.mla_cells)
    log = None if args.json else (lambda msg: print(msg, file=sys.stderr))
    doc = run(design, content, names, view_spec, rel_step=args.rel_step, edge_rel_step=args.edge_rel_step,
              sweep=sweep, log=log, optics=args.optics, tessellation=args.tessellation, fresnel=args.fresnel,
              display_blur=args.display_blur, fd_points=args.fd_points, motion_px=args.motion_px)
    bad = [p["name"] for p in doc["params"]
           if (not p["boundary"] and p["rel_err"] > args.tolerance)
           or p["forward_reverse_rel"] > doc["forward_reverse_tol"]]
    doc["tolerance"], doc["failed"] = args.tolerance, bad
    if args.json:
        print(_dump(doc))
    else:
        print(f"{design_path} + {args.content}: {doc['path']} path, {res[0]}x{res[1]} px, {args.spp} spp, focus "
              f"{', '.join(f'{f:g}' for f in focus)} mm, loss {doc['loss']:.6g}")
        print(table(doc))
        s = doc["seconds"]
        print(f"reverse {s['reverse']:.2f} s, forward {s['forward']:.2f} s, finite differences "
              f"{s['finite_differences']:.2f} s; edge term at {doc['edge_rel_step']:g} x the step scale; "
              + (f"FAILED: {', '.join(bad)}" if bad else f"interior parameters within {args.tolerance:g}"))
    return 1 if bad else 0


def _scheduler_args(args):
    """(scheduler address or None, workers, serial) of `tolerance` / `sweep`."""
    sched = args.scheduler
    if sched is not None and not (sched.startswith(("tcp://", "tls://", "inproc://", "ucx://")) or sched == "serial"):
        raise InputError(f"--scheduler = {sched!r}: expected a dask.distributed address tcp://HOST:PORT, or serial")
    if args.workers is not None and args.workers < 1:
        raise InputError(f"--workers = {args.workers}: must be >= 1")
    if sched is not None and sched.startswith("tcp://"):
        # Before any work: a scheduler that does not answer in 5 s is refused now, not after
        # the design is prepared and Dask's own 30 s connection timeout.
        import socket
        from urllib.parse import urlsplit

        try:
            u = urlsplit(sched)
            with socket.create_connection((u.hostname, u.port or 8786), timeout=5.0):
                pass
        except (OSError, ValueError) as e:
            raise InputError(f"--scheduler = {sched!r}: no scheduler answers there "
                             f"({getattr(e, 'strerror', None) or e})") from None
    serial = sched == "serial"
    return (None if serial else sched), args.workers, serial


def cmd_tolerance(args) -> int:
    from .tolerance.monte_carlo import RunMismatch, run_tolerance

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
                            progress=not args.json)
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
    print("  sensitivity (margin used at ± limit):")
    for r in doc["sensitivity"]:
        used = "inf" if r["margin_used_inf"] else ("-" if r["margin_used"] is None else f"{r['margin_used']:.3f}")
        print(f"    {r['rank']:2d}. {r['name']:28s} ±{r['limit']:g}  {used:>7s}  ({r['worst_target']})")
    print(f"wrote {args.out}/summary.json, trials.jsonl, sensitivity.jsonl, sensitivity.csv"
          + (", " + ", ".join(doc.get("plots", [])) if doc.get("plots") else ""))
    return 0


def cmd_sweep(args) -> int:
    from .design.overrides import load_with_overrides
    from .tolerance.sweep import parse_axes, run_sweep

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
        from .design.content import load_content
        from .render.focal_stack import FocalStackSpec

        content = load_content(args.content)
        view = content.view
        if args.spp < 1:
            raise InputError(f"--spp = {args.spp}: must be >= 1")
        spec = FocalStackSpec(focus_mm=list(view.focus_mm), cdp_mm=view.cdp_mm,
                              pupil_diameter_mm=view.pupil_diameter_mm, spp=args.spp,
                              resolution=_int_pair(args.resolution, "--resolution"), focus_cues=False)
    doc = run_sweep(design, args.out, axes, fixed, stride=stride, reference=args.reference, render=args.render,
                    render_spec=spec, content=content, scheduler=sched, workers=workers, serial=serial,
                    batch=args.batch, progress=not args.json)
    if args.json:
        print(_dump(doc))
        return 0
    keys = list(doc["axes"])
    print(f"{doc['design']}: {len(doc['points'])} points in {doc['seconds']:.1f} s ({doc['execution']['mode']})")
    for p in doc["points"]:
        vals = " ".join(f"{k}={p['values'][k]:.6g}" for k in keys)
        if p["error"]:
            print(f"  {vals}: {p['error']}")
            continue
        m = p["metrics"]
        fmt = lambda v, f: "-" if v is None else format(v, f)  # noqa: E731
        print(f"  {vals}: GD max {fmt(m['gd_max_deg'], '.4f')} deg, PA max {fmt(m['pa_max'], '.4f')}, "
              f"contrast min {fmt(m['contrast_nyquist_min'], '.3f')}, RMS {fmt(m['rms_spot_mean_arcmin'], '.3f')}'")
    print(f"wrote {args.out}/sweep.json, sweep.csv, sweep.png" + (", points/*/" if args.render else ""))
    return 0


def _add_dask(parser) -> None:
    parser.add_argument("--scheduler", help="dask.distributed scheduler address tcp://HOST:PORT (default: a local "
                        "cluster started here); 'serial': this process, no Dask")
    parser.add_argument("--workers", type=int, help="worker processes of the local cluster (default: CPU cores)")


def cmd_compare(args) -> int:
    from .analysis.compare import compare_paths, json_safe

    limits = {"min_psnr": args.min_psnr, "min_ssim": args.min_ssim, "max_abs": args.max_abs}
    for flag, v, ok in (("--min-psnr", args.min_psnr, lambda x: not math.isnan(x)),
                        ("--min-ssim", args.min_ssim, lambda x: -1.0 <= x <= 1.0),
                        ("--max-abs", args.max_abs, lambda x: x >= 0.0)):
        if v is not None and not ok(v):
            raise InputError(f"{flag} = {v!r}: " + {"--min-psnr": "a number of dB (inf allowed)",
                                                     "--min-ssim": "an SSIM in [-1, 1]",
                                                     "--max-abs": "a value >= 0"}[flag])
    doc = compare_paths(args.a, args.b, args.out, limits=limits)
    if args.json:
        print(_dump(json_safe(doc)))
        return 1 if doc["failed"] else 0
    for im in doc["images"]:
        psnr = "inf (identical)" if math.isinf(im["psnr"]) else f"{im['psnr']:.2f} dB"
        ssim = "-" if im["ssim"] is None else f"{im['ssim']:.4f}"
        rmse = ", ".join(f"{c} {v:.4g}" for c, v in im["rmse_channels"].items())
        print(f"{im['name']}: PSNR {psnr}, SSIM {ssim}, RMSE {im['rmse']:.4g} ({rmse}), "
              f"max |B-A| {im['max_abs']:.4g}")
    for msg in doc["failed"]:
        print(f"FAILED: {msg}")
    if args.out:
        print(f"wrote {args.out}/compare.json and {len(doc['images'])} heat map(s)")
    return 1 if doc["failed"] else 0


def cmd_regress(args) -> int:
    from .regression import check, update

    if args.update and args.junit:
        raise InputError("--junit: writes the checks of a comparison; not with --update")
    if args.seed is not None:
        _check_seed(args.seed, 2 ** 32 - 1)  # two seeds: seed and seed + 1
    if args.junit:
        _writable(args.junit, "--junit")
    if args.out:
        _writable(args.out, "--out", folder=True)
    given = {"content": args.content, "cdp_mm": args.cdp_mm, "pupil_mm": args.pupil_mm, "spp": args.spp,
             "seed": args.seed, "eye": args.eye, "mla_cells": args.mla_cells, "optics": args.optics,
             "tessellation": args.tessellation, "set": args.set,
             "focus_mm": _float_list(args.focus_mm, "--focus-mm") if args.focus_mm else None,
             "resolution": _int_pair(args.resolution, "--resolution") if args.resolution else None,
             "stride": _int_pair(args.stride, "--stride") if args.stride else None,
             "depths": _float_list(args.depths, "--depths") if args.depths else None,
             "metrics": False if args.no_metrics else None}
    log = (lambda msg: None) if args.json else (lambda msg: print(msg, file=sys.stderr))
    if args.update:
        doc = update(args.design, args.baseline, given, log=log)
        if args.json:
            print(_dump(doc))
            return 0
        o = doc["options"]
        print(f"baseline {args.baseline}: {args.design}, {o['spp']} spp, {o['resolution'][0]}x{o['resolution'][1]} px, "
              f"focus {','.join(f'{f:g}' for f in o['focus_mm'])} mm, seeds {doc['seeds']}, "
              f"{len(doc['metrics'])} metrics, {doc['render_s']:.1f} s")
        for name, n in doc["noise"].items():
            print(f"  {name}: seed-to-seed noise {100 * n['rms_noise']:.1f}% of the mean; a reseeded candidate "
                  f"fails from an RMS change of {100 * n['reseed_change_threshold']:.2f}%")
        return 0
    result = check(args.design, args.baseline, given, out_dir=args.out, junit=args.junit, log=log)
    if args.json:
        print(_dump(result.doc))
        return 1 if result.failed else 0
    print(f"{args.design} against {args.baseline}: {result.summary()}")
    if any(c.status != "ok" for c in result.checks):
        print(result.table(include_ok=False))
    if args.out:
        print(f"wrote {args.out}/report.json, report.txt and {len(result.files.get('heatmaps', []))} heat map(s)"
              + (f"; JUnit XML {args.junit}" if args.junit else ""))
    return 1 if result.failed else 0


class _Parser(argparse.ArgumentParser):
    """argparse with a one-line error (exit status 2) instead of the usage text."""

    def error(self, message):
        self.exit(2, f"lfsim: error: {self.prog}: {' '.join(message.split())}\n")


def build_parser() -> argparse.ArgumentParser:
    p = _Parser(prog="lfsim", description=__doc__.split("\n")[0])
    p.add_argument("--version", action="version", version=f"lfsim {__version__}")
    sub = p.add_subparsers(dest="verb", required=True, metavar="VERB")

    t = sub.add_parser("trace", help="trace rays from a CSV through a design")
    t.add_argument("design")
    t.add_argument("--rays", required=True, help="CSV with columns x,y,z,dx,dy,dz (global frame, mm)")
    t.add_argument("--wavelength-nm", type=float, default=None)
    t.add_argument("--precision", choices=("float64", "float32"), default="float64")
    t.add_argument("--out", help="write the CSV here (atomically) instead of stdout")
    _add_set(t)
    t.add_argument("--json", action="store_true")
    t.set_defaults(func=cmd_trace)

    f = sub.add_parser("first-order", help="first-order (paraxial / parabasal) properties")
    f.add_argument("design")
    f.add_argument("--wavelength-nm", type=float, default=None)
    f.add_argument("--method", choices=("auto", "paraxial", "parabasal"), default="auto")
    _add_set(f)
    f.add_argument("--json", action="store_true")
    f.set_defaults(func=cmd_first_order)

    pa = sub.add_parser("params", help="every design number by name (the names --set and [optimize] take)")
    pa.add_argument("design")
    _add_set(pa)
    pa.add_argument("--json", action="store_true")
    pa.set_defaults(func=cmd_params)

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
    an.add_argument("--no-plots", action="store_true")
    _add_set(an)
    an.add_argument("--json", action="store_true")
    an.set_defaults(func=cmd_analyze)

    lay = sub.add_parser("layout", help="layout and spot-diagram pictures plus a summary")
    lay.add_argument("design")
    lay.add_argument("--out", required=True, help="output directory")
    _add_set(lay)
    lay.add_argument("--json", action="store_true")
    lay.set_defaults(func=cmd_layout)

    op = sub.add_parser("optimize", help="optimize a design's [optimize] variables against the light-field merit")
    op.add_argument("design")
    op.add_argument("--out", required=True, help="output directory (optimized design, history, plots, checkpoints)")
    op.add_argument("--stages", help="comma-separated stages (default: the design's [optimize] stages)")
    op.add_argument("--iterations", type=int, help="iterations per stage (default: the design's)")
    op.add_argument("--solver", choices=("lm", "adam"), help="default: the design's")
    op.add_argument("--resume", action="store_true", help="continue from the checkpoints in --out")
    op.add_argument("--no-analyze", action="store_true", help="skip the before/after `analyze` runs")
    op.add_argument("--analyze-stride", default="1,1", help="lenslet stride of the before/after analysis (1,1)")
    _add_set(op)
    op.add_argument("--json", action="store_true")
    op.set_defaults(func=cmd_optimize)

    fs = sub.add_parser("focal-stack", help="retinal images of the display focused at several depths, "
                        "with the natural view, similarity and focus cues")
    fs.add_argument("design", nargs="?", help="InI design (default: the content file's [view] design)")
    fs.add_argument("--content", default=DEFAULT_CONTENT, help=f"content scene (default {DEFAULT_CONTENT})")
    fs.add_argument("--focus-mm", help="eye focus distances, mm, comma separated (default: the content's)")
    fs.add_argument("--cdp-mm", help="CDP distance the tunable lens is set to, mm (inf allowed)")
    fs.add_argument("--pupil-mm", type=float, help="eye pupil diameter, mm (default: the content's, else 3)")
    fs.add_argument("--eye", choices=("ideal", "arizona"), default="ideal")
    fs.add_argument("--spp", type=int, default=64, help="samples per pixel (default 64)")
    fs.add_argument("--resolution", help="W,H of the retinal images (default 512 wide, the display's aspect)")
    fs.add_argument("--seed", type=int, default=0)
    fs.add_argument("--mla-cells", choices=("per_surface", "fixed"), default="per_surface",
                    help="per_surface: one piece of glass, rays crossing between lenslets inside it go on "
                    "(crosstalk, default); fixed: baffled cells (an ideal aperture array)")
    fs.add_argument("--optics", choices=("analytic", "mesh"), default="analytic",
                    help="analytic: eye rays traced through the design inside the sensor (exact, default); "
                    "mesh: the optics as Mitsuba meshes, path-traced")
    fs.add_argument("--tessellation", type=float, default=1.0,
                    help="mesh density as a multiple of the defaults (--optics mesh; default 1)")
    fs.add_argument("--out", default="renders/focal_stack", help="output directory (default renders/focal_stack)")
    _add_set(fs)
    fs.add_argument("--json", action="store_true")
    fs.set_defaults(func=cmd_focal_stack)

    gcp = sub.add_parser("gradcheck", help="AD derivatives of a retinal render loss against central finite "
                         "differences, with the boundary (visibility-edge) term per parameter")
    gcp.add_argument("design", nargs="?", help="InI design (default: the content file's [view] design)")
    gcp.add_argument("--param", action="append", required=True, metavar="NAME[,NAME...]",
                     help="parameters to check (names from `lfsim params`; object.distance is the display gap)")
    gcp.add_argument("--content", default=DEFAULT_CONTENT, help=f"content scene (default {DEFAULT_CONTENT})")
    gcp.add_argument("--focus-mm", help="eye focus distances, mm, comma separated (default: the content's)")
    gcp.add_argument("--cdp-mm", help="CDP distance the tunable lens is set to, mm (default: the content's)")
    gcp.add_argument("--pupil-mm", type=float, help="eye pupil diameter, mm (default: the content's, else 3)")
    gcp.add_argument("--resolution", default="96,54", help="W,H of the retinal images (default 96,54)")
    gcp.add_argument("--spp", type=int, default=16, help="samples per pixel (default 16)")
    gcp.add_argument("--seed", type=int, default=0)
    gcp.add_argument("--optics", choices=("analytic", "mesh"), default="analytic",
                     help="differentiate the analytic display path (default) or the path-traced optics meshes "
                          "(Dr.Jit-generated vertices, specular-chain AD integrator, float32)")
    gcp.add_argument("--tessellation", type=float, default=0.25,
                     help="mesh path: mesh density x the default segment counts (default 0.25)")
    gcp.add_argument("--fresnel", action="store_true",
                     help="mesh path: interfaces refract with weight 1 - F (default: weight 1)")
    gcp.add_argument("--display-blur", type=float, default=None,
                     help="Gaussian sigma (display pixels) applied to the elemental images (default 0; mesh 2)")
    gcp.add_argument("--rel-step", type=float, default=None,
                     help="central-difference step relative to max(|value|, unit floor) "
                          "(default 1e-7; mesh path 1e-3)")
    gcp.add_argument("--fd-points", type=int, default=None,
                     help="points per side of the main difference, least-squares slope (default 1; mesh 4)")
    gcp.add_argument("--motion-px", type=float, default=None,
                     help="cap the main step so that it moves display hits (99th percentile) by at most this many "
                          "display pixels (default 1e-3; mesh 0.25; 0 = off)")
    gcp.add_argument("--edge-rel-step", type=float, default=None,
                     help="relative step at which the edge (boundary) term is measured (default 1e-3; mesh 1e-2)")
    gcp.add_argument("--sweep", help="further relative steps to report, comma separated (e.g. 1e-5,1e-6)")
    gcp.add_argument("--tolerance", type=float, default=0.02,
                     help="largest relative error of an interior parameter (default 0.02); exit 1 beyond")
    gcp.add_argument("--mla-cells", choices=("per_surface", "fixed"), default="per_surface")
    _add_set(gcp)
    gcp.add_argument("--json", action="store_true")
    gcp.set_defaults(func=cmd_gradcheck)


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
    sw.add_argument("--json", action="store_true")
    sw.set_defaults(func=cmd_sweep)

    cmp = sub.add_parser("compare", help="compare two EXR images or two folders of EXRs (focal stacks): PSNR, "
                         "SSIM, RMSE per channel, largest error, heat maps")
    cmp.add_argument("a", metavar="A", help="reference EXR (or folder of EXRs)")
    cmp.add_argument("b", metavar="B", help="EXR (or folder) compared with A; folders are matched by file name")
    cmp.add_argument("--out", default="renders/compare", help="folder for compare.json and the heat map PNGs "
                     "(default renders/compare)")
    cmp.add_argument("--min-psnr", type=float, help="exit 1 when the PSNR (dB) is below this")
    cmp.add_argument("--min-ssim", type=float, help="exit 1 when the SSIM is below this")
    cmp.add_argument("--max-abs", type=float, help="exit 1 when the largest absolute error is above this")
    cmp.add_argument("--json", action="store_true")
    cmp.set_defaults(func=cmd_compare)

    rg = sub.add_parser("regress", help="re-render a design's focal stack and re-compute its metrics against a "
                        "stored baseline; exit 1 on a regression")
    rg.add_argument("design")
    rg.add_argument("--baseline", required=True, help="baseline folder (created with --update)")
    rg.add_argument("--update", action="store_true", help="(re-)create the baseline from this design")
    rg.add_argument("--junit", help="write the checks as JUnit XML to this file")
    rg.add_argument("--out", default="renders/regress", help="folder for report.json, report.txt, the candidate's "
                    "images and heat maps (default renders/regress)")
    rg.add_argument("--content", help=f"content scene (default: the baseline's, else {DEFAULT_CONTENT})")
    rg.add_argument("--focus-mm", help="eye focus distances, mm, comma separated (default: the baseline's, else "
                    "the content's)")
    rg.add_argument("--cdp-mm", help="CDP distance, mm (inf allowed; default: the baseline's, else the content's)")
    rg.add_argument("--pupil-mm", type=float, help="eye pupil diameter, mm")
    rg.add_argument("--eye", choices=("ideal", "arizona"))
    rg.add_argument("--spp", type=int, help="samples per pixel (default: the baseline's, else 32)")
    rg.add_argument("--resolution", help="W,H of the retinal images (default: the baseline's, else 512 wide)")
    rg.add_argument("--seed", type=int, help="first of the two seeds (default: the baseline's, else 0)")
    rg.add_argument("--mla-cells", choices=("per_surface", "fixed"))
    rg.add_argument("--optics", choices=("analytic", "mesh"))
    rg.add_argument("--tessellation", type=float)
    rg.add_argument("--stride", help="lenslet stride SX,SY of the design metrics (default from [ini.analysis])")
    rg.add_argument("--depths", help="CDP depths (D) of the design metrics, comma separated (default all)")
    rg.add_argument("--no-metrics", action="store_true", help="images only (no design metrics)")
    _add_set(rg)
    rg.add_argument("--json", action="store_true")
    rg.set_defaults(func=cmd_regress)
    return p


def main(argv=None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if getattr(args, "wavelength_nm", None) is not None and not (
        math.isfinite(args.wavelength_nm) and args.wavelength_nm > 0):
        print(f"lfsim: error: --wavelength-nm = {args.wavelength_nm!r}: must be a positive number",
              file=sys.stderr)
        return 2
    try:
        return args.func(args)
    except (DesignError, InputError, BackendError) as e:
        print(f"lfsim: error: {e}", file=sys.stderr)
        return 2
    except ValueError as e:
        print(f"lfsim: error: {' '.join(str(e).split())}", file=sys.stderr)
        return 2
    except OSError as e:  # an output path that cannot be written, a directory given for a file, ...
        where = f"{e.filename}: " if e.filename else ""
        print(f"lfsim: error: {where}{' '.join(str(e.strerror or e).split())}", file=sys.stderr)
        return 2


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
