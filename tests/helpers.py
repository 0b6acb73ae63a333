"""Test helpers: small designs and a programmatic path reversal."""

from __future__ import annotations

import copy
import math

import numpy as np

from lfsim.optics.prescription import Surface, System


def euler_xyz(R: np.ndarray) -> tuple[float, float, float]:
    """Angles (deg) with R = Rx(a)·Ry(b)·Rz(c)."""
    b = math.asin(max(-1.0, min(1.0, R[0, 2])))
    a = math.atan2(-R[1, 2], R[2, 2])
    c = math.atan2(-R[0, 1], R[0, 0])
    return tuple(math.degrees(v) for v in (a, b, c))


def reversed_system(system: System, frames, end_plane_z: float) -> System:
    """The same physical surfaces traversed backwards (image → first surface).

    Every surface is placed with ``global_position`` and Euler tilts taken
    from its forward frame; media are swapped so each refraction goes from
    the forward 'after' medium to the forward 'before' medium. The path ends
    on a dummy plane z = ``end_plane_z`` (global, untilted).
    """
    media = system.media()
    surf = system.surfaces
    out = []
    for i in range(len(surf) - 2, -1, -1):  # skip the image surface
        s = surf[i]
        if s.interaction == "break":
            continue
        owner = surf[s.same_as] if s.same_as is not None else s
        R, o = frames[i]
        r = Surface(
            name=f"r{i}",
            curvature=owner.curvature, conic=owner.conic,
            asphere=dict(owner.asphere), xy=dict(owner.xy), norm_radius=owner.norm_radius,
            interaction=s.interaction,
            material=media[i] if s.interaction == "refract" else s.material,
            aperture=copy.deepcopy(s.aperture),
            global_position=tuple(o), tilt=euler_xyz(R),
            array=s.array,
        )
        out.append(r)
    out.append(Surface(name="end", global_position=(0.0, 0.0, end_plane_z), interaction="none"))
    return System(surfaces=out, arrays=dict(system.arrays), object_material=media[-1],
                  wavelengths_nm=list(system.wavelengths_nm),
                  primary_wavelength_nm=system.primary_wavelength_nm)


def trace_np(tracer, o, d, values=None, wavelength_nm=None):
    """Trace numpy rays with a SequentialTracer; numpy results (p, d, status, opl)."""
    import drjit as dr

    P = tracer.params(wavelength_nm, values=values)
    with dr.suspend_grad():
        out = tracer.trace(P, tracer.rays(o, d))
    p = np.stack([np.asarray(out.p[i]) for i in range(3)], axis=1)
    dd = np.stack([np.asarray(out.d[i]) for i in range(3)], axis=1)
    return p, dd, np.asarray(out.status), np.asarray(out.opl)
