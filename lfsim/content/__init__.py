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

from .elemental import METHODS, elemental_images, visual_rays
from .quads import quad_transform, scene_dict, shade, texture_image
from .schema import VIEW_DEFAULTS, ContentScene, ContentView, Quad, Texture, content_from_dict, load_content

__all__ = ["METHODS", "VIEW_DEFAULTS", "ContentScene", "ContentView", "Quad", "Texture", "content_from_dict",
           "elemental_images", "load_content", "quad_transform", "scene_dict", "shade", "texture_image",
           "visual_rays"]
