"""Verbs of the vision analyses: `psf`."""

from __future__ import annotations

import math
import sys

from .common import DEFAULT_CONTENT, InputError, _add_set, _check_seed, _dump, _fmt, _load_design


def _default_design(args):
    """DESIGN, or the default content's ``[view]`` design."""
    if args.design:
        return args.design
    from ..design.content import load_content

    d = load_content(DEFAULT_CONTENT).view.design
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
    _check_seed(args.seed)
    check_writable(args.out, "--out", folder=True)
    path = _default_design(args)
    design = _load_design(args, path)
    spec = PsfSpec(view=args.view, depth_d=depth, focus_d=focus, eye=args.eye, pupil_mm=float(args.pupil_mm),
                   wavelength_nm=args.wavelength_nm, diffraction=not args.no_diffraction, cdp_d=cdp,
                   fov_arcmin=args.fov_arcmin, resolution=args.resolution, spp=args.spp, seed=args.seed)
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


def register(sub) -> None:
    p = sub.add_parser("psf", help="retinal PSF of a point shown by the display at a depth, or of the real point")
    p.add_argument("design", nargs="?", help=f"InI design (default: the view design of {DEFAULT_CONTENT})")
    p.add_argument("--view", choices=("display", "natural"), default="display")
    p.add_argument("--depth-d", type=float, default=1.0, help="depth of the point, diopters (default 1)")
    p.add_argument("--focus-d", type=float, default=1.0, help="eye focus, diopters (default 1)")
    p.add_argument("--cdp-d", type=float, help="display: CDP state, diopters (default: the design's middle CDP)")
    p.add_argument("--eye", choices=("ideal", "arizona"), default="ideal")
    p.add_argument("--pupil-mm", type=float, default=3.0, help="eye pupil diameter, mm (default 3)")
    p.add_argument("--wavelength-nm", type=float, help="one wavelength (default: spectral, the display primaries)")
    p.add_argument("--no-diffraction", action="store_true", help="geometric images (no aperture diffraction)")
    p.add_argument("--fov-arcmin", type=float, help="image width, arcmin (default: from the blur expected)")
    p.add_argument("--resolution", type=int, default=161, help="pixels per side (default 161)")
    p.add_argument("--spp", type=int, default=1024, help="samples per pixel (default 1024)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", required=True, help="output directory (psf.exr, psf.png, psf.json)")
    p.add_argument("--json", action="store_true")
    _add_set(p)
    p.set_defaults(func=cmd_psf)
