"""The ``targets`` rule: lambda or k chosen to meet stated targets, calibrated on the recording's own design.

The ``success`` rule (:mod:`bayescal.identify.choose`) maximises one
number, the posterior probability that the chosen candidate is within 10 %
of the hindsight best.  A calibration engineer asks for three at once, at
every plausible quality of the machine:

* **gap**: the success probability at most ``gap`` below the best any rule
  could reach (``E[max_v p_v]``, the ceiling of :mod:`.ceiling`);
* **regret**: the expected ratio to the hindsight best at most ``regret``
  above the least any rule could reach (``E[min_v e_v]``);
* **tail**: ``P(ratio > tail_ratio)`` at most ``tail_share`` (p90 of the
  ratio at most ``tail_ratio`` when ``tail_share`` is 10 %);

for true machines at each of several scales ``c`` of the tolerances
(``x ~ N(0, c^2 I)`` in tolerance units; the rule is not told ``c``).

Rules reach a convex set of these averages, so by Lagrangian duality the
best compromise is an argmin: for a data set ``z`` it picks

    argmin_v  sum_c w_c(z) ( -a_c p_cv(z) + b_c e_cv(z) + g_c t_cv(z) ),

``p, e, t`` the success probability, expected ratio and tail probability
of candidate ``v`` under the posterior of prior scale ``c`` (Monte Carlo,
common draws), ``w_c(z) = p(z | c) / p_mix(z)`` how well scale ``c``
explains the data, and ``(a_c, b_c, g_c) >= 0`` Lagrange weights.  The
weights depend only on the design (``A``, the output map and the candidate
grid), not on the data, so they are *calibrated once per recording*:
:func:`calibrate_target_rule` simulates data sets from that design at every
scale and solves one linear programme (scipy's HiGHS) for the weights that
minimise the largest shortfall against the targets (the dual of "minimise
``t`` subject to every target missed by at most ``t``").  Where a rule that
knows the scale cannot meet a scale's tail target either (the least
``P(ratio > T)`` any rule has there is above ``tail_share``), that target is
first relaxed to the least attainable, so an impossible target does not
drag the others down; what still conflicts is borne by the relaxed scales
(the targets a rule knowing the scale could meet come first, tightened by
a small margin so that they hold on fresh data sets, not just on the
calibration sample).
``studies/choice_frontier.py`` derived this construction and
``studies/choice_rules.py`` measures the rule on held-out data sets
(docs/regularisation.md).

Everything is in the linear-Gaussian model of one Gauss-Newton step
(rows whitened, columns tolerance-scaled), the model the other rules use.
Written here because no library chooses a regularisation parameter under
several constraints at once; the linear programme is scipy's.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..errors import InputError
from .ceiling import ratios_to_best

__all__ = [
    "DEFAULT_SCALES",
    "RuleTargets",
    "default_targets",
    "TargetRule",
    "RuleDesign",
    "rule_design",
    "candidate_values",
    "scale_log_densities",
    "constraint_rows",
    "minimax_weights",
    "calibrate_target_rule",
]

#: Truth scales the rule must serve (tolerance multiples): machines made
#: better than the machine file says (0.5) up to four times worse.
DEFAULT_SCALES: tuple[float, ...] = (0.5, 1.0, 2.0, 4.0)

# the bound on a hard constraint's Lagrange weight (the soft ones sum to 1); feasibility is
# checked first, so the bound only has to exceed the largest multiplier a feasible problem needs
_HARD_BOUND = 1e7


@dataclass(frozen=True)
class RuleTargets:
    """What the ``targets`` rule is calibrated to deliver, at every truth scale.

    Attributes
    ----------
    gap : float
        Success probability at most this below the ceiling (0.03: 3 points).
    regret : float
        Expected ratio to the hindsight best at most this above the least attainable.
    tail_ratio : float
        ``T``: the ratio whose exceedance is bounded.
    tail_share : float
        ``P(ratio > T)`` at most this (0.10: p90 of the ratio at most ``T``).
    ratio : float
        The success event: output error at most ``ratio`` times the hindsight best's.
    """

    gap: float = 0.03
    regret: float = 0.02
    tail_ratio: float = 1.40
    tail_share: float = 0.10
    ratio: float = 1.1

    def __post_init__(self) -> None:
        for name in ("gap", "regret", "tail_share"):
            if not getattr(self, name) >= 0:
                raise InputError(f"{name}: expected >= 0, got {getattr(self, name)}")
        if not self.ratio >= 1.0 or not self.tail_ratio >= 1.0:
            raise InputError(f"ratio, tail_ratio: expected >= 1, got {self.ratio}, {self.tail_ratio}")

    def as_array(self) -> NDArray:
        """``(gap, regret, tail_share)``: the right-hand sides of the three constraints."""
        return np.array([self.gap, self.regret, self.tail_share])


def default_targets(method: str) -> RuleTargets:
    """The targets of issue 17 (``studies/choice_rules.py``): ridge regret 0.015, p90 1.25; TSVD 0.02, 1.40."""
    if method == "ridge":
        return RuleTargets(regret=0.015, tail_ratio=1.25)
    if method == "tsvd":
        return RuleTargets(regret=0.02, tail_ratio=1.40)
    raise InputError(f"method: expected 'ridge' or 'tsvd', got {method!r}")


@dataclass(frozen=True)
class RuleDesign:
    """A linear problem's design in its right singular coordinates: all the rule needs besides the data.

    Attributes
    ----------
    s : ndarray, shape (r,)
        Non-zero singular values of ``A`` (whitened, tolerance-scaled).
    U : ndarray, shape (N, r)
        Left singular vectors (``beta = U^T z``).
    RV : ndarray, shape (M, p)
        The output map in the right singular coordinates (QR-reduced: only
        ``|RV d|`` matters), the unseen directions last.
    F : ndarray, shape (n_candidates, r)
        Filter factors of the candidates.
    method : {"ridge", "tsvd"}
    grid : ndarray
        The candidates (``lam`` or ``k``).
    """

    s: NDArray
    U: NDArray
    RV: NDArray
    F: NDArray
    method: str
    grid: NDArray

    @property
    def p(self) -> int:
        """Number of parameters (the right singular coordinates, unseen ones included)."""
        return int(self.RV.shape[1])

    def estimates(self, beta: NDArray) -> NDArray:
        """Every candidate's estimate in the first ``r`` right singular coordinates, shape (n_candidates, r)."""
        return self.F * (beta / self.s)[None, :]


def rule_design(A: ArrayLike, method: str, grid: ArrayLike, output_map: ArrayLike | None = None) -> RuleDesign:
    """The :class:`RuleDesign` of ``A`` (whitened rows, scaled columns) for the candidates ``grid``.

    Parameters
    ----------
    A : array_like, shape (N, p)
    method : {"ridge", "tsvd"}
    grid : array_like
        ``lam`` values (ridge) or ``k`` values (TSVD).
    output_map : array_like, shape (M, p), optional
        ``G``: the output error of an estimate is ``|G (x_v - x)|``; default the identity.
    """
    A = np.asarray(A, dtype=float)
    if A.ndim != 2:
        raise InputError(f"A: expected a 2-D matrix, got shape {A.shape}")
    p = A.shape[1]
    U, s, Vt = np.linalg.svd(A, full_matrices=False)
    r = int(np.sum(s > 1e-12 * s[0])) if s.size and s[0] > 0 else 0
    if r == 0:
        raise InputError("A: no direction is observed (all singular values zero)")
    if Vt.shape[0] < p:  # fewer rows than parameters: the unseen directions complete V (estimates stay zero);
        # an orthonormal complement of the same V keeps U, s and V from one factorisation (a second
        # SVD call may flip signs)
        import scipy.linalg

        Vt = np.vstack([Vt, scipy.linalg.null_space(Vt).T])
    U, s = U[:, :r], s[:r]
    G = np.eye(p) if output_map is None else np.asarray(output_map, dtype=float)
    if G.ndim != 2 or G.shape[1] != p:
        raise InputError(f"output_map: expected shape (M, {p}), got {G.shape}")
    GV = G @ Vt.T
    RV = np.linalg.qr(GV, mode="r") if GV.shape[0] > p else GV
    grid = np.asarray(grid)
    if method == "ridge":
        F = s[None, :] ** 2 / (s[None, :] ** 2 + grid.astype(float)[:, None])
    elif method == "tsvd":
        F = (np.arange(r)[None, :] < grid.astype(int)[:, None]).astype(float)
    else:
        raise InputError(f"method: expected 'ridge' or 'tsvd', got {method!r}")
    return RuleDesign(s=s, U=U, RV=RV, F=F, method=method, grid=grid)


def candidate_values(design: RuleDesign, beta: NDArray, scales, targets: RuleTargets, n_draws: int,
                     seed) -> NDArray:
    """Success probability, expected ratio and tail probability of every candidate, under each scale's posterior.

    Parameters
    ----------
    design : RuleDesign
    beta : ndarray, shape (r,)
        ``U^T z`` of the data set (whitened).
    scales : sequence of float
        Prior scales ``c`` (tolerances): the truth ``x ~ N(0, c^2 I)``.
    targets : RuleTargets
        Its ``ratio`` and ``tail_ratio`` define the events.
    n_draws : int
        Posterior draws (the same standard normal draws serve every scale).
    seed : int or sequence of int
        Seeds the draws.

    Returns
    -------
    ndarray, shape (n_scales, n_candidates, 3)
        ``p_cv``, ``e_cv``, ``t_cv``.
    """
    s, p = design.s, design.p
    r = s.size
    z0 = np.random.default_rng(seed).standard_normal((n_draws, p))
    if design.method == "tsvd":
        return _tsvd_values(design, beta, scales, z0, targets)
    est = design.estimates(beta)
    # every scale's posterior draws in one array: one pass of the output errors for all of them
    truths = np.empty((len(scales), n_draws, p))
    for j, c in enumerate(scales):
        prec = s**2 + 1.0 / c**2
        mean = np.concatenate([s * beta / prec, np.zeros(p - r)])
        sd = np.concatenate([1.0 / np.sqrt(prec), np.full(p - r, float(c))])
        np.add(mean, sd * z0, out=truths[j])
    rel = ratios_to_best(truths.reshape(-1, p), est, design.RV).reshape(len(scales), n_draws, -1)
    out = np.empty((len(scales), est.shape[0], 3))
    # shares of draws as counts over n_draws: the same numbers as the mean of the booleans
    out[:, :, 0] = np.count_nonzero(rel <= targets.ratio, axis=1) / n_draws
    out[:, :, 1] = rel.mean(axis=1)
    out[:, :, 2] = np.count_nonzero(rel > targets.tail_ratio, axis=1) / n_draws
    return out


def _tsvd_values(design: RuleDesign, beta: NDArray, scales, z0: NDArray, targets: RuleTargets) -> NDArray:
    """:func:`candidate_values` for TSVD candidates: one product per draw, and no cancellation.

    The estimate of ``k`` is ``b = beta / s`` cut after ``k`` coordinates.
    Measured from the full estimate ``b`` (``k >= r``), a posterior draw is
    ``y = t - b`` and candidate ``k`` is off by ``f_k`` (``b``'s coordinates
    ``k..r-1``), so with ``H = RV^T RV`` its squared output error is
    ``y^T H y + 2 sum_{k<=i<r} (H y)_i b_i + f_k^T H f_k``: one product ``H y``
    per draw serves every ``k`` (cumulative sums from the end).  The general
    path forms ``|RV t|^2 - 2 (RV t).(RV e_k) + |RV e_k|^2``, which loses digits
    where ``s`` is large (``t`` is then ``b`` to within ``1/s``: on a 7-R arm
    with ``s`` up to 4e4, expected ratios off by up to 0.01); here ``y`` is
    formed directly (its seen part ``-b / (c^2 s^2 + 1) + z / sqrt(s^2 + 1/c^2)``)
    and every term is of the size of the error itself.  Candidates ``k >= r``
    are one estimate, valued once.  ``beta`` may be a stack of data sets
    (shape (B, r), ``z0`` (B, D, p)): the calibration values several per call.
    """
    s, p, r = design.s, design.p, design.s.size
    single = np.ndim(beta) == 1
    beta, z0 = np.atleast_2d(beta), z0[None] if single else z0
    B, D, S = beta.shape[0], z0.shape[1], len(scales)
    b = beta / s
    y = np.empty((B, S, D, p))
    for j, c in enumerate(scales):
        prec = s**2 + 1.0 / c**2
        sd = np.concatenate([1.0 / np.sqrt(prec), np.full(p - r, float(c))])
        np.multiply(sd, z0, out=y[:, j])
        y[:, j, :, :r] -= (b / (c**2 * prec))[:, None, :]
    H = design.RV.T @ design.RV
    Hy = y.reshape(-1, p) @ H
    q = np.einsum("ij,ij->i", y.reshape(-1, p), Hy).reshape(B, S * D, 1)
    # the distinct candidates (k = 0: the zero estimate; k >= r: b itself), and per draw the cross terms
    # sum_{k<=i<r} (H y)_i b_i for k = 0..r (the last one empty), cumulated from the end
    ks, inverse = np.unique(np.clip(np.asarray(design.grid).astype(int), 0, r), return_inverse=True)
    w = Hy[:, r - 1::-1].reshape(B, S * D, r)
    w *= b[:, None, ::-1]
    cross = np.zeros((B, S * D, r + 1))
    np.cumsum(w, axis=2, out=cross[:, :, 1:])  # cross[..., m]: the last m coordinates
    fHf = np.zeros((B, r + 1))
    bHb = b[:, ::-1, None] * H[r - 1::-1, r - 1::-1][None] * b[:, None, ::-1]
    fHf[:, 1:] = np.diagonal(np.cumsum(np.cumsum(bHb, axis=1), axis=2), axis1=1, axis2=2)
    err = cross[:, :, r - ks]
    err *= 2.0
    err += q
    err += fHf[:, None, r - ks]
    np.maximum(err, 0.0, out=err)
    best = err.min(axis=2, keepdims=True)
    # squared ratios, compared with the squared thresholds; where the best is 0, every ratio is 1 (as in
    # :func:`.ceiling.ratios_to_best`)
    if np.all(best > 0):
        err /= best
    else:
        with np.errstate(divide="ignore", invalid="ignore"):
            err = np.where(best > 0, err / np.where(best > 0, best, 1.0), 1.0)
    rel2 = err.reshape(B, S, D, -1)
    vals = np.empty((B, S, ks.size, 3))
    vals[..., 0] = np.count_nonzero(rel2 <= targets.ratio**2, axis=2) / D
    vals[..., 2] = np.count_nonzero(rel2 > targets.tail_ratio**2, axis=2) / D
    np.sqrt(rel2, out=rel2)
    vals[..., 1] = rel2.mean(axis=2)
    vals = vals[:, :, inverse]
    return vals[0] if single else vals


def scale_log_densities(s: NDArray, beta: NDArray, scales) -> NDArray:
    """``log p(z | c)`` per scale, up to a constant common to all scales: ``beta_i ~ N(0, c^2 s_i^2 + 1)``."""
    v = np.asarray(scales, dtype=float)[:, None] ** 2 * s[None, :] ** 2 + 1.0
    return -0.5 * np.sum(np.log(v) + beta[None, :] ** 2 / v, axis=1)


def _density_weights(logd: NDArray) -> NDArray:
    """``w_c = p(z | c) / mean_c' p(z | c')`` (the equal mixture of the scales), last axis the scales."""
    e = np.exp(logd - logd.max(axis=-1, keepdims=True))
    return e / e.mean(axis=-1, keepdims=True)


def constraint_rows(phi: NDArray, w: NDArray, targets: RuleTargets) -> NDArray:
    """``a[z, v, k]``: constraint ``k = (scale, target)`` of choosing ``v`` on data set ``z``, density-weighted.

    A rule meets every target at every scale when ``mean_z a[z, v(z), k] <= 0``
    for every ``k``, the data sets drawn from the equal mixture of the scales.

    Parameters
    ----------
    phi : ndarray, shape (n, S, V, 3)
        :func:`candidate_values` of every data set.
    w : ndarray, shape (n, S)
        Density weights ``p(z | c) / p_mix(z)``.
    targets : RuleTargets

    Returns
    -------
    ndarray, shape (n, V, 3 S)
        Constraint ``3 j + m`` is target ``m`` (gap, regret, tail) at scale ``j``.
    """
    gap = phi[..., 0].max(axis=2, keepdims=True) - phi[..., 0] - targets.gap
    reg = phi[..., 1] - phi[..., 1].min(axis=2, keepdims=True) - targets.regret
    tail = phi[..., 2] - targets.tail_share
    a = np.stack([gap, reg, tail], axis=-1) * w[:, :, None, None]
    n, S, V, _ = a.shape
    return a.transpose(0, 2, 1, 3).reshape(n, V, 3 * S)


def minimax_weights(a: NDArray, soft: NDArray | None = None, *, prune: bool = True) -> tuple[NDArray, float] | None:
    """Lagrange weights of "meet the hard constraints, minimise the largest soft one", by one linear programme.

    Over rules (randomised choices of ``v`` per data set) the programme
    ``min t`` subject to ``mean_z a[z, v(z), k] <= t`` (soft ``k``) and
    ``<= 0`` (hard ``k``) has the dual ``max mean_z min_v a[z, v] . lam``
    over ``lam >= 0`` with the soft weights summing to 1, solved here
    (scipy's HiGHS); the two values are equal.

    Parameters
    ----------
    a : ndarray, shape (n, V, K)
    soft : ndarray of bool, shape (K,), optional
        Which constraints are soft (default all; at least one must be).
    prune : bool
        With every constraint soft, leave out the rows of candidates that
        another candidate of the same data set beats in every constraint:
        they are implied (``lam >= 0``), so the programme is the same, and
        it is several times smaller.  Not with hard constraints: there the
        solver stops within its tolerance (1e-8) at a point that depends on
        the rows, and the feasibility test compares with 1e-12.

    Returns
    -------
    (lam, value) or None
        ``lam`` shape (K,), the soft part summing to 1; ``value`` the least
        largest soft constraint (``<= 0``: some rule meets them all on this
        sample).  None when the hard constraints cannot all be met on this
        sample (checked first, by this programme on the hard rows alone).
    """
    import scipy.optimize
    import scipy.sparse

    n, V, K = a.shape
    soft = np.ones(K, bool) if soft is None else np.asarray(soft, bool)
    if soft.shape != (K,) or not soft.any():
        raise InputError(f"soft: expected {K} flags, at least one True")
    if not soft.all() and minimax_weights(a[:, :, ~soft], prune=False)[1] > 1e-12:
        return None
    # the rows u_z <= a[z, v] . lam of candidates another candidate of the same data set beats in every
    # constraint are implied by that one's (lam >= 0): the programme without them has the same feasible
    # set, so the same solution, and is several times smaller (most candidates are beaten everywhere)
    z_idx, v_idx = np.nonzero(_undominated(a) if prune and soft.all() else np.ones((n, V), dtype=bool))
    m = z_idx.size
    lam_part = scipy.sparse.csr_matrix(-a[z_idx, v_idx])
    u_part = scipy.sparse.csr_matrix((np.ones(m), (np.arange(m), z_idx)), shape=(m, n))
    res = scipy.optimize.linprog(
        np.concatenate([np.zeros(K), -np.ones(n) / n]),
        A_ub=scipy.sparse.hstack([lam_part, u_part]).tocsr(), b_ub=np.zeros(m),
        A_eq=np.concatenate([soft.astype(float), np.zeros(n)])[None, :], b_eq=[1.0],
        bounds=[(0, None) if f else (0, _HARD_BOUND) for f in soft] + [(None, None)] * n, method="highs")
    if not res.success:
        raise RuntimeError(f"minimax_weights: the linear programme failed: {res.message}")
    lam = np.maximum(res.x[:K], 0.0)
    if np.any(lam[~soft] > 0.99 * _HARD_BOUND):  # feasible only at the edge: no usable weights
        return None
    return lam, float(-res.fun)


def _undominated(a: NDArray) -> NDArray:
    """``keep[z, v]``: no candidate ``u`` of data set ``z`` has ``a[z, u] <= a[z, v]`` everywhere and ``<`` somewhere,
    and none before ``v`` has ``a[z, u] == a[z, v]`` (a repeated row is implied by its first copy: TSVD's ``k``
    beyond the rank are one estimate)."""
    n, V, _ = a.shape
    keep = np.ones((n, V), dtype=bool)
    earlier = np.tril(np.ones((V, V), dtype=bool), -1)  # [v, u]: u before v
    step = max(1, 2_000_000 // max(V * V * a.shape[2], 1))  # data sets per block: a few MB of temporaries
    for z0 in range(0, n, step):
        az = a[z0:z0 + step]
        # [z, v, u]: candidate u at most candidate v in every constraint; and equal to it in every one
        le = np.all(az[:, None, :, :] <= az[:, :, None, :], axis=3)
        eq = np.all(az[:, None, :, :] == az[:, :, None, :], axis=3)
        beaten = (le & ~eq) | (eq & earlier)
        keep[z0:z0 + step] = ~beaten.any(axis=2)
    return keep


@dataclass(frozen=True)
class TargetRule:
    """The ``targets`` rule calibrated for one design: Lagrange weights per scale and target.

    Attributes
    ----------
    method : {"ridge", "tsvd"}
    grid : ndarray
        The candidates it was calibrated for.
    scales : tuple of float
        Truth scales (tolerances).
    weights : ndarray, shape (n_scales, 3)
        Lagrange weights of (gap, regret, tail) at each scale.
    targets : RuleTargets
    relaxed : tuple of float
        Per scale, how far its tail target was relaxed: the least
        ``P(ratio > T)`` a rule knowing the scale has on the calibration
        sample (reweighted to the scale), minus ``tail_share`` (0 where the
        target is attainable).
    shortfall : float
        The programme's value: the largest excess over the (relaxed)
        targets on the calibration sample (<= 0: every one met there).
    calibration : dict
        Per scale, the argmin rule's ``gap``, ``regret`` and ``tail`` on its
        own calibration sample; which ``programme`` gave the weights; and
        ``n_data`` (per scale), ``n_draws``, ``calibration_draws``, ``margin``, ``seed``.
    n_draws : int
        Posterior draws per scale (the rule uses as many as it was calibrated with).
    seed : int
    fingerprint : tuple
        The design it was calibrated on (singular values, output Gram
        matrix): :meth:`choose` refuses another.
    """

    method: str
    grid: NDArray
    scales: tuple[float, ...]
    weights: NDArray
    targets: RuleTargets
    relaxed: tuple[float, ...]
    shortfall: float
    calibration: dict = field(compare=False)
    n_draws: int = 600
    seed: int = 0
    fingerprint: tuple = field(default=(), compare=False, repr=False)

    def scores(self, phi: NDArray, logd: NDArray) -> NDArray:
        """The Lagrangian of every candidate (smaller is better) from :func:`candidate_values` and the log densities."""
        return _lagrangian(self.weights, _density_weights(logd), phi)

    def fits(self, design: RuleDesign) -> bool:
        """Whether this rule was calibrated on ``design`` (same method, grid, singular values and output Gram matrix)."""
        return (design.method == self.method and np.array_equal(np.asarray(design.grid, dtype=float),
                                                                np.asarray(self.grid, dtype=float))
                and bool(self.fingerprint) and _same_design(self.fingerprint, _fingerprint(design)))

    def choose(self, design: RuleDesign, beta: NDArray, seed=None) -> tuple[int, NDArray]:
        """Index into ``grid`` of the chosen candidate for the data ``beta = U^T z``, and the scores."""
        if design.method != self.method or design.grid.shape != self.grid.shape or \
                not np.allclose(design.grid, self.grid, rtol=1e-12, atol=0.0):
            raise InputError("target_rule: calibrated for another method or candidate grid")
        if self.fingerprint and not _same_design(self.fingerprint, _fingerprint(design)):
            raise InputError("target_rule: calibrated for another design (singular values or output map differ; "
                             "without an instrument sigma the design is whitened by the data's residual scale, "
                             "so a rule calibrated beforehand cannot apply)")
        phi = candidate_values(design, beta, self.scales, self.targets, self.n_draws,
                               [self.seed, 2] if seed is None else seed)
        sc = self.scores(phi, scale_log_densities(design.s, beta, self.scales))
        return int(np.argmin(sc)), sc

    def to_dict(self) -> dict:
        """JSON-ready: weights per scale and target, the targets, relaxations, shortfall and calibration."""
        return {"method": self.method, "scales": list(self.scales),
                "weights": {f"{c:g}": dict(zip(("gap", "regret", "tail"), map(float, self.weights[j])))
                            for j, c in enumerate(self.scales)},
                "targets": {"gap": self.targets.gap, "regret": self.targets.regret,
                            "tail_ratio": self.targets.tail_ratio, "tail_share": self.targets.tail_share,
                            "ratio": self.targets.ratio},
                "relaxed": dict(zip((f"{c:g}" for c in self.scales), self.relaxed)), "shortfall": self.shortfall,
                "calibration": self.calibration}


def _fingerprint(design: RuleDesign) -> tuple:
    """What identifies a design up to the signs of its singular vectors: ``s`` and the output map's Gram matrix."""
    return (design.s.copy(), design.RV.T @ design.RV)


def _same_design(a: tuple, b: tuple) -> bool:
    """Singular values equal to 1e-4 of each; output Gram matrices equal to 1e-4 of their largest entry.

    Not to the last digits: the Jacobian of a recording at the nominal geometry depends slightly on the
    measured values (the rotation residual's Jacobian on the measured orientation), so the same poses
    give designs whose singular values differ by up to 1e-6 of each and whose Gram matrices differ by up
    to 4e-7 of their largest entry from one data set to the next (seed2's repetitions, 5-DOF).  That is
    the same design for the calibration, whose own Monte Carlo error is far larger; another recording,
    or ``A`` whitened differently, differs by far more.  The Gram matrix is compared relative to its
    largest entry (its near-zero entries carry that noise too); each singular value relative to itself
    (the small ones set how much noise a candidate lets through), except those below 1e-9 of the largest,
    which are the numerical zeros of a rank-deficient design.
    """
    (s1, g1), (s2, g2) = a, b
    return (s1.shape == s2.shape and np.allclose(s1, s2, rtol=1e-4, atol=1e-9 * max(float(np.abs(s1).max()), 1e-300))
            and g1.shape == g2.shape and np.allclose(g1, g2, rtol=1e-4, atol=1e-4 * max(float(np.abs(g1).max()), 1e-300)))


def _lagrangian(weights: NDArray, w: NDArray, phi: NDArray) -> NDArray:
    """``sum_c w_c (-a_c p_cv + b_c e_cv + g_c t_cv)``; ``w`` shape (..., S), ``phi`` (..., S, V, 3) -> (..., V)."""
    # a vanishing weight on every constraint breaks ties (constraints with no weight still count a little)
    lam = weights + 1e-6 / weights.size
    return np.einsum("...s,...svk,sk->...v", w, phi * np.array([-1.0, 1.0, 1.0]), lam)


def _achieved(phi_c: NDArray, choice: NDArray, wc: NDArray) -> dict:
    """Gap, regret and tail of the choices at one scale, the data sets reweighted to it (self-normalised)."""
    d = np.arange(phi_c.shape[0])
    ww = wc / wc.sum()
    return {"gap": float(ww @ (phi_c[:, :, 0].max(axis=1) - phi_c[d, choice, 0])),
            "regret": float(ww @ (phi_c[d, choice, 1] - phi_c[:, :, 1].min(axis=1))),
            "tail": float(ww @ phi_c[d, choice, 2])}


def calibrate_target_rule(
    A: ArrayLike,
    method: str,
    grid: ArrayLike,
    *,
    output_map: ArrayLike | None = None,
    scales=DEFAULT_SCALES,
    targets: RuleTargets | None = None,
    n_data: int = 200,
    n_draws: int = 600,
    calibration_draws: int = 200,
    margin: float = 0.004,
    seed: int = 0,
) -> TargetRule:
    """Calibrate the ``targets`` rule for the design ``A`` by simulating data sets from it.

    ``n_data`` data sets per scale are drawn (``x ~ N(0, c^2 I)``,
    ``z = A x + e``, ``e ~ N(0, I)``); each is valued under every scale's
    posterior (:func:`candidate_values`).  A tail target no rule can meet
    at its scale, even knowing the scale, is relaxed to the least attainable
    tail.  Then one programme over the pooled, density-weighted data sets
    (:func:`constraint_rows`, :func:`minimax_weights`) gives the weights
    that minimise the largest excess over the targets, each tightened by
    ``margin``; if some excess remains and a tail was relaxed, a second
    programme meets the targets of the other scales and minimises the excess
    at the relaxed ones.

    Parameters
    ----------
    A : array_like, shape (N, p)
        Whitened, tolerance-scaled identification matrix (the recording's design).
    method : {"ridge", "tsvd"}
    grid : array_like
        Candidate ``lam`` (ridge) or ``k`` (TSVD) values.
    output_map : array_like, shape (M, p), optional
        ``G`` (tool-point Jacobians times tolerances); default the identity.
    scales : sequence of float
        Truth scales in tolerances (default :data:`DEFAULT_SCALES`).
    targets : RuleTargets, optional
        Default :func:`default_targets` of the method.
    n_data : int
        Simulated data sets per scale.
    n_draws : int
        Posterior draws per scale when the rule is applied to a recording's data.
    calibration_draws : int
        Posterior draws per scale for each simulated data set (the first ``calibration_draws`` of the
        ``n_draws`` the rule would take).  Fewer than ``n_draws``: the calibration averages its data sets'
        values, so their Monte Carlo error shrinks with the number of data sets, while the sample of data sets
        sets its accuracy.  At 200 draws the weights move far less than between calibration seeds at 600, and
        the chosen ``k`` of the bundled 3-PRS and of the 444-pose 7-R arm of ``benchmarks/identify_scale.py`` is
        the same for seeds 0-2 (``benchmarks/README.md``); the rule applied to the recording keeps ``n_draws``,
        where the Monte Carlo error of one data set decides.
    margin : float
        Every target tightened by this on the calibration sample (0.004: 0.4 point of gap or tail share, 0.004
        of regret, about one or two standard errors of a cell's estimate over 400 data sets).  It only changes
        the weights when the second programme runs (it shifts every constraint of the first alike); chosen on
        the 3-PRS 5-DOF situation of ``studies/choice_rules.py`` in an exploratory run with other seeds
        (docs/regularisation.md).
    seed : int

    Returns
    -------
    TargetRule
    """
    scales = _checked_scales(scales, margin, n_data, n_draws, calibration_draws)
    targets = default_targets(method) if targets is None else targets
    design = rule_design(A, method, grid, output_map)
    S = len(scales)
    phi, logd = _simulated_values(design, method, scales, targets, int(n_data), int(calibration_draws), seed)
    w = _density_weights(logd)
    lam, value, relax, programme = _target_programme(phi, w, targets, margin)
    rule = TargetRule(method=method, grid=np.asarray(design.grid), scales=scales, weights=lam.reshape(S, 3),
                      targets=targets, relaxed=tuple(float(x) for x in relax), shortfall=value, calibration={},
                      n_draws=int(n_draws), seed=int(seed), fingerprint=_fingerprint(design))
    choice = np.argmin(_lagrangian(rule.weights, w, phi), axis=1)
    per_scale = {f"{c:g}": _achieved(phi[:, j], choice, w[:, j]) for j, c in enumerate(scales)}
    calibration = {"per_scale": per_scale, "programme": programme, "n_data": int(n_data), "n_draws": int(n_draws),
                   "calibration_draws": int(calibration_draws),
                   "margin": float(margin), "seed": int(seed)}
    return TargetRule(**{**rule.__dict__, "calibration": calibration})


def _checked_scales(scales, margin, n_data, n_draws, calibration_draws) -> tuple[float, ...]:
    """The truth scales as floats, or InputError naming the option of :func:`calibrate_target_rule` out of range."""
    scales = tuple(float(c) for c in scales)
    if not scales or any(not c > 0 for c in scales):
        raise InputError(f"scales: expected positive tolerance multiples, got {scales}")
    if not 0 <= margin < 0.1:
        raise InputError(f"margin: expected from 0 to 0.1, got {margin}")
    if int(n_data) < 10 or int(n_draws) < 50 or int(calibration_draws) < 50:
        raise InputError(f"n_data, n_draws, calibration_draws: expected at least 10, 50 and 50, got {n_data}, "
                         f"{n_draws}, {calibration_draws}")
    return scales


def _simulated_values(design, method, scales, targets, n_data: int, calibration_draws: int, seed):
    """``n_data`` simulated data sets per scale, valued under every scale's posterior.

    Returns ``phi`` (n, S, n_candidates, 3) of :func:`candidate_values` and the data sets' log densities
    under each scale ``logd`` (n, S).
    """
    s, p, S = design.s, design.p, len(scales)
    rng = np.random.default_rng([seed, 1])
    n = n_data * S
    phi = np.empty((n, S, design.F.shape[0], 3))
    logd = np.empty((n, S))
    drawn_at = np.repeat(np.arange(S), n_data)
    betas = np.empty((n, s.size))
    for i in range(n):
        c = scales[drawn_at[i]]
        # the prior is isotropic, so the truth's right singular coordinates V^T x ~ N(0, c^2 I) too, and
        # beta = U^T z = s (V^T x)[:r] + U^T e with U^T e ~ N(0, I_r)
        betas[i] = s * (c * rng.standard_normal(p))[: s.size] + rng.standard_normal(s.size)
        logd[i] = scale_log_densities(s, betas[i], scales)
    if method == "tsvd":  # several data sets per call: the same numbers as one by one, less overhead
        block = 16
        for i0 in range(0, n, block):
            z0 = np.stack([np.random.default_rng([seed, 3, i]).standard_normal((calibration_draws, p))
                           for i in range(i0, min(i0 + block, n))])
            phi[i0:i0 + block] = _tsvd_values(design, betas[i0:i0 + block], scales, z0, targets)
    else:
        for i in range(n):
            phi[i] = candidate_values(design, betas[i], scales, targets, calibration_draws, [seed, 3, i])
    return phi, logd


def _target_programme(phi, w, targets, margin):
    """The rule's weights: ``(lam, value, relax, programme)`` of the minimax over the (relaxed, tightened) targets."""
    # the least tail any rule can have at each scale, knowing it (E_c[min_v t_cv], estimated like the
    # constraint rows: the pooled data sets reweighted to scale c): where it is above the target, that
    # target is relaxed to it, so an impossible target does not drag the others down (gap and regret
    # alone are always attainable: the success and the least-expected-ratio choices have zero gap and
    # zero regret)
    floor = (w * phi[:, :, :, 2].min(axis=2)).mean(axis=0) / w.mean(axis=0)
    relax = np.maximum(floor - targets.tail_share, 0.0)
    a = constraint_rows(phi, w, targets)
    a[:, :, 2::3] -= (relax[None, :] * w)[:, None, :]
    # every target tightened by the margin (density-weighted like the rows).  In the plain minimax a
    # common margin only shifts the value (the same weights); it matters in the second programme,
    # where the kept scales' targets are met exactly on the sample, which on fresh data sets would
    # hold about half the time
    a += float(margin) * np.repeat(w, 3, axis=1)[:, None, :]
    lam, value = minimax_weights(a)
    programme = "minimax over every target"
    if value > 0 and np.any(relax > 0) and not np.all(relax > 0):
        # the scales still conflict: meet the targets of the scales where a rule knowing the scale
        # can, and minimise the excess at the others
        second = minimax_weights(a, np.repeat(relax > 0, 3))
        if second is None:
            programme = "minimax over every target (the scales not relaxed cannot all be met together)"
        else:
            (lam, value), programme = second, "targets of the scales not relaxed met first"
    return lam, value, relax, programme

