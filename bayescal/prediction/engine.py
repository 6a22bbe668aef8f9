"""Predictive distribution of measured rows: the model, its parameters' uncertainty, a discrepancy, the noise.

Linearised at the parameters ``theta`` with the analytic Jacobian, every
row's predictive distribution is Gaussian with

    mean = h(theta) + delta_mean,
    cov  = G C G^T + J_s C_s J_s^T + D + c R          (a row no fit has seen),

where

* ``C`` is the covariance of the machine's parameters (and of its effect
  tables' parameters and the discrepancy's weights, jointly;
  :mod:`bayescal.prediction.record`) and ``G`` their columns of the row
  Jacobian (with the effects' columns and the discrepancy's features);
* the session's own parameters ``s`` (the instrument frames of
  ``predict --frame fit``, least squares; the body sensors' mountings, MAP
  under their prior ``N(s_0, diag(tau^2))``) are fitted on the recording's
  ``fit`` rows with the machine held fixed.  With ``A_s``, ``A_m`` the
  whitened fit rows' columns and ``P = diag(1/tau)`` (zero rows for the
  frames) the estimator is the least squares of the augmented system
  ``[A_s; P]``, ``s_hat = K a + M P s_0`` with ``[K, M] = pinv([A_s; P])``.
  A change ``d`` of the machine's parameters is partly absorbed by the
  refitted parameters, ``d_s = -K A_m d``, so each row sees
  ``G = J_m - J_s K A_m``: the gauge between frames and geometry is
  handled, and directions a frame absorbs cost no predictive variance.  The
  estimate's own error, the fit rows' noise through ``K`` and the prior's
  through ``M`` (the session's true mountings a draw from their prior),
  adds ``C_s = K diag(c) K^T + M M^T``: where the prior decides a direction
  (a sensor's mounting and the level of up, nearly one direction to it)
  its variance is the prior's, not the pseudo-inverse's;
* ``D`` is the part of the discrepancy's prior its inducing points do not
  carry (far from the calibration's inputs it returns to the prior);
* ``R`` is the instrument noise of the row (its sigma squared) and ``c``
  the noise factor the calibration's residuals supported.

A ``fit`` row was itself used to fit ``s``: its residual's noise is
``e_i - J_s,i K e`` (``e`` the fit rows' noise, whitened by ``sigma``
alone as the fit weighs them, covariance ``diag(c)``), so its covariance
is

    G C G^T + D + c R - h_i c S_i - S_i c h_i^T + J_s,i C_s J_s,i^T,

``S_i = diag(sigma_i)`` and ``h_i = J_s,i K_{:, i}`` the row's block of the
hat matrix (in whitened units, uniform ``c`` and no prior: ``c (I - H_ii)``,
the textbook residual covariance): the estimate's noise is subtracted, not
added, and a row that alone decides a direction (leverage one) has no
residual variance in it.  The discrepancy's leftover ``D`` (independent row
to row) is part of a fit row's error as the noise is: on the fit rows
``c R + D`` takes the place of ``c R`` in these formulas (a block
``P_i P_i^T`` in place of ``c S_i^2``), so the refit absorbs its share of
it and ``C_s`` carries the rest to every row.  The fit rows' residuals are correlated through
the fit and through ``d``; :class:`FitRowsJoint` carries that joint
covariance for the fit rows' test (:func:`bayescal.prediction.recording.row_group_tests`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from ..errors import InputError

__all__ = ["FitRowsJoint", "PredictiveRows", "predictive_rows"]


@dataclass(frozen=True)
class FitRowsJoint:
    """The joint covariance of the ``fit`` rows' residuals, block diagonal plus low rank.

    ``Cov(r_i, r_j) = [i == j] base_i + U_i W U_j^T`` over the fit rows ``i, j``: ``base`` the noise (and the
    discrepancy's residual variance) of each row, ``U W U^T`` what correlates the rows (the session's refit and
    the machine's parameters, common to every row). Its diagonal blocks are the fit rows' ``cov``.

    Attributes
    ----------
    base : ndarray, shape (n, dof, dof)
        mm^2, rad^2 and their products; NaN on the rows no fit used.
    U : ndarray, shape (n, dof, m)
        NaN on the rows no fit used.
    W : ndarray, shape (m, m)
        Symmetric, maybe indefinite.
    """

    base: NDArray
    U: NDArray
    W: NDArray


@dataclass(frozen=True)
class PredictiveRows:
    """Predictive mean and covariance of every row of a model.

    Attributes
    ----------
    mean : ndarray, shape (n, dof)
        mm, then rad.
    cov : ndarray, shape (n, dof, dof)
        A ``check`` row's predictive covariance; a ``fit`` row's is that of its residual after the session's
        refit (module docstring). mm^2, rad^2 and their products.
    success : ndarray of bool, shape (n,)
        False where the pose could not be solved (mean and cov are NaN there).
    message : tuple of str
        Why, where it failed.
    joint : FitRowsJoint, optional
        The fit rows' residuals' joint covariance (None where not computed).
    """

    mean: NDArray
    cov: NDArray
    success: NDArray
    message: tuple[str, ...]
    joint: FitRowsJoint | None = None

    @property
    def std(self) -> NDArray:
        """One-sigma predictive std of every measured component, shape (n, dof)."""
        return np.sqrt(np.clip(np.einsum("nii->ni", self.cov), 0.0, None))


@dataclass(frozen=True)
class SessionTerms:
    """What the session's refit on its fit rows does to the rows' covariance (:func:`_session_terms`).

    Attributes
    ----------
    G : ndarray, shape (n, dof, k)
        The calibrated parameters' columns less what the refit absorbs.
    extra : ndarray, shape (n, dof, dof)
        ``J_s C_s J_s^T``, the session estimate's error seen by every row (added to a held-out row's noise).
    fit_noise : ndarray, shape (n_fit, dof, dof)
        A fit row's residual covariance from the noise and the prior (replacing ``extra`` and the noise).
    L, Q : ndarray, shape (n_fit, dof, r)
        Its factors: the fit rows' residuals are ``(L Q'^T + P E (I - Q' Q'^T)) eta`` with ``eta`` white and
        ``P_i P_i^T = c S_i^2 + D_i`` (``P = sqrt(c) S`` without a discrepancy), so ``Cov(r_i, r_j) = [i == j]
        P_i P_i^T + L_i L_j^T - Q_i Q_j^T`` (``Q = P Q'``).
    """

    G: NDArray
    extra: NDArray
    fit_noise: NDArray
    L: NDArray
    Q: NDArray


def _own_noise(sig: NDArray, c: NDArray, D: NDArray | None) -> tuple[NDArray | None, NDArray]:
    """A fit row's own error, its noise and the discrepancy's leftover: ``(M^1/2, P)`` with ``P P^T = c S^2 + D``.

    ``M^1/2`` (n, dof, dof) is the symmetric root of ``M = diag(c) + S^-1 D S^-1`` (``c`` one factor per
    component; the error in the fit's whitened units), ``P = S M^1/2``; ``M^1/2`` is None and ``P`` the diagonal
    ``sqrt(c) sigma`` (n, dof) without ``D``.
    """
    if D is None or not np.any(D):
        return None, sig * np.sqrt(c)
    n, dof = sig.shape
    M = D / (sig[:, :, None] * sig[:, None, :]) + np.diag(c)[None]
    w, V = np.linalg.eigh(M)
    root = (V * np.sqrt(np.clip(w, 0.0, None))[:, None, :]) @ np.swapaxes(V, 1, 2)
    return root, sig[:, :, None] * root


def _session_terms(Js: NDArray, Jm: NDArray, sig: NDArray, c: NDArray, fr: NDArray,
                   prior_std: NDArray | None = None, D: NDArray | None = None) -> SessionTerms:
    """The session's refit terms (module docstring), from the SVD of its augmented whitened fit rows.

    ``Js`` (n, dof, s) of the session's parameters, ``Jm`` (n, dof, k) of the calibrated ones, ``sig`` the rows'
    sigma (the fit's weights), ``c`` the per-component noise factor, ``fr`` the rows the session is fitted on,
    ``prior_std`` (s,) each session parameter's prior std in its unit (inf: none, least squares).

    The estimator is the least squares of ``[A_s; P]`` (``P = diag(1/prior_std)``, its rows for the parameters
    with a prior): it is solved through the SVD of that augmented matrix, columns scaled to unit norm (frames
    in mm and rad, mountings in rad: the rank decision is then one of directions, not units), never through its
    normal matrix: a sensor's mounting and the level of up are nearly one direction to the fit rows (singular
    value 1e-7 of the largest), whose square sits at round-off of ``A_s^T A_s`` and turned the session's noise
    term indefinite, its size a matter of the BLAS (tests/prediction/test_session_terms.py). Both noise terms
    are built from factors, positive semi-definite by construction.

    ``D`` (n, dof, dof), the discrepancy's leftover variance of each row (independent row to row), is part of a
    fit row's error as the noise is: the refit absorbs its share of it too (:func:`_own_noise`), and the
    estimate's error that every row sees carries the fit rows' share.
    """
    n_fit, dof, p = int(fr.sum()), Js.shape[1], Js.shape[2]
    As = (Js[fr] / sig[fr][:, :, None]).reshape(n_fit * dof, p)
    Am = (Jm[fr] / sig[fr][:, :, None]).reshape(n_fit * dof, Jm.shape[2])  # explicit rows: no machine parameter is fine
    std = np.full(p, np.inf) if prior_std is None else np.asarray(prior_std, dtype=float)
    has = np.isfinite(std) & (std > 0)
    Aa = np.vstack([As, np.eye(p)[has] / std[has, None]])  # the prior as rows: MAP is their least squares
    norm = np.linalg.norm(Aa, axis=0)
    norm = np.where(norm > 0, norm, 1.0)
    U, s, Vt = np.linalg.svd(Aa / norm, full_matrices=False)
    keep = s > (s[0] if s.size else 0.0) * max(Aa.shape) * np.finfo(float).eps
    U, B = U[:, keep], (Vt[keep].T / s[keep]) / norm[:, None]  # pinv([A_s; P]) = B U^T
    G = Jm - Js @ (B @ (U[: n_fit * dof].T @ Am))
    # the estimate's error B U^T T eta = (B R^T) Q'^T eta, with T U = Q' R and T the root of the whitened rows'
    # error covariance (diag(c_aug)^(1/2) without D): the fit rows' noise (factor c, and D) and the prior's (a
    # unit-variance draw per prior row)
    root, P = _own_noise(sig[fr], c, None if D is None else D[fr])
    if root is None:
        c_aug = np.r_[np.tile(c, n_fit), np.ones(int(has.sum()))]
        Qp, R = np.linalg.qr(U * np.sqrt(c_aug)[:, None])
    else:  # each fit row's block of U turned by its error's root, the prior's rows as they are
        Uf = (root @ U[: n_fit * dof].reshape(n_fit, dof, -1)).reshape(n_fit * dof, -1)
        Qp, R = np.linalg.qr(np.vstack([Uf, U[n_fit * dof:]]))
    F = Js @ (B @ R.T)
    # a fit row's residual noise is its own, P_i E_i eta (P_i = sqrt(c) S_i without D), less the estimate's seen
    # by it, F_i Q'^T eta: the own splits into its part along Q' (with the estimate's: L Q'^T eta) and the part
    # orthogonal to Q', of covariance P_i (I - Q'_i Q'_i^T) P_i^T, built from Q'_i's singular values (1 - sv^2
    # clipped at zero) so that a row of leverage one has no residual variance there, never a negative one
    Qi = Qp[: n_fit * dof].reshape(n_fit, dof, Qp.shape[1])
    PQ = P[:, :, None] * Qi if root is None else P @ Qi
    L = PQ - F[fr]
    V, left = _outside(Qi)
    O = P[:, :, None] * V if root is None else P @ V
    fit_noise = (O * left[:, None, :]) @ np.swapaxes(O, 1, 2) + L @ np.swapaxes(L, 1, 2)
    return SessionTerms(G, F @ np.swapaxes(F, 1, 2), fit_noise, L, PQ)


def _outside(Qi: NDArray) -> tuple[NDArray, NDArray]:
    """``(V, w)`` with ``I - Q_i Q_i^T = V_i diag(w_i) V_i^T``, ``Q_i`` (dof, r) each row's block of ``Q'``.

    ``w = (1 - sv)(1 + sv)`` of ``Q_i``'s singular values, clipped at zero (1 beyond them): never negative, where
    forming ``I - Q_i Q_i^T`` would leave round-off of either sign in a direction the row alone decides.
    """
    n, dof, r = Qi.shape
    if r == 0:
        return np.broadcast_to(np.eye(dof), (n, dof, dof)), np.ones((n, dof))
    V, sv, _ = np.linalg.svd(Qi, full_matrices=True)
    w = np.ones((n, dof))
    w[:, : sv.shape[1]] = np.clip((1.0 - sv) * (1.0 + sv), 0.0, None)
    return V, w


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


def _covariances(G, C, D, sig, c, fr, terms: SessionTerms | None) -> tuple[NDArray, FitRowsJoint]:
    """Every row's covariance (module docstring) before the variance factor, and the fit rows' joint covariance.

    ``G`` (n, dof, k), ``C`` (k, k), ``D`` (n, dof, dof), ``sig`` (n, dof), ``c`` (dof,), ``fr`` (n,) bool the
    fit rows, ``terms`` the session's refit (None: no session parameter, a fit row's residual is its prediction
    error).
    """
    n, dof = sig.shape
    noise = np.einsum("ni,ij->nij", sig**2 * c, np.eye(dof))
    gcg = (G @ C) @ np.swapaxes(G, 1, 2)  # batched products: blocked BLAS, not einsum's loops
    core = gcg + D
    base = np.full((n, dof, dof), np.nan)
    base[fr] = noise[fr] + D[fr]
    if terms is None:
        U = np.where(fr[:, None, None], G, np.nan)
        return core + noise, FitRowsJoint(base, U, C)
    cov = core + terms.extra + noise
    cov[fr] = gcg[fr] + terms.fit_noise  # D is in a fit row's own error, through the refit (_session_terms)
    r, k = terms.L.shape[2], G.shape[2]
    U = np.full((n, dof, 2 * r + k), np.nan)
    U[fr] = np.concatenate([terms.L, terms.Q, G[fr]], axis=2)
    W = np.zeros((2 * r + k,) * 2)
    W[:r, :r], W[r: 2 * r, r: 2 * r], W[2 * r:, 2 * r:] = np.eye(r), -np.eye(r), C
    return cov, FitRowsJoint(base, U, W)


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
    session_prior_std: NDArray | None = None,
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
        Parameters fitted to the session (instrument frames, sensor mountings) on ``fit_rows``.
    fit_rows : ndarray of bool, shape (n,), optional
        The rows the session was fitted on (default: every row): ``cov`` is their residual's, ``joint`` theirs.
    session_prior_std : ndarray, shape (s,), optional
        Each ``session_index`` parameter's prior std in a MAP fit (mm or rad); ``inf`` (default): least squares.
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
    fr = np.ones(sub.n_poses, dtype=bool) if fit_rows is None else np.asarray(fit_rows, dtype=bool)[ok]
    terms = None
    if session_index is not None and np.size(session_index):
        terms = _session_terms(J[:, :, np.asarray(session_index, dtype=int)], Jm, sig, c, fr, session_prior_std, D)
    G = Jm if terms is None else terms.G
    mean[ok] = mu
    k = np.sqrt(np.broadcast_to(np.asarray(variance_factor, dtype=float), (dof,)))
    return _scaled(mean, ok, msg, *_covariances(G, C, D, sig, c, fr, terms), k)


def _scaled(mean, ok, msg, cov_ok, joint_ok: FitRowsJoint, k) -> PredictiveRows:
    """The rows' answer: the solved rows' covariances times ``k_a k_b`` (entry ``(a, b)``), NaN on the others."""
    n, dof = mean.shape
    cov, base, U = (np.full((n, dof, w), np.nan) for w in (dof, dof, joint_ok.U.shape[2]))
    cov_ok = np.outer(k, k) * cov_ok
    cov[ok] = 0.5 * (cov_ok + np.swapaxes(cov_ok, 1, 2))
    base[ok], U[ok] = np.outer(k, k) * joint_ok.base, k[:, None] * joint_ok.U
    return PredictiveRows(mean, cov, ok, msg, FitRowsJoint(base, U, joint_ok.W))
