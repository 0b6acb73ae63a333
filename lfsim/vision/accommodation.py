"""The predicted accommodation response to a point shown by the display at a depth.

For each target depth, the retinal image of a broadband point (:mod:`lfsim.vision.psf`:
on the display path, the point as its elemental images show it at the display's CDP state;
in the natural view, the real point) is rendered for a sweep of the eye's accommodation.
Each state is scored by a retinal image-quality metric, and the predicted response is the
accommodation that maximizes it, as in the light-field display analyses of Huang & Hua,
*Opt. Express* 25(16):18508 (2017) and Qin et al., *Opt. Express* 29(5):7342 (2021).

The metric (:data:`METRIC`) is the **mean retinal MTF over a band of 3–10 cycles/degree**,
the modulation of the luminance PSF's optical transfer function averaged over the annulus
of spatial frequencies in that band. Accommodation is driven mainly by mid spatial
frequencies, most strongly around 3–5 cpd (Owens, *Vision Res.* 20:159 (1980); Mathews &
Kruger, *Vision Res.* 34:1967 (1994)); the band is a setting (``band_cpd``).

An accommodation state is the eye's focus distance at :data:`REFERENCE_NM` (555 nm, the
peak of the photopic luminosity function): the ideal eye (aberration- and dispersion-free)
is focused there at every wavelength; the Arizona eye's accommodation parameter is solved
so that it is focused there at 555 nm (:func:`lfsim.render.eye_models.solve_accommodation`),
and its longitudinal chromatic aberration then moves the focus at other wavelengths. A
monochromatic target at 450 or 650 nm thus shows the eye's chromatic aberration, and a
broadband natural target is seen best near its own depth.

The sweep uses the same random samples at every state (the same seed), so the noise of a
curve is common to its points and its peak is steady; the peak is refined by a parabola
through the best state and its two neighbours.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, replace

import numpy as np

from .focus_cues import refine_peak

#: Reference wavelength of an accommodation state (nm): the photopic luminosity peak.
REFERENCE_NM = 555.0
METRIC = "mean retinal MTF over 3-10 cpd (luminance)"


@dataclass
class AccommodationSpec:
    """What to sweep (diopters, mm, arcmin, cycles/degree)."""

    depths_d: tuple[float, ...] = (0.5, 1.0, 1.5, 2.0, 2.5)
    cdp_d: float | None = None  # default: the design's middle CDP
    pupil_mm: float = 4.0
    eye: str = "arizona"
    wavelength_nm: float | None = None  # None: spectral (the display primaries)
    diffraction: bool = True
    band_cpd: tuple[float, float] = (3.0, 10.0)
    step_d: float = 0.1
    margin_d: float = 0.5
    fov_arcmin: float = 96.0
    resolution: int = 96
    spp: int = 256
    seed: int = 0
    wavelength_samples: int = 4


def band_mtf(lum: np.ndarray, px_arcmin: float, band_cpd: tuple[float, float]) -> float:
    """Mean modulation of the OTF of a PSF image (H, W) over the annulus of spatial
    frequencies ``band_cpd`` (cycles/degree), each frequency radius weighted alike (the
    MTF's radial profile averaged over the band)."""
    H, W = lum.shape
    total = float(lum.sum())
    if not (math.isfinite(total) and total > 0):
        raise FloatingPointError("the PSF image holds no energy")
    F = np.abs(np.fft.fft2(lum / total))
    d_deg = px_arcmin / 60.0
    fy = np.fft.fftfreq(H, d=d_deg)[:, None]
    fx = np.fft.fftfreq(W, d=d_deg)[None, :]
    f = np.hypot(fx, fy)
    lo, hi = band_cpd
    df = 1.0 / (max(H, W) * d_deg)  # the frequency step: rings of that width
    edges = np.arange(lo, hi + 0.5 * df, df)
    if len(edges) < 2:
        edges = np.array([lo, hi])
    k = np.digitize(f.ravel(), edges) - 1
    sel = (k >= 0) & (k < len(edges) - 1)
    n = np.bincount(k[sel], minlength=len(edges) - 1)
    s = np.bincount(k[sel], weights=F.ravel()[sel], minlength=len(edges) - 1)
    ring = s[n > 0] / n[n > 0]
    if not len(ring):
        raise ValueError(f"band {band_cpd} cpd holds no frequency of a {W}x{H} image at {px_arcmin:.3g} arcmin/px")
    return float(ring.mean())


def peak(states: np.ndarray, scores: np.ndarray) -> float:
    """The accommodation of a curve's maximum: the best state, refined by the vertex of the
    parabola through it and its two neighbours (kept between them)."""
    return refine_peak(np.asarray(states, dtype=np.float64), np.asarray(scores, dtype=np.float64),
                       int(np.argmax(scores)))


def sweep_states(target_d: float, cdp_d: float, spec: AccommodationSpec) -> np.ndarray:
    """Accommodation states (D): from the nearer of target and CDP minus the margin to the
    farther plus it, in steps of ``step_d``, none beyond infinity (0 D)."""
    lo = max(0.0, min(target_d, cdp_d) - spec.margin_d)
    hi = max(target_d, cdp_d) + spec.margin_d
    n = int(round((hi - lo) / spec.step_d))
    return np.round(lo + spec.step_d * np.arange(n + 1), 9)


def _psf_spec(spec: AccommodationSpec, view: str, target_d: float, cdp_d: float):
    from .psf import PsfSpec

    return PsfSpec(view=view, depth_d=float(target_d), focus_d=float(target_d), eye=spec.eye,
                   pupil_mm=spec.pupil_mm, wavelength_nm=spec.wavelength_nm, diffraction=spec.diffraction,
                   cdp_d=cdp_d, fov_arcmin=spec.fov_arcmin, resolution=spec.resolution, spp=spec.spp,
                   seed=spec.seed, wavelength_samples=spec.wavelength_samples,
                   point_arcmin=spec.fov_arcmin / spec.resolution)


def curve(design, spec: AccommodationSpec, view: str, target_d: float, cdp_d: float, states,
          progress=None) -> np.ndarray:
    """Scores of ``states`` (D) for a point at ``target_d`` on one view."""
    from .psf import PsfRenderer

    out = np.empty(len(states))
    with PsfRenderer(design, _psf_spec(spec, view, target_d, cdp_d), log=lambda *_: None,
                     reference_nm=REFERENCE_NM) as r:
        for j, a in enumerate(states):
            img, _ = r.render_image(float(a))
            out[j] = band_mtf(r.luminance(img), r.px, spec.band_cpd)
            if progress:
                progress()
    return out


def response(design, spec: AccommodationSpec, log=print) -> dict:
    """The accommodation response to each of ``spec.depths_d`` (see the module docstring)."""
    from ..progress import bar

    ini = design.ini
    if ini is None:
        raise ValueError(f"{design.path}: the accommodation response needs an InI design (an [ini] section)")
    cdp_d = spec.cdp_d if spec.cdp_d is not None else float(ini.cdp_diopters[len(ini.cdp_diopters) // 2])
    spec = replace(spec, cdp_d=cdp_d)
    t0 = time.perf_counter()
    grids = [sweep_states(float(D), cdp_d, spec) for D in spec.depths_d]
    total = 2 * sum(len(g) for g in grids)
    log(f"accommodation: {len(spec.depths_d)} depths, CDP {cdp_d:g} D, eye {spec.eye} "
        f"({spec.pupil_mm:g} mm), {total} retinal images")
    b = bar(total=total, desc="accommodation", unit="image")
    points = []
    try:
        for D, states in zip(spec.depths_d, grids):
            disp = curve(design, spec, "display", float(D), cdp_d, states, progress=b.update)
            nat = curve(design, spec, "natural", float(D), cdp_d, states, progress=b.update)
            points.append({"target_d": float(D), "response_d": peak(states, disp),
                           "natural_response_d": peak(states, nat),
                           # A peak on the sweep's end: the maximum may lie beyond it (widen --margin-d).
                           "at_sweep_edge": bool(np.argmax(disp) in (0, len(states) - 1)),
                           "natural_at_sweep_edge": bool(np.argmax(nat) in (0, len(states) - 1)),
                           "curve": [[float(a), float(s)] for a, s in zip(states, disp)],
                           "natural_curve": [[float(a), float(s)] for a, s in zip(states, nat)]})
    finally:
        b.close()
    return {"design": str(design.path), "cdp_d": cdp_d, "pupil_mm": spec.pupil_mm, "eye": spec.eye,
            "metric": METRIC.replace("3-10", f"{spec.band_cpd[0]:g}-{spec.band_cpd[1]:g}"),
            "band_cpd": list(spec.band_cpd), "reference_nm": REFERENCE_NM,
            "wavelength_nm": spec.wavelength_nm, "diffraction": spec.diffraction, "spp": spec.spp,
            "resolution": spec.resolution, "fov_arcmin": spec.fov_arcmin, "seed": spec.seed,
            "points": points, "total_s": round(time.perf_counter() - t0, 3)}


def plot(doc: dict, path) -> None:
    """The response against the target (display and natural view, the target and CDP lines)
    and each target's score curves, written atomically to ``path`` (PNG)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from ..fileio import save_figure

    pts = doc["points"]
    t = np.array([p["target_d"] for p in pts])
    fig, (ax, bx) = plt.subplots(1, 2, figsize=(11, 4.6))
    lim = [0.0, max(float(t.max()), doc["cdp_d"]) + 0.5]
    ax.plot(lim, lim, color="0.75", lw=1, label="response = target")
    ax.axhline(doc["cdp_d"], color="tab:red", ls=":", lw=1, label=f"CDP {doc['cdp_d']:g} D")
    ax.plot(t, [p["natural_response_d"] for p in pts], "s--", color="tab:green", label="natural view")
    ax.plot(t, [p["response_d"] for p in pts], "o-", color="tab:blue", label="display")
    ax.set(xlim=lim, ylim=lim, xlabel="target depth (D)", ylabel="accommodation response (D)",
           title=f"{doc['eye']} eye, {doc['pupil_mm']:g} mm pupil")
    ax.set_aspect("equal")
    ax.legend(loc="upper left", fontsize=8)
    cmap = plt.get_cmap("viridis")
    for i, p in enumerate(pts):
        c = cmap(i / max(1, len(pts) - 1))
        a, s = np.array(p["curve"]).T
        an, sn = np.array(p["natural_curve"]).T
        bx.plot(a, s, "-", color=c, label=f"{p['target_d']:g} D")
        bx.plot(an, sn, ":", color=c)
        bx.axvline(p["response_d"], color=c, lw=0.6, alpha=0.6)
    bx.set(xlabel="accommodation (D, focus at 555 nm)", ylabel=doc["metric"],
           title="score curves (solid: display, dotted: natural)")
    bx.legend(fontsize=8, title="target")
    fig.tight_layout()
    save_figure(fig, path, dpi=110)
    plt.close(fig)


def write(out_dir, doc: dict) -> dict:
    """Write ``accommodation.json`` and ``accommodation.png`` atomically into ``out_dir``."""
    from pathlib import Path

    from ..fileio import atomic_dir, write_json

    with atomic_dir(out_dir, "accommodation.json") as tmp:
        tmp = Path(tmp)
        plot(doc, tmp / "accommodation.png")
        doc = dict(doc, png="accommodation.png")
        write_json(tmp / "accommodation.json", doc)
    return doc
