"""Field and pupil sampling for conventional (single-pupil) systems.

Rays are aimed paraxially: each ray passes through its point of the paraxial
entrance pupil (position and diameter from first-order optics). The x axis is
sagittal, y tangential; fields are along +y.
"""

from __future__ import annotations

import math

import numpy as np

from .first_order import FirstOrder
from .prescription import System


def pupil_grid(n: int, kind: str = "hexapolar") -> np.ndarray:
    """Normalized pupil coordinates (K, 2) inside the unit circle.

    ``kind``: "hexapolar" (n rings, 6·i points on ring i, plus the centre),
    "square" (n×n grid clipped to the circle), "fan_y" (n points on the y
    axis from −1 to 1), "fan_x".
    """
    if n < 1:
        raise ValueError(f"pupil sampling n must be >= 1, got {n}")
    if kind == "hexapolar":
        pts = [(0.0, 0.0)]
        for i in range(1, n + 1):
            r = i / n
            for k in range(6 * i):
                a = 2 * math.pi * k / (6 * i)
                pts.append((r * math.cos(a), r * math.sin(a)))
        return np.array(pts)
    if kind == "square":
        g = np.linspace(-1, 1, n) if n > 1 else np.zeros(1)
        X, Y = np.meshgrid(g, g)
        m = X**2 + Y**2 <= 1 + 1e-12
        return np.stack([X[m], Y[m]], axis=1)
    if kind in ("fan_y", "fan_x"):
        g = np.linspace(-1, 1, n) if n > 1 else np.zeros(1)
        z = np.zeros_like(g)
        return np.stack([z, g] if kind == "fan_y" else [g, z], axis=1)
    raise ValueError(f"unknown pupil sampling {kind!r}: hexapolar, square, fan_y, fan_x")


def _least_sag(system: System, ep: np.ndarray, d: np.ndarray) -> float:
    """The least rotationally symmetric sag (base conic and even asphere) of an untilted,
    undecentred first surface at the heights where the rays through ``ep`` along ``d`` cross
    its vertex plane (0 for any other first surface)."""
    s = system.surfaces[0]
    if any(s.tilt) or any(s.decenter) or s.global_position is not None:
        return 0.0
    t = -ep[:, 2] / d[:, 2]
    r2 = (ep[:, 0] + t * d[:, 0]) ** 2 + (ep[:, 1] + t * d[:, 1]) ** 2
    c, k = s.curvature, s.conic
    arg = np.maximum(1.0 - (1.0 + k) * c * c * r2, 0.0)
    z = c * r2 / (1.0 + np.sqrt(arg)) + sum(a * r2 ** (o // 2) for o, a in s.asphere.items())
    return float(min(np.min(z), 0.0))


def field_rays(system: System, fo: FirstOrder, field: float, pupil: np.ndarray,
               start_z: float | None = None):
    """Origins and directions (global) of rays of one field through pupil points.

    ``field`` is an angle (deg) or an object height (mm) per the system's
    field type. Origins lie on the plane ``start_z`` (default: 1 mm before
    the first vertex, the entrance pupil or the first surface where these
    rays cross it (a surface bulging toward the object), whichever is
    earliest; or at the object for a finite object).
    """
    a = 0.5 * fo.entrance_pupil_diameter
    z_ep = fo.entrance_pupil_position
    ep = np.stack([pupil[:, 0] * a, pupil[:, 1] * a, np.full(len(pupil), z_ep)], axis=1)
    if math.isinf(system.object_distance):
        th = math.radians(field)
        d = np.tile([0.0, math.sin(th), math.cos(th)], (len(pupil), 1))
        z0 = min(0.0, z_ep, _least_sag(system, ep, d)) - 1.0 if start_z is None else start_z
        t = (z0 - ep[:, 2]) / d[:, 2]
        o = ep + t[:, None] * d
    else:
        o = np.tile([0.0, field, -system.object_distance], (len(pupil), 1))
        d = ep - o
        d /= np.linalg.norm(d, axis=1, keepdims=True)
    return o, d
