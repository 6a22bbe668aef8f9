"""The one Gauss-Newton loop of bayescal: iteration counting, step control, stop tests and messages.

Three fits iterate with it: :func:`bayescal.identify.identify` (filtered
solves for the total deviation from nominal), the joint fit of geometry and
effects :func:`bayescal.effects.fit_map` (normal equations under the prior)
and the step identification of a redundant module
:func:`bayescal.redundant.identify_step` (least squares in a truncated SVD
basis).  Each supplies

* ``evaluate(x, state) -> (cost, state)``: its state at the parameters ``x``
  (prediction, residuals, whatever its proposals need) and the cost, a sum of
  whitened squares (chi-square units).  ``state`` is the current state (a
  warm start); an evaluation that fails (a pose with no solution) raises one
  of the exception types the caller names (``failures``);
* ``propose(x, state) -> Proposal``: the Gauss-Newton step from a state, and
  optionally the decrease of the cost its linearised model predicts; a
  proposal that cannot be made (an ill-posed linear problem) raises
  :class:`Refused`;
* a :class:`StepControl`: which steps are accepted.

The loop measures steps and the divergence bound in units of ``scale`` (the
tolerances, the prior standard deviations), so that ``xtol`` means the same
everywhere.  After taking a step it stops, converged, when

* the proposed (full) step was below ``xtol``;
* the caller's proposal predicted its decrease and it was below ``dtol``, in
  chi-square units (for a Gauss-Newton step the squared distance to the
  linearised optimum in the metric of the posterior);
* the proposed step was below :data:`FLOOR` ``* xtol`` and the cost changed by
  no more than round-off (:data:`ROUNDOFF` of it): the floor round-off sets on
  an ill-conditioned problem, about eps times the condition number.

No test looks at the decrease relative to the total cost: rows no parameter
moves (a model that misses an effect) can dominate the cost and made such a
test stop a fit far from its optimum (tests/test_iteration.py: a curved
valley under 6,000 constant rows).

A step is accepted by its :class:`StepControl`: with ``descent`` only when
the cost (or the caller's ``merit``, a regularised fit's penalised cost) does
not rise (beyond round-off), else whenever it can be evaluated;
a proposal that already passes the convergence tests is taken as it is.  A
step that is not accepted is halved, from the full step or, with
``remember``, from twice the share the last iteration took.  When no halving
is accepted the loop stops: unsuccessful, unless the step (and its predicted
decrease) is within :data:`FLOOR` times the tolerances, where the cost's
round-off hides what is left.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .progress import report

__all__ = ["Refused", "Proposal", "StepControl", "Iterated", "gauss_newton", "ROUNDOFF", "FLOOR"]

#: Relative change of a cost (a sum of many squares) that is round-off: a rise this small does not
#: refuse a step, a change this small after a small step is the floor.
ROUNDOFF = 1e-12
#: A step below this many ``xtol`` that no longer changes the cost (or that no halving can make lower
#: it) is at the round-off floor, not short of the optimum.
FLOOR = 1e3


class Refused(Exception):
    """Raised by a proposal that cannot propose a step; the loop stops unsuccessful with its message."""


@dataclass(frozen=True)
class Proposal:
    """A Gauss-Newton step from the current parameters.

    Attributes
    ----------
    step : ndarray
        The full step, in the units of the parameters ``x``.
    target : ndarray, optional
        ``x + step`` as the proposal computed it, when it solved for the new
        point itself (a solve for the total deviation): the loop takes this
        point for the full step, so that it is not ``x + (target - x)`` up to
        round-off.
    predicted : float, optional
        The decrease of the cost the linearised model predicts for the full
        step (chi-square units; for a Gauss-Newton step ``g^T H^-1 g``, the
        gradient in the metric of the model's Hessian).  Stops the loop below
        ``dtol``.
    """

    step: NDArray
    target: NDArray | None = None
    predicted: float | None = None


@dataclass(frozen=True)
class StepControl:
    """Which steps the loop accepts.

    Attributes
    ----------
    descent : bool
        Accept a step only when the cost does not rise beyond round-off
        (one that already passes the convergence tests is accepted as it
        is: what it does to the cost is round-off).  Otherwise
        every step that can be evaluated is accepted, so that a fixed-point
        iteration is not changed by the control (the cost of a nearly
        unidentifiable problem may rise at the first steps and then fall).
    halvings : int
        How many times a step that fails is halved before the loop gives up.
    remember : bool
        Start each iteration from twice the share of the step the last one
        took (at most the full step) instead of the full step: in a curved
        valley the step is cut alike every time, and starting near that cut
        saves the evaluations of halving down to it again.
    bound : float
        Divergence: a point beyond this many ``scale`` from zero.
    merit : callable, optional
        ``merit(x, state, cost)``: what a step under ``descent`` must not
        raise, when that is not the cost itself (a regularised fit, whose
        chi-square may rise where the prior pulls: the penalised cost its
        fixed point minimises).  The stop tests stay on the cost.
    """

    descent: bool = False
    halvings: int = 12
    remember: bool = False
    bound: float = np.inf
    merit: Callable[[NDArray, Any, float], float] | None = None


@dataclass
class Iterated:
    """Where the loop stopped, and why.

    Attributes
    ----------
    x : ndarray
        The last accepted parameters.
    state : object
        The caller's state at ``x``.
    cost : float
        At ``x``.
    iterations : int
        Iterations begun (the last may have taken no step).
    success : bool
    message : str
        Why it stopped, when that was not convergence ('' then; a message
        also for a success at the round-off floor with no step taken).
    reason : str
        ``"converged"``, ``"floor"`` (no step lowers the cost, at the round-off floor),
        ``"max_iter"``, ``"diverged"``, ``"unsolvable"``, ``"no_descent"`` or ``"refused"``.
    history : list of ndarray
        The accepted points, the start first.
    costs : list of float
        Their costs.
    last_step : float
        The last proposed step, in units of ``scale`` (0 before any).
    """

    x: NDArray
    state: Any
    cost: float
    iterations: int
    success: bool
    message: str
    reason: str
    history: list
    costs: list
    last_step: float = 0.0


def _size(v: NDArray, scale) -> float:
    """Largest entry of ``|v| / scale``."""
    v = np.asarray(v)
    return float(np.abs(v / scale).max()) if v.size else 0.0


def _line_search(x, cost, state, prop: Proposal, share: float, evaluate, control: StepControl, converged: bool,
                 failures):
    """The step at ``share``, halved until accepted: ``(x, cost, state, share, failure)``.

    ``x`` is None when no trial was accepted; ``failure`` is then the last
    trial's message if every trial failed to evaluate (else None).
    """
    failure, evaluated = None, False
    merit = control.merit
    level = cost if merit is None else merit(x, state, cost)
    for h in range(control.halvings + 1):
        trial = prop.target if (share == 1.0 and prop.target is not None) else x + share * prop.step
        try:
            new_cost, new_state = evaluate(trial, state)
        except failures as exc:
            failure = str(exc)
        else:
            evaluated = True
            new_level = new_cost if merit is None else merit(trial, new_state, new_cost)
            if not control.descent or converged or new_level <= level * (1.0 + ROUNDOFF):
                return trial, float(new_cost), new_state, share, None
        if h < control.halvings:
            share = share / 2.0
    return None, None, None, share, None if evaluated else failure


def _converged(prop: Proposal, size: float, xtol: float, dtol: float | None) -> bool:
    """The convergence tests a proposal passes before its step is taken (the module docstring)."""
    return size < xtol or (dtol is not None and prop.predicted is not None and prop.predicted < dtol)


def _at_floor(prop: Proposal, size: float, xtol: float, dtol: float | None) -> bool:
    """Whether a step no halving can make lower the cost is within :data:`FLOOR` times the tolerances.

    Then the cost's round-off (or the kinematics' solve tolerance) hides the
    decrease, and the fit is where it can be resolved.  A proposal that
    predicts its decrease must predict one below ``FLOOR * dtol`` as well: a
    small step that should lower the cost by many units and does not is a
    failure, not a floor.
    """
    small = prop.predicted is None or dtol is None or prop.predicted < FLOOR * dtol
    return size < FLOOR * xtol and small


def gauss_newton(
    x0: ArrayLike,
    start: tuple[float, Any],
    evaluate: Callable[[NDArray, Any], tuple[float, Any]],
    propose: Callable[[NDArray, Any], Proposal],
    *,
    control: StepControl = StepControl(),
    scale: ArrayLike = 1.0,
    max_iter: int = 50,
    xtol: float = 1e-8,
    dtol: float | None = None,
    unit: str = "",
    failures: tuple[type[BaseException], ...] = (),
) -> Iterated:
    """Iterate Gauss-Newton steps from ``x0`` until a stop test holds (see the module docstring).

    Parameters
    ----------
    x0 : array_like
        Start, in the caller's units.
    start : (float, object)
        ``evaluate``'s answer at ``x0`` (the caller evaluates the start itself,
        to report a failure there its own way).
    evaluate, propose : callable
        See the module docstring.
    control : StepControl
    scale : array_like
        Typical size of each parameter (broadcast against ``x``; ``inf`` for
        one that never moves): steps, ``xtol`` and ``control.bound`` are in
        these units.
    max_iter : int
    xtol : float
        Convergence when the proposed step is below this (units of ``scale``).
    dtol : float, optional
        Convergence when a proposal's predicted decrease is below this
        (chi-square units).
    unit : str
        What ``scale`` is, for the messages ("tolerances").
    failures : tuple of exception types
        What ``evaluate`` raises for parameters it cannot evaluate.

    Returns
    -------
    Iterated
    """
    x = np.array(x0, dtype=float)
    cost, state = start
    history, costs = [x], [float(cost)]
    share, size, unit = 1.0, 0.0, f" {unit}" if unit else ""

    def end(it, success, message, reason):
        return Iterated(x, state, cost, it, success, message, reason, history, costs, size)

    for it in range(1, max_iter + 1):
        try:
            prop = propose(x, state)
        except Refused as exc:
            return end(it, False, str(exc), "refused")
        size = _size(prop.step, scale)
        if (diverged := _diverged(prop, x, size, scale, control.bound, unit)) is not None:
            return end(it, False, diverged, "diverged")
        share = min(1.0, 2.0 * share) if control.remember else 1.0
        # a proposal that already passes the convergence tests is taken whatever it does to the cost (round-off)
        new_x, new_cost, new_state, share, failure = _line_search(x, cost, state, prop, share, evaluate, control,
                                                                  _converged(prop, size, xtol, dtol), failures)
        if new_x is None:
            return end(it, *_no_step(prop, size, cost, failure, xtol, dtol, unit))
        previous = cost
        x, cost, state = new_x, new_cost, new_state
        history.append(x)
        costs.append(cost)
        # a large recording takes seconds per iteration: say so when a caller listens (bayescal.progress)
        report(lambda: f"Gauss-Newton iteration {it} of at most {max_iter}: cost {cost:.6g}, step {size:.2e}{unit}")
        floor = size < FLOOR * xtol and abs(previous - cost) <= ROUNDOFF * max(cost, 1.0)
        if _converged(prop, size, xtol, dtol) or floor:
            return end(it, True, "", "converged")
    return end(max_iter, False, f"did not converge in {max_iter} iterations (last step {size:.2e}{unit})", "max_iter")


def _diverged(prop, x: NDArray, size: float, scale, bound: float, unit: str) -> str | None:
    """Why a proposed step diverges (not finite, or the estimate beyond ``bound``), or None."""
    if not np.isfinite(size):
        return "diverged: the step is not finite"
    full = prop.target if prop.target is not None else x + prop.step
    if _size(full, scale) > bound:
        return f"diverged: the estimate grew beyond {bound:.0e}{unit}"
    return None


def _no_step(prop, size: float, cost: float, failure, xtol: float, dtol: float, unit: str) -> tuple[bool, str, str]:
    """``(success, message, reason)`` when no trial of the line search lowered the cost."""
    if failure is not None:  # no trial could be evaluated
        return False, f"diverged: {failure}", "unsolvable"
    predicted = "" if prop.predicted is None else f", predicted decrease {prop.predicted:.2e}"
    detail = f"step {size:.2e}{unit}{predicted}, cost {cost:.6g}"
    if _at_floor(prop, size, xtol, dtol):
        return True, f"no step lowers the cost: at the round-off floor ({detail})", "floor"
    return False, f"no step lowers the cost ({detail})", "no_descent"
