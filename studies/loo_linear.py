"""Leave-one-out prediction errors of linear estimators, exactly, for a linearised measurement model.

For a model linearised at the nominal geometry, ``y = J theta + e`` (``y``
the measured values minus the nominal prediction, mm), every calibration
that is linear in the data, re-fitted without row ``i`` and predicting row
``i``, makes the error

    err_i = y_i - J_i K_(-i) y_(-i) = (M y)_i,

where ``K_(-i)`` is the estimator's gain on the other rows.  With the truth
drawn as ``theta ~ N(0, diag(tol^2))`` and ``e ~ N(0, diag(sigma^2))``, the
expected squared error of each row is ``diag(M (J T J' + S) M')``: no Monte
Carlo is needed for a linear estimator, and the perfect calibration (the
true ``theta``) has ``err_i = e_i``, expected ``sigma_i^2``, the floor no
calibration goes below, because the left-out row's noise is independent of
the rows the calibration saw.  The Bayes-optimal calibration (the posterior
mean under the true prior and noise) has the smallest expected error of all
calibrations: its expectation is the floor of what a method can reach from
these data.

Used by ``studies/delta_klipper.py`` to separate what Klipper's
``DELTA_CALIBRATE`` loses to noise from what it loses to its fit.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from numpy.typing import ArrayLike, NDArray

__all__ = [
    "wls_gain", "map_gain", "evidence_map_gain", "loo_operator", "loo_errors", "expected_sq_error", "log_evidence",
    "profiled_log_evidence", "evidence_ratio",
]

#: A gain: (Jacobian of the kept rows, their indices) -> matrix K, theta_hat = K y_kept.
Gain = Callable[[NDArray, NDArray], NDArray]


def wls_gain(weights: Callable[[NDArray], NDArray]) -> Gain:
    """Weighted least squares (minimum norm where rank-deficient) with row weights ``weights(rows)`` (1/mm^2)."""

    def gain(J: NDArray, rows: NDArray) -> NDArray:
        w = np.asarray(weights(rows), dtype=float)
        return np.linalg.pinv(J * np.sqrt(w)[:, None]) * np.sqrt(w)[None, :]

    return gain


def map_gain(sigma: ArrayLike, tol: ArrayLike) -> Gain:
    """Posterior mean under ``theta ~ N(0, diag(tol^2))`` with row noise ``sigma`` (mm; indexed by row).

    ``tol`` entries of 0 fix those parameters at nominal.
    """
    sigma = np.asarray(sigma, dtype=float)
    tol = np.asarray(tol, dtype=float)

    def gain(J: NDArray, rows: NDArray) -> NDArray:
        # K = T J' (J T J' + S)^-1 (the data-space form: no inverse of T, so fixed parameters are allowed)
        JT = J * tol**2
        C = JT @ J.T + np.diag(sigma[rows] ** 2)
        return np.linalg.solve(C, JT).T

    return gain


def loo_operator(J: ArrayLike, gain: Gain) -> NDArray:
    """The matrix ``M`` with ``err = M y``: each row's leave-one-out prediction error, shape (n, n).

    Parameters
    ----------
    J : array_like, shape (n, p)
        Jacobian of the rows' predictions (mm per parameter unit).
    gain : callable
        ``gain(J_kept, kept_rows)`` -> ``K`` of shape (p, n - 1).
    """
    J = np.asarray(J, dtype=float)
    n = J.shape[0]
    M = np.eye(n)
    for i in range(n):
        keep = np.delete(np.arange(n), i)
        M[i, keep] = -J[i] @ gain(J[keep], keep)
    return M


def loo_errors(J: ArrayLike, y: ArrayLike, gain: Gain) -> NDArray:
    """Leave-one-out errors ``y_i - J_i K_(-i) y_(-i)`` of one data vector (mm), shape (n,)."""
    return loo_operator(J, gain) @ np.asarray(y, dtype=float)


def expected_sq_error(M: ArrayLike, J: ArrayLike, tol: ArrayLike, sigma: ArrayLike) -> NDArray:
    """``E[err_i^2]`` under ``theta ~ N(0, diag(tol^2))``, ``e ~ N(0, diag(sigma^2))`` (mm^2), shape (n,)."""
    M, J = np.asarray(M, dtype=float), np.asarray(J, dtype=float)
    cov = (J * np.asarray(tol, dtype=float) ** 2) @ J.T + np.diag(np.asarray(sigma, dtype=float) ** 2)
    return np.einsum("ij,jk,ik->i", M, cov, M)


def log_evidence(J: ArrayLike, y: ArrayLike, tol: ArrayLike, sigma: ArrayLike) -> float:
    """Log marginal likelihood of ``y`` under ``y ~ N(0, J T J' + S)`` (nats)."""
    J, y = np.asarray(J, dtype=float), np.asarray(y, dtype=float)
    C = (J * np.asarray(tol, dtype=float) ** 2) @ J.T + np.diag(np.asarray(sigma, dtype=float) ** 2)
    L = np.linalg.cholesky(C)
    z = np.linalg.solve(L, y)
    return float(-0.5 * z @ z - np.sum(np.log(np.diag(L))) - 0.5 * y.size * np.log(2 * np.pi))


def profiled_log_evidence(J: ArrayLike, y: ArrayLike, tol: ArrayLike, sigma: ArrayLike, ratio: float) -> float:
    """Log evidence with the prior ``ratio * tol`` and the noise ``s * sigma``, ``s`` at its maximum (nats).

    ``y ~ N(0, s^2 (ratio^2 J T J' + S))``: the stated sigmas are relative
    weights, ``ratio`` is the geometry's spread against the noise in units
    of the tolerances over the stated sigmas; the common noise scale ``s``
    is profiled out (``s^2 = y' C0^-1 y / n``).
    """
    J, y = np.asarray(J, dtype=float), np.asarray(y, dtype=float)
    C = ratio**2 * (J * np.asarray(tol, dtype=float) ** 2) @ J.T + np.diag(np.asarray(sigma, dtype=float) ** 2)
    L = np.linalg.cholesky(C)
    z = np.linalg.solve(L, y)
    n = y.size
    s2 = float(z @ z) / n
    return float(-0.5 * n * (1.0 + np.log(2 * np.pi * s2)) - np.sum(np.log(np.diag(L))))


def evidence_ratio(J: ArrayLike, y: ArrayLike, tol: ArrayLike, sigma: ArrayLike,
                   bounds: tuple[float, float] = (0.05, 20.0)) -> float:
    """The ``ratio`` maximising :func:`profiled_log_evidence` within ``bounds`` (dimensionless)."""
    from scipy.optimize import minimize_scalar

    lo, hi = np.log(bounds[0]), np.log(bounds[1])
    r = minimize_scalar(lambda v: -profiled_log_evidence(J, y, tol, sigma, np.exp(v)), bounds=(lo, hi), method="bounded",
                        options={"xatol": 1e-3})
    return float(np.exp(r.x))


def evidence_map_gain(y: ArrayLike, sigma: ArrayLike, tol: ArrayLike, bounds: tuple[float, float] = (0.05, 20.0)) -> Gain:
    """Posterior mean with the prior ``ratio * tol``, ``ratio`` from the evidence of the kept rows of ``y``.

    The linear counterpart of ``identify --method map`` with the noise not
    stated (empirical Bayes over the ratio, the noise scale profiled).
    Not a linear estimator (the ratio depends on the data): use with
    :func:`loo_errors` on one data vector, not with :func:`expected_sq_error`.
    """
    y, sigma, tol = (np.asarray(a, dtype=float) for a in (y, sigma, tol))

    def gain(J: NDArray, rows: NDArray) -> NDArray:
        ratio = evidence_ratio(J, y[rows], tol, sigma[rows], bounds)
        return map_gain(sigma, ratio * tol)(J, rows)

    return gain
