"""Atomic output files: written to a temporary sibling, then renamed into place.

A reader never sees a half-written file, and an interrupted run leaves the
previous version (or nothing) behind.
"""

from __future__ import annotations

import json
import os
import tempfile
from contextlib import contextmanager
from pathlib import Path


@contextmanager
def atomic_path(path: str | Path):
    """Yield a temporary path beside ``path``; rename it to ``path`` on success."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    try:
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=path.suffix or ".tmp", dir=path.parent)
    except OSError as e:  # name the file asked for, not the temporary one beside it
        raise OSError(e.errno, e.strerror, str(path)) from None
    os.close(fd)
    os.chmod(tmp, 0o666 & ~_umask())  # mkstemp makes 0600; a plain open() would honour the umask
    try:
        yield Path(tmp)
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)


def check_replaceable(path: str | Path, manifest: str | None, flag: str = "--out") -> None:
    """Refuse, before any work, to replace a folder that is not this kind of output.

    A folder output replaces ``path`` as a whole, so ``path`` must be absent,
    empty, or a previous output of the same kind (it holds ``manifest``, e.g.
    ``index.json``): pointing ``--out`` at a home folder or a checkout must never
    delete it. Raises a one-line ``ValueError`` naming ``flag``.
    """
    p = Path(path)
    if not p.exists():
        return
    if not p.is_dir():
        raise ValueError(f"{flag} = {str(path)!r}: exists and is not a folder")
    if os.path.ismount(p):  # the output replaces the folder as a whole, which a mount point cannot be
        raise ValueError(f"{flag} = {str(path)!r}: a mount point cannot be replaced; give a folder inside it")
    if manifest is not None and (p / manifest).is_file():
        return
    if any(p.iterdir()):
        what = f"no {manifest}" if manifest else "not empty"
        raise ValueError(f"{flag} = {str(path)!r}: the folder exists and is not a previous output of this kind "
                         f"({what}); the output replaces its folder, so give a new or empty folder")


@contextmanager
def atomic_dir(path: str | Path, manifest: str | None = None, flag: str = "--out"):
    """Yield a new temporary folder beside ``path``; on success it replaces ``path``.

    A run that fails or is interrupted leaves an existing ``path`` exactly as it
    was (and removes its temporary folder); a reader of ``path`` sees the old
    folder or the new one, never a mixture. Only the final swap of the two
    folders is not one atomic step: there ``path`` is briefly absent. An
    existing ``path`` must be empty or hold ``manifest`` (see
    :func:`check_replaceable`), checked on entry, before any work.
    """
    import shutil

    path = Path(os.path.abspath(path))  # "x/.." is the folder above x, and x need not exist
    check_replaceable(path, manifest, flag)
    path.parent.mkdir(parents=True, exist_ok=True)
    try:  # the new folder is made beside ``path``, so its parent must take it
        tmp = Path(tempfile.mkdtemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent))
    except OSError as e:
        raise ValueError(f"{flag} = {str(path)!r}: cannot write in {path.parent} ({e.strerror})") from None
    os.chmod(tmp, 0o777 & ~_umask())
    try:
        yield tmp
        old = None
        if path.exists():
            old = Path(tempfile.mkdtemp(prefix=f".{path.name}.", suffix=".old", dir=path.parent))
            os.replace(path, old / "x")
        os.replace(tmp, path)
        if old is not None:
            shutil.rmtree(old, ignore_errors=True)
    finally:
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)


def check_writable(path: str | Path, flag: str, folder: bool = False) -> None:
    """Refuse, before any work, an output that cannot be written.

    Probes ``path`` itself when it exists (a folder for ``folder``), else the
    nearest existing folder above it. ``flag`` names the option in the one-line
    ``ValueError``.
    """
    p = Path(path)
    if p.exists():
        if folder != p.is_dir():
            raise ValueError(f"{flag} = {str(path)!r}: {'not a folder' if folder else 'is a folder'}")
        target = p
    else:
        target = next(q for q in p.absolute().parents if q.exists())
        if not target.is_dir():
            raise ValueError(f"{flag} = {str(path)!r}: {target} is not a folder")
    probe_dir = target if target.is_dir() else target.parent
    try:  # a real probe: permission bits say nothing for root or on special file systems
        fd, probe = tempfile.mkstemp(prefix=".lfsim-probe-", dir=probe_dir)
        os.close(fd)
        os.unlink(probe)
    except OSError as e:
        raise ValueError(f"{flag} = {str(path)!r}: cannot write in {probe_dir} ({e.strerror})") from None


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def write_text(path: str | Path, text: str) -> None:
    with atomic_path(path) as tmp:
        tmp.write_text(text, encoding="utf-8")


def write_json(path: str | Path, obj) -> None:
    write_text(path, json.dumps(obj, indent=2, allow_nan=False) + "\n")


def save_figure(fig, path: str | Path, **kw) -> None:
    """Save a matplotlib figure atomically (format from the suffix)."""
    path = Path(path)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format=path.suffix.lstrip(".") or "png", **kw)
