"""The physical parts of a system's optical path: lenses, prisms, lenslet arrays, mirrors.

Shared by the meshes of a scene (:mod:`lfsim.render.meshes`) and the merit's
glass constraints (:mod:`lfsim.optics.solids`).
"""

from __future__ import annotations

from dataclasses import dataclass

from .prescription import System


@dataclass
class Component:
    """A physical part of the optical path: its kind, surfaces and name.

    kind : ``"lens"`` (refracting surfaces with glass between), ``"prism"``
    (a glass run with reflect/tir surfaces), ``"lenslet_array"`` (refracting
    surfaces of an array group), ``"paraxial"``, ``"paraxial_array"``,
    ``"aperture_array"`` (a dummy array surface with an aperture), ``"mirror"``
    (a mirror in the ambient medium) or ``"face"`` (a lone refracting surface).
    """

    kind: str
    surfaces: list[int]
    name: str


def components(system: System) -> list[Component]:
    """The physical parts of the optical path, in order (last surface excluded:
    it is the image / viewing window, the sensor's business)."""
    surf = system.surfaces
    last = len(surf) - 1
    media = system.media()
    amb = system.object_material
    groups = system.array_groups()
    out: list[Component] = []
    i = 0
    while i < last:
        s = surf[i]
        if s.array is not None:
            idx = [j for j in groups[s.array] if j < last]
            refr = [j for j in idx if surf[j].interaction == "refract"]
            if refr:
                out.append(Component("lenslet_array", refr, s.array))
            out += [Component("paraxial_array", [j], surf[j].name) for j in idx if surf[j].interaction == "paraxial"]
            out += [Component("aperture_array", [j], surf[j].name) for j in idx
                    if surf[j].interaction == "none" and surf[j].aperture is not None]
            i = groups[s.array][-1] + 1
            continue
        if s.interaction == "paraxial":
            out.append(Component("paraxial", [i], s.name))
        elif s.interaction == "reflect" and media[i] == amb:
            out.append(Component("mirror", [i], s.name))
        elif s.interaction in ("refract", "tir") and media[i] == amb and media[i + 1] != amb:
            run, j = [i], i + 1
            while j < last and media[j + 1] != amb:
                if surf[j].interaction in ("refract", "reflect", "tir"):
                    run.append(j)
                j += 1
            if j < last and surf[j].interaction == "refract":
                run.append(j)
                kind = "prism" if any(surf[k].interaction in ("reflect", "tir") for k in run) else "lens"
                out.append(Component(kind, run, f"{surf[run[0]].name}_{surf[run[-1]].name}"))
            else:  # glass up to the image: single faces
                out += [Component("face", [k], surf[k].name) for k in run if surf[k].same_as is None]
            i = j + 1
            continue
        elif s.interaction in ("refract", "tir", "reflect") and media[i] != media[i + 1]:
            out.append(Component("face", [i], s.name))
        i += 1
    return out
