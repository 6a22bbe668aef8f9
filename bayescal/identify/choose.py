"""Choosing the ridge parameter ``lam`` and the TSVD truncation ``k`` without a human.

All rules work on the *linear* problem ``A x ~ z`` of one Gauss-Newton step
on the total deviation from nominal (rows whitened by the instrument sigma,
columns scaled by the tolerances, see :mod:`bayescal.identify.gauss_newton`),
through the SVD ``A = U diag(s) V^T``, ``beta = U^T z``:

* ``cv``: K-fold cross-validation over *poses* (all rows of a pose are held
  out together): the seed's V/U curve of the output error, computed on
  held-out measured poses because a real user does not know the true machine.
* ``lcurve``: the corner of the L-curve ``(log |A x - z|, log |x|)``, the
  point of maximum curvature (analytic for ridge, Menger curvature of the
  discrete points for TSVD).
* ``gcv``: generalised cross-validation ``|A x - z|^2 / (N - sum f)^2``.
* ``discrepancy``: the residual matches the noise: ``|A x - z|^2 = N - sum f``
  (whitened rows, so the expected residual of a fit with ``sum f`` effective
  parameters).  The most regularised solution with ``|A x - z|^2 <= N - sum f``
  is taken; if none, the one closest to equality.
* ``evidence``: the marginal likelihood of the linear-Gaussian model
  ``z = A x + e``, ``e ~ N(0, I)``, ``x ~ N(0, I / lam)`` (``lam`` is the
  noise-to-prior variance ratio; ``lam = 1`` is the tolerance prior),
  maximised over ``lam``.  For TSVD, the evidence of the truncated model
  ``x = V_k c`` with ``c ~ N(0, I / lam)``, maximised over ``lam`` for each
  ``k``.  When the machine file gives no instrument sigma the noise scale is
  profiled out.
* ``risk``: the Bayes decision for the empirical-Bayes prior.  With
  ``lam_ev`` the evidence choice of ridge, the posterior of ``x`` is
  ``N(m, Sigma)``, ``m`` the ridge solution at ``lam_ev``; the rule picks the
  value whose solution ``x_v`` minimises the posterior expected squared
  error ``E|x_v - x|^2 = |x_v - m|^2 + tr Sigma``.  For ridge that is
  ``lam_ev`` itself (the posterior mean), so ``risk`` and ``evidence``
  coincide.  For TSVD the posterior is diagonal in the right singular
  vectors, so keeping direction ``i`` costs ``(beta_i / s_i - m_i)^2`` and
  dropping it ``m_i^2``: keep it iff ``s_i^2 > lam_ev``, i.e.
  ``k = #{s_i^2 > lam_ev}`` (the directions the data determine better than
  the prior does).
* ``success``: the Bayes decision for the *success event* of the study
  (output error within ``ratio`` = 10 % of the best candidate's, the best
  picked in hindsight knowing the truth).  Under the same empirical-Bayes
  posterior as ``risk``, the posterior probability that each candidate's
  output error ``|G (x_v - x)|`` is within ``ratio`` of ``min_u |G (x_u - x)|``
  is estimated from ``n_posterior`` seeded posterior draws
  (:func:`bayescal.identify.ceiling.success_probabilities`, the machinery of
  the success ceiling), with the prior ratio integrated out: each draw takes
  its ``lam`` from the posterior of ``lam`` over :func:`lambda_grid`, the
  evidence times a hyperprior on the prior scale ``c = sigma / sqrt(lam)``
  (:func:`lambda_posterior`, :mod:`bayescal.identify.scale_prior`: the
  tolerances are information, the scale is not left flat in ``log lam``);
  the candidate with the largest probability wins (ties: the smaller
  posterior expected ratio).  So it is the Bayes decision for the success
  event in the hierarchical model ``c ~ hyperprior``, ``x ~ N(0, c^2 I)``.
  ``G`` is the output map (tool-point Jacobians, tolerance-scaled); without
  one, the scaled parameter error ``|x_v - x|``.  The default for lambda
  (``studies/choice_rules.py``, docs/regularisation.md).
* ``targets``: the Lagrangian compromise of :mod:`.target_rule`, calibrated
  on the problem's own design to keep the success probability within 3
  points of the ceiling, the regret on the expected ratio and the tail
  ``P(ratio > T)`` within their targets at truth scales 0.5-4 times the
  tolerances at once.  Its calibration simulates data sets from ``A``
  (a few seconds), so it is computed only when asked for (``rule`` or
  ``target_rule``); once per design, then cached (without an instrument
  sigma the design is whitened by each data set's residual scale, so the
  calibration is redone for every data set).  The default for k.

Where the problem is linearised (see :func:`choose_regularisation`): ridge
iterates rule and Gauss-Newton to a fixed point (linearise at the converged
ridge solution, apply the rule, re-solve, at most ``max_rounds`` times);
TSVD applies the rule once at the start geometry, where bayescal's TSVD
fixes its subspace.

References
----------
P. C. Hansen, *Rank-Deficient and Discrete Ill-Posed Problems*, SIAM 1998, ch. 7.
G. H. Golub, M. Heath, G. Wahba, "Generalized cross-validation as a method for
choosing a good ridge parameter", Technometrics 21 (1979).
D. J. C. MacKay, "Bayesian interpolation", Neural Computation 4 (1992).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..constants import CALIBRATED_RULES, DEFAULT_RULE, RULE_NAMES, RULES
from ..errors import InputError
from ..limits import LAM_RANGE
from ..measurement import MeasurementModel
from .ceiling import success_probabilities
from ..progress import report
from .gauss_newton import identify, resolve_free, whitened_system
from .result import IdentificationResult
from .scale_prior import DEFAULT_HYPERPRIOR, ScaleHyperprior
from .target_rule import TargetRule, calibrate_target_rule, rule_design

__all__ = [
    "RULES",
    "CALIBRATED_RULES",
    "RULE_NAMES",
    "DEFAULT_RULE",
    "RegularisationChoice",
    "choose_linear",
    "choose_regularisation",
    "linearised_problem",
    "lambda_grid",
    "evidence_lambda",
    "lambda_posterior",
]

# RULES, CALIBRATED_RULES, RULE_NAMES and DEFAULT_RULE are defined in bayescal.constants (the command line
# offers them without importing numpy) and exported from here as before.

#: Posterior draws of the ``success`` rule.  With 400 the rule's own Monte
#: Carlo noise cost 0.3-0.6 point of success probability against the ceiling
#: in studies/choice_rules.py (the same rule knowing the true prior scale);
#: with 2000, 0.1-0.3.  The draws are cheap next to the SVD of a recording.
N_POSTERIOR = 2000

_LOG2PI = float(np.log(2.0 * np.pi))


# --------------------------------------------------------------------- result
@dataclass(frozen=True)
class RegularisationChoice:
    """The regularisation a rule chose, with what every other rule would choose.

    Attributes
    ----------
    method : {"ridge", "tsvd"}
    rule : str
        The rule that decided ``value``.
    value : float or int
        ``lam`` (dimensionless, relative to the whitened tolerance-scaled
        matrix) or ``k``.
    choices : dict of str to float or int
        The value every rule picks.
    grid : ndarray
        ``lam`` values (ridge, ascending) or ``k = 1..p`` (TSVD).
    curves : dict of str to ndarray
        Over ``grid``: ``residual_norm``, ``solution_norm`` (whitened, scaled),
        ``effective_parameters`` (sum of filter factors), ``gcv``, ``cv``
        (mean squared held-out whitened error), ``discrepancy``
        (``|r|^2 - (N - sum f)``), ``log_evidence``, ``curvature`` (L-curve),
        ``posterior_risk`` (posterior expected squared error of the scaled
        solution under the empirical-Bayes prior, see ``risk``),
        ``success_probability`` (posterior probability of being within
        ``ratio`` of the hindsight best, see ``success``) and
        ``success_expected_ratio``.
    singular_values : ndarray
    n_rows, n_params : int
        Rows (whitened residuals) and identified parameters of the linear problem.
    noise_known : bool
        Whether the instrument sigma came from the machine file.
    linearisation : str
        Where the linear problem was taken.
    rounds : int
        Rule + Gauss-Newton rounds (ridge fixed point).
    folds : int
        Cross-validation folds used.
    target_rule : dict, optional
        The ``targets`` rule's calibration (:meth:`~bayescal.identify.target_rule.TargetRule.to_dict`), when it ran.
    """

    method: str
    rule: str
    value: float | int
    choices: dict
    grid: NDArray
    curves: dict
    singular_values: NDArray
    n_rows: int
    n_params: int
    noise_known: bool = True
    linearisation: str = ""
    rounds: int = 1
    folds: int = 0
    target_rule: dict | None = None

    @property
    def symbol(self) -> str:
        return "lambda" if self.method == "ridge" else "k"

    def _fmt(self, v) -> str:
        return f"{v:.4g}" if self.method == "ridge" else f"{int(v)}"

    def report(self) -> str:
        """The chosen value and, beside it, what the other rules pick."""
        lines = [
            f"regularisation: {self.method} {self.symbol} = {self._fmt(self.value)} chosen by '{self.rule}' "
            f"({self.n_rows} rows, {self.n_params} parameters; {self.linearisation})",
        ]
        for r in RULE_NAMES:
            if r in self.choices:
                mark = "  <- used" if r == self.rule else ""
                lines.append(f"    {r:<12} {self.symbol} = {self._fmt(self.choices[r])}{mark}")
        if not self.noise_known:
            lines.append("    (no instrument sigma in the machine file: the discrepancy rule used the default sigma)")
        return "\n".join(lines)

    def to_dict(self) -> dict:
        return {
            "method": self.method,
            "rule": self.rule,
            "value": self.value,
            "choices": dict(self.choices),
            "grid": self.grid,
            "curves": dict(self.curves),
            "singular_values": self.singular_values,
            "n_rows": self.n_rows,
            "n_params": self.n_params,
            "noise_known": self.noise_known,
            "linearisation": self.linearisation,
            "rounds": self.rounds,
            "folds": self.folds,
        } | ({} if self.target_rule is None else {"target_rule": self.target_rule})


# ------------------------------------------------------------ linear algebra
@dataclass(frozen=True)
class _Svd:
    s: NDArray
    V: NDArray
    beta: NDArray
    c_perp: float  # |z|^2 - |U^T z|^2: residual no solution can remove
    n_rows: int


def _svd(A: NDArray, z: NDArray) -> _Svd:
    U, s, Vt = np.linalg.svd(A, full_matrices=False)
    beta = U.T @ z
    return _Svd(s=s, V=Vt.T, beta=beta, c_perp=max(float(z @ z - beta @ beta), 0.0), n_rows=A.shape[0])


def _check_noise_estimable(A: NDArray, z: NDArray, d: _Svd, noise_known: bool, method: str) -> None:
    """InputError when no noise is stated and the rows leave nothing to estimate it from.

    One height of a printer (no ``[measurement]``), or 19 copies of it: the rules' evidence divided by a
    residual of zero and ``numpy`` raised "Probabilities contain NaN" (a traceback).  Copied rows add none.
    """
    if noise_known:
        return
    rank = int(np.sum(d.s > 1e-12 * d.s.max())) if d.s.size and d.s.max() > 0 else 0
    distinct = int(np.unique(np.column_stack([A, z]), axis=0).shape[0])
    if distinct <= rank:
        what = "lam" if method == "ridge" else "k"
        raise InputError(f"{what}='auto': no noise stated and no residual degrees of freedom to estimate it from "
                         f"({distinct} distinct measured component(s) for the {rank} the data determine); give a "
                         f"number (--{what}), more measurements, or the noise ([measurement] in the machine file)")


def _safe_inv(s: NDArray) -> NDArray:
    return np.where(s > 0, 1.0 / np.where(s > 0, s, 1.0), 0.0)


def lambda_grid(s: NDArray, n: int = 241) -> NDArray:
    """Log-spaced ``lam`` from ``1e-3 s_min^2`` to ``1e2 s_max^2`` (``s_min`` at most 1e-12 ``s_max``).

    Within the accepted range (:data:`bayescal.limits.LAM_RANGE`): a rule cannot choose a ``lam`` that
    ``identify`` would refuse.
    """
    s = np.asarray(s, dtype=float)
    smax = float(s[0]) if s.size and s[0] > 0 else 1.0
    smin = max(float(s[s > 0][-1]) if np.any(s > 0) else smax, 1e-6 * smax)
    hi = min(1e2 * smax**2, LAM_RANGE[1])
    return np.logspace(np.log10(min(1e-3 * smin**2, hi)), np.log10(hi), n)


def _filters(method: str, s: NDArray, grid: NDArray) -> NDArray:
    """Filter factors, shape (n_grid, p)."""
    if method == "ridge":
        s2 = s**2
        return s2[None, :] / (s2[None, :] + grid[:, None])
    return (np.arange(s.size)[None, :] < grid[:, None]).astype(float)


def _solutions(d: _Svd, F: NDArray) -> NDArray:
    """Solutions for every filter row, shape (p, n_grid)."""
    return d.V @ (F * (d.beta * _safe_inv(d.s))[None, :]).T


def _log_evidence_ridge(d: _Svd, lams: NDArray, noise_known: bool) -> NDArray:
    # z ~ N(0, I + A A^T / lam): eigenvalues 1 + s^2/lam along U, 1 elsewhere
    g = 1.0 + d.s[None, :] ** 2 / lams[:, None]
    quad = np.sum(d.beta[None, :] ** 2 / g, axis=1) + d.c_perp
    logdet = np.sum(np.log(g), axis=1)
    N = d.n_rows
    if noise_known:
        return -0.5 * (quad + logdet + N * _LOG2PI)
    # noise scale profiled out: sigma^2 = quad / N
    return -0.5 * (N * np.log(np.maximum(quad, 1e-300) / N) + logdet + N * (1.0 + _LOG2PI))


def _log_evidence_tsvd(d: _Svd, lams: NDArray, noise_known: bool) -> tuple[NDArray, NDArray]:
    """Evidence of the truncated models k = 1..p, each maximised over the prior ratio ``lam``."""
    b2 = d.beta**2
    g = 1.0 + d.s[None, :] ** 2 / lams[:, None]  # (n_lam, p)
    kept_quad = np.cumsum(b2[None, :] / g, axis=1)  # sum_{i<=k} beta^2 / g
    rest = np.sum(b2) - np.cumsum(b2)  # sum_{i>k} beta^2
    quad = kept_quad + rest[None, :] + d.c_perp
    logdet = np.cumsum(np.log(g), axis=1)
    N = d.n_rows
    if noise_known:
        ev = -0.5 * (quad + logdet + N * _LOG2PI)
    else:
        ev = -0.5 * (N * np.log(np.maximum(quad, 1e-300) / N) + logdet + N * (1.0 + _LOG2PI))
    best = np.argmax(ev, axis=0)
    return ev[best, np.arange(ev.shape[1])], lams[best]


def evidence_lambda(A: ArrayLike, z: ArrayLike, *, noise_known: bool = True, n_grid: int = 241) -> float:
    """The ridge ``lam`` that maximises the evidence of ``z = A x + e``, ``x ~ N(0, I / lam)``, ``e ~ N(0, I)``.

    ``lam`` is the noise-to-prior variance ratio (dimensionless); with rows
    whitened by the instrument sigma and columns scaled by the tolerances,
    ``1 / sqrt(lam)`` is the prior scale the data support, in tolerances.
    Searched over :func:`lambda_grid` (``n_grid`` points, about 0.1 decade apart).
    """
    d = _svd(np.asarray(A, dtype=float), np.asarray(z, dtype=float).reshape(-1))
    grid = lambda_grid(d.s, n_grid)
    return float(grid[int(np.argmax(_log_evidence_ridge(d, grid, noise_known)))])


def _log_lambda_posterior(d: _Svd, lams: NDArray, noise_known: bool, hyperprior: ScaleHyperprior) -> NDArray:
    """Log posterior of ``lam`` on a log-spaced grid: log evidence + log hyperprior of ``log c``, up to a constant.

    ``c^2 = sigma2 / lam`` is the prior scale in tolerances; ``sigma2 = 1``
    for whitened rows, else the noise scale profiled at each ``lam``.  On a
    log grid ``d log c = -d log lam / 2`` (known noise), a constant factor.
    """
    log_ev = _log_evidence_ridge(d, lams, noise_known)
    if noise_known:
        log_sigma2 = np.zeros(lams.size)
    else:
        g = 1.0 + d.s[None, :] ** 2 / lams[:, None]
        quad = np.sum(d.beta[None, :] ** 2 / g, axis=1) + d.c_perp
        log_sigma2 = np.log(np.maximum(quad, 1e-300) / d.n_rows)
    return log_ev + hyperprior.log_density(0.5 * (log_sigma2 - np.log(lams)))


def lambda_posterior(
    A: ArrayLike, z: ArrayLike, *, hyperprior: ScaleHyperprior = DEFAULT_HYPERPRIOR, noise_known: bool = True,
    n_grid: int = 241,
) -> tuple[NDArray, NDArray]:
    """Posterior probabilities of the ridge ``lam`` over :func:`lambda_grid`: evidence times the hyperprior on the scale.

    Parameters
    ----------
    A : array_like, shape (N, p)
        Whitened, tolerance-scaled identification matrix.
    z : array_like, shape (N,)
        Whitened right-hand side.
    hyperprior : ScaleHyperprior
        Density of the prior scale ``c = sqrt(sigma2 / lam)`` (tolerances).
    noise_known : bool
        Rows whitened by a known sigma (else the noise scale is profiled out).
    n_grid : int
        Grid points (about 0.1 decade apart for 241).

    Returns
    -------
    grid : ndarray, shape (n_grid,)
        ``lam`` values, ascending (dimensionless).
    weights : ndarray, shape (n_grid,)
        Posterior probability of each grid value (sum 1).
    """
    d = _svd(np.asarray(A, dtype=float), np.asarray(z, dtype=float).reshape(-1))
    grid = lambda_grid(d.s, n_grid)
    lp = _log_lambda_posterior(d, grid, noise_known, hyperprior)
    w = np.exp(lp - lp.max())
    return grid, w / w.sum()


def _posterior_risk(d: _Svd, F: NDArray, noise_known: bool) -> tuple[float, NDArray]:
    """Posterior expected ``|x_v - x|^2`` of each filtered solution under the empirical-Bayes prior.

    The prior ``x ~ N(0, I / lam_ev)`` with ``lam_ev`` maximising the ridge
    evidence over a fine grid.  In the right singular vectors the posterior
    is independent per direction: mean ``m_i = s_i beta_i / (s_i^2 + lam_ev)``,
    variance ``sigma2 / (s_i^2 + lam_ev)`` (``sigma2 = 1`` for whitened rows,
    else the profiled noise scale), plus ``1 / lam_ev`` per unseen dimension
    (``p > rank``).  Returns ``lam_ev`` and the risk over the filter rows.
    """
    grid = lambda_grid(d.s)
    ev = _log_evidence_ridge(d, grid, noise_known)
    lam_ev = float(grid[int(np.argmax(ev))])
    g = d.s**2 + lam_ev
    m = d.s * d.beta / g
    if noise_known:
        sigma2 = 1.0
    else:
        quad = float(np.sum(d.beta**2 / (1.0 + d.s**2 / lam_ev)) + d.c_perp)
        sigma2 = quad / d.n_rows
    unseen = d.V.shape[0] - d.s.size
    trace = sigma2 * float(np.sum(1.0 / g)) + unseen * sigma2 / lam_ev
    est = F * (d.beta * _safe_inv(d.s))[None, :]
    return lam_ev, np.sum((est - m[None, :]) ** 2, axis=1) + trace


def _success_curve(
    A: NDArray, d: _Svd, F: NDArray, noise_known: bool, G: NDArray | None, ratio: float, n_posterior: int, seed: int,
    integrate_scale: bool = True, hyperprior: ScaleHyperprior = DEFAULT_HYPERPRIOR,
) -> tuple[float, NDArray, NDArray]:
    """``lam_ev`` and, per filter row, the posterior probability of success and expected ratio to the best.

    ``integrate_scale``: the prior ratio ``lam`` is drawn per posterior draw
    from its own posterior (evidence times ``hyperprior`` over
    :func:`lambda_grid`) instead of being fixed at the evidence maximum
    ``lam_ev``: the evidence of one scale from a few dozen parameters is
    uncertain by tens of per cent.
    """
    grid = lambda_grid(d.s)
    log_ev = _log_evidence_ridge(d, grid, noise_known)
    lam_ev = float(grid[int(np.argmax(log_ev))])
    rng = np.random.default_rng([seed, 1])
    if integrate_scale:
        lp = _log_lambda_posterior(d, grid, noise_known, hyperprior)
        w = np.exp(lp - lp.max())
        lam = grid[rng.choice(grid.size, size=n_posterior, p=w / w.sum())]
    else:
        lam = np.full(n_posterior, lam_ev)
    g = d.s[None, :] ** 2 + lam[:, None]  # (n_posterior, r)
    if noise_known:
        sigma2 = np.ones(n_posterior)
    else:  # the profiled noise scale at each lam
        sigma2 = (np.sum(d.beta[None, :] ** 2 / (1.0 + d.s[None, :] ** 2 / lam[:, None]), axis=1) + d.c_perp) / d.n_rows
    m = d.s[None, :] * d.beta[None, :] / g
    sd = np.sqrt(sigma2[:, None] / g)
    p, r = A.shape[1], d.s.size
    if p > r:  # directions A does not see: estimates stay 0 there, the posterior is the prior
        # an orthonormal complement of the same V: a second SVD call may flip the signs of its vectors
        import scipy.linalg

        V = np.hstack([d.V, scipy.linalg.null_space(d.V.T)])
        m = np.hstack([m, np.zeros((n_posterior, p - r))])
        sd = np.hstack([sd, np.repeat(np.sqrt(sigma2 / lam)[:, None], p - r, axis=1)])
    else:
        V = d.V
    GV = V if G is None else np.asarray(G, dtype=float) @ V
    if GV.shape[0] > p:  # |GV e| = |R e| with GV = Q R: fewer rows, same answer
        GV = np.linalg.qr(GV, mode="r")
    est = F * (d.beta * _safe_inv(d.s))[None, :]
    prob, exp_ratio = success_probabilities(est, m, sd, GV, ratio=ratio, n_posterior=n_posterior, seed=seed)
    return lam_ev, prob, exp_ratio


def _ridge_curvature(d: _Svd, lams: NDArray) -> NDArray:
    """Signed curvature of ``(log |r|, log |x|)`` against ``t = log lam``, analytic.

    With ``f = s^2 / (s^2 + lam)``: ``df/dt = -f (1 - f)``.  Positive at the
    L corner (the curve turns counter-clockwise when lam grows).
    """
    F = _filters("ridge", d.s, lams)
    b2 = d.beta[None, :] ** 2
    is2 = _safe_inv(d.s)[None, :] ** 2
    rho2 = np.sum((1 - F) ** 2 * b2, axis=1) + d.c_perp
    eta2 = np.sum(F**2 * b2 * is2, axis=1)
    drho2 = np.sum(2 * F * (1 - F) ** 2 * b2, axis=1)
    ddrho2 = np.sum(-2 * F * (1 - F) ** 2 * (1 - 3 * F) * b2, axis=1)
    deta2 = np.sum(-2 * F**2 * (1 - F) * b2 * is2, axis=1)
    ddeta2 = np.sum(2 * F**2 * (1 - F) * (2 - 3 * F) * b2 * is2, axis=1)
    rho2 = np.maximum(rho2, 1e-300)
    eta2 = np.maximum(eta2, 1e-300)
    R1, H1 = drho2 / (2 * rho2), deta2 / (2 * eta2)
    R2 = ddrho2 / (2 * rho2) - drho2**2 / (2 * rho2**2)
    H2 = ddeta2 / (2 * eta2) - deta2**2 / (2 * eta2**2)
    den = np.maximum((R1**2 + H1**2) ** 1.5, 1e-300)
    return (R1 * H2 - R2 * H1) / den


def _menger_curvature(x: NDArray, y: NDArray) -> NDArray:
    """Signed curvature of the circle through consecutive points (ends: -inf)."""
    kappa = np.full(x.size, -np.inf)
    if x.size < 3:
        return kappa
    ax, ay = x[1:-1] - x[:-2], y[1:-1] - y[:-2]
    bx, by = x[2:] - x[1:-1], y[2:] - y[1:-1]
    cx, cy = x[2:] - x[:-2], y[2:] - y[:-2]
    cross = ax * by - ay * bx
    den = np.hypot(ax, ay) * np.hypot(bx, by) * np.hypot(cx, cy)
    with np.errstate(divide="ignore", invalid="ignore"):
        kappa[1:-1] = np.where(den > 0, 2 * cross / np.where(den > 0, den, 1.0), -np.inf)
    return kappa


def _cv_curve(A: NDArray, z: NDArray, groups: NDArray, method: str, grid: NDArray, folds: int, seed: int) -> tuple[NDArray, int]:
    """Mean squared held-out (whitened) prediction error, K-fold over groups (poses)."""
    labels = np.unique(groups)
    K = int(min(folds, labels.size))
    if K < 2:
        return np.full(grid.size, np.nan), 0
    perm = np.random.default_rng(seed).permutation(labels)
    fold_of = {g: i % K for i, g in enumerate(perm)}
    fold = np.array([fold_of[g] for g in groups])
    sse = np.zeros(grid.size)
    for i in range(K):
        te = fold == i
        d = _svd(A[~te], z[~te])
        if method == "tsvd":
            # a training fold may have fewer rows than parameters
            g = np.minimum(grid, d.s.size)
            F = (np.arange(d.s.size)[None, :] < g[:, None]).astype(float)
        else:
            F = _filters(method, d.s, grid)
        X = _solutions(d, F)
        err = z[te][:, None] - A[te] @ X
        sse += np.sum(err**2, axis=0)
    return sse / A.shape[0], K


def choose_linear(
    A: ArrayLike, z: ArrayLike, method: str, *, rule: str | None = None, groups: ArrayLike | None = None,
    noise_known: bool = True, grid: ArrayLike | None = None, folds: int = 6, seed: int = 0,
    linearisation: str = "given linear problem", output_map: ArrayLike | None = None, ratio: float = 1.1,
    n_posterior: int = N_POSTERIOR, integrate_scale: bool = True, hyperprior: ScaleHyperprior | None = None,
    target_rule: TargetRule | None = None, target_calibration: dict | None = None,
) -> RegularisationChoice:
    """Apply every rule to the linear problem ``A x ~ z`` (rows whitened).

    Parameters
    ----------
    A : array_like, shape (N, p)
        Whitened, column-scaled identification matrix.
    z : array_like, shape (N,)
        Whitened right-hand side (for the total deviation from nominal).
    method : {"ridge", "tsvd"}
    rule : str, optional
        One of :data:`RULES`; :data:`DEFAULT_RULE` by default.
    groups : array_like of int, shape (N,), optional
        Which pose each row belongs to (cross-validation holds out whole poses).  Default: every row its own group.
    noise_known : bool
        Whether the rows are whitened by a known sigma (else the evidence profiles out a noise scale).
    grid : array_like, optional
        ``lam`` values (ridge) or ``k`` values (TSVD); default :func:`lambda_grid` or ``1..p``.
    folds : int
        Cross-validation folds.
    seed : int
        Seeds the assignment of poses to folds and the posterior draws of ``success``.
    linearisation : str
        Where the linear problem was taken (for the report).
    output_map : array_like, shape (M, p), optional
        ``G``: the output error of an estimate is ``|G (x_v - x)|`` (for example tool-point Jacobians times the
        tolerances, mm per scaled unit; only ratios matter).  Default: the scaled parameter error.
    ratio : float
        The ``success`` rule's event: output error at most ``ratio`` times the best candidate's.
    n_posterior : int
        Posterior draws of the ``success`` rule.
    integrate_scale : bool
        ``success``: average over the posterior of the prior scale (True), else plug in its evidence maximum.
    hyperprior : ScaleHyperprior, optional
        ``success``: the hyperprior on the prior scale that, times the evidence, gives the posterior of ``lam``
        (default :data:`bayescal.identify.scale_prior.DEFAULT_HYPERPRIOR`;
        :data:`~bayescal.identify.scale_prior.FLAT_HYPERPRIOR` for flat in ``log lam``).
    target_rule : TargetRule, optional
        ``targets``: the rule calibrated for this design (for example by
        :func:`bayescal.identify.target_rule.calibrate_target_rule`, when many data sets share one design); by default
        calibrated here (and cached), which it is only when ``rule`` is ``"targets"``.
    target_calibration : dict, optional
        Keyword arguments of the calibration done here (:func:`~bayescal.identify.target_rule.calibrate_target_rule`:
        ``n_data``, ``calibration_draws``, ``n_draws``, ``margin``, ``scales``, ``targets``, ``seed``).

    Returns
    -------
    RegularisationChoice
        With ``rule="targets"`` (or ``target_rule``), ``curves["targets_score"]`` holds the rule's Lagrangian per
        candidate and ``target_rule`` its calibration (weights, relaxations, what it achieved on its sample).
    """
    A, z, rule = _checked_problem(A, z, method, rule)
    N, p = A.shape
    groups = np.arange(N) if groups is None else np.asarray(groups).reshape(-1)
    d = _svd(A, z)
    _check_noise_estimable(A, z, d, noise_known, method)
    grid = _candidate_grid(method, d, grid)
    output_map = _checked_success_options(output_map, ratio, p)
    success = (output_map, ratio, n_posterior, integrate_scale, DEFAULT_HYPERPRIOR if hyperprior is None else hyperprior)
    curves, i_disc, K = _rule_curves(A, z, d, groups, method, grid, folds, seed, noise_known, success)
    picks = _rule_picks(method, curves, i_disc)
    calibration = None
    if rule == "targets" or target_rule is not None:
        picks["targets"], curves["targets_score"], calibration = _targets_pick(
            A, z, d, method, grid, output_map, noise_known, target_rule, seed, target_calibration or {})
    cast = float if method == "ridge" else int
    choices = {r: cast(grid[i]) for r, i in picks.items() if i is not None}
    if rule not in choices:
        raise InputError(f"rule {rule!r}: needs at least two poses for cross-validation")
    return RegularisationChoice(
        method=method, rule=rule, value=choices[rule], choices=choices, grid=np.asarray(grid), curves=curves,
        singular_values=d.s, n_rows=N, n_params=p, noise_known=noise_known, linearisation=linearisation, folds=K,
        target_rule=calibration,
    )


def _rule_curves(A, z, d, groups, method: str, grid, folds: int, seed: int, noise_known: bool, success: tuple):
    """Every rule's curve over the candidates ``grid`` (the choice's ``curves``), the discrepancy's pick and folds.

    ``success``: ``(output_map, ratio, n_posterior, integrate_scale, hyperprior)`` of the success rule.
    """
    N = A.shape[0]
    F = _filters(method, d.s, grid)
    res2, xnorm2, peff, gcv, disc = _fit_curves(d, F, N)
    cv, K = _cv_curve(A, z, groups, method, grid, folds, seed)
    curvature, log_ev, i_disc, extras = _corner_and_evidence(method, d, grid, res2, xnorm2, disc, noise_known)
    lam_ev, risk = _posterior_risk(d, F, noise_known)
    extras["risk_prior_ratio"] = lam_ev
    output_map, ratio, n_posterior, integrate_scale, hyperprior = success
    _, succ, exp_ratio = _success_curve(A, d, F, noise_known, output_map, ratio, n_posterior, seed, integrate_scale,
                                        hyperprior)
    extras["success_expected_ratio"] = exp_ratio
    curves = dict(residual_norm=np.sqrt(res2), solution_norm=np.sqrt(xnorm2), effective_parameters=peff, gcv=gcv,
                  cv=cv, discrepancy=disc, log_evidence=log_ev, curvature=curvature, posterior_risk=risk,
                  success_probability=succ, **extras)
    return curves, i_disc, K


def _rule_picks(method: str, curves: dict, i_disc) -> dict:
    """The candidate index each rule picks from its curve (None: the rule has no answer, cv with one pose)."""
    cv, curvature, risk = curves["cv"], curves["curvature"], curves["posterior_risk"]
    return {
        "cv": int(np.nanargmin(cv)) if np.isfinite(cv).any() else None,
        "lcurve": int(np.argmax(np.where(np.isfinite(curvature), curvature, -np.inf))),
        "gcv": int(np.argmin(curves["gcv"])),
        "discrepancy": i_disc,
        "evidence": int(np.argmax(curves["log_evidence"])),
        # ties (TSVD: directions with beta_i = 0) go to the most regularised value
        "risk": int(np.flatnonzero(risk <= risk.min() * (1 + 1e-12))[0 if method == "tsvd" else -1]),
        # largest probability; ties (common for neighbouring lambdas) to the smaller expected ratio
        "success": int(np.lexsort((curves["success_expected_ratio"], -curves["success_probability"]))[0]),
    }


def _checked_problem(A: ArrayLike, z: ArrayLike, method: str, rule: str | None) -> tuple[NDArray, NDArray, str]:
    """``A`` and ``z`` as float arrays and the rule (the method's default if None), or a clear refusal."""
    if method not in ("ridge", "tsvd"):
        raise InputError(f"method: automatic choice is for 'ridge' or 'tsvd', got {method!r}")
    rule = DEFAULT_RULE[method] if rule is None else rule
    if rule not in RULE_NAMES:
        raise InputError(f"rule: expected one of {', '.join(RULE_NAMES)}, got {rule!r}")
    A = np.asarray(A, dtype=float)
    z = np.asarray(z, dtype=float).reshape(-1)
    if A.ndim != 2 or A.shape[0] != z.size:
        raise InputError(f"A, z: expected shapes (N, p) and (N,), got {A.shape} and {z.shape}")
    return A, z, rule


def _candidate_grid(method: str, d: _Svd, grid: ArrayLike | None) -> NDArray:
    """The candidates: ``lam`` (ridge, sorted; default :func:`lambda_grid`) or ranks ``k`` (TSVD; default ``1..p``)."""
    if method == "ridge":
        grid = lambda_grid(d.s) if grid is None else np.sort(np.asarray(grid, dtype=float))
        if np.any(grid <= 0):
            raise InputError("grid: ridge parameters must be positive")
    else:
        grid = np.arange(1, d.s.size + 1) if grid is None else np.asarray(grid, dtype=int)
        if np.any(grid < 1) or np.any(grid > d.s.size):
            raise InputError(f"grid: k must be from 1 to {d.s.size}")
    return grid


def _fit_curves(d: _Svd, F: NDArray, N: int) -> tuple[NDArray, NDArray, NDArray, NDArray, NDArray]:
    """Per candidate: squared residual and solution norms, effective parameters, GCV and the discrepancy."""
    b2 = d.beta[None, :] ** 2
    res2 = np.sum((1 - F) ** 2 * b2, axis=1) + d.c_perp
    xnorm2 = np.sum(F**2 * b2 * _safe_inv(d.s)[None, :] ** 2, axis=1)
    peff = F.sum(axis=1)
    with np.errstate(divide="ignore"):
        gcv = res2 / np.maximum(N - peff, 1e-12) ** 2
    disc = res2 - (N - peff)
    return res2, xnorm2, peff, gcv, disc


def _corner_and_evidence(method: str, d: _Svd, grid: NDArray, res2: NDArray, xnorm2: NDArray, disc: NDArray,
                         noise_known: bool) -> tuple[NDArray, NDArray, int, dict]:
    """The L-curve's curvature, the log evidence, the discrepancy principle's pick and the extra curves (TSVD)."""
    rho, eta = 0.5 * np.log(np.maximum(res2, 1e-300)), 0.5 * np.log(np.maximum(xnorm2, 1e-300))
    extras: dict = {}
    if method == "ridge":
        curvature = _ridge_curvature(d, grid)
        log_ev = _log_evidence_ridge(d, grid, noise_known)
        # the discrepancy principle: most regularised lam with |r|^2 <= N - sum f
        ok = np.flatnonzero(disc <= 0)
        i_disc = int(ok[-1]) if ok.size else int(np.argmin(disc))
    else:
        # order by increasing regularisation (decreasing k) so the corner turns the same way as ridge's
        curvature = _menger_curvature(rho[::-1], eta[::-1])[::-1]
        log_ev, lam_k = _log_evidence_tsvd(d, lambda_grid(d.s, 121), noise_known)
        log_ev = log_ev[grid - 1]
        extras["evidence_prior_ratio"] = lam_k[grid - 1]
        ok = np.flatnonzero(disc <= 0)
        i_disc = int(ok[0]) if ok.size else int(np.argmin(disc))
    return curvature, log_ev, i_disc, extras


def _checked_success_options(output_map: ArrayLike | None, ratio: float, p: int) -> NDArray | None:
    """The ``success`` rule's output map (as floats) and ratio, checked."""
    if output_map is not None:
        output_map = np.asarray(output_map, dtype=float)
        if output_map.ndim != 2 or output_map.shape[1] != p:
            raise InputError(f"output_map: expected shape (M, {p}), got {output_map.shape}")
    if not ratio >= 1.0:
        raise InputError(f"ratio: expected >= 1, got {ratio}")
    return output_map


# the calibration of ``targets`` depends only on the design (and the calibration options): keep the last few.
# Looked up by the design's fingerprint (singular values, output Gram matrix, within 1e-6), not by the bytes
# of A: a recording's Jacobian recomputed for another data set (a forward solve started elsewhere) differs
# in the last digits, and a byte key missed it every time
_TARGET_RULES: list = []
_TARGET_RULES_KEPT = 8


def _residual_sigma(d: _Svd) -> float:
    """The noise scale of the unregularised fit: its residual over ``N - rank`` degrees of freedom."""
    seen = d.s > 1e-12 * d.s[0]
    dof = d.n_rows - int(np.sum(seen))
    # what U^T z leaves, plus the directions A does not reach (zero singular values)
    resid = d.c_perp + float(np.sum(d.beta[~seen] ** 2))
    if dof < 1 or resid <= 0:
        raise InputError("rule 'targets': without an instrument sigma in the machine file it needs more "
                         f"rows than parameters and a non-zero residual ({d.n_rows} rows, {d.s.size} parameters)")
    return float(np.sqrt(resid / dof))


def _targets_pick(A, z, d, method, grid, output_map, noise_known, target_rule, seed, calibration):
    """The ``targets`` rule's pick, its scores and its calibration (calibrated here if not given)."""
    sigma = 1.0 if noise_known else _residual_sigma(d)  # else whiten by the unregularised fit's noise scale
    design = rule_design(A / sigma, method, grid, output_map)
    if target_rule is None:
        options = repr(sorted(calibration.items()))
        target_rule = next((r for o, r in reversed(_TARGET_RULES) if o == options and r.fits(design)), None)
        if target_rule is None:
            # a property of the design, so its own fixed seed; ``seed`` seeds the draws for these data
            target_rule = calibrate_target_rule(A / sigma, method, grid, output_map=output_map, **calibration)
            _TARGET_RULES.append((options, target_rule))
            del _TARGET_RULES[:-_TARGET_RULES_KEPT]
    i, scores = target_rule.choose(design, design.U.T @ (z / sigma), seed=[seed, 2])
    return i, scores, target_rule.to_dict()


# ------------------------------------------------------- nonlinear problems
def linearised_problem(model: MeasurementModel, theta: NDArray, idx: NDArray, scale: NDArray) -> tuple[NDArray, NDArray, NDArray]:
    """``A = W J S`` (free columns), ``z = W (y - h) + A theta/S`` and the pose of each row, at ``theta``."""
    pred = model.predict(theta)
    if not pred.success.all():
        i = int(np.flatnonzero(~pred.success)[0])
        raise InputError(f"pose {i + 1}: {pred.poses.message[i]} at the linearisation point")
    r, J = whitened_system(model, theta, pred)
    S = scale[idx]
    A = J[:, idx] * S
    z = r + A @ (theta[idx] / S)
    groups = np.repeat(np.arange(model.n_poses), model.dof)
    return A, z, groups


def _tool_output_map(machine, q: ArrayLike, idx: NDArray, scale: NDArray) -> NDArray | None:
    """Tool-point Jacobians at ``q`` (nominal geometry), tolerance-scaled: mm per scaled unit, shape (3 n, |idx|).

    None (the ``success`` rule then judges the scaled parameter error) when a
    pose cannot be solved at nominal.
    """
    if q is None:
        return None
    q = np.atleast_2d(np.asarray(q, dtype=float))
    poses = machine.forward(q)
    if not np.all(poses.success):
        return None
    J = machine.tool_jacobian(q, None, poses)[:, :3, :][:, :, idx] * scale[idx]
    return J.reshape(-1, idx.size)


def choose_regularisation(
    model: MeasurementModel,
    method: str,
    *,
    rule: str | None = None,
    free: ArrayLike | str | None = None,
    theta0: ArrayLike | None = None,
    scale: ArrayLike | None = None,
    folds: int = 6,
    seed: int = 0,
    max_rounds: int = 3,
    max_iter: int = 50,
    eval_q: ArrayLike | None = None,
    hyperprior: ScaleHyperprior | None = None,
    target_calibration: dict | None = None,
) -> tuple[RegularisationChoice, IdentificationResult]:
    """Choose ``lam`` (ridge) or ``k`` (TSVD) for a measurement model, and identify with it.

    Ridge: a pilot fit with ``lam = 1`` (MAP under the tolerance prior); then
    up to ``max_rounds`` times: linearise at the converged solution, apply the
    rules, re-solve with the chosen ``lam`` (warm start).  Stops when ``lam``
    changes by less than 10 %.  TSVD: the rules are applied once, at the
    start geometry, where TSVD fixes its subspace; then TSVD runs with the
    chosen ``k``.

    The ``success`` rule judges candidates by the tool-point error at the
    actuator positions ``eval_q`` (default: the measured poses), through the
    tool-point Jacobians at nominal, with the prior scale integrated over
    ``hyperprior`` (default :data:`~bayescal.identify.scale_prior.DEFAULT_HYPERPRIOR`).
    The ``targets`` rule judges them the same way; ``target_calibration``
    passes options to its calibration (see :func:`choose_linear`).

    Returns
    -------
    (RegularisationChoice, IdentificationResult)
        The result carries the choice in ``extras["regularisation"]``.
    """
    machine = model.machine
    P = machine.n_params
    if model.y_measured is None:
        raise InputError("identify: the measurement model has no measured values")
    theta = np.zeros(P) if theta0 is None else np.array(theta0, dtype=float).reshape(P)
    S_all = machine.tolerance if scale is None else np.asarray(scale, dtype=float).reshape(P)
    idx, _ = resolve_free(model, free, theta, prior=True)  # ridge and tsvd: what identify does with them
    free_arg = "auto" if free is None else free  # identify resolves it as here (and reports what it left)
    known = bool(machine.noise.given)
    kw = dict(rule=rule, noise_known=known, folds=folds, seed=seed, hyperprior=hyperprior,
              target_calibration=target_calibration,
              output_map=_tool_output_map(machine, model.q if eval_q is None else eval_q, idx, S_all))
    if method == "tsvd":
        A, z, groups = linearised_problem(model, theta, idx, S_all)
        choice = choose_linear(A, z, "tsvd", groups=groups, linearisation="linearised at the start geometry", **kw)
        res = identify(model, method="tsvd", k=int(choice.value), free=free_arg, theta0=theta, scale=scale, max_iter=max_iter)
    elif method == "ridge":
        res = identify(model, method="ridge", lam=1.0, free=free_arg, theta0=theta, scale=scale, max_iter=max_iter)
        first = res
        choice, rounds, lam_prev = None, 0, 1.0
        for rounds in range(1, max_rounds + 1):
            report(lambda: f"automatic lambda: round {rounds} of at most {max_rounds} (lambda {lam_prev:.3g})")
            # a failed fit is no place to linearise: fall back to the start
            A, z, groups = linearised_problem(model, res.theta if res.success else theta, idx, S_all)
            choice = choose_linear(
                A, z, "ridge", groups=groups,
                linearisation=f"linearised at the converged ridge solution (round {rounds})", **kw,
            )
            lam = float(choice.value)
            res = identify(model, method="ridge", lam=lam, free=free_arg, theta0=res.theta, scale=scale, max_iter=max_iter)
            if abs(np.log(lam / lam_prev)) < np.log(1.1) or not res.success:
                break
            lam_prev = lam
        choice = replace(choice, rounds=rounds)
        # the later rounds start from the earlier solution: report "before" against the start
        res = replace(res, rms_before=first.rms_before, residuals_before=first.residuals_before)
    else:
        raise InputError(f"method: automatic choice is for 'ridge' or 'tsvd', got {method!r}")
    res = replace(res, extras={**res.extras, "regularisation": choice.to_dict()})
    return choice, res
