"""Plain-data description of a sequential optical system.

This is the seam between the design-file loader (``lfsim.design``) and the
tracer: no files, no Dr.Jit. Every design number the tracer can differentiate
is named by :meth:`System.parameter_table` (owned by :mod:`lfsim.optics.vector`).

Surface model (one for tracing, metrics and meshes), in the surface's local
frame with the vertex at the origin and +z the local axis::

    z(x, y) = c r² / (1 + sqrt(1 − (1 + k) c² r²))            base conic
            + Σ_{i=2..8} A_{2i} r^{2i}                          even asphere
            + Σ_{i+j≤10} c_ij (x/R_n)^i (y/R_n)^j               XY polynomial

with ``r² = x² + y²``, curvature ``c = 1/radius``, conic ``k`` and
normalization radius ``R_n``.

Frames (like a lens-design program's coordinate breaks): a surface's local
frame is the current frame, translated by ``decenter`` (x, y), then rotated by
``tilt`` (degrees, right-handed) as R = Rx·Ry·Rz: about x, then the rotated
y′, then the rotated z″ (intrinsic). If ``return_axis`` is true (default on a
surface; false by default on a coordinate break) the following surfaces
continue from the frame *before* the tilt/decenter; otherwise they follow the
tilted frame. ``thickness`` then moves the current frame along its own z. A
surface with ``global_position`` ignores the chain: it is placed at that
point of the global frame, its ``tilt`` (same order) taken from the global
axes and its ``decenter`` along its own tilted x and y. A surface with ``same_as`` reuses the
frame and shape of an earlier one (a physical surface met twice, e.g. a
prism face used first in total internal reflection and then in refraction).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from .materials import AIR, Material

#: Allowed even-asphere orders.
ASPHERE_ORDERS = (4, 6, 8, 10, 12, 14, 16)
#: Highest total order of XY-polynomial terms.
XY_MAX_ORDER = 10

#: How a surface acts on a ray: refract into ``material``; reflect (mirror);
#: reflect by total internal reflection against ``material`` (failing rays are
#: flagged); "none" (a dummy surface: intersected, direction unchanged);
#: "break" (a coordinate break: only changes the frame, not intersected);
#: "paraxial" (an ideal thin lens of power ``power`` on a plane, same medium).
INTERACTIONS = ("refract", "reflect", "tir", "none", "break", "paraxial")


@dataclass
class Aperture:
    """A clear aperture in the surface's local (x, y); ``kind`` circular or rectangular."""

    kind: str
    radius: float = 0.0
    half_width: tuple[float, float] = (0.0, 0.0)
    decenter: tuple[float, float] = (0.0, 0.0)

    def extent(self) -> float:
        """Largest distance from the vertex axis any point of the aperture reaches."""
        dx, dy = self.decenter
        if self.kind == "circular":
            return math.hypot(dx, dy) + self.radius
        hx, hy = self.half_width
        return math.hypot(abs(dx) + hx, abs(dy) + hy)


@dataclass
class Surface:
    name: str
    curvature: float = 0.0
    conic: float = 0.0
    asphere: dict[int, float] = field(default_factory=dict)
    xy: dict[tuple[int, int], float] = field(default_factory=dict)
    norm_radius: float = 1.0
    thickness: float = 0.0
    material: Material = AIR  # medium after the surface
    interaction: str = "refract"
    aperture: Aperture | None = None
    semi_diameter: float | None = None
    stop: bool = False
    decenter: tuple[float, float] = (0.0, 0.0)
    tilt: tuple[float, float, float] = (0.0, 0.0, 0.0)
    return_axis: bool = True
    global_position: tuple[float, float, float] | None = None
    same_as: int | None = None  # index of an earlier surface whose frame and shape are reused
    array: str | None = None  # lenslet-array group name
    power: float = 0.0  # ideal-lens power (1/mm) of a "paraxial" surface
    virtual: bool = False  # deliberate virtual geometry: may cross its neighbours

    @property
    def is_plane(self) -> bool:
        return self.curvature == 0.0 and not self.asphere and not self.xy

    @property
    def needs_newton(self) -> bool:
        return bool(self.asphere) or bool(self.xy)


@dataclass
class LensletArray:
    """A group of consecutive surfaces repeated on an M×N grid.

    Lenslet (m, n), m = 0..M−1 along x and n = 0..N−1 along y, has its vertex
    axis at ``center + ((m − (M−1)/2)·pitch_x, (n − (N−1)/2)·pitch_y)`` in the
    local frame of each surface of the group, and owns the cell
    ``|x − x_m| ≤ pitch_x/2, |y − y_n| ≤ pitch_y/2``.
    """

    name: str
    m: int
    n: int
    pitch: tuple[float, float]
    center: tuple[float, float] = (0.0, 0.0)


@dataclass
class System:
    """A sequential system; the last surface is the image surface."""

    surfaces: list[Surface]
    arrays: dict[str, LensletArray] = field(default_factory=dict)
    object_distance: float = math.inf  # from the object to the first surface vertex
    object_material: Material = AIR
    aperture_type: str = "epd"  # "epd" (mm), "fno" (image-space F/#), "na" (object-space NA)
    aperture_value: float = 0.0
    field_type: str = "angle"  # "angle" (deg) or "height" (mm, object)
    fields: list[float] = field(default_factory=lambda: [0.0])
    wavelengths_nm: list[float] = field(default_factory=lambda: [587.5618])
    primary_wavelength_nm: float = 587.5618
    name: str = ""

    # ------------------------------------------------------------------ media
    def media(self) -> list[Material]:
        """Medium *before* each surface (list of len(surfaces)) plus the final medium."""
        out = [self.object_material]
        for s in self.surfaces:
            out.append(s.material if s.interaction == "refract" else out[-1])
        return out

    @property
    def stop_index(self) -> int | None:
        idx = [i for i, s in enumerate(self.surfaces) if s.stop]
        return idx[0] if idx else None

    def array_groups(self) -> dict[str, list[int]]:
        """Surface indices of each lenslet-array group (consecutive)."""
        groups: dict[str, list[int]] = {}
        for i, s in enumerate(self.surfaces):
            if s.array is not None:
                groups.setdefault(s.array, []).append(i)
        return groups

    # ------------------------------------------------------------- parameters
    def parameter_table(self) -> list[tuple[str, float, str]]:
        """Every differentiable design number: ``(name, value, unit)``
        (:func:`lfsim.optics.vector.parameter_table`)."""
        from .vector import parameter_table

        return parameter_table(self)

    def parameter_names(self) -> list[str]:
        return [r[0] for r in self.parameter_table()]

    def parameter_values(self, wavelength_nm: float) -> list[float]:
        """Values of :meth:`parameter_table` with indices evaluated at ``wavelength_nm``."""
        from .vector import DesignVector

        return DesignVector(self).values(wavelength_nm).tolist()
