"""Pictures of the InI metrics, like the paper's Figs. 7 and 8.

* ``contrast_map.png`` (Fig. 7a): contrast at the Nyquist frequency of every
  sampled field, placed at its paraxial visual angle.
* ``mtf_lenslets.png`` (Fig. 7b): diffraction MTF of the centre field of the
  centre and two corner lenslets; ``mtf_depths.png`` (Fig. 7c): the centre
  lenslet at every CDP depth.
* ``distortion_grid.png`` (Fig. 8a): paraxial grid of virtual EI centres (black)
  and the real chief rays (blue asterisks), per depth.
* ``footprints.png`` (Fig. 8b/c): footprint envelopes on the viewing window of
  every field of chosen lenslets (colours) over the paraxial ones (black).
* ``through_focus.png`` (with ``--through-focus``): the contrast at Nyquist against the
  eye's focus (mean over the fields per CDP state, and chosen fields per orientation), and
  maps over the lenslet array of each EI centre's best focus relative to its CDP (the
  curvature of the virtual image across the lenslets) and of its astigmatism.
"""

from __future__ import annotations

import textwrap
from pathlib import Path

import numpy as np

from ..fileio import save_figure

DEG = 180.0 / np.pi


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _pick_depth(model, prefer=1.0, subs=None) -> int:
    ks = np.arange(len(model.depths)) if subs is None else np.unique(subs.k)
    return int(ks[np.argmin(np.abs(np.array(model.depths)[ks] - prefer))])


def _nearest(subs, k, m, n) -> int | None:
    sel = np.flatnonzero(subs.k == k)
    if len(sel) == 0:
        return None
    d = (subs.m[sel] - m) ** 2 + (subs.n[sel] - n) ** 2
    return int(sel[np.argmin(d)])


def _angles(r):
    return np.degrees(np.arctan(r))


def contrast_map(res, path, k=None):
    plt = _plt()
    model, subs = res["model"], res["subs"]
    k = _pick_depth(model, subs=subs) if k is None else k
    sel = subs.k == k
    chief = res["sets"].slices["chief"]
    pos = _angles(res["r_par"][sel][:, :, chief][:, :, 0])  # (S, F, 2) degrees
    c = res["contrast"][sel]
    fig, ax = plt.subplots(figsize=(8, 5), dpi=130)
    sc = ax.scatter(pos[..., 0].ravel(), pos[..., 1].ravel(), c=c.ravel(), cmap="viridis", vmin=0,
                    vmax=max(1e-9, float(np.max(c))), s=22, edgecolors="none")
    fig.colorbar(sc, ax=ax, label=f"contrast at {res['nyquist_cpd']:.2f} cycles/deg (Nyquist)")
    ax.set_xlabel("horizontal visual angle (deg)")
    ax.set_ylabel("vertical visual angle (deg)")
    ax.set_aspect("equal")
    from .ini_analysis import contrast_min

    worst = float(np.min(contrast_min(res)[sel]))
    found = f" (worst {worst:.3f}, searched between fields)" if res.get("refined") else ""
    # over the whole figure (axes and colour bar), wrapped: a long design name never runs under the bar
    fig.suptitle(textwrap.fill(model.design.name, 95) + "\n"
                 + f"contrast at Nyquist, CDP {model.depths[k]:g} D: min {np.min(c):.3f}, mean {np.mean(c):.3f} "
                 f"over {c.size} fields{found}", fontsize=9)
    save_figure(fig, path, bbox_inches="tight")
    plt.close(fig)


def _mtf_plot(res, picks, path, title):
    plt = _plt()
    f = res["freqs_cpd"]
    fig, ax = plt.subplots(figsize=(7, 4.5), dpi=130)
    colors = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    for j, (label, i) in enumerate(picks):
        col = colors[j % len(colors)]
        ax.plot(f, res["dif"][i, 0, :, 0], color=col, label=f"{label} horizontal")
        ax.plot(f, res["dif"][i, 0, :, 1], color=col, ls="--", label=f"{label} vertical")
    ax.axvline(res["nyquist_cpd"], color="k", lw=0.8, ls=":")
    ax.axhline(0.2, color="grey", lw=0.6, ls=":")
    ax.set_xlim(0, f[-1])
    ax.set_ylim(0, 1.02)
    ax.set_xlabel("angular frequency (cycles/deg)")
    ax.set_ylabel("diffraction MTF")
    ax.set_title(title)
    ax.legend(fontsize=7, ncol=2)
    save_figure(fig, path, bbox_inches="tight")
    plt.close(fig)


def mtf_lenslets(res, path, k=None):
    model, subs = res["model"], res["subs"]
    k = _pick_depth(model, subs=subs) if k is None else k
    M, N = model.arr.m, model.arr.n
    picks = []
    for m, n in ((M // 2, N // 2), (0, 0), (M - 1, 0)):
        i = _nearest(subs, k, m, n)
        if i is not None and all(i != p for _, p in picks):
            picks.append((f"lenslet ({subs.m[i] + 1},{subs.n[i] + 1})", i))
    _mtf_plot(res, picks, path, f"Centre field MTF, CDP {model.depths[k]:g} D")


def mtf_depths(res, path):
    model, subs = res["model"], res["subs"]
    picks = []
    for k, D in enumerate(model.depths):
        i = _nearest(subs, k, model.arr.m // 2, model.arr.n // 2)
        if i is not None:
            picks.append((f"{D:g} D", i))
    _mtf_plot(res, picks, path, f"Centre lenslet ({model.arr.m // 2 + 1},{model.arr.n // 2 + 1}), "
              "centre field, by CDP depth")


def distortion_grid(res, path):
    plt = _plt()
    model, subs = res["model"], res["subs"]
    chief = res["sets"].slices["chief"]
    ks = [int(k) for k in np.unique(subs.k)]
    nd = len(ks)
    fig, axes = plt.subplots(1, nd, figsize=(5.2 * nd, 4.2), dpi=130, squeeze=False)
    for k, ax in zip(ks, axes[0]):
        sel = np.flatnonzero(subs.k == k)
        par = _angles(res["r_par"][sel, 0, chief][:, 0])
        real = _angles(res["r"][sel, 0, chief][:, 0])
        ms, ns = subs.m[sel], subs.n[sel]
        for key, other in ((ms, ns), (ns, ms)):
            for v in np.unique(key):
                line = np.flatnonzero(key == v)
                line = line[np.argsort(other[line])]
                ax.plot(par[line, 0], par[line, 1], color="k", lw=0.7)
        ax.plot(real[:, 0], real[:, 1], "*", color="tab:blue", ms=5)
        gd = res["gd"][sel][res["chief_ok"][sel, 0]]
        gd = gd if gd.size else np.zeros(1)
        ax.set_title(f"CDP {model.depths[k]:g} D: GD max {np.max(gd):.3f}°, mean {np.mean(gd):.3f}°", fontsize=9)
        ax.set_xlabel("horizontal (deg)")
        ax.set_ylabel("vertical (deg)")
        ax.set_aspect("equal")
    fig.suptitle(f"{model.design.name}: virtual EI centres, paraxial (black grid) vs real chief rays (*)")
    save_figure(fig, path, bbox_inches="tight")
    plt.close(fig)


def footprints(res, path, k=None):
    plt = _plt()
    model, subs = res["model"], res["subs"]
    k = _pick_depth(model, subs=subs) if k is None else k
    per = res["sets"].slices["perimeter"]
    M, N = model.arr.m, model.arr.n
    wanted = [(m, n) for n in (0, N // 2, N - 1) for m in (0, M // 2, M - 1)]
    fig, ax = plt.subplots(figsize=(6.5, 6), dpi=130)
    colors = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    done = []
    for m, n in wanted:
        i = _nearest(subs, k, m, n)
        if i is None or i in done:
            continue
        done.append(i)
        col = colors[len(done) % len(colors)]
        for f in range(subs.fields.shape[0]):
            ok = res["bundle"].ok[i, f, per]
            real = res["bundle"].pos[i, f, per][ok]
            par = res["par"][i, f, per, :2]
            ax.fill(par[:, 0], par[:, 1], fill=False, ec="k", lw=0.5,
                    label="paraxial" if not done[1:] and f == 0 else None)
            if len(real):
                ax.fill(real[:, 0], real[:, 1], fill=False, ec=col, lw=0.9,
                        label=f"({subs.m[i] + 1},{subs.n[i] + 1})" if f == 0 else None)
    r = 0.5 * model.spec.pupil_diameter
    ax.add_patch(plt.Circle((0, 0), r, fill=False, ls=":", color="grey"))
    ax.set_aspect("equal")
    ax.set_xlabel("viewing window x (mm)")
    ax.set_ylabel("viewing window y (mm)")
    pa = res["pa"][subs.k == k][res["pa_ok"][subs.k == k]]
    pa = pa if pa.size else np.zeros(1)
    ax.set_title(f"Footprints on the viewing window, CDP {model.depths[k]:g} D\n"
                 f"paraxial (black) vs real; PA max {np.max(pa):.3f}, mean {np.mean(pa):.3f}; "
                 f"eye pupil {2 * r:g} mm (dotted)", fontsize=9)
    # beside the axes, so it never covers a footprint
    ax.legend(fontsize=7, title="real, lenslet (m,n)", title_fontsize=7, loc="upper left",
              bbox_to_anchor=(1.02, 1.0), borderaxespad=0.0)
    save_figure(fig, path, bbox_inches="tight")
    plt.close(fig)


def through_focus(res, path, k=None):
    """Through-focus contrast and the best-focus maps of :func:`lfsim.analysis.ini_analysis.through_focus`."""
    plt = _plt()
    model, subs, tf = res["model"], res["subs"], res["through_focus"]
    k = _pick_depth(model, subs=subs) if k is None else k
    sel = subs.k == k
    off = tf["offsets_d"]
    fig, axes = plt.subplots(1, 3, figsize=(17, 5.2), dpi=120, layout="constrained")
    ax = axes[0]
    for kk, D in enumerate(model.depths):
        s = subs.k == kk
        if np.any(s):
            ax.plot(off, np.mean(np.min(tf["contrast"][:, s], axis=-1), axis=(1, 2)), lw=2,
                    label=f"mean, CDP {D:g} D")
    colors = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    M, N = model.arr.m, model.arr.n
    picks = []
    for m, n in ((M // 2, N // 2), (M // 2, 0), (0, 0)):
        i = _nearest(subs, k, m, n)
        if i is not None and i not in picks:
            picks.append(i)
    for j, i in enumerate(picks):
        col = colors[(j + len(model.depths)) % len(colors)]
        lab = f"lenslet ({subs.m[i] + 1},{subs.n[i] + 1}) centre field"
        ax.plot(off, tf["contrast"][:, i, 0, 0], color=col, lw=1, label=lab + ", horizontal")
        ax.plot(off, tf["contrast"][:, i, 0, 1], color=col, lw=1, ls="--", label=lab + ", vertical")
    ax.axvline(0.0, color="k", lw=0.8, ls=":")
    ax.axhline(0.2, color="grey", lw=0.6, ls=":")
    ax.set_xlim(off[0], off[-1])
    ax.set_ylim(0, 1.02)
    ax.set_xlabel("eye focus − CDP (D)")
    ax.set_ylabel(f"contrast at {res['nyquist_cpd']:.2f} cycles/deg (Nyquist)")
    ax.set_title(f"through focus (lenslets at CDP {model.depths[k]:g} D)", fontsize=9)
    ax.legend(fontsize=6, loc="upper center", bbox_to_anchor=(0.5, -0.14), ncol=2)
    best = tf["best_d"][sel][:, 0]  # each sampled lenslet's EI-centre field
    grid = np.full((2, N, M), np.nan)
    grid[0, subs.n[sel], subs.m[sel]] = 0.5 * (best[:, 0] + best[:, 1])
    grid[1, subs.n[sel], subs.m[sel]] = best[:, 0] - best[:, 1]
    for ax, v, label, cmap in ((axes[1], grid[0], "best focus − CDP", "coolwarm"),
                               (axes[2], grid[1], "astigmatism, horizontal − vertical", "PuOr")):
        lim = max(0.05, float(np.nanmax(np.abs(v)))) if np.any(np.isfinite(v)) else 1.0
        im = ax.imshow(np.ma.masked_invalid(v), origin="lower", cmap=cmap, vmin=-lim, vmax=lim,
                       extent=(0.5, M + 0.5, 0.5, N + 0.5))
        fig.colorbar(im, ax=ax, label=label + " (D)", shrink=0.8)
        from matplotlib.ticker import MaxNLocator

        ax.xaxis.set_major_locator(MaxNLocator(integer=True))
        ax.yaxis.set_major_locator(MaxNLocator(integer=True))
        ax.set_xlabel("lenslet m")
        ax.set_ylabel("lenslet n")
        ax.set_title(f"{label}, per lenslet (EI centre)" + ("\nblank: not sampled" if np.any(np.isnan(v)) else ""),
                     fontsize=9)
    at_cdp = np.mean(np.min(tf["contrast"][len(off) // 2, sel], axis=-1))
    fig.suptitle(textwrap.fill(model.design.name, 120) + "\n"
                 + f"CDP {model.depths[k]:g} D: contrast mean {at_cdp:.3f} at the CDP, "
                 f"{np.mean(tf['common_best'][sel]):.3f} with each field at its best focus", fontsize=9)
    save_figure(fig, path, bbox_inches="tight")
    plt.close(fig)


def write_all(res, out_dir) -> list[str]:
    """Write every picture into ``out_dir``; returns their file names."""
    out = Path(out_dir)
    names = ["contrast_map.png", "mtf_lenslets.png", "mtf_depths.png", "distortion_grid.png", "footprints.png"]
    contrast_map(res, out / names[0])
    mtf_lenslets(res, out / names[1])
    mtf_depths(res, out / names[2])
    distortion_grid(res, out / names[3])
    footprints(res, out / names[4])
    if res.get("through_focus") is not None:
        names.append("through_focus.png")
        through_focus(res, out / names[-1])
    return names
