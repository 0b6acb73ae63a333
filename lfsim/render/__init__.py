"""Mitsuba 3 rendering of InI-HMD designs: optics meshes, display emitter, eye
sensor, elemental images and retinal focal stacks.

All scenes are in millimetres, in the design's global frame (light travels +z
from the microdisplay toward the eye). Visual space — the content scene and the
eye — uses the viewing-window frame: origin at the viewing-window centre, +z
along the line of sight toward the eye, +x to the viewer's right, +y up; the
eye looks along −z, so a point at distance d in front of the eye is at
z = −d.
"""

from __future__ import annotations

from ..backend import mitsuba

__all__ = ["mitsuba"]
