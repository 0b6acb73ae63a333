"""The retinal point-spread function of a point at a depth, on the display path or in the natural view.

* **natural**: the real point (a self-luminous square of :data:`POINT_ARCMIN` per side, far
  below the eye's diffraction blur) at the depth, seen by the eye focused at the focus distance.
* **display**: the point as the InI display shows it at the CDP state: in every elemental
  image, the one pixel whose real chief ray (:func:`lfsim.content.visual_rays`, the
  elemental images' own rays) passes nearest the point, lit if that miss is within the
  pixel's own angular size (a lenslet whose view does not hold the point shows nothing);
  then the display seen through the design by the same eye.

Both are rendered by the retinal renderer (:mod:`lfsim.render`): spectral unless a
wavelength is given, with diffraction unless it is turned off. The figures are taken from
the image's luminance ``Y = 0.2126 R + 0.7152 G + 0.0722 B`` normalized to unit energy (in
the natural view the point's own energy, so the tail that falls outside the image counts;
on the display path the energy inside the image):
``fwhm_arcmin`` (the full width at half maximum of the azimuthal average about the
centroid), ``ee50_arcmin`` (the diameter of the circle about the centroid that holds half
the energy), ``peak`` (the unit-energy PSF's value at its centre, per arcmin², from a fit
to its core), ``energy_in_image`` and
``first_minimum_arcmin`` (the radius of the azimuthal average's first dark ring: its
minimum between 0.8 and 1.55 FWHM, where an Airy pattern's lies, or None).
"""

from __future__ import annotations

import math
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

VIEWS = ("display", "natural")
#: Side of the natural view's point (arcmin): a square far below the diffraction blur.
POINT_ARCMIN = 0.3
#: Luminance weights of linear sRGB (ITU-R BT.709).
LUMA = np.array([0.2126, 0.7152, 0.0722])


@dataclass
class PsfSpec:
    """What to render (diopters, mm, arcmin, nm)."""

    view: str = "display"
    depth_d: float = 1.0
    focus_d: float = 1.0
    eye: str = "ideal"
    pupil_mm: float = 3.0
    wavelength_nm: float | None = None  # None: spectral
    diffraction: bool = True
    cdp_d: float | None = None  # display: the CDP state (default: the design's middle CDP)
    fov_arcmin: float | None = None  # default: from the blur expected (see auto_fov)
    resolution: int = 161
    spp: int = 1024
    seed: int = 0
    wavelength_samples: int = 4
    point_arcmin: float = POINT_ARCMIN  # natural view: the point's side


def _distance_mm(diopters: float) -> float:
    return math.inf if diopters == 0 else 1000.0 / diopters


def auto_fov(spec: PsfSpec, view_aperture_mm: float) -> float:
    """Image width (arcmin): 3× the geometric defocus blur plus 16 Airy radii of the smallest
    aperture, at least 12 arcmin."""
    blur = abs(spec.focus_d - spec.depth_d) * spec.pupil_mm * 1e-3 * (180 * 60 / math.pi)
    lam = spec.wavelength_nm or 650.0
    airy = 1.22 * lam * 1e-6 / min(spec.pupil_mm, view_aperture_mm) * (180 * 60 / math.pi)
    return max(12.0, 3.0 * blur + 16.0 * airy)


def profile_stats(lum: np.ndarray, px_arcmin: float, total: float | None = None) -> dict:
    """Figures of a PSF image (H, W), pixels ``px_arcmin`` wide (see the module docstring).

    ``total``: the PSF's whole energy in the image's units (the sum its pixels would have
    if none fell outside), when it is known; else the image's own sum. The Airy pattern's
    tail is heavy (1 − EE ≈ 2 / (π x)): a window 16 Airy radii wide leaves about 2 % out.
    """
    inside = float(lum.sum())
    if not (math.isfinite(inside) and inside > 0):
        raise FloatingPointError("the PSF image holds no energy (the point is not seen)")
    total = inside if total is None else float(total)
    p = lum / total
    H, W = p.shape
    yy, xx = np.mgrid[0:H, 0:W]
    cx, cy = float((p * xx).sum()), float((p * yy).sum())
    # The centre from the core: the whole image's centroid is thrown about by the noise of
    # the far tail, and an off-centre profile is a blurred one. Refine it inside the circle
    # of twice the half-energy radius.
    for _ in range(4):
        rr = np.hypot(xx - cx, yy - cy)
        order = np.argsort(rr.ravel())
        r50 = float(rr.ravel()[order][np.searchsorted(np.cumsum(p.ravel()[order]), 0.5)])
        w = p * (rr <= max(2.0 * r50, 2.0))
        cx, cy = float((w * xx).sum() / w.sum()), float((w * yy).sum() / w.sum())
    r = np.hypot(xx - cx, yy - cy).ravel() * px_arcmin
    v = p.ravel()
    order = np.argsort(r)
    r_s, cum = r[order], np.cumsum(v[order])
    ee50 = 2.0 * float(np.interp(0.5, cum, r_s))
    # Azimuthal average in rings of half a pixel.
    dr_ = 0.5 * px_arcmin
    k = (r / dr_).astype(np.int64)
    n_ring = np.bincount(k)
    ring = np.bincount(k, weights=v) / np.maximum(n_ring, 1)
    rc = (np.arange(len(ring)) + 0.5) * dr_
    valid = n_ring > 0
    rc, ring = rc[valid], ring[valid]
    # The peak from the core: a least-squares fit a + b r² + c r⁴ to the rings inside the
    # radius holding 40 % of the energy (the few pixels at the very centre alone are too
    # noisy); the half-maximum radius from a straight line through the rings between 35 and
    # 65 % of it (one noisy ring does not decide where the profile crosses).
    r40 = float(np.interp(0.4, cum, r_s))
    core = rc <= max(r40, 3.5 * dr_)
    wts = np.sqrt(n_ring[valid][core].astype(np.float64))
    A = np.stack([np.ones(core.sum()), rc[core] ** 2, rc[core] ** 4], axis=1) * wts[:, None]
    coef = np.linalg.lstsq(A, ring[core] * wts, rcond=None)[0]
    top = float(coef[0]) if coef[0] > 0 else float(ring[:3].max())  # unit-energy PSF per pixel
    # A PSF whose centre is not its peak (a defocused disc, dark in the middle): the maximum
    # is the smoothed profile's, and the half maximum is found outside it.
    sm5 = np.convolve(ring, np.ones(5) / 5.0, mode="same")
    i_max = int(np.argmax(sm5))
    ringed = True
    if sm5[i_max] > 1.15 * top:
        top = float(sm5[i_max])
        ringed = False  # no central peak, so no first dark ring to speak of
    fwhm = None
    below = i_max + np.nonzero(ring[i_max:] < 0.5 * top)[0]
    if len(below):
        i0 = int(below[0])
        band = np.arange(max(0, i0 - 8), min(len(ring), i0 + 8))
        band = band[(ring[band] > 0.35 * top) & (ring[band] < 0.65 * top)]
        if len(band) >= 2:
            slope, icpt = np.polyfit(rc[band], ring[band], 1, w=np.sqrt(n_ring[valid][band]))
            fwhm = 2.0 * float((0.5 * top - icpt) / slope) if slope < 0 else None
        if fwhm is None:
            fwhm = 2.0 * float(rc[i0])
    first_min = None
    # The first dark ring: the smoothed profile's minimum between 0.8 and 1.55 FWHM (an Airy
    # pattern's is at 1.22 λ/D = 1.18 FWHM, its first bright ring at 1.59 FWHM).
    if fwhm is not None and ringed:
        win = max(1, int(round(0.1 * fwhm / dr_)))
        sm = np.convolve(ring, np.ones(win) / win, mode="same")
        sel = np.nonzero((rc >= 0.8 * fwhm) & (rc <= 1.55 * fwhm))[0]
        if len(sel) >= 3:
            i = int(sel[np.argmin(sm[sel])])
            if sel[0] < i < sel[-1]:  # a minimum inside the window, not its edge
                first_min = float(rc[i])
    return {"fwhm_arcmin": fwhm, "ee50_arcmin": ee50, "peak": top / px_arcmin ** 2,
            # A Monte Carlo estimate: noise can lift it past 1 when nearly all energy is inside.
            "energy_in_image": min(inside / total, 1.0),
            "first_minimum_arcmin": first_min, "centroid_arcmin": [(cx + 0.5 - W / 2) * px_arcmin,
                                                                  (H / 2 - cy - 0.5) * px_arcmin]}


def point_display(model, layout, depth_d: float) -> tuple[np.ndarray, int]:
    """The display image (H, W, 3) of a point on the line of sight at ``depth_d``, and the
    number of elemental images that show it."""
    from ..content import visual_rays

    centres = layout.pixel_centers().reshape(-1, 2)
    o, d, ok = visual_rays(model, layout, centres, "real", 0)
    if depth_d == 0:
        miss = np.arccos(np.clip(-d[:, 2], -1.0, 1.0))
    else:
        P = np.array([0.0, 0.0, -1000.0 / depth_d])
        v = P - o
        t = np.einsum("ij,ij->i", v, d)
        miss = np.linalg.norm(v - t[:, None] * d, axis=1) / np.maximum(t, 1e-9)
        miss[t <= 0] = np.inf
    miss[~ok] = np.inf
    m, n = layout.lenslet_of(centres)
    lens = m * layout.n + n
    img = np.zeros(len(centres), dtype=np.float32)
    shown = 0
    W = layout.width
    for L in np.unique(lens):
        idx = np.nonzero(lens == L)[0]
        j = idx[np.argmin(miss[idx])]
        # The pixel's own angular size: the angle to its row neighbour's chief ray.
        nb = j + 1 if (j + 1) % W and lens[min(j + 1, len(lens) - 1)] == L else j - 1
        px_angle = float(np.arccos(np.clip(np.dot(d[j], d[nb]), -1.0, 1.0)))
        if ok[j] and ok[nb] and miss[j] <= 0.75 * px_angle:
            img[j] = 1.0
            shown += 1
    return np.repeat(img.reshape(layout.height, layout.width)[..., None], 3, axis=-1), shown


class PsfRenderer:
    """A point at one depth set up once (the display image, the optics, the loaded scene),
    rendered for any eye focus: :meth:`render`. ``reference_nm``: the wavelength at which the
    Arizona eye's accommodation is solved for the focus distance (the ideal eye has none)."""

    def __init__(self, design, spec: PsfSpec, log=print, reference_nm: float = 550.0):
        from ..content import content_from_dict, scene_dict
        from ..ini.model import model_at_depth
        from ..render import mitsuba
        from ..render.analytic import ReverseOptics
        from ..render.display import DisplayLayout
        from ..render.display_eye import attach
        from ..render.focal_stack import INTEGRATOR, load_scene
        from ..render.spectra import describe, monochrome, natural_primaries, primaries_doc, spectral

        if spec.view not in VIEWS:
            raise ValueError(f"view = {spec.view!r}: expected one of {', '.join(VIEWS)}")
        mitsuba()
        self.spec, self.reference_nm, self.keys = spec, float(reference_nm), []
        self.doc = {"view": spec.view, "depth_d": spec.depth_d, "eye": spec.eye, "pupil_mm": spec.pupil_mm,
                    "diffraction": spec.diffraction, "spp": spec.spp, "seed": spec.seed}
        if spec.view == "display":
            ini = design.ini
            if ini is None:
                raise ValueError(f"{design.path}: --view display needs an InI design (an [ini] section)")
            cdp_d = spec.cdp_d if spec.cdp_d is not None else float(ini.cdp_diopters[len(ini.cdp_diopters) // 2])
            model = model_at_depth(design, cdp_d)
            layout = DisplayLayout.from_model(model, 0)
            aperture = float(min(model.arr.pitch))
            self.doc["cdp_d"] = cdp_d
            design_nm = model.lam
        else:
            aperture, design_nm = spec.pupil_mm, 550.0
        # The natural view's point is a real, broadband one; the display shows its primaries.
        self.passes = (monochrome(spec.wavelength_nm) if spec.wavelength_nm is not None
                       else spectral(spec.wavelength_samples,
                                     natural_primaries() if spec.view == "natural" else None))
        self.doc["wavelengths_nm"] = [list(p.nm) for p in self.passes]
        self.doc["primaries"] = primaries_doc() if spec.wavelength_nm is None else None
        self.doc["design_wavelength_nm"] = design_nm
        self.fov = spec.fov_arcmin or auto_fov(spec, aperture)
        self.N = int(spec.resolution)
        self.px = self.fov / self.N
        self.doc.update(fov_arcmin=self.fov, resolution=self.N, pixel_arcmin=self.px)
        self.log = log
        self.log(f"psf: {spec.view} view, point at {spec.depth_d:g} D, eye ({spec.eye}, {spec.pupil_mm:g} mm), "
                 f"{describe(self.passes)}, diffraction {'on' if spec.diffraction else 'off'}, "
                 f"{self.N}x{self.N} px over {self.fov:.1f} arcmin")
        if spec.view == "natural":
            L = _distance_mm(spec.depth_d)
            dist = 1e6 if math.isinf(L) else L
            a = 0.5 * dist * math.tan(math.radians(spec.point_arcmin / 60.0))
            content = content_from_dict({"objects": [{"corners": [[-a, -a, -dist], [a, -a, -dist], [-a, a, -dist]],
                                                      "texture": {"type": "constant"}}]}, "<psf point>")
            self.scene = load_scene(dict(scene_dict(content), integrator=INTEGRATOR))
        else:
            display, shown = point_display(model, layout, spec.depth_d)
            self.doc["elemental_images_showing_the_point"] = shown
            if shown == 0:
                raise ValueError(f"depth {spec.depth_d:g} D: no elemental image of {design.path} shows a point there")
            pupil = spec.pupil_mm if spec.diffraction else None
            self.keys = [attach(ReverseOptics(model, 0, wavelengths=w, diffraction_pupil_mm=pupil))
                         for w in self.passes]
            self.scene = load_scene({"type": "scene", "display": layout.emitter_dict(display),
                                     "integrator": INTEGRATOR})

    def close(self) -> None:
        from ..render.display_eye import release

        for key in self.keys:
            release(key)
        self.keys = []

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    def render_image(self, focus_d: float) -> tuple[np.ndarray, float]:
        """The PSF image (H, W, 3) float32 with the eye focused at ``focus_d``, and its render seconds."""
        from ..render.display_eye import sensor_dict as display_sensor
        from ..render.eye import EyeSpec
        from ..render.focal_stack import render, render_passes

        spec, N, fov = self.spec, self.N, self.fov

        def eye_for(w):
            return EyeSpec(spec.eye, spec.pupil_mm, _distance_mm(focus_d), (fov / 60.0, fov / 60.0), (N, N),
                           wavelength_nm=self.reference_nm, wavelengths=w, diffraction=spec.diffraction)

        if spec.view == "natural":
            if spec.eye == "ideal" and not spec.diffraction:
                # Dispersion-free and geometric: the same image at every wavelength.
                img, secs = render(self.scene, eye_for(None).sensor_dict(None, spec.spp, spec.seed))
            else:
                jobs = [(self.scene, eye_for(w).sensor_dict(None, spec.spp, spec.seed)) for w in self.passes]
                img, secs = render_passes(jobs, self.passes)
        else:
            jobs = [(self.scene, display_sensor(eye_for(w), key, spec.spp, spec.seed))
                    for w, key in zip(self.passes, self.keys)]
            img, secs = render_passes(jobs, self.passes)
        if not np.all(np.isfinite(img)):
            raise FloatingPointError("non-finite pixels in the PSF image")
        return img, secs

    def luminance(self, img: np.ndarray) -> np.ndarray:
        return img.astype(np.float64) @ LUMA

    def render(self, focus_d: float) -> tuple[np.ndarray, dict]:
        """Render with the eye focused at ``focus_d``; returns ``(image, figures and settings)``."""
        t0 = time.perf_counter()
        img, secs = self.render_image(focus_d)
        # The natural view's point has a known energy: radiance 1 over its solid angle, in pixels.
        total = (self.spec.point_arcmin / self.px) ** 2 if self.spec.view == "natural" else None
        doc = dict(self.doc, focus_d=focus_d)
        doc.update(profile_stats(self.luminance(img), self.px, total))
        doc["render_s"] = round(secs, 3)
        doc["total_s"] = round(time.perf_counter() - t0, 3)
        return img, doc


def render_psf(design, spec: PsfSpec, log=print) -> tuple[np.ndarray, dict]:
    """Render the PSF; returns ``(image (H, W, 3) float32, figures and settings)``."""
    t0 = time.perf_counter()
    with PsfRenderer(design, spec, log=log) as r:
        img, doc = r.render(spec.focus_d)
    doc["total_s"] = round(time.perf_counter() - t0, 3)
    return img, doc


def write_psf(out_dir, img: np.ndarray, doc: dict, meta: dict) -> dict:
    """Write ``psf.exr`` (linear), ``psf.png`` (scaled to its peak) and ``psf.json`` atomically."""
    from ..fileio import atomic_dir, write_json
    from ..render.focal_stack import write_exr, write_png

    with atomic_dir(out_dir, "psf.json") as tmp:
        tmp = Path(tmp)
        write_exr(tmp / "psf.exr", img, {**meta, "kind": "psf", "pixel_arcmin": doc["pixel_arcmin"]})
        peak = float(img.max())
        write_png(tmp / "psf.png", img / peak if peak > 0 else img)
        doc = dict(doc, exr="psf.exr", png="psf.png", spec=asdict(PsfSpec(**{k: v for k, v in meta.items()
                                                                              if k in PsfSpec.__dataclass_fields__})))
        write_json(tmp / "psf.json", doc)
    return doc
