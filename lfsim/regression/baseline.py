"""The baseline folder of ``lfsim regress``: what was rendered, how, and the tolerances.

Layout::

    DIR/baseline.json      options, seeds, tolerances, design metrics, image list, noise levels
    DIR/design.toml        the design as rendered (``--set`` overrides applied), for reference
    DIR/images/<kind>_<focus>mm_seed<S>.exr   retinal images, float32, one per seed

Paths inside ``baseline.json`` are relative to ``DIR``. A baseline is written
into a temporary sibling folder and swapped into place, so a reader sees the
old baseline or the new one, never a mixture.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np

FORMAT = "lfsim-regression-baseline"
VERSION = 1

#: Default tolerances (stored in each baseline, where they can be edited).
DEFAULT_TOLERANCES = {
    # Significance of the noise-aware image statistics (lfsim.regression.noise): |z| above this.
    "z_max": 4.0,
    # ...and an effect above these floors (fractions): RMS change of the image (of its mean),
    # relative loss of band-pass detail energy, relative rise of the squared error against
    # the natural view.
    "image_change_floor": 0.005,
    "detail_floor": 0.005,
    "error_floor": 0.005,
    # Tile sizes (px) of the significance test: larger than the noise's correlation length.
    "tile_px": 8,
    "detail_tile_px": 16,
    # Deterministic figures (design metrics, field of view): |candidate - baseline| <= abs + rel |baseline|.
    "metric_rel": 1e-6,
    "metric_abs": 1e-9,
    # Per-figure overrides: {"metric summary.pa_max": {"rel": 1e-3, "abs": 0}}.
    "per_check": {},
}


class BaselineError(ValueError):
    """A missing, unreadable or inconsistent baseline (one line naming the file)."""


def image_name(kind: str, focus_mm: float, seed: int) -> str:
    return f"images/{kind}_{focus_mm:g}mm_seed{seed}.exr"


def relative(path, base: Path) -> str:
    """``path`` relative to ``base`` when possible (portable baselines), else absolute."""
    p = Path(path).resolve()
    try:
        return os.path.relpath(p, Path(base).resolve())
    except ValueError:  # another drive
        return str(p)


def resolve(path: str, base: Path) -> Path:
    p = Path(path)
    return p if p.is_absolute() else (Path(base) / p)


def read(folder) -> dict:
    """``baseline.json`` of ``folder``, checked for the keys a comparison needs."""
    folder = Path(folder)
    path = folder / "baseline.json"
    if not path.is_file():
        raise BaselineError(f"{path}: missing: create the baseline first (lfsim regress DESIGN --baseline "
                            f"{folder} --update)")
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        raise BaselineError(f"{path}: not a readable baseline ({' '.join(str(e).split())})") from None
    if not isinstance(doc, dict) or doc.get("format") != FORMAT:
        raise BaselineError(f"{path}: format = {doc.get('format') if isinstance(doc, dict) else None!r}: "
                            f"expected {FORMAT!r}")
    if doc.get("version") != VERSION:
        raise BaselineError(f"{path}: version = {doc.get('version')!r}: this lfsim reads version {VERSION}; "
                            "re-create the baseline with --update")
    for key in ("options", "seeds", "images", "tolerances"):
        if key not in doc:
            raise BaselineError(f"{path}: {key} = missing")
    tol = dict(DEFAULT_TOLERANCES)
    tol.update(doc["tolerances"] or {})
    for key in ("z_max", "image_change_floor", "detail_floor", "error_floor", "metric_rel", "metric_abs"):
        v = tol[key]
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not v >= 0:
            raise BaselineError(f"{path}: tolerances.{key} = {v!r}: expected a number >= 0")
    for key in ("tile_px", "detail_tile_px"):
        v = tol[key]
        if isinstance(v, bool) or not isinstance(v, int) or v < 1:
            raise BaselineError(f"{path}: tolerances.{key} = {v!r}: expected an integer >= 1")
    doc["tolerances"] = tol
    return doc


def load_images(folder, doc: dict) -> dict:
    """``{(kind, focus index): [image per seed]}`` of a baseline (float32 arrays)."""
    from ..analysis.compare import CompareInputError, read_image

    folder = Path(folder)
    focus = doc["options"]["focus_mm"]
    out: dict = {}
    for rec in doc["images"]:
        path = resolve(rec["exr"], folder)
        try:
            img, channels = read_image(path)
        except CompareInputError as e:
            raise BaselineError(str(e)) from None
        if img.shape[2] != 3:
            raise BaselineError(f"{path}: channels {','.join(channels)}: expected R,G,B")
        try:
            i = focus.index(rec["focus_mm"])
            k = doc["seeds"].index(rec["seed"])
        except ValueError:
            raise BaselineError(f"{folder / 'baseline.json'}: images: {rec['exr']} has a focus or seed "
                                "the baseline does not list") from None
        out.setdefault((rec["kind"], i), [None] * len(doc["seeds"]))[k] = img
    for key, imgs in out.items():
        if any(v is None for v in imgs):
            raise BaselineError(f"{folder / 'baseline.json'}: images: {key[0]} at {focus[key[1]]:g} mm "
                                "lacks a seed")
    return out


def check_replaceable(folder) -> None:
    """Refuse to replace a path that is neither missing, an empty folder, nor a baseline folder."""
    from ..fileio import check_replaceable as check

    try:
        check(folder, "baseline.json", "--baseline")
    except ValueError as e:
        raise BaselineError(str(e)) from None


def write(folder, doc: dict, images: dict, design_text: str | None = None) -> None:
    """Write a baseline: ``images`` = ``{(kind, focus index): [image per seed]}``; swapped in atomically.

    ``doc`` is completed with the ``images`` list and written as ``baseline.json``.
    """
    from ..fileio import atomic_dir, write_json, write_text
    from ..render.focal_stack import write_exr

    folder = Path(folder)
    check_replaceable(folder)
    with atomic_dir(folder, "baseline.json", "--baseline") as tmp:
        recs = []
        focus = doc["options"]["focus_mm"]
        for (kind, i), imgs in sorted(images.items()):
            for seed, img in zip(doc["seeds"], imgs):
                name = image_name(kind, focus[i], seed)
                write_exr(tmp / name, np.asarray(img, np.float32),
                          {"kind": kind, "focus_mm": focus[i], "seed": seed, "spp": doc["options"]["spp"],
                           "design": doc.get("design", {}).get("path", "")})
                recs.append({"kind": kind, "focus_mm": focus[i], "seed": seed, "exr": name})
        doc = dict(doc, images=recs)
        if design_text is not None:
            write_text(tmp / "design.toml", design_text)
        write_json(tmp / "baseline.json", doc)
