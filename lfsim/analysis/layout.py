"""Lens layout (y-z section with traced ray fans), spot diagrams and a summary.

This is a plain conventional-lens view of a design: first-order data, RMS
spot radius per field at the image surface, and two pictures.
"""

from __future__ import annotations

import math

import numpy as np

from ..fileio import save_figure, write_json
from ..optics.sampling import field_rays, pupil_grid
from ..optics.solids import element_section, glass_pairs


def _figure():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def spot_statistics(design, fo, rings: int = 8, wavelength_nm=None):
    """RMS and geometric spot radii (µm) per field at the image surface.

    Centred on the chief ray (pupil centre). Returns a list of dicts and the
    per-field spot points (local image-surface x, y in mm).
    """
    tracer = design.tracer()
    R_img, o_img = tracer.frames_numpy()[-1]
    pupil = pupil_grid(rings, "hexapolar")
    rows, spots = [], []
    for f in design.system.fields:
        o, d = field_rays(design.system, fo, f, pupil)
        r = design.trace(o, d, wavelength_nm=wavelength_nm)
        loc = (r.positions - o_img) @ R_img
        ok = r.status == 0
        if not ok[0]:
            rows.append({"field": f, "rays": int(ok.sum()), "rms_um": None, "geo_um": None,
                         "chief_x_mm": None, "chief_y_mm": None, "vignetted_fraction": float(1 - ok.mean())})
            spots.append(np.zeros((0, 2)))
            continue
        xy = loc[ok, :2]
        rel = xy - loc[0, :2]
        rows.append({
            "field": f,
            "rays": int(ok.sum()),
            "rms_um": float(1e3 * np.sqrt(np.mean(np.sum(rel**2, axis=1)))),
            "geo_um": float(1e3 * np.max(np.linalg.norm(rel, axis=1))),
            "chief_x_mm": float(loc[0, 0]),
            "chief_y_mm": float(loc[0, 1]),
            "vignetted_fraction": float(1 - ok.mean()),
        })
        spots.append(rel)
    return rows, spots


def plot_layout(design, fo, path, rays_per_field: int = 7, ray_sets=None, legend_title: str = "field",
                display=None, labels=None):
    """Draw the y-z section: surface profiles and a tangential fan per field.

    ``ray_sets``: instead of the fans, ``[(label, points (L, N, 3), ok (L, N))]`` drawn one
    colour per set (an InI design's sub-systems: :func:`ini_ray_sets`); ``display``:
    ``((y_min, y_max), z)``, a display drawn as a bar in the global y-z plane; ``labels``:
    ``{surface index: text}`` written beside those surfaces. A lenslet array's surfaces are
    drawn cell by cell along y."""
    labels = labels or {}
    plt = _figure()
    tracer = design.tracer()
    frames = tracer.frames_numpy()
    if ray_sets is None:
        ray_sets = []
        pupil = pupil_grid(rays_per_field, "fan_y")
        for f in design.system.fields:
            o, d = field_rays(design.system, fo, f, pupil)
            r = design.trace(o, d, record=True)
            pts = np.concatenate([o[None], r.path], axis=0)
            last = np.where(r.status == 0, len(r.path), r.failed_at)  # hits kept before a failure
            ok = np.arange(len(pts))[:, None] <= last[None, :]
            ray_sets.append((f"{f:g}{'°' if design.system.field_type == 'angle' else ' mm'}", pts, ok))
    fig, ax = plt.subplots(figsize=(10, 4.5))
    # Glass elements drawn as built (lfsim.optics.solids.element_section): both faces across
    # the rim about the element's axis, joined by the edge, so that a decentred, tilted or
    # wedged lens shows its blank; other surfaces over their own apertures.
    values = np.asarray(design.system.parameter_values(design.wavelength()))
    drawn = set()
    for i, j, rad in glass_pairs(design.system, tracer.names, values, len(design.surfaces)):
        front, back = element_section(tracer, values, i, j, rad)
        ok = np.isfinite(front[:, 0]) & np.isfinite(back[:, 0])
        if ok.sum() < 2:
            continue
        outline = np.concatenate([front[ok], back[ok][::-1], front[ok][:1]])
        ax.fill(outline[:, 2], outline[:, 1], color="tab:blue", alpha=0.08, lw=0)
        ax.plot(outline[:, 2], outline[:, 1], color="0.2", lw=1.2)
        drawn.update((i, j))
    for i, s in enumerate(design.surfaces):
        if s.interaction == "break" or i in drawn:
            continue
        R, o = frames[i]
        ap = s.aperture
        hits = np.concatenate([pts[i + 1, ok[i + 1]] for _, pts, ok in ray_sets if i + 1 < len(pts)] or
                              [np.zeros((0, 3))])
        if ap is not None:  # the aperture's extent along local y
            half = ap.radius if ap.kind == "circular" else ap.half_width[1]
            lo, hi = ap.decenter[1] - half, ap.decenter[1] + half
        elif len(hits):  # no aperture (an ideal lens, a dummy plane): where the drawn rays cross it
            y_loc = (hits - o) @ R[:, 1]
            pad = 0.05 * max(float(np.ptp(y_loc)), 1.0)
            lo, hi = float(np.min(y_loc)) - pad, float(np.max(y_loc)) + pad
        elif i < len(design.surfaces) - 1:
            lo, hi = -0.6 * fo.entrance_pupil_diameter, 0.6 * fo.entrance_pupil_diameter
        else:
            continue
        style = dict(color="0.2", lw=1.2) if s.interaction != "none" else dict(color="0.5", lw=0.8, ls="--")
        if s.interaction == "reflect":
            style = dict(color="tab:purple", lw=1.6)
        arr = design.system.arrays.get(s.array) if s.array is not None else None
        # A lenslet array: every cell of the section's column, each lenslet about its own vertex.
        cells = ([arr.center[1] + (n - (arr.n - 1) / 2) * arr.pitch[1] for n in range(arr.n)] if arr else [0.0])
        for yc in cells:
            y = np.linspace(max(lo, -arr.pitch[1] / 2) if arr else lo, min(hi, arr.pitch[1] / 2) if arr else hi, 101)
            z = tracer.sag_numpy(i, np.zeros_like(y), y)
            pts = np.stack([np.zeros_like(y), y + yc, z], axis=1) @ R.T + o
            ax.plot(pts[:, 2], pts[:, 1], **style)
        if i in labels:
            mid = pts[len(pts) // 2]
            ax.annotate(labels[i], (mid[2], mid[1]), xytext=(-8, 0), textcoords="offset points", fontsize=8,
                        color="0.3", ha="right", va="center",
                        bbox=dict(boxstyle="square,pad=0.1", fc="white", ec="none", alpha=0.8))
    if display is not None:  # the display's active area, y extent at its plane z
        (y0, y1), zd = display
        ax.plot([zd, zd], [y0, y1], color="k", lw=3, solid_capstyle="butt")
        ax.annotate("display", (zd, y1), xytext=(-6, 4), textcoords="offset points", fontsize=8, color="0.3")
    colors = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    for k, (label, pts, ok) in enumerate(ray_sets):
        for j in range(pts.shape[1]):
            keep = ok[:, j]
            ax.plot(pts[keep, j, 2], pts[keep, j, 1], color=colors[k % len(colors)], lw=0.6,
                    label=label if j == 0 else None)
    ax.set_aspect("equal")
    ax.set_xlabel("z (mm)")
    ax.set_ylabel("y (mm)")
    ax.set_title(f"{design.name}: layout (y-z section)")
    ax.legend(title=legend_title, fontsize=8, loc="upper left", bbox_to_anchor=(1.01, 1.0))
    ax.grid(alpha=0.3)
    save_figure(fig, path, dpi=130, bbox_inches="tight")
    plt.close(fig)


def wavelength_colour(nm: float):
    """An RGB colour for a wavelength (nm), for plots: matplotlib's turbo map over 400–700 nm."""
    import matplotlib

    return matplotlib.colormaps["turbo"](float(np.clip((nm - 400.0) / 300.0, 0.0, 1.0)))


def plot_spots(design, rows, spots, path, airy_um: float | None = None):
    """One panel per field: every design wavelength's spot about the primary chief ray,
    and the Airy disc of the primary wavelength (radius 1.22 λ F/#) dashed.

    ``spots``: ``{wavelength_nm: [points (K, 2) mm per field]}``.
    """
    plt = _figure()
    n = len(rows)
    fig, axes = plt.subplots(1, n, figsize=(3.2 * n, 3.6), squeeze=False)
    for f, (ax, row) in enumerate(zip(axes[0], rows)):
        lim = 1e-3
        for lam, per_field in spots.items():
            pts = per_field[f]
            if len(pts):
                ax.plot(1e3 * pts[:, 0], 1e3 * pts[:, 1], ".", ms=2, color=wavelength_colour(lam),
                        label=f"{lam:g} nm")
                lim = max(lim, 1e3 * np.max(np.abs(pts)))
        if airy_um is not None and np.isfinite(airy_um):
            t = np.linspace(0.0, 2.0 * np.pi, 181)
            ax.plot(airy_um * np.cos(t), airy_um * np.sin(t), "k--", lw=0.8, label=f"Airy r = {airy_um:.2f} µm")
            lim = max(lim, airy_um)
        lim *= 1.15
        ax.set_xlim(-lim, lim)
        ax.set_ylim(-lim, lim)
        ax.set_aspect("equal")
        unit = "°" if design.system.field_type == "angle" else " mm"
        rms = "n/a" if row["rms_um"] is None else f"{row['rms_um']:.2f} µm"
        ax.set_title(f"field {row['field']:g}{unit}\nRMS {rms}", fontsize=9)
        ax.set_xlabel("x (µm)")
        ax.grid(alpha=0.3)
    axes[0][0].set_ylabel("y (µm)")
    handles, labels = axes[0][0].get_legend_handles_labels()
    if handles:
        fig.legend(handles, labels, loc="lower center", ncol=len(labels), fontsize=8, markerscale=4,
                   frameon=False, bbox_to_anchor=(0.5, -0.1))
    fig.suptitle(f"{design.name}: spot diagrams at the image surface, about the "
                 f"{design.system.primary_wavelength_nm:g} nm chief ray (RMS at that wavelength)", fontsize=10)
    fig.tight_layout()
    save_figure(fig, path, dpi=130, bbox_inches="tight")
    plt.close(fig)


def ini_ray_sets(model, k: int):
    """An InI design's rays for :func:`plot_layout`: the top, middle and bottom lenslets of the
    middle column, each with the chief and ±y marginal rays (stop edge midpoints) of its EI's
    centre and of two points ±0.45 of the EI's height off it, in CDP state ``k``."""
    from ..ini.subsystems import ray_paths, sample

    M, N = model.arr.m, model.arr.n
    lenslets = list(dict.fromkeys([(M // 2, 0), (M // 2, N // 2), (M // 2, N - 1)]))
    subs = sample(model, lenslets=lenslets, depths=[k], fields=[[0.0, 0.0], [0.0, 0.9], [0.0, -0.9]])
    rho = np.array([[0.0, 0.0], [0.0, 1.0], [0.0, -1.0]])
    S, F = subs.display.shape[:2]
    per = F * len(rho)  # rays per sub-system: every field's chief and marginal rays, in one launch
    pts, ok = ray_paths(model, np.repeat(subs.display.reshape(-1, 2), len(rho), axis=0),
                        np.repeat(subs.m, per), np.repeat(subs.n, per), np.tile(rho, (S * F, 1)), k)
    return [(f"({subs.m[i] + 1}, {subs.n[i] + 1})", pts[:, i * per:(i + 1) * per], ok[:, i * per:(i + 1) * per])
            for i in range(S)]


def layout_report(design, out_dir) -> dict:
    """Write ``layout.png``, ``spots.png`` and ``summary.json`` into ``out_dir``
    (a folder replaced as a whole on success: see :func:`lfsim.fileio.atomic_dir`).

    An InI design (an ``[ini]`` section) is drawn with the rays of three lenslets' sub-systems
    at its middle CDP state (:func:`ini_ray_sets`), and its summary holds the InI first order
    of every CDP state and the package (``ini``, ``package``) instead of a conventional lens's
    focal lengths and spots, which a lenslet array does not have: ``spots.png`` is not written
    (per-lenslet spots and MTFs: ``lfsim analyze``)."""
    from ..fileio import atomic_dir

    if design.ini is not None:
        return _ini_layout_report(design, out_dir)
    fo = design.first_order()
    rows, spots = spot_statistics(design, fo)
    by_wl = {}
    for lam in design.system.wavelengths_nm:  # every wavelength about the primary chief ray
        r_l, s_l = spot_statistics(design, fo, wavelength_nm=lam)
        by_wl[lam] = [pts + ([a["chief_x_mm"] - b["chief_x_mm"], a["chief_y_mm"] - b["chief_y_mm"]]
                             if a["chief_x_mm"] is not None and b["chief_x_mm"] is not None else np.nan)
                      for pts, a, b in zip(s_l, r_l, rows)]
    lam0 = design.system.primary_wavelength_nm
    airy_um = 1.22 * lam0 * 1e-3 * fo.fno if fo.fno is not None and math.isfinite(fo.fno) else None
    summary = {
        "design": design.name,
        "file": design.path,
        "wavelength_nm": design.system.primary_wavelength_nm,
        "first_order": fo.as_dict(),
        "spots": rows,
        "airy_radius_um": airy_um,
        "images": {"layout": "layout.png", "spots": "spots.png"},
    }
    with atomic_dir(out_dir, "summary.json") as out:
        plot_layout(design, fo, out / "layout.png")
        plot_spots(design, rows, by_wl, out / "spots.png", airy_um)
        write_json(out / "summary.json", summary)
    return summary


def _ini_layout_report(design, out_dir) -> dict:
    from ..fileio import atomic_dir
    from ..ini.model import IniModel
    from ..ini.package import package

    model = IniModel(design)
    k = len(model.depths) // 2
    fo = design.first_order()
    summary = {
        "design": design.name,
        "file": design.path,
        "wavelength_nm": design.system.primary_wavelength_nm,
        "ini": {"lenslets": [model.arr.m, model.arr.n], "display_gap_mm": float(model.g),
                "drawn_cdp_diopters": model.depths[k],
                "first_order": {f"{D:g}": model.state(j).as_dict() for j, D in enumerate(model.depths)}},
        "package": package(model),
        "images": {"layout": "layout.png"},
    }
    sets = ini_ray_sets(model, k)
    with atomic_dir(out_dir, "summary.json") as out:
        half = 0.5 * model.arr.n * model.state(k).p_ei[1]
        plot_layout(design, fo, out / "layout.png", ray_sets=sets, legend_title=f"lenslet, CDP {model.depths[k]:g} D",
                    display=((-half, half), -model.g), labels={model.spec.viewing_window: "eye (viewing window)"})
        write_json(out / "summary.json", summary)
    return summary
