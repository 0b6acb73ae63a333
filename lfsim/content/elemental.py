"""Elemental images: what the microdisplay shows for a 3D content scene.

Each display pixel lights, through its lenslet, a beam that the eye sees as
coming from one direction of visual space. Two ways to find that ray:

* ``"real"``: the pixel's chief ray — from the pixel centre through the centre
  of its lenslet's stop, aimed with real rays — traced through the real
  lenslet, relay and eyepiece to the viewing window (the same tracer as the
  metrics). Shading the content along that ray pre-corrects the optics'
  distortion (GD, Eq. 11) by construction.
* ``"pinhole"``: the first-order model (Eqs. 1–10; every lenslet a pinhole at
  its stop centre, the relay and eyepiece paraxial): the classic
  pinhole-per-lenslet rendering, blind to distortion.

The visual-space ray starts on the viewing window at the chief ray's point h
and runs along −d (from the eye into the scene); its first hit on the content
is the pixel's value.
"""

from __future__ import annotations

import numpy as np

from .quads import shade

METHODS = ("real", "pinhole")


def _subpixel_offsets(samples: int) -> np.ndarray:
    """Stratified offsets (samples², 2) inside a pixel, in pixel units."""
    g = (np.arange(samples) + 0.5) / samples - 0.5
    X, Y = np.meshgrid(g, g)
    return np.stack([X.ravel(), Y.ravel()], axis=1)


def visual_rays(model, layout, xy: np.ndarray, method: str = "real", k: int = 0):
    """Visual-space rays of display points ``xy`` (N, 2): origins (N, 3), directions (N, 3), valid (N,)."""
    from ..ini.subsystems import trace_rays

    if method not in METHODS:
        raise ValueError(f"method = {method!r}: expected one of {', '.join(METHODS)}")
    m, n = layout.lenslet_of(xy)
    if method == "real":
        pos, d, _, status, _ = trace_rays(model, xy, m, n, np.zeros(2), k, iterations=8)
        valid = status == 0
    else:
        c = model.lenslet_center(m, n)
        st = model.paraxial_vw(k, xy, c, np.zeros_like(xy))
        pos = st[:, 0:2]
        d = np.column_stack([st[:, 2], st[:, 3], np.ones(len(st))])
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        valid = np.ones(len(st), dtype=bool)
    origins = np.column_stack([pos, np.zeros(len(pos))])
    return origins, -d, valid


def elemental_images(model, content_scene, layout=None, method: str = "real",
                     samples: int = 1, k: int = 0, background=(0.0, 0.0, 0.0), chunk: int = 1 << 20,
                     progress=None) -> np.ndarray:
    """The display image (H, W, 3, float32, linear) for a Mitsuba content scene.

    ``samples``: a samples×samples stratified grid inside every pixel (box
    filter); ``progress``: called with the number of pixels done per chunk.
    """
    if layout is None:
        from ..render.display import DisplayLayout

        layout = DisplayLayout.from_model(model, k)
    centres = layout.pixel_centers().reshape(-1, 2)
    offs = _subpixel_offsets(int(samples)) * layout.pixel_pitch * np.array([1.0, -1.0])
    img = np.zeros((len(centres), 3), dtype=np.float64)
    rows = max(1, chunk // len(offs))
    for a in range(0, len(centres), rows):
        c = centres[a:a + rows]
        xy = (c[:, None, :] + offs[None]).reshape(-1, 2)
        o, d, ok = visual_rays(model, layout, xy, method, k)
        L = shade(content_scene, o, d, ok, background)
        img[a:a + len(c)] = L.reshape(len(c), len(offs), 3).mean(axis=1)
        if progress is not None:
            progress(len(c))
    return img.reshape(layout.height, layout.width, 3).astype(np.float32)
