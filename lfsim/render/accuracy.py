"""How far the mesh path is from the analytic path, with the noise taken out.

Two Monte Carlo renders differ by noise as well as by geometry. To measure the
geometry alone (the tessellation error) both paths here see the *same* eye
rays — common random numbers: every pixel's jittered film positions and pupil
samples are drawn once, turned into rays by the eye sensor, and then

* traced backwards through the design by :class:`~.analytic.ReverseOptics`
  (the analytic reference), or
* walked through the Mitsuba meshes of the optics
  (:func:`~.optics_scene.trace_scene`),

and both read the display image bilinearly where they cross the display
plane (as Mitsuba's bilinear bitmap does). The pixel value is the mean over
its samples, the eye's estimator. What is left between the two images is the
tessellation (and float32) error.
"""

from __future__ import annotations

import time

import numpy as np

from ..backend import from_numpy
from . import mitsuba


def eye_rays(eye_spec, spp: int, seed: int = 0):
    """Eye rays of every pixel (viewing-window frame, numpy): origins, directions,
    weights (N,) and pixel index (N,), N = W·H·spp (stratified film jitter,
    uniform pupil samples)."""
    import drjit as dr

    mi = mitsuba()
    sensor = eye_spec.load(None, spp=1, seed=seed)
    W, H = eye_spec.resolution
    rng = np.random.default_rng(seed)
    pix = np.repeat(np.arange(W * H), spp)
    u = ((pix % W) + rng.random(pix.size)) / W
    v = ((pix // W) + rng.random(pix.size)) / H
    ap = rng.random((pix.size, 2))
    f = lambda a: from_numpy(mi.Float, np.asarray(a, dtype=np.float32))  # noqa: E731
    with dr.suspend_grad():
        ray, w = sensor.sample_ray(mi.Float(0.0), mi.Float(0.5), mi.Point2f(f(u), f(v)),
                                   mi.Point2f(f(ap[:, 0]), f(ap[:, 1])))
        dr.eval(ray, w)
    o = np.column_stack([np.asarray(ray.o[i], dtype=np.float64) for i in range(3)])
    d = np.column_stack([np.asarray(ray.d[i], dtype=np.float64) for i in range(3)])
    return o, d, np.asarray(w[0], dtype=np.float64), pix


def display_lookup(layout, image: np.ndarray, xy: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """Radiance (N, 3) of the display image at global points ``xy`` (bilinear between
    pixel centres, clamped at the border; 0 off the display or for invalid rays)."""
    from scipy.ndimage import map_coordinates

    p = layout.pixel_pitch
    col = (xy[:, 0] - layout.center[0]) / p + 0.5 * layout.width - 0.5
    row = 0.5 * layout.height - (xy[:, 1] - layout.center[1]) / p - 0.5
    on = valid & (col >= -0.5) & (col <= layout.width - 0.5) & (row >= -0.5) & (row <= layout.height - 0.5)
    c = np.clip(col, 0, layout.width - 1)
    r = np.clip(row, 0, layout.height - 1)
    out = np.stack([map_coordinates(image[..., k], [r, c], order=1, mode="nearest") for k in range(3)], axis=1)
    return np.where(on[:, None], out, 0.0)


def _image(values: np.ndarray, weights: np.ndarray, pix: np.ndarray, W: int, H: int) -> np.ndarray:
    acc = np.zeros((W * H, 3))
    np.add.at(acc, pix, values * weights[:, None])
    spp = np.bincount(pix, minlength=W * H)[:, None]
    return (acc / np.maximum(spp, 1)).reshape(H, W, 3)


def paired_renders(model, layout, display: np.ndarray, eye_spec, spp: int = 16,
                   densities=(0.25, 0.5, 1.0, 2.0), seed: int = 0) -> dict:
    """Analytic and mesh images from the same eye rays.

    ``densities``: tessellations as multiples of the default segment counts
    (:func:`lfsim.render.meshes.tessellation`). Returns ``{"analytic": (image,
    seconds), density: (image, seconds), ...}``; the mesh times include
    building and loading the meshes.
    """
    from .analytic import ReverseOptics
    from .meshes import tessellation
    from .optics_scene import optics_shapes, trace_scene

    mi = mitsuba()
    W, H = eye_spec.resolution
    o, d, w, pix = eye_rays(eye_spec, spp, seed)
    out = {}
    t0 = time.perf_counter()
    rev = ReverseOptics(model, 0)
    p, dd, ok = rev.to_display_numpy(o, d)
    L = display_lookup(layout, display, p[:, :2], ok & (dd[:, 2] < 0))
    out["analytic"] = (_image(L, w, pix, W, H), time.perf_counter() - t0)
    og, dg = o @ model.R_vw.T + model.o_vw, d @ model.R_vw.T
    for S in densities:
        t0 = time.perf_counter()
        scene = mi.load_dict({"type": "scene", **optics_shapes(model.design, values=model.values(0),
                                                                 **tessellation(S))})
        res = trace_scene(scene, og, dg, max_depth=64)
        dz = res.directions[:, 2]
        t = (layout.z - res.positions[:, 2]) / np.where(dz < 0, dz, -1.0)
        hit = res.positions + t[:, None] * res.directions
        L = display_lookup(layout, display, hit[:, :2], res.valid & (dz < 0))
        out[S] = (_image(L, w, pix, W, H), time.perf_counter() - t0)
    return out


def relative_rmse(img: np.ndarray, ref: np.ndarray) -> float:
    """RMSE of ``img`` against ``ref`` divided by the mean of ``ref``."""
    return float(np.sqrt(np.mean((np.asarray(img) - ref) ** 2)) / max(float(np.mean(ref)), 1e-30))


def error_vs_time(design, content, cdp_mm: float = 750.0, resolution=(128, 74), spps=(4, 16, 64, 256),
                  reference_spp: int = 4096, densities=(0.125, 0.25, 0.5, 1.0, 2.0), pair_spp: int = 64,
                  pupil_mm: float = 3.0) -> dict:
    """Render error against run time of one design: samples per pixel and mesh tessellation.

    * ``spp``: the analytic display path rendered by Mitsuba at each of ``spps``
      (seed 0) against a ``reference_spp`` render of the same path (seed 1000,
      the converged reference): relative RMSE (:func:`relative_rmse`) and seconds.
    * ``tessellation``: the mesh path at each density of ``densities``
      (× :func:`lfsim.render.meshes.tessellation` defaults) against the
      analytic path with the same eye rays (:func:`paired_renders`, common
      random numbers at ``pair_spp``), so only the geometric error is left;
      seconds include building and loading the meshes.

    The display shows ``content``'s elemental images for the CDP at ``cdp_mm``;
    the ideal eye (``pupil_mm``) focuses at the CDP. Returns ``{"spp": [{spp,
    rel_rmse, seconds}], "reference_seconds", "tessellation": [{density,
    segments, lenslet_segments, prism_segments, rel_rmse, seconds}],
    "analytic_pair_seconds"}``.
    """
    from ..content import elemental_images, scene_dict
    from ..ini.model import model_at_depth
    from . import display_eye
    from .analytic import ReverseOptics
    from .display import DisplayLayout
    from .eye import EyeSpec
    from .focal_stack import INTEGRATOR, render
    from .meshes import tessellation

    mi = mitsuba()
    model = model_at_depth(design, 1000.0 / cdp_mm)
    layout = DisplayLayout.from_model(model)
    display = elemental_images(model, mi.load_dict(scene_dict(content)), layout)
    fx, fy = model.state(0).fov_deg
    eye = EyeSpec("ideal", pupil_mm, cdp_mm, (fx, fy), tuple(resolution))
    key = display_eye.attach(ReverseOptics(model, 0))
    try:
        def analytic(spp, seed):
            return render({"type": "scene", "display": layout.emitter_dict(display),
                           "sensor": display_eye.sensor_dict(eye, key, spp, seed), "integrator": INTEGRATOR})

        ref, t_ref = analytic(reference_spp, 1000)
        rows_spp = []
        for spp in spps:
            img, secs = analytic(spp, 0)
            rows_spp.append({"spp": int(spp), "rel_rmse": relative_rmse(img, ref), "seconds": secs})
    finally:
        display_eye.release(key)
    pairs = paired_renders(model, layout, display, eye, spp=pair_spp, densities=tuple(densities))
    base, t_an = pairs["analytic"]
    rows_seg = [{"density": float(S), **tessellation(S), "rel_rmse": relative_rmse(pairs[S][0], base),
                 "seconds": pairs[S][1]} for S in densities]
    return {"spp": rows_spp, "reference_seconds": t_ref, "tessellation": rows_seg, "analytic_pair_seconds": t_an}


def wavelength_error(design, content, cdp_mm: float = 750.0, resolution=(128, 74), spp: int = 64,
                     samples=(1, 2, 4, 8), reference_samples: int = 16, pupil_mm: float = 3.0,
                     diffraction: bool = True) -> dict:
    """Error against run time of the wavelength nodes per primary of a spectral render.

    The analytic display path (colour, diffraction unless turned off; ideal eye focused at
    the CDP) at each count of ``samples`` nodes per primary against ``reference_samples``
    nodes, all with the same seed: the film, pupil and wavelength samples are the same
    numbers, so what is left is the wavelength quadrature's error (and the noise of which
    node each ray's wavelength sample falls on). ``noise`` is the reference against itself
    at another seed: the Monte Carlo error of one render at this spp. Returns ``{"samples":
    [{samples, rel_rmse, seconds}], "noise", "reference_seconds"}``.
    """
    from ..content import elemental_images, scene_dict
    from ..ini.model import model_at_depth
    from . import display_eye
    from .analytic import ReverseOptics
    from .display import DisplayLayout
    from .eye import EyeSpec
    from .focal_stack import INTEGRATOR, load_scene, render_passes
    from .spectra import spectral

    mi = mitsuba()
    model = model_at_depth(design, 1000.0 / cdp_mm)
    layout = DisplayLayout.from_model(model)
    display = elemental_images(model, mi.load_dict(scene_dict(content)), layout)
    fx, fy = model.state(0).fov_deg
    scene = load_scene({"type": "scene", "display": layout.emitter_dict(display), "integrator": INTEGRATOR})

    def run(k, seed):
        passes = spectral(int(k))
        keys = [display_eye.attach(ReverseOptics(model, 0, wavelengths=w,
                                                 diffraction_pupil_mm=pupil_mm if diffraction else None))
                for w in passes]
        try:
            jobs = [(scene, display_eye.sensor_dict(
                EyeSpec("ideal", pupil_mm, cdp_mm, (fx, fy), tuple(resolution), wavelengths=w,
                        diffraction=diffraction), key, spp, seed)) for w, key in zip(passes, keys)]
            return render_passes(jobs, passes)
        finally:
            for key in keys:
                display_eye.release(key)

    ref, t_ref = run(reference_samples, 0)
    other, _ = run(reference_samples, 1000)
    rows = []
    for k in samples:
        img, secs = run(k, 0)
        rows.append({"samples": int(k), "rel_rmse": relative_rmse(img, ref), "seconds": secs})
    return {"samples": rows, "noise": relative_rmse(other, ref), "reference_seconds": t_ref}


def sampler_noise(design, content, samplers=("independent", "multijitter", "lfsim_sobol"), spps=(16, 64, 256),
                  cdp_mm: float = 750.0, focus_mm: float = 1000.0, resolution=(512, 309), pupil_mm: float = 3.0,
                  kinds=("display", "natural"), diffraction=(True, False), wavelength_samples: int = 8) -> dict:
    """Monte Carlo error of one retinal image against run time, per sampler and spp.

    The focal stack's images (colour, ``wavelength_samples`` nodes per primary as the focal
    stack's default; ideal eye
    with a ``pupil_mm`` pupil focused at ``focus_mm``; the display showing ``content``'s
    elemental images for the CDP at ``cdp_mm``), rendered with each of ``samplers`` (Mitsuba
    plugin names) at each of ``spps``, with and without ``diffraction``. The error is the
    relative RMSE of one image from two seeds, ``RMS(a − b) / √2 / mean``: the estimators are
    unbiased, so this is the error against the converged image, without rendering one.
    Seconds: the first seed's render (its three passes, kernels compiled before). Returns ``{"rows": [{kind,
    diffraction, sampler, spp, rel_rmse, seconds}]}``.
    """
    from ..content import elemental_images, scene_dict
    from ..ini.model import model_at_depth
    from . import display_eye
    from .analytic import ReverseOptics
    from .display import DisplayLayout
    from .eye import EyeSpec, sampler_type
    from .focal_stack import INTEGRATOR, load_scene, render_passes
    from .spectra import spectral

    mi = mitsuba()
    sampler_type(1)  # registers lfsim_sobol
    model = model_at_depth(design, 1000.0 / cdp_mm)
    layout = DisplayLayout.from_model(model)
    content_scene = mi.load_dict(scene_dict(content))
    display = elemental_images(model, content_scene, layout, background=content.background)
    fx, fy = model.state(0).fov_deg
    passes = spectral(int(wavelength_samples), content.primaries)
    scenes = {"display": load_scene({"type": "scene", "display": layout.emitter_dict(display),
                                     "integrator": INTEGRATOR}),
              "natural": load_scene(dict(scene_dict(content), integrator=INTEGRATOR))}
    rows = []
    for diff in diffraction:
        keys = [display_eye.attach(ReverseOptics(model, 0, wavelengths=w,
                                                 diffraction_pupil_mm=pupil_mm if diff else None))
                for w in passes]
        try:
            for kind in kinds:
                for sampler in samplers:
                    for i, spp in enumerate(spps):
                        def run(seed):
                            jobs = []
                            for w, key in zip(passes, keys):
                                eye = EyeSpec("ideal", pupil_mm, focus_mm, (fx, fy), tuple(resolution),
                                              wavelengths=w, diffraction=bool(diff))
                                d = (display_eye.sensor_dict(eye, key, spp, seed) if kind == "display"
                                     else eye.sensor_dict(None, spp, seed))
                                d["sampler"] = {"type": sampler, "sample_count": int(spp), "seed": int(seed)}
                                jobs.append((scenes[kind], d))
                            return render_passes(jobs, passes)

                        if i == 0:
                            run(2)  # compiles this sampler's kernels outside the timing
                        a, secs = run(0)
                        b, _ = run(1)
                        err = float(np.sqrt(np.mean((a - b) ** 2) / 2.0) / max(float(np.mean(0.5 * (a + b))), 1e-30))
                        rows.append({"kind": kind, "diffraction": bool(diff), "sampler": sampler, "spp": int(spp),
                                     "rel_rmse": err, "seconds": secs})
        finally:
            for key in keys:
                display_eye.release(key)
    return {"rows": rows}
