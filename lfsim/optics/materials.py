"""Optical materials: refractive index as a function of wavelength.

Indices are relative to air at the catalog's reference conditions (the usual
lens-design convention), so ``air`` is exactly 1. Wavelengths are in
nanometres at this interface; dispersion formulas use micrometres inside.

Kinds of material:

* catalog glasses and plastics (``data/materials.toml``), by name,
  case-insensitive: Sellmeier or power-series formulas with their sources;
* any other glass of the SCHOTT, OHARA, HOYA, CDGM, HIKARI, SUMITA, LZOS and
  CRYSTRAN catalogs (:mod:`lfsim.optics.glass_catalogs`), by its catalog name;
* a constant index (a number in the design file);
* an (nd, Vd) model glass: ``n(λ) = A + B/λ²`` through nd at the d line
  (587.5618 nm) with ``nF − nC = (nd − 1)/Vd``;
* ``air`` (n = 1).
"""

from __future__ import annotations

import difflib
import math
import tomllib
from dataclasses import dataclass, field
from functools import lru_cache
from importlib import resources

import numpy as np

#: Fraunhofer lines (nm) used by catalog nd / Vd.
LAMBDA_D = 587.5618
LAMBDA_F = 486.1327
LAMBDA_C = 656.2725


class MaterialError(ValueError):
    """A material could not be resolved; the message lists what is allowed."""


@dataclass(frozen=True)
class Material:
    """A dispersive (or constant) optical medium."""

    name: str
    kind: str  # "air", "constant", "sellmeier", "polynomial", "abbe"
    coefficients: tuple = ()
    range_nm: tuple[float, float] = (0.0, math.inf)
    source: str = ""
    extra: dict = field(default_factory=dict, compare=False, hash=False)

    def index(self, wavelength_nm) -> np.ndarray | float:
        """Refractive index at ``wavelength_nm`` (scalar or array, nm)."""
        lam = np.asarray(wavelength_nm, dtype=np.float64)
        if np.any(lam <= 0):
            raise MaterialError(f"wavelength must be > 0 nm, got {wavelength_nm!r}")
        um2 = (lam * 1e-3) ** 2
        if self.kind == "air":
            n = np.ones_like(lam)
        elif self.kind == "constant":
            n = np.full_like(lam, self.coefficients[0])
        elif self.kind == "sellmeier":
            B, C = self.coefficients
            n2 = 1.0 + sum(b * um2 / (um2 - c) for b, c in zip(B, C))
            n = np.sqrt(n2)
        elif self.kind == "polynomial":
            powers, coef = self.coefficients
            lam_um = lam * 1e-3
            n = np.sqrt(sum(a * lam_um**p for p, a in zip(powers, coef)))
        elif self.kind == "abbe":
            A, B = self.coefficients
            n = A + B / um2
        elif self.kind == "vendor":
            from .glass_catalogs import refractive_index

            n = refractive_index(self.coefficients, lam)
        else:  # pragma: no cover - guarded by constructors
            raise MaterialError(f"unknown material kind {self.kind!r}")
        return float(n) if n.ndim == 0 else n

    @property
    def nd(self) -> float:
        return float(self.index(LAMBDA_D))

    @property
    def vd(self) -> float:
        """Abbe number (nd − 1)/(nF − nC); infinite for a non-dispersive medium."""
        dn = self.index(LAMBDA_F) - self.index(LAMBDA_C)
        return math.inf if dn == 0 else (self.nd - 1.0) / float(dn)

    def in_range(self, wavelength_nm: float) -> bool:
        return self.range_nm[0] <= wavelength_nm <= self.range_nm[1]


AIR = Material("air", "air")


def constant(n: float) -> Material:
    """A non-dispersive medium of index ``n`` (must be finite and ≥ 1 or a valid index)."""
    if not (isinstance(n, (int, float)) and math.isfinite(n) and n > 0):
        raise MaterialError(f"a constant index must be a finite number > 0, got {n!r}")
    return Material(f"n={n:g}", "constant", (float(n),))


def abbe(nd: float, vd: float) -> Material:
    """Model glass from nd and Vd: ``n(λ) = A + B/λ²`` (λ in µm).

    B is fixed by the principal dispersion nF − nC = (nd − 1)/Vd and A by
    n(587.5618 nm) = nd, so the model reproduces nd and Vd exactly.
    """
    if not (math.isfinite(nd) and nd >= 1.0):
        raise MaterialError(f"nd must be a finite number >= 1, got {nd!r}")
    if not (math.isfinite(vd) and vd > 0):
        raise MaterialError(f"vd must be a finite number > 0, got {vd!r}")
    inv = lambda lam_nm: 1.0 / (lam_nm * 1e-3) ** 2  # noqa: E731
    B = (nd - 1.0) / vd / (inv(LAMBDA_F) - inv(LAMBDA_C))
    A = nd - B * inv(LAMBDA_D)
    return Material(f"nd={nd:g},vd={vd:g}", "abbe", (A, B))


@lru_cache(maxsize=1)
def catalog() -> dict[str, Material]:
    """All catalog materials by upper-case name."""
    text = resources.files("lfsim.optics").joinpath("data/materials.toml").read_text()
    data = tomllib.loads(text)
    out: dict[str, Material] = {}
    for name, entry in data.items():
        formula = entry["formula"]
        rng = tuple(1e3 * float(v) for v in entry.get("range_um", (0.0, math.inf)))
        extra = {k: entry[k] for k in ("nd", "vd") if k in entry}
        if formula == "sellmeier":
            coef = (tuple(map(float, entry["B"])), tuple(map(float, entry["C"])))
        elif formula == "polynomial":
            coef = (tuple(map(float, entry["powers"])), tuple(map(float, entry["coefficients"])))
        else:  # pragma: no cover - data file is ours
            raise MaterialError(f"materials.toml: [{name}] formula {formula!r} is not supported")
        out[name.upper()] = Material(name, formula, coef, rng, entry.get("source", ""), extra)
    return out


def vendor_glass(name: str) -> Material:
    """A glass of the vendor catalogs (:mod:`lfsim.optics.glass_catalogs`), by its catalog
    name, the vendor given as a suffix (``NSSK2_SCHOTT``) or inferred."""
    from . import glass_catalogs as gc

    try:
        hit = gc.resolve(name)
    except ValueError as e:
        raise MaterialError(str(e)) from None
    if hit is None:
        builtin = {gc.name_key(m.name): m.name for m in catalog().values()}
        near = [builtin[k] for k in difflib.get_close_matches(gc.name_key(name), list(builtin), n=3, cutoff=0.7)]
        near += [m for m in gc.close_matches(name) if gc.name_key(m.split(' (')[0]) not in builtin]
        hint = f"close matches: {', '.join(near)}; " if near else ""
        raise MaterialError(
            f"unknown material {name!r}: {hint}allowed 'air', a number, {{nd=..., vd=...}}, "
            f"{', '.join(sorted(builtin.values()))}, {', '.join(sorted({v[0] for v in gc.PLASTICS.values()}))} "
            f"or a glass of the {', '.join(gc.VENDORS)} catalogs")
    canonical, ref = hit
    return Material(canonical, "vendor", ref, gc.range_nm(ref), f"refractiveindex.info ({'/'.join(ref)})")


def lookup(spec) -> Material:
    """Resolve a design-file material value.

    ``spec`` may be ``"air"``, a name of the built-in table (case-insensitive) or of a vendor
    catalog (:func:`vendor_glass`), a number (constant index) or a mapping
    ``{nd = ..., vd = ...}``.
    """
    if isinstance(spec, bool):
        raise MaterialError(f"a material cannot be a boolean ({spec!r})")
    if isinstance(spec, (int, float)):
        return constant(float(spec))
    if isinstance(spec, dict):
        keys = set(spec)
        for k in sorted(keys & {"nd", "vd", "n"}):
            v = spec[k]
            if isinstance(v, bool) or not isinstance(v, (int, float)):
                raise MaterialError(f"{k} must be a number, got {v!r}")
        if keys == {"nd", "vd"}:
            return abbe(float(spec["nd"]), float(spec["vd"]))
        if keys == {"n"}:
            return constant(float(spec["n"]))
        raise MaterialError(
            f"a material table must have keys {{nd, vd}} or {{n}}, got {sorted(keys)}"
        )
    if isinstance(spec, str):
        if spec.strip().lower() == "air":
            return AIR
        cat = catalog()
        key = spec.strip().upper()
        if key in cat:
            return cat[key]
        return vendor_glass(spec)
    raise MaterialError(f"a material must be a name, a number or a table, got {spec!r}")
