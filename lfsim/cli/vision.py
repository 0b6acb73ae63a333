"""Verbs of the vision analyses: `psf`, `accommodation`."""

from __future__ import annotations

import math
import sys

from .common import (
    DEFAULT_CONTENT,
    InputError,
    _add_set,
    _check_seed,
    _dump,
    _float_list,
    _fmt,
    _load_design,
    content_path,
)


def _default_design(args):
    """DESIGN, or the default content's ``[view]`` design."""
    if args.design:
        return args.design
    from ..content import load_content

    d = load_content(content_path(DEFAULT_CONTENT)).view.design
    if d is None:
        raise InputError(f"{DEFAULT_CONTENT}: view.design = missing: give a DESIGN argument")
    return d


def _diopters(flag, v, allow_none=False):
    if v is None and allow_none:
        return None
    if not (math.isfinite(v) and 0 <= v <= 20):
        raise InputError(f"{flag} = {v!r}: must be a vergence in 0..20 D (0 = infinity)")
    return float(v)


def cmd_psf(args) -> int:
    from ..fileio import check_writable
    from ..vision.psf import PsfSpec, render_psf, write_psf

    depth = _diopters("--depth-d", args.depth_d)
    focus = _diopters("--focus-d", args.focus_d)
    cdp = _diopters("--cdp-d", args.cdp_d, allow_none=True)
    _common_checks(args)
    check_writable(args.out, "--out", folder=True)
    path = _default_design(args)
    design = _load_design(args, path)
    spec = PsfSpec(view=args.view, depth_d=depth, focus_d=focus, eye=args.eye, pupil_mm=float(args.pupil_mm),
                   wavelength_nm=args.wavelength_nm, diffraction=not args.no_diffraction, cdp_d=cdp,
                   fov_arcmin=args.fov_arcmin, resolution=args.resolution, spp=args.spp, seed=args.seed,
                   wavelength_samples=args.wavelength_samples)
    log = (lambda *a, **k: None) if args.json else (lambda msg: print(msg, file=sys.stderr))
    img, doc = render_psf(design, spec, log=log)
    doc = write_psf(args.out, img, dict(doc, design=str(path)),
                    {k: v for k, v in vars(spec).items() if v is not None} | {"design": str(path)})
    if args.json:
        print(_dump(doc))
        return 0
    print(f"{path}: {spec.view} PSF of a point at {depth:g} D, eye focused at {focus:g} D "
          f"({spec.eye}, {spec.pupil_mm:g} mm): FWHM {_fmt(doc['fwhm_arcmin'], '.3f', 'arcmin')}, "
          f"EE50 diameter {doc['ee50_arcmin']:.3f} arcmin, peak {doc['peak']:.4g} /arcmin^2 -> {args.out}")
    return 0


def _common_checks(args) -> None:
    if not (math.isfinite(args.pupil_mm) and 0 < args.pupil_mm <= 10):
        raise InputError(f"--pupil-mm = {args.pupil_mm!r}: must be in (0, 10] mm")
    if args.wavelength_nm is not None and not (math.isfinite(args.wavelength_nm) and 380 <= args.wavelength_nm <= 780):
        raise InputError(f"--wavelength-nm = {args.wavelength_nm!r}: must lie in 380..780 nm")
    if args.fov_arcmin is not None and not (math.isfinite(args.fov_arcmin) and 0.5 <= args.fov_arcmin <= 600):
        raise InputError(f"--fov-arcmin = {args.fov_arcmin!r}: must be in 0.5..600 arcmin")
    if not 8 <= args.resolution <= 2048:
        raise InputError(f"--resolution = {args.resolution}: must be in 8..2048 px")
    if args.spp < 1:
        raise InputError(f"--spp = {args.spp}: must be >= 1")
    if not 1 <= args.wavelength_samples <= 64:
        raise InputError(f"--wavelength-samples = {args.wavelength_samples}: must be in 1..64")
    _check_seed(args.seed)


def cmd_accommodation(args) -> int:
    from ..fileio import check_writable
    from ..vision.accommodation import AccommodationSpec, response, write

    depths = [_diopters("--depths-d", v) for v in _float_list(args.depths_d, "--depths-d")]
    cdp = _diopters("--cdp-d", args.cdp_d, allow_none=True)
    _common_checks(args)
    band = _float_list(args.band_cpd, "--band-cpd")
    if len(band) != 2 or not 0 < band[0] < band[1] <= 60:
        raise InputError(f"--band-cpd = {args.band_cpd!r}: must be LO,HI with 0 < LO < HI <= 60 cpd")
    if not (math.isfinite(args.step_d) and 0.005 <= args.step_d <= 1):
        raise InputError(f"--step-d = {args.step_d!r}: must be in 0.005..1 D")
    if not (math.isfinite(args.margin_d) and 2 * args.step_d <= args.margin_d <= 5):
        raise InputError(f"--margin-d = {args.margin_d!r}: must be in 2 steps..5 D")
    px = args.fov_arcmin / args.resolution
    if band[1] > 30.0 / px:
        raise InputError(f"--band-cpd = {args.band_cpd!r}: above the images' Nyquist frequency {30.0 / px:.1f} cpd "
                         f"(--fov-arcmin / --resolution = {px:.3g} arcmin per pixel)")
    if args.out is not None:
        check_writable(args.out, "--out", folder=True)
    path = _default_design(args)
    design = _load_design(args, path)
    if design.ini is None:
        raise InputError(f"{path}: ini = missing: accommodation needs an InI design ([ini] section)")
    spec = AccommodationSpec(depths_d=tuple(depths), cdp_d=cdp, pupil_mm=float(args.pupil_mm), eye=args.eye,
                             wavelength_nm=args.wavelength_nm, diffraction=not args.no_diffraction,
                             band_cpd=(band[0], band[1]), step_d=float(args.step_d), margin_d=float(args.margin_d),
                             fov_arcmin=float(args.fov_arcmin), resolution=args.resolution, spp=args.spp,
                             seed=args.seed, wavelength_samples=args.wavelength_samples)
    log = (lambda *a, **k: None) if args.json else (lambda msg: print(msg, file=sys.stderr))
    doc = response(design, spec, log=log)
    doc["design"] = str(path)
    if args.out is not None:
        doc = write(args.out, doc)
    if args.json:
        print(_dump(doc))
        return 0
    print(f"{path}: accommodation response, CDP {doc['cdp_d']:g} D, {spec.eye} eye, {spec.pupil_mm:g} mm pupil "
          f"({doc['metric']})")
    for p in doc["points"]:
        print(f"  target {p['target_d']:5.2f} D: display {p['response_d']:5.2f} D, natural view "
              f"{p['natural_response_d']:5.2f} D"
              + ("  (display peak at the sweep's end: widen --margin-d)" if p["at_sweep_edge"] else ""))
    if args.out is not None:
        print(f"wrote {args.out}/accommodation.json, accommodation.png")
    return 0


def register(sub) -> None:
    p = sub.add_parser("psf", help="retinal PSF of a point shown by the display at a depth, or of the real point")
    p.add_argument("design", nargs="?", help=f"InI design (default: the view design of {DEFAULT_CONTENT})")
    p.add_argument("--view", choices=("display", "natural"), default="display",
                   help="display (default): the elemental images of the point, through the optics; "
                        "natural: the real point")
    p.add_argument("--depth-d", type=float, default=1.0, help="depth of the point, diopters (default 1)")
    p.add_argument("--focus-d", type=float, default=1.0, help="eye focus, diopters (default 1)")
    p.add_argument("--cdp-d", type=float, help="display: CDP state, diopters (default: the design's middle CDP)")
    p.add_argument("--eye", choices=("ideal", "arizona"), default="ideal",
                   help="ideal (default): aberration- and dispersion-free; arizona: the Arizona eye, dispersive")
    p.add_argument("--pupil-mm", type=float, default=3.0, help="eye pupil diameter, mm (default 3)")
    p.add_argument("--wavelength-nm", type=float,
                   help="one wavelength (default: spectral: the display primaries on the display, "
                        "broadband white in the natural view)")
    p.add_argument("--no-diffraction", action="store_true", help="geometric images (no aperture diffraction)")
    p.add_argument("--fov-arcmin", type=float, help="image width, arcmin (default: from the blur expected)")
    p.add_argument("--resolution", type=int, default=161, help="pixels per side (default 161)")
    p.add_argument("--spp", type=int, default=1024, help="samples per pixel (default 1024)")
    p.add_argument("--wavelength-samples", type=int, default=4,
                   help="spectral: wavelength nodes per display primary (default 4)")
    p.add_argument("--seed", type=int, default=0, help="random seed of the render (default 0)")
    p.add_argument("--out", required=True, help="output directory (psf.exr, psf.png, psf.json)")
    p.add_argument("--json", action="store_true", help="print the figures as JSON on stdout")
    _add_set(p)
    p.set_defaults(func=cmd_psf)

    a = sub.add_parser("accommodation",
                       help="predicted accommodation response to points shown at depths (display and natural view)")
    a.add_argument("design", nargs="?", help=f"InI design (default: the view design of {DEFAULT_CONTENT})")
    a.add_argument("--depths-d", default="0.5,1,1.5,2,2.5",
                   help="target depths, diopters, comma separated (default 0.5,1,1.5,2,2.5)")
    a.add_argument("--cdp-d", type=float, help="CDP state of the display, diopters (default: the design's middle CDP)")
    a.add_argument("--pupil-mm", type=float, default=4.0, help="eye pupil diameter, mm (default 4)")
    a.add_argument("--eye", choices=("ideal", "arizona"), default="arizona",
                   help="arizona (default): the Arizona eye, dispersive; ideal: aberration- and dispersion-free")
    a.add_argument("--wavelength-nm", type=float,
                   help="one wavelength (default: spectral: the display primaries on the display, "
                        "broadband white in the natural view)")
    a.add_argument("--wavelength-samples", type=int, default=4,
                   help="spectral: wavelength nodes per display primary (default 4)")
    a.add_argument("--no-diffraction", action="store_true", help="geometric images (no aperture diffraction)")
    a.add_argument("--band-cpd", default="3,10", help="spatial-frequency band of the metric, cpd (default 3,10)")
    a.add_argument("--step-d", type=float, default=0.1, help="accommodation step of the sweep, D (default 0.1)")
    a.add_argument("--margin-d", type=float, default=0.5,
                   help="sweep beyond the target and the CDP on each side, D (default 0.5)")
    a.add_argument("--fov-arcmin", type=float, default=96.0, help="retinal image width, arcmin (default 96)")
    a.add_argument("--resolution", type=int, default=96, help="pixels per side of each image (default 96)")
    a.add_argument("--spp", type=int, default=256, help="samples per pixel (default 256)")
    a.add_argument("--seed", type=int, default=0, help="random seed, the same at every state (default 0)")
    a.add_argument("--out", help="output directory (accommodation.json, accommodation.png); default: none written")
    a.add_argument("--json", action="store_true", help="print the result as JSON on stdout")
    _add_set(a)
    a.set_defaults(func=cmd_accommodation)
