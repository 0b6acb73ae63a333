"""First-order (Gaussian) optics: focal lengths, focal points, pupils, magnification.

Two independent routes give the 2×2 reduced ray-transfer matrices
``(y, ν = n·u) → (y', ν')`` from which every first-order quantity follows:

* :func:`paraxial_matrices` — the classic y-nu trace of a rotationally
  symmetric, untilted system (signed indices after mirrors);
* :func:`parabasal_matrices` — for any system (tilted, decentered, freeform):
  the optical-axis ray (OAR: from the object centre through the stop centre)
  is found by real-ray aiming, and the exact derivatives of parabasal rays
  about it are taken with Dr.Jit forward-mode AD in one batched launch
  (the zero-step limit of the finite parabasal rays lens-design programs use).

Both give ``M_front`` (first vertex plane → stop) and ``M_total`` (first
vertex plane → image surface), per meridian (x and y); :func:`from_matrices`
turns them into the quantities below. Positions are measured along the axis
(the OAR), from the first surface vertex for object-side quantities and from
the image surface for image-side quantities, as lens-design programs do;
``bfl`` is from the last surface before the image.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np

from ..backend import compact_kernels, to_numpy
from .prescription import System


@dataclass
class FirstOrder:
    efl: float  # 1/φ (mm)
    efl_x: float  # 1/φ in the x meridian (differs for anamorphic systems)
    bfl: float  # last surface → back focal point (mm)
    front_focal_point: float  # from the first vertex (negative: in front of it)
    back_focal_point: float  # from the image surface
    front_principal_plane: float  # from the first vertex
    back_principal_plane: float  # from the image surface
    entrance_pupil_position: float  # from the first vertex
    entrance_pupil_diameter: float
    exit_pupil_position: float  # from the image surface
    exit_pupil_diameter: float
    paraxial_image_distance: float  # from the last surface before the image
    magnification: float  # paraxial transverse magnification (0 for an object at infinity)
    fno: float  # efl / EPD (image-space F-number, infinite conjugate)
    working_fno: float  # 1 / (2 n' |u'|) of the paraxial marginal ray
    n_object: float
    n_image: float
    wavelength_nm: float
    method: str  # "paraxial" or "parabasal"

    def as_dict(self) -> dict:
        return {k: (None if isinstance(v, float) and not math.isfinite(v) else v)
                for k, v in asdict(self).items()}

    #: Unit of each quantity ("" for a pure number).
    UNITS = {"efl": "mm", "efl_x": "mm", "bfl": "mm", "front_focal_point": "mm", "back_focal_point": "mm",
             "front_principal_plane": "mm", "back_principal_plane": "mm", "entrance_pupil_position": "mm",
             "entrance_pupil_diameter": "mm", "exit_pupil_position": "mm", "exit_pupil_diameter": "mm",
             "paraxial_image_distance": "mm", "magnification": "x", "fno": "", "working_fno": "",
             "n_object": "", "n_image": "", "wavelength_nm": "nm", "method": ""}


def _transfer(t, n):
    return np.array([[1.0, t / n], [0.0, 1.0]])


def is_rotationally_symmetric(system: System) -> bool:
    for s in system.surfaces:
        if s.xy or s.same_as is not None or s.array or s.interaction == "break" or s.global_position:
            return False
        if any(s.decenter) or any(s.tilt):
            return False
    return True


def paraxial_matrices(system: System, wavelength_nm: float):
    """y-nu trace of a rotationally symmetric system.

    Returns ``(M_front, M_total, n_object, n_image)``; ``M_front`` ends just
    after the stop surface, ``M_total`` at the image surface. Indices carry
    the sign of the propagation direction (negative after an odd number of
    reflections), so mirrors and negative thicknesses work as usual.
    """
    surf = system.surfaces
    stop = system.stop_index if system.stop_index is not None else 0
    n = float(system.object_material.index(wavelength_nm))
    n_obj = n
    M = np.eye(2)
    M_front = None
    for i, s in enumerate(surf):
        if i > 0:
            M = _transfer(surf[i - 1].thickness, n) @ M
        if s.interaction == "refract":
            n2 = math.copysign(float(s.material.index(wavelength_nm)), n)
            M = np.array([[1.0, 0.0], [-(n2 - n) * s.curvature, 1.0]]) @ M
            n = n2
        elif s.interaction in ("reflect", "tir"):
            M = np.array([[1.0, 0.0], [2.0 * n * s.curvature, 1.0]]) @ M
            n = -n
        elif s.interaction == "paraxial":
            # an ideal lens bends along the propagation direction (tan θ' = tan θ − hφ/|n|), so in
            # reduced angles n·u of either sign its power enters as is
            M = np.array([[1.0, 0.0], [-s.power, 1.0]]) @ M
        if i == stop:
            M_front = M.copy()
    return M_front, M, n_obj, n


def from_matrices(system: System, M_front, M_total, n_obj, n_img, wavelength_nm, t_last,
                  method: str, efl_x: float | None = None) -> FirstOrder:
    """First-order quantities from the reduced matrices (see the module docstring).

    ``t_last`` is the axial distance from the last surface before the image
    to the image surface.
    """
    A, B, C, D = M_total.ravel()
    Af, Bf = M_front[0]
    nabs_o, nabs_i = abs(n_obj), abs(n_img)
    phi = -C
    inf = math.inf
    efl = 1.0 / phi if phi != 0 else inf
    # Back focal point: a ray from infinity (ν = 0) crosses the axis at −n'A/C.
    bfp = -n_img * A / C if C != 0 else inf
    ffp = n_obj * D / C if C != 0 else -inf
    bpp = bfp - n_img / phi if phi != 0 else inf
    fpp = ffp + n_obj / phi if phi != 0 else -inf
    epp = n_obj * Bf / Af if Af != 0 else inf

    s_obj = system.object_distance
    ap_t, ap_v = system.aperture_type, system.aperture_value
    if ap_t == "epd":
        epd = ap_v
    elif ap_t == "fno":
        epd = abs(efl) / ap_v if ap_v > 0 else 0.0
    else:  # object-space NA, paraxial u = NA / n
        epd = 2.0 * (s_obj + epp) * ap_v / nabs_o if math.isfinite(s_obj) else 0.0
    # Paraxial marginal ray at the first vertex plane.
    if math.isinf(s_obj):
        y0, nu0 = 0.5 * epd, 0.0
    else:
        nu0 = n_obj * 0.5 * epd / (s_obj + epp) if s_obj + epp != 0 else 0.0
        y0 = nu0 * s_obj / n_obj
    y_stop = Af * y0 + Bf * nu0
    M_back = M_total @ np.linalg.inv(M_front)
    Bb, Db = M_back[0, 1], M_back[1, 1]
    xpp = -n_img * Bb / Db if Db != 0 else inf
    xpd = 2.0 * abs(y_stop / Db) if Db != 0 else inf
    y1 = A * y0 + B * nu0
    nu1 = C * y0 + D * nu0
    z_img = -n_img * y1 / nu1 if nu1 != 0 else inf  # from the image surface
    pid = t_last + z_img
    mag = A + z_img * C / n_img if math.isfinite(s_obj) and math.isfinite(z_img) else 0.0
    fno = abs(efl) / epd if epd > 0 else inf
    wfno = nabs_i / (2.0 * abs(nu1)) if nu1 != 0 else inf
    return FirstOrder(
        efl=efl, efl_x=efl if efl_x is None else efl_x, bfl=t_last + bfp,
        front_focal_point=ffp, back_focal_point=bfp,
        front_principal_plane=fpp, back_principal_plane=bpp,
        entrance_pupil_position=epp, entrance_pupil_diameter=epd,
        exit_pupil_position=xpp, exit_pupil_diameter=xpd,
        paraxial_image_distance=pid, magnification=mag, fno=fno, working_fno=wfno,
        n_object=nabs_o, n_image=nabs_i, wavelength_nm=wavelength_nm, method=method,
    )


# --------------------------------------------------------------- parabasal
def _perp_basis(d, up):
    """Right-handed basis (e1, e2) ⟂ d with e2 as close as possible to ``up``."""
    d = d / np.linalg.norm(d)
    e2 = up - np.dot(up, d) * d
    if np.linalg.norm(e2) < 1e-8:
        e2 = np.array([1.0, 0.0, 0.0]) - d[0] * d
    e2 /= np.linalg.norm(e2)
    e1 = np.cross(e2, d)
    return e1, e2


def find_axis_ray(tracer, P_np, stop: int, n_obj: float, object_distance: float):
    """Real-ray aim of the optical-axis ray through the stop centre.

    Returns the OAR origin (on the first vertex plane, or at the object point)
    and direction in the global frame.
    """
    import drjit as dr

    P = tracer.params(values=P_np)
    R_stop, o_stop = tracer.frames_numpy(P)[stop]

    def shoot(U):
        """Rays of aim parameters U (K, 2): stop hits in the stop frame (K, 2), status, o, d."""
        K = len(U)
        if math.isinf(object_distance):
            o = np.column_stack([U, np.zeros(K)])
            d = np.tile([0.0, 0.0, 1.0], (K, 1))
        else:
            o = np.tile([0.0, 0.0, -object_distance], (K, 1))
            d = np.column_stack([U, np.ones(K)])
        with dr.suspend_grad(), compact_kernels():
            out = tracer.trace(P, tracer.rays(o, d), last=stop)
            p_stop, status = to_numpy(out.p, out.status)  # one kernel
        local = (p_stop - o_stop) @ R_stop
        return local[:, :2], status.astype(np.int64), o, d / np.linalg.norm(d, axis=1, keepdims=True)

    u = np.zeros(2)
    h = 1e-6
    steps = np.array([[0.0, 0.0], [h, 0.0], [-h, 0.0], [0.0, h], [0.0, -h]])
    for _ in range(30):
        # The ray and its four central-difference neighbours in one launch.
        r5, st5, o5, d5 = shoot(u + steps)
        r, o, d = r5[0], o5[0], d5[0]
        if np.max(np.abs(r)) < 1e-13:
            break
        J = np.column_stack([(r5[1] - r5[2]) / (2 * h), (r5[3] - r5[4]) / (2 * h)])
        u = u - np.linalg.solve(J, r)
    return o, d


def parabasal_matrices(tracer, wavelength_nm: float):
    """Reduced 2×2 matrices (x and y meridians) about the optical-axis ray.

    Returns ``(Mx_front, Mx_total, My_front, My_total, n_obj, n_img, t_last)``.
    """
    import drjit as dr

    from .tracer import RayState

    system = tracer.system
    T = tracer.T
    stop = system.stop_index if system.stop_index is not None else 0
    P_np = np.asarray(system.parameter_values(wavelength_nm))
    n_obj = float(system.object_material.index(wavelength_nm))
    media = system.media()
    n_img = float(media[-1].index(wavelength_nm))
    o0, d0 = find_axis_ray(tracer, P_np, stop, n_obj, system.object_distance)

    e1, e2 = _perp_basis(d0, np.array([0.0, 1.0, 0.0]))
    # Four parabasal rays: x, y position offsets and x, y reduced-angle offsets.
    dp = np.array([e1, e2, 0 * e1, 0 * e1])
    dd = np.array([0 * e1, 0 * e1, e1 / n_obj, e2 / n_obj])
    if not math.isinf(system.object_distance):
        # Finite object: position offsets act on the first vertex plane, so
        # move the origin there along the OAR first.
        t = -o0[2] / d0[2]
        o0 = o0 + t * d0
    P = tracer.params(values=P_np)
    s = dr.zeros(T.Float, 4)
    dr.enable_grad(s)
    o = T.Array3(*(T.Float(o0[i]) + s * T.Float(dp[:, i]) for i in range(3)))
    d = T.Array3(*(T.Float(d0[i]) + s * T.Float(dd[:, i]) for i in range(3)))
    out = tracer.trace(P, RayState(o, d), record=True)
    dr.set_grad(s, 1.0)
    targets = [out.path[stop][0], out.path[stop][1], out.path[-1][0], out.path[-1][1]]
    dr.forward_to(*targets, flags=dr.ADFlag.ClearNone)

    def parity(k):
        # An odd number of reflections mirrors the image; flip e1 so x keeps its sense.
        return -1.0 if sum(s.interaction in ("reflect", "tir") for s in system.surfaces[: k + 1]) % 2 else 1.0

    # Every value and derivative needed below in one (compact) kernel.
    last = len(system.surfaces) - 1
    need = [stop, last] + ([last - 1] if last >= 1 else [])
    with compact_kernels():
        flat = [v for k in need for v in (out.path[k][0], out.path[k][1])]
        vals = to_numpy(*flat, *(dr.grad(v) for v in flat[:4]))
    got = {k: (vals[2 * j], vals[2 * j + 1]) for j, k in enumerate(need)}
    grads = {k: (vals[len(flat) + 2 * j], vals[len(flat) + 2 * j + 1]) for j, k in enumerate(need[:2])}

    def jac(k, n_here, up_frame):
        p0, dir0 = got[k][0][0].astype(np.float64), got[k][1][0].astype(np.float64)
        Jp, Jd = grads[k]  # (4 rays, 3)
        # Position derivative projected on the plane ⟂ the OAR through the hit point.
        Jp = Jp - np.outer(Jp @ dir0, dir0)
        f1, f2 = _perp_basis(dir0, up_frame)
        f1 = parity(k) * f1
        rows = np.array([Jp @ f1, Jp @ f2, n_here * (Jd @ f1), n_here * (Jd @ f2)])  # (4 out, 4 in)
        return rows, p0, dir0

    frames = tracer.frames_numpy(P)

    def up_of(k):
        return frames[k][0][:, 1]

    n_stop = float(media[stop + 1].index(wavelength_nm))
    Jf, _, _ = jac(stop, n_stop, up_of(stop))
    Jt, p_img, dir_img = jac(len(system.surfaces) - 1, n_img, up_of(len(system.surfaces) - 1))
    # Axial distance from the last surface before the image to the image surface.
    if len(system.surfaces) >= 2:
        p_last = got[last - 1][0][0].astype(np.float64)
        t_last = float(np.dot(p_img - p_last, dir_img))
    else:
        t_last = 0.0
    Mx_f, Mx_t = Jf[np.ix_([0, 2], [0, 2])], Jt[np.ix_([0, 2], [0, 2])]
    My_f, My_t = Jf[np.ix_([1, 3], [1, 3])], Jt[np.ix_([1, 3], [1, 3])]
    return Mx_f, Mx_t, My_f, My_t, n_obj, n_img, t_last


def first_order(system: System, wavelength_nm: float, tracer=None, method: str = "auto") -> FirstOrder:
    """First-order properties of ``system`` at ``wavelength_nm``.

    ``method``: "paraxial" (rotationally symmetric systems only), "parabasal"
    (any system; needs ``tracer``) or "auto" (paraxial when possible).
    """
    if method == "auto":
        method = "paraxial" if is_rotationally_symmetric(system) else "parabasal"
    if method == "paraxial":
        if not is_rotationally_symmetric(system):
            raise ValueError("the paraxial y-nu trace needs a rotationally symmetric, untilted system")
        Mf, Mt, n_o, n_i = paraxial_matrices(system, wavelength_nm)
        t_last = system.surfaces[-2].thickness if len(system.surfaces) > 1 else 0.0
        return from_matrices(system, Mf, Mt, n_o, n_i, wavelength_nm, t_last, "paraxial")
    if method != "parabasal":
        raise ValueError(f"unknown method {method!r}: use 'auto', 'paraxial' or 'parabasal'")
    if tracer is None:
        from .tracer import SequentialTracer

        tracer = SequentialTracer(system, "float64")
    Mx_f, Mx_t, My_f, My_t, n_o, n_i, t_last = parabasal_matrices(tracer, wavelength_nm)
    fx = -1.0 / Mx_t[1, 0] if Mx_t[1, 0] != 0 else math.inf
    return from_matrices(system, My_f, My_t, n_o, n_i, wavelength_nm, t_last, "parabasal", efl_x=fx)
