"""The discrepancy's basis: a squared-exponential kernel with one length scale per input, on inducing points.

A Gaussian process ``f ~ GP(0, s^2 k)`` with

    k(x, x') = exp(-1/2 sum_j ((x_j - x'_j) / l_j)^2)

over standardised inputs is approximated on ``m`` inducing inputs ``U``
(the deterministic training conditional, DTC / subset of regressors;
Quinonero-Candela and Rasmussen, JMLR 6, 2005):

    f(x) = s phi(x)^T v,   v ~ N(0, I_m),   phi(x) = L^-1 k(U, x),   L L^T = k(U, U) + jitter I,

so that ``phi(x)^T phi(x') = k(x, U) k(U, U)^-1 k(U, x')`` (the Nystrom
kernel).  Everything the identification needs is then linear in ``v``,
which costs ``O(N m^2)`` for ``N`` poses instead of the exact GP's
``O(N^3)``.  The part of the prior the inducing points do not carry,
``s^2 (1 - |phi(x)|^2)``, is added to every prediction's variance, so that
far from the data the predictive variance returns to the prior's ``s^2``.

Why not scikit-learn's ``GaussianProcessRegressor``: it is exact (cubic in
the poses: 5,000 poses cost a 15,000-row Cholesky factor per evaluation),
single-output, and its kernels cannot express what the calibration needs, a
vector-valued function mapped into the measured rows through each pose's
own measurement Jacobian and projected off the span of the identification
Jacobian (:mod:`bayescal.discrepancy.fit`).  The kernel itself is the
two-line formula above.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray
from scipy import linalg

__all__ = ["se_kernel", "nystrom_features", "farthest_points", "JITTER"]

#: Relative jitter on k(U, U) (unit diagonal): keeps the Cholesky factor of nearby inducing points finite.
JITTER = 1e-6


def se_kernel(X: NDArray, U: NDArray, length_scales: NDArray) -> NDArray:
    """``k(X, U)``, shape (n, m), of the squared-exponential kernel with per-input length scales (unit variance)."""
    ls = np.asarray(length_scales, dtype=float)
    A = np.asarray(X, dtype=float) / ls
    B = np.asarray(U, dtype=float) / ls
    d2 = np.sum(A**2, axis=1)[:, None] + np.sum(B**2, axis=1)[None, :] - 2.0 * A @ B.T
    return np.exp(-0.5 * np.clip(d2, 0.0, None))


def nystrom_features(X: NDArray, U: NDArray, length_scales: NDArray, *, chol: NDArray | None = None) -> tuple[NDArray, NDArray]:
    """``phi(X)`` of the module docstring, shape (n, m), and the Cholesky factor ``L`` of ``k(U, U) + jitter I``.

    ``|phi(x)|^2 <= 1`` (up to the jitter): the inducing points carry at most the prior's variance.
    """
    if chol is None:
        Kuu = se_kernel(U, U, length_scales)
        chol = linalg.cholesky(Kuu + JITTER * np.eye(U.shape[0]), lower=True)
    Kxu = se_kernel(X, U, length_scales)
    phi = linalg.solve_triangular(chol, Kxu.T, lower=True).T
    return phi, chol


def farthest_points(X: NDArray, m: int, *, weights: NDArray | None = None) -> NDArray:
    """Indices of ``m`` rows of ``X`` spread over its span (greedy farthest-point order, deterministic).

    Starts at the row nearest the centroid; each next row is the one
    farthest from those chosen (in the metric ``x * weights``).
    """
    X = np.asarray(X, dtype=float)
    W = X if weights is None else X * np.asarray(weights, dtype=float)
    n = W.shape[0]
    m = min(int(m), n)
    first = int(np.argmin(np.sum((W - W.mean(axis=0)) ** 2, axis=1)))
    chosen = [first]
    d2 = np.sum((W - W[first]) ** 2, axis=1)
    for _ in range(1, m):
        nxt = int(np.argmax(d2))
        if d2[nxt] <= 0:
            break  # the rest are copies of chosen rows
        chosen.append(nxt)
        d2 = np.minimum(d2, np.sum((W - W[nxt]) ** 2, axis=1))
    return np.array(chosen, dtype=int)
