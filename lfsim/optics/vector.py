"""The design vector: every differentiable number of a design, in one order.

One :class:`DesignVector` per :class:`~lfsim.optics.prescription.System` owns

* the parameter table (names, values, units) that the tracer packs into its
  array ``P``, the optimizer varies, tolerancing perturbs and ``lfsim params``
  lists;
* the block layout: ``P`` may hold several copies of the vector (CDP states,
  Jacobian columns, tolerance trials), block ``b`` starting at ``b·size``;
* what is built from it: the shape coefficients of a surface (its
  ``same_as`` owner's), the lenslet axes of an array, and the index parameter
  of each medium.

Every consumer (tracer, first-order model, meshes, both differentiable
renderers, merit) reads values through a *getter* ``get(name)``: a per-lane
``dr.gather`` from ``P``, an opaque Dr.Jit scalar, or a plain float. The
formulas below are then written once for all of them.

Names: ``<surface>.<key>`` (``curvature``, ``conic``, ``A4``…, ``x2y0``…,
``decenter_x``/``_y``, ``tilt_x``/``_y``/``_z``, ``position_x``/``_y``/``_z``,
``thickness``, ``power``, ``index``), ``<array>.pitch_x``/``_y``,
``<array>.center_x``/``_y``, ``object.index`` and, for an object at a finite
distance, ``object.distance`` (mm from the object to the first vertex; in an
InI display the gap g from the microdisplay to the MLA). Indices are filled
per wavelength from the materials.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np

from .prescription import System

#: The object distance: the display gap g of an InI design (Eq. 1's g).
GAP = "object.distance"


def parameter_table(system: System) -> list[tuple[str, float, str]]:
    """Every differentiable design number of ``system``: ``(name, value, unit)``.

    Shape parameters of a ``same_as`` surface are those of its original
    (they are one physical surface). Indices are listed by the medium that
    follows a refracting surface, with value NaN here (see
    :meth:`DesignVector.values`). ``object.distance`` comes last, and only
    when the object is at a finite distance.
    """
    rows: list[tuple[str, float, str]] = [("object.index", float("nan"), "")]
    for s in system.surfaces:
        if s.same_as is None:
            rows += [(f"{s.name}.curvature", s.curvature, "1/mm"), (f"{s.name}.conic", s.conic, "")]
            rows += [(f"{s.name}.A{o}", v, f"mm^{1 - o}") for o, v in sorted(s.asphere.items())]
            rows += [(f"{s.name}.x{i}y{j}", v, "mm") for (i, j), v in sorted(s.xy.items())]
            rows += [
                (f"{s.name}.decenter_x", s.decenter[0], "mm"),
                (f"{s.name}.decenter_y", s.decenter[1], "mm"),
                (f"{s.name}.tilt_x", s.tilt[0], "deg"),
                (f"{s.name}.tilt_y", s.tilt[1], "deg"),
                (f"{s.name}.tilt_z", s.tilt[2], "deg"),
            ]
            if s.global_position is not None:
                rows += [(f"{s.name}.position_{a}", v, "mm") for a, v in zip("xyz", s.global_position)]
        if s.interaction == "paraxial":
            rows.append((f"{s.name}.power", s.power, "1/mm"))
        rows.append((f"{s.name}.thickness", s.thickness, "mm"))
        if s.interaction in ("refract", "tir"):
            rows.append((f"{s.name}.index", float("nan"), ""))
    for a in system.arrays.values():
        rows += [
            (f"{a.name}.pitch_x", a.pitch[0], "mm"),
            (f"{a.name}.pitch_y", a.pitch[1], "mm"),
            (f"{a.name}.center_x", a.center[0], "mm"),
            (f"{a.name}.center_y", a.center[1], "mm"),
        ]
    if math.isfinite(system.object_distance):
        rows.append((GAP, float(system.object_distance), "mm"))
    return rows


def _identity(v):
    return v


class DesignVector:
    """The design vector of ``system`` and the quantities built from it (see the module)."""

    def __init__(self, system: System):
        self.system = system
        self.table = parameter_table(system)
        self.names = [r[0] for r in self.table]
        self.units = {r[0]: r[2] for r in self.table}
        self.index = {n: i for i, n in enumerate(self.names)}
        self.size = len(self.names)
        self.media = self._media()

    # ------------------------------------------------------------- values
    def values(self, wavelength_nm: float | None = None) -> np.ndarray:
        """The vector at ``wavelength_nm`` (default: the primary), indices filled."""
        sysm = self.system
        lam = sysm.primary_wavelength_nm if wavelength_nm is None else float(wavelength_nm)
        index_of = {f"{s.name}.index": s.material for s in sysm.surfaces if s.interaction in ("refract", "tir")}
        index_of["object.index"] = sysm.object_material
        return np.array([float(index_of[n].index(lam)) if n in index_of else v for n, v, _ in self.table],
                        dtype=np.float64)

    def rows(self, wavelength_nm: float | None = None) -> list[tuple[str, float, str]]:
        """The table with each index evaluated at ``wavelength_nm`` (default: the primary)."""
        return [(n, float(v), u) for (n, _, u), v in zip(self.table, self.values(wavelength_nm))]

    # ------------------------------------------------------------- surfaces
    def owner(self, i: int) -> int:
        """Index of the surface whose frame and shape surface ``i`` uses (its ``same_as``)."""
        s = self.system.surfaces[i]
        return s.same_as if s.same_as is not None else i

    def shape(self, i: int, get: Callable[[str], object], const: Callable[[float], object] = _identity):
        """Surface ``i``'s :class:`Shape` (its owner's coefficients), each read by ``get(name)``;
        ``const`` wraps the fixed normalization 1/R_n (e.g. as an opaque scalar)."""
        from .surfaces import Shape  # Dr.Jit only where shapes are built

        o = self.system.surfaces[self.owner(i)]
        return Shape(c=get(f"{o.name}.curvature"), k=get(f"{o.name}.conic"),
                     asphere={k: get(f"{o.name}.A{k}") for k in o.asphere},
                     xy={ij: get(f"{o.name}.x{ij[0]}y{ij[1]}") for ij in o.xy},
                     inv_norm=const(1.0 / o.norm_radius))

    def lenslet_centre(self, array: str, m, n, get: Callable[[str], object],
                       const: Callable[[float], object] = _identity):
        """Axis (x, y) of lenslet (m, n) of ``array`` in its surfaces' local frames (Eq. 1):
        ``center + (m − (M−1)/2)·pitch_x``, likewise in y; m, n 0-based (arrays allowed).
        ``const`` wraps the count-dependent offsets (M−1)/2, (N−1)/2."""
        a = self.system.arrays[array]
        x = get(f"{array}.center_x") + (m - const(0.5 * (a.m - 1))) * get(f"{array}.pitch_x")
        y = get(f"{array}.center_y") + (n - const(0.5 * (a.n - 1))) * get(f"{array}.pitch_y")
        return x, y

    def _media(self) -> list[str]:
        """Index parameter of the medium *before* each surface, plus the final medium."""
        cur = "object.index"
        out = []
        for s in self.system.surfaces:
            out.append(cur)
            if s.interaction == "refract":
                cur = f"{s.name}.index"
        out.append(cur)
        return out

    def numpy_getter(self, values) -> Callable[[str], float]:
        """``get(name)`` reading one block of a numpy vector."""
        v = np.asarray(values, dtype=np.float64)
        return lambda name: float(v[self.index[name]])
