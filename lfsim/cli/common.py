"""Helpers shared by the verbs: design loading with --set, option parsing, JSON output."""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

import numpy as np


class InputError(Exception):
    """Bad command-line input (already formatted as one line)."""


class OneLineParser(argparse.ArgumentParser):
    """argparse with a one-line error (exit status 2) instead of the usage text: ``lfsim:
    error: VERB: ...`` for the command line's verbs, ``PROG: error: ...`` for a script."""

    def error(self, message):
        said = " ".join(str(message).split())
        if self.prog == "lfsim" or self.prog.startswith("lfsim "):
            verb = self.prog.removeprefix("lfsim").strip()  # "lfsim focal-stack" -> "focal-stack"
            self.exit(2, f"lfsim: error: {verb + ': ' if verb else ''}{said}\n")
        self.exit(2, f"{self.prog}: error: {said}\n")


def _load_design(args, path=None):
    """The verb's design, with its ``--set KEY=VALUE`` overrides applied (lfsim.design.overrides)."""
    from ..design.overrides import load_with_overrides, parse_sets

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


def _check_seed(seed: int, end: int = 2 ** 32) -> None:
    """Mitsuba's samplers take 32-bit unsigned seeds."""
    if not 0 <= seed < end:
        raise InputError(f"--seed = {seed}: must be an integer in [0, {end})")


def _fmt(v, spec: str, unit: str = "", none: str = "undefined") -> str:
    """A number with its unit, or ``none`` ("undefined": a quantity that is not finite) for None."""
    return none if v is None else f"{format(v, spec)} {unit}".rstrip()


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


DEFAULT_CONTENT = "scenes/fig9_wall.toml"


def content_path(path: str) -> str:
    """``path``, except the default content when run outside the checkout: the shipped
    ``scenes/fig9_wall.toml`` beside the package."""
    if path == DEFAULT_CONTENT and not Path(path).exists():
        shipped = Path(__file__).resolve().parents[2] / DEFAULT_CONTENT
        if shipped.exists():
            return str(shipped)
    return path


def _is_content_file(path) -> bool:
    """Whether ``path`` is a content file (a Mitsuba XML, or a TOML with [[objects]] or [scene]
    and no [[surfaces]]) rather than a design."""
    import tomllib
    from pathlib import Path

    p = Path(path)
    if p.suffix.lower() == ".xml":
        return True
    try:
        data = tomllib.loads(p.read_text())
    except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError):
        return False
    return "surfaces" not in data and ("objects" in data or "scene" in data)


def _view_of(args, verb: str):
    """The content, design and eye view of a render verb: ``(content, design_path, design, focus_mm,
    cdp_mm, pupil_mm)``, from the arguments or else the content file's ``[view]``."""
    from ..content import load_content

    if args.design is not None and args.content == DEFAULT_CONTENT and _is_content_file(args.design):
        # `lfsim focal-stack scenes/tabletop.toml`: a content file alone; its [view] names the design.
        args.content, args.design = args.design, None
    args.content = content_path(args.content)
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


def _add_dask(parser) -> None:
    parser.add_argument("--scheduler", help="dask.distributed scheduler address tcp://HOST:PORT (default: a local "
                        "cluster started here); 'serial': this process, no Dask")
    parser.add_argument("--workers", type=int, help="worker processes of the local cluster (default: CPU cores)")
