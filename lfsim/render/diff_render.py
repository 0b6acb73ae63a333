"""Differentiable retinal images of the analytic display path (Dr.Jit end to end).

The same estimator as the analytic path of :mod:`lfsim.render.display_eye`
(eye rays traced backwards through the design's own surfaces to the display,
whose image is read with a bilinear lookup), written so that every design
number is an attached Dr.Jit variable:

* **Design vector** ``P``: the forward parameter table of the design
  (:meth:`System.parameter_table`, the names ``lfsim params`` lists, with
  the tunable lens's power of the rendered CDP state in ``<TL>.power``);
  its ``object.distance`` is the display-to-MLA gap g (the display plane is
  ``z = −g``).
* **Reversed system** (:func:`lfsim.optics.reverse.reversed_system`): its
  parameter array is a differentiable function of ``P`` (:class:`ReverseMap`):
  shapes, indices, powers and lenslet pitches are copied, and each surface's
  global position and Euler tilts come from the forward frames
  :meth:`SequentialTracer.frames` evaluated on ``P``. The eye sits on the
  viewing window, whose frame is also taken from ``P``.
* **Estimator** per pixel ``p`` (spp samples ``(u_s, q_s)``: film position in
  the pixel and pupil point, from a seeded generator)::

      I_p(θ) = 1/spp Σ_s  V_s(θ) · E(x_s(θ), y_s(θ))

  where ``x_s, y_s`` is where the eye ray of sample s, traced back through the
  design, meets the display plane, ``E`` the display image with bilinear
  interpolation (C⁰ in position, so its position derivative exists almost
  everywhere) and ``V_s`` the visibility: 1 when the ray passes every
  surface's aperture and lands on the display, else 0.

``dI/dθ`` by automatic differentiation is the derivative of the integrand
along fixed samples (the *interior* term). Where θ moves a discontinuity of
the integrand in sample space — ``V`` switching (aperture edges, the display
edge) or the lenslet a ray crosses changing (an integer cell index: the ray
then reads another elemental image) — the derivative of the expected image has
an additional *boundary* term that this estimator does not see
(:mod:`lfsim.render.gradcheck` measures it).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import drjit as dr
import numpy as np

from .. import backend
from ..backend import from_numpy
from ..content import VIEW_DEFAULTS
from ..optics.reverse import reversed_system
from ..optics.tracer import RayState, SequentialTracer


def _euler_deg(R):
    """Dr.Jit version of :func:`lfsim.optics.reverse.euler_xyz`: (a, b, c) in degrees
    with ``R = Rx(a)·Ry(b)·Rz(c)``."""
    deg = 180.0 / math.pi
    b = dr.asin(dr.clip(R[0][2], -1.0, 1.0))
    a = dr.atan2(-R[1][2], R[2][2])
    c = dr.atan2(-R[0][1], R[0][0])
    return a * deg, b * deg, c * deg


class ReverseMap:
    """Design vector ``P`` → parameter array of the reversed (eye → display) system.

    Parameters
    ----------
    model : lfsim.ini.model.IniModel
        The design in one CDP state (state 0 is used).
    precision : str
    """

    def __init__(self, model, precision: str = "float64"):
        spec, system = model.spec, model.system
        self.model = model
        self.fwd = SequentialTracer(system, precision)
        self.T = self.fwd.T
        self.names = self.fwd.names
        self.index = self.fwd.index
        self.values0 = model.values(0)
        self.vw = spec.viewing_window
        last = spec.viewing_window - 1
        frames = self.fwd.frames_numpy(self.fwd.params(values=model.values(0)))
        powers = {}
        if spec.tunable is not None:
            name = system.surfaces[spec.tunable].name
            powers[name] = float(model.values(0)[self.fwd.index[f"{name}.power"]])
        self.system = reversed_system(system, frames, end_plane_z=-model.g, first=0, last=last,
                                      powers=powers)
        self.rev = SequentialTracer(self.system, precision)
        self.wavelength_nm = model.lam
        # Which forward surface each reversed surface is (the order of reversed_system).
        order = [i for i in range(last, -1, -1) if system.surfaces[i].interaction != "break"]
        media = self.fwd.vector.media
        n_p = len(self.names)
        zero = n_p  # slot of a constant 0 in the source array
        self._computed = []  # (reversed name, forward surface index or None for 'end')
        src = {}
        for j, s_rev in enumerate(self.system.surfaces[:-1]):
            i = order[j]
            s = system.surfaces[i]
            owner = system.surfaces[s.same_as] if s.same_as is not None else s
            for suffix in ["curvature", "conic"] + [f"A{o}" for o in owner.asphere] + \
                    [f"x{a}y{b}" for a, b in owner.xy]:
                src[f"{s_rev.name}.{suffix}"] = self.index[f"{owner.name}.{suffix}"]
            for suffix in ("decenter_x", "decenter_y", "thickness"):
                src[f"{s_rev.name}.{suffix}"] = zero
            if s_rev.interaction == "paraxial":
                src[f"{s_rev.name}.power"] = self.index[f"{s.name}.power"]
            if s_rev.interaction == "refract":
                src[f"{s_rev.name}.index"] = self.index[media[i]]
            elif s_rev.interaction == "tir":
                src[f"{s_rev.name}.index"] = self.index[f"{s.name}.index"]
            self._computed.append((s_rev.name, i))
        src["object.index"] = self.index[media[last + 1]]
        for suffix in ("curvature", "conic", "decenter_x", "decenter_y", "tilt_x", "tilt_y", "tilt_z",
                       "position_x", "position_y", "thickness"):
            src[f"end.{suffix}"] = zero
        for a in self.system.arrays.values():
            for suffix in ("pitch_x", "pitch_y", "center_x", "center_y"):
                src[f"{a.name}.{suffix}"] = self.index[f"{a.name}.{suffix}"]
        # Computed entries follow the constant 0 in the source array, in this order.
        k = zero + 1
        for name, _ in self._computed:
            for suffix in ("position_x", "position_y", "position_z", "tilt_x", "tilt_y", "tilt_z"):
                src[f"{name}.{suffix}"] = k
                k += 1
        src["end.position_z"] = k
        missing = [n for n in self.rev.names if n not in src]
        if missing:  # a surface kind this map does not know: refuse rather than render wrong
            raise ValueError(f"reversed-system parameters without a source: {', '.join(missing)}")
        self._src = np.array([src[n] for n in self.rev.names], dtype=np.uint32)

    def params(self, values=None):
        """The design vector (``T.Float``) at ``values`` (default: the model's state 0)."""
        v = self.values0 if values is None else np.asarray(values, dtype=np.float64).ravel()
        if v.size != len(self.names):
            raise ValueError(f"expected {len(self.names)} design values, got {v.size}")
        return backend.from_numpy(self.T.Float, v.astype(self.T.np_dtype))

    def frames(self, P):
        """Forward frames (R, o) of every surface at ``P`` (differentiable)."""
        return forward_frames(self.fwd, P)

    def reverse_params(self, P, frames=None):
        """The reversed system's parameter array at design vector ``P`` (differentiable)."""
        T = self.T
        Rs, os_ = frames if frames is not None else self.frames(P)
        values = []
        for _, i in self._computed:
            a, b, c = _euler_deg(Rs[i])
            o = os_[i]
            values += [o.x, o.y, o.z, a, b, c]
        values.append(-dr.gather(T.Float, P, T.UInt32(self.index["object.distance"])))
        return self._assemble(P, values)

    def _assemble(self, P, values):
        """Copied entries by one gather from ``P``; computed ones (width-1 arrays) put in
        place with selects (a reverse pass through ``dr.concat`` of width-1 pieces lost
        gradients at random)."""
        T = self.T
        n_p = len(self.names)
        n = len(self._src)
        copy = self._src < n_p
        out = dr.gather(T.Float, P, T.UInt32(np.where(copy, self._src, 0).astype(np.uint32)))
        out = dr.select(T.Bool(copy), out, 0.0)
        slot = dr.arange(T.UInt32, n)
        for j in np.nonzero(self._src > n_p)[0]:
            out = dr.select(slot == int(j), values[int(self._src[j]) - n_p - 1], out)
        return out

    def eye_frame(self, frames):
        """(R, o) of the viewing window (the eye's frame) from forward frames."""
        Rs, os_ = frames
        return Rs[self.vw], os_[self.vw]


def forward_frames(tracer: SequentialTracer, P):
    """Forward frames (R, o) of every surface of ``tracer`` at design vector ``P``, whose first
    ``tracer.n_params`` entries are the forward parameter table (differentiable)."""
    return tracer.frames(dr.gather(tracer.T.Float, P, dr.arange(tracer.T.UInt32, tracer.n_params)))


def flat_leaves(arrays: list, R_vw, o_vw) -> list:
    """``arrays`` then the eye frame's entries (``o_vw[a]``, ``R_vw[a][0..2]`` for each row a):
    the flat order in which leaves and their adjoints are paired by ``_pull_back``."""
    out = list(arrays)
    for a in range(3):
        out.append(o_vw[a])
        out.extend(R_vw[a][b] for b in range(3))
    return out


def ideal_aim(px, py, fov_deg, focus_mm: float) -> np.ndarray:
    """Where the ideal eye's rays of film samples ``(px, py)`` (in [0, 1), row 0 at the
    top) aim, float64 (N, 3): the focus point on the sphere of radius ``focus_mm`` about
    the pupil centre, or the chief direction at infinity (angular mapping, as
    :mod:`lfsim.render.eye`)."""
    hx, hy = (math.radians(float(f)) * 0.5 for f in fov_deg)
    tx = np.tan((2.0 * np.asarray(px, dtype=np.float64) - 1.0) * hx)
    ty = np.tan((1.0 - 2.0 * np.asarray(py, dtype=np.float64)) * hy)
    c = np.stack([tx, ty, -np.ones_like(tx)], axis=1)
    c /= np.linalg.norm(c, axis=1, keepdims=True)
    return c * focus_mm if math.isfinite(focus_mm) else c


def ideal_rays(q, aim, finite: bool, xp=np):
    """Origins and unit directions of ideal-eye rays from pupil points ``q`` toward
    ``aim`` (:func:`ideal_aim`); ``xp``: numpy (arrays (N, 2), (N, 3)) or a Dr.Jit
    Array3 type (``q`` a pair of arrays, ``aim`` an Array3)."""
    if xp is np:
        o = np.column_stack([q, np.zeros(len(q))])
        d = aim - o if finite else aim.copy()
        return o, d / np.linalg.norm(d, axis=1, keepdims=True)
    o = xp(q[0], q[1], 0.0)
    d = xp(aim.x - q[0], aim.y - q[1], aim.z) if finite else xp(aim)
    return o, dr.normalize(d)


@dataclass
class RayBatch:
    """Per-sample result of :meth:`AnalyticRenderer.trace` (Dr.Jit arrays)."""

    x: object  # display-plane hit, global x (mm)
    y: object
    valid: object  # Bool: passed every surface and landed on the display, heading to it
    status: object  # UInt32 tracer status
    value: list  # per channel: V · E(x, y)


@dataclass
class ViewSpec:
    """What :class:`AnalyticRenderer` renders (lengths mm; None: the content's [view])."""

    focus_mm: list[float] = field(default_factory=lambda: list(VIEW_DEFAULTS.focus_mm))
    cdp_mm: float = VIEW_DEFAULTS.cdp_mm
    pupil_diameter_mm: float = VIEW_DEFAULTS.pupil_diameter_mm
    resolution: tuple[int, int] = (96, 54)
    spp: int = 16
    seed: int = 0
    eye_model: str = "ideal"
    cells: str = "per_surface"


class AnalyticRenderer:
    """Retinal images of the display through the design, differentiable in the design vector.

    Parameters
    ----------
    design : lfsim.Design
        A design with an ``[ini]`` section.
    view : ViewSpec
    content : lfsim.content.ContentScene, optional
        What the display shows: its elemental images are computed once, for
        the nominal design (``display`` may give them instead). The display
        content stays fixed while the design vector changes: a derivative is
        that of the retinal image of a given display image.
    display : ndarray (H, W, C), optional
        The display image (linear); default: the content's elemental images.
    precision : {"float64", "float32"}
        Arithmetic of the trace and the lookup (float64 for finite differences).
    channels : int
        1: luminance of the display image; 3: RGB.
    """

    def __init__(self, design, view: ViewSpec, content=None, display=None, precision: str = "float64",
                 channels: int = 1):
        from ..ini.model import model_at_depth
        from .display import DisplayLayout

        if design.ini is None:
            raise ValueError(f"{design.path or design.name}: the design has no [ini] section")
        if view.cells not in ("per_surface", "fixed"):
            raise ValueError(f"cells = {view.cells!r}: expected 'per_surface' or 'fixed'")
        self.design, self.view = design, view
        cdp_D = 0.0 if math.isinf(view.cdp_mm) else 1000.0 / view.cdp_mm
        self.model = model = model_at_depth(design, cdp_D)
        self.map = ReverseMap(model, precision)
        self.T = T = self.map.T
        self.names, self.index = self.map.names, self.map.index
        self.values0 = self.map.values0.copy()
        self.layout = DisplayLayout.from_model(model, 0)
        self.fov_deg = model.state(0).fov_deg
        if display is None:
            if content is None:
                raise ValueError("give the content (or the display image) to render")
            display = self._elemental_images(content)
        img = np.asarray(display, dtype=np.float64)
        if img.ndim == 2:
            img = img[..., None]
        if channels == 1 and img.shape[-1] == 3:
            img = img @ np.array([0.2126, 0.7152, 0.0722])[:, None]
        self.display = img
        self.channels = img.shape[-1]
        self._data = backend.from_numpy(T.Float, img.reshape(-1).astype(T.np_dtype))
        self.W, self.H = (int(v) for v in view.resolution)
        self.spp = int(view.spp)
        self.n_pixels = self.W * self.H
        self._aims = []  # per focus: (q, aim, finite) of the ideal eye's samples (float64), else None
        self._rays = [self._eye_rays(float(f)) for f in view.focus_mm]

    # ------------------------------------------------------------ set-up
    def _elemental_images(self, content):
        from ..content import elemental_images, scene_dict
        from . import mitsuba

        mi = mitsuba()
        scene = mi.load_dict(scene_dict(content))
        return elemental_images(self.model, scene, self.layout, background=content.background)

    def _eye_rays(self, focus_mm: float):
        """Eye rays (viewing-window frame) of every sample, pixel-major, spp per pixel."""
        import mitsuba as mi

        from .eye import EyeSpec

        view = self.view
        eye = EyeSpec(view.eye_model, view.pupil_diameter_mm, focus_mm, tuple(self.fov_deg), (self.W, self.H))
        sensor = eye.load(None, self.spp, view.seed)
        rng = np.random.default_rng([int(view.seed), int(round(focus_mm * 1000))])
        n = self.n_pixels * self.spp
        pix = np.repeat(np.arange(self.n_pixels), self.spp)
        px = (pix % self.W + rng.random(n)) / self.W
        py = (pix // self.W + rng.random(n)) / self.H
        pupil = rng.random((n, 2))
        with dr.suspend_grad():
            f32 = lambda a: a.astype(np.float32)  # noqa: E731
            ray, w = sensor.sample_ray(0.0, 0.0, mi.Point2f(*from_numpy(mi.Float, f32(px), f32(py))),
                                       mi.Point2f(*from_numpy(mi.Float, f32(pupil[:, 0]), f32(pupil[:, 1]))))
            dr.eval(ray.o, ray.d, w)  # one kernel (each read alone would sample again)
            o = np.stack([np.asarray(ray.o[i], dtype=np.float64) for i in range(3)], axis=1)
            d = np.stack([np.asarray(ray.d[i], dtype=np.float64) for i in range(3)], axis=1)
            ok = np.asarray(w[0]) > 0
        if view.eye_model == "ideal":
            # The ideal eye's rays again in float64, as functions of the pupil point q
            # (the sensor's float32 origin, taken as exact): q → the focus point, or
            # along the chief direction at infinity. The boundary term differentiates
            # them in q (:mod:`lfsim.render.boundary`).
            q = o[:, :2].copy()
            aim = ideal_aim(f32(px).astype(np.float64), f32(py).astype(np.float64), tuple(self.fov_deg), focus_mm)
            o, d = ideal_rays(q, aim, math.isfinite(focus_mm))
            self._aims.append((q, aim, math.isfinite(focus_mm)))
        else:
            self._aims.append(None)
        T = self.T
        c = backend.from_numpy(T.Float, *(a.astype(T.np_dtype) for a in (*o.T, *d.T, ok.astype(np.float64))))
        return T.Array3(*c[:3]), T.Array3(*c[3:6]), c[6] > 0.5

    # ----------------------------------------------------------- render
    def params(self, values=None):
        """Design vector as a Dr.Jit array (enable its gradient to differentiate)."""
        return self.map.params(values)

    def optics(self, P):
        """What the trace needs from the design vector: (P_rev, R_vw, o_vw), differentiable."""
        frames = self.map.frames(P)
        R_vw, o_vw = self.map.eye_frame(frames)
        return self.map.reverse_params(P, frames), R_vw, o_vw

    def trace(self, P, k: int = 0, optics=None, rays=None, probe: list | None = None) -> RayBatch:
        """Trace the eye rays of focus ``k`` to the display at design vector ``P``
        (or at ``optics`` = :meth:`optics` output, e.g. detached leaves). ``rays``:
        other eye rays ``(o, d, ok)`` in the viewing-window frame; ``probe``: filled
        with the tracer's :class:`~lfsim.optics.tracer.ProbeHit` records."""
        T = self.T
        P_rev, R_vw, o_vw = optics if optics is not None else self.optics(P)
        o_l, d_l, ok_eye = self._rays[k] if rays is None else rays
        n = dr.width(o_l)
        # An opaque (evaluated) index, as the tracer's default block.
        zero = dr.opaque(T.UInt32, 0, n)
        R = dr.gather(T.Matrix3, R_vw, zero)
        o = R @ o_l + dr.gather(T.Array3, o_vw, zero)
        d = R @ d_l
        out = self.map.rev.trace(P_rev, RayState(o, d), block=zero, cells=self.view.cells, probe=probe)
        lay = self.layout
        pitch = lay.pixel_pitch
        fx = (out.p.x - lay.center[0]) / pitch + 0.5 * lay.width - 0.5
        fy = (lay.center[1] - out.p.y) / pitch + 0.5 * lay.height - 0.5
        on = ((dr.abs(out.p.x - lay.center[0]) <= 0.5 * lay.width * pitch)
              & (dr.abs(out.p.y - lay.center[1]) <= 0.5 * lay.height * pitch))
        valid = ok_eye & (out.status == 0) & (out.d.z < 0.0) & on
        # Evaluate the traced rays before the lookup (smaller kernels to compile).
        dr.eval(fx, fy, valid)
        value = self._bilinear(fx, fy, valid)
        return RayBatch(out.p.x, out.p.y, valid, out.status, value)

    def _bilinear(self, fx, fy, valid):
        """Bilinear lookup of the display image at continuous pixel coordinates
        (pixel centres at integers; clamped at the border, as Mitsuba's bitmap)."""
        T = self.T
        W, H, C = self.layout.width, self.layout.height, self.channels
        fx = dr.select(valid, dr.clip(fx, 0.0, W - 1.0), 0.0)
        fy = dr.select(valid, dr.clip(fy, 0.0, H - 1.0), 0.0)
        x0 = dr.minimum(T.UInt32(dr.floor(dr.detach(fx))), W - 2)
        y0 = dr.minimum(T.UInt32(dr.floor(dr.detach(fy))), H - 2)
        ax, ay = fx - T.Float(x0), fy - T.Float(y0)
        base = (y0 * W + x0) * C
        out = []
        for c in range(C):
            v00 = dr.gather(T.Float, self._data, base + c, valid)
            v10 = dr.gather(T.Float, self._data, base + C + c, valid)
            v01 = dr.gather(T.Float, self._data, base + W * C + c, valid)
            v11 = dr.gather(T.Float, self._data, base + (W + 1) * C + c, valid)
            top = dr.fma(ax, v10 - v00, v00)
            bot = dr.fma(ax, v11 - v01, v01)
            out.append(dr.select(valid, dr.fma(ay, bot - top, top), 0.0))
        return out

    def image(self, P, k: int = 0, batch: RayBatch | None = None, optics=None):
        """Retinal image of focus ``k``: list of per-channel Dr.Jit arrays (H·W, row-major,
        row 0 at the top), differentiable in ``P`` (forward mode; see :meth:`backward`)."""
        b = batch if batch is not None else self.trace(P, k, optics)
        return [dr.block_sum(v, self.spp) / self.spp for v in b.value]

    def backward(self, P, objective, wrt=None, extra=None):
        """Reverse-mode gradient of ``objective(optics)`` (a Dr.Jit scalar built from
        :meth:`image` / :meth:`trace` with ``optics=``) with respect to the design vector.

        Mixed mode, exact by the chain rule: the render (millions of samples) is
        differentiated in reverse mode with respect to detached leaves — the
        reversed system's parameters and the eye frame — and those adjoints are
        pulled back through the small map ``P → (P_rev, R_vw, o_vw)`` by one
        forward-mode pass per parameter in ``wrt`` (indices; default all).
        (Dr.Jit 1.5 on LLVM lost part of the gradient when the reverse pass also
        went through the map, whose frames read the same leaf more than once.)
        ``extra(optics)``: a scalar whose derivative is added but whose value is not
        (the boundary term, :meth:`lfsim.render.boundary.BoundaryTerm.objective`).
        Returns ``(objective value, dObjective/dP)`` (float, numpy array; zero
        outside ``wrt``).
        """
        with dr.suspend_grad():
            leaves = [dr.detach(v) for v in self.optics(P)]
        for v in leaves:
            dr.enable_grad(v)
        value = objective(tuple(leaves))
        # ``extra``: a term differentiated with the objective but not part of its value
        # (the boundary term's B, :mod:`lfsim.render.boundary`).
        dr.backward(value if extra is None else value + extra(tuple(leaves)))
        adj = [dr.detach(dr.grad(v)) for v in leaves]
        return float(value[0]), self._pull_back(P, flat_leaves(adj[0:1], adj[1], adj[2]), wrt)

    def _leaves(self, P) -> list:
        """The map ``P → (P_rev, R_vw, o_vw)`` whose outputs :meth:`backward` detaches,
        flattened in the order of :func:`flat_leaves`."""
        P_rev, R_vw, o_vw = self.optics(P)
        return flat_leaves([P_rev], R_vw, o_vw)

    def _pull_back(self, P, adj: list, wrt=None) -> np.ndarray:
        """``d/dP_i Σ_j <adj_j, leaf_j(P)>`` for every ``i`` in ``wrt`` (default all), one
        forward-mode pass each: the second half of the mixed-mode reverse gradient."""
        T = self.T
        values = np.asarray(dr.detach(P), dtype=np.float64)
        grad = np.zeros(len(self.names))
        for i in (range(len(self.names)) if wrt is None else wrt):
            t = dr.zeros(T.Float, 1)
            dr.enable_grad(t)
            e = np.zeros(len(self.names))
            e[int(i)] = 1.0
            pull = T.Float(0.0)
            for v, a in zip(self._leaves(self.params(values) + t * T.Float(e)), adj):
                pull = pull + T.Float(dr.sum(v * a))
            dr.forward_from(t)
            grad[int(i)] = float(dr.grad(pull)[0])
        return grad

    def image_numpy(self, values=None, k: int = 0) -> np.ndarray:
        """(H, W, C) float64 retinal image of focus ``k`` at ``values`` (no gradients)."""
        with dr.suspend_grad():
            img = self.image(self.params(values), k)
            dr.eval(img)
            return np.stack([np.asarray(c, dtype=np.float64) for c in img], axis=-1).reshape(self.H, self.W, -1)
