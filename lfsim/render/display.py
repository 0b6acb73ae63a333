"""The microdisplay: its pixel grid, the elemental-image layout, and its Mitsuba emitter.

The display is the object plane of the design (``z = −g`` in the global frame,
emitting toward +z). It has ``M·Nx × N·Ny`` pixels of pitch ``pixel_pitch``
(M×N lenslets, Nx×Ny pixels per elemental image), centred on the lenslet
array's axis. Images of the display are stored as arrays ``(H, W, 3)`` with
row 0 at the top (+y) and column 0 at the left (−x), as seen from the lenslet
side. Each pixel belongs to the elemental image whose centre (from the InI
model: its paraxial chief ray through the lenslet's stop centre crosses the
viewing-window centre, Eq. 2) is nearest, i.e. to that lenslet.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


def check_display_size(model, k: int, p_ei) -> None:
    """The display (M·px × N·py pixels of ``pixel_pitch``) must hold the M × N elemental
    images the optics lay out (pitch ``p_ei`` from Eq. 2, CDP state ``k``).

    The EI pitch may differ a little from ``pixels_per_ei × pixel_pitch`` (it
    changes with the tunable lens's power when the lens is not at a pupil), so
    the outer EIs are cut or widened by a few pixels; more than half an EI of
    mismatch at the display's edge, ``M·|p_EI − px·pitch| > p_EI``, means an
    outer elemental image falls off the display (or the display holds a whole
    EI for no lenslet): a :class:`~lfsim.design.DesignError` on
    ``ini.pixels_per_ei``.
    """
    from ..design.errors import DesignError

    spec, arr = model.spec, model.arr
    _, have = model.display_ei()
    mismatch = model.display_mismatch(np.asarray(p_ei, dtype=np.float64))
    for i in range(2):
        if not mismatch[i] <= 1.0:
            raise DesignError(
                model.file, "ini.pixels_per_ei", list(spec.pixels_per_ei),
                f"{arr.m} x {arr.n} elemental images of {abs(p_ei[0]):.5g} x {abs(p_ei[1]):.5g} mm "
                f"(Eq. 2, CDP {model.depths[k]:g} D) need a display of {arr.m * abs(p_ei[0]):.5g} x "
                f"{arr.n * abs(p_ei[1]):.5g} mm; {spec.pixels_per_ei[0]} x {spec.pixels_per_ei[1]} px of "
                f"{spec.pixel_pitch:g} mm per elemental image make {arr.m * have[0]:.5g} x {arr.n * have[1]:.5g} mm")


@dataclass
class DisplayLayout:
    """Pixel grid and elemental-image layout of one CDP state (lengths mm)."""

    width: int  # pixels along x
    height: int  # pixels along y
    pixel_pitch: float
    center: tuple[float, float]  # display centre (global x, y)
    z: float  # display plane (global z)
    m: int  # lenslets along x
    n: int  # lenslets along y
    ei_origin: np.ndarray  # (2,) centre of EI (0, 0)
    ei_basis: np.ndarray  # (2, 2) columns: EI-centre steps for m + 1 and n + 1

    @classmethod
    def from_model(cls, model, k: int = 0) -> DisplayLayout:
        """Layout of CDP state ``k`` of an :class:`~lfsim.ini.model.IniModel`."""
        spec, arr = model.spec, model.arr
        c = model.ei_centers(k, np.array([0, 1, 0]), np.array([0, 0, 1]))
        basis = np.stack([c[1] - c[0], c[2] - c[0]], axis=1)
        check_display_size(model, k, (basis[0, 0], basis[1, 1]))
        return cls(width=int(arr.m * spec.pixels_per_ei[0]), height=int(arr.n * spec.pixels_per_ei[1]),
                   pixel_pitch=float(spec.pixel_pitch), center=(float(arr.center[0]), float(arr.center[1])),
                   z=-float(model.g), m=int(arr.m), n=int(arr.n), ei_origin=c[0], ei_basis=basis)

    @property
    def size_mm(self) -> tuple[float, float]:
        return self.width * self.pixel_pitch, self.height * self.pixel_pitch

    def pixel_centers(self) -> np.ndarray:
        """(H, W, 2) global (x, y) of every pixel centre (row 0 at +y)."""
        p = self.pixel_pitch
        x = self.center[0] + (np.arange(self.width) + 0.5 - 0.5 * self.width) * p
        y = self.center[1] + (0.5 * self.height - np.arange(self.height) - 0.5) * p
        X, Y = np.meshgrid(x, y)
        return np.stack([X, Y], axis=-1)

    def lenslet_of(self, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Lenslet (m, n) (0-based) whose elemental image holds display points ``xy`` (..., 2)."""
        u = np.linalg.solve(self.ei_basis, (np.asarray(xy) - self.ei_origin).reshape(-1, 2).T).T
        m = np.clip(np.rint(u[:, 0]), 0, self.m - 1).astype(np.int32)
        n = np.clip(np.rint(u[:, 1]), 0, self.n - 1).astype(np.int32)
        shape = np.shape(xy)[:-1]
        return m.reshape(shape), n.reshape(shape)

    def emitter_dict(self, image: np.ndarray, scale: float = 1.0) -> dict:
        """Mitsuba dict of the display: a one-sided ``rectangle`` at ``z`` facing +z
        whose ``area`` emitter shows ``image`` (H, W, 3, linear RGB) at the
        physical pixel pitch (bilinear lookup, so positions stay differentiable)."""
        from . import mitsuba

        mi = mitsuba()
        img = np.asarray(image, dtype=np.float32)
        if img.shape[:2] != (self.height, self.width):
            raise ValueError(f"display image is {img.shape[1]}x{img.shape[0]} pixels, the display "
                             f"has {self.width}x{self.height}")
        if img.ndim == 2:
            img = np.repeat(img[..., None], 3, axis=-1)
        # Mitsuba's rectangle maps bitmap row 0 to local y = -1: flip so row 0 is +y.
        tex = mi.TensorXf(np.ascontiguousarray(img[::-1] * np.float32(scale)))
        w, h = self.size_mm
        T = mi.ScalarTransform4f
        to_world = T().translate([self.center[0], self.center[1], self.z]) @ T().scale([0.5 * w, 0.5 * h, 1.0])
        return {
            "type": "rectangle",
            "to_world": to_world,
            "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.0, 0.0, 0.0]}},
            "emitter": {"type": "area",
                        "radiance": {"type": "bitmap", "data": tex, "raw": True,
                                     "filter_type": "bilinear", "wrap_mode": "clamp"}},
        }
