"""Generic least-squares solvers: Levenberg–Marquardt and Adam, with box bounds and checkpoints.

Both minimise the merit ``F(x) = Σ r_i(x)²`` of a :class:`Problem` that returns
weighted residuals ``r`` (M,) and their Jacobian ``J`` (M, K). Nothing here knows
what the variables mean: physics lives in the problem.

Variables are solved in scaled units ``z = x / scale`` so that, for example, a
curvature of 1e-2 mm⁻¹ and an aspheric coefficient of 1e-7 mm⁻³ take steps of
comparable size. The default ``scale`` is ``|x0|``, and 1 for a variable with
``|x0| < 1e-12`` (a variable that starts at zero has no magnitude to go by; pass
``scale`` for it). Tolerances, step and gradient norms are in scaled units.

Bounds are honoured exactly at every evaluated point: each trial point is
projected onto the box ``lower ≤ x ≤ upper`` (in physical units, so no rounding
of the scaling can leave it), and ``x0`` itself is projected before the first
evaluation.

Checkpoints are ``.npz`` files (arrays plus one JSON record) written atomically
after every accepted iteration (temporary file in the same directory, then
``os.replace``). They record a fingerprint (solver, K, hashes of ``x0``, bounds
and scale, and the solver settings); resuming with a different fingerprint, or on
a problem whose cost at the checkpointed ``x`` differs from the recorded one, is
refused with a ``ValueError``. Iteration limits are not part of the fingerprint,
so a run can be resumed with a larger limit; ``resume=True`` without an existing
file starts afresh, and a resumed run evaluates the problem once at the
checkpointed ``x`` (that call is counted). The solvers draw no random numbers
and their arithmetic does not depend on time, so a resumed run reproduces an
uninterrupted one bit for bit when the problem is deterministic.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Protocol

import numpy as np

from ..progress import bar as tqdm

_LAMBDA_MAX = 1e30  # damping beyond which LM declares the run stalled
_COST_RTOL = 1e-9  # agreement required between a checkpoint's cost and the problem's on resume


class Problem(Protocol):
    """What the solvers need: weighted residuals and their Jacobian.

    The number of rows M may change from point to point: a problem may leave
    out rows that are 0 with a 0 Jacobian row (inactive hinge constraints),
    since they add nothing to the merit or to the linear model of a step.
    """

    def residuals(self, x: np.ndarray) -> np.ndarray:
        """Weighted residuals (M,) at ``x`` (K,); the merit is ``sum(r**2)``."""
        ...

    def jacobian(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Residuals (M,) and Jacobian ``∂r/∂x`` (M, K) at ``x``."""
        ...


@dataclass
class Bounds:
    """Box bounds ``lower ≤ x ≤ upper`` (K,); ``±inf`` leaves a side open."""

    lower: np.ndarray
    upper: np.ndarray

    def __post_init__(self):
        self.lower = np.array(self.lower, dtype=np.float64).reshape(-1)
        self.upper = np.array(self.upper, dtype=np.float64).reshape(-1)
        if self.lower.shape != self.upper.shape:
            raise ValueError(f"bounds: lower has {self.lower.size} entries, upper {self.upper.size}")
        if np.isnan(self.lower).any() or np.isnan(self.upper).any() or (self.lower > self.upper).any():
            raise ValueError("bounds: need lower <= upper and no NaN")

    @classmethod
    def none(cls, K: int) -> Bounds:
        """Unbounded box in ``K`` variables."""
        return cls(np.full(K, -np.inf), np.full(K, np.inf))


@dataclass
class OptimizeResult:
    """Outcome of a solver run.

    ``cost`` is ``sum(r**2)`` at ``x`` and ``cost0`` at the (projected) start.
    ``evaluations`` counts calls to ``residuals`` and ``jacobian`` together,
    including those at rejected trial points and the one a resumed run makes at
    its checkpoint. ``status`` is ``"converged"``, ``"max_iterations"``,
    ``"stalled"`` (no acceptable step could be found) or ``"stopped"`` (the
    callback asked to stop). ``history`` holds one record per accepted iteration.
    """

    x: np.ndarray
    cost: float
    cost0: float
    iterations: int
    evaluations: int
    status: str
    history: list[dict] = field(default_factory=list)


def penalty(values, lower=None, upper=None, weight=1.0) -> np.ndarray:
    """Residuals for inequality constraints ``lower ≤ values ≤ upper``.

    Returns ``weight·max(0, lower − v) + weight·max(0, v − upper)`` with the
    broadcast shape of the inputs (a side that is ``None`` is open). Inside the
    feasible range the residual is exactly zero, so a satisfied constraint does
    not pull on the design; outside it grows linearly with the violation. The
    residual has a kink at the boundary, but its square — what the merit sees —
    is an exterior quadratic penalty with a continuous gradient, which is the
    smoothness Gauss–Newton and LM need (the gain ratio absorbs the change of the
    linear model at the kink). A smooth surrogate such as softplus was not used
    because it would penalise feasible designs. NaN values propagate, so the
    solver rejects the point.
    """
    v = np.asarray(values, dtype=np.float64)
    out = np.where(np.isnan(v), np.nan, 0.0)
    if lower is not None:
        out = out + np.maximum(0.0, np.asarray(lower, dtype=np.float64) - v)
    if upper is not None:
        out = out + np.maximum(0.0, v - np.asarray(upper, dtype=np.float64))
    return np.asarray(weight, dtype=np.float64) * out


# ---------------------------------------------------------------- shared plumbing

def _setup(x0, bounds, scale):
    x0 = np.array(x0, dtype=np.float64).reshape(-1)
    K = x0.size
    if not np.isfinite(x0).all():
        raise ValueError("x0 contains non-finite values")
    b = Bounds.none(K) if bounds is None else bounds
    if b.lower.size != K:
        raise ValueError(f"bounds have {b.lower.size} entries, x0 has {K}")
    if scale is None:
        s = np.abs(x0)
        s[s < 1e-12] = 1.0
    else:
        s = np.broadcast_to(np.asarray(scale, dtype=np.float64), (K,)).copy()
        if not (np.isfinite(s).all() and (s > 0).all()):
            raise ValueError("scale must be positive and finite")
    return x0, b.lower, b.upper, s


def _digest(*arrays) -> str:
    h = hashlib.sha256()
    for a in arrays:
        h.update(np.ascontiguousarray(a, dtype=np.float64).tobytes())
    return h.hexdigest()[:16]


def _evaluate(problem, x):
    """``(r, J, finite)`` from ``problem.jacobian`` with shapes checked."""
    r, J = problem.jacobian(x.copy())
    r = np.asarray(r, dtype=np.float64).reshape(-1)
    J = np.asarray(J, dtype=np.float64)
    if J.shape != (r.size, x.size):
        raise ValueError(f"jacobian returned r {r.shape} and J {J.shape}; expected ({r.size},) "
                         f"and ({r.size}, {x.size})")
    return r, J, bool(np.isfinite(r).all() and np.isfinite(J).all())


def _projected(g, x, lower, upper):
    """Gradient with components that push against an active bound set to zero."""
    active = ((x <= lower) & (g > 0)) | ((x >= upper) & (g < 0))
    return np.where(active, 0.0, g), active


def _save(path, meta, arrays):
    path = Path(path)
    fd, tmp = tempfile.mkstemp(prefix=path.name + ".", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            np.savez(f, meta=np.array(json.dumps(meta)), **arrays)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise


class CheckpointMismatch(ValueError):
    """A checkpoint of another problem or other settings; ``keys`` names what differs."""

    def __init__(self, message: str, keys: list[str]):
        super().__init__(message)
        self.keys = keys


def _load(path, fingerprint):
    with np.load(path, allow_pickle=False) as z:
        meta = json.loads(str(z["meta"]))
        arrays = {k: z[k] for k in z.files if k != "meta"}
    stored = meta.get("fingerprint", {})
    if stored != fingerprint:
        keys = sorted(k for k in set(stored) | set(fingerprint) if stored.get(k) != fingerprint.get(k))
        raise CheckpointMismatch(f"checkpoint {path} belongs to a different problem or settings "
                                 f"(differs in {', '.join(keys)}); refusing to resume", keys)
    return meta, arrays


class _Monitor:
    """Progress bar, per-iteration timing, checkpoint writing and the user callback."""

    def __init__(self, name, total, start, progress, checkpoint, callback, on_iteration=None):
        self.bar = tqdm(total=total, initial=start, desc=name, disable=not progress, leave=False)
        self.checkpoint, self.callback, self.on_iteration = checkpoint, callback, on_iteration
        self.t0 = time.perf_counter()

    def lap(self) -> float:
        """Seconds since the previous lap (wall clock; reported only, never used in the math)."""
        t = time.perf_counter()
        dt, self.t0 = t - self.t0, t
        return dt

    def accepted(self, iteration, x, cost, meta, arrays) -> bool:
        """Record an accepted iteration; True when the callback asks to stop."""
        if self.checkpoint is not None:
            _save(self.checkpoint, meta, arrays)
        if self.on_iteration is not None and meta["history"]:
            self.on_iteration(dict(meta["history"][-1]))
        self.bar.update(1)
        self.bar.set_postfix_str(f"cost={cost:.6g}")
        return bool(self.callback(iteration, x.copy(), cost)) if self.callback is not None else False


def _start(problem, solver, x0, lower, upper, scale, settings, checkpoint, resume):
    """Fresh state at the projected ``x0``, or the state of a checkpoint re-evaluated and verified."""
    fp = {"solver": solver, "K": int(x0.size), "x0": _digest(x0), "bounds": _digest(lower, upper),
          "scale": _digest(scale), "settings": settings}
    if resume and checkpoint is not None and Path(checkpoint).exists():
        meta, arrays = _load(checkpoint, fp)
        r, J, finite = _evaluate(problem, arrays["x"])
        cost = float(r @ r) if finite else np.nan
        if not abs(cost - meta["cost"]) <= _COST_RTOL * abs(meta["cost"]):
            raise ValueError(f"checkpoint {checkpoint}: the problem gives cost={cost:.17g} at the "
                             f"checkpointed x, not cost={meta['cost']:.17g}; refusing to resume")
        meta["evaluations"] += 1
        return meta, arrays, r, J
    x = np.clip(x0, lower, upper)
    r, J, finite = _evaluate(problem, x)
    if not finite:
        raise ValueError("residuals or Jacobian are not finite at x0; start from a point where the problem is defined")
    cost = float(r @ r)
    meta = {"fingerprint": fp, "M": int(r.size), "cost": cost, "cost0": cost, "iteration": 0,
            "evaluations": 1, "history": [], "status": None}
    return meta, {"x": x}, r, J


def _result(meta, x, status) -> OptimizeResult:
    return OptimizeResult(x=x.copy(), cost=meta["cost"], cost0=meta["cost0"], iterations=meta["iteration"],
                          evaluations=meta["evaluations"], status=status, history=meta["history"])


# ---------------------------------------------------------------- Levenberg–Marquardt

def _hinge_rows(problem, r, J, hinges: bool):
    """Split ``(r, J)`` into the smooth rows and the problem's hinge rows ``(g, G)`` (the
    last ``len(g)`` entries of ``r``, whose residual is ``max(0, g)``); no hinge rows
    unless ``hinges`` and the problem reports them (``problem.hinges``)."""
    if not hinges:
        return r, J, np.zeros(0), np.zeros((0, J.shape[1]))
    g, G = getattr(problem, "hinges", (np.zeros(0), None))
    H = len(g)
    if H == 0:
        return r, J, np.zeros(0), np.zeros((0, J.shape[1]))
    G = np.asarray(G, dtype=np.float64)
    if G.shape != (H, J.shape[1]) or r.size < H:
        raise ValueError(f"problem.hinges gave g {np.shape(g)} and G {G.shape} for r {r.shape}, J {J.shape}")
    return r[:-H], J[:-H], np.asarray(g, dtype=np.float64), G


def _hinge_step(R, qtr, G, g, damp, max_sweeps: int = 50):
    """Minimiser of ``‖qtr + R h‖² + ‖max(0, g + G h)‖² + ‖damp·h‖²`` (a strictly convex,
    piecewise quadratic model): the hinge rows predicted active at the step are kept as
    linear rows, the others dropped, and the set is updated until it repeats (a
    semismooth Newton iteration; a set seen before is merged with the new one). Returns
    ``h``."""
    act = g > 0.0
    seen = set()
    n = R.shape[1]
    h = np.zeros(n)
    for _ in range(max_sweeps):
        A = np.vstack([R, G[act], np.diag(damp)])
        b = np.concatenate([-qtr, -g[act], np.zeros(n)])
        h = np.linalg.lstsq(A, b, rcond=None)[0]
        with np.errstate(invalid="ignore"):
            new = (g + G @ h) > 0.0
        if np.array_equal(new, act):
            break
        key = new.tobytes()
        act = (new | act) if key in seen else new
        seen.add(key)
    return h


def levenberg_marquardt(problem: Problem, x0, bounds: Bounds | None = None, max_iterations: int = 50,
                        lambda0: float = 1e-3, ftol: float = 1e-10, xtol: float = 1e-12, gtol: float = 1e-10,
                        scale=None, checkpoint=None, resume: bool = False, progress: bool = False,
                        callback: Callable | None = None, on_iteration: Callable | None = None,
                        hinges: bool = False) -> OptimizeResult:
    """Damped least squares (Levenberg 1944; Marquardt 1963) with Nielsen's damping update.

    In scaled units ``z = x/scale`` each trial step ``h`` minimises
    ``‖r + J h‖² + λ‖D h‖²``, solved as the linear least-squares problem
    ``[R; √λ D] h ≈ [−Qᵀr; 0]`` with ``J = QR`` (Householder QR once per
    iteration, then an SVD-based ``lstsq`` of the small stacked system for each
    trial λ), so ``JᵀJ`` and its squared condition number never enter. ``D`` is
    Marquardt's diagonal scaling, the running maximum of the column norms of the
    scaled ``J`` (Moré 1978), which makes λ a dimensionless relative damping;
    ``lambda0`` is its start value.
    The trial point is projected onto the bounds; variables held at a bound by a
    gradient pointing out of the box are frozen for the step (projected
    Gauss–Newton on the active set). With the gain ratio
    ``ρ = (F(x) − F(x+h)) / (F(x) − ‖r + J h‖²)`` a step with ρ > 0 is accepted
    and ``λ ← λ·max(1/3, 1 − (2ρ − 1)³)``, ``ν ← 2``; otherwise
    ``λ ← λ·ν``, ``ν ← 2ν`` (Nielsen 1999; Madsen, Nielsen & Tingleff 2004,
    "Methods for Non-Linear Least Squares Problems", §3.2). A trial point with
    non-finite residuals or Jacobian is rejected in the same way.

    Trial points are evaluated with ``residuals``; ``jacobian`` is called only at
    accepted points. Convergence (status ``"converged"``): ``F = 0``; the
    max-norm of the projected gradient ``2 Jᵀr`` (scaled units) ≤ ``gtol``; the
    projected step ``‖h‖ ≤ xtol·(‖z‖ + xtol)``; or an accepted step whose actual
    and predicted reductions are both ≤ ``ftol·F``. ``"stalled"``: λ exceeded
    1e30 without an acceptable step. ``max_iterations`` counts accepted steps.

    History records: ``iteration``, ``cost`` (after the step), ``lambda`` (the
    damping of the accepted step), ``step_norm`` (‖h‖, scaled), ``grad_norm``
    (max-norm of the projected gradient at the new point, scaled), ``seconds``.
    ``callback(iteration, x, cost)`` returning True stops with ``"stopped"``;
    ``on_iteration(record)`` receives each history record as it is made (a log line).

    ``hinges`` (the ``lm-hinge`` solver): the problem's constraint rows enter the
    step model as hinges. After each ``jacobian`` call, ``problem.hinges`` gives
    ``(g, G)``: the signed excess of each constraint row over its limit and its
    Jacobian, **whether or not the limit holds** there; their residuals
    ``max(0, g)`` are the last ``len(g)`` entries of ``r``. The trial step then
    minimises ``‖r_s + J_s h‖² + ‖max(0, g + G h)‖² + λ‖D h‖²`` (:func:`_hinge_step`)
    instead of treating every row as linear: a constraint that holds is not pulled
    on, but a step that would break it sees the cost of doing so, and one that is
    broken is not extrapolated past its limit. ``pred`` in the gain ratio is this
    model's reduction. Without ``hinges`` a constraint that holds has a zero row
    and the model cannot see a step break it (the gain ratio then rejects such
    steps, and the damping grows).
    """
    x0, lower, upper, scale = _setup(x0, bounds, scale)
    settings = {"lambda0": float(lambda0), "ftol": float(ftol), "xtol": float(xtol), "gtol": float(gtol)}
    if hinges:
        settings["hinges"] = True
    meta, arrays, r, J = _start(problem, "levenberg_marquardt", x0, lower, upper, scale, settings,
                                checkpoint, resume)
    r_s, J_s, hg, hG = _hinge_rows(problem, r, J, hinges)
    x = arrays["x"]
    d = arrays.get("d", np.zeros(x.size))
    lam, nu = meta.get("lam", float(lambda0)), meta.get("nu", 2.0)
    cost, status = meta["cost"], meta["status"]
    mon = _Monitor("LM", max_iterations, meta["iteration"], progress, checkpoint, callback, on_iteration)
    try:
        while status is None:
            Js = J * scale
            d = np.maximum(d, np.linalg.norm(Js, axis=0))
            d[d == 0] = 1.0
            g, active = _projected(Js.T @ r, x, lower, upper)
            if cost == 0.0 or 2.0 * np.max(np.abs(g), initial=0.0) <= gtol:
                status = "converged"
                break
            if meta["iteration"] >= max_iterations:
                status = "max_iterations"
                break
            free = ~active
            Jss, Gs = J_s * scale, hG * scale
            # once per iteration; each trial λ then costs O(K³), not O(MK²)
            Q, R = np.linalg.qr(Jss[:, free] if hg.size else Js[:, free])
            qtr = Q.T @ (r_s if hg.size else r)
            rhs = np.concatenate([-qtr, np.zeros(int(free.sum()))])
            while True:
                h = np.zeros(x.size)
                if hg.size:
                    h[free] = _hinge_step(R, qtr, Gs[:, free], hg, np.sqrt(lam) * d[free])
                else:
                    A = np.vstack([R, np.diag(np.sqrt(lam) * d[free])])
                    h[free] = np.linalg.lstsq(A, rhs, rcond=None)[0]
                x_t = np.clip(x + scale * h, lower, upper)
                h = (x_t - x) / scale
                if np.linalg.norm(h) <= xtol * (np.linalg.norm(x / scale) + xtol):
                    status = "converged"
                    break
                if hg.size:  # the piecewise-quadratic model's reduction
                    Jh = Jss @ h
                    with np.errstate(invalid="ignore"):
                        gh = np.maximum(hg + Gs @ h, 0.0)
                    pred = cost - float((r_s + Jh) @ (r_s + Jh)) - float(np.nan_to_num(gh) @ np.nan_to_num(gh))
                else:
                    Jh = Js @ h
                    pred = -(2.0 * (r @ Jh) + Jh @ Jh)
                rho, step = -np.inf, None
                if pred > 0:
                    r_t = np.asarray(problem.residuals(x_t.copy()), dtype=np.float64).reshape(-1)
                    meta["evaluations"] += 1
                    if np.isfinite(r_t).all():
                        cost_t = float(r_t @ r_t)
                        rho = float((cost - cost_t) / pred)
                    if rho > 0:
                        step = _evaluate(problem, x_t)
                        meta["evaluations"] += 1
                if step is not None and step[2]:
                    break
                lam, nu = lam * nu, nu * 2.0
                if not lam <= _LAMBDA_MAX:
                    status = "stalled"
                    break
            if status is not None:
                break
            small = cost - cost_t <= ftol * cost and pred <= ftol * cost
            lam_used = lam
            x, (r, J, _) = x_t, step
            r_s, J_s, hg, hG = _hinge_rows(problem, r, J, hinges)
            cost = float(r @ r)
            lam, nu = float(lam * max(1.0 / 3.0, 1.0 - (2.0 * rho - 1.0) ** 3)), 2.0
            g_new, _ = _projected((J * scale).T @ r, x, lower, upper)
            meta["iteration"] += 1
            meta["history"].append({"iteration": meta["iteration"], "cost": cost, "lambda": lam_used,
                                    "step_norm": float(np.linalg.norm(h)),
                                    "grad_norm": float(2.0 * np.max(np.abs(g_new), initial=0.0)),
                                    "seconds": mon.lap()})
            if small:
                status = "converged"
            meta.update(cost=cost, lam=lam, nu=nu, status=status)
            if mon.accepted(meta["iteration"], x, cost, meta, {"x": x, "d": d}) and status is None:
                status = "stopped"
    finally:
        mon.bar.close()
    return _result(meta, x, status)


# ---------------------------------------------------------------- Adam

def adam(problem: Problem, x0, bounds: Bounds | None = None, iterations: int = 200, lr: float = 1e-2,
         betas: tuple[float, float] = (0.9, 0.999), eps: float = 1e-8, scale=None, checkpoint=None,
         resume: bool = False, progress: bool = False, callback: Callable | None = None,
         on_iteration: Callable | None = None) -> OptimizeResult:
    """Adam (Kingma & Ba 2015, Algorithm 1) on the merit gradient ``2 Jᵀr`` in scaled units.

    ``m ← β₁m + (1−β₁)g``, ``v ← β₂v + (1−β₂)g²``, ``z ← z − lr·m̂/(√v̂ + eps)`` with
    the bias corrections ``m̂ = m/(1−β₁ᵗ)``, ``v̂ = v/(1−β₂ᵗ)``; ``lr`` is in
    scaled units (a relative step of about ``lr`` per variable with the default
    ``scale``). Each new iterate is projected onto the bounds. If the problem is
    not finite at a new iterate, the update is undone and ``lr`` halved for the
    rest of the run (``"stalled"`` once it has been halved 40 times in a row).
    ``iterations`` counts accepted updates, one ``jacobian`` call each. The
    result is the best iterate seen (lowest cost), not necessarily the last;
    history records (``iteration``, ``cost``, ``lr``, ``step_norm``,
    ``grad_norm``, ``seconds``) describe every accepted update; ``on_iteration``
    receives each as it is made.
    """
    x0, lower, upper, scale = _setup(x0, bounds, scale)
    b1, b2 = float(betas[0]), float(betas[1])
    settings = {"lr": float(lr), "betas": [b1, b2], "eps": float(eps)}
    meta, arrays, r, J = _start(problem, "adam", x0, lower, upper, scale, settings, checkpoint, resume)
    x = arrays["x"]
    m, v = arrays.get("m", np.zeros(x.size)), arrays.get("v", np.zeros(x.size))
    best_x = arrays.get("best_x", x)
    meta.setdefault("t", 0)
    meta.setdefault("lr_factor", 1.0)
    meta.setdefault("best_cost", meta["cost"])
    status, halvings = meta["status"], 0
    mon = _Monitor("Adam", iterations, meta["iteration"], progress, checkpoint, callback, on_iteration)
    try:
        while status is None:
            g = 2.0 * (J * scale).T @ r
            if meta["cost"] == 0.0 or not _projected(g, x, lower, upper)[0].any():
                status = "converged"
                break
            if meta["iteration"] >= iterations:
                status = "max_iterations"
                break
            t = meta["t"] + 1
            m_t, v_t = b1 * m + (1.0 - b1) * g, b2 * v + (1.0 - b2) * g * g
            step_lr = lr * meta["lr_factor"]
            z_step = -step_lr * (m_t / (1.0 - b1**t)) / (np.sqrt(v_t / (1.0 - b2**t)) + eps)
            x_t = np.clip(x + scale * z_step, lower, upper)
            r_t, J_t, finite = _evaluate(problem, x_t)
            meta["evaluations"] += 1
            if not finite:
                meta["lr_factor"] *= 0.5
                halvings += 1
                if halvings >= 40:
                    status = "stalled"
                continue
            halvings = 0
            h = (x_t - x) / scale
            x, r, J, m, v = x_t, r_t, J_t, m_t, v_t
            cost = float(r @ r)
            if cost < meta["best_cost"]:
                best_x, meta["best_cost"] = x, cost
            g_new, _ = _projected(2.0 * (J * scale).T @ r, x, lower, upper)
            meta["iteration"] += 1
            meta["history"].append({"iteration": meta["iteration"], "cost": cost, "lr": step_lr,
                                    "step_norm": float(np.linalg.norm(h)),
                                    "grad_norm": float(np.max(np.abs(g_new), initial=0.0)),
                                    "seconds": mon.lap()})
            meta.update(cost=cost, t=t)
            if mon.accepted(meta["iteration"], x, cost, meta, {"x": x, "m": m, "v": v, "best_x": best_x}):
                status = "stopped"
    finally:
        mon.bar.close()
    meta["cost"] = meta["best_cost"]
    return _result(meta, best_x, status)
