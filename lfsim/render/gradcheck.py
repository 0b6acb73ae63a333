"""Gradient check of retinal renders: automatic differentiation against finite differences.

For a render loss ``L(θ)`` of the analytic display path
(:class:`~lfsim.render.diff_render.AnalyticRenderer`) and named design
parameters θ_k, :func:`gradcheck` reports

* ``ad``: dL/dθ_k by reverse-mode AD (one ``dr.backward`` for all k);
* ``ad_forward``: the same by forward mode (``dr.forward_from`` along e_k);
* ``fd``: the central difference ``(L(θ + h e_k) − L(θ − h e_k)) / 2h`` with
  the same samples (common random numbers) at the step h of
  :func:`fd_step` (relative 1e-7 by default), capped on the analytic path so
  that it moves the display hits by at most :data:`MOTION_PX` pixels
  (:func:`motion_step`: the bilinear kinks of the display image are then
  almost never crossed); ``fd_interior``: the same with every sample whose
  discrete path changed (:func:`difference`) kept at its θ value;
* ``ad_kept``: AD restricted to the samples that ``fd_interior`` kept
  (:func:`sample_derivatives`), its exact counterpart:
  ``interior_rel_err = |ad_kept − fd_interior| / |fd_interior|``. (Holding
  the flagged samples at θ drops their interior part from the difference;
  comparing it with the full AD biased the check by that part: 5.6 % and
  44 % for L1.index and F1b.thickness on the mesh path.)
* ``boundary_term``: at the larger edge step (relative 1e-3), where many
  samples cross a visibility edge (another lenslet cell, vignetted or not,
  on or off the display), the flagged samples' share of the difference
  (``fd − fd_interior``) minus their own interior (AD) part: the boundary
  term that the AD estimator does not contain, and ``bias = −boundary_term
  / (ad + boundary_term)``, the share of the full derivative AD misses;
* ``boundary``: true when some samples crossed an edge at the edge step and
  the edge term is at least :data:`BOUNDARY_SHARE` of the full derivative.

The renderer is the analytic path or the mesh path
(:class:`lfsim.render.mesh_ad.MeshRenderer`, float32 Mitsuba arithmetic: its
differences use larger steps and a least-squares slope over several, see
:func:`difference`).

Loss: ``L = Σ_focus mean_pixels (I − R)²`` against a target R (by default the
natural view of the content through the same eye), which is smooth in the
image.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import drjit as dr
import numpy as np

#: Smallest |value| a step is scaled from, by unit (a parameter at 0 still needs a step).
STEP_FLOOR = {"mm": 1.0, "deg": 1.0, "1/mm": 1e-2, "": 1.0}
#: Default relative step of the central differences.
REL_STEP = 1e-7
#: Analytic path: the main step is also capped so that it moves the 99th percentile of
#: display hits by at most this many display pixels (:func:`motion_step`). At the
#: 1e-7 rule step the prism mirror's z-shift moved hits by 0.014 px on ini_freeform
#: and the bilinear kinks of the binary elemental images cost 2.4-2.7 %.
MOTION_PX = 1e-3
#: Relative step at which the edge (boundary) term is measured: enough samples cross edges.
EDGE_REL_STEP = 1e-3
#: A parameter is boundary-type when its edge term is at least this share of |fd|.
BOUNDARY_SHARE = 0.005
#: The total derivative passes when it is within this share of the full difference at the
#: edge step, or within :data:`TOTAL_SIGMAS` of that difference's Monte Carlo noise.
TOTAL_REL_TOL = 0.05
TOTAL_SIGMAS = 3.0


#: Coordinates (a surface's global position, decenter or tilt) have no magnitude of their
#: own: their value depends on where the frame's origin lies (the prism mirror of
#: ini_freeform_optimized sits at z = 280.6 mm, tilted 100°), so their steps scale from
#: the unit's floor alone.
COORDINATE_KINDS = ("position_", "decenter_", "tilt_")


def fd_step(name: str, value: float, unit: str, rel: float = REL_STEP) -> float:
    """Central-difference step: ``rel · max(|value|, floor(unit))``, or ``rel · floor`` for
    a coordinate (:data:`COORDINATE_KINDS`).

    Floors: 1 mm for lengths, 1° for angles, 0.01 mm⁻¹ (10 D) for powers and
    curvatures, 1 for indices and conics; aspheric coefficients (mm^(1−2i))
    use their own magnitude, or 1e-6 at zero.
    """
    floor = STEP_FLOOR.get(unit, 1e-6)
    if name.rsplit(".", 1)[-1].startswith(COORDINATE_KINDS):
        return float(rel * floor)
    return float(rel * max(abs(float(value)), floor))


def natural_targets(renderer, content, spp: int | None = None, seed: int = 1) -> list[np.ndarray]:
    """The natural view of ``content`` through the renderer's eye, per focus (H, W, C)."""
    from ..content import scene_dict
    from .eye import EyeSpec
    from .focal_stack import INTEGRATOR, render

    v = renderer.view
    out = []
    for f in v.focus_mm:
        eye = EyeSpec(v.eye_model, v.pupil_diameter_mm, float(f), tuple(renderer.fov_deg),
                      (renderer.W, renderer.H))
        sd = scene_dict(content)
        sd["sensor"] = eye.sensor_dict(None, int(spp or renderer.spp), seed)
        sd["integrator"] = INTEGRATOR
        img, _ = render(sd)
        img = img.astype(np.float64)
        if renderer.channels == 1:
            img = img @ np.array([0.2126, 0.7152, 0.0722])[:, None]
        out.append(img)
    return out


class RenderLoss:
    """``L(P) = Σ_k mean (I_k(P) − R_k)²`` over the renderer's focus distances.

    ``targets``: list of (H, W, C) arrays, one per focus distance.
    """

    def __init__(self, renderer, targets):
        from .. import backend

        self.r = renderer
        T = renderer.T
        if len(targets) != len(renderer.view.focus_mm):
            raise ValueError(f"{len(targets)} targets for {len(renderer.view.focus_mm)} focus distances")
        self.targets, self.targets_np = [], []
        for t in targets:
            t = np.asarray(t, dtype=np.float64).reshape(renderer.H, renderer.W, -1)
            if t.shape[-1] != renderer.channels:
                raise ValueError(f"target has {t.shape[-1]} channels, the renderer {renderer.channels}")
            self.targets_np.append(t.reshape(-1, renderer.channels))
            self.targets.append([backend.from_numpy(T.Float, t[..., c].ravel().astype(T.np_dtype))
                                 for c in range(renderer.channels)])
        self.norm = 1.0 / (renderer.n_pixels * renderer.channels)

    def __call__(self, P, optics=None):
        total = 0.0
        for k, ref in enumerate(self.targets):
            img = self.r.image(P, k, optics=optics)
            for c in range(self.r.channels):
                total = total + dr.sum(dr.square(img[c] - ref[c])) * self.norm
        return total

    def sample_weights(self, values, k: int) -> np.ndarray:
        """(N, C) derivative of the loss with respect to each sample's value at focus ``k``:
        ``2 norm (I_p − R_p) / spp`` of the sample's pixel."""
        r = self.r
        img = r.image_numpy(values, k).reshape(r.n_pixels, -1)
        return np.repeat(2.0 * self.norm * (img - self.targets_np[k]) / r.spp, r.spp, axis=0)

    def value(self, values) -> float:
        with dr.suspend_grad():
            return float(self(self.r.params(values))[0])


def gradient(loss: RenderLoss, values=None, wrt=None, total: bool = False, boundary_options=None):
    """(L, dL/dP) by reverse-mode AD at ``values`` (numpy, full design vector);
    ``wrt``: indices of the entries wanted (default all). ``total``: the total
    derivative, the boundary term of the visibility edges included
    (:mod:`lfsim.render.boundary`; the ideal eye only); else the interior term."""
    r = loss.r
    extra = None
    if total:
        from .boundary import BoundaryTerm

        bt = BoundaryTerm(r, **(boundary_options or {}))
        weights = [loss.sample_weights(values, k) for k in range(len(r.view.focus_mm))]

        def extra(optics):
            return sum((bt.objective(optics, k, w) for k, w in enumerate(weights)), r.T.Float(0.0))
    if extra is None:  # the mesh path's backward takes no extra term
        return r.backward(r.params(values), lambda optics: loss(None, optics), wrt)
    return r.backward(r.params(values), lambda optics: loss(None, optics), wrt, extra=extra)


def directional(loss: RenderLoss, direction, values=None) -> float:
    """dL/dt of ``L(P + t·direction)`` at t = 0, by forward-mode AD."""
    from .. import backend

    r = loss.r
    T = r.T
    t = dr.zeros(T.Float, 1)
    dr.enable_grad(t)
    V = backend.from_numpy(T.Float, np.asarray(direction, dtype=np.float64).astype(T.np_dtype))
    P = r.params(values) + t * V
    L = loss(P)
    dr.forward_from(t)
    return float(dr.grad(L)[0])


def _batch_numpy(r, values, k):
    with dr.suspend_grad():
        b = r.trace(r.params(values), k)
        dr.eval(b.x, b.y, b.valid, b.status, *b.value)
        return (np.asarray(b.x, dtype=np.float64), np.asarray(b.y, dtype=np.float64),
                np.asarray(b.valid, dtype=bool), np.asarray(b.status),
                np.stack([np.asarray(v, dtype=np.float64) for v in b.value], axis=-1))


@dataclass
class Difference:
    """Central difference of the loss over [θ−h, θ+h], split by continuity of the samples."""

    step: float
    fd: float  # (L(θ+h) − L(θ−h)) / 2h
    fd_interior: float  # the same with every sample whose path changed kept at its θ value
    edge_samples: int  # samples whose discrete path changed (cell, vignetting, on/off display)
    flagged: list | None = None  # per focus: bool (n_samples,), the samples held at θ
    #: Standard error of ``fd_interior`` from the spread of the central differences at
    #: the steps j·h it combines (``points`` > 1; 0 otherwise): the float32 rounding
    #: noise of the estimate itself, conservative where the steps' truncation differs.
    fd_interior_noise: float = 0.0
    #: Monte Carlo standard error of ``fd`` (:func:`_fd_noise`): what another set of samples
    #: would change, the yardstick of a total derivative against it.
    fd_noise: float = 0.0

    @property
    def boundary_term(self) -> float:
        return self.fd - self.fd_interior


def sample_derivatives(loss: RenderLoss, values, i: int, speeds: list | None = None) -> list[np.ndarray]:
    """Per focus: dL_s/dθ_i of every sample's share of the loss, by forward-mode AD.

    ``L = Σ_p w_p I_p`` to first order with ``w_p = 2 norm (I_p − R_p)`` and
    ``I_p = 1/spp Σ_s f_s``, so sample s carries ``w_p f_s'/spp``; their sum
    is ``dL/dθ_i`` (:func:`directional`). Restricted to the samples a
    :class:`Difference` kept, it is the AD counterpart of ``fd_interior``.
    Returns float64 arrays of shape (n_samples,); ``speeds`` (a list) gets,
    per focus, |d(display hit)/dθ_i| (mm per unit) of the valid samples.
    """
    r = loss.r
    T = r.T
    v0 = np.asarray(values, dtype=np.float64)
    e = np.zeros(len(r.names))
    e[i] = 1.0
    out = []
    for k in range(len(r.view.focus_mm)):
        w = loss.sample_weights(v0, k)  # (N, C)
        t = dr.zeros(T.Float, 1)
        dr.enable_grad(t)
        P = r.params(v0) + t * T.Float(e)
        b = r.trace(P, k)
        dr.set_grad(t, 1.0)
        # forward_to keeps the targets' gradients (the hits are interior nodes) and, unlike
        # forward_from(..., ClearNone), clears the graph's edges: edges left alive reached
        # the next derivative through Mitsuba's replayed virtual calls (isolate_grad error).
        gx, gy, *gv = dr.forward_to(b.x, b.y, *b.value)
        dr.eval(gx, gy, b.valid, *gv)  # one kernel (each read alone would re-render)
        g = np.stack([np.asarray(v, dtype=np.float64) for v in gv], axis=-1)
        g = np.where(np.isfinite(g), g, 0.0)
        out.append(np.sum(w * g, axis=-1))
        if speeds is not None:
            ok = np.asarray(dr.detach(b.valid), dtype=bool)
            sp = np.hypot(np.asarray(gx, dtype=np.float64), np.asarray(gy, dtype=np.float64))
            speeds.append(sp[ok & np.isfinite(sp)])
    return out


def motion_step(speeds, pixel_pitch: float, motion_px: float) -> float:
    """Largest step that moves the 99th percentile of display hits by ``motion_px`` pixels.

    ``speeds``: per-sample |d(hit)/dθ| (mm per unit of θ, from
    :func:`sample_derivatives`). A central difference reads the display's
    bilinear lookup over ±h: every sample within h·|x'| of a texel-centre
    line (a kink of the bilinear interpolant) gets the mean of two slopes
    instead of one, so the difference converges only linearly in the
    hits' motion. inf when no hit moves.
    """
    sp = np.concatenate([np.ravel(a) for a in speeds]) if speeds else np.zeros(0)
    sp = sp[sp > 0]
    if sp.size == 0:
        return float("inf")
    return float(motion_px * pixel_pitch / np.percentile(sp, 99.0))


def _numpy_loss(loss, samples) -> float:
    r = loss.r
    total = 0.0
    for k, f in enumerate(samples):
        img = f.reshape(r.n_pixels, r.spp, -1).mean(axis=1)
        ref = loss.targets_np[k]
        total += float(np.sum((img - ref) ** 2)) * loss.norm
    return total


def difference(loss: RenderLoss, values, i: int, h: float, points: int = 1, kinks: bool = False) -> Difference:
    """Central difference of parameter ``i`` at step ``h``, with its interior part.

    A sample's path changed when its tracer status (mesh path: the sequence
    of shapes met) or visibility differs among the evaluated points, or its
    display hit jumps. A jump is a second difference ``δ² = x₊ − 2x₀ + x₋``
    larger than a quarter display pixel (another lenslet's image), *or*
    larger than a quarter of the first difference ``|x₊ − x₋|`` (plus a
    rounding floor). A smooth hit has ``|δ²| ≈ h²|x''| ≪ |δ¹| ≈ 2h|x'|``; a
    hit that jumps by J inside [θ−h, θ+h] has ``|δ²| ≈ |δ¹| ≈ J`` whatever
    J. The relative rule catches the small jumps that the pixel rule misses
    at small steps: rays that switch lenslet cell between two faces of a
    thick lenslet (crosstalk, ``cells = per_surface``) land a fraction of a
    pixel from where they would have, and at h = 1e-7 one such sample
    contributes J·∇E/2h, as much as thousands of smooth ones (measured on
    ini_freeform: L1.index 6.9 % and S4.x0y3 46 % off before this rule).
    ``kinks``: also flag a sample whose display hit moves into another cell
    of the bilinear interpolant (crosses a texel-centre line, where the
    lookup's slope jumps): its difference is the mean of two slopes, AD's
    one of them. At h = 1e-7 on ini_freeform a single such sample (of
    248,832) moved 1.5e-4 px and carried the 0.9 % gap of L1.index. Meant
    for steps that move hits by a small fraction of a pixel (analytic path).
    ``fd_interior`` keeps the flagged samples at their θ value, so it is the
    difference of the continuous part of the integrand over the samples
    kept (``flagged`` lists them per focus); ``fd − fd_interior`` is the
    difference's share of the flagged samples.

    ``points`` > 1: the least-squares slope through θ ± j·h, j = 1 … points
    (the weighted mean Σ j² D_j / Σ j² of the central differences D_j at
    steps j·h; exact for polynomials up to degree 2 like a single central
    difference). It averages out the rounding noise of float32 renders
    (mesh path), which does not shrink with h.
    """
    r = loss.r
    v0 = np.asarray(values, dtype=np.float64)
    js = list(range(1, int(points) + 1))
    tol = 0.25 * r.layout.pixel_pitch
    # Rounding floor of a display hit: float64 ~1e-13 mm, float32 (mesh) ~1e-5 mm.
    floor = (1e-9 if np.dtype(r.T.np_dtype) == np.float64 and getattr(r, "path", "analytic") != "mesh"
             else 1e-4) * r.layout.pixel_pitch
    flags = []
    L_all = {j: [[], []] for j in js}
    L_int = {j: [[], []] for j in js}
    n = 0
    for k in range(len(r.view.focus_mm)):
        x0, y0, ok0, s0, f0 = _batch_numpy(r, v0, k)
        evals = {}
        for j in js:
            for sgn in (-1, 1):
                v = v0.copy()
                v[i] += sgn * j * h
                evals[(j, sgn)] = _batch_numpy(r, v, k)
        flip = np.zeros(len(x0), dtype=bool)
        for j in js:
            xm, ym, okm, sm, _ = evals[(j, -1)]
            xp, yp, okp, sp, _ = evals[(j, 1)]
            d2 = np.hypot(xp - 2 * x0 + xm, yp - 2 * y0 + ym)
            d1 = np.hypot(xp - xm, yp - ym)
            jump = (okm | ok0 | okp) & ((d2 > tol) | (d2 > 0.25 * d1 + floor))
            flip |= (okm != ok0) | (okp != ok0) | (sm != s0) | (sp != s0) | jump
            if kinks:
                cells = [_texel_cell(r.layout, x, y) for x, y in ((xm, ym), (x0, y0), (xp, yp))]
                flip |= (okm | ok0 | okp) & ((cells[0] != cells[1]) | (cells[2] != cells[1]))
        n += int(np.count_nonzero(flip))
        flags.append(flip)
        for j in js:
            for side, sgn in enumerate((-1, 1)):
                f = evals[(j, sgn)][4]
                L_all[j][side].append(f)
                L_int[j][side].append(np.where(flip[:, None], f0, f))

    def diffs(L):
        return np.array([(_numpy_loss(loss, L[j][1]) - _numpy_loss(loss, L[j][0])) / (2 * j * h) for j in js])

    w = np.array([j * j for j in js], dtype=np.float64)
    D_all, D_int = diffs(L_all), diffs(L_int)
    fd_noise = _fd_noise(loss, L_all[js[0]], h)
    fd_int = float(np.sum(w * D_int) / np.sum(w))
    noise = 0.0
    if len(js) > 1:
        # Weighted spread of the D_j about their mean, over (points − 1) degrees of freedom.
        noise = float(np.sqrt(np.sum(w * (D_int - fd_int) ** 2) / np.sum(w) / (len(js) - 1)))
    return Difference(h, float(np.sum(w * D_all) / np.sum(w)), fd_int, n, flags, noise, fd_noise)


def _fd_noise(loss: RenderLoss, sides, h: float) -> float:
    """Monte Carlo standard error of the central difference ``(L₊ − L₋)/2h`` from the spread
    of its samples within each pixel (first order in the pixel means).

    Per pixel ``ΔL_p = norm Σ_c (I₊ − I₋)(I₊ + I₋ − 2R)``; a sample s of the pixel enters
    it through ``z_s = 2 norm/spp Σ_c [(I₊ − R) f₊,s − (I₋ − R) f₋,s]``, so
    ``Var ΔL_p ≈ spp · var(z)`` (the samples of a pixel are independent), and pixels and
    focus distances add. ``sides``: per side (−, +) the per-focus (N, C) sample values.
    """
    r = loss.r
    var = 0.0
    for k in range(len(sides[0])):
        fm = sides[0][k].reshape(r.n_pixels, r.spp, -1)
        fp = sides[1][k].reshape(r.n_pixels, r.spp, -1)
        ref = loss.targets_np[k][:, None, :]
        Ip, Im = fp.mean(axis=1, keepdims=True), fm.mean(axis=1, keepdims=True)
        z = 2.0 * loss.norm / r.spp * np.sum((Ip - ref) * fp - (Im - ref) * fm, axis=-1)
        if r.spp > 1:
            var += float(np.sum(r.spp * np.var(z, axis=1, ddof=1)))
    return float(np.sqrt(var) / (2.0 * h))


def _texel_cell(lay, x, y):
    """Index of the bilinear cell (between four texel centres) of display hits (x, y) (mm)."""
    fx = np.floor((x - lay.center[0]) / lay.pixel_pitch + 0.5 * lay.width - 0.5)
    fy = np.floor((lay.center[1] - y) / lay.pixel_pitch + 0.5 * lay.height - 0.5)
    return fy * (lay.width + 1) + fx


def gradcheck(renderer, targets, names: list[str], values=None, rel_step: float = REL_STEP,
              edge_rel_step: float = EDGE_REL_STEP, sweep: tuple[float, ...] = (), log=None,
              fd_points: int = 1, motion_px: float | None = None) -> dict:
    """Compare AD (reverse and forward) with central differences for ``names``.

    Returns ``{"loss", "params": [...], "seconds": {...}}``. Each parameter record:

    ``name``, ``value``, ``unit``; ``ad`` (reverse mode), ``ad_forward``;
    ``fd``, ``fd_interior``, ``fd_step`` (the central difference at the step
    of :func:`fd_step` with ``rel_step`` (``rule_step``), capped by
    :func:`motion_step` at ``motion_px`` display pixels (default: analytic
    path :data:`MOTION_PX`, mesh path :data:`MESH_MOTION_PX`; 0: off), and its
    interior part; analytic path: samples crossing a bilinear kink are flagged too);
    ``ad_kept`` (AD over the samples ``fd_interior`` kept, ``kept_samples``;
    ``flagged_samples`` held at θ); ``rel_err = |ad − fd| / |fd|`` and
    ``interior_rel_err = |ad_kept − fd_interior| / |fd_interior|``;
    ``boundary_term`` (per unit of the parameter), measured at
    the larger ``edge_rel_step`` where enough samples cross an edge
    (``edge_samples``, ``edge_step``; the flagged samples' difference minus
    their AD); ``bias = −boundary_term / (ad +
    boundary_term)``, the share of the full derivative that AD misses;
    ``boundary`` (see the module docstring); ``forward_reverse_rel``; with
    ``sweep`` (relative steps, uncapped), ``fd_sweep`` [{``rel_step``, ``step``, ``fd``,
    ``fd_interior``, ``ad_kept``, ``interior_rel_err``, ``boundary_term``, ``edge_samples``}]. ``fd_points``: points
    per side of the main difference (see :func:`difference`; the edge term
    always uses one).
    """
    r = renderer
    if fd_points < 1:
        raise ValueError(f"fd_points = {fd_points!r}: expected >= 1")
    unknown = [n for n in names if n not in r.index]
    if unknown:
        raise ValueError(f"unknown parameter(s) {', '.join(unknown)}: see `lfsim params DESIGN` "
                         f"(and {', '.join(r.names[-1:])})")
    mesh = getattr(r, "path", "analytic") == "mesh"
    if motion_px is None:
        motion_px = MESH_MOTION_PX if mesh else MOTION_PX
    # Kink crossings are flagged where steps are tiny (analytic, float64); the mesh
    # path's float32 steps move hits by tenths of a pixel over a blurred display.
    kinks = not mesh
    loss = RenderLoss(r, targets)
    v0 = r.values0.copy() if values is None else np.asarray(values, dtype=np.float64)
    units = _units(r)
    t0 = time.perf_counter()
    wrt = [r.index[n] for n in names]
    L0, grad = gradient(loss, v0, wrt)
    t_rev = time.perf_counter() - t0
    grad_total, t_total = None, None
    if total_available(r):
        t0 = time.perf_counter()
        _, grad_total = gradient(loss, v0, wrt, total=True)
        t_total = time.perf_counter() - t0
    rows, t_fwd, t_fd = [], 0.0, 0.0
    for name in names:
        i = r.index[name]
        e = np.zeros_like(v0)
        e[i] = 1.0
        t0 = time.perf_counter()
        ad_f = directional(loss, e, v0)
        t_fwd += time.perf_counter() - t0
        t0 = time.perf_counter()
        speeds: list = []
        per = sample_derivatives(loss, v0, i, speeds)
        t_fwd += time.perf_counter() - t0
        t0 = time.perf_counter()
        h_rule = fd_step(name, v0[i], units[i], rel_step)
        h = h_rule if not motion_px else min(h_rule, motion_step(speeds, r.layout.pixel_pitch, motion_px))
        main = difference(loss, v0, i, h, fd_points, kinks=kinks)
        edge = difference(loss, v0, i, fd_step(name, v0[i], units[i], edge_rel_step))
        sw = [(rel, difference(loss, v0, i, fd_step(name, v0[i], units[i], rel), kinks=kinks)) for rel in sweep]
        t_fd += time.perf_counter() - t0
        ad = float(grad[i])

        def kept(d):  # AD over the samples the difference kept (its fair counterpart)
            return float(sum(np.sum(g[~f]) for g, f in zip(per, d.flagged)))

        ad_kept = kept(main)
        # Edge term: the flagged samples' change minus their own interior (AD) part.
        B = edge.boundary_term - (ad - kept(edge))
        total = ad + B
        rec = {"name": name, "value": float(v0[i]), "unit": units[i], "ad": ad, "ad_forward": ad_f,
               "ad_kept": ad_kept, "kept_samples": int(sum(f.size for f in main.flagged)) - main.edge_samples,
               "flagged_samples": main.edge_samples,
               "fd": main.fd, "fd_interior": main.fd_interior, "fd_step": main.step, "rule_step": h_rule,
               "rel_err": _rel(ad, main.fd), "interior_rel_err": _rel(ad_kept, main.fd_interior),
               "interior_noise_rel": (main.fd_interior_noise / abs(main.fd_interior)
                                      if main.fd_interior != 0.0 else 0.0),
               "boundary_term": B, "edge_step": edge.step, "edge_samples": edge.edge_samples,
               "bias": (-B / total) if total != 0.0 else 0.0,
               "boundary": bool(edge.edge_samples > 0 and abs(B) >= BOUNDARY_SHARE * abs(total)),
               "forward_reverse_rel": _rel(ad_f, ad)}
        # The total derivative (boundary term included) against the full difference at the
        # edge step, with that difference's own Monte Carlo noise as the yardstick.
        rec["fd_total"], rec["fd_noise"] = edge.fd, edge.fd_noise
        if grad_total is not None:
            at = float(grad_total[i])
            rec["ad_total"] = at
            rec["ad_boundary"] = at - ad
            rec["total_rel_err"] = _rel(at, edge.fd)
            rec["total_sigma"] = abs(at - edge.fd) / edge.fd_noise if edge.fd_noise > 0 else (
                0.0 if at == edge.fd else float("inf"))
            rec["total_ok"] = bool(abs(at - edge.fd) <= max(TOTAL_REL_TOL * abs(edge.fd),
                                                            TOTAL_SIGMAS * edge.fd_noise))
        if sweep:
            rec["fd_sweep"] = [{"rel_step": rel, "step": d.step, "fd": d.fd, "fd_interior": d.fd_interior,
                                "ad_kept": kept(d), "interior_rel_err": _rel(kept(d), d.fd_interior),
                                "boundary_term": d.boundary_term - (ad - kept(d)), "edge_samples": d.edge_samples}
                               for rel, d in sw]
        rows.append(rec)
        if log:
            tot = f"  total {rec['ad_total']:.6g} vs {edge.fd:.6g} ± {edge.fd_noise:.2g}" if "ad_total" in rec else ""
            log(f"{name}: ad {ad:.6g}  fd {main.fd:.6g}  interior {main.fd_interior:.6g}  edge term {B:.3g}{tot}")
    seconds = {"reverse": round(t_rev, 3), "forward": round(t_fwd, 3), "finite_differences": round(t_fd, 3)}
    if t_total is not None:
        seconds["reverse_total"] = round(t_total, 3)
    return {"loss": L0, "params": rows, "samples": r.n_pixels * r.spp * len(r.view.focus_mm),
            "total": grad_total is not None, "seconds": seconds}


def total_available(r) -> bool:
    """Whether the renderer's total derivative exists: the analytic path with the ideal eye
    (:mod:`lfsim.render.boundary`)."""
    return getattr(r, "path", "analytic") == "analytic" and all(a is not None for a in getattr(r, "_aims", [None]))


def _rel(a: float, b: float) -> float:
    if b == 0.0:
        return 0.0 if a == 0.0 else float("inf")
    return abs(a - b) / abs(b)


def _units(r) -> list[str]:
    table = {n: u for n, _, u in r.model.system.parameter_table()}
    return [table.get(n, "mm") for n in r.names]


#: Mesh path defaults (float32 Mitsuba arithmetic): the relative step of the main
#: difference, its points per side (least-squares slope) and the edge step.
MESH_REL_STEP = 1e-3
MESH_FD_POINTS = 4
MESH_EDGE_REL_STEP = 1e-2
#: Mesh path: the main step is capped to move the 99th percentile of display hits by
#: 0.25 display pixel (smooth on the σ = 2 px display). At the 1e-3 rule step with 4
#: points, L1.index moved them further and the slope's cubic term cost 7 % (Fresnel on).
MESH_MOTION_PX = 0.25
#: Mesh path: Gaussian σ (display pixels) of the display image. Float32 forces
#: differences whose steps move display hits by 0.1–0.5 pixel; with binary
#: elemental images the bilinear kinks then dominate them (measured: 7–95 %
#: off on ini_coaxial), with σ = 2 px they are smooth at that scale.
MESH_DISPLAY_BLUR = 2.0
#: Largest forward/reverse disagreement accepted, per path (float64 / float32 renders).
FORWARD_REVERSE_TOL = {"analytic": 1e-6, "mesh": 1e-4}


#: Cost of one reverse- plus one forward-mode AD render, in primal renders (measured: about 5).
AD_RENDERS = 6.0


def estimate(view, n_params: int, fd_points: int, n_sweep: int, mesh: bool, target_spp: int | None = None):
    """Run time and peak memory of a gradient check (:class:`lfsim.budget.Estimate`): the target
    (natural view), the AD renders and, per parameter, the finite differences, edge and sweep steps."""
    from .. import budget

    W, H = view.resolution
    samples = W * H * view.spp * len(view.focus_mm)
    rate = budget.threads() * budget.RATES["display_mesh" if mesh else "display_analytic"]
    renders = AD_RENDERS + n_params * (2 * fd_points + 2 + 2 * n_sweep)
    target = W * H * (target_spp or 4 * view.spp) * len(view.focus_mm)
    seconds = renders * samples / rate + target / (budget.threads() * budget.RATES["natural"])
    # AD keeps each lane's path state for the reverse pass: about 1 kB per sample (float64 analytic path)
    nbytes = budget.BASE_BYTES + 1024.0 * samples
    return budget.Estimate(f"gradient check of {n_params} parameter(s), {renders:.0f} renders of {W}x{H} px x "
                           f"{view.spp} spp x {len(view.focus_mm)} focus distance(s)", seconds, nbytes,
                           note="plus kernel compiles on a design's first run")


def run(design, content, names: list[str], view, rel_step: float | None = None,
        edge_rel_step: float | None = None, sweep: tuple[float, ...] = (), precision: str = "float64",
        target_spp: int | None = None, log=None, optics: str = "analytic", tessellation: float = 0.25,
        fresnel: bool = False, display_blur: float | None = None, fd_points: int | None = None,
        motion_px: float | None = None) -> dict:
    """Gradient check of the analytic (or mesh) display path for ``design`` showing ``content``.

    Builds an :class:`~lfsim.render.diff_render.AnalyticRenderer` (``optics
    = "analytic"``) or a :class:`~lfsim.render.mesh_ad.MeshRenderer`
    (``"mesh"``: Mitsuba meshes at ``tessellation`` × the default density,
    path-traced by the specular-chain integrator, float32; ``fresnel``:
    interfaces weigh refraction by 1 − F) for ``view`` (a
    :class:`~lfsim.render.diff_render.ViewSpec`), renders the natural view
    of the content through the same eye as the target (``target_spp``,
    default 4 × the view's spp) and calls :func:`gradcheck`.
    ``display_blur``: Gaussian σ (display pixels) applied to the elemental
    images (default 0; mesh: :data:`MESH_DISPLAY_BLUR`). Steps default to the path's (:data:`REL_STEP`,
    :data:`EDGE_REL_STEP`; mesh: :data:`MESH_REL_STEP` with
    :data:`MESH_FD_POINTS` points per side, :data:`MESH_EDGE_REL_STEP`). The
    returned document adds the settings (``design``, ``content``, ``path``,
    ``resolution``, ``spp``, ``focus_mm``, ``cdp_mm``, ``pupil_mm``,
    ``seed``, ``cells``, ``precision``, ``rel_step``, ``edge_rel_step``,
    ``fd_points``, mesh: ``tessellation``, ``fresnel``) and ``setup_s``.
    """
    from .diff_render import AnalyticRenderer

    if optics not in ("analytic", "mesh"):
        raise ValueError(f"optics = {optics!r}: expected 'analytic' or 'mesh'")
    mesh = optics == "mesh"
    rel_step = rel_step if rel_step is not None else (MESH_REL_STEP if mesh else REL_STEP)
    edge_rel_step = edge_rel_step if edge_rel_step is not None else (MESH_EDGE_REL_STEP if mesh else EDGE_REL_STEP)
    fd_points = int(fd_points if fd_points is not None else (MESH_FD_POINTS if mesh else 1))
    display_blur = float(display_blur if display_blur is not None else (MESH_DISPLAY_BLUR if mesh else 0.0))
    motion_px = float(motion_px if motion_px is not None else (MESH_MOTION_PX if mesh else MOTION_PX))
    from .. import budget

    budget.check(estimate(view, len(names), fd_points, len(sweep), mesh, target_spp), log=log,
                 hint="lower --resolution or --spp, or fewer --param")
    t0 = time.perf_counter()
    display = None
    if display_blur > 0 or mesh:
        base = AnalyticRenderer(design, view, content=content, precision=precision)
        display = base.display
        if display_blur > 0:
            from scipy.ndimage import gaussian_filter

            display = gaussian_filter(display, (display_blur, display_blur, 0), mode="nearest")
    if mesh:
        from .mesh_ad import MeshRenderer
        from .meshes import tessellation as _tess

        r = MeshRenderer(design, view, display=display, tessellation=_tess(tessellation), fresnel=fresnel)
        precision = "float32"
    elif display is not None:
        r = AnalyticRenderer(design, view, display=display, precision=precision)
    else:
        r = AnalyticRenderer(design, view, content=content, precision=precision)
    unknown = [n for n in names if n not in r.index]
    if unknown:
        raise ValueError(f"--param {','.join(unknown)}: not a parameter of {design.path or design.name} "
                         "(lfsim params DESIGN lists them)")
    targets = natural_targets(r, content, spp=target_spp or 4 * view.spp, seed=view.seed + 1)
    setup = time.perf_counter() - t0
    doc = gradcheck(r, targets, names, rel_step=rel_step, edge_rel_step=edge_rel_step, sweep=sweep, log=log,
                    fd_points=fd_points, motion_px=motion_px)
    extra = {"tessellation": tessellation, "fresnel": bool(fresnel)} if mesh else {}
    doc = {"design": design.path or design.name, "content": getattr(content, "path", None),
           "path": optics, **extra, "display_blur": display_blur, "resolution": [r.W, r.H], "spp": r.spp,
           "focus_mm": list(view.focus_mm), "cdp_mm": view.cdp_mm, "pupil_mm": view.pupil_diameter_mm,
           "seed": view.seed, "cells": view.cells, "precision": precision, "rel_step": rel_step,
           "edge_rel_step": edge_rel_step, "fd_points": fd_points, "motion_px": motion_px,
           "forward_reverse_tol": FORWARD_REVERSE_TOL[optics], "setup_s": round(setup, 3), **doc}
    return doc


def table(doc: dict) -> str:
    """The gradcheck table as text (one row per parameter, with its unit; a note on the derivatives' units)."""
    head = (f"{'parameter':18s} {'value':>12s} {'unit':5s} {'AD':>12s} {'FD':>12s} {'rel err':>9s} {'AD kept':>12s} "
            f"{'FD interior':>12s} {'int err':>9s} {'FD step':>9s} {'edge term':>11s} {'bias':>8s} {'edges':>6s}  type")
    lines = [head, "-" * len(head)]
    for p in doc["params"]:
        kind = "boundary" if p["boundary"] else "interior"
        lines.append(f"{p['name']:18s} {p['value']:12.6g} {p.get('unit') or '-':5s} {p['ad']:12.5g} {p['fd']:12.5g} "
                     f"{p['rel_err']:9.2e} "
                     f"{p['ad_kept']:12.5g} {p['fd_interior']:12.5g} {p['interior_rel_err']:9.2e} "
                     f"{p['fd_step']:9.2e} {p['boundary_term']:11.4g} {100 * p['bias']:7.1f}% "
                     f"{p['edge_samples']:6d}  {kind}"
                     + (f"  total {p['ad_total']:.5g} (boundary {p['ad_boundary']:.4g}) vs {p['fd_total']:.5g} "
                        f"± {p['fd_noise']:.2g} ({p['total_sigma']:.1f} σ{'' if p['total_ok'] else ', FAIL'}"
                        f"{'; weak: noise >= |FD|' if p['fd_noise'] >= abs(p['fd_total']) else ''})"
                        if "ad_total" in p else ""))
    lines.append("AD, FD, AD kept, FD interior, edge term: d(loss)/d(parameter) per unit of the parameter "
                 "(the loss, a sum over focus distances of mean squared image differences, has no unit); "
                 "FD step in the parameter's unit. FD and rel err: the plain difference at the capped step "
                 "(a sample jumping there shows as a large error); the interior columns check AD along fixed "
                 "samples; 'edge term' is the finite-difference estimate of the boundary part (a diagnosis)"
                 + ("; 'total' is AD plus the boundary term against the full difference at the edge step, "
                    "the pass/fail of the derivative" if doc.get("total") else
                    "; no total derivative on this path (the analytic path with the ideal eye has one)"))
    return "\n".join(lines)
