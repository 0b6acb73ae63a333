"""The ``lfsim`` command. Thin: parse arguments, call the packages, print.

Exit status: 0 success, 1 a check failed, 2 bad input (one line on stderr
naming the file, key and value; never a traceback).
"""

from __future__ import annotations

import argparse
import math
import sys

from .. import __version__, budget, progress
from ..backend import BackendError
from ..design import DesignError
from . import ini, optics, render, tolerance, vision
from .common import InputError, OneLineParser
from .optics import read_rays_csv

__all__ = ["InputError", "OneLineParser", "build_parser", "main", "read_rays_csv"]


def build_parser() -> argparse.ArgumentParser:
    p = OneLineParser(prog="lfsim", description="lfsim: light-field rendering simulator for integral-imaging "
                      "head-mounted displays (design, analyze, optimize, render focal stacks).")
    p.add_argument("--version", action="version", version=f"lfsim {__version__}")
    sub = p.add_subparsers(dest="verb", required=True, metavar="VERB")
    for verbs in (optics, ini, render, tolerance, vision):
        verbs.register(sub)
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
        with budget.use(budget.Limits.from_args(args)), progress.heartbeat(f"lfsim {args.verb}"):
            return args.func(args)
    except (DesignError, InputError, BackendError) as e:
        print(f"lfsim: error: {e}", file=sys.stderr)
        return 2
    except ValueError as e:
        print(f"lfsim: error: {' '.join(str(e).split())}", file=sys.stderr)
        return 2
    except BrokenPipeError:  # the reader of our output went away (`lfsim params D | head`): not an error
        import os

        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())  # no second error at exit's flush
        return 0
    except OSError as e:  # an output path that cannot be written, a directory given for a file, ...
        where = f"{e.filename}: " if e.filename else ""
        print(f"lfsim: error: {where}{' '.join(str(e.strerror or e).split())}", file=sys.stderr)
        return 2
