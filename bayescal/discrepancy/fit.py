"""Fitting a discrepancy with the geometry: hyperparameters by marginal likelihood, the rest by the joint posterior.

At a calibrated geometry ``theta`` (the geometry-only MAP) the whitened
residual ``r`` (``N`` rows) and the whitened identification matrix ``A``
(``N x p``, the free parameters, instrument frames included) are given.
Linearised there, Kennedy and O'Hagan's model is

    r = A dtheta + F v + e,   dtheta ~ N(m0, C0),   v ~ N(0, I),   e ~ N(0, c I),

with ``F`` the whitened feature matrix of the discrepancy
(:meth:`Discrepancy.rows`), ``C0`` the geometry's prior (its tolerances,
scaled as the MAP scaled them) and ``m0`` the prior mean less ``theta``.

**The gauge between geometry and discrepancy** is decided by the two
priors, stated: a mismatch that a geometric error within its tolerance
explains costs the geometry little and the discrepancy its prior; a
smooth error no geometric parameter describes (or one far beyond the
tolerances) goes to the discrepancy.  A discrepancy free in the span of
``A`` (projected off it) was tried first: the marginal likelihood then
favoured huge, slowly varying functions whose geometric part cancelled
against the geometry, and held-out poses improved by 6 % only where the
joint prior gives 35 % (tests/discrepancy).  On recordings without a
mismatch the discrepancy's scale collapses and the geometry is the MAP's
(tested).

**Hyperparameters** (length scale per input, prior scale per group of
outputs, noise factor ``c``) maximise the marginal likelihood of ``r``,
with ``X = [A C0^(1/2), F]``, ``M = X^T X``, ``b = X^T r'`` (Woodbury):

    -2 log p = (|r'|^2 - b^T (c I + M)^-1 b) / c + N log c + log det(I + M / c)

by L-BFGS-B in log space.  Beyond :data:`MAX_HYPER_POSES` poses they are
estimated on a seeded subset (the posterior then on all poses), which keeps
the cost near linear in the poses.  Inducing points are picked by farthest
points in the standardised inputs, then again in the length-scaled inputs
after a first fit (irrelevant inputs stop spreading them).

**Is it there?**  The gain in log marginal likelihood over the geometry
alone (noise factor profiled) is a log Bayes factor; below
:data:`MIN_EVIDENCE_GAIN` the discrepancy is not supported and a caller
should drop it (a clean recording).
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy import linalg, optimize
from threadpoolctl import threadpool_limits

from ..errors import InputError
from .kernel import JITTER, farthest_points, nystrom_features, se_kernel
from .model import OUTPUT_NAMES, Discrepancy, discrepancy_inputs, output_rows_map

__all__ = ["DiscrepancyFit", "fit_discrepancy", "fold_fits", "default_inputs", "joint_design", "MIN_EVIDENCE_GAIN",
           "MAX_HYPER_POSES"]

#: Log Bayes factor (in nats) a discrepancy must gain over the geometry alone to be kept.  The gain is a
#: maximised likelihood ratio over a handful of hyperparameters, so on recordings without a mismatch it
#: has a tail: on 25 clean recordings of the 6R arm it was 2.6 on average and 7.7 at most (6 nats kept 2 of
#: 25); 10 nats leaves that tail out while every mismatch of studies/discrepancy_coverage.py gains hundreds.
MIN_EVIDENCE_GAIN = 10.0
#: Poses at most on which the hyperparameters are estimated (a seeded subset beyond).
MAX_HYPER_POSES = 1200
#: Inducing points at most (and at most half the poses).
MAX_INDUCING = 48
#: Auxiliary channels that are bookkeeping, not physics: never default inputs (``pose_id``, ``source_key``, ...).
_NOT_PHYSICS = re.compile(r"(^|_)(id|key|index|idx|line|sample|row|count|number)$|^sigma_", re.I)


@dataclass(frozen=True)
class DiscrepancyFit:
    """A discrepancy fitted jointly with the geometry's linearisation at a calibration.

    Attributes
    ----------
    discrepancy : Discrepancy
        With the posterior mean of its weights.
    noise_factor : float
        ``c``: the noise variance relative to the model's sigma, with the discrepancy accounted for.
    covariance : ndarray, shape (p + K, p + K)
        Joint posterior covariance of the free parameters (their units) and the weights.
    dtheta : ndarray, shape (p,)
        The joint posterior's correction of the free parameters (the geometry-only MAP plus this is
        the geometry fitted with the discrepancy).
    supported : bool
        ``log_evidence_gain >= MIN_EVIDENCE_GAIN``.
    chi2 : float
        Whitened residual sum of squares after the joint posterior mean (at the model's sigma).
    effective_params : float
        Effective number of parameters of the joint fit (trace of its hat matrix), geometry included.
    free : ndarray of int
    """

    discrepancy: Discrepancy
    noise_factor: float
    covariance: NDArray
    dtheta: NDArray
    supported: bool
    chi2: float
    effective_params: float
    free: NDArray

    def joint_covariance(self, geometry_cov: NDArray | None = None) -> NDArray:
        """Covariance of the free parameters and the weights (what predictions at new poses propagate)."""
        return self.covariance


def default_inputs(model) -> tuple[str, ...]:
    """The discrepancy's default inputs: every actuator and every auxiliary channel that varies.

    Channels named like bookkeeping (``pose_id``, ...) are left out, and so are the readings of sensors on bodies
    other than the base (measurements of the outcome, docs/formats.md section 8: predicting a pose must not need them).
    """
    from ..sensors.columns import is_body_measurement

    n_act = np.asarray(model.pose_q).shape[1]
    names = [f"q{i + 1}" for i in range(n_act)]
    for k, v in (model.aux or {}).items():
        v = np.asarray(v, dtype=float)
        if (_NOT_PHYSICS.search(k) or is_body_measurement(k) or not np.all(np.isfinite(v))
                or np.ptp(v) <= 0):
            continue
        names.append(k)
    return tuple(names)


def _outputs(dof: int) -> tuple[str, ...]:
    return OUTPUT_NAMES if dof >= 5 else OUTPUT_NAMES[:3]


class _Problem:
    """The whitened pieces of one fit (module docstring), for a set of poses.

    ``X_A = A C0^(1/2)``: the geometry's columns scaled by its prior std, so
    that the unknowns ``u = (C0^(-1/2) (dtheta - m0), v)`` all have prior
    ``N(0, I)``; ``r'`` is the residual less the prior mean's prediction.
    """

    def __init__(self, model, theta, prediction, free, inputs, outputs, center, scale, prior_sd, prior_shift):
        sig = np.asarray(model.row_sigma, dtype=float)
        n, dof = sig.shape
        self.n, self.dof = n, dof
        r = (model.residual(prediction) / sig).reshape(-1)
        J = model.jacobian(theta, prediction)[:, :, free] / sig[:, :, None]
        A = J.reshape(n * dof, -1)
        self.XA = A * prior_sd
        self.r0 = r  # the geometry-only calibration's whitened residual
        self.r = r - A @ prior_shift
        self.N = n * dof
        G = output_rows_map(model, theta, prediction, outputs) / sig[:, :, None]  # (n, dof, n_out)
        self.g = np.einsum("nao,nap->nop", G, G)  # (n, n_out, n_out)
        # output pairs no row couples (a position row never sees a rotation output): their blocks are zero
        self.coupled = np.any(self.g != 0.0, axis=0)
        XAr = self.XA.reshape(n, dof, -1)
        self.H = np.einsum("nap,nao->nop", XAr, G)  # (n, n_out, p)
        self.Gr = np.einsum("nao,na->no", G, self.r.reshape(n, dof))  # (n, n_out)
        self.AtA = self.XA.T @ self.XA
        self.Atr = self.XA.T @ self.r
        self.Z = (discrepancy_inputs(model, inputs) - center) / scale
        self.n_out = len(outputs)

    def pieces(self, phi: NDArray, s: NDArray) -> tuple[NDArray, NDArray]:
        """``M = X^T X`` and ``b = X^T r'`` of ``X = [X_A, F]`` for features ``phi`` (n, m) and output scales ``s``."""
        m, o = phi.shape[1], self.n_out
        p = self.AtA.shape[0]
        K = o * m
        M = np.zeros((p + K, p + K))
        M[:p, :p] = self.AtA
        # F^T F in (o, q) blocks of m x m: s_o s_q sum_n g_noq phi_n phi_n^T (one BLAS product per block)
        for a in range(o):
            for c in range(a, o):
                if not self.coupled[a, c]:
                    continue
                blk = (phi * self.g[:, a, c][:, None]).T @ phi * (s[a] * s[c])
                M[p + a * m:p + (a + 1) * m, p + c * m:p + (c + 1) * m] = blk
                M[p + c * m:p + (c + 1) * m, p + a * m:p + (a + 1) * m] = blk.T
            # X_A^T F, block o: sum_n H_n,o phi_n^T s_o
            AF = self.H[:, a, :].T @ phi * s[a]
            M[:p, p + a * m:p + (a + 1) * m] = AF
            M[p + a * m:p + (a + 1) * m, :p] = AF.T
        b = np.concatenate([self.Atr, (np.einsum("no,nj->oj", self.Gr, phi) * s[:, None]).reshape(-1)])
        return M, b

    def rows(self, poses: NDArray) -> "_Problem":
        """The problem of the poses ``poses`` alone (the training poses of a fold), from this one's pose-wise pieces.

        Every piece but the sums over rows is the pose's own (its residual, Jacobian rows, output map and
        inputs), so these are the numbers a problem built on ``model.subset(poses)`` has; the sums are formed
        as that one forms them.
        """
        poses = np.asarray(poses, dtype=int)
        out = object.__new__(_Problem)
        n, dof = poses.size, self.dof
        rows = (poses[:, None] * dof + np.arange(dof)[None, :]).reshape(-1)
        out.n, out.dof, out.N, out.n_out = n, dof, n * dof, self.n_out
        # in this one's memory order: BLAS sums A^T r in another order for another layout (round-off apart)
        out.XA = np.asarray(self.XA[rows], order="F" if self.XA.flags.f_contiguous else "C")
        out.r0, out.r = self.r0[rows], self.r[rows]
        out.g, out.H, out.Gr, out.Z = self.g[poses], self.H[poses], self.Gr[poses], self.Z[poses]
        out.coupled = np.any(out.g != 0.0, axis=0)
        out.AtA = out.XA.T @ out.XA
        out.Atr = out.XA.T @ out.r
        return out

    def null(self) -> tuple[NDArray, NDArray]:
        """``M``, ``b`` of the geometry alone (no discrepancy)."""
        return self.AtA, self.Atr


def _neg_log_ml(M, b, rr, N_eff, c) -> float:
    K = M.shape[0]
    try:
        L = linalg.cholesky(np.eye(K) + M / c, lower=True)
    except linalg.LinAlgError:
        return np.inf
    # (c I + M)^-1 b = (I + M/c)^-1 b / c
    y = linalg.cho_solve((L, True), b) / c
    quad = (rr - b @ y) / c
    return 0.5 * (quad + N_eff * math.log(c) + 2.0 * np.sum(np.log(np.diag(L))))


def _groups(outputs) -> NDArray:
    """Index of each output's scale group: positions share one prior scale, rotations another."""
    return np.array([0 if o in ("x", "y", "z") else 1 for o in outputs])


def _unpack(x, d, n_groups, groups, fit_noise):
    ls = np.exp(x[:d])
    sg = np.exp(x[d: d + n_groups])
    c = math.exp(x[d + n_groups]) if fit_noise else 1.0
    return ls, sg[groups], c


def _optimise(prob: _Problem, U, x0, bounds, d, n_groups, groups, fit_noise, maxiter):
    rr = float(prob.r @ prob.r)

    def f(x):
        try:
            value, grad = _neg_log_ml_and_gradient(prob, U, x, d, n_groups, groups, fit_noise, rr)
        except linalg.LinAlgError:
            return 1e300, np.zeros_like(x)
        # a factor that lost its positive definiteness to round-off gives no usable value: a wall, not a NaN
        return (value, grad) if np.isfinite(value) and np.all(np.isfinite(grad)) else (1e300, np.zeros_like(x))

    # the analytic gradient (not L-BFGS-B's finite differences): a tenth of the likelihood evaluations, and
    # a search path that does not move with round-off elsewhere (the marginal likelihood is flat near its top)
    res = optimize.minimize(f, x0, jac=True, method="L-BFGS-B", bounds=bounds, options={"maxiter": maxiter})
    return res.x, float(res.fun)


def _neg_log_ml_and_gradient(prob: _Problem, U, x, d, n_groups, groups, fit_noise, rr) -> tuple[float, NDArray]:
    """:func:`_neg_log_ml` at the hyperparameters ``x`` (log length scales, log group scales, log noise factor) and its gradient.

    With ``K = c I + M``, ``y = K^-1 b``: ``d nll = <G_M, dM> + g_b . db (+ the noise factor's own term)`` with
    ``G_M = (y y^T / c + K^-1) / 2`` and ``g_b = -y / c``; ``M`` and ``b`` are quadratic and linear in the
    features ``phi = k(X, U) L^-T`` and scale with the output scales; ``phi`` depends on the length scales
    through ``k(X, U)`` and the Cholesky factor ``L`` of ``k(U, U) + jitter I`` (its derivative
    ``dL = L Phi(L^-1 dK_UU L^-T)``, ``Phi`` the lower triangle with half the diagonal).  Checked against
    central differences in tests/discrepancy.
    """
    ls, s, c = _unpack(x, d, n_groups, groups, fit_noise)
    Kuu = se_kernel(U, U, ls)
    L = linalg.cholesky(Kuu + JITTER * np.eye(U.shape[0]), lower=True)
    Kxu = se_kernel(prob.Z, U, ls)
    phi = linalg.solve_triangular(L, Kxu.T, lower=True).T
    M, b = prob.pieces(phi, s)
    n_all = M.shape[0]
    Lk = linalg.cholesky(np.eye(n_all) + M / c, lower=True)
    y = linalg.cho_solve((Lk, True), b) / c
    bty = float(b @ y)
    nll = 0.5 * ((rr - bty) / c + prob.N * math.log(c) + 2.0 * np.sum(np.log(np.diag(Lk))))
    Kinv = linalg.cho_solve((Lk, True), np.eye(n_all)) / c
    GM = 0.5 * (np.outer(y, y) / c + Kinv)
    gb = -y / c
    grad = np.zeros_like(x)
    if fit_noise:  # d nll / d log c
        grad[-1] = 0.5 * c * (-(rr - bty) / c**2 + float(y @ y) / c + prob.N / c + np.trace(Kinv) - n_all / c)
    # output scales: M = D M~ D, b = D b~ with D = diag(1, s_o on block o)
    p, m, o = prob.AtA.shape[0], phi.shape[1], prob.n_out
    per_row = 2.0 * np.sum(M * GM, axis=1) + gb * b
    per_out = per_row[p:].reshape(o, m).sum(axis=1)
    np.add.at(grad, d + groups, per_out)
    # features: d nll / d phi
    psi = np.zeros_like(phi)
    for a in range(o):
        blk_a = slice(p + a * m, p + (a + 1) * m)
        psi += (2.0 * s[a]) * (prob.H[:, a, :] @ GM[:p, blk_a])
        psi += s[a] * np.outer(prob.Gr[:, a], gb[blk_a])
        for cc in range(o):
            if prob.coupled[a, cc]:
                G_ac = GM[blk_a, p + cc * m:p + (cc + 1) * m]
                psi += (s[a] * s[cc]) * ((phi * prob.g[:, a, cc][:, None]) @ (G_ac + G_ac.T))
    # through phi = k(X, U) L^-T to the kernels: d nll = <P, dk(X, U)> + <Q, dk(U, U)>
    P = linalg.solve_triangular(L, psi.T, lower=True, trans="T").T
    B = psi.T @ phi
    Bt = np.tril(B, -1) + 0.5 * np.diag(np.diag(B))
    C = 0.5 * (Bt + Bt.T)
    Q = -linalg.solve_triangular(L, linalg.solve_triangular(L, C, lower=True, trans="T").T, lower=True, trans="T")
    # d k / d log l_j = k (x_j - u_j)^2 / l_j^2
    grad[:d] = (_weighted_sq_dist(P * Kxu, prob.Z, U) + _weighted_sq_dist(Q * Kuu, U, U)) / ls**2
    return float(nll), grad


def _weighted_sq_dist(W: NDArray, X: NDArray, Y: NDArray) -> NDArray:
    """``sum_{n,i} W_ni (X_nj - Y_ij)^2`` for every input ``j``."""
    return W.sum(axis=1) @ X**2 - 2.0 * np.sum(X * (W @ Y), axis=0) + W.sum(axis=0) @ Y**2


def fit_discrepancy(model, theta, free, prior_sd, *, prior_mean=None, inputs=None, n_inducing: int | None = None,
                    fit_noise: bool = True, seed: int = 0, maxiter: int = 40,
                    hyper: Discrepancy | None = None, noise_factor: float = 1.0) -> DiscrepancyFit:
    """Fit a discrepancy jointly with the geometry's linearisation at a calibration (module docstring).

    Parameters
    ----------
    model : MeasurementModel
        The calibrated recording (its sigma whitens the rows).
    theta : ndarray, shape (P,)
        The calibrated parameters (the geometry-only MAP).
    free : ndarray of bool, shape (P,)
        Which parameters the calibration fitted.
    prior_sd : ndarray, shape (n_free,)
        The geometry's prior std of the free parameters (their units): the
        tolerances over ``sqrt(lam)`` of the MAP, which decide, with the
        discrepancy's prior, how a mismatch is split between them.
    prior_mean : ndarray, shape (n_free,), optional
        The geometry's prior mean (default zeros: nominal).
    inputs : sequence of str, optional
        ``q<i>`` and auxiliary channel names; default :func:`default_inputs`.
    n_inducing : int, optional
        Inducing points (default: min(48, poses // 3)).
    fit_noise : bool
        Estimate the noise factor ``c`` with the rest (else ``c = 1``: the model's sigma as stated).
    seed : int
        For the subset of poses the hyperparameters are estimated on (large recordings).
    maxiter : int
        L-BFGS-B iterations of the first stage.
    hyper : Discrepancy, optional
        Keep this discrepancy's inputs, standardisation, inducing points,
        length and output scales (no search) and refit only the joint
        posterior, with the noise factor ``noise_factor``.
    noise_factor : float
        With ``hyper``: ``c`` (default 1: the model's sigma as it is).

    Returns
    -------
    DiscrepancyFit
    """
    theta = np.asarray(theta, dtype=float)
    free_idx = np.flatnonzero(free) if np.asarray(free).dtype == bool else np.asarray(free, dtype=int)
    prior_sd = np.asarray(prior_sd, dtype=float).reshape(free_idx.size)
    if np.any(~np.isfinite(prior_sd)) or np.any(prior_sd <= 0):
        raise InputError("fit_discrepancy: the geometry's prior std must be finite and positive (a method with a prior)")
    shift = (np.zeros(free_idx.size) if prior_mean is None else np.asarray(prior_mean, dtype=float).reshape(free_idx.size)) \
        - theta[free_idx]
    if model.y_measured is None:
        raise InputError("fit_discrepancy: the model has no measured values")
    # the matrices are small (a few hundred): threaded BLAS only costs here, badly on a loaded machine (8x seen)
    with threadpool_limits(1):
        if hyper is not None:
            pred = model.predict(theta)
            if not pred.success.all():
                raise InputError("fit_discrepancy: a pose cannot be solved at the calibrated geometry")
            prob = _Problem(model, theta, pred, free_idx, hyper.inputs, hyper.outputs, hyper.center, hyper.scale,
                            prior_sd, shift)
            return _posterior(model, prob, hyper, free_idx, prior_sd, shift, float(noise_factor), hyper.log_evidence_gain)
        return _fit(model, theta, free_idx, prior_sd, shift, inputs, n_inducing, fit_noise, seed, maxiter)


def fold_fits(model, theta, free, prior_sd, hyper: Discrepancy, noise_factor: float, folds) -> list[DiscrepancyFit]:
    """The joint posterior on each fold's training poses at the hyperparameters ``hyper``: a cross-validation's fits.

    The same fits as ``fit_discrepancy(model.subset(train), theta, free, prior_sd, hyper=hyper,
    noise_factor=noise_factor)`` with ``train`` every pose not in the fold, number for number: the recording
    is solved and differentiated once at ``theta`` and each training set's rows are taken from that
    (:meth:`_Problem.rows`), instead of once per fold (at 100,000 poses about 2 s of CPU a fold).

    Parameters
    ----------
    model : MeasurementModel
        The calibrated recording (one pose per row).
    theta : ndarray, shape (P,)
    free : ndarray of bool, shape (P,)
    prior_sd : ndarray, shape (n_free,)
    hyper : Discrepancy
        Its inputs, standardisation, inducing points, length and output scales are kept.
    noise_factor : float
    folds : sequence of ndarray of int
        The held-out poses of each fold.

    Returns
    -------
    list of DiscrepancyFit
        One per fold.

    Raises
    ------
    InputError
        A pose cannot be solved at ``theta`` (every pose trains some fold), or no measured values.
    """
    theta = np.asarray(theta, dtype=float)
    free_idx = np.flatnonzero(free) if np.asarray(free).dtype == bool else np.asarray(free, dtype=int)
    prior_sd = np.asarray(prior_sd, dtype=float).reshape(free_idx.size)
    if np.any(~np.isfinite(prior_sd)) or np.any(prior_sd <= 0):
        raise InputError("fit_discrepancy: the geometry's prior std must be finite and positive (a method with a prior)")
    shift = np.zeros(free_idx.size) - theta[free_idx]  # as fit_discrepancy forms it (the prior mean: nominal)
    if model.y_measured is None:
        raise InputError("fit_discrepancy: the model has no measured values")
    n = model.n_poses
    with threadpool_limits(1):
        pred = model.predict(theta)
        if not pred.success.all():
            raise InputError("fit_discrepancy: a pose cannot be solved at the calibrated geometry")
        prob = _Problem(model, theta, pred, free_idx, hyper.inputs, hyper.outputs, hyper.center, hyper.scale,
                        prior_sd, shift)
        return [_posterior(model, prob.rows(np.setdiff1d(np.arange(n), test)), hyper, free_idx, prior_sd, shift,
                           float(noise_factor), hyper.log_evidence_gain) for test in folds]


def _fit(model, theta, free_idx, prior_sd, shift, inputs, n_inducing, fit_noise, seed, maxiter) -> DiscrepancyFit:
    inputs = tuple(default_inputs(model) if inputs is None else inputs)
    if not inputs:
        raise InputError("fit_discrepancy: no inputs (actuators or auxiliary channels) to model the discrepancy over")
    outputs = _outputs(model.dof)
    X = discrepancy_inputs(model, inputs)
    if X.shape[0] != model.n_poses:
        raise InputError("fit_discrepancy: takes recordings of measured poses (one pose per row)")
    center = X.mean(axis=0)
    scale = X.std(axis=0)
    if np.any(scale <= 0):
        flat = [n for n, sc in zip(inputs, scale) if sc <= 0]
        raise InputError(f"discrepancy inputs {', '.join(flat)}: constant over the recording; nothing to model")
    n = model.n_poses
    m = int(n_inducing) if n_inducing is not None else max(4, min(MAX_INDUCING, n // 3))
    m = min(m, n)
    pred = model.predict(theta)
    if not pred.success.all():
        raise InputError("fit_discrepancy: a pose cannot be solved at the calibrated geometry")
    rng = np.random.default_rng(seed)
    sub = np.sort(rng.choice(n, MAX_HYPER_POSES, replace=False)) if n > MAX_HYPER_POSES else np.arange(n)
    sub_model = model if sub.size == n else model.subset(sub)
    sub_pred = pred if sub.size == n else sub_model.predict(theta)
    hp = _Problem(sub_model, theta, sub_pred, free_idx, inputs, outputs, center, scale, prior_sd, shift)
    groups = _groups(outputs)
    n_groups = int(groups.max()) + 1
    d = len(inputs)
    rr = float(hp.r @ hp.r)
    # the geometry alone, noise factor profiled: the null model the discrepancy must beat
    M0, b0 = hp.null()
    nll0, c0 = _null_fit(M0, b0, rr, hp.N, fit_noise)
    # start: unit length scales, output scale from the residual's size, noise factor from the null fit
    sig_rows = np.asarray(sub_model.row_sigma, dtype=float)
    red = math.sqrt(max(c0, 1e-12))
    s0 = [red * float(np.median(sig_rows[:, :3])),
          red * float(np.median(sig_rows[:, 3:])) if sig_rows.shape[1] > 3 else 1.0]
    x0 = np.concatenate([np.zeros(d), np.log(np.maximum(s0[:n_groups], 1e-12)),
                         [math.log(max(0.5 * c0, 1e-6))] if fit_noise else []])
    bounds = ([(math.log(0.03), math.log(30.0))] * d
              + [(math.log(max(v, 1e-12)) - 12, math.log(max(v, 1e-12)) + 5) for v in s0[:n_groups]]
              + ([(math.log(1e-4), math.log(1e4))] if fit_noise else []))
    x0 = np.clip(x0, [b[0] for b in bounds], [b[1] for b in bounds])
    U = hp.Z[farthest_points(hp.Z, m)]
    x, _ = _optimise(hp, U, x0, bounds, d, n_groups, groups, fit_noise, maxiter)
    # inducing points again, where the fitted length scales say the function varies (a polish from there)
    ls, _, _ = _unpack(x, d, n_groups, groups, fit_noise)
    U = hp.Z[farthest_points(hp.Z, m, weights=1.0 / ls)]
    x, nll = _optimise(hp, U, x, bounds, d, n_groups, groups, fit_noise, max(10, maxiter // 3))
    ls, s, c = _unpack(x, d, n_groups, groups, fit_noise)
    gain = float(nll0 - nll)
    full = hp if sub.size == n else _Problem(model, theta, pred, free_idx, inputs, outputs, center, scale, prior_sd, shift)
    template = Discrepancy(inputs=inputs, center=center, scale=scale, length_scales=ls, outputs=outputs,
                           output_scales=s, inducing=U, weights=np.zeros(len(outputs) * U.shape[0]),
                           log_evidence_gain=gain)
    return _posterior(model, full, template, free_idx, prior_sd, shift, c, gain)


def _null_fit(M0, b0, rr, N, fit_noise) -> tuple[float, float]:
    """Negative log marginal likelihood of the geometry alone, at its best noise factor (and that factor)."""
    if not fit_noise:
        return _neg_log_ml(M0, b0, rr, N, 1.0), 1.0
    res = optimize.minimize_scalar(lambda lc: _neg_log_ml(M0, b0, rr, N, math.exp(lc)),
                                   bounds=(math.log(1e-4), math.log(1e4)), method="bounded")
    return float(res.fun), math.exp(float(res.x))


def _posterior(model, prob: _Problem, template: Discrepancy, free_idx, prior_sd, shift, c: float,
               gain: float) -> DiscrepancyFit:
    """The joint Gaussian posterior of the geometry's correction and the weights at fixed hyperparameters."""
    phi, _ = nystrom_features(prob.Z, template.inducing, template.length_scales)
    M, b = prob.pieces(phi, template.output_scales)
    n_all = M.shape[0]
    L = linalg.cholesky(np.eye(n_all) + M / c, lower=True)
    cov_u = linalg.cho_solve((L, True), np.eye(n_all))
    mu_u = cov_u @ b / c
    p = free_idx.size
    # back to the geometry's units: dtheta = shift + C0^(1/2) u_theta (shift: prior mean less the calibration)
    T = np.concatenate([prior_sd, np.ones(n_all - p)])
    cov = cov_u * np.outer(T, T)
    dtheta = shift + prior_sd * mu_u[:p]
    w = mu_u[p:]
    rr = float(prob.r @ prob.r)
    chi2 = rr - 2.0 * float(b @ mu_u) + float(mu_u @ M @ mu_u)
    hat = float(np.trace(cov_u @ M) / c)
    # the share of the geometry-only calibration's residual the joint fit removes
    r0 = float(prob.r0 @ prob.r0)
    disc = Discrepancy(
        inputs=template.inputs, center=template.center, scale=template.scale, length_scales=template.length_scales,
        outputs=template.outputs, output_scales=template.output_scales, inducing=template.inducing, weights=w,
        log_evidence_gain=gain, explained=float(np.clip(1.0 - chi2 / max(r0, 1e-300), 0.0, 1.0)),
    )
    return DiscrepancyFit(discrepancy=disc, noise_factor=float(c), covariance=0.5 * (cov + cov.T), dtheta=dtheta,
                          supported=gain >= MIN_EVIDENCE_GAIN, chi2=chi2, effective_params=hat, free=free_idx)


def joint_design(model, theta, fitted: DiscrepancyFit, prior_sd) -> tuple[NDArray, NDArray]:
    """The joint fit's whitened design and residual at ``theta``: ``([J C0^(1/2), F], W (y - h - delta))``.

    Every column has prior ``N(0, I)`` (ridge ``lam = 1``), as the per-pose
    outlier test (:func:`bayescal.outliers.pose_test_linear`) expects; rows pose by pose.
    """
    pred = model.predict(theta)
    if not pred.success.all():
        raise InputError("joint_design: a pose cannot be solved at the joint fit's geometry")
    sig = np.asarray(model.row_sigma, dtype=float)
    mean, F, _ = fitted.discrepancy.rows(model, theta, pred)
    J = model.jacobian(theta, pred)[:, :, fitted.free] * np.asarray(prior_sd, dtype=float)
    A = (np.concatenate([J, F], axis=2) / sig[:, :, None]).reshape(model.n_poses * model.dof, -1)
    r = ((model.residual(pred) - mean) / sig).reshape(-1)
    return A, r
