"""Path-traced display pixels: a Mitsuba sensor whose rays come from lfsim's tracer.

Sensor plugin ``lfsim_pixel_rays``: its film is the microdisplay (one film
pixel per display pixel) and film pixel i shoots the visual-space ray that
display pixel i emits — given as a table (origins, directions, weights),
traced beforehand through the real optics (:mod:`.elemental`). Mitsuba's
integrator (``path``) then shades it in the content scene, so a lit scene's
BSDFs, textures, area lights and environments all count.

:func:`render_rays` renders the spp in passes split into two halves with
independent samples; their difference gives the noise of the estimate
(the standard error of the mean per pixel), reported beside the image.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass

import numpy as np

from ..backend import from_numpy, mitsuba, register_plugin

PLUGIN_NAME = "lfsim_pixel_rays"
#: Ray tables by id (Mitsuba properties hold only plain values).
_TABLES: dict[str, tuple] = {}
_ids = itertools.count()
#: Samples per Mitsuba launch (pixels × spp): bounds the wavefront's memory.
SAMPLES_PER_LAUNCH = 1 << 24


def _sensor_class(mi):
    import drjit as dr

    class PixelRays(mi.Sensor):
        def __init__(self, props):
            key = props["rays"]
            if key not in _TABLES:
                raise ValueError(f"{PLUGIN_NAME}: rays = {key!r}: no such ray table")
            super().__init__(props)
            self.o, self.d, self.w = _TABLES[key]

        def sample_ray(self, time, wavelength_sample, position_sample, aperture_sample, active=True):
            # Film position -> display pixel. render_rays() hands over pixel centres; with
            # mi.render's random positions a sample within float32 rounding (~1e-4 px) of a
            # pixel edge may take its neighbour's ray.
            film = self.film()
            crop = mi.Vector2i(film.crop_size())
            px = dr.clip(mi.Vector2i(dr.floor(position_sample * mi.Vector2f(crop))), 0, crop - 1)
            idx = mi.UInt32(px.y) * mi.UInt32(crop.x) + mi.UInt32(px.x)
            o = dr.gather(mi.Point3f, self.o, idx, active)
            d = dr.gather(mi.Vector3f, self.d, idx, active)
            w = dr.gather(mi.Float, self.w, idx, active)
            wav, ww = self.sample_wavelengths(dr.zeros(mi.SurfaceInteraction3f), wavelength_sample, active)
            return mi.Ray3f(o, d, time, wav), ww * w

        def sample_ray_differential(self, time, wavelength_sample, position_sample, aperture_sample, active=True):
            ray, w = self.sample_ray(time, wavelength_sample, position_sample, aperture_sample, active)
            return mi.RayDifferential3f(ray), w

        def to_string(self):
            return f"PixelRays[{self.film()}]"

    return PixelRays


def register():
    """Register ``lfsim_pixel_rays`` (idempotent); returns the mitsuba module."""
    return register_plugin("sensor", PLUGIN_NAME, _sensor_class)


def _table(mi, origins, directions, weights):
    o = np.asarray(origins, dtype=np.float32)
    d = np.asarray(directions, dtype=np.float32)
    d = d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-30)
    # Aligned copies: a kernel reading a mapped numpy buffer bakes its alignment into the IR.
    return (mi.Point3f(*from_numpy(mi.Float, *(o[:, k] for k in range(3)))),
            mi.Vector3f(*from_numpy(mi.Float, *(d[:, k] for k in range(3)))),
            from_numpy(mi.Float, np.asarray(weights, dtype=np.float32)))


def sensor(origins, directions, weights, width: int, height: int, spp: int, seed: int = 0):
    """A loaded ``lfsim_pixel_rays`` sensor over a ``width`` × ``height`` film; ray i (row-major,
    row 0 at the top) is film pixel i's. Returns ``(sensor, key)``; :func:`release` the key."""
    mi = register()
    key = f"rays{next(_ids)}"
    _TABLES[key] = _table(mi, origins, directions, weights)
    s = mi.load_dict({"type": PLUGIN_NAME, "rays": key,
                      "film": {"type": "hdrfilm", "width": int(width), "height": int(height),
                               "pixel_format": "rgb", "rfilter": {"type": "box"}},
                      "sampler": {"type": "independent", "sample_count": int(spp), "seed": int(seed)}})
    return s, key


def release(key: str) -> None:
    _TABLES.pop(key, None)


@dataclass
class Shaded:
    """A path-traced pixel image and its noise."""

    image: np.ndarray  # (H, W, 3) float32, linear
    spp: int
    #: Standard error of the mean, RMS over pixels with rays, relative to their mean radiance.
    noise_rel: float | None
    seconds: float


def integrator(max_depth: int) -> dict:
    return {"type": "path", "max_depth": int(max_depth), "hide_emitters": False}


def _sample_pixels(mi, scene, sens, integ, width: int, height: int, spp: int, seed: int) -> np.ndarray:
    """Mean radiance (N, 3) of ``spp`` integrator samples per display pixel along the sensor's rays.

    The loop of ``mi.render`` without its film: each sample asks the sensor for its pixel's
    ray at the pixel's centre (so no sample can fall across a pixel edge) and Mitsuba's
    integrator for the radiance; the samples of a pixel are summed in one block reduction.
    """
    import drjit as dr

    n = width * height
    lane = dr.arange(mi.UInt32, n * spp)
    pix = lane // spp
    pos = (mi.Vector2f(mi.Float(pix % width), mi.Float(pix // width)) + 0.5) / mi.ScalarVector2f(width, height)
    sampler = sens.sampler().clone()
    sampler.seed(seed, n * spp)
    ray, w = sens.sample_ray(0.0, sampler.next_1d(), pos, sampler.next_2d())
    L, valid, _ = integ.sample(scene, sampler, mi.RayDifferential3f(ray), None, w[0] > 0)
    L = dr.select(valid, L * w, 0.0)
    out = [dr.block_sum(L[k], spp) / spp for k in range(3)]
    dr.eval(*out)
    return np.stack([np.asarray(c, dtype=np.float64) for c in out], axis=1)


def render_rays(scene, rays_for_pass, width: int, height: int, spp: int, max_depth: int, seed: int = 0,
                fresh_rays: bool = False, progress=None) -> Shaded:
    """Path-trace ``spp`` samples per pixel along tabulated rays.

    ``rays_for_pass(p) -> (origins, directions, valid)``: the scene-frame rays of
    pass ``p`` (numpy (N, 3), (N, 3), (N,), N = width·height). With
    ``fresh_rays`` every pass is one sample per pixel along new rays (a ray
    bundle integrated by Monte Carlo); else one table serves all passes. A
    pixel's value is the mean over its valid rays. ``progress(samples)`` is
    called per pass with the pixel-samples done.
    """
    import time

    mi = register()
    t0 = time.perf_counter()
    n = width * height
    spp = int(spp)
    if spp < 1:
        raise ValueError(f"spp = {spp}: must be >= 1")
    per = 1 if fresh_rays else max(1, min(spp, SAMPLES_PER_LAUNCH // max(n, 1)))
    # Passes alternate between halves A and B (independent samples) for the noise estimate.
    sizes = [per] * (spp // per) + ([spp % per] if spp % per else [])
    if len(sizes) == 1 and spp >= 2:
        sizes = [spp - spp // 2, spp // 2]
    acc = [np.zeros((n, 3)), np.zeros((n, 3))]
    cnt = [np.zeros(n), np.zeros(n)]
    integ = mi.load_dict(integrator(max_depth))
    table = None
    for p, s in enumerate(sizes):
        if fresh_rays or table is None:
            o, d, ok = rays_for_pass(p)
            ok = np.asarray(ok, dtype=bool)
            table = (o, d, ok)
        o, d, ok = table
        sens, key = sensor(o, d, ok.astype(np.float32), width, height, s, seed=seed * 7919 + p)
        try:
            img = _sample_pixels(mi, scene, sens, integ, width, height, s, seed * 7919 + p)
        finally:
            release(key)
        h = p % 2
        acc[h] += img * s
        cnt[h] += ok * s
        if progress is not None:
            progress(s * n)
    tot = cnt[0] + cnt[1]
    has = tot > 0
    out = np.zeros((n, 3))
    out[has] = (acc[0] + acc[1])[has] / tot[has, None]
    noise = None
    both = (cnt[0] > 0) & (cnt[1] > 0)
    if np.any(both):
        a = acc[0][both] / cnt[0][both, None]
        b = acc[1][both] / cnt[1][both, None]
        # Var(a - b) = s^2 (1/na + 1/nb); the full estimate's variance is s^2 / (na + nb).
        na, nb, nt = cnt[0][both], cnt[1][both], tot[both]
        se = np.abs(a - b) / np.sqrt(nt * (1.0 / na + 1.0 / nb))[:, None]
        mean = float(np.mean(out[both]))
        if mean > 0:
            noise = float(math.sqrt(np.mean(se ** 2)) / mean)
    if not np.all(np.isfinite(out)):
        raise FloatingPointError("non-finite pixels in the path-traced elemental images")
    return Shaded(out.reshape(height, width, 3).astype(np.float32), spp, noise, time.perf_counter() - t0)


def surface_aovs(scene, origins, directions, valid, scale: float = 1.0, normal_to_visual=None):
    """Depth and normal of the first surface along scene-frame rays: ``(depth (N,), normal (N, 3))``.

    depth: distance (mm, × ``scale`` from scene units) along the ray to the first
    surface, inf where the ray meets nothing, 0 where ``valid`` is False;
    normal: the unit shading normal turned toward the ray's origin
    (``normal_to_visual`` maps it to visual space), 0 without a hit.
    """
    import drjit as dr

    mi = mitsuba()
    o, d, _ = _table(mi, origins, directions, np.ones(len(origins)))
    si = scene.ray_intersect(mi.Ray3f(o, d))
    n = si.sh_frame.n
    n = dr.select(dr.dot(n, d) > 0, -n, n)
    dr.eval(si.t, n, si.is_valid())
    hit = np.asarray(si.is_valid(), dtype=bool)
    t = np.asarray(si.t, dtype=np.float64) * scale
    N = np.stack([np.asarray(n[k], dtype=np.float64) for k in range(3)], axis=1)
    ok = np.asarray(valid, dtype=bool)
    depth = np.where(hit, t, np.inf)
    depth[~ok] = 0.0
    N[~(hit & ok)] = 0.0
    if normal_to_visual is not None:
        N = normal_to_visual(N)
    return depth, N
