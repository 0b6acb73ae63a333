"""Retinal focal stacks: the display seen through the design, focused at several depths.

For a design, a content scene and a CDP depth:

1. the InI model of that CDP state (the tunable lens set for it);
2. the elemental images: every display pixel's real chief ray traced to the
   viewing window and on into the content scene (:mod:`.elemental`);
3. for each focus distance, the retinal image of the display through the
   optics — the analytic path (:mod:`.display_eye`: the scene holds only the
   display, the sensor traces the design) or the mesh path (the display, the
   optics as meshes with lfsim's BSDFs and the eye at the viewing window,
   path-traced by Mitsuba) — and the natural view of the content through the same eye (the
   ground truth), with SSIM and PSNR between them (scikit-image);
4. float32 EXRs with metadata, PNG previews, a contact sheet and
   ``index.json`` (the contract in docs/contracts.md), all written atomically.

Images are in degrees of visual field over the display's FOV, so the display
and natural views line up pixel for pixel.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..content import VIEW_DEFAULTS
from ..metrics.image import exposure, ssim_matched
from . import mitsuba


def natural_integrator(content) -> dict | None:
    """The integrator of a content's natural view: None (the scene dict's own, emission of the
    first hit) for self-luminous content; Mitsuba's path tracer for a Mitsuba scene."""
    if not content.path_traced:
        return None
    from ..content.pathtrace import integrator

    return integrator(content.scene.max_depth)

#: Every scene a retinal camera sees here is emitters only (the display, the content's
#: emissive quads, a constant background): depth 1 is the emitted radiance of the first hit,
#: with no emitter or BSDF sampling after it (the same image as depth 2, 1.3-1.4x faster).
INTEGRATOR = {"type": "path", "max_depth": 1, "hide_emitters": False}
#: Through the optics meshes: every face is a delta interaction, so a path
#: needs (faces + 2) bounces and must not be cut short by roulette.
MESH_INTEGRATOR = {"type": "path", "max_depth": 256, "rr_depth": 1024, "hide_emitters": False}


@dataclass
class FocalStackSpec:
    """What to render (lengths mm; None: the content file's [view] or a default)."""

    focus_mm: list[float] = field(default_factory=lambda: list(VIEW_DEFAULTS.focus_mm))
    cdp_mm: float = VIEW_DEFAULTS.cdp_mm
    pupil_diameter_mm: float = VIEW_DEFAULTS.pupil_diameter_mm
    spp: int = 64
    resolution: tuple[int, int] | None = None  # default: 512 wide, the display's aspect
    seed: int = 0
    eye_model: str = "ideal"
    ei_method: str = "real"
    ei_samples: int = 1
    # Elemental images of a path-traced (Mitsuba-scene) content, or of any content with
    # ei_bundle: samples per display pixel; ei_bundle integrates over each pixel's ray bundle
    # (pixel area × lenslet stop) instead of shading its chief ray.
    ei_spp: int = 16
    ei_bundle: bool = False
    # Per-channel elemental images: each colour channel's pixels shaded along rays traced at its
    # display primary's median wavelength, pre-correcting the optics' lateral colour (spectral
    # renders on the analytic path only).
    ei_colour: bool = False
    natural: bool = True
    mla_cells: str = "per_surface"  # "fixed": baffled lenslet cells (an ideal aperture array)
    optics: str = "analytic"  # "mesh": Mitsuba meshes of the optics, path-traced
    tessellation: float = 1.0  # mesh density, × lfsim.render.meshes defaults
    focus_cues: bool = True  # the focus-cue analysis (lfsim.vision.focus_cues.focal_stack)
    wavelength_nm: float | None = None  # None: spectral (wavelength_samples per primary); else monochrome
    # Wavelength nodes per display primary (lfsim.render.spectra): 8 meets the accuracy report's
    # 3 % quadrature target (4: 3.4 %) at the same cost (a ray traces one wavelength).
    wavelength_samples: int = 8
    diffraction: bool = True  # the views' apertures and the eye pupil diffract (lfsim.render.diffraction)

    def wavelengths(self, design_nm: float, primaries: dict | None = None):
        """The render passes' wavelength nodes (list of :class:`lfsim.render.spectra.Wavelengths`):
        one pass per primary on the analytic path unless ``wavelength_nm`` is set; the mesh path
        is monochrome at ``design_nm`` (its glass BSDFs hold one index)."""
        from .spectra import monochrome, spectral

        if self.wavelength_nm is not None:
            return monochrome(self.wavelength_nm)
        if self.optics == "mesh":
            return monochrome(design_nm)
        return spectral(self.wavelength_samples, primaries)


def _srgb8(img: np.ndarray) -> np.ndarray:
    """Linear RGB → 8-bit sRGB (Mitsuba's conversion, clamped to [0, 1])."""
    mi = mitsuba()
    bmp = mi.Bitmap(np.ascontiguousarray(np.clip(img, 0.0, 1.0), dtype=np.float32))
    return np.array(bmp.convert(mi.Bitmap.PixelFormat.RGB, mi.Struct.Type.UInt8, srgb_gamma=True))


def write_exr(path: Path, img: np.ndarray, meta: dict, extra: dict | None = None) -> None:
    """A float32 RGB EXR (ZIP) with string/float metadata, written atomically; ``extra``:
    more channels by name (``{"depth.Z": (H, W), "normal": (H, W, 3)}``, AOVs)."""
    import OpenEXR

    from ..fileio import atomic_path

    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    for k, v in meta.items():
        header[f"lfsim_{k}"] = float(v) if isinstance(v, (int, float)) and not isinstance(v, bool) else str(v)
    with atomic_path(path) as tmp:
        channels = {"RGB": np.ascontiguousarray(img, dtype=np.float32)}
        for k, v in (extra or {}).items():
            channels[k] = np.ascontiguousarray(v, dtype=np.float32)
        with OpenEXR.File(header, channels) as f:
            f.write(str(tmp))


def read_exr(path) -> tuple[np.ndarray, dict]:
    """(image (H, W, 3) float32, header dict) of an EXR written by :func:`write_exr`."""
    import OpenEXR

    with OpenEXR.File(str(path)) as f:
        return np.array(f.channels()["RGB"].pixels, dtype=np.float32), dict(f.header())


def write_png(path: Path, img: np.ndarray) -> None:
    """An 8-bit sRGB preview of a linear image, written atomically."""
    from ..fileio import atomic_path

    mi = mitsuba()
    with atomic_path(path) as tmp:
        mi.Bitmap(_srgb8(img)).write(str(tmp))


def similarity(img: np.ndarray, ref: np.ndarray) -> tuple[float, float]:
    """(SSIM, PSNR dB) of ``img`` against ``ref``: the convention of
    :mod:`lfsim.metrics.image` (the one ``lfsim compare`` reports)."""
    from ..metrics.image import psnr, ssim

    return float(ssim(ref, img)), float(psnr(ref, img))


def load_scene(scene_dict: dict):
    """``mi.load_dict`` of a scene dict (one place, so a focal stack's scenes can be inspected)."""
    return mitsuba().load_dict(scene_dict)


def render(scene_dict, sensor: dict | None = None, integrator: dict | None = None) -> tuple[np.ndarray, float]:
    """Render a Mitsuba scene (a dict, or a loaded ``mi.Scene``); (image (H, W, 3) float32, seconds).

    ``sensor``: a sensor dict rendered instead of the scene's own, so one
    loaded scene (its meshes and their acceleration structure) serves every
    eye of a focal stack.
    """
    mi = mitsuba()
    t0 = time.perf_counter()
    scene = mi.load_dict(scene_dict) if isinstance(scene_dict, dict) else scene_dict
    kw = {} if sensor is None else {"sensor": mi.load_dict(sensor)}
    if integrator is not None:
        kw["integrator"] = mi.load_dict(integrator)
    img = np.array(mi.render(scene, **kw), dtype=np.float32)[..., :3]
    return img, time.perf_counter() - t0


def render_passes(jobs, passes) -> tuple[np.ndarray, float]:
    """Render ``jobs`` (``(scene, sensor)`` per wavelength pass of ``passes``) into one image:
    a pass with a channel gives that channel, a monochrome pass every channel."""
    if len(jobs) == 1 and passes[0].channel is None:
        return render(*jobs[0])
    img, total = None, 0.0
    for (scene, sensor, *integ), w in zip(jobs, passes):
        part, secs = render(scene, sensor, *integ)
        total += secs
        img = np.zeros_like(part) if img is None else img
        img[..., w.channel] = part[..., w.channel]
    return img, total


def estimate(spec: FocalStackSpec, resolution: tuple[int, int], display_px: int):
    """The run time and peak memory of a focal stack (:class:`lfsim.budget.Estimate`), before it starts.

    ``resolution``: the retinal images' (W, H); ``display_px``: pixels of the
    elemental images. Throughputs: :data:`lfsim.budget.RATES`, scaled by Dr.Jit's threads.
    """
    from .. import budget

    W, H = resolution
    n = len(spec.focus_mm)
    samples = W * H * spec.spp
    rate = budget.threads() * budget.RATES["display_mesh" if spec.optics == "mesh" else "display_analytic"]
    nat = budget.threads() * budget.RATES["natural"]
    npass = len(spec.wavelengths(550.0))  # display passes (a spectral render: one per primary)
    diffracts = spec.diffraction and spec.optics == "analytic"
    nat_pass = npass if spec.eye_model != "ideal" or diffracts else 1
    seconds = (npass * n * samples / rate + ((n * nat_pass + 1) * samples / nat if spec.natural else 0.0)
               + display_px * spec.ei_samples * (4 if spec.ei_colour else 1)
               / (budget.threads() * budget.RATES["elemental_px"])
               + (2 * n + 1) * W * H * budget.POST_S_PER_PX)
    images = 2 * n + 1 if spec.natural else n
    nbytes = budget.BASE_BYTES + W * H * budget.BYTES_PER_PX * max(1.0, images / 4) \
        + display_px * budget.BYTES_PER_DISPLAY_PX
    what = (f"focal stack of {images} images at {W}x{H} px x {spec.spp} spp ({budget.count(images * samples)} samples, "
            f"{spec.optics} optics) from {budget.count(display_px)} display px")
    return budget.Estimate(what, seconds, nbytes, note="plus kernel compiles on a design's first run")


def focal_stack(design, content, out_dir, spec: FocalStackSpec | None = None, progress: bool = False,
                log=print, limits=None, analyses=()) -> tuple[dict, dict]:
    """Render a focal stack; writes ``out_dir`` (the EXRs and PNGs, the contact sheet, what
    each of ``analyses`` writes, and ``index.json`` last).

    ``analyses``: ``(name, f)`` pairs, ``f(stack, content_scene, out) -> entry``, run on the
    finished stack inside the output folder, each entry kept as ``index.json``'s ``name``
    (the focus-cue analysis, :func:`lfsim.vision.focus_cues.focal_stack`, is one).

    Returns ``(index, stack)``: the ``index.json`` document and the images in
    memory, ``stack = {"fov_deg", "images": {(kind, focus_mm): (H, W, 3)},
    "reference", "content_scene"}``, where ``reference`` is the natural view
    through a pinhole pupil (everything sharp), for focus-cue analysis.

    The stack is written into a temporary folder beside ``out_dir`` that
    replaces it only on success: a failed or interrupted render leaves an
    existing ``out_dir`` as it was. ``limits`` (:class:`lfsim.budget.Limits`):
    a stack estimated beyond them is refused before any rendering
    (:func:`estimate`), and a long one's estimate is logged first.
    """
    from ..fileio import atomic_dir

    with atomic_dir(out_dir, "index.json") as tmp:
        return _focal_stack(design, content, tmp, spec, progress, log, limits, analyses)


def _focal_stack(design, content, out_dir, spec, progress, log, limits=None, analyses=()):
    from .. import budget
    from ..content import display_work, scene_dict, shade_display
    from ..fileio import write_json
    from ..ini.model import model_at_depth
    from .analytic import ReverseOptics
    from .display import DisplayLayout
    from .display_eye import attach, release
    from .display_eye import sensor_dict as display_sensor
    from .eye import EyeSpec
    from .spectra import describe, natural_primaries, primaries_doc

    spec = spec or FocalStackSpec()
    mitsuba()
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    t_all = time.perf_counter()
    cdp_D = 0.0 if math.isinf(spec.cdp_mm) else 1000.0 / spec.cdp_mm
    model = model_at_depth(design, cdp_D)
    state = model.state(0)
    layout = DisplayLayout.from_model(model, 0)
    fx, fy = state.fov_deg
    W, H = spec.resolution or (512, max(1, int(round(512 * fy / fx))))
    budget.check(estimate(spec, (W, H), layout.width * layout.height), limits, log,
                 hint="lower --resolution or --spp")
    content_scene = content.mitsuba_scene()

    passes = spec.wavelengths(model.lam, content.primaries)
    channel_models = channel_wavelengths = None
    if spec.ei_colour:
        if passes[0].channel is None:
            raise ValueError("ei_colour: per-channel elemental images need a spectral render (no wavelength_nm, "
                             "analytic optics)")
        from .spectra import CHANNELS, DEFAULT_PRIMARIES

        prim = content.primaries or DEFAULT_PRIMARIES
        channel_wavelengths = [round(float(prim[c].quantiles([0.5])[0]), 3) for c in CHANNELS]
        channel_models = [model.at_wavelength(x) for x in channel_wavelengths]
    bar = None
    if progress:
        from ..progress import bar as tqdm

        bar = tqdm(total=display_work(layout, content, spec.ei_spp, spec.ei_bundle, 3 if channel_models else 1),
                   desc="elemental images",
                   unit="px" if not (content.path_traced or spec.ei_bundle) else "sample", unit_scale=True,
                   leave=False)
    ei = shade_display(model, content, layout, method=spec.ei_method, samples=spec.ei_samples, spp=spec.ei_spp,
                       bundle=spec.ei_bundle, seed=spec.seed, progress=bar.update if bar else None,
                       channel_models=channel_models)
    display, t_ei = ei.image, ei.seconds
    if bar:
        bar.close()
    # The natural view is the real scene: broadband light through the sRGB colour-matching
    # functions, not the display's primaries (the same nodes count; monochrome stays monochrome).
    nat_passes = passes if passes[0].channel is None else spec.wavelengths(model.lam, natural_primaries())
    # Diffraction on the analytic path only (the mesh path's BSDFs bend no ray by an aperture).
    diffraction = spec.diffraction and spec.optics == "analytic"
    base_meta = {"design": design.path or design.name, "content": content.path, "cdp_mm": spec.cdp_mm,
                 "optics": spec.optics, "diffraction": int(diffraction),
                 "wavelengths_nm": ";".join(",".join(f"{v:.2f}" for v in w.nm) for w in passes),
                 "pupil_mm": spec.pupil_diameter_mm, "eye": spec.eye_model, "seed": spec.seed,
                 "fov_x_deg": fx, "fov_y_deg": fy}
    ei_meta = {k: ("none" if v is None else (int(v) if isinstance(v, bool) else v)) for k, v in ei.doc().items()}
    write_exr(out / "elemental_images.exr", display, dict(base_meta, kind="elemental_images", **ei_meta),
              extra={"depth.Z": ei.depth, "normal": ei.normal})
    write_png(out / "elemental_images.png", display)
    how = (f"{ei.spp} ray(s) per pixel over its bundle" if ei.bundle else f"{spec.ei_method} chief rays")
    if channel_wavelengths:
        how += ", R / G / B along rays at " + " / ".join(f"{v:.1f}" for v in channel_wavelengths) + " nm"
    if ei.path_traced:
        how += f", path-traced at {ei.spp} spp"
    noise = "" if ei.noise_rel is None else f", noise {100 * ei.noise_rel:.2f} % (standard error, RMS/mean)"
    log(f"elemental images: {layout.width}x{layout.height} px ({how}) in {t_ei:.1f} s{noise}")

    if spec.optics not in ("analytic", "mesh"):
        raise ValueError(f"optics = {spec.optics!r}: expected 'analytic' or 'mesh'")
    spectral = passes[0].channel is not None
    log(f"wavelengths: {describe(passes)}; diffraction {'on' if diffraction else 'off'}")
    keys = [attach(ReverseOptics(model, 0, cells=spec.mla_cells, wavelengths=w,
                                 diffraction_pupil_mm=spec.pupil_diameter_mm if diffraction else None))
            for w in passes]
    shapes = None
    if spec.optics == "mesh":
        from .meshes import tessellation
        from .optics_scene import optics_shapes

        t0 = time.perf_counter()
        shapes = optics_shapes(design, values=model.values(0), **tessellation(spec.tessellation))
        log(f"optics meshes: {len(shapes)} shapes at {spec.tessellation:g} x default density "
            f"in {time.perf_counter() - t0:.1f} s")
        vw = np.eye(4)
        vw[:3, :3], vw[:3, 3] = model.R_vw, model.o_vw

    loaded: dict = {}

    def scene_for(kind, eye, key=None):
        """The display through the optics (analytic or mesh path; ``key``: the attached optics
        of the pass), or the content seen directly: the scene (loaded once per kind) and this
        eye's sensor dict."""
        if kind == "display" and shapes is not None:
            sensor = eye.sensor_dict(vw, spec.spp, spec.seed)
        elif kind == "display":
            sensor = display_sensor(eye, key, spec.spp, spec.seed)
        else:
            sensor = eye.sensor_dict(None, spec.spp, spec.seed)
        if kind not in loaded:
            if kind == "display":
                sd = {"type": "scene", "display": layout.emitter_dict(display), **(shapes or {}),
                      "integrator": MESH_INTEGRATOR if shapes is not None else INTEGRATOR}
            elif content.path_traced:
                loaded[kind] = content_scene
            else:
                sd = scene_dict(content)
                sd["integrator"] = INTEGRATOR
            if kind not in loaded:
                loaded[kind] = load_scene(sd)
        if kind != "display" and content.path_traced:
            # The natural view of a Mitsuba scene: the eye placed in the scene's own frame, path-traced.
            sensor = eye.sensor_dict(content.to_scene, spec.spp, spec.seed)
            return loaded[kind], sensor, natural_integrator(content)
        return loaded[kind], sensor

    images = []
    try:
        jobs = [(f, kind) for f in spec.focus_mm for kind in (("display", "natural") if spec.natural
                                                              else ("display",))]
        it = jobs
        if progress:
            from ..progress import bar as tqdm

            it = tqdm(jobs, desc="retinal images", unit="img", leave=False)
        by_focus = {}
        for f, kind in it:
            def eye_for(w):
                return EyeSpec(spec.eye_model, spec.pupil_diameter_mm, float(f), (fx, fy), (W, H), wavelengths=w,
                               diffraction=diffraction)

            if kind == "natural" and spec.eye_model == "ideal" and not diffraction:
                # The ideal eye is dispersion-free: without diffraction its natural view is
                # the same at every wavelength, one pass.
                img, secs = render(*scene_for(kind, eye_for(None)))
            else:
                ps = passes if kind == "display" else nat_passes
                img, secs = render_passes([scene_for(kind, eye_for(w), key) for w, key in zip(ps, keys)], ps)
            if not np.all(np.isfinite(img)):
                raise FloatingPointError(f"non-finite pixels in the {kind} image at {f:g} mm")
            tag = f"{kind}_{f:g}mm"
            meta = dict(base_meta, kind=kind, focus_mm=f, spp=spec.spp, render_s=round(secs, 3))
            if kind == "natural":
                meta["wavelengths_nm"] = ";".join(",".join(f"{v:.2f}" for v in w.nm) for w in nat_passes)
            write_exr(out / f"{tag}.exr", img, meta)
            write_png(out / f"{tag}.png", img)
            by_focus.setdefault(f, {})[kind] = img
            images.append({"kind": kind, "focus_mm": float(f), "exr": f"{tag}.exr", "png": f"{tag}.png",
                           "spp": spec.spp, "render_s": round(secs, 3)})
            log(f"{kind:8s} focus {f:7.1f} mm: {W}x{H} at {spec.spp} spp in {secs:.1f} s")
        # The sharp reference: the natural view through a pinhole pupil (no defocus).
        eye = EyeSpec("ideal", 0.01, math.inf, (fx, fy), (W, H))
        reference, secs = render(*scene_for("natural", eye))
        write_exr(out / "reference_pinhole.exr", reference,
                  dict(base_meta, kind="reference", pupil_mm=0.01, spp=spec.spp, render_s=round(secs, 3)))
        write_png(out / "reference_pinhole.png", reference)
    finally:
        for key in keys:
            release(key)
    for rec in images:
        pair = by_focus[rec["focus_mm"]]
        if "natural" in pair and rec["kind"] != "natural":
            s, p = similarity(pair[rec["kind"]], pair["natural"])
            rec["ssim_vs_natural"], rec["psnr_vs_natural"] = s, (p if math.isfinite(p) else None)
            rec["exposure_vs_natural"] = exposure(pair["natural"], pair[rec["kind"]])
            rec["ssim_vs_natural_matched"] = ssim_matched(pair["natural"], pair[rec["kind"]])
    sheet = contact_sheet(out / "contact_sheet.png", spec.focus_mm, by_focus, spec, design, content)
    doc = {"design": design.path or design.name, "content": content.path, "cdp_mm": spec.cdp_mm,
           "cdp_diopters": cdp_D, "tunable_power_diopters": state.tunable_power_diopters,
           "pupil_diameter_mm": spec.pupil_diameter_mm, "eye_model": spec.eye_model,
           "mla_cells": spec.mla_cells, "optics": spec.optics,
           "wavelengths_nm": [list(w.nm) for w in passes],
           "natural_wavelengths_nm": [list(w.nm) for w in nat_passes], "spectral": spectral,
           "primaries": primaries_doc(content.primaries) if spectral else None, "diffraction": diffraction,
           **({"tessellation": spec.tessellation} if spec.optics == "mesh" else {}),
           "fov_deg": [fx, fy], "resolution": [W, H], "seed": spec.seed,
           "display": {"width": layout.width, "height": layout.height, "pixel_pitch_mm": layout.pixel_pitch,
                       "exr": "elemental_images.exr", "png": "elemental_images.png",
                       **ei.doc(), "method": spec.ei_method, "channel_wavelengths_nm": channel_wavelengths,
                       "aovs": {"depth": "depth.Z", "normal": "normal"}},
           "images": images,
           "reference": {"exr": "reference_pinhole.exr", "png": "reference_pinhole.png",
                         "pupil_diameter_mm": 0.01},
           "contact_sheet": sheet}
    stack = {"fov_deg": (fx, fy), "reference": reference, "content_scene": content,
             "images": {(k, f): v for f, pair in by_focus.items() for k, v in pair.items()}}
    for name, fn in analyses:
        doc[name] = fn(stack, content, out)
    doc["total_s"] = round(time.perf_counter() - t_all, 3)
    write_json(out / "index.json", doc)
    return doc, stack


def contact_sheet(path: Path, focus_mm, by_focus: dict, spec: FocalStackSpec, design, content) -> str:
    """Display (top) and natural (bottom) views per focus distance, labelled."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from ..fileio import save_figure

    kinds = [k for k in ("display", "natural") if any(k in by_focus[f] for f in focus_mm)]
    n = len(focus_mm)
    any_img = by_focus[focus_mm[0]]["display"]
    aspect = any_img.shape[0] / any_img.shape[1]
    fig, axes = plt.subplots(len(kinds), n, figsize=(3.6 * n, 3.6 * aspect * len(kinds) + 0.9), squeeze=False)
    for j, f in enumerate(focus_mm):
        for i, kind in enumerate(kinds):
            ax = axes[i, j]
            ax.imshow(_srgb8(by_focus[f][kind]), interpolation="lanczos")
            ax.set_xticks([])
            ax.set_yticks([])
            if i == 0:
                ax.set_title(f"focus {f:g} mm ({1000 / f:.2f} D)", fontsize=10)
            if j == 0:
                ax.set_ylabel("through the display" if kind == "display" else "natural view", fontsize=10)
    cdp = "inf" if math.isinf(spec.cdp_mm) else f"{spec.cdp_mm:g} mm"
    fig.suptitle(f"{Path(str(design.path or design.name)).name} + {Path(content.path).name}: CDP {cdp}, "
                 f"{spec.pupil_diameter_mm:g} mm pupil, {spec.eye_model} eye, {spec.spp} spp", fontsize=10)
    fig.tight_layout()
    save_figure(fig, path, dpi=110)
    plt.close(fig)
    return Path(path).name
