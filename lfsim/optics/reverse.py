"""The same physical surfaces traversed backwards (light from the image side).

A display simulator looks at the optics from the eye: a ray that leaves the
viewing window toward the eyepiece meets the design's surfaces in reverse
order and ends on the object (display) plane. :func:`reversed_system` builds
that path as an ordinary sequential :class:`System`, so the tracer that
computes the metrics also renders (one surface model, no second description).
"""

from __future__ import annotations

import copy
import math

import numpy as np

from .prescription import Surface, System


def euler_xyz(R: np.ndarray) -> tuple[float, float, float]:
    """Angles (deg) (a, b, c) with ``R = Rx(a)·Ry(b)·Rz(c)`` (the tracer's tilt order)."""
    b = math.asin(max(-1.0, min(1.0, float(R[0, 2]))))
    a = math.atan2(-R[1, 2], R[2, 2])
    c = math.atan2(-R[0, 1], R[0, 0])
    return tuple(math.degrees(v) for v in (a, b, c))


def reversed_system(system: System, frames, end_plane_z: float, first: int = 0,
                    last: int | None = None, powers: dict[str, float] | None = None) -> System:
    """Surfaces ``last..first`` of ``system`` (default: all but the image surface), backwards.

    Every surface keeps its name, shape, aperture and lenslet-array group and
    is placed with ``global_position`` and the Euler tilts of its forward
    frame (``frames[i] = (R, o)``, e.g. from
    :meth:`~lfsim.optics.tracer.SequentialTracer.frames_numpy` of one
    parameter block). Media are swapped so each refraction goes from the
    forward 'after' medium to the forward 'before' one; mirrors and total
    internal reflection stay what they are, and a ``same_as`` surface becomes
    a copy of its original's shape in its own (shared) frame. The path ends on
    the untilted plane ``z = end_plane_z`` of the global frame (the display).

    ``powers``: ideal-lens powers (1/mm) by surface name, overriding the
    prescription's (a tunable lens's power in one CDP state).
    """
    media = system.media()
    surf = system.surfaces
    last = len(surf) - 2 if last is None else last
    powers = powers or {}
    out = []
    for i in range(last, first - 1, -1):
        s = surf[i]
        if s.interaction == "break":
            continue
        owner = surf[s.same_as] if s.same_as is not None else s
        R, o = frames[i]
        out.append(Surface(
            name=s.name,
            curvature=owner.curvature, conic=owner.conic,
            asphere=dict(owner.asphere), xy=dict(owner.xy), norm_radius=owner.norm_radius,
            interaction=s.interaction,
            # refraction back into the forward 'before' medium; a TIR surface's
            # material is the medium outside it, unchanged
            material=media[i] if s.interaction == "refract" else s.material,
            aperture=copy.deepcopy(s.aperture),
            global_position=tuple(float(v) for v in o), tilt=euler_xyz(R),
            array=s.array,
            power=float(powers.get(s.name, s.power)),
        ))
    out.append(Surface(name="end", global_position=(0.0, 0.0, float(end_plane_z)), interaction="none"))
    return System(surfaces=out, arrays=dict(system.arrays), object_material=media[last + 1],
                  wavelengths_nm=list(system.wavelengths_nm),
                  primary_wavelength_nm=system.primary_wavelength_nm, name=f"{system.name} (reversed)")
