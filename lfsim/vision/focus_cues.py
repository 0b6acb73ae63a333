"""Focus-cue analysis of a focal stack (the paper's Fig. 9 experiment).

The content's depth along each image column is found by casting the eye's
chief rays into the content scene; columns are grouped into bands of equal
width, each labelled with its median depth.
The sharpness of a band is the energy of a band-pass (difference of
Gaussians, σ = 1 and 2.5 pixels: above Monte Carlo pixel noise, below the
texture's scale) of the retinal image, relative to the same energy in the
natural view through a pinhole pupil (everything sharp), so the texture's own
angular frequency content, which changes with distance, cancels: the ratio is
the fraction of the content's detail that reaches the retina. The profile is smoothed over
three bands; the band where it peaks (refined by a parabola through its
neighbours, in diopters) is where the eye sees the content sharpest.
"""

from __future__ import annotations

import math

import numpy as np

LUMA = np.array([0.2126, 0.7152, 0.0722])


def column_depths(content, fov_deg, width: int, height: int, rows: int = 9) -> np.ndarray:
    """Distance (mm, along the line of sight −z) of the content (a ContentScene) seen in each
    image column (median over ``rows`` rows across the image; NaN where nothing is hit)."""
    fx, fy = (math.radians(v) for v in fov_deg)
    ax = ((np.arange(width) + 0.5) / width - 0.5) * fx
    ay = (0.5 - (np.linspace(0.5, height - 0.5, rows)) / height) * fy
    AX, AY = np.meshgrid(ax, ay)
    d = np.stack([np.tan(AX), np.tan(AY), -np.ones_like(AX)], axis=-1).reshape(-1, 3)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    t, _ = content.first_surface(np.zeros_like(d), d)
    z = np.where(np.isfinite(t), t * -d[:, 2], np.nan)
    z = z.reshape(rows, width)
    out = np.full(width, np.nan)
    hit = ~np.all(np.isnan(z), axis=0)
    out[hit] = np.nanmedian(z[:, hit], axis=0)
    return out


def _bandpass(img: np.ndarray) -> np.ndarray:
    from skimage.filters import difference_of_gaussians

    return difference_of_gaussians(np.asarray(img, dtype=np.float64) @ LUMA, 1.0, 2.5)


def _bands(bands: int, width: int) -> int:
    """Bands of at least 3 columns each (at most ``bands``)."""
    return max(1, min(int(bands), width // 3))


def sharpness_profile(img: np.ndarray, reference: np.ndarray, depth_mm: np.ndarray, bands: int = 24,
                      margin: int = 4):
    """Per band of columns: (depth in diopters, sharpness ratio). Bands without content are
    dropped; a narrow image gets fewer bands (each at least 3 columns wide), a short one a
    smaller row margin."""
    a, b = _bandpass(img), _bandpass(reference)
    H, W = a.shape
    margin = min(margin, max(0, (H - 1) // 2))
    a, b = a[margin:H - margin], b[margin:H - margin]
    bands = _bands(bands, W)
    edges = np.linspace(0, W, bands + 1).astype(int)
    D, S = [], []
    for lo, hi in zip(edges[:-1], edges[1:]):
        dep = depth_mm[lo:hi]
        if np.any(np.isnan(dep)) or hi - lo < 3:
            continue
        ea = np.mean(a[:, lo:hi] ** 2)
        eb = np.mean(b[:, lo:hi] ** 2)
        if eb <= 0:
            continue
        D.append(1000.0 / np.median(dep))
        S.append(ea / eb)
    return np.array(D), np.array(S)


def _smoothed(D: np.ndarray, S: np.ndarray):
    """The profile in increasing depth (D), smoothed over three bands."""
    order = np.argsort(D)
    D, S = D[order], S[order]
    if len(S) >= 3:
        S = np.convolve(np.pad(S, 1, mode="edge"), np.ones(3) / 3.0, mode="valid")
    return D, S


def refine_peak(D: np.ndarray, S: np.ndarray, i: int) -> float:
    """Sample ``i``'s abscissa refined by the vertex of the parabola through it and its two
    neighbours (``D`` increasing), when that vertex is a maximum between them; ``D[i]``
    itself at either end, or where the parabola opens upward."""
    if 0 < i < len(D) - 1:
        (x0, x1, x2), (y0, y1, y2) = D[i - 1:i + 2], S[i - 1:i + 2]
        if x0 < x1 < x2:  # the parabola through the three points, in closed form
            a = ((y2 - y1) / (x2 - x1) - (y1 - y0) / (x1 - x0)) / (x2 - x0)
            if a < 0:
                b = (y1 - y0) / (x1 - x0) - a * (x0 + x1)
                v = -b / (2.0 * a)
                if x0 <= v <= x2:
                    return float(v)
    return float(D[i])


def peak_diopters(D: np.ndarray, S: np.ndarray) -> float | None:
    """Depth (D) of the sharpest band, refined by a parabola through it and its neighbours;
    None when no band has content."""
    if len(S) == 0:
        return None
    D, S = _smoothed(D, S)
    return refine_peak(D, S, int(np.argmax(S)))


#: A second peak of the smoothed profile counts when it lies this far (D) from the sharpest band.
RUNNER_UP_MIN_SEPARATION_D = 0.15
#: ``lfsim focal-stack`` names a second peak on the console when it reaches this fraction of the peak.
RUNNER_UP_NOTE_RATIO = 0.95


def runner_up(D: np.ndarray, S: np.ndarray) -> tuple[float, float] | None:
    """The smoothed profile's highest local maximum other than its peak, at least
    :data:`RUNNER_UP_MIN_SEPARATION_D` from it: ``(depth in D, its height over the peak's)``;
    None when the profile has no such second peak.

    A profile with two near-equal peaks has a sharpest band that Monte Carlo noise can move
    from one to the other: the ratio says how firmly the band is the sharpest."""
    if len(S) < 3:
        return None
    D, S = _smoothed(D, S)
    top = int(np.argmax(S))
    if S[top] <= 0:
        return None
    best = None
    for i in range(len(S)):
        left = S[i - 1] if i > 0 else -np.inf
        right = S[i + 1] if i < len(S) - 1 else -np.inf
        if i == top or not (S[i] > left and S[i] >= right) or abs(D[i] - D[top]) < RUNNER_UP_MIN_SEPARATION_D:
            continue
        if best is None or S[i] > S[best]:
            best = i
    if best is None:
        return None
    return refine_peak(D, S, best), float(S[best] / S[top])


def analyze(stack: dict, content_scene, out_dir=None, bands: int = 24) -> dict:
    """Focus-cue table of a rendered stack.

    ``stack``: {"fov_deg", "images": {(kind, focus_mm): image}, "reference": image}.
    Returns per focus distance and kind: the sharpest band's depth (D), its
    offset from the focus (D), the runner-up peak (:func:`runner_up`), and the profile; writes ``focus_cues.png`` and
    ``focus_cues.json`` to ``out_dir`` when given.
    """
    ref = stack["reference"]
    H, W = ref.shape[:2]
    bands = _bands(bands, W)
    depth = column_depths(content_scene, stack["fov_deg"], W, H)
    rows = []
    for (kind, f), img in sorted(stack["images"].items(), key=lambda kv: (kv[0][0], kv[0][1])):
        D, S = sharpness_profile(img, ref, depth, bands)
        peak = peak_diopters(D, S)
        second = runner_up(D, S)
        focus_D = 1000.0 / f
        far = np.abs(D - focus_D) > 0.5
        rows.append({"kind": kind, "focus_mm": float(f), "focus_diopters": focus_D,
                     "sharpest_diopters": peak, "offset_diopters": None if peak is None else peak - focus_D,
                     "sharpness_peak": float(np.max(S)) if len(S) else None,
                     "sharpness_far_mean": float(np.mean(S[far])) if np.any(far) else None,
                     "runner_up_diopters": None if second is None else second[0],
                     "runner_up_ratio": None if second is None else second[1],
                     "profile_diopters": [float(v) for v in D], "profile_sharpness": [float(v) for v in S]})
    seen = np.isfinite(depth)
    span = [float(np.min(1000 / depth[seen])), float(np.max(1000 / depth[seen]))] if seen.any() else None
    doc = {"bands": bands, "depth_range_diopters": span, "results": rows}
    if out_dir is not None:
        from pathlib import Path

        from ..fileio import write_json

        out = Path(out_dir)
        doc["plot"] = plot(doc, out / "focus_cues.png")
        write_json(out / "focus_cues.json", doc)
    return doc


def plot(doc: dict, path) -> str:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from ..fileio import save_figure

    kinds = sorted({r["kind"] for r in doc["results"]})
    fig, axes = plt.subplots(1, len(kinds), figsize=(5.2 * len(kinds), 3.8), squeeze=False)
    colors = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    for ax, kind in zip(axes[0], kinds):
        rs = [r for r in doc["results"] if r["kind"] == kind]
        for i, r in enumerate(rs):
            c = colors[i % len(colors)]
            ax.plot(r["profile_diopters"], r["profile_sharpness"], "o", ms=3, color=c, alpha=0.6)
            Ds, Ss = _smoothed(np.asarray(r["profile_diopters"]), np.asarray(r["profile_sharpness"]))
            ax.plot(Ds, Ss, "-", color=c, label=f"focus {r['focus_mm']:g} mm ({r['focus_diopters']:.2f} D)")
            ax.axvline(r["focus_diopters"], color=c, ls=":", lw=1)
            if r["sharpest_diopters"] is not None:
                ax.axvline(r["sharpest_diopters"], color=c, ls="--", lw=1)
            if (r.get("runner_up_ratio") or 0.0) >= RUNNER_UP_NOTE_RATIO:
                ax.axvline(r["runner_up_diopters"], color=c, ls="-.", lw=0.8)
        ax.set_xlabel("depth of the content along the wall (D)")
        ax.set_ylabel("sharpness / pinhole view")
        ax.set_title("through the display" if kind == "display" else "natural view")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    fig.suptitle("Focus cues: points = bands, line = smoothed over three bands; dotted = focus distance, "
                 f"dashed = sharpest band, dash-dot = a second peak at >= {100 * RUNNER_UP_NOTE_RATIO:.0f}% of it",
                 fontsize=9)
    fig.tight_layout()
    save_figure(fig, path, dpi=110)
    plt.close(fig)
    return "focus_cues.png"


def index_entry(stack: dict, content_scene, out) -> dict:
    """Run :func:`analyze` on a focal stack being written to ``out``; the ``focus_cues``
    entry of its ``index.json`` (an analysis for :func:`lfsim.render.focal_stack.focal_stack`)."""
    cues = analyze(stack, content_scene, out)
    keep = ("kind", "focus_mm", "focus_diopters", "sharpest_diopters", "offset_diopters", "sharpness_peak",
            "sharpness_far_mean", "runner_up_diopters", "runner_up_ratio")
    return {"json": "focus_cues.json", "png": cues["plot"],
            "sharpest": [{k: r[k] for k in keep} for r in cues["results"]]}


def focal_stack(design, content, out_dir, spec=None, **kw):
    """:func:`lfsim.render.focal_stack.focal_stack` with the focus-cue analysis
    (``focus_cues.json``/``.png`` and ``index.json``'s ``focus_cues``) unless
    ``spec.focus_cues`` is off."""
    from ..render.focal_stack import FocalStackSpec
    from ..render.focal_stack import focal_stack as render_stack

    spec = spec or FocalStackSpec()
    analyses = [("focus_cues", index_entry)] if spec.focus_cues else []
    return render_stack(design, content, out_dir, spec, analyses=analyses, **kw)
