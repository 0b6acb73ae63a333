"""Sub-systems of an InI-HMD (Section 3): lenslet × elemental image × CDP depth.

Every sampled sub-system (m, n, depth) × field point × pupil sample becomes one
ray; all of them are traced in a single Dr.Jit launch (split only to bound
memory), with each ray carrying its lenslet index (the tracer forces it through
that lenslet and flags crosstalk) and its parameter block (the CDP state: the
tunable lens's power). Rays go from the display toward the viewing window, as
in the method, and are aimed at their pupil point on each lenslet's stop by a
few real-ray Newton steps (the paraxial stop map as the Jacobian).
"""

from __future__ import annotations

from dataclasses import dataclass
from dataclasses import fields as dc_fields

import drjit as dr
import numpy as np

from ..backend import compact_kernels, from_numpy, to_numpy
from ..optics.tracer import RayState
from ..optics.vector import GAP
from .model import IniModel


@dataclass
class Subsystems:
    """Sampled sub-systems (0-based lenslet indices) and their field points."""

    m: np.ndarray  # (S,)
    n: np.ndarray  # (S,)
    k: np.ndarray  # (S,) CDP state index
    fields: np.ndarray  # (F, 2) field fractions of the EI half-size, in [−1, 1]
    center: np.ndarray  # (S, 2) lenslet centres, Eq. (1)
    display: np.ndarray  # (S, F, 2) display points of the fields (EI centre + offset)

    def __len__(self) -> int:
        return len(self.m)


def lenslet_indices(count: int, stride: int, keep_upper_half: bool) -> np.ndarray:
    """0-based lenslet indices along one axis: every ``stride``-th, both ends included;
    with symmetry only the upper half (centre included)."""
    idx = list(range(0, count, stride))
    if idx[-1] != count - 1:
        idx.append(count - 1)
    idx = np.array(idx)
    if keep_upper_half:
        idx = idx[2 * idx >= count - 1]
        if (count - 1) % 2 == 0 and (count - 1) // 2 not in idx:
            idx = np.concatenate([[(count - 1) // 2], idx])
    return idx


def field_grid(nf: int, fraction: float) -> np.ndarray:
    """``nf × nf`` field fractions in [−fraction, fraction]² (the centre first when nf is odd)."""
    v = np.linspace(-fraction, fraction, nf) if nf > 1 else np.zeros(1)
    fx, fy = np.meshgrid(v, v, indexing="xy")
    f = np.stack([fx.ravel(), fy.ravel()], axis=1)
    order = np.argsort(np.hypot(f[:, 0], f[:, 1]), kind="stable")
    return f[order]


def sample(model: IniModel, stride=None, symmetry=None, depths=None, lenslets=None,
           fields=None) -> Subsystems:
    """Choose sub-systems and fields (defaults from the design's ``[ini.analysis]``).

    Parameters
    ----------
    stride : (int, int)
    symmetry : {"none", "x", "y", "xy"}
        "x": the design is mirror-symmetric in x, evaluate lenslets with x ≥ 0 only.
    depths : list of int, optional
        CDP state indices (default all).
    lenslets : list of (m, n), optional
        Explicit 0-based lenslets (overrides stride and symmetry).
    fields : (F, 2) array, optional
        Field fractions (default: ``fields × fields`` grid at ``field_fraction``).
    """
    spec, arr = model.spec, model.arr
    stride = stride or spec.stride
    symmetry = symmetry or spec.symmetry
    depths = list(range(len(model.depths))) if depths is None else list(depths)
    if lenslets is None:
        mi = lenslet_indices(arr.m, stride[0], "x" in symmetry)
        ni = lenslet_indices(arr.n, stride[1], "y" in symmetry)
        mm, nn = np.meshgrid(mi, ni, indexing="xy")
        lenslets = np.stack([mm.ravel(), nn.ravel()], axis=1)
    lenslets = np.asarray(lenslets, dtype=np.int64).reshape(-1, 2)
    if fields is None:
        fields = field_grid(spec.fields, spec.field_fraction)
    fields = np.asarray(fields, dtype=np.float64).reshape(-1, 2)
    m = np.tile(lenslets[:, 0], len(depths))
    n = np.tile(lenslets[:, 1], len(depths))
    k = np.repeat(np.array(depths, dtype=np.int64), len(lenslets))
    center = model.lenslet_center(m, n)
    display = display_points(model, m, n, k, fields)
    return Subsystems(m, n, k, fields, center, display)


def display_points(model: IniModel, m, n, k, fields) -> np.ndarray:
    """Display points (mm) of field fractions in the elemental images of lenslets (m, n) at CDP states k.

    ``fields`` is (F, 2), shared by every sub-system, or (S, F, 2), per
    sub-system. A fraction of ±1 is the centre of the EI's edge pixel: half an
    EI less half a pixel from the EI centre (Eq. 1 layout, ``model.ei_centers``).
    """
    m, n, k = (np.asarray(a).reshape(-1) for a in (m, n, k))
    fields = np.asarray(fields, dtype=np.float64)
    per_sub = fields.ndim == 3
    display = np.empty((len(m), fields.shape[-2], 2))
    ppe = np.array(model.spec.pixels_per_ei, dtype=np.float64)
    for kk in set(k.tolist()):
        sel = k == kk
        s0 = model.ei_centers(kk, m[sel], n[sel])
        half = 0.5 * model.ei_pitch(kk) * (1.0 - 1.0 / ppe)
        f = fields[sel] if per_sub else fields[None, :, :]
        display[sel] = s0[:, None, :] + f * half
    return display


@dataclass
class Bundle:
    """Rays of sub-systems × fields × pupil samples at the viewing window (VW frame).

    Shapes: (S, F, R, ...). ``pos`` (x, y) on the VW plane, ``dir`` unit
    direction (+z toward the eye), ``opl`` optical path from the display point
    (mm), ``status`` (0 = reached the VW), ``rho`` (R, 2) the pupil samples.
    """

    subs: Subsystems
    rho: np.ndarray
    pos: np.ndarray
    dir: np.ndarray
    opl: np.ndarray
    status: np.ndarray
    aim_error: float  # largest stop miss of a traced ray after aiming (mm)

    @property
    def ok(self) -> np.ndarray:
        return self.status == 0

    def slopes(self) -> np.ndarray:
        return self.dir[..., :2] / self.dir[..., 2:3]


def trace(model: IniModel, subs: Subsystems, rho: np.ndarray, aim_iterations: int = 30,
          max_rays: int = 2_000_000, progress=None) -> Bundle:
    """Trace every (sub-system, field, pupil sample) ray to the viewing window.

    ``rho`` (R, 2) are pupil points in units of the stop half-widths. Launches
    hold at most ``max_rays`` rays (whole sub-systems each).
    """
    return trace_many([model], subs, rho, aim_iterations, max_rays, progress)[0]


def trace_many(models: list[IniModel], subs: Subsystems, rho: np.ndarray, aim_iterations: int = 30,
               max_rays: int = 2_000_000, progress=None) -> list[Bundle]:
    """:func:`trace` of the same sub-systems in several designs, fused into shared launches.

    ``models`` are InI models of designs with the same surfaces and parameter
    table (e.g. the perturbed copies of one design in a tolerance run); their
    parameter vectors are stacked as blocks of one packed array and every ray
    carries its design's block, so one kernel launch traces all of them. Each
    design's rays are aimed with its own first-order data and stop, and stop
    their Newton steps when that design's rays have converged, so every
    design's bundle is bit for bit the bundle :func:`trace` gives it alone.
    Returns one :class:`Bundle` per model.
    """
    rho = np.asarray(rho, dtype=np.float64).reshape(-1, 2)
    K = len(models)
    S, F, R = len(subs), subs.display.shape[1], len(rho)
    per_sub = F * R * K
    step = max(1, max_rays // per_sub)
    pos = np.empty((K, S, F, R, 2))
    dirs = np.empty((K, S, F, R, 3))
    opl = np.empty((K, S, F, R))
    status = np.empty((K, S, F, R), dtype=np.int64)
    worst = np.zeros(K)
    for a in range(0, S, step):
        b = min(S, a + step)
        out = _trace_chunk(models, subs, slice(a, b), rho, aim_iterations)
        pos[:, a:b], dirs[:, a:b], opl[:, a:b], status[:, a:b], err = out
        worst = np.maximum(worst, err)
        if progress is not None:
            progress(b - a)
    return [Bundle(subs, rho, pos[u], dirs[u], opl[u], status[u], float(worst[u])) for u in range(K)]


def _trace_chunk(models: list[IniModel], subs: Subsystems, sl: slice, rho: np.ndarray, iterations: int):
    s = subs.display[sl]  # (s, F, 2); lenslet centres follow from (m, n)
    ns, F, R = s.shape[0], s.shape[1], len(rho)
    K = len(models)
    shape = (K, ns, F, R)
    s_r = np.broadcast_to(s[None, :, :, None, :], shape + (2,)).reshape(-1, 2)
    rho_r = np.broadcast_to(rho[None, None, None, :, :], shape + (2,)).reshape(-1, 2)
    m_r = np.broadcast_to(subs.m[sl][None, :, None, None], shape).ravel()
    n_r = np.broadcast_to(subs.n[sl][None, :, None, None], shape).ravel()
    k_r = np.broadcast_to(subs.k[sl][None, :, None, None], shape).ravel()
    u_r = np.broadcast_to(np.arange(K)[:, None, None, None], shape).ravel()
    pl, dl, opl, status, worst = trace_rays_many(models, u_r, s_r, m_r, n_r, rho_r, k_r, iterations)
    return (pl.reshape(shape + (2,)), dl.reshape(shape + (3,)), opl.reshape(shape),
            status.reshape(shape), worst)


def trace_rays(model: IniModel, s, m, n, rho, k, iterations: int = 30):
    """Aim and trace flat ray lists from the display to the viewing window.

    Ray i leaves display point ``s[i]`` (x, y) through the point ``rho[i]``
    (units of the stop half-widths, 0 = the stop centre: the chief ray) of
    lenslet (``m[i]``, ``n[i]``) (0-based) in CDP state ``k[i]``. The slope is
    first aimed paraxially, then by real-ray Newton steps on the stop hit.

    Returns ``(pos (N, 2), dir (N, 3), opl (N,), status (N,), aim_error)``: the
    viewing-window position and unit direction in the viewing-window frame
    (failed rays: 0 and +z), the optical path (mm), the tracer status, and the
    largest stop miss of a surviving ray (mm).
    """
    s = np.asarray(s, dtype=np.float64).reshape(-1, 2)
    pl, dl, opl, status, worst = trace_rays_many([model], np.zeros(len(s), dtype=np.int64), s, m, n, rho, k,
                                                 iterations)
    return pl, dl, opl, status, float(worst[0])


def _stack(models: list[IniModel]):
    """The packed parameters of ``models`` (block ``u·states + k``) and their common tracer."""
    tr = models[0].tracer
    for mo in models[1:]:
        if (mo.tracer.n_params != tr.n_params or mo.tracer.names != tr.names
                or len(mo.depths) != len(models[0].depths)):
            raise ValueError(f"{mo.file}: cannot share launches with {models[0].file} "
                             "(another parameter table or CDP state count)")
    P = tr.params(values=np.concatenate([mo.values() for mo in models]))
    return tr, P, len(models[0].depths)


def _trace_aimed(models: list[IniModel], u, s, m, n, rho, k, iterations: int, record: bool = False):
    """Aim the rays (:func:`_aim_many`) and trace them from the display to the viewing window in
    one launch (``record``: every surface's hit too). Returns ``(tracer, P, out, block, launch
    origins (N, 3), stop miss)``."""
    tr, P, nk = _stack(models)
    T = tr.T
    s_r, m_r, n_r, k_r, t, err = _aim_many(models, u, s, m, n, rho, k, iterations, (tr, P, nk))
    o = np.column_stack([s_r, np.array([-mo.g for mo in models])[u]])
    d = np.column_stack([t, np.ones(len(t))])
    with dr.suspend_grad():
        block = from_numpy(T.UInt32, (u * nk + k_r).astype(np.uint32))
        lens = from_numpy(T.Int32, m_r, n_r)
        out = tr.trace(P, tr.rays(o, d), block=block, lenslet=lens, record=record, first=0,
                       last=models[0].spec.viewing_window)
    return tr, P, out, block, o, err


def ray_paths(model: IniModel, s, m, n, rho, k, iterations: int = 30):
    """Aimed rays' points from the display to the viewing window, global frame, for drawing.

    The rays of :func:`trace_rays` (display point ``s``, stop point ``rho`` of lenslet
    (``m``, ``n``), CDP state ``k``). Returns ``(points (L + 1, N, 3), ok (L + 1, N))``:
    the display point and the hit on every surface up to the viewing window (L surfaces);
    ``ok`` is False from the surface where a ray failed on.
    """
    s = np.asarray(s, dtype=np.float64).reshape(-1, 2)
    _, _, out, _, o, _ = _trace_aimed([model], np.zeros(len(s), dtype=np.int64), s, m, n, rho, k, iterations,
                                      record=True)
    with dr.suspend_grad():
        got = to_numpy(out.failed_at, *[p for p, _ in out.path])
    failed_at, hits = got[0].astype(np.int64), got[1:]
    points = np.stack([o] + list(hits))  # (L + 1, N, 3)
    idx = np.arange(len(hits) + 1)[:, None] - 1  # surface index of each row (−1: the display)
    ok = (failed_at[None, :] < 0) | (idx < failed_at[None, :])
    return points, ok


def trace_rays_many(models: list[IniModel], u, s, m, n, rho, k, iterations: int = 30):
    """:func:`trace_rays` for rays of several designs in one launch: ray i belongs to ``models[u[i]]``.

    Returns ``(pos, dir, opl, status, aim_error (K,))``, the largest stop
    miss per model.
    """
    sp = models[0].spec
    u = np.asarray(u, dtype=np.int64).reshape(-1)
    tr, P, out, block, _, err = _trace_aimed(models, u, s, m, n, rho, k, iterations)
    T = tr.T
    with dr.suspend_grad():
        # In the viewing-window frame of each ray's design (one kernel with the trace).
        Rs, os_ = tr.frames(P)
        R_vw, o_vw = Rs[sp.viewing_window].T, os_[sp.viewing_window]
        dr.eval(R_vw, o_vw)
        R = dr.gather(T.Matrix3, R_vw, block)
        p_loc = R @ (out.p - dr.gather(T.Array3, o_vw, block))
        d_loc = R @ out.d
        pl, dl, opl, status = to_numpy(p_loc, d_loc, out.opl, out.status)
    opl = opl.astype(np.float64)
    status = status.astype(np.int64)
    ok = status == 0
    pl = np.where(ok[:, None], pl, 0.0)
    dl = np.where(ok[:, None], dl, np.array([0.0, 0.0, 1.0]))
    opl = np.where(ok, opl, 0.0)
    worst = np.array([float(np.max(np.abs(err[ok & (u == j)]))) if np.any(ok & (u == j)) else 0.0
                      for j in range(len(models))])
    return pl[:, :2], dl, opl, status, worst


def _aim(model: IniModel, s, m, n, rho, k, iterations: int):
    """Launch slopes that put each ray on its pupil point of its lenslet's stop
    (paraxial aim, then real-ray Newton steps with the paraxial stop map as the
    Jacobian). Returns the flat inputs, the slopes (N, 2) and the stop miss."""
    s = np.asarray(s, dtype=np.float64).reshape(-1, 2)
    return _aim_many([model], np.zeros(len(s), dtype=np.int64), s, m, n, rho, k, iterations)


def _aim_many(models: list[IniModel], u, s, m, n, rho, k, iterations: int, stacked=None):
    """:func:`_aim` for rays of several designs (ray i of ``models[u[i]]``) in shared launches.

    Newton's method on the stop hit, inside Dr.Jit: each iteration is one
    launch that traces every ray to its lenslet's stop twice over (two
    copies, each carrying a forward-mode seed on one launch slope), so the
    2×2 Jacobian ∂(stop hit)/∂(slope) is exact and the iteration converges
    quadratically (3–4 steps from the paraxial aim instead of ~14 with the
    paraxial Jacobian). Every ray has its own convergence mask (|miss| below
    1e-13 mm, or failed): once converged, its slope is frozen, so a ray's
    result does not depend on the other rays it is launched with (a design's
    rays get the same steps alone as in a batch). The launch compiles once
    per design structure: counts, frames and targets are data. Returns the
    flat inputs, the slopes (N, 2) and the last stop miss (N, 2) (0 for
    failed rays).
    """
    tr, P, nk = stacked or _stack(models)
    T = tr.T
    sp = models[0].spec
    s_r = np.asarray(s, dtype=np.float64).reshape(-1, 2)
    N = len(s_r)
    u = np.broadcast_to(np.asarray(u, dtype=np.int64), N)
    rho_r = np.broadcast_to(np.asarray(rho, dtype=np.float64), s_r.shape)
    m_r = np.broadcast_to(np.asarray(m), N).astype(np.int32)
    n_r = np.broadcast_to(np.asarray(n), N).astype(np.int32)
    k_r = np.broadcast_to(np.asarray(k), N).astype(np.uint32)
    goal = np.empty_like(s_r)  # the pupil point on the stop, in the stop frame
    t = np.empty_like(s_r)
    for j, mo in enumerate(models):
        q = u == j
        c = mo.lenslet_center(m_r[q], n_r[q])
        t[q] = mo.aim(s_r[q], c, rho_r[q])
        goal[q] = c + rho_r[q] * mo.stop_half
    z0 = np.array([-mo.g for mo in models])[u]
    blk = (u * nk + k_r).astype(np.uint32)
    with dr.suspend_grad():
        block = from_numpy(T.UInt32, blk)
        lm, ln = from_numpy(T.Int32, m_r, n_r)
        sx, sy, sz, gx, gy, tx, ty = from_numpy(T.Float, s_r[:, 0], s_r[:, 1], z0, goal[:, 0], goal[:, 1],
                                                t[:, 0], t[:, 1])
        Rs, os_ = tr.frames(P)
        R_stop, o_stop = Rs[sp.stop].T, os_[sp.stop]  # global → stop frame, per block
        dr.eval(R_stop, o_stop)
        # Two copies of every ray: copy 0 carries the seed on tan_x, copy 1 on tan_y.
        lane = dr.arange(T.UInt32, 2 * N)
        ray = lane % tr.const(N, "UInt32")
        second = lane >= tr.const(N, "UInt32")
        blk2 = dr.gather(T.UInt32, block, ray)
        lens2 = (dr.gather(T.Int32, lm, ray), dr.gather(T.Int32, ln, ray))
        o2 = T.Array3(dr.gather(T.Float, sx, ray), dr.gather(T.Float, sy, ray), dr.gather(T.Float, sz, ray))
        R2 = dr.gather(T.Matrix3, R_stop, blk2)
        c2 = dr.gather(T.Array3, o_stop, blk2)
        g2x, g2y = dr.gather(T.Float, gx, ray), dr.gather(T.Float, gy, ray)
        dr.eval(ray, second, blk2, lens2, o2, R2, c2, g2x, g2y)
        done = dr.zeros(T.Bool, N)
        ex, ey = dr.zeros(T.Float, N), dr.zeros(T.Float, N)
        idx, idx2 = dr.arange(T.UInt32, N), dr.arange(T.UInt32, N) + tr.const(N, "UInt32")
    for _ in range(iterations):
        seed = dr.zeros(T.Float, 1)
        dr.enable_grad(seed)
        sd = dr.gather(T.Float, seed, dr.zeros(T.UInt32, 2 * N))
        d2 = T.Array3(dr.gather(T.Float, tx, ray) + dr.select(second, 0.0, sd),
                      dr.gather(T.Float, ty, ray) + dr.select(second, sd, 0.0), 1.0)
        out = tr.trace(P, RayState(o2, d2), block=blk2, lenslet=lens2, first=0, last=sp.stop, clip=False)
        loc = R2 @ (out.p - c2)
        mx, my = loc.x - g2x, loc.y - g2y
        dr.forward_from(seed)
        jx, jy = dr.grad(mx), dr.grad(my)
        with dr.suspend_grad():
            mx, my, jx, jy = dr.detach(mx), dr.detach(my), dr.detach(jx), dr.detach(jy)
            alive = dr.gather(T.UInt32, out.status, idx) == 0
            # Lanes 0..N-1: miss and its column ∂/∂tan_x; lanes N..2N-1: column ∂/∂tan_y.
            miss_x, miss_y = dr.gather(T.Float, mx, idx), dr.gather(T.Float, my, idx)
            a, c = dr.gather(T.Float, jx, idx), dr.gather(T.Float, jy, idx)
            b, d = dr.gather(T.Float, jx, idx2), dr.gather(T.Float, jy, idx2)
            miss_x = dr.select(alive, miss_x, 0.0)
            miss_y = dr.select(alive, miss_y, 0.0)
            ex, ey = dr.select(done, ex, miss_x), dr.select(done, ey, miss_y)
            det = a * d - b * c
            conv = (dr.abs(miss_x) < 1e-13) & (dr.abs(miss_y) < 1e-13)
            step = ~done & ~conv & (det != 0.0)
            inv = 1.0 / dr.select(step, det, 1.0)
            tx = dr.select(step, tx - (d * miss_x - b * miss_y) * inv, tx)
            ty = dr.select(step, ty - (a * miss_y - c * miss_x) * inv, ty)
            done = done | conv | (det == 0.0)
            dr.eval(tx, ty, ex, ey, done)
            if dr.all(done):
                break
    t, err = to_numpy(T.Array3(tx, ty, 0.0), T.Array3(ex, ey, 0.0), dtype=np.float64)
    return s_r, m_r, n_r, k_r, t[:, :2], err[:, :2]


@dataclass
class RayJacobian:
    """Aimed rays at the viewing window and their derivatives w.r.t. design columns.

    Values (N rays): ``pos`` (N, 2), ``dir`` (N, 3) in the viewing-window
    frame, ``status`` (N,) of the unclipped trace (apertures and lenslet cells
    not applied, so a ray that leaves its cell keeps a smooth path),
    ``surf`` (N, S, 2) hit (x, y) on each recorded surface in its local
    frame (on a lenslet-array surface: relative to the ray's lenslet axis),
    ``cos_in`` (N, S)
    cosine of incidence there. Derivatives ``d_pos`` (N, 2, K), ``d_dir``
    (N, 3, K), ``d_surf`` (N, S, 2, K), ``d_cos_in`` (N, S, K) are total
    derivatives: the launch slope is re-aimed (implicit function theorem on
    the stop hit), so every ray keeps its pupil point. ``ds_*``: the same
    w.r.t. the ray's display point (for a display layout that moves).
    """

    pos: np.ndarray
    dir: np.ndarray
    status: np.ndarray
    surf: np.ndarray
    cos_in: np.ndarray
    d_pos: np.ndarray
    d_dir: np.ndarray
    d_surf: np.ndarray
    d_cos_in: np.ndarray
    ds_pos: np.ndarray | None  # (N, 2, 2): total derivatives w.r.t. the display point (x, y)
    ds_dir: np.ndarray | None  # (N, 3, 2)
    ds_surf: np.ndarray | None  # (N, S, 2, 2)
    ds_cos_in: np.ndarray | None  # (N, S, 2); all four None when ``ds`` was folded in


#: Rays × derivative copies per launch of :func:`trace_rays_jacobian` (about 3.4 kB each with a
#: 20-surface freeform design): larger bundles are traced in chunks of at most this many.
MAX_RAY_COPIES = 1_000_000


def trace_rays_jacobian(model: IniModel, s, m, n, rho, k, columns, record=(), iterations: int = 30,
                        derivatives: bool = True, max_ray_copies: int | None = None, ds=None, select=None,
                        column_scale=None) -> RayJacobian:
    """:func:`trace_rays` plus forward-mode derivatives, in launches of at most
    ``max_ray_copies`` rays × (K + 4) copies (K + 2 with ``ds``; default
    :data:`MAX_RAY_COPIES`).

    Every ray is aimed and differentiated on its own, so the chunks give the
    same numbers as one launch; only the peak memory is bounded. ``ds``
    (N, 2, K), optional: the derivative of each ray's display point with
    respect to each column (a display layout that moves with the design). With
    it, copy j moves column j and the display point together, the re-aiming
    is applied inside the kernel, and only the K total derivatives come back
    (``ds_*`` are None): the same totals as ``d_* + ds_* · ds`` without
    ``ds``, in about half the memory and host time. Then also ``select``
    (optional): a function of the values (a :class:`RayJacobian` without
    derivatives) returning an (N, len(record)) mask of the recorded hits whose
    derivatives are needed (a constraint that is active there); the others
    come back as 0 and are neither computed nor copied. ``column_scale`` (K,):
    factors applied to the derivative columns (with ``ds``).
    """
    N = len(np.asarray(s).reshape(-1, 2))
    C = len(columns) + (4 if ds is None else 2) if derivatives else 1
    budget = MAX_RAY_COPIES if max_ray_copies is None else int(max_ray_copies)
    step = max(1, budget // C)
    if N <= step:
        return _trace_rays_jacobian(model, s, m, n, rho, k, columns, record, iterations, derivatives, ds, select,
                                    column_scale)
    s, rho = np.asarray(s).reshape(-1, 2), np.asarray(rho).reshape(-1, 2)
    m, n, k = (np.broadcast_to(np.asarray(a), (N,)) for a in (m, n, k))
    parts = [_trace_rays_jacobian(model, s[i:i + step], m[i:i + step], n[i:i + step], rho[i:i + step],
                                  k[i:i + step], columns, record, iterations, derivatives,
                                  None if ds is None else ds[i:i + step], select, column_scale)
             for i in range(0, N, step)]
    return RayJacobian(**{f.name: (None if getattr(parts[0], f.name) is None else
                                   np.concatenate([getattr(p, f.name) for p in parts], axis=0))
                          for f in dc_fields(RayJacobian)})


def _trace_rays_jacobian(model: IniModel, s, m, n, rho, k, columns, record=(), iterations: int = 30,
                         derivatives: bool = True, ds=None, select=None, column_scale=None) -> RayJacobian:
    """:func:`trace_rays` plus forward-mode derivatives, in one Dr.Jit launch.

    ``columns``: K pairs ``(parameter name, CDP state or None)``; a column
    moves that parameter in every state (None) or in one state only (e.g. the
    tunable lens's power). The rays are replicated K + 2 times: copy j moves
    column j, the last two copies move the launch slope (x, y); a single AD
    seed then yields every column in one forward pass (two more copies move
    the display point, unless ``ds`` moves it in the column copies), and the
    aim correction ``dt/dp = −(∂stop/∂t)⁻¹ ∂stop/∂p`` turns partial into total
    derivatives (in numpy, or with ``ds`` in a second kernel on the device).
    ``record``: surface indices whose hits (relative to the lenslet axis) and
    incidence cosines are returned too.
    """
    tr, T = model.tracer, model.T
    sp = model.spec
    s_r, m_r, n_r, k_r, t, _ = _aim(model, s, m, n, rho, k, iterations)
    N, nb, npar = len(s_r), len(model.depths), tr.n_params
    K = len(columns) if derivatives else 0
    fused = derivatives and ds is not None
    C = (K + 2 if fused else K + 4) if derivatives else 1
    base = np.concatenate([model.values(i) for i in range(nb)])
    mask = np.zeros((C, nb, npar))
    for c, (name, state) in enumerate(columns[:K]):
        if name not in tr.index:
            raise ValueError(f"unknown parameter {name!r}: see parameter_names()")
        if state is None:
            mask[c, :, tr.index[name]] = 1.0
        else:
            mask[c, int(state), tr.index[name]] = 1.0
    record = list(record)
    R_s, o_s = tr.frames_numpy()[sp.stop]
    c_r = model.lenslet_center(m_r, n_r)
    # The forward-mode kernel (26 k IR ops on the 19-surface freeform design) compiles at
    # vector width 4: at 8 its registers spill (measured, cold `optimize --iterations 1` on
    # ini_freeform: 23 s to compile and 1.9 s per launch at 4; the whole run 273 s -> 68 s).
    with compact_kernels():
        seed = dr.zeros(T.Float, 1)
        dr.enable_grad(seed)
        # One scalar seed, gathered to each width it is used at (no broadcast of a
        # width-1 variable across arrays of different widths).
        seed_p = dr.gather(T.Float, seed, dr.zeros(T.UInt32, C * nb * npar))
        P = T.Float(np.tile(base, C)) + seed_p * T.Float(mask.ravel())
        seed_r = dr.gather(T.Float, seed, dr.zeros(T.UInt32, C * N))
        # Counts and design numbers enter as opaque data (one kernel for any ray
        # count, column count or display gap).
        opq = tr.const
        j = dr.arange(T.UInt32, C * N)
        ray = j % opq(N, "UInt32")
        copy = j // opq(N, "UInt32")
        g = lambda a, typ: dr.gather(typ, from_numpy(typ, a), ray)  # noqa: E731
        block = copy * opq(nb, "UInt32") + g(k_r, T.UInt32)
        tx = g(t[:, 0], T.Float) + seed_r * dr.select(copy == opq(K, "UInt32"), 1.0, 0.0)
        ty = g(t[:, 1], T.Float) + seed_r * dr.select(copy == opq(K + 1, "UInt32"), 1.0, 0.0)
        one = dr.full(T.Float, 1.0, C * N)
        if fused:  # copy j < K moves its column's display point by ds[:, :, j]
            dsk = np.zeros((C, N, 2))
            dsk[:K] = np.moveaxis(np.asarray(ds, dtype=np.float64).reshape(N, 2, K), 2, 0)
            dsx, dsy = (from_numpy(T.Float, np.ascontiguousarray(dsk[..., a]).ravel()) for a in (0, 1))
            sx = g(s_r[:, 0], T.Float) + seed_r * dsx
            sy = g(s_r[:, 1], T.Float) + seed_r * dsy
        else:
            sx = g(s_r[:, 0], T.Float) + seed_r * dr.select(copy == opq(K + 2, "UInt32"), 1.0, 0.0)
            sy = g(s_r[:, 1], T.Float) + seed_r * dr.select(copy == opq(K + 3, "UInt32"), 1.0, 0.0)
        # Rays start on the display plane z = −g of their block: the gap is a column like any other.
        o = T.Array3(sx, sy, -dr.gather(T.Float, P, block * opq(npar, "UInt32") + tr.index[GAP]))
        out = tr.trace(P, RayState(o, T.Array3(tx, ty, one)), block=block,
                       lenslet=(g(m_r, T.Int32), g(n_r, T.Int32)), first=0, last=sp.viewing_window,
                       record=True, clip=False)
        Rs, os_ = tr.frames(P)
        Rv = dr.gather(T.Matrix3, Rs[sp.viewing_window].T, block)  # global → local
        ov = dr.gather(T.Array3, os_[sp.viewing_window], block)
        pl = Rv @ (out.p - ov)
        dl = Rv @ out.d
        stop_p = out.path[sp.stop][0]
        Rst = T.Matrix3(*(opq(float(v)) for v in R_s.T.ravel()))
        sl = Rst @ (stop_p - T.Array3(*(opq(float(v)) for v in o_s)))
        outs = [sl.x, sl.y, pl.x, pl.y, dl.x, dl.y, dl.z]
        cx, cy = g(c_r[:, 0], T.Float), g(c_r[:, 1], T.Float)
        for i in record:
            p_i, d_i = out.path[i]
            Ri = dr.gather(T.Matrix3, Rs[i].T, block)  # global → surface i's local frame
            q = Ri @ (p_i - dr.gather(T.Array3, os_[i], block))
            d_prev = out.path[i - 1][1] if i > 0 else dr.normalize(T.Array3(tx, ty, one))
            # incidence from the directions before and after (the normal is along their difference)
            dd = d_i - d_prev
            nrm = dr.norm(dd)
            cos_in = dr.select(nrm > 0, dr.abs(dr.dot(d_prev, dd)) / dr.maximum(nrm, 1e-300), 1.0)
            if model.system.surfaces[i].array is not None:
                outs += [q.x - cx, q.y - cy, cos_in]  # relative to the ray's lenslet axis
            else:
                outs += [q.x, q.y, cos_in]
        grads = []
        if derivatives:
            dr.forward_from(seed, flags=dr.ADFlag.ClearNone)
            grads = [dr.grad(v) for v in outs]
        # One kernel for every value and derivative (evaluated one by one, each would
        # re-run the whole trace).
        dr.eval(*outs, out.status, *grads)
        if fused:  # the values of copy 0 (every copy has the same)
            first = dr.arange(T.UInt32, N)
            vals0 = [dr.gather(T.Float, v, first) for v in outs]
            status0 = dr.gather(type(out.status), out.status, first)
            dr.eval(*vals0, status0)
    nS = len(record)
    if fused:
        val = np.stack([np.asarray(v, dtype=np.float64) for v in vals0], axis=1)  # (N, O)
        status = np.asarray(status0).astype(np.int64)
    else:
        val = np.stack([np.asarray(v, dtype=np.float64)[:N] for v in outs], axis=1)  # (N, O)
        status = np.asarray(out.status)[:N].astype(np.int64)
    surf = val[:, 7:].reshape(N, nS, 3) if nS else np.zeros((N, 0, 3))
    res = dict(pos=val[:, 2:4], dir=val[:, 4:7], status=status, surf=surf[..., :2], cos_in=surf[..., 2])
    if not derivatives:
        z = np.zeros
        return RayJacobian(**res, d_pos=z((N, 2, 0)), d_dir=z((N, 3, 0)), d_surf=z((N, nS, 2, 0)),
                           d_cos_in=z((N, nS, 0)), ds_pos=z((N, 2, 2)), ds_dir=z((N, 3, 2)),
                           ds_surf=z((N, nS, 2, 2)), ds_cos_in=z((N, nS, 2)))
    if fused:
        scale = np.ones(K) if column_scale is None else np.asarray(column_scale, dtype=np.float64)

        def fetch(outputs, rays):  # (n, len(outputs), K) totals of these outputs for these rays
            tot = _reaimed_totals(T, opq, grads, out.status, outputs, rays, N, K)
            n_ = N if rays is None else len(rays)
            a = np.empty((n_, len(outputs), K))
            for o_, v in enumerate(tot):
                a[:, o_, :] = np.asarray(v, dtype=np.float64).reshape(K, n_).T
            return a * scale

        with dr.suspend_grad():
            pd = fetch(list(range(2, 7)), None)  # VW position and direction: every ray
            need = (np.ones((N, nS), dtype=bool) if select is None
                    else np.asarray(select(RayJacobian(**res, d_pos=None, d_dir=None, d_surf=None, d_cos_in=None,
                                                       ds_pos=None, ds_dir=None, ds_surf=None, ds_cos_in=None)),
                                    dtype=bool).reshape(N, nS))
            # recorded hits: only where asked (np.zeros maps untouched pages lazily)
            d_surf, d_cos = np.zeros((N, nS, 2, K)), np.zeros((N, nS, K))
            for j in range(nS):
                idx = np.nonzero(need[:, j])[0]
                if idx.size:
                    a = fetch([7 + 3 * j, 8 + 3 * j, 9 + 3 * j], idx)
                    d_surf[idx, j], d_cos[idx, j] = a[:, 0:2], a[:, 2]
        return RayJacobian(**res, d_pos=pd[:, 0:2], d_dir=pd[:, 2:5], d_surf=d_surf, d_cos_in=d_cos,
                           ds_pos=None, ds_dir=None, ds_surf=None, ds_cos_in=None)
    G = np.stack([np.asarray(gv, dtype=np.float64).reshape(C, N) for gv in grads], axis=1)  # (C, O, N)
    G = np.moveaxis(G, 2, 0)  # (N, C, O)
    dt = G[:, K:K + 2, :]  # (N, 2, O)
    A = np.moveaxis(dt[:, :, 0:2], 1, 2)  # ∂stop/∂t (N, 2, 2): rows stop x/y, cols t x/y
    ok = (status == 0) & (np.abs(np.linalg.det(A)) > 0)
    A = np.where(ok[:, None, None], A, np.eye(2))

    def total(dq):  # partials (N, Q, O) → total derivatives (N, O, Q) with the ray re-aimed
        dtdq = -np.linalg.solve(A, np.moveaxis(dq[:, :, 0:2], 1, 2))  # (N, 2, Q)
        tot = np.moveaxis(dq, 1, 2) + np.einsum("nto,ntq->noq", dt, dtdq)
        tot = np.where(np.isfinite(tot), tot, 0.0)
        tot[status != 0] = 0.0
        return tot

    tp, ts = total(G[:, :K, :]), total(G[:, K + 2:K + 4, :])
    sp_ = tp[:, 7:, :].reshape(N, nS, 3, K) if nS else np.zeros((N, 0, 3, K))
    ss_ = ts[:, 7:, :].reshape(N, nS, 3, 2) if nS else np.zeros((N, 0, 3, 2))
    return RayJacobian(**res, d_pos=tp[:, 2:4], d_dir=tp[:, 4:7], d_surf=sp_[:, :, :2], d_cos_in=sp_[:, :, 2],
                       ds_pos=ts[:, 2:4], ds_dir=ts[:, 4:7], ds_surf=ss_[:, :, :2], ds_cos_in=ss_[:, :, 2])


def _reaimed_totals(T, opq, grads, status, outputs, rays, N: int, K: int):
    """Total derivatives of ``grads[o]`` for ``o`` in ``outputs``, copies 0..K−1, re-aimed
    on the device, for every ray (``rays`` None) or the rays at the indices ``rays``.

    Lane (j, i) of the forward pass holds the partial derivatives of ray i for
    copy j; copies K and K + 1 hold those for the launch slope. Holding the
    stop hit (``grads[0:2]``) fixed, ``dt = −A⁻¹ ∂stop/∂p`` with A = ∂stop/∂t,
    and ``total = ∂o/∂p + ∂o/∂t · dt`` (implicit function theorem). Rays that
    failed, a singular A or a non-finite total give 0. Returns one array of
    K·n lanes (copy-major) per output.
    """
    n = N if rays is None else len(rays)
    i = dr.arange(T.UInt32, K * n)
    e = i % opq(n, "UInt32")
    ray = e if rays is None else dr.gather(T.UInt32, from_numpy(T.UInt32, np.asarray(rays, dtype=np.uint32)), e)
    lane = (i // opq(n, "UInt32")) * opq(N, "UInt32") + ray
    tx_lane = ray + opq(K * N, "UInt32")
    ty_lane = tx_lane + opq(N, "UInt32")
    a, b = dr.gather(T.Float, grads[0], tx_lane), dr.gather(T.Float, grads[0], ty_lane)
    c, d = dr.gather(T.Float, grads[1], tx_lane), dr.gather(T.Float, grads[1], ty_lane)
    px, py = dr.gather(T.Float, grads[0], lane), dr.gather(T.Float, grads[1], lane)
    det = a * d - b * c
    good = (dr.gather(type(status), status, ray) == 0) & (det != 0.0)
    inv = 1.0 / dr.select(good, det, 1.0)
    dtx = -(d * px - b * py) * inv
    dty = -(a * py - c * px) * inv
    totals = []
    for o in outputs:
        gv = grads[o]
        tot = (dr.gather(T.Float, gv, lane) + dtx * dr.gather(T.Float, gv, tx_lane)
               + dty * dr.gather(T.Float, gv, ty_lane))
        totals.append(dr.select(good & dr.isfinite(tot), tot, 0.0))
    dr.eval(*totals)
    return totals
