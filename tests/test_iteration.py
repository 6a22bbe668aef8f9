"""The one Gauss-Newton loop (bayescal.iteration): stop tests, step control, messages."""

from __future__ import annotations

import inspect

import numpy as np
import pytest

from bayescal.effects.model import MAP_DTOL, MAP_STEP_CONTROL, fit_map
from bayescal.errors import KinematicsError
from bayescal.iteration import Proposal, Refused, StepControl, gauss_newton

#: Rows no parameter moves (a model that misses an effect): each a residual of one sigma.
N_CONSTANT = 6_000


class _Valley:
    """Rosenbrock-like residuals ``(a (y - x^2), 1 - x)`` and constant rows; least squares at (1, 1) (closed form).

    ``a = 100`` bends the valley more than Rosenbrock's own ``a = 10``: Gauss-Newton's steps are cut by the line
    search all the way along it, and their decreases are small against the constant rows' cost.
    """

    def __init__(self, a: float = 100.0, n_constant: int = N_CONSTANT):
        self.a, self.n_constant, self.evaluations = a, n_constant, 0

    def residuals(self, x):
        return np.concatenate([[self.a * (x[1] - x[0] ** 2), 1.0 - x[0]], np.ones(self.n_constant)])

    def evaluate(self, x, state):
        self.evaluations += 1
        r = self.residuals(x)
        return float(r @ r), r

    def propose(self, x, r):
        # Gauss-Newton on the residuals r(x + d) ~ r + J d; the constant rows' Jacobian is zero
        J = np.zeros((r.size, 2))
        J[0], J[1] = [-2 * self.a * x[0], self.a], [-1.0, 0.0]
        g = -J.T @ r
        d = np.linalg.solve(J.T @ J, g)
        return Proposal(step=d, predicted=float(d @ g))

    def run(self, x0, **options):
        x0 = np.asarray(x0, dtype=float)
        return gauss_newton(x0, self.evaluate(x0, None), self.evaluate, self.propose, **options)


def _as_fit_map(**override):
    """The loop's options as fit_map sets them (its step control, decrease tolerance and defaults)."""
    defaults = inspect.signature(fit_map).parameters
    options = dict(control=MAP_STEP_CONTROL, dtol=MAP_DTOL, xtol=defaults["xtol"].default,
                   max_iter=defaults["max_iter"].default)
    options.update(override)
    return options


def test_a_curved_valley_under_constant_rows_converges_to_its_closed_form_optimum():
    valley = _Valley()
    out = valley.run([-0.5, 2.0], **_as_fit_map())
    assert out.success and out.reason == "converged", out.message
    np.testing.assert_allclose(out.x, [1.0, 1.0], atol=1e-6)
    assert out.cost == pytest.approx(N_CONSTANT, abs=1e-9)  # the constant rows are all that is left
    # the problem is one the old test (decrease below 1e-7 of the total cost) stopped far from the optimum on:
    # a step of the iteration decreased the cost by less than that while still 0.1 or more away from (1, 1)
    costs, points = np.array(out.costs), np.array(out.history)
    early = (costs[:-1] - costs[1:] < 1e-7 * costs[:-1]) & (np.abs(points[1:] - 1.0).max(axis=1) > 0.1)
    assert early.any()


def test_the_constant_rows_do_not_change_the_iteration():
    # the same valley without them: the same points (the stop tests do not see cost no parameter can reduce)
    with_rows = _Valley().run([-0.5, 2.0], **_as_fit_map())
    without = _Valley(n_constant=0).run([-0.5, 2.0], **_as_fit_map())
    assert with_rows.iterations == without.iterations
    np.testing.assert_allclose(np.array(with_rows.history), np.array(without.history), rtol=0, atol=1e-12)


def test_a_linear_problem_converges_in_one_step_to_least_squares():
    rng = np.random.default_rng(3)
    A, y = rng.normal(size=(30, 4)), rng.normal(size=30)

    def evaluate(x, state):
        r = y - A @ x
        return float(r @ r), r

    out = gauss_newton(np.zeros(4), evaluate(np.zeros(4), None), evaluate,
                       lambda x, r: Proposal(step=np.linalg.lstsq(A, r, rcond=None)[0]), xtol=1e-10)
    np.testing.assert_allclose(out.x, np.linalg.lstsq(A, y, rcond=None)[0], rtol=1e-12)
    assert out.success and out.iterations == 2 and len(out.history) == 3  # the second step is round-off


def _line(limit=np.inf, start=0.0):
    """A one-parameter problem with its minimum at x = 10 whose evaluation fails beyond ``limit``."""

    def evaluate(x, state):
        if x[0] > limit:
            raise KinematicsError(f"pose 1 cannot be solved at x = {x[0]:g}")
        r = np.array([10.0 - x[0]])
        return float(r @ r), r

    x0 = np.array([start])
    return x0, evaluate(x0, None), evaluate


def test_any_step_that_can_be_evaluated_is_taken_whole_and_only_a_failed_one_is_halved():
    x0, start, evaluate = _line(limit=6.0)
    # an overshooting proposal (to 2 x the minimum): taken whole, the cost rising, as identify's iteration does
    out = gauss_newton(x0, start, evaluate, lambda x, r: Proposal(step=2 * r), max_iter=1,
                       failures=(KinematicsError,))
    assert out.x[0] == 5.0  # 20 fails (beyond the limit), 10 fails, 5 is taken
    x0, start, evaluate = _line(start=4.0)
    out = gauss_newton(x0, start, evaluate, lambda x, r: Proposal(step=3 * r), max_iter=1)
    assert out.x[0] == 22.0 and out.costs == [36.0, 144.0]  # the cost rose fourfold: taken all the same


def test_a_step_no_halving_can_evaluate_says_so():
    x0, start, evaluate = _line(limit=-1.0, start=-2.0)
    out = gauss_newton(x0, start, evaluate, lambda x, r: Proposal(step=r), control=StepControl(halvings=3),
                       failures=(KinematicsError,))
    assert not out.success and out.reason == "unsolvable"
    assert out.message == "diverged: pose 1 cannot be solved at x = -0.5"  # the last trial: 12 / 2^3 from -2
    assert out.x[0] == -2.0


def test_descent_halves_a_step_that_raises_the_cost_and_remembers_the_share():
    x0, start, evaluate = _line()
    calls = []

    def counted(x, state):
        calls.append(x[0])
        return evaluate(x, state)

    # a proposal 8 times too long: 80 raises the cost, 40 too, 20 does not (cost equal): share 1/4 taken
    out = gauss_newton(x0, start, counted, lambda x, r: Proposal(step=8 * r),
                       control=StepControl(descent=True, halvings=7, remember=True), max_iter=2)
    assert calls[:3] == [80.0, 40.0, 20.0]
    # the next iteration starts from twice the share taken (1/2 of 8 (10 - 20) = -40), not from the full step
    assert calls[3] == 20.0 - 40.0
    assert out.iterations == 2


def test_descent_compares_the_merit_when_one_is_given_and_stops_on_the_cost():
    """A ridge-like merit, cost + (x / 2)^2 (minimum at x = 8), refuses a step the cost alone accepts."""
    x0, start, evaluate = _line()
    calls = []

    def merit(x, state, cost):
        calls.append((x[0], cost))
        return cost + (x[0] / 2.0) ** 2

    out = gauss_newton(x0, start, evaluate, lambda x, r: Proposal(step=np.array([18.0 - x[0]])),
                       control=StepControl(descent=True, halvings=3, merit=merit), max_iter=1)
    # the full step to 18: cost 64 < 100 but merit 64 + 81 = 145 > 100, refused; the half step to 9: merit 21.25 taken
    assert out.x[0] == 9.0 and out.cost == 1.0
    assert calls == [(0.0, 100.0), (18.0, 64.0), (9.0, 1.0)]
    # without the merit the full step is taken (the cost alone falls)
    plain = gauss_newton(x0, start, evaluate, lambda x, r: Proposal(step=np.array([18.0 - x[0]])),
                         control=StepControl(descent=True, halvings=3), max_iter=1)
    assert plain.x[0] == 18.0 and plain.costs == [100.0, 64.0]


def test_descent_with_no_step_lowering_the_cost_fails_unless_at_the_floor():
    x0, start, evaluate = _line()
    away = gauss_newton(x0, start, evaluate, lambda x, r: Proposal(step=-np.ones(1), predicted=1.0),
                        control=StepControl(descent=True, halvings=3), xtol=1e-4, dtol=1e-6)
    assert not away.success and away.reason == "no_descent" and away.x[0] == 0.0
    assert away.message.startswith("no step lowers the cost (step 1.00e+00")
    # the same at a step and a predicted decrease within FLOOR (1e3) of the tolerances: round-off, converged
    floor = gauss_newton(x0, start, evaluate, lambda x, r: Proposal(step=-0.05 * np.ones(1), predicted=1e-4),
                         control=StepControl(descent=True, halvings=3), xtol=1e-4, dtol=1e-6)
    assert floor.success and floor.reason == "floor"
    # a small step that should lower the cost by many units and does not is no floor
    steep = gauss_newton(x0, start, evaluate, lambda x, r: Proposal(step=-0.05 * np.ones(1), predicted=10.0),
                         control=StepControl(descent=True, halvings=3), xtol=1e-4, dtol=1e-6)
    assert not steep.success and steep.reason == "no_descent"


def test_a_refused_proposal_a_divergence_and_the_iteration_limit_stop_unsuccessful():
    x0, start, evaluate = _line()

    def refuse(x, r):
        raise Refused("least squares is ill-posed")

    out = gauss_newton(x0, start, evaluate, refuse)
    assert (out.success, out.reason, out.message) == (False, "refused", "least squares is ill-posed")
    out = gauss_newton(x0, start, evaluate, lambda x, r: Proposal(step=np.full(1, 2e6)),
                       control=StepControl(bound=1e6), scale=1.0, unit="tolerances")
    assert out.reason == "diverged" and out.message == "diverged: the estimate grew beyond 1e+06 tolerances"
    out = gauss_newton(x0, start, evaluate, lambda x, r: Proposal(step=np.full(1, np.nan)))
    assert out.reason == "diverged" and "not finite" in out.message
    # half steps: 10 -> 5 -> 2.5 -> ... never below xtol in 3 iterations
    out = gauss_newton(x0, start, evaluate, lambda x, r: Proposal(step=0.5 * r), scale=2.0, max_iter=3,
                       unit="tolerances")
    assert out.reason == "max_iter" and out.iterations == 3
    assert out.message == "did not converge in 3 iterations (last step 6.25e-01 tolerances)"  # (10 - 7.5) / 2 / 2
