"""The :class:`Design` object: a loaded design file and its numpy-facing API."""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..optics.prescription import System
from .errors import surface_names
from .loader import ini_from_dict, load_system, optimize_from_dict, system_from_dict


@dataclass
class TraceResult:
    """Rays at the last surface (numpy, global frame).

    Attributes
    ----------
    positions, directions : (N, 3) float64
    status : (N,) int, 0 = reached the last surface (see ``lfsim.optics.Status``)
    opl : (N,) optical path length from the ray origin, mm
    failed_at : (N,) index into ``design.surfaces`` of the first failure, −1 if none
    lenslet : (N, 2) lenslet (m, n) of the first lenslet array, −1 if none
    path : (S, N, 3) hit points at every surface, when ``record=True``
    """

    positions: np.ndarray
    directions: np.ndarray
    status: np.ndarray
    opl: np.ndarray
    failed_at: np.ndarray
    lenslet: np.ndarray
    path: np.ndarray | None = None


def _as_rays(name, a, check: bool = True) -> np.ndarray:
    arr = np.asarray(a, dtype=np.float64)
    if arr.ndim == 1 and arr.shape[0] == 3:
        arr = arr[None, :]
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise ValueError(f"{name} must be an (N, 3) array, got shape {arr.shape}")
    if check and not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} contains non-finite values")
    return arr


def _check_directions(d: np.ndarray, n2: np.ndarray | None = None) -> None:
    """Finite and nonzero rows, by one pass over |d|² (``n2``, computed by the trace
    kernel when given), exact checks only when it flags a row."""
    if n2 is None:
        n2 = np.einsum("ij,ij->i", d, d)
    if np.all(np.isfinite(n2)) and np.all(n2 > 0.0):
        return
    if not np.all(np.isfinite(d)):
        raise ValueError("directions contains non-finite values")
    if not np.all(np.any(d != 0.0, axis=1)):
        raise ValueError("directions contain a zero vector")


class Design:
    """A validated design: its optics :class:`System` plus the raw file table."""

    def __init__(self, system: System, raw: dict | None = None, path: str | None = None):
        self.system = system
        self.raw = raw or {}
        self.path = path
        self._tracers: dict = {}
        with surface_names(self.raw):
            #: The validated ``[ini]`` section (:class:`IniSpec`), None for a plain lens.
            self.ini = ini_from_dict(self.raw, system, path or "<dict>")
            #: The validated ``[optimize]`` section (:class:`OptimizeSpec`), None when absent.
            self.optimize = optimize_from_dict(self.raw, system, self.ini, path or "<dict>")

    @classmethod
    def from_dict(cls, data: dict, file: str = "<dict>") -> Design:
        return cls(system_from_dict(data, file), data, file)

    # ------------------------------------------------------------ properties
    @property
    def name(self) -> str:
        return self.system.name

    @property
    def surfaces(self):
        return self.system.surfaces

    def wavelength(self, wavelength_nm: float | None = None) -> float:
        """``wavelength_nm`` (default: the primary), checked against every medium's data range.

        Raises ``ValueError`` (one line naming the file, the value and the
        medium) where a dispersion formula would be extrapolated.
        """
        if wavelength_nm is None:
            return float(self.system.primary_wavelength_nm)
        lam = float(wavelength_nm)
        where = self.path or "<dict>"
        if not (math.isfinite(lam) and lam > 0):
            raise ValueError(f"{where}: wavelength_nm = {wavelength_nm!r}: must be a positive number")
        media = [("object.material", self.system.object_material)] + [
            (f"surfaces[{i}].material", s.material) for i, s in enumerate(self.surfaces)]
        for key, m in media:
            if not m.in_range(lam):
                raise ValueError(f"{where}: wavelength_nm = {lam:g}: {key} {m.name} has dispersion data "
                                 f"for {m.range_nm[0]:g}-{m.range_nm[1]:g} nm only")
        return lam

    def parameter_names(self) -> list[str]:
        return self.system.parameter_names()

    def parameters(self, wavelength_nm: float | None = None) -> list[tuple[str, float, str]]:
        """The design vector as ``(name, value, unit)`` rows, indices at ``wavelength_nm``
        (default: the primary wavelength); see :mod:`lfsim.optics.vector`."""
        from ..optics.vector import DesignVector

        return DesignVector(self.system).rows(self.wavelength(wavelength_nm))

    def tracer(self, precision: str = "float64", **kw):
        """The compiled :class:`~lfsim.optics.SequentialTracer` (cached per settings)."""
        from ..optics.tracer import SequentialTracer

        key = (precision, tuple(sorted(kw.items())))
        if key not in self._tracers:
            self._tracers[key] = SequentialTracer(self.system, precision, **kw)
        return self._tracers[key]

    # ----------------------------------------------------------------- trace
    def trace(self, origins, directions, wavelength_nm: float | None = None,
              precision: str = "float64", lenslet=None, record: bool = False) -> TraceResult:
        """Trace rays given in the design's global frame to the last surface.

        Parameters
        ----------
        origins, directions : array_like (N, 3)
            Ray starts (mm) and directions (normalized here; must be nonzero).
        wavelength_nm : float, optional
            Defaults to the system's primary wavelength.
        precision : {"float64", "float32"}
        lenslet : array_like (N, 2) of int, optional
            Lenslet (m, n) each ray goes through in the first lenslet array.
        record : bool
            Also return the hit point at every surface (``path``).
        """
        o = _as_rays("origins", origins)
        d = _as_rays("directions", directions, check=False)
        if o.shape != d.shape:
            raise ValueError(f"origins {o.shape} and directions {d.shape} differ in shape")
        lam = self.wavelength(wavelength_nm)
        if len(o) == 0:
            e3, e1 = np.zeros((0, 3)), np.zeros(0, dtype=np.int64)
            return TraceResult(e3, e3.copy(), e1, np.zeros(0), e1.copy(), np.zeros((0, 2), np.int64),
                               np.zeros((len(self.surfaces), 0, 3)) if record else None)
        lz = None
        if lenslet is not None:
            lz = np.asarray(lenslet)
            if lz.shape != (o.shape[0], 2) or not np.issubdtype(lz.dtype, np.integer):
                raise ValueError(f"lenslet must be an (N, 2) integer array, got {lz.shape} {lz.dtype}")
            if not self.system.arrays:
                raise ValueError("lenslet given but the design has no lenslet array")
        res = self.tracer(precision).trace_numpy(o, d, lam, lenslet=lz, record=record)
        # Checked after the launch, from the |d|² the kernel computed (the trace of a bad
        # row is discarded with the whole result).
        _check_directions(d, res.pop("direction_norm2"))
        return TraceResult(path=res.pop("path", None), **res)

    def first_order(self, wavelength_nm: float | None = None, method: str = "auto"):
        """First-order properties (see :func:`lfsim.optics.first_order.first_order`)."""
        from ..optics.first_order import first_order

        lam = self.wavelength(wavelength_nm)
        tracer = None if method == "paraxial" else self.tracer("float64")
        return first_order(self.system, lam, tracer=tracer, method=method)


def load(path: str | Path) -> Design:
    """Load and validate a design file (TOML). Raises :class:`DesignError`."""
    system, raw = load_system(path)
    return Design(system, raw, str(path))
