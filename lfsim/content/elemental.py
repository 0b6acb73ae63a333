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

import math
from dataclasses import dataclass

import numpy as np

from .quads import shade

METHODS = ("real", "pinhole")


def _subpixel_offsets(samples: int) -> np.ndarray:
    """Stratified offsets (samples², 2) inside a pixel, in pixel units."""
    g = (np.arange(samples) + 0.5) / samples - 0.5
    X, Y = np.meshgrid(g, g)
    return np.stack([X.ravel(), Y.ravel()], axis=1)


def visual_rays(model, layout, xy: np.ndarray, method: str = "real", k: int = 0, rho: np.ndarray | None = None):
    """Visual-space rays of display points ``xy`` (N, 2): origins (N, 3), directions (N, 3), valid (N,).

    ``rho`` (N, 2): the rays' points on their lenslet's stop, in stop half-widths
    (:func:`lfsim.ini.subsystems.trace_rays`); None: the stop centre (chief rays).
    """
    from ..ini.subsystems import trace_rays

    if method not in METHODS:
        raise ValueError(f"method = {method!r}: expected one of {', '.join(METHODS)}")
    m, n = layout.lenslet_of(xy)
    rho = np.zeros(2) if rho is None else np.asarray(rho, dtype=np.float64)
    if method == "real":
        pos, d, _, status, _ = trace_rays(model, xy, m, n, rho, k, iterations=8)
        valid = status == 0
    else:
        c = model.lenslet_center(m, n)
        st = model.paraxial_vw(k, xy, c, np.broadcast_to(rho, np.shape(xy)))
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


@dataclass
class ElementalImages:
    """The display image of a content and what came with it."""

    image: np.ndarray  # (H, W, 3) float32, linear
    #: Distance (mm) along each pixel's chief ray from the viewing window to the first
    #: content surface; inf: it meets nothing; 0: the pixel sends no ray to the window.
    depth: np.ndarray
    normal: np.ndarray  # (H, W, 3) unit visual-space normal of that surface, 0 without one
    method: str
    bundle: bool
    path_traced: bool
    spp: int  # samples per pixel (1 for the quads' chief rays)
    noise_rel: float | None  # standard error, RMS over pixels, relative to the mean (None: exact)
    seconds: float

    def doc(self) -> dict:
        return {"method": self.method, "bundle": self.bundle, "path_traced": self.path_traced, "spp": self.spp,
                "noise_rel": self.noise_rel, "render_s": round(self.seconds, 3)}


def _stop_samples(model, rng, n: int) -> np.ndarray:
    """Uniform points (n, 2) on the lenslet stop, in stop half-widths (a circle of radius r
    is r/√2 per half-width, :attr:`lfsim.ini.model.IniModel.stop_half`)."""
    ap = model.system.surfaces[model.spec.stop].aperture
    u = rng.random((n, 2))
    if ap is not None and ap.kind != "rectangular":
        r, phi = np.sqrt(u[:, 0]) * math.sqrt(2.0), 2.0 * math.pi * u[:, 1]
        return np.column_stack([r * np.cos(phi), r * np.sin(phi)])
    return 2.0 * u - 1.0


def display_work(layout, content, spp: int, bundle: bool, channels: int = 1) -> int:
    """Pixel-samples :func:`shade_display` reports to ``progress`` in all (``channels``: 3 with
    its ``channel_models``)."""
    n = layout.width * layout.height
    return n * (int(spp) if (content.path_traced or bundle) else 1) * int(channels)


def shade_display(model, content, layout, method: str = "real", samples: int = 1, spp: int = 16,
                  bundle: bool = False, seed: int = 0, k: int = 0, progress=None,
                  channel_models=None) -> ElementalImages:
    """The elemental images of a :class:`~lfsim.content.ContentScene` on ``layout``'s display.

    * Self-luminous content (quads, RGB-D): the emission along each pixel's
      chief ray (``samples``² stratified points inside the pixel), exact.
    * A Mitsuba scene: path-traced by Mitsuba along the same rays
      (:mod:`.pathtrace`), ``spp`` samples per pixel, with the noise reported.
    * ``bundle``: either kind integrated over the pixel's ray bundle instead —
      ``spp`` rays per pixel, each from a uniform point of the pixel's area
      through a uniform point of its lenslet's stop, traced through the real
      optics (rays vignetted on the way do not count).

    ``channel_models``: three models of the same design (R, G, B; e.g. at each display
    primary's median wavelength, the tunable lens at ``model``'s power): each colour channel
    is shaded along the rays of its own model, so the elemental images pre-correct the
    optics' lateral colour as they pre-correct its distortion (the display layout, the depth
    and the normals stay ``model``'s). None: every channel along ``model``'s rays.

    ``progress(n)``: called with the pixel-samples done (:func:`display_work` in all).
    """
    import time

    from . import pathtrace

    t0 = time.perf_counter()
    W, H = layout.width, layout.height
    centres = layout.pixel_centers().reshape(-1, 2)
    o0, d0, ok0 = visual_rays(model, layout, centres, method, k)
    src = content.scene
    scene = content.mitsuba_scene()

    def shade_with(m, o1, d1, ok1):
        def rays_for_pass(p):
            if p == 0 and not bundle:
                o, d, ok = o1, d1, ok1
            else:
                rng = np.random.default_rng([int(seed), int(p), 0x1F5B])
                jitter = (rng.random((len(centres), 2)) - 0.5) * layout.pixel_pitch
                o, d, ok = visual_rays(m, layout, centres + jitter, method, k,
                                       rho=_stop_samples(m, rng, len(centres)))
            return (*content.rays_to_scene(o, d), ok)

        if content.path_traced or bundle:
            depth_max = src.max_depth if content.path_traced else 1  # 1: emission of the first hit
            sh = pathtrace.render_rays(scene, rays_for_pass, W, H, spp, depth_max, seed=seed, fresh_rays=bundle,
                                       progress=progress)
            return sh.image, sh.spp, sh.noise_rel
        if int(samples) == 1:  # the chief rays already traced
            img1 = shade(scene, o1, d1, ok1, content.background).reshape(H, W, 3)
            if progress is not None:
                progress(W * H)
            return img1, 1, None
        return (elemental_images(m, scene, layout, method, samples, k, content.background, progress=progress),
                int(samples) ** 2, None)

    if channel_models is None:
        img, n_spp, noise = shade_with(model, o0, d0, ok0)
    else:
        if len(channel_models) != 3:
            raise ValueError(f"channel_models: expected three models (R, G, B), got {len(channel_models)}")
        parts = [shade_with(m, *visual_rays(m, layout, centres, method, k)) for m in channel_models]
        img = np.stack([part[0][..., c] for c, part in enumerate(parts)], axis=-1)
        n_spp = parts[0][1]
        noise = None if parts[0][2] is None else float(max(part[2] for part in parts))
    depth, normal = content.first_surface(o0, d0, ok0)
    return ElementalImages(img, depth.reshape(H, W).astype(np.float32), normal.reshape(H, W, 3).astype(np.float32),
                           method, bool(bundle), content.path_traced, n_spp, noise, time.perf_counter() - t0)
