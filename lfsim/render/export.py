"""A design's display path as a Mitsuba scene that plain ``mitsuba`` renders.

``lfsim export DESIGN --mitsuba DIR [--content C]`` writes ``DIR/scene.xml``
with its PLY meshes and the elemental images:

* the **display**: a one-sided rectangle at the display plane whose area
  emitter shows ``elemental_images.exr``, the elemental images of the content
  (lfsim's real chief rays; a Mitsuba-scene content path-traced);
* the **optics** as meshes of the same analytic surfaces lfsim traces
  (:func:`lfsim.render.optics_scene.optics_shapes`) with Mitsuba's built-in
  BSDFs: ``dielectric`` for every refracting or TIR face (its indices at the
  design's primary wavelength; Fresnel reflection included, as Mitsuba models
  it), a perfect ``conductor`` for mirrors, black ``diffuse`` for rims, mounts
  and masks;
* the **eye**: Mitsuba's ``thinlens`` camera at the viewing window, its
  aperture the pupil, focused at the focus distance, over the display's field;
* a ``path`` integrator deep enough for every face of the chain.

Mitsuba has no ideal (paraxial) lens. Each ``type = "paraxial"`` surface is
written as an equivalent equi-convex (or equi-concave) N-BK7 singlet of the
same power at the same place — centred on the thin lens's plane, its thick-lens
power matched exactly, 0.2 mm thick at its thinnest — and the substitution is
listed in ``export.json``. Designs whose only ideal lens is a weak tunable lens
(a few dioptres) are reproduced closely; an ideal eyepiece becomes a real
singlet with its aberrations.
"""

from __future__ import annotations

import copy
import math
from pathlib import Path

import numpy as np

#: Glass and thinnest thickness (mm) of the singlets standing in for ideal lenses.
GLASS = "N-BK7"
MIN_THICKNESS_MM = 0.2
#: Keys of a design file that describe the optics (the rest is InI, optimization, ...).
OPTICS_KEYS = ("name", "description", "system", "object", "arrays", "surfaces")


def singlet(power: float, n: float, radius: float) -> tuple[float, float]:
    """Curvature ``c`` (front +c, back −c) and centre thickness of an equi-convex/-concave
    singlet of index ``n`` in air with thick-lens power ``power`` (1/mm) over a clear
    ``radius``: P = 2(n−1)c − (n−1)² t c² / n, thinnest point ``MIN_THICKNESS_MM``."""
    t = MIN_THICKNESS_MM
    c = 0.0
    for _ in range(60):
        disc = 1.0 - t * power / n
        if disc <= 0:
            raise ValueError(f"no singlet of {GLASS} reaches {1000 * power:.4g} D at {t:.3g} mm thickness")
        c = n / ((n - 1.0) * t) * (1.0 - math.sqrt(disc)) if power != 0 else 0.0
        if abs(c) * radius >= 0.999:
            raise ValueError(f"an equivalent {GLASS} singlet of {1000 * power:.4g} D cannot cover a "
                             f"{radius:.3g} mm radius (its radius of curvature {1 / abs(c):.3g} mm)")
        sag = (1.0 - math.sqrt(1.0 - (c * radius) ** 2)) / abs(c) if c else 0.0
        t_new = MIN_THICKNESS_MM + (2.0 * sag if c > 0 else 0.0)
        if abs(t_new - t) < 1e-12:
            break
        t = t_new
    return c, t


def plain_system(design, values=None, wavelength_nm=None):
    """The design's optics with every ideal lens replaced by its equivalent singlet.

    Returns ``(System, substitutions)``: the new system (no [ini] or optimization
    sections) and per replaced surface ``{surface, power_diopters, glass, radius_mm,
    center_thickness_mm, clear_radius_mm}``.
    """
    from ..design.loader import system_from_dict
    from ..optics.materials import lookup
    from .meshes import SurfaceModel, _region_grid, clear_region, default_extent

    model = SurfaceModel(design, values, wavelength_nm)
    system = model.system
    raw = copy.deepcopy({k: v for k, v in design.raw.items() if k in OPTICS_KEYS})
    surfaces = raw.get("surfaces", [])
    if len(surfaces) != len(system.surfaces):
        raise ValueError(f"{design.path}: {len(surfaces)} surface tables but {len(system.surfaces)} surfaces")
    n = float(lookup(GLASS).index(model.wavelength_nm))
    extent = default_extent(system)
    out, subs = [], []
    carried = 0.0  # power of ideal lenses in contact with the next one (thickness 0): one singlet
    for i, (s, surf) in enumerate(zip(surfaces, system.surfaces)):
        if surf.interaction != "paraxial":
            out.append(s)
            continue
        if abs(model.index_before(i) - 1.0) > 1e-9:
            raise ValueError(f"{design.path}: surface {surf.name}: an ideal lens in a medium of index "
                             f"{model.index_before(i):.6g} has no singlet stand-in (air only)")
        gap = float(s.get("thickness", 0.0))
        P = model.power(i) + carried
        carried = 0.0
        nxt = system.surfaces[i + 1] if i + 1 < len(system.surfaces) else None
        base = {k: v for k, v in s.items() if k not in ("type", "focal_length", "power", "comment", "thickness",
                                                         "virtual")}
        if (gap == 0.0 and nxt is not None and nxt.interaction == "paraxial" and surf.array is None
                and nxt.array is None and "global_position" not in surfaces[i + 1]):
            carried = P  # no surface of its own: its power joins the lens in contact after it
            continue
        if P == 0.0:
            out.append({**base, "dummy": True, "thickness": gap})
            continue
        xy = _region_grid(clear_region(system, i, extent), 16)[0]
        radius = float(np.max(np.hypot(xy[:, 0], xy[:, 1])))
        if surf.array is not None:
            a = system.arrays[surf.array]
            radius = min(radius, 0.5 * math.hypot(*a.pitch))
        c, t = singlet(P, n, radius)
        name = surf.name
        front = {**base, "name": f"{name}a", "curvature": c, "thickness": t, "material": GLASS,
                 "comment": f"stand-in for the ideal lens {name} ({1000 * P:+.6g} D): {GLASS} singlet"}
        back = {k: v for k, v in base.items() if k not in ("global_position", "tilt", "decenter", "name")}
        back.update({"name": f"{name}b", "curvature": -c, "material": "air"})
        if "semi_diameter" not in s and surf.array is None and surf.aperture is None:
            front["semi_diameter"] = back["semi_diameter"] = radius
        if "global_position" in s:  # placed by position: the front vertex on the lens's plane
            back["thickness"] = gap - t
        else:  # centred on the lens's plane: the surface before it gives up half the thickness
            prev = out[-1] if out else raw.get("object")  # the first surface: the object distance gives
            room = "thickness" if out else "distance"
            if not isinstance(prev, dict) or room not in prev or float(prev[room]) < 0.5 * t:
                raise ValueError(f"{design.path}: surface {name}: no room before it to centre its "
                                 f"{t:.3g} mm singlet stand-in")
            if out:
                out[-1] = dict(prev, thickness=float(prev["thickness"]) - 0.5 * t)
            else:
                raw["object"] = dict(prev, distance=float(prev["distance"]) - 0.5 * t)
            back["thickness"] = gap - 0.5 * t
        out += [front, back]
        subs.append({"surface": name, "power_diopters": 1000.0 * P, "glass": GLASS, "index": n,
                     "radius_mm": (1.0 / c), "center_thickness_mm": t, "clear_radius_mm": radius})
    raw["surfaces"] = out
    return system_from_dict(raw, f"{design.path or design.name} (paraxial lenses as singlets)"), subs


def _plain_bsdf(b: dict) -> dict:
    from .bsdfs import INTERFACE, THINLENS

    t = b.get("type")
    if t == INTERFACE:
        return {"type": "dielectric", "int_ior": float(b["int_ior"]), "ext_ior": float(b["ext_ior"])}
    if t == THINLENS:
        raise ValueError("an ideal lens is left in the exported optics")
    return b


def export_mitsuba(design, content, out_dir, cdp_mm: float, focus_mm: float, pupil_mm: float,
                   resolution: tuple[int, int] | None = None, spp: int = 256, tessellation: float = 1.0,
                   ei_spp: int = 16, seed: int = 0, log=print) -> dict:
    """Write the plain-Mitsuba scene of ``design`` showing ``content`` (module docstring)
    into ``out_dir`` (atomically); returns the ``export.json`` document."""
    from ..content import shade_display
    from ..fileio import atomic_dir, write_json
    from ..ini.model import model_at_depth
    from . import mitsuba
    from .display import DisplayLayout
    from .focal_stack import write_exr
    from .meshes import tessellation as density
    from .optics_scene import optics_shapes, write_scene_xml

    mi = mitsuba()
    cdp_D = 0.0 if math.isinf(cdp_mm) else 1000.0 / cdp_mm
    model = model_at_depth(design, cdp_D)
    layout = DisplayLayout.from_model(model, 0)
    fx, fy = model.state(0).fov_deg
    W, H = resolution or (512, max(1, int(round(512 * fy / fx))))
    system, subs = plain_system(design, model.values(0), model.lam)
    for s in subs:
        log(f"ideal lens {s['surface']} ({s['power_diopters']:+.4g} D) written as an {s['glass']} singlet "
            f"(R = {s['radius_mm']:+.5g} mm, {s['center_thickness_mm']:.3g} mm thick)")
    ei = shade_display(model, content, layout, spp=ei_spp, seed=seed)
    with atomic_dir(out_dir, "scene.xml") as tmp:
        tmp = Path(tmp)
        (tmp / "meshes").mkdir(parents=True, exist_ok=True)
        exr = tmp / "meshes" / "elemental_images.exr"
        write_exr(exr, ei.image, {"kind": "elemental_images", "design": design.path or design.name,
                                  "content": content.path, "cdp_mm": cdp_mm})
        shapes = optics_shapes(system, wavelength_nm=model.lam, mesh_dir=tmp / "meshes", **density(tessellation))
        for v in shapes.values():
            v["bsdf"] = _plain_bsdf(v["bsdf"])
        T = mi.ScalarTransform4f
        w, h = layout.size_mm
        flip = T().translate([0.0, 1.0, 0.0]) @ T().scale([1.0, -1.0, 1.0])
        display = {"type": "rectangle",
                   "to_world": T().translate([layout.center[0], layout.center[1], layout.z])
                   @ T().scale([0.5 * w, 0.5 * h, 1.0]),
                   "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.0, 0.0, 0.0]}},
                   "emitter": {"type": "area", "radiance": {
                       "type": "bitmap", "filename": str(exr), "raw": True, "filter_type": "bilinear",
                       "wrap_mode": "clamp", "to_uv": flip}}}
        vw = np.eye(4)
        vw[:3, :3], vw[:3, 3] = model.R_vw, model.o_vw
        # Mitsuba's cameras look along local +z with +x to the image's left: turned 180 deg about
        # y, the eye looks along visual -z with the viewer's right on the image's right.
        cam = vw @ np.diag([-1.0, 1.0, -1.0, 1.0])
        sensor = {"type": "thinlens", "to_world": T(cam.tolist()), "fov": float(fx), "fov_axis": "x",
                  "aperture_radius": 0.5 * float(pupil_mm), "focus_distance": float(focus_mm),
                  "near_clip": 0.01, "far_clip": 1e7,
                  "film": {"type": "hdrfilm", "width": int(W), "height": int(H), "rfilter": {"type": "box"}},
                  "sampler": {"type": "independent", "sample_count": int(spp), "seed": int(seed)}}
        scene = {"type": "scene",
                 "integrator": {"type": "path", "max_depth": 256, "rr_depth": 1024, "hide_emitters": False},
                 "eye": sensor, "display": display, **shapes}
        write_scene_xml(scene, tmp, "scene.xml")
        doc = {"design": design.path or design.name, "content": content.path, "cdp_mm": cdp_mm,
               "focus_mm": focus_mm, "pupil_mm": pupil_mm, "wavelength_nm": model.lam,
               "resolution": [int(W), int(H)], "spp": int(spp), "scene": "scene.xml",
               "elemental_images": "meshes/elemental_images.exr", "shapes": len(shapes),
               "paraxial_substitutions": subs,
               "render": "mitsuba -m scalar_rgb scene.xml -o retina.exr (any RGB variant)"}
        write_json(tmp / "export.json", doc)
    return doc
