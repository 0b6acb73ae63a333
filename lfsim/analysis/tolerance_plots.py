"""Plots of a tolerance run: metric histograms, cumulative yield curves, the sensitivity chart.

All from the records and ``summary.json`` of :func:`lfsim.tolerance.monte_carlo.run_tolerance`
(matplotlib, Agg; written atomically).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..fileio import save_figure

#: (metric, label, target name, kind) of the panels.
PANELS = (
    ("gd_max_deg", "GD max (deg, Eq. 11)", "gd_max_deg", "max"),
    ("pa_max", "PA max (Eq. 12)", "pa_max", "max"),
    ("contrast_nyquist_min", "contrast at Nyquist, min", "contrast_nyquist_min", "min"),
    ("rms_spot_mean_arcmin", "RMS spot mean (arcmin)", "rms_spot_mean_arcmin", "max"),
)


def _values(records, key):
    return np.array([r["metrics"][key] for r in records
                     if r.get("metrics") and r["metrics"].get(key) is not None], dtype=np.float64)


def histograms(doc: dict, records: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(PANELS), figsize=(4.2 * len(PANELS), 3.4))
    for ax, (key, label, target, _) in zip(axes, PANELS):
        v = _values(records, key)
        if v.size:
            ax.hist(v, bins=max(10, min(50, v.size // 10)), color="#4878a8", alpha=0.85)
        nom = (doc.get("nominal") or {}).get(key)
        if nom is not None:
            ax.axvline(nom, color="k", ls="--", lw=1, label="nominal")
        if target in doc["targets"]:
            ax.axvline(doc["targets"][target], color="#c03030", lw=1.5, label="target")
        ax.set_xlabel(label)
        ax.set_ylabel("trials")
        ax.legend(fontsize=7)
    fig.suptitle(f"{doc['design']}: {doc['trials']} trials, yield {_pct(doc['yield'])}")
    fig.tight_layout()
    save_figure(fig, path, dpi=110)
    plt.close(fig)


def cumulative(doc: dict, records: list[dict], path: Path) -> None:
    """Empirical cumulative distributions: for a 'max' metric the fraction of trials at or
    below x (the yield if the target were x), for a 'min' metric the fraction at or above x."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(PANELS), figsize=(4.2 * len(PANELS), 3.4))
    n = max(1, len(records))
    for ax, (key, label, target, kind) in zip(axes, PANELS):
        v = np.sort(_values(records, key))
        if v.size:
            if kind == "max":
                ax.step(v, np.arange(1, v.size + 1) / n, where="post", color="#4878a8")
            else:
                ax.step(v, 1.0 - np.arange(v.size) / n, where="post", color="#4878a8")
        if target in doc["targets"]:
            ax.axvline(doc["targets"][target], color="#c03030", lw=1.5, label="target")
            y = doc["yield_by_target"].get(target)
            if y is not None:
                ax.axhline(y, color="#c03030", lw=0.8, ls=":")
        ax.set_ylim(0, 1.02)
        ax.set_xlabel(label)
        ax.set_ylabel("fraction of trials " + ("<= x" if kind == "max" else ">= x"))
        ax.grid(alpha=0.3)
    fig.suptitle(f"cumulative yield curves (yield, all targets: {_pct(doc['yield'])})")
    fig.tight_layout()
    save_figure(fig, path, dpi=110)
    plt.close(fig)


def sensitivity_chart(doc: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = doc["sensitivity"]
    fig, ax = plt.subplots(figsize=(7.5, 0.35 * len(rows) + 1.4))
    names = [r["name"] for r in rows][::-1]
    vals = [(5.0 if r["margin_used_inf"] else (r["margin_used"] or 0.0)) for r in rows][::-1]
    colors = ["#c03030" if v >= 1 else "#4878a8" for v in vals]
    ax.barh(names, vals, color=colors)
    ax.axvline(1.0, color="k", lw=0.8, ls="--")
    ax.set_xlabel("margin used at ± limit (1 = the whole margin to the target)")
    ax.set_title("sensitivity: each tolerance alone at its limit")
    fig.tight_layout()
    save_figure(fig, path, dpi=110)
    plt.close(fig)


def _pct(y):
    return "n/a" if y is None else f"{100 * y:.1f} %"


def write_all(doc: dict, records: list[dict], out_dir) -> list[str]:
    out = Path(out_dir)
    histograms(doc, records, out / "histograms.png")
    cumulative(doc, records, out / "cumulative.png")
    sensitivity_chart(doc, out / "sensitivity.png")
    return ["histograms.png", "cumulative.png", "sensitivity.png"]
