"""Mitsuba scenes as content: any scene Mitsuba loads, placed in visual space.

A scene (an XML file, a Python dict or a loaded ``mi.Scene``) with its shapes,
BSDFs, textures and emitters is either already in visual-space millimetres
(the eye at the origin looking along −z, +x right, +y up) or placed there by a
content TOML's ``[scene]`` section::

    [scene]
    file = "tabletop.xml"          # relative to the TOML
    units = "mm"                   # the scene's length unit: mm, cm, m, in, or a number of mm
    rotate_deg = [0.0, 0.0, 0.0]   # rotations about x, then y, then z (degrees), after scaling
    translate_mm = [0.0, 0.0, 0.0] # then this shift (visual-space mm)
    max_depth = 8                  # path length of the path tracer (Mitsuba's max_depth)

The scene itself is never edited: lfsim maps its visual-space rays into the
scene's frame (a similarity transform, so angles, radiance and which surface
a ray meets do not change) and maps depths back by the scale.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..design.errors import DesignError

#: Millimetres per unit name.
UNITS = {"mm": 1.0, "cm": 10.0, "m": 1000.0, "in": 25.4}
#: Default path length: enough for a few diffuse bounces and glossy inter-reflections.
MAX_DEPTH = 8


def _rotation(deg) -> np.ndarray:
    """R = Rz·Ry·Rx of rotations (degrees) about x, then y, then z."""
    ax, ay, az = (math.radians(float(v)) for v in deg)
    cx, sx, cy, sy, cz, sz = math.cos(ax), math.sin(ax), math.cos(ay), math.sin(ay), math.cos(az), math.sin(az)
    Rx = np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]])
    Ry = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
    Rz = np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]])
    return Rz @ Ry @ Rx


@dataclass
class SceneSource:
    """A Mitsuba scene and where it sits in visual space.

    ``to_visual`` maps scene coordinates to visual-space mm:
    ``p_visual = scale · R · p_scene + t``.
    """

    file: str | None = None  # XML path (None: ``scene`` holds a dict or a loaded mi.Scene)
    scene: object = None
    scale: float = 1.0
    rotation: np.ndarray = field(default_factory=lambda: np.eye(3))
    translation: np.ndarray = field(default_factory=lambda: np.zeros(3))
    max_depth: int = MAX_DEPTH
    label: str = "<scene>"  # how errors name it
    _loaded: object = None

    @property
    def to_visual(self) -> np.ndarray:
        M = np.eye(4)
        M[:3, :3], M[:3, 3] = self.scale * self.rotation, self.translation
        return M

    @property
    def to_scene(self) -> np.ndarray:
        """Visual space → scene frame (4×4)."""
        M = np.eye(4)
        Rt = self.rotation.T / self.scale
        M[:3, :3], M[:3, 3] = Rt, -Rt @ self.translation
        return M

    @property
    def identity(self) -> bool:
        return bool(np.allclose(self.to_visual, np.eye(4), rtol=0, atol=1e-15))

    def rays_to_scene(self, origins: np.ndarray, directions: np.ndarray):
        """Visual-space rays (N, 3) in the scene frame (unit directions)."""
        if self.identity:
            return origins, directions
        Rt = self.rotation.T
        o = ((origins - self.translation) @ Rt.T) / self.scale
        return o, directions @ Rt.T

    def normals_to_visual(self, normals: np.ndarray) -> np.ndarray:
        return normals @ self.rotation.T

    def load(self):
        """The loaded ``mi.Scene`` (once), checked: it has an emitter and lies in front of the eye."""
        if self._loaded is None:
            from ..backend import mitsuba

            mi = mitsuba()
            if isinstance(self.scene, mi.Scene):
                scene = self.scene
            else:
                try:
                    scene = mi.load_file(self.file) if self.file is not None else mi.load_dict(self.scene)
                except Exception as e:  # Mitsuba raises RuntimeError/TypeError/ValueError with a long text
                    msg = " ".join(str(e).split())
                    raise DesignError(self.label, "", None, f"Mitsuba cannot load the scene: {msg[:300]}") from None
            self._check(scene)
            self._loaded = scene
        return self._loaded

    def _check(self, scene) -> None:
        if len(scene.emitters()) == 0:
            raise DesignError(self.label, "", None, "the scene has no emitter (an area light, an "
                              "environment or a constant background): it would render black")
        shapes = scene.shapes()
        if not shapes:
            return  # an environment alone: it surrounds the eye
        bb = scene.bbox()
        lo, hi = np.array(bb.min, dtype=np.float64), np.array(bb.max, dtype=np.float64)
        if not (np.all(np.isfinite(lo)) and np.all(np.isfinite(hi))):
            return
        corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
        zv = corners @ (self.scale * self.rotation).T + self.translation
        if zv[:, 2].min() >= 0.0:
            raise DesignError(self.label, "", None, "the scene lies behind the eye: in visual space (eye at "
                              "the origin looking along -z) its shapes span z = "
                              f"{zv[:, 2].min():.4g} to {zv[:, 2].max():.4g} mm; place it at z < 0 "
                              "(a [scene] rotate_deg / translate_mm) or check its units")


def units_mm(file: str, key: str, v) -> float:
    """A ``units`` value: a unit name of :data:`UNITS` or a positive number of mm."""
    if isinstance(v, str) and v in UNITS:
        return UNITS[v]
    if isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) and v > 0:
        return float(v)
    raise DesignError(file, key, v, f"unknown units: expected one of {', '.join(UNITS)} or a number of mm > 0")


def parse_scene_section(file: str, sec, base: Path) -> SceneSource:
    """The content TOML's ``[scene]`` table (module docstring)."""
    if not isinstance(sec, dict):
        raise DesignError(file, "scene", sec, "expected a table { file = ..., units = ... }")
    from .schema import no_unknown

    no_unknown(file, "scene.", sec, {"file", "units", "rotate_deg", "translate_mm", "max_depth"})
    src = sec.get("file")
    if not isinstance(src, str) or not src:
        raise DesignError(file, "scene.file", src, "expected a Mitsuba scene file (XML), relative to this file")
    full = (base / src).resolve()
    if not full.is_file():
        raise DesignError(file, "scene.file", src, f"no such file ({full})")
    if full.suffix.lower() != ".xml":
        raise DesignError(file, "scene.file", src, "expected a Mitsuba XML scene (.xml)")
    scale = units_mm(file, "scene.units", sec.get("units", "mm"))
    vecs = {}
    for key in ("rotate_deg", "translate_mm"):
        v = sec.get(key, [0.0, 0.0, 0.0])
        if not (isinstance(v, list) and len(v) == 3 and all(isinstance(x, (int, float)) and not isinstance(x, bool)
                                                           and math.isfinite(x) for x in v)):
            raise DesignError(file, f"scene.{key}", v, "expected three finite numbers [x, y, z]")
        vecs[key] = np.array(v, dtype=np.float64)
    depth = sec.get("max_depth", MAX_DEPTH)
    if isinstance(depth, bool) or not isinstance(depth, int) or depth < 1:
        raise DesignError(file, "scene.max_depth", depth, "expected an integer >= 1")
    return SceneSource(file=str(full), scale=scale, rotation=_rotation(vecs["rotate_deg"]),
                       translation=vecs["translate_mm"], max_depth=depth, label=str(full))
