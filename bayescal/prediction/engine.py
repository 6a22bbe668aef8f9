"""Predictive distribution of measured rows: the model, its parameters' uncertainty, a discrepancy, the noise.

Linearised at the parameters ``theta`` with the analytic Jacobian, every
row's predictive distribution is Gaussian with

    mean = h(theta) + delta_mean,
    cov  = G C G^T + J_s C_s J_s^T + D + c R,

where

* ``C`` is the covariance of the machine's parameters (and of its effect
  tables' parameters and the discrepancy's weights, jointly;
  :mod:`bayescal.prediction.record`) and ``G`` their columns of the row
  Jacobian (with the effects' columns and the discrepancy's features);
* the session's own parameters ``s`` (the instrument frames of
  ``predict --frame fit``) are fitted on the recording's ``fit`` rows with
  the machine held fixed.  A change ``d`` of the machine's parameters is
  then partly absorbed by the refitted frames,
  ``d_s = -(A_s^T A_s)^+ A_s^T A_m d`` (whitened fit rows), so each row sees
  ``G = J_m - J_s K`` with ``K = (A_s^T A_s)^+ A_s^T A_m``: the gauge
  between frames and geometry is handled, and directions a frame absorbs
  cost no predictive variance.  The frames' own estimation noise adds
  ``J_s c (A_s^T A_s)^+ J_s^T``;
* ``D`` is the part of the discrepancy's prior its inducing points do not
  carry (far from the calibration's inputs it returns to the prior);
* ``R`` is the instrument noise of the row (its sigma squared) and ``c``
  the noise factor the calibration's residuals supported.

Rows of ``fit`` poses are scored with the same formula (their own noise
correlation with the frame fit is neglected: the number that matters is
that of the ``check`` rows, which no fit has seen).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from ..errors import InputError

__all__ = ["PredictiveRows", "predictive_rows"]


@dataclass(frozen=True)
class PredictiveRows:
    """Predictive mean and covariance of every row of a model.

    Attributes
    ----------
    mean : ndarray, shape (n, dof)
        mm, then rad.
    cov : ndarray, shape (n, dof, dof)
    success : ndarray of bool, shape (n,)
        False where the pose could not be solved (mean and cov are NaN there).
    message : tuple of str
        Why, where it failed.
    """

    mean: NDArray
    cov: NDArray
    success: NDArray
    message: tuple[str, ...]

    @property
    def std(self) -> NDArray:
        """One-sigma predictive std of every measured component, shape (n, dof)."""
        return np.sqrt(np.clip(np.einsum("nii->ni", self.cov), 0.0, None))


def _session_terms(Js: NDArray, Jm: NDArray, sig: NDArray, c: NDArray, fr: NDArray) -> tuple[NDArray, NDArray]:
    """``(G, extra)``: the parameters' Jacobian less what the session's refit absorbs, and the session estimate's noise.

    ``Js`` (n, dof, s) of the session's parameters, ``Jm`` (n, dof, k) of the calibrated ones, ``sig`` the rows'
    sigma, ``c`` the per-component noise factor, ``fr`` the rows the session is fitted on.

    The session's least squares is solved through the SVD of its whitened fit rows ``A_s``, columns scaled to
    unit norm (frames in mm and rad, mountings in rad: the rank decision is then one of directions, not units),
    never through ``A_s^T A_s``: a sensor's mounting and the level of up are nearly one direction to it (singular
    value 1e-7 of the largest), whose square sits at round-off of the normal matrix and turned the session's
    noise term indefinite, its size a matter of the BLAS (tests/prediction/test_session_terms.py). The noise
    term is built as ``F F^T``, positive semi-definite by construction.
    """
    dof = Js.shape[1]
    rows = int(fr.sum()) * dof
    As = (Js[fr] / sig[fr][:, :, None]).reshape(rows, Js.shape[2])
    Am = (Jm[fr] / sig[fr][:, :, None]).reshape(rows, Jm.shape[2])  # explicit rows: no machine parameter is fine
    norm = np.linalg.norm(As, axis=0)
    norm = np.where(norm > 0, norm, 1.0)
    U, s, Vt = np.linalg.svd(As / norm, full_matrices=False)
    keep = s > (s[0] if s.size else 0.0) * max(As.shape) * np.finfo(float).eps
    U, B = U[:, keep], (Vt[keep].T / s[keep]) / norm[:, None]  # pinv(A_s) = B U^T
    G = Jm - Js @ (B @ (U.T @ Am))
    # the session's estimate's own noise, pinv(A_s) diag(c) pinv(A_s)^T = (B R^T)(B R^T)^T with U^T diag(c) U = R^T R
    c_rows = np.tile(c, int(fr.sum()))
    R = np.linalg.qr(U * np.sqrt(c_rows)[:, None], mode="r")
    F = Js @ (B @ R.T)
    return G, F @ np.swapaxes(F, 1, 2)


def _with_discrepancy(discrepancy, sub, theta, sub_pred, J, Jm, residual_variance: bool):
    """``(mean, Jm, D)``: the rows' mean with the discrepancy's, its weights' columns appended to ``Jm``, and ``D``,
    the discrepancy's prior variance its inducing points do not carry (zeros without one or when not asked)."""
    dof = J.shape[1]
    if discrepancy is None:
        return sub_pred.y.copy(), Jm, np.zeros((sub.n_poses, dof, dof))
    dmean, F, D = discrepancy.rows(sub, theta, sub_pred, J=J)
    return sub_pred.y + dmean, np.concatenate([Jm, F], axis=2), D if residual_variance else np.zeros_like(D)


def _columns(J: NDArray, machine_index: NDArray, extra_columns: NDArray | None, ok: NDArray) -> NDArray:
    """The machine's parameters' columns of the solved rows, then the further parameters' (effect tables')."""
    Jm = J[:, :, machine_index]
    if extra_columns is None:
        return Jm
    return np.concatenate([Jm, np.asarray(extra_columns, dtype=float)[ok]], axis=2)


def predictive_rows(
    model,
    theta: NDArray,
    covariance: NDArray,
    *,
    machine_index: NDArray,
    noise_factor: float = 1.0,
    discrepancy=None,
    session_index: NDArray | None = None,
    fit_rows: NDArray | None = None,
    variance_factor: float = 1.0,
    residual_variance: bool = True,
    extra_columns: NDArray | None = None,
) -> PredictiveRows:
    """The predictive distribution of every row of ``model`` (module docstring).

    Parameters
    ----------
    model : MeasurementModel
        The rows to predict (its ``row_sigma`` is the instrument noise ``R``).
    theta : ndarray, shape (P,)
        Parameters of ``model.machine`` at which to predict.
    covariance : ndarray, shape (k, k)
        Of the parameters ``machine_index`` (then, with a discrepancy, of its
        weights): mm, rad and their products.
    machine_index : ndarray of int, shape (k_m,)
        Which of ``model.machine``'s parameters ``covariance`` is over.
    noise_factor : float or ndarray, shape (dof,)
        ``c``: factor on the instrument variance, one for every row or one
        per measured component (a calibration's noise scale on the tool's
        rows, 1 on a body sensor's tilt rows).
    discrepancy : Discrepancy, optional
        Added to the mean; its weights are the last rows of ``covariance``.
    session_index : ndarray of int, optional
        Parameters fitted to the session (instrument frames) on ``fit_rows``.
    fit_rows : ndarray of bool, shape (n,), optional
        Which rows the session's parameters were fitted on.
    variance_factor : float or ndarray, shape (dof,)
        ``kappa`` on the whole covariance (:func:`bayescal.prediction.loo.loo_variance_factor`), or per
        measured component (entry ``(a, b)`` of a row's covariance scaled by ``sqrt(kappa_a kappa_b)``).
    residual_variance : bool
        Add ``D``, the discrepancy's prior variance its inducing points do not
        carry (False: the parameters' part alone, the hat matrix of a fit).
    extra_columns : ndarray, shape (n, dof, m), optional
        Derivatives by ``m`` parameters beyond the machine's (``[effect.*]`` tables'): ``covariance``
        is over the ``machine_index`` parameters, these, then the discrepancy's weights.

    Returns
    -------
    PredictiveRows
    """
    theta, machine_index = np.asarray(theta, dtype=float), np.asarray(machine_index, dtype=int)
    n, dof = model.n_poses, model.dof
    pred = model.predict(theta)
    ok = np.asarray(pred.success, dtype=bool)
    msg = tuple("" if s else str(m) for s, m in zip(ok, pred.poses.message))
    mean, cov = np.full((n, dof), np.nan), np.full((n, dof, dof), np.nan)
    if not ok.any():
        return PredictiveRows(mean, cov, ok, msg)
    sub = model if ok.all() else model.subset(np.flatnonzero(ok))
    sub_pred = pred if ok.all() else sub.predict(theta)
    J = sub.jacobian(theta, sub_pred)  # (n_ok, dof, P)
    Jm = _columns(J, machine_index, extra_columns, ok)
    mu, Jm, D = _with_discrepancy(discrepancy, sub, theta, sub_pred, J, Jm, residual_variance)
    C = np.asarray(covariance, dtype=float)
    if C.shape != (Jm.shape[2],) * 2:
        raise InputError(f"predictive_rows: covariance of shape {C.shape} for {Jm.shape[2]} parameters and weights")
    sig = np.asarray(sub.row_sigma, dtype=float)
    c = np.broadcast_to(np.asarray(noise_factor, dtype=float), (dof,))
    noise = np.einsum("ni,ij->nij", sig**2 * c, np.eye(dof))
    G, extra = Jm, np.zeros_like(D)
    if session_index is not None and np.size(session_index):
        fr = np.ones(sub.n_poses, dtype=bool) if fit_rows is None else np.asarray(fit_rows, dtype=bool)[ok]
        G, extra = _session_terms(J[:, :, np.asarray(session_index, dtype=int)], Jm, sig, c, fr)
    # batched products (einsum over two contracted indices would loop in Python-free but unblocked C)
    k = np.sqrt(np.broadcast_to(np.asarray(variance_factor, dtype=float), (dof,)))
    cov_ok = np.outer(k, k) * ((G @ C) @ np.swapaxes(G, 1, 2) + extra + D + noise)
    mean[ok] = mu
    cov[ok] = 0.5 * (cov_ok + np.swapaxes(cov_ok, 1, 2))
    return PredictiveRows(mean, cov, ok, msg)

