"""The ``fit`` rows' test of a prediction: does each row group scatter as its predictive distribution says?

``bayescal predict`` fits the session's own parameters (instrument frames, body-sensor mountings) on the
recording's ``fit`` rows; those rows are then evidence about the session that no calibration saw.  Each row
group (the tool's rows, each body sensor's tilt rows) is tested on them: the sum over the fit rows of the squared
Mahalanobis distance of the group's residual under its own residual covariance
(:mod:`bayescal.prediction.engine`: the refit's share subtracted, the prior's counted)

    T = sum_i r_i^T S_i^+ r_i,

and where ``T`` exceeds what chance allows at :data:`ROW_TEST_ALPHA`, the group's predictive covariance is
multiplied by ``T / E[T]`` (Birge's ratio) on every row.

The null distribution.  With ``r`` Gaussian of the fit rows' joint residual covariance ``Sigma``
(:class:`~bayescal.prediction.engine.FitRowsJoint`) and ``E = blockdiag(S_i^+)``, ``T`` is distributed as
``sum_j lambda_j chi2_1`` with ``lambda`` the eigenvalues of ``K = E^1/2 Sigma E^1/2``; ``E[T] = tr K`` is the
components' count (``S_i`` are ``Sigma``'s diagonal blocks), no parameter taken.  It is not chi-square on any
count: "components less parameters" is the expectation of the *plain noise's* Mahalanobis sum after a
least-squares fit, which neither the machine's uncertainty in the covariance nor a MAP fit (a prior deciding
what the rows do not see) keeps; and the rows' residuals are correlated (one refit, one machine, whose
uncertainty moves every row at once), so a few eigenvalues stand far above one.  On the telescope's tip sensor
(docs/real-setup.md) the largest are 14.5, 7.8, 4.9 and 4.1 of 180: chi-square on 180 rejects a true model in
7 % of sessions at a nominal 1 %, a mean-and-variance match in 2 %.  So the largest eigenvalues are computed
(:data:`TOP` of them), the rest matched in mean and variance by one scaled chi-square, and the tail is the
saddlepoint approximation of that sum (:func:`bayescal.distributions.weighted_chi2_sf`): 1.01 % there, and
checked by Monte Carlo in tests/prediction/test_fit_rows.py.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray

from .engine import PredictiveRows

__all__ = ["ROW_TEST_ALPHA", "RowGroupTest", "row_group_tests"]

#: Level of the fit rows' test below which a row group's covariance is widened (:func:`row_group_tests`).
ROW_TEST_ALPHA = 0.01

#: How many of the largest eigenvalues of the statistic's null distribution are computed (the rest matched).
TOP = 20

#: Up to this many components a group's whitened covariance is formed and all its eigenvalues taken; above, the
#: largest :data:`TOP` by Lanczos iteration (scipy's eigsh) on products with it.
DENSE_MAX = 1500


@dataclass(frozen=True)
class RowGroupTest:
    """One group of rows (the tool's, or one body sensor's) tested on the session's ``fit`` rows.

    Attributes
    ----------
    group : str
        ``"tool"`` or the sensor's body.
    chi2 : float
        Sum over the fit rows of the squared Mahalanobis distance of the group's residual under its residual
        covariance (pseudo-inverse where a row decided a direction alone).
    expected : int
        Its expectation when the predictive distribution is right: the group's components over the fit rows with
        residual variance (the ranks of their covariances).
    p_value : float
        Upper tail of ``chi2`` under its null distribution (module docstring).
    widen : float
        Factor on the group's predictive covariance: ``chi2 / expected`` where ``p_value`` is below
        :data:`ROW_TEST_ALPHA`, else 1.
    """

    group: str
    chi2: float
    expected: int
    p_value: float
    widen: float

    def note(self) -> str:
        what, why = (("the tool's rows", "the calibration's noise and uncertainty do not cover this session")
                     if self.group == "tool" else
                     (f"the sensor on {self.group!r}: its tilt rows", "the machine file's sigma_tilt and the model of "
                      "what moves the sensor's body, neither tested by the calibration, do not account for them"))
        return (f"{what} scatter {np.sqrt(self.widen):.3g} times their predicted std on the fit rows (chi-square "
                f"{self.chi2:.4g} for {self.expected} expected, p = {self.p_value:.2g}): their regions are "
                f"widened by that, on every row ({why})")


def row_group_tests(model, pr: PredictiveRows, fit_rows: np.ndarray) -> tuple[RowGroupTest, ...]:
    """Test the tool's rows and each body sensor's rows of the ``fit`` rows against their predictive distribution.

    The tool's rows are predicted through the calibration's noise scale and leave-one-out factor, which another
    day's instrument or machine need not share; a sensor on a moving body through the file's ``sigma_tilt`` and
    the effects that move its body, which no calibration tested. Groups apart: a noisy accelerometer beside a
    precise inclinometer is widened alone. Never narrowed (module docstring).

    Parameters
    ----------
    model : MeasurementModel
        The tool's ``tool_dof`` rows, then two tilt rows per sensor in ``model.sensors.bodies``' order.
    pr : PredictiveRows
        Of every row of ``model``, with its fit rows' ``joint`` covariance.
    fit_rows : ndarray of bool
        The rows the session was fitted on (those of ``pr``).

    Returns
    -------
    tuple of RowGroupTest
        The tool's first, then one per sensor (a group without enough fit rows: ``widen`` 1 and NaN statistics).
    """
    td = model.tool_dof
    use = np.asarray(fit_rows, dtype=bool) & np.asarray(pr.success, dtype=bool)
    bodies = tuple(model.sensors.bodies) if td < model.dof else ()
    groups = [("tool", slice(0, td))] + [(b, slice(td + 2 * k, td + 2 * k + 2)) for k, b in enumerate(bodies)]
    r = (np.asarray(model.y_measured, dtype=float) - pr.mean)[use]
    j = pr.joint
    return tuple(_group_test(name, r[:, sl], pr.cov[use][:, sl, sl],
                             None if j is None else (j.base[use][:, sl, sl], j.U[use][:, sl], j.W))
                 for name, sl in groups)


def _group_test(name: str, r: NDArray, S: NDArray, joint) -> RowGroupTest:
    """:class:`RowGroupTest` of residuals ``r`` (n, k) under covariances ``S`` (n, k, k), ``joint`` the rows' joint
    covariance ``(base, U, W)`` (:class:`bayescal.prediction.engine.FitRowsJoint`, these rows and components)."""
    from ..distributions import weighted_chi2_sf
    from .score import pinv_blocks

    nan = RowGroupTest(name, float("nan"), 0, float("nan"), 1.0)
    if joint is None or not all(np.all(np.isfinite(a)) for a in (r, S, *joint)):
        return nan
    Eh, rank = pinv_blocks(S, power=0.5)
    expected = int(rank.sum())
    if expected < 3:
        return replace(nan, expected=expected)
    x = np.einsum("nij,nj->ni", Eh, r)
    total = float(np.sum(x * x))
    weights, dofs = _null_weights(Eh, *joint)
    if not weights.size:
        return replace(nan, chi2=total, expected=expected)
    p = weighted_chi2_sf(total, weights, dofs)
    return RowGroupTest(name, total, expected, p, max(1.0, total / expected) if p < ROW_TEST_ALPHA else 1.0)


def _null_weights(Eh: NDArray, base: NDArray, U: NDArray, W: NDArray) -> tuple[NDArray, NDArray]:
    """The null distribution of ``T`` as ``sum_j w_j chi2_{h_j}``: ``(w, h)`` (module docstring).

    ``Eh`` (n, k, k) are the rows' ``S_i^{+1/2}``; ``Sigma = blockdiag(base) + U W U^T`` (``base`` (n, k, k),
    ``U`` (n, k, m), ``W`` (m, m)). The :data:`TOP` largest eigenvalues of ``K = E^1/2 Sigma E^1/2`` with one
    degree of freedom each, then one term for the others with their mean ``tr K - sum`` and variance
    ``2 (tr K^2 - sum of squares)``: ``w = var / (2 mean)``, ``h = 2 mean^2 / var``. ``tr K^2`` is summed
    over rows without forming ``K``: ``sum_i tr(B_i^2) + 2 tr(W V^T B V) + tr((W V^T V)^2)`` with
    ``B = E^1/2 base E^1/2`` and ``V = E^1/2 U``.
    """
    B = Eh @ base @ Eh
    V = Eh @ U
    M = np.tensordot(V, V, axes=([0, 1], [0, 1]))
    WM = W @ M
    trace = float(np.einsum("nii->", B) + np.trace(WM))
    trace2 = float(np.einsum("nij,nji->", B, B) + 2.0 * np.sum(W * np.tensordot(V, B @ V, axes=([0, 1], [0, 1])))
                   + np.einsum("ab,ba->", WM, WM))
    top = np.clip(_largest(B, V, W), 0.0, None)
    mean, var = trace - top.sum(), 2.0 * (trace2 - np.sum(top**2))
    if not (mean > 1e-9 * trace and var > 1e-12 * trace2):  # every eigenvalue computed
        return top, np.ones(top.size)
    return np.r_[top, var / (2.0 * mean)], np.r_[np.ones(top.size), 2.0 * mean**2 / var]


def _largest(B: NDArray, V: NDArray, W: NDArray) -> NDArray:
    """The :data:`TOP` largest eigenvalues of ``K = blockdiag(B) + V W V^T`` (every one up to :data:`DENSE_MAX`)."""
    n, k, m = V.shape
    N = n * k
    Vf = V.reshape(N, m)
    if N <= DENSE_MAX:
        K = Vf @ W @ Vf.T
        for i in range(n):  # the rows' blocks on the diagonal
            K[i * k:(i + 1) * k, i * k:(i + 1) * k] += B[i]
        return np.linalg.eigvalsh(0.5 * (K + K.T))[::-1][:TOP]
    from scipy.sparse.linalg import LinearOperator, eigsh

    def product(x):
        x = np.asarray(x, dtype=float).reshape(N)
        return (np.einsum("nij,nj->ni", B, x.reshape(n, k)).reshape(N) + Vf @ (W @ (Vf.T @ x)))

    op = LinearOperator((N, N), matvec=product, dtype=float)
    return np.sort(eigsh(op, k=min(TOP, N - 1), which="LA", return_eigenvectors=False))[::-1]
