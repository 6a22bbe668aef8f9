"""Fitting a discrepancy to a calibration: hyperparameters by marginal likelihood, weights by their posterior.

At a calibrated geometry ``theta`` the whitened residual ``r`` (``N`` rows)
and the whitened identification matrix ``A`` (``N x p``, the free
parameters, instrument frames included) are given.  The gauge: the
discrepancy must not take what the geometry explains, so it is fitted in
the orthogonal complement of the span of ``A`` (``Q`` an orthonormal basis
of that span, ``P = I - Q Q^T``):

    P r = P F v + P e,     v ~ N(0, I),   e ~ N(0, c I),

with ``F`` the whitened feature matrix (:meth:`Discrepancy.rows`).  By
construction the geometry's fit is then the same with and without the
discrepancy (its normal equations decouple), and a discrepancy that merely
re-describes a geometric error is impossible.

**Hyperparameters** (length scale per input, prior scale per group of
outputs, noise factor ``c``) maximise the restricted marginal likelihood of
``P r`` (Woodbury, ``M = F^T P F``, ``b = F^T P r``, ``N' = N - rank A``):

    -2 log p = (|P r|^2 - b^T (c I + M)^-1 b) / c + N' log c + log det(I + M / c)

by L-BFGS-B in log space.  Beyond :data:`MAX_HYPER_POSES` poses they are
estimated on a seeded subset (the weights then on all poses), which keeps
the cost near linear in the poses.  Inducing points are picked by farthest
points in the standardised inputs, then again in the length-scaled inputs
after a first fit (irrelevant inputs stop spreading them).

**Is it there?**  The gain in log marginal likelihood over ``s = 0`` (the
residual as white noise with its own ``c``) is a log Bayes factor; below
:data:`MIN_EVIDENCE_GAIN` the discrepancy is not supported and a caller
should drop it (a clean recording).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy import linalg, optimize
from threadpoolctl import threadpool_limits

from ..errors import InputError
from ..identifiability import STRUCTURAL_RTOL
from .kernel import farthest_points, nystrom_features
from .model import OUTPUT_NAMES, Discrepancy, discrepancy_inputs, output_rows_map

__all__ = ["DiscrepancyFit", "fit_discrepancy", "default_inputs", "MIN_EVIDENCE_GAIN", "MAX_HYPER_POSES"]

#: Log Bayes factor (in nats) a discrepancy must gain over white noise to be kept.
MIN_EVIDENCE_GAIN = 6.0
#: Poses at most on which the hyperparameters are estimated (a seeded subset beyond).
MAX_HYPER_POSES = 1200
#: Inducing points at most (and at most half the poses).
MAX_INDUCING = 48
#: Auxiliary channels that are bookkeeping, not physics: never default inputs.
_NOT_PHYSICS = ("pose_id", "id", "index", "line", "sample", "sigma_position", "sigma_angle")


@dataclass(frozen=True)
class DiscrepancyFit:
    """A discrepancy fitted at a calibrated geometry.

    Attributes
    ----------
    discrepancy : Discrepancy
    noise_factor : float
        ``c``: the noise variance relative to the model's sigma, with the discrepancy accounted for.
    weight_cov : ndarray, shape (K, K)
        Posterior covariance of the weights ``v``.
    B : ndarray, shape (p, K)
        Least-squares map from weights to the free parameters (the projection's geometric part), physical units.
    supported : bool
        ``log_evidence_gain >= MIN_EVIDENCE_GAIN``.
    chi2 : float
        Whitened residual sum of squares after the discrepancy's mean (at the model's sigma).
    effective_params : float
        The discrepancy's effective number of parameters (trace of its hat matrix).
    free : ndarray of int
        The free parameters ``B`` refers to.
    """

    discrepancy: Discrepancy
    noise_factor: float
    weight_cov: NDArray
    B: NDArray
    supported: bool
    chi2: float
    effective_params: float
    free: NDArray

    def joint_covariance(self, geometry_cov: NDArray) -> NDArray:
        """Covariance of ``(theta_free - B v, v)``: what predictions at new poses propagate (module :mod:`.model`)."""
        C = np.asarray(geometry_cov, dtype=float)
        BS = self.B @ self.weight_cov
        top = np.hstack([C + BS @ self.B.T, -BS])
        bottom = np.hstack([-BS.T, self.weight_cov])
        J = np.vstack([top, bottom])
        return 0.5 * (J + J.T)


def default_inputs(model) -> tuple[str, ...]:
    """The discrepancy's default inputs: every actuator and every auxiliary channel that varies.

    Channels named like bookkeeping (``pose_id``, ...) are left out.
    """
    n_act = np.asarray(model.pose_q).shape[1]
    names = [f"q{i + 1}" for i in range(n_act)]
    for k, v in (model.aux or {}).items():
        v = np.asarray(v, dtype=float)
        if k.lower() in _NOT_PHYSICS or not np.all(np.isfinite(v)) or np.ptp(v) <= 0:
            continue
        names.append(k)
    return tuple(names)


def _outputs(dof: int) -> tuple[str, ...]:
    return OUTPUT_NAMES if dof >= 5 else OUTPUT_NAMES[:3]


class _Problem:
    """The whitened, projected pieces of one fit (module docstring), for a set of poses."""

    def __init__(self, model, theta, prediction, free, inputs, outputs, center, scale):
        sig = np.asarray(model.row_sigma, dtype=float)
        n, dof = sig.shape
        self.n, self.dof = n, dof
        r = (model.residual(prediction) / sig).reshape(-1)
        J = model.jacobian(theta, prediction)[:, :, free] / sig[:, :, None]
        A = J.reshape(n * dof, -1)
        U, s, Vt = np.linalg.svd(A, full_matrices=False)
        rank = int(np.sum(s > STRUCTURAL_RTOL * s[0])) if s.size and s[0] > 0 else 0
        self.Q, self.s_r, self.V_r = U[:, :rank], s[:rank], Vt[:rank].T
        self.rank = rank
        self.r_perp = r - self.Q @ (self.Q.T @ r)
        self.N_eff = n * dof - rank
        G = output_rows_map(model, theta, prediction, outputs) / sig[:, :, None]  # (n, dof, n_out)
        self.G = G
        self.g = np.einsum("nao,nap->nop", G, G)  # (n, n_out, n_out)
        # output pairs no row couples (a position row never sees a rotation output): their blocks are zero
        self.coupled = np.any(self.g != 0.0, axis=0)
        Qr = self.Q.reshape(n, dof, rank)
        self.H = np.einsum("nar,nao->nor", Qr, G)  # (n, n_out, rank)
        self.Gr = np.einsum("nao,na->no", G, self.r_perp.reshape(n, dof))  # (n, n_out)
        self.Z = (discrepancy_inputs(model, inputs) - center) / scale
        self.n_out = len(outputs)

    def pieces(self, phi: NDArray, s: NDArray) -> tuple[NDArray, NDArray, NDArray]:
        """``M = F^T P F``, ``b = F^T P r`` and ``Q^T F`` for features ``phi`` (n, m) and output scales ``s``."""
        m, o = phi.shape[1], self.n_out
        # F^T F in (o, p) blocks of m x m: s_o s_p sum_n g_nop phi_n phi_n^T (one BLAS product per block)
        FtF = np.zeros((o * m, o * m))
        for a in range(o):
            for c in range(a, o):
                if not self.coupled[a, c]:
                    continue
                blk = (phi * self.g[:, a, c][:, None]).T @ phi * (s[a] * s[c])
                FtF[a * m:(a + 1) * m, c * m:(c + 1) * m] = blk
                FtF[c * m:(c + 1) * m, a * m:(a + 1) * m] = blk.T
        QtF = np.hstack([self.H[:, a, :].T @ phi * s[a] for a in range(o)]) if self.rank else np.zeros((0, o * m))
        M = FtF - QtF.T @ QtF
        b = (np.einsum("no,nj->oj", self.Gr, phi) * s[:, None]).reshape(-1)
        return 0.5 * (M + M.T), b, QtF


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
    rr = float(prob.r_perp @ prob.r_perp)

    def f(x):
        ls, s, c = _unpack(x, d, n_groups, groups, fit_noise)
        try:
            phi, _ = nystrom_features(prob.Z, U, ls)
        except linalg.LinAlgError:
            return 1e300
        M, b, _ = prob.pieces(phi, s)
        v = _neg_log_ml(M, b, rr, prob.N_eff, c)
        return v if np.isfinite(v) else 1e300

    res = optimize.minimize(f, x0, method="L-BFGS-B", bounds=bounds, options={"maxiter": maxiter})
    return res.x, float(res.fun)


def fit_discrepancy(model, theta, free, *, inputs=None, n_inducing: int | None = None, fit_noise: bool = True,
                    seed: int = 0, maxiter: int = 40, hyper: Discrepancy | None = None) -> DiscrepancyFit:
    """Fit a discrepancy to the residual of a calibration (module docstring).

    Parameters
    ----------
    model : MeasurementModel
        The calibrated recording (its sigma whitens the rows).
    theta : ndarray, shape (P,)
        The calibrated parameters.
    free : ndarray of bool or int, shape (P,) or (p,)
        Which parameters the calibration fitted (their span is kept off the discrepancy).
    inputs : sequence of str, optional
        ``q<i>`` and auxiliary channel names; default :func:`default_inputs`.
    n_inducing : int, optional
        Inducing points (default: min(48, poses // 3)).
    fit_noise : bool
        Estimate the noise factor ``c`` with the rest (else ``c = 1``: the model's sigma as stated).
    seed : int
        For the subset of poses the hyperparameters are estimated on (large recordings).
    maxiter : int
        L-BFGS-B iterations per stage.
    hyper : Discrepancy, optional
        Keep this discrepancy's inputs, standardisation, inducing points,
        length and output scales (no search) and refit only the weights,
        with the noise factor 1 (the model's sigma as it is): a geometry
        refitted at the noise the first fit estimated.

    Returns
    -------
    DiscrepancyFit
    """
    theta = np.asarray(theta, dtype=float)
    free_idx = np.flatnonzero(free) if np.asarray(free).dtype == bool else np.asarray(free, dtype=int)
    if model.y_measured is None:
        raise InputError("fit_discrepancy: the model has no measured values")
    # the matrices are small (a few hundred): threaded BLAS only costs here, badly on a loaded machine (8x seen)
    with threadpool_limits(1):
        if hyper is not None:
            return _refit_weights(model, theta, free_idx, hyper)
        return _fit(model, theta, free_idx, inputs, n_inducing, fit_noise, seed, maxiter)


def _fit(model, theta, free_idx, inputs, n_inducing, fit_noise, seed, maxiter) -> DiscrepancyFit:
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
    hp = _Problem(sub_model, theta, sub_pred, free_idx, inputs, outputs, center, scale)
    groups = _groups(outputs)
    n_groups = int(groups.max()) + 1
    d = len(inputs)
    # start: unit length scales, output scale from the projected residual, noise factor at the rest
    rms = math.sqrt(max(float(hp.r_perp @ hp.r_perp) / max(hp.N_eff, 1), 1e-12))
    sig_rows = np.asarray(sub_model.row_sigma, dtype=float)
    s0 = [rms * float(np.median(sig_rows[:, :3])), rms * float(np.median(sig_rows[:, 3:])) if sig_rows.shape[1] > 3 else 1.0]
    x0 = np.concatenate([np.zeros(d), np.log(np.maximum(s0[:n_groups], 1e-12)),
                         [math.log(max(0.5 * rms**2, 1e-6))] if fit_noise else []])
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
    rr = float(hp.r_perp @ hp.r_perp)
    c0 = rr / max(hp.N_eff, 1)
    nll0 = 0.5 * (rr / c0 + hp.N_eff * math.log(c0)) if fit_noise else 0.5 * rr
    gain = float(nll0 - nll)
    # the weights' posterior on every pose
    full = hp if sub.size == n else _Problem(model, theta, pred, free_idx, inputs, outputs, center, scale)
    template = Discrepancy(inputs=inputs, center=center, scale=scale, length_scales=ls, outputs=outputs,
                           output_scales=s, inducing=U, weights=np.zeros(len(outputs) * U.shape[0]),
                           log_evidence_gain=gain)
    return _posterior(model, full, template, free_idx, c, gain)


def _refit_weights(model, theta, free_idx, hyper: Discrepancy) -> DiscrepancyFit:
    pred = model.predict(theta)
    if not pred.success.all():
        raise InputError("fit_discrepancy: a pose cannot be solved at the calibrated geometry")
    prob = _Problem(model, theta, pred, free_idx, hyper.inputs, hyper.outputs, hyper.center, hyper.scale)
    return _posterior(model, prob, hyper, free_idx, 1.0, hyper.log_evidence_gain)


def _posterior(model, prob: _Problem, template: Discrepancy, free_idx, c: float, gain: float) -> DiscrepancyFit:
    """The weights' Gaussian posterior at fixed hyperparameters, and the fitted discrepancy."""
    phi, _ = nystrom_features(prob.Z, template.inducing, template.length_scales)
    M, b, QtF = prob.pieces(phi, template.output_scales)
    K = M.shape[0]
    L = linalg.cholesky(np.eye(K) + M / c, lower=True)
    cov = linalg.cho_solve((L, True), np.eye(K))
    mu = cov @ b / c
    # the projection's geometric part: A^+ Q Q^T F = V_r diag(1/s_r) Q^T F, physical units
    B = (prob.V_r / prob.s_r) @ QtF
    names = model.machine.layout.names
    rr = float(prob.r_perp @ prob.r_perp)
    chi2 = rr - 2.0 * float(b @ mu) + float(mu @ M @ mu)
    hat = float(np.trace(cov @ M) / c)
    disc = Discrepancy(
        inputs=template.inputs, center=template.center, scale=template.scale, length_scales=template.length_scales,
        outputs=template.outputs, output_scales=template.output_scales, inducing=template.inducing, weights=mu,
        shift_names=tuple(names[j] for j in free_idx), shift=B @ mu, log_evidence_gain=gain,
        explained=float(np.clip(1.0 - chi2 / max(rr, 1e-300), 0.0, 1.0)),
    )
    return DiscrepancyFit(discrepancy=disc, noise_factor=float(c), weight_cov=0.5 * (cov + cov.T), B=B,
                          supported=gain >= MIN_EVIDENCE_GAIN, chi2=chi2, effective_params=hat, free=free_idx)
