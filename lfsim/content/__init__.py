"""Content: the 3D scene an InI-HMD shows, and the elemental images that show it.

Content lives in visual space (the viewing-window frame: the eye at the origin
looking along −z, +x to the viewer's right, +y up, millimetres). Three kinds:

* **quads** (:mod:`.schema`, :mod:`.quads`): self-luminous textured
  rectangles from a content TOML — exact and noise-free, shaded by one ray per
  pixel (the fast path);
* **Mitsuba scenes** (:mod:`.mitsuba_scene`): any scene Mitsuba loads (XML,
  a dict or a loaded ``mi.Scene``), with shapes, BSDFs, textures and
  emitters, in visual-space millimetres or placed by a content TOML's
  ``[scene]`` scale and transform; path-traced;
* **RGB-D images** (:mod:`.rgbd`): an image and a depth map turned into a
  textured height-field mesh.

The elemental images of any of them (:mod:`.elemental`) shade each display
pixel along the visual-space ray that pixel emits, traced through the real
optics by lfsim's tracer.
"""

from __future__ import annotations

from .elemental import METHODS, ElementalImages, display_work, elemental_images, shade_display, visual_rays
from .quads import quad_transform, scene_dict, shade, texture_image
from .schema import VIEW_DEFAULTS, ContentScene, ContentView, Quad, Texture, content_from_dict, load_content

__all__ = ["METHODS", "VIEW_DEFAULTS", "ContentScene", "ContentView", "ElementalImages", "Quad", "Texture",
           "content_from_dict", "display_work", "elemental_images", "from_mitsuba", "load_content", "quad_transform",
           "scene_dict", "shade", "shade_display", "texture_image", "visual_rays"]


def from_mitsuba(scene, name: str = "scene", view: ContentView | None = None, units="mm",
                 rotate_deg=(0.0, 0.0, 0.0), translate_mm=(0.0, 0.0, 0.0), max_depth: int | None = None,
                 primaries: dict | None = None) -> ContentScene:
    """Content from a Mitsuba scene: a loaded ``mi.Scene``, a scene dict, or an XML path.

    ``units`` (a name of :data:`lfsim.content.mitsuba_scene.UNITS` or mm per unit),
    ``rotate_deg`` (about x, then y, then z) and ``translate_mm`` place the scene in
    visual space; the defaults take it as given, in visual-space millimetres.
    """
    import numpy as np

    from .mitsuba_scene import MAX_DEPTH, SceneSource, _rotation, units_mm

    label = str(scene) if isinstance(scene, str) else f"<{name}>"
    src = SceneSource(file=scene if isinstance(scene, str) else None,
                      scene=None if isinstance(scene, str) else scene, scale=units_mm(label, "units", units),
                      rotation=_rotation(rotate_deg), translation=np.asarray(translate_mm, dtype=np.float64),
                      max_depth=MAX_DEPTH if max_depth is None else int(max_depth), label=label)
    content = ContentScene(label, name, [], view=view or VIEW_DEFAULTS, primaries=primaries, scene=src)
    content.mitsuba_scene()
    return content
