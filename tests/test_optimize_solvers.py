"""Generic solvers of lfsim.optimize on problems with known answers (numpy/scipy references)."""

import os

import numpy as np
import pytest
from scipy.optimize import least_squares, lsq_linear

from lfsim.optimize import Bounds, adam, levenberg_marquardt, penalty


class Linear:
    """r = A x − b."""

    def __init__(self, A, b):
        self.A, self.b = A, b

    def residuals(self, x):
        return self.A @ x - self.b

    def jacobian(self, x):
        return self.residuals(x), self.A


class Rosenbrock:
    """r = [k(x₂ − x₁²), 1 − x₁]; minimum 0 at (1, 1)."""

    def __init__(self, k=10.0):
        self.k = k

    def residuals(self, x):
        return np.array([self.k * (x[1] - x[0] ** 2), 1.0 - x[0]])

    def jacobian(self, x):
        return self.residuals(x), np.array([[-2.0 * self.k * x[0], self.k], [-1.0, 0.0]])


class ExpDecay:
    """r = a·exp(−b t) − y: a ~ 1e3 and b ~ 1e-3, six orders of magnitude apart."""

    def __init__(self):
        rng = np.random.default_rng(7)
        self.t = np.linspace(0.0, 3000.0, 40)
        self.y = 1.2e3 * np.exp(-8e-4 * self.t) + 5.0 * rng.standard_normal(self.t.size)

    def residuals(self, x):
        return x[0] * np.exp(-x[1] * self.t) - self.y

    def jac(self, x):
        e = np.exp(-x[1] * self.t)
        return np.stack([e, -x[0] * self.t * e], axis=1)

    def jacobian(self, x):
        return self.residuals(x), self.jac(x)


class LogNaN:
    """r = log(x) − log 2: NaN for x < 0, where the first Gauss–Newton step from x = 10 lands."""

    def __init__(self):
        self.nan_trials = 0

    def residuals(self, x):
        with np.errstate(invalid="ignore"):
            r = np.log(x) - np.log(2.0)
        self.nan_trials += int(not np.isfinite(r).all())
        return r

    def jacobian(self, x):
        return self.residuals(x), np.array([[1.0 / x[0]]])


def _random_linear(m, k, seed):
    rng = np.random.default_rng(seed)
    return rng.standard_normal((m, k)) * np.logspace(0, 2, k), rng.standard_normal(m)


def test_lm_linear_matches_lstsq():
    A, b = _random_linear(30, 6, 0)
    res = levenberg_marquardt(Linear(A, b), np.ones(6))
    ref = np.linalg.lstsq(A, b, rcond=None)[0]
    assert res.status == "converged"
    np.testing.assert_allclose(res.x, ref, rtol=0, atol=1e-10)
    assert res.cost == pytest.approx(np.sum((A @ ref - b) ** 2), rel=1e-12)


def test_lm_rosenbrock():
    res = levenberg_marquardt(Rosenbrock(), [-1.2, 1.0])
    assert res.status == "converged"
    np.testing.assert_allclose(res.x, [1.0, 1.0], rtol=0, atol=1e-8)
    assert res.cost0 == pytest.approx(24.2)
    costs = [h["cost"] for h in res.history]
    assert np.all(np.diff(costs) < 0) and len(costs) == res.iterations
    assert set(res.history[0]) == {"iteration", "cost", "lambda", "step_norm", "grad_norm", "seconds"}


def test_lm_badly_scaled_exponential_matches_scipy():
    p, x0, scale = ExpDecay(), np.array([800.0, 1.5e-3]), np.array([1e3, 1e-3])
    res = levenberg_marquardt(p, x0, scale=scale)
    ref = least_squares(p.residuals, x0, jac=p.jac, x_scale=scale, method="trf",
                        xtol=1e-15, ftol=1e-15, gtol=1e-15)
    assert res.status == "converged"
    np.testing.assert_allclose(res.x, ref.x, rtol=1e-8)
    assert res.cost == pytest.approx(2.0 * ref.cost, rel=1e-12)  # scipy's cost is ½Σr²
    assert res.cost < 1e-3 * res.cost0


def test_lm_bounds_linear_matches_lsq_linear():
    A, b = _random_linear(12, 3, 1)
    lower, upper = np.array([0.0, 0.0, -np.inf]), np.array([0.5, np.inf, 0.01])
    free = np.linalg.lstsq(A, b, rcond=None)[0]
    assert np.any(free < lower) or np.any(free > upper)  # the unconstrained minimum is outside the box
    seen = []
    res = levenberg_marquardt(Linear(A, b), np.array([0.2, 0.3, 0.0]), bounds=Bounds(lower, upper),
                              callback=lambda i, x, c: seen.append(x))
    ref = lsq_linear(A, b, bounds=(lower, upper), tol=1e-14, method="bvls")
    assert res.status == "converged"
    np.testing.assert_allclose(res.x, ref.x, rtol=0, atol=1e-9)
    for x in seen + [res.x]:
        assert np.all(x >= lower) and np.all(x <= upper)
    assert np.any(res.x == lower) or np.any(res.x == upper)  # ends exactly on the box


def test_lm_rosenbrock_with_bound_ends_on_the_box():
    res = levenberg_marquardt(Rosenbrock(), [-1.2, 1.0], bounds=Bounds([-2.0, -2.0], [0.5, 2.0]))
    assert res.status == "converged"
    assert res.x[0] == 0.5
    assert res.x[1] == pytest.approx(0.25, abs=1e-8)


def test_lm_rejects_nan_trial_point():
    p = LogNaN()
    res = levenberg_marquardt(p, [10.0])
    assert p.nan_trials >= 1
    assert res.status == "converged"
    assert res.x[0] == pytest.approx(2.0, rel=1e-10)
    assert np.all(np.isfinite([h["cost"] for h in res.history]))
    # one Jacobian at x0, then per accepted step one trial residual and one Jacobian, plus the rejected trials
    assert res.evaluations == 1 + 2 * res.iterations + p.nan_trials


def test_lm_rejects_nonfinite_jacobian_at_trial_point():
    class JacobianNaNBelow3:
        def residuals(self, x):
            return x - 2.0

        def jacobian(self, x):
            return x - 2.0, np.array([[1.0 if x[0] >= 3.0 else np.nan]])

    res = levenberg_marquardt(JacobianNaNBelow3(), [10.0])
    assert res.status in ("converged", "stalled")
    assert 3.0 <= res.x[0] < 3.0 + 1e-6
    assert np.all(np.isfinite([h["cost"] for h in res.history]))


def test_nonfinite_start_is_refused():
    with pytest.raises(ValueError, match="not finite at x0"):
        levenberg_marquardt(LogNaN(), [-1.0])
    with pytest.raises(ValueError, match="not finite at x0"):
        adam(LogNaN(), [-1.0])


def test_lm_checkpoint_resume_is_bit_identical(tmp_path):
    full = levenberg_marquardt(Rosenbrock(), [-1.2, 1.0], max_iterations=10)
    assert full.status == "max_iterations" and full.iterations == 10
    ck = tmp_path / "lm.npz"
    part = levenberg_marquardt(Rosenbrock(), [-1.2, 1.0], max_iterations=4, checkpoint=ck)
    assert part.iterations == 4 and ck.exists()
    assert os.listdir(tmp_path) == ["lm.npz"]  # no temporary file left behind
    resumed = levenberg_marquardt(Rosenbrock(), [-1.2, 1.0], max_iterations=10, checkpoint=ck, resume=True)
    assert resumed.iterations == 10 and resumed.status == "max_iterations"
    assert np.array_equal(resumed.x, full.x)
    for key in ("cost", "lambda", "step_norm", "grad_norm"):
        assert [h[key] for h in resumed.history] == [h[key] for h in full.history]
    assert resumed.cost == full.cost and resumed.cost0 == full.cost0


def test_adam_checkpoint_resume_is_bit_identical(tmp_path):
    args = (Rosenbrock(), [-1.2, 1.0])
    full = adam(*args, iterations=30, lr=0.05)
    ck = tmp_path / "adam.npz"
    adam(*args, iterations=12, lr=0.05, checkpoint=ck)
    resumed = adam(*args, iterations=30, lr=0.05, checkpoint=ck, resume=True)
    assert np.array_equal(resumed.x, full.x) and resumed.cost == full.cost
    assert [h["cost"] for h in resumed.history] == [h["cost"] for h in full.history]


def test_resume_refuses_a_different_problem(tmp_path):
    ck = tmp_path / "run.npz"
    levenberg_marquardt(Rosenbrock(), [-1.2, 1.0], max_iterations=3, checkpoint=ck)
    attempts = [
        lambda: levenberg_marquardt(Rosenbrock(), [-1.0, 1.0], checkpoint=ck, resume=True),  # x0
        lambda: levenberg_marquardt(Rosenbrock(), [-1.2, 1.0], lambda0=1.0, checkpoint=ck, resume=True),
        lambda: adam(Rosenbrock(), [-1.2, 1.0], checkpoint=ck, resume=True),  # solver
        lambda: levenberg_marquardt(Linear(np.eye(3), np.ones(3)), np.ones(3), checkpoint=ck, resume=True),
        lambda: levenberg_marquardt(Rosenbrock(k=20.0), [-1.2, 1.0], checkpoint=ck, resume=True),  # cost
    ]
    for attempt in attempts:
        with pytest.raises(ValueError, match="refusing to resume") as err:
            attempt()
        assert "\n" not in str(err.value)


def test_deterministic():
    a = levenberg_marquardt(ExpDecay(), [800.0, 1.5e-3], scale=[1e3, 1e-3])
    b = levenberg_marquardt(ExpDecay(), [800.0, 1.5e-3], scale=[1e3, 1e-3])
    assert np.array_equal(a.x, b.x) and [h["cost"] for h in a.history] == [h["cost"] for h in b.history]


def _quadratic():
    rng = np.random.default_rng(3)
    A = np.diag([1.0, 2.0, 4.0, 8.0]) + 0.1 * rng.standard_normal((4, 4))
    return Linear(A, A @ np.array([3.0, -2.0, 0.5, 1.5]))


def test_adam_convex_quadratic():
    res = adam(_quadratic(), np.ones(4), iterations=300, lr=0.05)
    assert res.iterations == 300 and res.evaluations == 301
    assert res.cost <= 1e-6 * res.cost0
    assert res.cost == min(h["cost"] for h in res.history)  # the best iterate is returned
    assert set(res.history[0]) == {"iteration", "cost", "lr", "step_norm", "grad_norm", "seconds"}


def test_adam_honours_bounds():
    lower, upper = np.array([0.0, -1.0, 0.0, 0.0]), np.array([2.0, 1.0, 1.0, 1.0])
    seen = []
    res = adam(_quadratic(), np.full(4, 0.5), bounds=Bounds(lower, upper), iterations=300, lr=0.05,
               callback=lambda i, x, c: seen.append(x))
    ref = lsq_linear(_quadratic().A, _quadratic().b, bounds=(lower, upper), tol=1e-14, method="bvls")
    for x in seen:
        assert np.all(x >= lower) and np.all(x <= upper)
    assert res.x[0] == 2.0 and res.x[1] == -1.0
    assert res.cost == pytest.approx(np.sum((ref.fun) ** 2), rel=1e-6)


def test_callback_stops_and_progress_shows_cost(capsys, monkeypatch):
    import lfsim.progress

    monkeypatch.setattr(lfsim.progress, "LOG_CLOSE_AFTER", 0.0)  # a log line even for this short run
    res = levenberg_marquardt(Rosenbrock(), [-1.2, 1.0], progress=True, callback=lambda i, x, c: i >= 3)
    assert res.status == "stopped" and res.iterations == 3
    err = capsys.readouterr().err
    assert "cost=" in err and "\r" not in err  # stderr is not a terminal: plain lines


def test_penalty_zero_inside_linear_outside():
    v = np.array([-1.0, 0.0, 0.7, 2.0, 3.5])
    np.testing.assert_array_equal(penalty(v, lower=0.0, upper=2.0, weight=2.0), [2.0, 0.0, 0.0, 0.0, 3.0])
    np.testing.assert_array_equal(penalty(v, lower=0.5), [1.5, 0.5, 0.0, 0.0, 0.0])
    np.testing.assert_array_equal(penalty(v, upper=[0.0, 0.0, 0.0, 0.0, 4.0]), [0.0, 0.0, 0.7, 2.0, 0.0])
    slope = (penalty(5.0 + 1e-3, upper=2.0, weight=3.0) - penalty(5.0, upper=2.0, weight=3.0)) / 1e-3
    assert slope == pytest.approx(3.0, rel=1e-9)
    assert np.isnan(penalty([np.nan], lower=0.0)).all()
    assert not penalty(v).any()


class HingedRosenbrock:
    """Rosenbrock's residuals with a disc constraint x₁² + x₂² ≤ 1.5 as a hinge of weight
    ``w``, its row last: residual w·max(0, g), g = x₁² + x₂² − 1.5. ``hinges`` reports
    (g, ∂g) after every ``jacobian`` call, also where the constraint holds (lm-hinge)."""

    def __init__(self, w=30.0):
        self.w, self.base, self.jacobians = w, Rosenbrock(), 0
        self.hinges = (np.zeros(0), None)

    def _g(self, x):
        return np.array([self.w * (x[0] ** 2 + x[1] ** 2 - 1.5)]), np.array([[2 * self.w * x[0], 2 * self.w * x[1]]])

    def residuals(self, x):
        return np.concatenate([self.base.residuals(x), np.maximum(self._g(x)[0], 0.0)])

    def jacobian(self, x):
        self.jacobians += 1
        r0, J0 = self.base.jacobian(x)
        g, G = self._g(x)
        self.hinges = (g, G)
        return (np.concatenate([r0, np.maximum(g, 0.0)]),
                np.vstack([J0, np.where((g > 0)[:, None], G, 0.0)]))


def test_hinge_step_is_the_minimiser_of_its_piecewise_quadratic_model():
    """_hinge_step against scipy's minimiser of ‖qtr + R h‖² + ‖max(0, g + G h)‖² + ‖d h‖²
    (convex, C¹) on random models with hinges on both sides of their limit."""
    from scipy.optimize import minimize

    from lfsim.optimize.solvers import _hinge_step

    rng = np.random.default_rng(3)
    for trial in range(20):
        n, m = 5, 8
        R = np.triu(rng.standard_normal((n, n))) + 3 * np.eye(n)
        qtr, G, g = rng.standard_normal(n), 3 * rng.standard_normal((m, n)), rng.standard_normal(m)
        d = np.full(n, 0.1 * (trial + 1))

        def model(h):
            e = qtr + R @ h
            c = np.maximum(g + G @ h, 0.0)
            return e @ e + c @ c + (d * h) @ (d * h)

        def grad(h):
            return 2 * R.T @ (qtr + R @ h) + 2 * G.T @ np.maximum(g + G @ h, 0.0) + 2 * d * d * h

        h = _hinge_step(R, qtr, G, g, d)
        ref = minimize(model, np.zeros(n), jac=grad, method="BFGS", options={"gtol": 1e-12}).x
        np.testing.assert_allclose(h, ref, rtol=0, atol=1e-6)
        assert np.abs(grad(h)).max() < 1e-9 * max(1.0, np.abs(G).max() ** 2)


def test_lm_hinge_reaches_the_penalty_optimum_in_fewer_evaluations():
    """A constraint that holds at the start and binds at the optimum: plain LM's model
    cannot see its row (zero until it is broken), so steps that break it are rejected
    and the damping grows; lm-hinge's model keeps it. Both end at scipy's minimiser of
    the same exterior-penalty merit; lm-hinge with fewer evaluations."""
    x0 = np.array([-0.5, 0.2])  # inside the disc: the hinge holds, g < 0
    plain = levenberg_marquardt(HingedRosenbrock(), x0, max_iterations=500)
    hinge = levenberg_marquardt(HingedRosenbrock(), x0, max_iterations=500, hinges=True)
    p = HingedRosenbrock()
    ref = least_squares(p.residuals, x0, jac=lambda x: p.jacobian(x)[1], method="trf",
                        xtol=1e-15, ftol=1e-15, gtol=1e-15)
    assert plain.status == hinge.status == "converged"
    for res in (plain, hinge):
        np.testing.assert_allclose(res.x, ref.x, rtol=0, atol=1e-7)
        assert res.cost == pytest.approx(2.0 * ref.cost, rel=1e-9)
    assert p._g(ref.x)[0][0] > 0  # the optimum lies on the binding side of the limit
    assert hinge.evaluations < plain.evaluations


def test_lm_hinge_without_hinge_rows_is_plain_lm():
    """A problem that reports no hinge rows: lm-hinge takes plain LM's steps, bit for bit."""
    a = levenberg_marquardt(Rosenbrock(), [-1.2, 1.0])
    b = levenberg_marquardt(Rosenbrock(), [-1.2, 1.0], hinges=True)
    assert np.array_equal(a.x, b.x) and a.evaluations == b.evaluations
