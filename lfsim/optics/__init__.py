"""Optics: surfaces, frames, materials, the sequential tracer, first-order optics."""

from .materials import Material
from .materials import lookup as material
from .prescription import Aperture, LensletArray, Surface, System

__all__ = ["Aperture", "LensletArray", "Material", "Surface", "System", "material"]


def __getattr__(name):  # the tracer imports Dr.Jit: load it only when asked for
    if name in ("SequentialTracer", "Status", "RayState", "TraceOutput"):
        from . import tracer

        return getattr(tracer, name)
    raise AttributeError(name)
