"""Verbs of the retinal-image stage: `focal-stack`, `gradcheck`, `compare`, `regress`."""

from __future__ import annotations

import math
import sys

from .. import budget
from ..fileio import check_writable as _writable
from .common import DEFAULT_CONTENT, InputError, _add_set, _check_seed, _dump, _float_list, _fmt, _int_pair, _view_of


def cmd_focal_stack(args) -> int:
    from pathlib import Path

    from ..render.focal_stack import FocalStackSpec
    from ..vision.focus_cues import RUNNER_UP_NOTE_RATIO, focal_stack

    content, design_path, design, focus, cdp, pupil = _view_of(args, "lfsim focal-stack")
    if args.spp < 1:
        raise InputError(f"--spp = {args.spp}: must be >= 1")
    _check_seed(args.seed)
    if not (math.isfinite(args.tessellation) and args.tessellation > 0):
        raise InputError(f"--tessellation = {args.tessellation!r}: must be > 0")
    res = _int_pair(args.resolution, "--resolution") if args.resolution else None
    if args.wavelength_nm is not None and not (math.isfinite(args.wavelength_nm) and 380 <= args.wavelength_nm <= 780):
        raise InputError(f"--wavelength-nm = {args.wavelength_nm!r}: must lie in 380..780 nm")
    if args.wavelength_samples < 1:
        raise InputError(f"--wavelength-samples = {args.wavelength_samples}: must be >= 1")
    if args.ei_spp < 1:
        raise InputError(f"--ei-spp = {args.ei_spp}: must be >= 1")
    if args.ei_colour and (args.wavelength_nm is not None or args.optics == "mesh"):
        what = f"--wavelength-nm {args.wavelength_nm:g}" if args.wavelength_nm is not None else "--optics mesh"
        raise InputError(f"--ei-colour with {what}: per-channel elemental images need a spectral render "
                         "(the analytic optics, no --wavelength-nm)")
    spec = FocalStackSpec(focus_mm=[float(f) for f in focus], cdp_mm=cdp, pupil_diameter_mm=float(pupil),
                          spp=args.spp, resolution=res, seed=args.seed, eye_model=args.eye,
                          mla_cells=args.mla_cells, optics=args.optics, tessellation=args.tessellation,
                          wavelength_nm=args.wavelength_nm, wavelength_samples=args.wavelength_samples,
                          diffraction=not args.no_diffraction, ei_spp=args.ei_spp, ei_bundle=args.ei_bundle,
                          ei_colour=args.ei_colour)
    quiet = args.json  # progress: a bar on a terminal, periodic lines in a log
    log = (lambda *a, **k: None) if args.json else (lambda msg: print(msg, file=sys.stderr))
    doc, _ = focal_stack(design, content, args.out, spec, progress=not quiet, log=log)
    if args.json:
        print(_dump(doc))
        return 0
    print(f"{Path(design_path).name} + {Path(args.content).name}: CDP {cdp:g} mm "
          f"(tunable lens {_fmt(doc['tunable_power_diopters'], '+.4f', 'D', none='none')}), {pupil:g} mm pupil, "
          f"{spec.spp} spp, "
          f"{doc['resolution'][0]}x{doc['resolution'][1]} px, {doc['total_s']:.1f} s -> {args.out}")
    for im in doc["images"]:
        ssim = (f"SSIM {im['ssim_vs_natural']:.3f}, PSNR {im['psnr_vs_natural']:.1f} dB"
                + _matched(im) if im["kind"] == "display" else "")
        print(f"  {im['kind']:8s} focus {im['focus_mm']:7.1f} mm  {im['render_s']:6.1f} s  {ssim}")
    for r in doc["focus_cues"]["sharpest"]:
        if r["sharpest_diopters"] is None:
            print(f"  sharpest band ({r['kind']}, focus {r['focus_diopters']:.2f} D): none (no band has content)")
            continue
        second = ""
        if (r.get("runner_up_ratio") or 0.0) >= RUNNER_UP_NOTE_RATIO:
            second = (f"; a second peak at {r['runner_up_diopters']:.2f} D reaches "
                      f"{100 * r['runner_up_ratio']:.0f}% of it")
        print(f"  sharpest band ({r['kind']}, focus {r['focus_diopters']:.2f} D): {r['sharpest_diopters']:.2f} D "
              f"(offset {r['offset_diopters']:+.2f} D{second})")
    return 0


def _matched(im: dict) -> str:
    """The console's note of a display view's exposure-matched SSIM (empty without one)."""
    e, s = im.get("exposure_vs_natural"), im.get("ssim_vs_natural_matched")
    return "" if e is None or s is None else f"; SSIM {s:.3f} at matched exposure ({e:.2f}x the light)"


def cmd_export(args) -> int:
    from pathlib import Path

    from ..render.export import export_mitsuba

    if args.zmx is not None or args.seq is not None:
        return _export_lens(args)
    if args.lenslet is not None:
        raise InputError("--lenslet: only with --zmx or --seq")
    if args.mitsuba is None:
        raise InputError("lfsim export: give an output: --mitsuba DIR (a scene plain mitsuba renders), "
                         "--zmx FILE or --seq FILE (the lens as a Zemax or CODE V file)")
    content, design_path, design, focus, cdp, pupil = _view_of(args, "lfsim export")
    if args.focus_mm is None:
        focus = focus[:1]
    if len(focus) != 1:
        raise InputError(f"--focus-mm = {args.focus_mm!r}: the exported eye has one focus distance (give one)")
    for flag, v in (("--spp", args.spp), ("--ei-spp", args.ei_spp)):
        if v < 1:
            raise InputError(f"{flag} = {v}: must be >= 1")
    if not (math.isfinite(args.tessellation) and args.tessellation > 0):
        raise InputError(f"--tessellation = {args.tessellation!r}: must be > 0")
    res = _int_pair(args.resolution, "--resolution") if args.resolution else None
    _writable(args.mitsuba, "--mitsuba")
    log = (lambda *a, **k: None) if args.json else (lambda msg: print(msg, file=sys.stderr))
    doc = export_mitsuba(design, content, args.mitsuba, cdp, focus[0], pupil, resolution=res, spp=args.spp,
                         tessellation=args.tessellation, ei_spp=args.ei_spp, log=log)
    if args.json:
        print(_dump(doc))
        return 0
    print(f"{Path(design_path).name} + {Path(args.content).name}: {doc['shapes']} optics shapes, display, "
          f"thinlens eye (focus {focus[0]:g} mm, {pupil:g} mm pupil) -> {Path(args.mitsuba) / 'scene.xml'}")
    print(f"  render it: cd {args.mitsuba} && mitsuba -m scalar_rgb scene.xml -o retina.exr")
    return 0


def _export_lens(args) -> int:
    from ..design.lensfiles import export_text
    from ..fileio import write_text
    from .common import _load_design

    if args.mitsuba is not None:
        raise InputError("lfsim export: --mitsuba and --zmx/--seq are separate runs; give one kind")
    if args.design is None:
        raise InputError("lfsim export: give the DESIGN to write as a lens file")
    lenslet = None
    if args.lenslet is not None:
        try:
            lenslet = tuple(int(v) for v in args.lenslet.split(","))
        except ValueError:
            lenslet = ()
        if len(lenslet) != 2 or min(lenslet) < 0:
            raise InputError(f"--lenslet = {args.lenslet!r}: expected M,N, two integers >= 0 (0-based lenslet)")
    outs = [(flag, path, fmt) for flag, path, fmt in (("--zmx", args.zmx, "zmx"), ("--seq", args.seq, "seq"))
            if path is not None]
    for flag, path, fmt in outs:
        if not path.lower().endswith(f".{fmt}"):
            raise InputError(f"{flag} = {path!r}: the file must end in .{fmt}")
        _writable(path, flag)
    design = _load_design(args)
    texts = [(flag, path, *export_text(design, fmt, lenslet)) for flag, path, fmt in outs]  # all, then write
    doc = {"design": args.design, "lenslet": list(lenslet) if lenslet else None, "files": []}
    for flag, path, text, notes in texts:
        write_text(path, text)
        doc["files"].append({"format": flag[2:], "path": path, "notes": list(notes)})
        if not args.json:
            for note in notes:
                print(f"lfsim export: note: {note}", file=sys.stderr)
            print(f"{args.design} -> {path}")
    if args.json:
        print(_dump(doc))
    return 0


def cmd_gradcheck(args) -> int:
    from ..render.diff_render import ViewSpec
    from ..render.gradcheck import run, table

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
    # A parameter fails when its interior AD misses the difference (a parameter without
    # an edge term), forward and reverse mode disagree, or the total derivative (where
    # the path has one) misses the full difference by more than 5 % and 3 sigma.
    bad = [p["name"] for p in doc["params"]
           if (not p["boundary"] and p["rel_err"] > args.tolerance)
           or p["forward_reverse_rel"] > doc["forward_reverse_tol"]
           or p.get("total_ok") is False]
    doc["tolerance"], doc["failed"] = args.tolerance, bad
    if args.json:
        from ..analysis.compare import json_safe

        # Relative errors and sigmas against a zero difference are infinite: null in JSON.
        print(_dump(json_safe(doc)))
    else:
        print(f"{design_path} + {args.content}: {doc['path']} path, {res[0]}x{res[1]} px, {args.spp} spp, focus "
              f"{', '.join(f'{f:g}' for f in focus)} mm, loss {doc['loss']:.6g}")
        print(table(doc))
        s = doc["seconds"]
        print(f"reverse {s['reverse']:.2f} s, forward {s['forward']:.2f} s, finite differences "
              f"{s['finite_differences']:.2f} s; edge term at {doc['edge_rel_step']:g} x the step scale; "
              + (f"FAILED: {', '.join(bad)}" if bad else f"interior parameters within {args.tolerance:g}"
                 + (", totals within 5 % or 3 sigma of the full difference" if doc.get("total") else "")))
    return 1 if bad else 0


def cmd_compare(args) -> int:
    from ..analysis.compare import compare_paths, json_safe

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
    from ..regression import check, update

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


def register(sub) -> None:
    """Add this module's verbs to the `lfsim` sub-command parser."""
    fs = sub.add_parser("focal-stack", help="retinal images of the display focused at several depths, "
                        "with the natural view, similarity and focus cues")
    fs.add_argument("design", nargs="?", help="InI design (default: the content file's [view] design)")
    fs.add_argument("--content", default=DEFAULT_CONTENT, help=f"content: a content TOML or a Mitsuba XML scene in "
                    f"visual-space mm (default {DEFAULT_CONTENT})")
    fs.add_argument("--ei-spp", type=int, default=16,
                    help="samples per display pixel of path-traced elemental images (a Mitsuba-scene content) "
                    "and of --ei-bundle (default 16)")
    fs.add_argument("--ei-bundle", action="store_true",
                    help="anti-aliased elemental images: each pixel integrates over its ray bundle (pixel "
                    "area x lenslet stop, --ei-spp rays) instead of shading its chief ray")
    fs.add_argument("--ei-colour", action="store_true",
                    help="per-channel elemental images: each colour channel shaded along rays traced at its "
                    "display primary's median wavelength, pre-correcting the optics' lateral colour")
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
    fs.add_argument("--wavelength-nm", type=float,
                    help="render every channel at this one wavelength, nm (default: spectral, the display "
                         "primaries' spectra on the display, broadband white through the sRGB "
                         "colour-matching functions in the natural view; the mesh optics are "
                         "monochrome at the design's primary)")
    fs.add_argument("--no-diffraction", action="store_true",
                    help="geometric images: no diffraction by the views' apertures and the pupil")
    fs.add_argument("--wavelength-samples", type=int, default=8,
                    help="wavelength nodes per display primary of a spectral render (default 8)")
    fs.add_argument("--tessellation", type=float, default=1.0,
                    help="mesh density as a multiple of the defaults (--optics mesh; default 1)")
    fs.add_argument("--out", default="renders/focal_stack", help="output directory (default renders/focal_stack)")
    budget.add_flags(fs)
    _add_set(fs)
    fs.add_argument("--json", action="store_true")
    fs.set_defaults(func=cmd_focal_stack)

    ex = sub.add_parser("export", help="write a design's display path as a Mitsuba scene (XML + PLY + the "
                        "elemental images) that plain mitsuba renders, or the lens as a Zemax/CODE V file")
    ex.add_argument("design", nargs="?", help="InI design (default: the content file's [view] design); any "
                    "design with --zmx/--seq")
    ex.add_argument("--mitsuba", metavar="DIR", help="write DIR/scene.xml, its meshes and elemental images")
    ex.add_argument("--zmx", metavar="FILE", help="write the lens as a Zemax .zmx file (any design)")
    ex.add_argument("--seq", metavar="FILE", help="write the lens as a CODE V .seq file (any design)")
    ex.add_argument("--lenslet", metavar="M,N", help="with --zmx/--seq: the lenslet (0-based) whose sub-system "
                    "a design with lenslet arrays is written as")
    ex.add_argument("--content", default=DEFAULT_CONTENT, help=f"content shown on the display (default "
                    f"{DEFAULT_CONTENT})")
    ex.add_argument("--focus-mm", help="the eye's focus distance, mm (default: the content's first)")
    ex.add_argument("--cdp-mm", help="CDP distance the tunable lens is set to, mm (inf allowed)")
    ex.add_argument("--pupil-mm", type=float, help="eye pupil diameter, mm (default: the content's, else 3)")
    ex.add_argument("--spp", type=int, default=256, help="samples per pixel written into the scene (default 256)")
    ex.add_argument("--ei-spp", type=int, default=16, help="samples per display pixel of a path-traced content")
    ex.add_argument("--resolution", help="W,H of the eye's film (default 512 wide, the display's aspect)")
    ex.add_argument("--tessellation", type=float, default=1.0, help="mesh density, x the defaults (default 1)")
    _add_set(ex)
    ex.add_argument("--json", action="store_true")
    ex.set_defaults(func=cmd_export)

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
                     help="largest relative error of an interior parameter (default 0.02); exit 1 beyond it, "
                          "and when a total derivative misses the full difference by more than 5 %% and 3 sigma")
    gcp.add_argument("--mla-cells", choices=("per_surface", "fixed"), default="per_surface")
    budget.add_flags(gcp)
    _add_set(gcp)
    gcp.add_argument("--json", action="store_true")
    gcp.set_defaults(func=cmd_gradcheck)

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
    budget.add_flags(rg)
    _add_set(rg)
    rg.add_argument("--json", action="store_true")
    rg.set_defaults(func=cmd_regress)
