"""Lens files of other optical-design programs: CODE V ``.seq`` and Zemax ``.zmx``.

:func:`import_lens` reads one into a design table (validated as an lfsim design) and
:func:`write_imported` writes it as a design file; :func:`export_text` writes a loaded
design in either format. The readers and writers are lfsim's own; what each format
supports is listed in ``docs/lens-files.md``. No Dr.Jit, no Mitsuba here.
"""

from __future__ import annotations

from pathlib import Path

from ...fileio import write_text
from .common import Imported, LensFileError

FORMATS = {".seq": "CODE V", ".zmx": "Zemax"}

__all__ = ["FORMATS", "Imported", "LensFileError", "export_text", "import_lens", "write_export", "write_imported"]


def import_lens(path: str | Path) -> Imported:
    """Read a ``.seq`` or ``.zmx`` file into a design table, checked by the design loader.

    Raises :class:`LensFileError` / :class:`~lfsim.design.DesignError` (one line) on anything
    the file holds that lfsim cannot represent.
    """
    from ..loader import system_from_dict
    from .codev import read_seq
    from .zemax import read_zmx

    p = Path(path)
    suffix = p.suffix.lower()
    if suffix not in FORMATS:
        raise LensFileError(str(p), None, "expected a CODE V .seq or a Zemax .zmx file")
    if not p.exists():
        raise LensFileError(str(p), None, "file not found")
    if p.is_dir():
        raise LensFileError(str(p), None, "is a folder, not a lens file")
    imp = read_seq(p) if suffix == ".seq" else read_zmx(p)
    system_from_dict(imp.raw, f"{p} (imported)")
    return imp


def design_text(path: str | Path, imp: Imported) -> str:
    from ..writer import design_text as toml_text

    p = Path(path)
    header = [f"Imported by lfsim from the {FORMATS[p.suffix.lower()]} file {p.name}.",
              "Units mm, degrees, nm. Each surface's comment names its line or SURF in the source file."]
    header += [f"Note: {n}" for n in imp.notes]
    return toml_text(imp.raw, header)


def write_imported(path: str | Path, out: str | Path) -> Imported:
    """Import ``path`` and write the design to ``out`` atomically; nothing is written on error."""
    imp = import_lens(path)
    write_text(out, design_text(path, imp))
    return imp


def export_text(design, fmt: str, lenslet: tuple[int, int] | None = None) -> tuple[str, list[str]]:
    """The design as ``fmt`` ("zmx" or "seq") text, and notes on what the format could not keep."""
    from .codev import write_seq
    from .export import plan
    from .zemax import write_zmx

    pl = plan(design, lenslet)
    title = design.name or Path(design.path or "design").stem
    if lenslet is not None:
        title += f" (lenslet {lenslet[0]},{lenslet[1]})"
    writers = {"zmx": write_zmx, "seq": write_seq}
    if fmt not in writers:
        raise ValueError(f"unknown lens-file format {fmt!r}: zmx or seq")
    try:
        return writers[fmt](pl, title), pl.notes
    except ValueError as e:  # what the format cannot hold, said of this design file
        raise ValueError(f"{design.path or title}: {e}") from None


def write_export(design, out: str | Path, fmt: str, lenslet: tuple[int, int] | None = None) -> list[str]:
    text, notes = export_text(design, fmt, lenslet)
    write_text(out, text)
    return notes
