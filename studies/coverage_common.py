"""What the coverage studies share: fit one simulated machine by named methods and judge each fit against its truth.

Used by ``studies/coverage.py`` (true machines drawn from the tolerance prior)
and ``studies/coverage_offprior.py`` (true machines drawn off it).  The
importing script puts the checkout on ``sys.path`` first, as for
``studies/real_common.py``.

A fit on the identifiable set is judged against the *projected* truth
``theta[idx] + K theta[fixed]``, ``K = pinv(J_idx) J_fixed`` (whitened
Jacobian at nominal): the reduced-model parameters that reproduce the true
machine at the recording's poses.  A fit on all parameters (``map_all*``)
is judged against the truth itself.
"""

from __future__ import annotations

import warnings

import numpy as np

from bayescal.bayes import kalman_filter, map_estimate
from bayescal.bayes.accuracy import tool_point_jacobian, tool_point_std
from bayescal.identify import identify
from bayescal.measurement import MeasurementModel

#: Half-width of the two-sided 90 % interval in standard deviations.
Z90 = 1.6448536269514722

#: The identification methods by name: each takes the model and the fresh evaluation poses.
FITTERS = {
    "ls": lambda model, q_eval: identify(model, method="ls"),
    "map": lambda model, q_eval: map_estimate(model),
    "map_eb": lambda model, q_eval: map_estimate(model, prior_scale="empirical"),
    "map_all": lambda model, q_eval: map_estimate(model, free="all"),
    "map_all_eb": lambda model, q_eval: map_estimate(model, free="all", prior_scale="empirical"),
    "kalman": lambda model, q_eval: kalman_filter(model, eval_q=q_eval[:2]),
}


def fit_methods(model: MeasurementModel, methods: tuple[str, ...], q_eval: np.ndarray) -> dict:
    """The fit of ``model`` by each method of ``methods`` (names of :data:`FITTERS`), in that order.

    Warnings are silenced: a study counts the unsuccessful fits itself.
    ``q_eval`` (n, n_actuators; mm or rad) are the fresh poses; the Kalman
    filter reports its tool-point std at the first two.
    """
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return {m: FITTERS[m](model, q_eval) for m in methods}


def projected_truth(model: MeasurementModel, theta: np.ndarray, free: np.ndarray) -> np.ndarray:
    """Reduced-model parameters equivalent to the full truth: ``theta[idx] + K theta[fixed]`` (units of theta)."""
    idx, fix = np.flatnonzero(free), np.flatnonzero(~free)
    if fix.size == 0:
        return theta[idx]
    J = (model.jacobian(None, model.predict(None)) / model.sigma[None, :, None]).reshape(-1, theta.size)
    K = np.linalg.lstsq(J[:, idx], J[:, fix], rcond=None)[0]  # J_idx theta_eq = J_idx theta_idx + J_fix theta_fix
    return theta[idx] + K @ theta[fix]


def parameter_target(model: MeasurementModel, theta: np.ndarray, free: np.ndarray, *, all_params: bool) -> np.ndarray:
    """What a fit of ``theta[free]`` estimates: the truth itself (``all_params``, a fit on all
    parameters whose prior covers the null space) or the projected truth."""
    return theta[np.flatnonzero(free)] if all_params else projected_truth(model, theta, free)


def z_scores(machine, res, target: np.ndarray, q_eval: np.ndarray, p_true: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Standardised errors of a fit with a covariance: parameters and tool points at fresh poses.

    Parameters
    ----------
    machine : Machine
    res
        A fit with ``theta``, ``free`` and ``covariance`` (of ``theta[free]``).
    target : ndarray, shape (k,)
        :func:`parameter_target` of the fit.
    q_eval : ndarray, shape (n, n_actuators)
        Fresh poses (mm or rad).
    p_true : ndarray, shape (n, 3)
        The true machine's tool points there, mm.

    Returns
    -------
    z_param : ndarray, shape (k,)
        ``(estimate - target) / sd``.
    z_tool : ndarray, shape (n, 3)
        ``(p_true - p(q, theta_hat)) / sqrt(diag(G C G^T))`` per axis.
    """
    idx = np.flatnonzero(res.free)
    z_param = (res.theta[idx] - target) / np.sqrt(np.diag(res.covariance))
    G = tool_point_jacobian(machine, q_eval, res.theta, idx)
    z_tool = (p_true - machine.forward(q_eval, res.theta).position) / tool_point_std(G, res.covariance)
    return z_param, z_tool
