"""How often *any* rule for lambda or k can land near the best value on the output-error curve.

The seed picks lambda and k at the bottom of the output-error curve, which
is computed with the true machine known.  A rule sees only the measurement.
This module computes, for a linear-Gaussian idealisation of a calibration
problem, the largest probability with which any rule (any function of the
data) can choose a value whose output error is within a factor ``ratio`` of
the curve's best:

* the truth is drawn from the prior, ``x ~ N(0, I)`` (tolerance-scaled
  coordinates, so this is the tolerance prior), the data from
  ``z = A x + e``, ``e ~ N(0, I)`` (whitened rows);
* the estimates are the filtered solutions ``x_v = V diag(f_v) diag(1/s) U^T z``
  for every candidate value ``v`` (ridge lambdas or TSVD truncations);
* the output error of a value is ``|G (x_v - x)|`` (``G`` maps scaled
  parameters to the quantity calibration is judged by, e.g. tool points over
  an evaluation grid; only ratios matter, so its scale is irrelevant);
* given ``z`` the truth is distributed as the posterior ``N(m, Sigma)``,
  ``Sigma = (A^T A + I)^-1``, ``m = Sigma A^T z``, so the probability that a
  value ``v`` is within ``ratio`` of the curve's best is
  ``p_v(z) = P(|G(x_v - x)| <= ratio min_u |G(x_u - x)| | z)``.  No rule can
  succeed with a larger conditional probability than ``max_v p_v(z)``, and
  the rule ``argmax_v p_v(z)`` attains it (Bayes decision for the 0-1 loss of
  "within ``ratio``").  The **ceiling** is ``E_z[max_v p_v(z)]``.

``p_v`` is estimated from posterior samples; taking the maximum of Monte
Carlo estimates biases the ceiling slightly *upwards*, so a ceiling below a
target is conservative evidence that the target cannot be reached.  The
realised success rate of that Bayes rule on the simulated truths is
reported beside it: it matches the ceiling when the posterior is right,
which is what the tests check.

Written here because no library computes it; it is a few lines of linear
algebra on top of :func:`numpy.linalg.svd`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..errors import InputError

__all__ = ["ChoiceCeiling", "choice_ceiling", "success_probabilities", "within_best", "ratios_to_best"]


@dataclass(frozen=True)
class ChoiceCeiling:
    """The attainable share of "within ``ratio`` of the curve's best".

    Attributes
    ----------
    method : {"ridge", "tsvd"}
    ratio : float
        Tolerance on the output-error ratio (1.1: within 10 %).
    ceiling : float
        ``E_z[max_v p_v(z)]``: the largest expected success rate of any rule.
    ceiling_se : float
        Monte Carlo standard error of ``ceiling`` over the data draws.
    bayes_rule_rate : float
        Share of simulated truths on which the Bayes rule succeeded.
    fixed_rates : dict of str to float
        Realised success rate of given fixed values (for example
        ``lambda = 1``), keyed by label.
    n_data, n_posterior : int
        Data sets simulated and posterior samples per data set.
    """

    method: str
    ratio: float
    ceiling: float
    ceiling_se: float
    bayes_rule_rate: float
    fixed_rates: dict
    n_data: int
    n_posterior: int

    def report(self) -> str:
        fixed = ", ".join(f"{k} {100 * v:.0f} %" for k, v in self.fixed_rates.items())
        return (f"{self.method}: any rule is within {100 * (self.ratio - 1):.0f} % of the curve's best with probability "
                f"at most {100 * self.ceiling:.0f} % (+- {100 * self.ceiling_se:.0f}); the Bayes rule realised "
                f"{100 * self.bayes_rule_rate:.0f} %" + (f"; {fixed}" if fixed else "")
                + f" ({self.n_data} data sets x {self.n_posterior} posterior samples)")

    def to_dict(self) -> dict:
        return {"method": self.method, "ratio": self.ratio, "ceiling": self.ceiling, "ceiling_se": self.ceiling_se,
                "bayes_rule_rate": self.bayes_rule_rate, "fixed_rates": dict(self.fixed_rates),
                "n_data": self.n_data, "n_posterior": self.n_posterior}


def _checked_problem(A, G, ratio, n_data, n_posterior) -> tuple[NDArray, NDArray]:
    """``A`` and ``G`` as float matrices of matching columns, or InputError naming what :func:`choice_ceiling` refuses."""
    A = np.asarray(A, dtype=float)
    G = np.asarray(G, dtype=float)
    if A.ndim != 2 or G.ndim != 2 or G.shape[1] != A.shape[1]:
        raise InputError(f"A, G: expected shapes (N, p) and (M, p), got {A.shape} and {G.shape}")
    if ratio < 1.0:
        raise InputError(f"ratio: expected >= 1, got {ratio}")
    if n_data < 1 or n_posterior < 2:
        raise InputError(f"n_data, n_posterior: expected >= 1 and >= 2, got {n_data} and {n_posterior}")
    return A, G


def _candidate_filters(method: str, values: NDArray, s: NDArray) -> NDArray:
    """Filter factors (n_values, rank) of every candidate ``lambda`` (ridge) or ``k`` (TSVD)."""
    if method == "ridge":
        lams = values.astype(float)
        if np.any(lams <= 0):
            raise InputError("values: ridge lambdas must be positive")
        return s[None, :] ** 2 / (s[None, :] ** 2 + lams[:, None])
    if method == "tsvd":
        ks = values.astype(int)
        if np.any(ks < 1) or np.any(ks > s.size):
            raise InputError(f"values: k must be from 1 to {s.size}")
        return (np.arange(s.size)[None, :] < ks[:, None]).astype(float)
    raise InputError(f"method: expected 'ridge' or 'tsvd', got {method!r}")


def _fixed_indices(values: NDArray, fixed: dict | None) -> dict[str, int]:
    """Index into ``values`` of each fixed value to report, or InputError naming one that is not a candidate."""
    fixed_idx = {}
    for label, v in dict(fixed or {}).items():
        hit = np.flatnonzero(np.isclose(values.astype(float), float(v), rtol=1e-12, atol=0.0))
        if hit.size == 0:
            raise InputError(f"fixed[{label!r}]: {v} is not one of the candidate values")
        fixed_idx[label] = int(hit[0])
    return fixed_idx


def choice_ceiling(
    A: ArrayLike,
    G: ArrayLike,
    method: str,
    values: ArrayLike,
    *,
    ratio: float = 1.1,
    fixed: dict | None = None,
    n_data: int = 200,
    n_posterior: int = 400,
    seed: int = 0,
    truth_scale: float = 1.0,
) -> ChoiceCeiling:
    """Largest expected share of data sets on which any rule lands within ``ratio`` of the curve's best.

    Parameters
    ----------
    A : array_like, shape (N, p)
        Whitened, tolerance-scaled identification matrix (dimensionless).
    G : array_like, shape (M, p)
        Output map: output error of an estimate ``x_hat`` is ``|G (x_hat - x)|``
        (for example tool-point Jacobians over an evaluation grid, mm per
        tolerance; stacked rows).
    method : {"ridge", "tsvd"}
    values : array_like
        Candidate ``lambda`` values (ridge, > 0) or ``k`` values (TSVD, 1..rank).
    ratio : float
        Success means an output error at most ``ratio`` times the best over ``values``.
    fixed : dict of str to float or int, optional
        Fixed values (members of ``values``) whose realised success rates to report.
    n_data, n_posterior : int
        Data sets simulated, and posterior samples per data set.
    seed : int
    truth_scale : float
        Draw the truths from ``N(0, truth_scale^2 I)`` while the posterior
        still assumes ``N(0, I)``: what happens when the tolerances are
        wrong by that factor (then the ceiling is no longer attained, and
        ``bayes_rule_rate`` shows what the rule really achieves).

    Returns
    -------
    ChoiceCeiling
    """
    A, G = _checked_problem(A, G, ratio, n_data, n_posterior)
    p = A.shape[1]
    # only s and V are needed: the data are simulated in the singular coordinates
    _, s, Vt_full = np.linalg.svd(A, full_matrices=True)
    values = np.asarray(values)
    F = _candidate_filters(method, values, s)
    fixed_idx = _fixed_indices(values, fixed)
    inv_s = np.where(s > 1e-12 * s[0], 1.0 / np.where(s > 0, s, 1.0), 0.0)
    # posterior N(m, Sigma) in the right singular vectors: independent per direction
    post_sd = 1.0 / np.sqrt(s**2 + 1.0)
    unseen = p - s.size  # directions A does not touch keep the prior N(0, 1)
    GV = G @ Vt_full.T  # (M, p)
    rng = np.random.default_rng(seed)
    best_p, bayes_ok = np.empty(n_data), np.empty(n_data, dtype=bool)
    fixed_ok = {label: np.empty(n_data, dtype=bool) for label in fixed_idx}
    for t in range(n_data):
        c_true = truth_scale * rng.normal(size=p)  # truth in the rotated coordinates V^T x (the prior is isotropic)
        beta = s * c_true[: s.size] + rng.normal(size=s.size)  # U^T z; the rest of z carries no information
        est = F * (beta * inv_s)[None, :]  # (n_values, rank) coordinates of every estimate
        mean = s * beta / (s**2 + 1.0)
        draws = mean[None, :] + rng.normal(size=(n_posterior, s.size)) * post_sd[None, :]
        if unseen:
            draws = np.hstack([draws, rng.normal(size=(n_posterior, unseen))])
        truths = np.vstack([draws, c_true[None, :]])  # posterior samples, then the true value
        within, _ = within_best(truths, est, GV, ratio)
        p_v = within[:-1].mean(axis=0)
        j = int(np.argmax(p_v))
        best_p[t], bayes_ok[t] = p_v[j], within[-1, j]
        for label, i in fixed_idx.items():
            fixed_ok[label][t] = within[-1, i]
    return ChoiceCeiling(
        method=method, ratio=float(ratio), ceiling=float(best_p.mean()),
        ceiling_se=float(best_p.std(ddof=1) / np.sqrt(n_data)) if n_data > 1 else float("nan"),
        bayes_rule_rate=float(bayes_ok.mean()), fixed_rates={k: float(v.mean()) for k, v in fixed_ok.items()},
        n_data=int(n_data), n_posterior=int(n_posterior),
    )


def within_best(truths: NDArray, est: NDArray, GV: NDArray, ratio: float) -> tuple[NDArray, NDArray]:
    """Which candidates are within ``ratio`` of the best, for each possible truth.

    Parameters
    ----------
    truths : ndarray, shape (n, p)
        Truths in the coordinates of the estimates (for example ``V^T x``).
    est : ndarray, shape (n_values, r)
        Candidate estimates in the first ``r <= p`` of those coordinates
        (the others are zero).
    GV : ndarray, shape (M, p)
        Output map in those coordinates.
    ratio : float

    Returns
    -------
    within : ndarray of bool, shape (n, n_values)
        ``|GV (est_v - t)| <= ratio min_u |GV (est_u - t)|``.
    rel : ndarray, shape (n, n_values)
        ``|GV (est_v - t)| / min_u |GV (est_u - t)|`` (the ratio to the hindsight best; 1 where all are 0).
    """
    err, best = _output_errors(truths, est, GV)
    return err <= ratio * best, _ratios(err, best)


def ratios_to_best(truths: NDArray, est: NDArray, GV: NDArray) -> NDArray:
    """The ``rel`` of :func:`within_best` alone (the same numbers), computed in place.

    ``calibrate_target_rule`` evaluates it for hundreds of data sets times
    several prior scales; the second result's comparison and the temporaries
    of :func:`within_best` cost as much as the arithmetic there.
    """
    err, best = _output_errors(truths, est, GV)
    if np.all(best > 0):
        err /= best  # every row has a best above 0: the ratio itself
        return err
    return _ratios(err, best)


def _output_errors(truths: NDArray, est: NDArray, GV: NDArray) -> tuple[NDArray, NDArray]:
    """``|GV (est_v - t)|`` for every truth and candidate (n, n_values), and its minimum per truth (n, 1)."""
    # output errors |GV (e - t)|^2 = |GV t|^2 - 2 (GV t).(GV e) + |GV e|^2, without forming n x n_values x M
    Gt = truths @ GV.T  # (n, M)
    Ge = est @ GV[:, : est.shape[1]].T  # (n_values, M)
    # |GV t|^2 - 2.0 * Gt @ Ge.T + |GV e|^2, in that order, in place
    err = (2.0 * Gt) @ Ge.T
    np.subtract(np.sum(Gt**2, axis=1)[:, None], err, out=err)
    err += np.sum(Ge**2, axis=1)[None, :]
    np.maximum(err, 0.0, out=err)
    np.sqrt(err, out=err)
    return err, err.min(axis=1, keepdims=True)


def _ratios(err: NDArray, best: NDArray) -> NDArray:
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(best > 0, err / np.where(best > 0, best, 1.0), 1.0)


def success_probabilities(
    est: ArrayLike,
    mean: ArrayLike,
    sd: ArrayLike,
    GV: ArrayLike,
    *,
    ratio: float = 1.1,
    n_posterior: int = 400,
    seed: int = 0,
) -> tuple[NDArray, NDArray]:
    """Posterior probability that each candidate is within ``ratio`` of the hindsight best, by Monte Carlo.

    The posterior of the truth is independent Gaussian in the coordinates of
    the estimates: ``t_i ~ N(mean_i, sd_i^2)`` (the right singular vectors of
    a linear-Gaussian problem with an isotropic prior).  The same draws serve
    every candidate (common random numbers), so differences between
    candidates carry less Monte Carlo noise than the probabilities.

    Parameters
    ----------
    est : array_like, shape (n_values, r)
        Candidate estimates (first ``r`` coordinates; the rest zero).
    mean, sd : array_like, shape (p,) or (n_posterior, p)
        Posterior mean and standard deviation per coordinate (``p >= r``);
        with one row per draw, each draw comes from its own component (a
        mixture, for example over the prior scale).
    GV : array_like, shape (M, p)
        Output map in those coordinates (only ``|GV d|`` matters, so any
        ``Q`` with ``Q^T Q = GV^T GV`` gives the same answer).
    ratio : float
        Success: output error at most ``ratio`` times the best candidate's.
    n_posterior : int
        Posterior draws.
    seed : int
        Seeds the draws (the answer is a deterministic function of the data).

    Returns
    -------
    prob : ndarray, shape (n_values,)
        ``P(within ratio | data)`` per candidate.
    expected_ratio : ndarray, shape (n_values,)
        ``E[error_v / min_u error_u | data]`` per candidate.
    """
    est = np.atleast_2d(np.asarray(est, dtype=float))
    mean = np.asarray(mean, dtype=float)
    sd = np.asarray(sd, dtype=float)
    GV = np.asarray(GV, dtype=float)
    p = mean.shape[-1] if mean.ndim else 0
    if (sd.shape != mean.shape or mean.ndim not in (1, 2) or (mean.ndim == 2 and mean.shape[0] != n_posterior)
            or GV.ndim != 2 or GV.shape[1] != p or est.shape[1] > p):
        raise InputError(f"est, mean, sd, GV: inconsistent shapes {est.shape}, {mean.shape}, {sd.shape}, {GV.shape}")
    if n_posterior < 2:
        raise InputError(f"n_posterior: expected >= 2, got {n_posterior}")
    # a (n_posterior, p) mean and sd: a mixture, one component per draw (e.g. over the prior scale)
    draws = mean + np.random.default_rng(seed).normal(size=(n_posterior, p)) * sd
    within, rel = within_best(draws, est, GV, ratio)
    return within.mean(axis=0), rel.mean(axis=0)
