"""Content scene files: the 3D scene an InI-HMD shows, in visual space.

Visual space is the viewing-window frame (see :mod:`lfsim.render`): origin at
the viewing-window centre, the eye looks along −z, +x to the viewer's right,
+y up, millimetres; a point d mm in front of the eye is at z = −d. Objects are
self-luminous textured quads (their radiance is the texture), so a render has
no lighting noise and the natural view is the exact ground truth::

    name = "slanted wall"
    [view]                       # defaults for renders of this content (all optional;
                                 # unset keys take ContentView's defaults, shown here)
    design = "ini_coaxial.toml"  # path relative to this file
    cdp_mm = 750.0               # CDP depth the display state is set to (inf allowed)
    focus_mm = [600.0, 1000.0, 1400.0]
    pupil_diameter = 3.0
    background = [0.0, 0.0, 0.0] # radiance where a ray meets no object
    [display]                    # optional: the microdisplay's primaries in spectral renders
    primaries = { R = { peak_nm = 620.0, fwhm_nm = 35.0 },     # Gaussian, or tabulated:
                  G = { wavelengths_nm = [...], values = [...] }, B = { ... } }
    [[objects]]
    type = "quad"
    corners = [[x0, y0, z0], [x1, y1, z1], [x2, y2, z2]]  # origin, +u end, +v end
    texture = { type = "noise", feature_mm = 3.0, seed = 1 }
    radiance = 1.0               # scale (or [r, g, b])

Texture types: ``constant`` (1, so the quad shows its ``radiance``), ``noise``
(binary band-limited noise, ``feature_mm``, ``seed``, ``texel_mm``), ``checker``
(``period_mm``), ``bars`` (vertical bars, ``period_mm``), ``image`` (``path`` relative to the file, PNG/JPEG/EXR,
sRGB decoded to linear). The quad's u axis runs along the texture's columns
(left to right), v along its rows (bottom to top); its front (u × v) must
face the eye.
"""

from __future__ import annotations

import math
import tomllib
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..design.errors import DesignError

TEXTURES = ("constant", "noise", "checker", "bars", "image")


@dataclass
class Texture:
    kind: str
    params: dict


@dataclass
class Quad:
    name: str
    corners: np.ndarray  # (3, 3): origin, +u end, +v end
    texture: Texture
    radiance: tuple[float, float, float]

    @property
    def u(self) -> np.ndarray:
        return self.corners[1] - self.corners[0]

    @property
    def v(self) -> np.ndarray:
        return self.corners[2] - self.corners[0]


@dataclass(frozen=True)
class ContentView:
    """A content file's ``[view]``: how its renders look by default.

    The field defaults are the one statement of lfsim's view defaults: the
    render specs (``FocalStackSpec``, ``ViewSpec``), the CLI verbs and
    ``lfsim regress`` all start from them. ``design`` is an absolute path or None.
    """

    design: str | None = None
    cdp_mm: float = 750.0  # CDP depth the display state is set to (inf allowed)
    focus_mm: tuple[float, ...] = (600.0, 1000.0, 1400.0)
    pupil_diameter_mm: float = 3.0


#: lfsim's view defaults (a ``[view]`` that sets nothing).
VIEW_DEFAULTS = ContentView()


@dataclass
class ContentScene:
    """A loaded content file: quads and RGB-D objects (self-luminous, exact), or a Mitsuba scene
    (``scene``, path-traced)."""

    path: str
    name: str
    objects: list  # Quad and RgbdObject (lfsim.content.rgbd); empty for a Mitsuba scene
    background: tuple[float, float, float] = (0.0, 0.0, 0.0)
    view: ContentView = VIEW_DEFAULTS
    #: Display primaries of spectral renders ({"R", "G", "B"}: lfsim.render.spectra.Primary);
    #: None: the default OLED microdisplay's.
    primaries: dict | None = None
    #: A Mitsuba scene (lfsim.content.mitsuba_scene.SceneSource); None: the objects above.
    scene: object = None

    @property
    def path_traced(self) -> bool:
        """True for a Mitsuba scene (lit surfaces: path-traced, with noise); False for
        self-luminous objects (the emitted radiance of the first hit: exact)."""
        return self.scene is not None

    def mitsuba_scene(self):
        """The content as a loaded ``mi.Scene`` (once per ContentScene), in its own frame
        (:attr:`to_scene` maps visual space into it)."""
        if self.scene is not None:
            return self.scene.load()
        if getattr(self, "_mi_scene", None) is None:
            from ..backend import mitsuba
            from .quads import scene_dict

            self._mi_scene = mitsuba().load_dict(scene_dict(self))
        return self._mi_scene

    def rays_to_scene(self, origins: np.ndarray, directions: np.ndarray):
        """Visual-space rays (N, 3) in the Mitsuba scene's frame (unchanged for objects)."""
        return (origins, directions) if self.scene is None else self.scene.rays_to_scene(origins, directions)

    def first_surface(self, origins: np.ndarray, directions: np.ndarray, valid=None):
        """``(distance mm (N,), visual-space unit normal (N, 3))`` of the first content surface along
        visual-space rays: inf / 0 where a ray meets nothing, 0 / 0 where ``valid`` is False."""
        from .pathtrace import surface_aovs

        so, sd = self.rays_to_scene(origins, directions)
        ok = np.ones(len(origins), dtype=bool) if valid is None else valid
        if self.scene is None:
            return surface_aovs(self.mitsuba_scene(), so, sd, ok)
        return surface_aovs(self.mitsuba_scene(), so, sd, ok, self.scene.scale, self.scene.normals_to_visual)

    @property
    def to_scene(self) -> np.ndarray:
        """Visual space → the Mitsuba scene's frame (4×4; identity for objects)."""
        return np.eye(4) if self.scene is None else self.scene.to_scene


def _primaries(file, data) -> dict | None:
    """The ``[display]`` section: ``primaries = { R = {...}, G = {...}, B = {...} }``, each a
    Gaussian ``{ peak_nm, fwhm_nm }`` or a table ``{ wavelengths_nm = [...], values = [...] }``."""
    from ..render.spectra import CHANNELS, Primary

    disp = data.get("display")
    if disp is None:
        return None
    if not isinstance(disp, dict):
        raise DesignError(file, "display", disp, "expected a table")
    unknown = set(disp) - {"primaries"}
    if unknown:
        k = sorted(unknown)[0]
        raise DesignError(file, f"display.{k}", disp[k], "unknown key")
    prim = disp.get("primaries")
    if not isinstance(prim, dict) or set(prim) != set(CHANNELS):
        raise DesignError(file, "display.primaries", prim, "expected a table with R, G and B spectra")
    out = {}
    for c in CHANNELS:
        t = prim[c]
        key = f"display.primaries.{c}"
        if not isinstance(t, dict) or set(t) not in ({"peak_nm", "fwhm_nm"}, {"wavelengths_nm", "values"}):
            raise DesignError(file, key, t, "expected { peak_nm, fwhm_nm } or { wavelengths_nm = [...], "
                              "values = [...] }")
        try:
            if "peak_nm" in t:
                out[c] = Primary(peak_nm=t["peak_nm"], fwhm_nm=t["fwhm_nm"])
            else:
                lam, val = t["wavelengths_nm"], t["values"]
                if not (isinstance(lam, list) and isinstance(val, list)):
                    raise ValueError("wavelengths_nm and values must be lists of numbers")
                out[c] = Primary(wavelengths_nm=tuple(lam), values=tuple(val))
        except (ValueError, TypeError) as e:
            raise DesignError(file, key, t, str(e)) from None
    med = {c: float(out[c].quantiles([0.5])[0]) for c in CHANNELS}
    if not med["B"] < med["G"] < med["R"]:
        raise DesignError(file, "display.primaries", prim,
                          "the median wavelengths must rise from B to G to R (here R "
                          f"{med['R']:.0f} nm, G {med['G']:.0f} nm, B {med['B']:.0f} nm): are channels swapped?")
    return out


def no_unknown(file, prefix: str, table: dict, allowed) -> None:
    """A one-line error for the first key of ``table`` not in ``allowed`` (``prefix``: its dotted path)."""
    unknown = set(table) - set(allowed)
    if unknown:
        k = sorted(unknown)[0]
        raise DesignError(file, f"{prefix}{k}", table[k], "unknown key")


def _num(file, key, v, positive=False, allow_inf=False):
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        raise DesignError(file, key, v, "expected a number")
    v = float(v)
    if math.isnan(v) or (math.isinf(v) and not allow_inf):
        raise DesignError(file, key, v, "expected a finite number")
    if positive and not v > 0:
        raise DesignError(file, key, v, "expected a number > 0")
    return v


def _rgb(file, key, v):
    if isinstance(v, (int, float)) and not isinstance(v, bool):
        v = [v, v, v]
    if not isinstance(v, list) or len(v) != 3:
        raise DesignError(file, key, v, "expected a number or [r, g, b]")
    out = tuple(_num(file, f"{key}[{i}]", x) for i, x in enumerate(v))
    if min(out) < 0:
        raise DesignError(file, key, v, "radiance must be >= 0")
    return out


def _texture(file, key, t, base: Path) -> Texture:
    if not isinstance(t, dict):
        raise DesignError(file, key, t, "expected a table { type = ... }")
    kind = t.get("type")
    if kind not in TEXTURES:
        raise DesignError(file, f"{key}.type", kind, f"expected one of {', '.join(TEXTURES)}")
    p = {}
    if kind == "noise":
        p["feature_mm"] = _num(file, f"{key}.feature_mm", t.get("feature_mm", 3.0), positive=True)
        p["texel_mm"] = _num(file, f"{key}.texel_mm", t.get("texel_mm", p["feature_mm"] / 4), positive=True)
        seed = t.get("seed", 0)
        if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:
            raise DesignError(file, f"{key}.seed", seed, "expected an integer >= 0")
        p["seed"] = seed
    elif kind == "constant":
        pass
    elif kind in ("checker", "bars"):
        p["period_mm"] = _num(file, f"{key}.period_mm", t.get("period_mm", 10.0), positive=True)
    else:
        src = t.get("path")
        if not isinstance(src, str):
            raise DesignError(file, f"{key}.path", src, "expected an image file path")
        full = (base / src).resolve()
        if not full.is_file():
            raise DesignError(file, f"{key}.path", src, f"no such file ({full})")
        p["path"] = str(full)
    unknown = set(t) - set(p) - {"type"}
    if unknown:
        raise DesignError(file, f"{key}.{sorted(unknown)[0]}", t[sorted(unknown)[0]], "unknown key")
    return Texture(kind, p)


def load_content(path: str | Path) -> ContentScene:
    """Load and validate a content file (errors name file, key and value): a content TOML
    (objects, or a ``[scene]``), or a Mitsuba XML scene in visual-space millimetres."""
    path = Path(path)
    file = str(path)
    if not path.is_file():
        raise DesignError(file, "", None, "content file not found")
    if path.suffix.lower() == ".xml":
        from .mitsuba_scene import SceneSource

        src = SceneSource(file=str(path.resolve()), label=file)
        content = ContentScene(file, path.stem, [], scene=src)
        content.mitsuba_scene()  # load and check now: a bad scene fails before any work
        return content
    try:
        data = tomllib.loads(path.read_text())
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as e:
        raise DesignError(file, "", None, f"not valid TOML ({e})") from None
    return content_from_dict(data, file, path.parent)


def content_from_dict(data: dict, file: str = "<dict>", base: Path = Path(".")) -> ContentScene:
    unknown = set(data) - {"name", "description", "view", "display", "objects", "scene"}
    if unknown:
        k = sorted(unknown)[0]
        raise DesignError(file, k, data[k], "unknown key (expected name, description, view, display, objects "
                          "or scene)")
    objs = data.get("objects")
    src = None
    if "scene" in data:
        from .mitsuba_scene import parse_scene_section

        if objs is not None:
            raise DesignError(file, "objects", objs, "a content file holds a [scene] or [[objects]], not both "
                              "(add the objects to the Mitsuba scene)")
        src = parse_scene_section(file, data["scene"], base)
        objs = []
    elif not isinstance(objs, list) or not objs:
        raise DesignError(file, "objects", objs, "expected at least one [[objects]] table, or a [scene]")
    out = []
    for i, o in enumerate(objs):
        key = f"objects[{i}]"
        if not isinstance(o, dict):
            raise DesignError(file, key, o, "expected a table")
        if o.get("type", "quad") == "rgbd":
            from .rgbd import parse_rgbd

            out.append(parse_rgbd(file, key, o, base, i))
            continue
        if o.get("type", "quad") != "quad":
            raise DesignError(file, f"{key}.type", o.get("type"), "expected \"quad\" or \"rgbd\"")
        c = o.get("corners")
        if not (isinstance(c, list) and len(c) == 3 and all(isinstance(r, list) and len(r) == 3 for r in c)):
            raise DesignError(file, f"{key}.corners", c, "expected three [x, y, z] points (mm)")
        C = np.array([[_num(file, f"{key}.corners[{a}][{b}]", c[a][b]) for b in range(3)] for a in range(3)])
        u, v = C[1] - C[0], C[2] - C[0]
        nrm = np.cross(u, v)
        if np.linalg.norm(nrm) < 1e-9 * max(np.linalg.norm(u) * np.linalg.norm(v), 1e-300):
            raise DesignError(file, f"{key}.corners", c, "the three corners are collinear")
        centre = C[0] + 0.5 * (u + v)
        if np.dot(nrm, -centre) <= 0:
            raise DesignError(file, f"{key}.corners", c, "the quad's front (u x v) faces away from "
                              "the eye at the origin: swap the +u and +v corners")
        tex = _texture(file, f"{key}.texture", o.get("texture", {"type": "checker"}), base)
        rad = _rgb(file, f"{key}.radiance", o.get("radiance", 1.0))
        out.append(Quad(str(o.get("name", f"object{i}")), C, tex, rad))
    view = data.get("view", {})
    if not isinstance(view, dict):
        raise DesignError(file, "view", view, "expected a table")
    no_unknown(file, "view.", view, {"design", "cdp_mm", "focus_mm", "pupil_diameter", "background"})
    v = {}
    if "design" in view:
        d = view["design"]
        if not isinstance(d, str) or not (base / d).is_file():
            raise DesignError(file, "view.design", d, "expected a design file path (relative to this file)")
        v["design"] = str((base / d).resolve())
    if "cdp_mm" in view:
        v["cdp_mm"] = _num(file, "view.cdp_mm", view["cdp_mm"], positive=True, allow_inf=True)
    if "focus_mm" in view:
        f = view["focus_mm"]
        if not isinstance(f, list) or not f:
            raise DesignError(file, "view.focus_mm", f, "expected a list of distances (mm)")
        v["focus_mm"] = tuple(_num(file, f"view.focus_mm[{i}]", x, positive=True, allow_inf=True)
                              for i, x in enumerate(f))
    if "pupil_diameter" in view:
        v["pupil_diameter_mm"] = _num(file, "view.pupil_diameter", view["pupil_diameter"], positive=True)
    bg = _rgb(file, "view.background", view.get("background", 0.0))
    if src is not None and any(b > 0 for b in bg):
        raise DesignError(file, "view.background", view["background"], "a Mitsuba scene has its own "
                          "environment: give it a constant or envmap emitter instead")
    content = ContentScene(file, str(data.get("name", Path(file).stem)), out, bg, ContentView(**v),
                           _primaries(file, data), scene=src)
    if src is not None:
        content.mitsuba_scene()  # load and check now: a bad scene fails before any work
    return content
