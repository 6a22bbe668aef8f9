"""Predictive distribution of measured rows: the model, its parameters' uncertainty, a discrepancy, the noise.

Linearised at the parameters ``theta`` with the analytic Jacobian, every
row's predictive distribution is Gaussian with

    mean = h(theta) + delta_mean,
    cov  = G C G^T + J_s C_s J_s^T + D + c R,

where

* ``C`` is the covariance of the machine's parameters (and of the
  discrepancy's weights, jointly; :mod:`bayescal.prediction.record`) and ``G``
  their columns of the row Jacobian (with the discrepancy's features);
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
    noise_factor : float
        ``c``: factor on the instrument variance.
    discrepancy : Discrepancy, optional
        Added to the mean; its weights are the last rows of ``covariance``.
    session_index : ndarray of int, optional
        Parameters fitted to the session (instrument frames) on ``fit_rows``.
    fit_rows : ndarray of bool, shape (n,), optional
        Which rows the session's parameters were fitted on.
    variance_factor : float
        ``kappa`` on the whole covariance (:func:`bayescal.prediction.loo.loo_variance_factor`).
    residual_variance : bool
        Add ``D``, the discrepancy's prior variance its inducing points do not
        carry (False: the parameters' part alone, the hat matrix of a fit).

    Returns
    -------
    PredictiveRows
    """
    theta = np.asarray(theta, dtype=float)
    machine_index = np.asarray(machine_index, dtype=int)
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
    Jm = J[:, :, machine_index]
    mu = sub_pred.y.copy()
    D = np.zeros((sub.n_poses, dof, dof))
    if discrepancy is not None:
        dmean, F, D = discrepancy.rows(sub, theta, sub_pred, J=J)
        mu = mu + dmean
        if not residual_variance:
            D = np.zeros_like(D)
        Jm = np.concatenate([Jm, F], axis=2)
    C = np.asarray(covariance, dtype=float)
    if C.shape != (Jm.shape[2],) * 2:
        raise InputError(f"predictive_rows: covariance of shape {C.shape} for {Jm.shape[2]} parameters and weights")
    sig = np.asarray(sub.row_sigma, dtype=float)
    noise = noise_factor * np.einsum("ni,ij->nij", sig**2, np.eye(dof))
    G = Jm
    extra = np.zeros_like(D)
    if session_index is not None and np.size(session_index):
        fr = np.ones(sub.n_poses, dtype=bool) if fit_rows is None else np.asarray(fit_rows, dtype=bool)[ok]
        G, extra = _session_frame_terms(J, Jm, sig, np.asarray(session_index, dtype=int), fr, noise_factor)
    # batched products (einsum over two contracted indices would loop in Python-free but unblocked C)
    cov_ok = variance_factor * ((G @ C) @ np.swapaxes(G, 1, 2) + extra + D + noise)
    mean[ok] = mu
    cov[ok] = 0.5 * (cov_ok + np.swapaxes(cov_ok, 1, 2))
    return PredictiveRows(mean, cov, ok, msg)


def _session_frame_terms(J: NDArray, Jm: NDArray, sig: NDArray, s_idx: NDArray, fr: NDArray, noise_factor: float):
    """The rows' sensitivity once the session's frames are refitted on the ``fr`` rows, and the frames' own term.

    Returns ``G = Jm - Js K`` (the frames absorb what they can of a parameter change) and the covariance the
    frames' fit adds, ``noise_factor * Js M^-1 Js^T`` (mm^2, rad^2).
    """
    dof = J.shape[1]
    Js = J[:, :, s_idx]
    rows = int(fr.sum()) * dof
    As = (Js[fr] / sig[fr][:, :, None]).reshape(rows, s_idx.size)
    Am = (Jm[fr] / sig[fr][:, :, None]).reshape(rows, Jm.shape[2])  # explicit rows: no machine parameter is fine
    Minv = np.linalg.pinv(As.T @ As)
    K = Minv @ (As.T @ Am)
    return Jm - Js @ K, noise_factor * (Js @ Minv) @ np.swapaxes(Js, 1, 2)
