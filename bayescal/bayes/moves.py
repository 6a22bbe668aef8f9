"""emcee moves for the posterior sampler.

:class:`SnookerMove` is Ter Braak & Vrugt's (2008) DE snooker update.  It
replaces emcee 3.1.6's :class:`emcee.moves.DESnookerMove`, whose proposal
projects on ``delta / sqrt(|delta|)`` instead of the unit vector
``delta / |delta|``: the step then scales with ``|delta|``, the proposal is
no longer symmetric along the snooker line, the ``(d - 1) log`` Jacobian
factor does not correct for it, and the chain does not leave the target
invariant.  On a 33-dimensional standard normal with 68 walkers, emcee's
move alone gives marginal standard deviations of about 0.73 instead of 1
(0.86 in an 0.8 DE / 0.2 snooker mix); this one gives 1 (see
tests/bayes/test_moves.py).

:class:`IndependenceMove` is an independence Metropolis-Hastings move: every
walker proposes a fresh draw from a fixed multivariate t distribution
centred at the MAP with the Laplace covariance as its scale matrix, and
accepts it with the Hastings factor ``log g(x) - log g(x')``.  When the
posterior is close to its Laplace approximation (the 3-PRS at its
tolerances: linearisation errors of 0.01 sigma) most proposals are accepted
and consecutive draws are nearly independent, whatever the dimension, where
the DE moves need a random walk of ~100 steps through 30+ dimensions.  Given a
:class:`~bayescal.bayes.bent_laplace.BentLaplace` map, the t draws are
pushed through it instead of the straight Laplace map, so the proposal
follows the curved valley of the directions the prior decides (the map's
Jacobian is constant, so the Hastings factor is the t's).  The
t's heavy tails keep the importance weights ``pi / g`` bounded for a
posterior with Gaussian tails (a uniformly ergodic chain).  When the
posterior is far from Gaussian its acceptance falls and the DE moves mixed
with it do the work; the mixture leaves the target invariant either way,
since each move does.  Where the posterior is nearly the map's Gaussian,
the t's tails waste half the proposals in 30+ dimensions; the proposal
``gaussian_weight`` Gaussian + the rest t (same map) is then accepted far
more often, and :func:`choose_proposal` decides from draws of the t whether
the posterior's tails allow it.
"""

from __future__ import annotations

import numpy as np
from emcee.moves import DEMove, DESnookerMove, MHMove
from numpy.typing import ArrayLike
from scipy import special

from .bent_laplace import BentLaplace

__all__ = ["SnookerMove", "IndependenceMove", "default_moves", "importance_efficiency", "largest_weights",
           "choose_proposal"]

#: Degrees of freedom of the independence proposal.  Heavier tails (smaller
#: df) make walkers less sticky where the posterior is wider than its Laplace
#: approximation (on a 4-D banana, df = 25 let single walkers stick in an arm
#: and gave a skewness of 2.5 instead of 0.44 at 5000 steps; df = 10 gives
#: the right moments, tau 6-12 steps); lighter tails accept more in 30+
#: dimensions when the posterior is Gaussian (3-PRS example: tau 1.9 steps
#: at df = 25, 2.6 at df = 10, 3.5 at df = 5).
T_DOF = 10.0
#: Weights of the default mixture (with a Laplace approximation).
IMH_WEIGHT, DE_WEIGHT, SNOOKER_WEIGHT = 0.9, 0.07, 0.03
#: Weight of the Gaussian in the independence proposal where :func:`choose_proposal` mixes it in (the rest: the t).
GAUSSIAN_WEIGHT = 0.9
#: The mixture is used only if its largest importance weight is at most this fraction of the t's (see
#: :func:`choose_proposal`): on the 3-PRS example and the positioner it is a half or less, on a banana 1 or more.
GAUSSIAN_GAIN = 0.75


class SnookerMove(DESnookerMove):
    """DE snooker move with the unit projection direction (see the module docstring).

    Parameters
    ----------
    gammas : float
        Step factor along the snooker line; 1.7 as recommended by Ter Braak & Vrugt.
    """

    def get_proposal(self, s, c, random):
        ns = len(s)
        nc = list(map(len, c))
        ndim = s.shape[1]
        q = np.empty_like(s)
        metropolis = np.empty(ns, dtype=np.float64)
        for i in range(ns):
            w = np.array([c[j][random.randint(nc[j])] for j in range(3)])
            random.shuffle(w)
            z, z1, z2 = w
            delta = s[i] - z
            norm = np.linalg.norm(delta)
            e = delta / norm
            # x' = x + gamma ((z1 - z2) . e) e: a symmetric move along the line through z
            q[i] = s[i] + e * self.gammas * (np.dot(e, z1) - np.dot(e, z2))
            metropolis[i] = np.log(np.linalg.norm(q[i] - z)) - np.log(norm)
        return q, (ndim - 1.0) * metropolis


class IndependenceMove(MHMove):
    """Independence Metropolis-Hastings with a multivariate t proposal.

    Parameters
    ----------
    mean : array_like, shape (d,)
        Proposal centre (the MAP), mm or rad.
    cov : array_like, shape (d, d)
        Proposal scale matrix (the Laplace covariance), symmetric positive definite.
    df : float
        Degrees of freedom of the t (``inf``: a Gaussian).
    scale : float
        Factor on the scale matrix's square root (> 1 inflates the proposal).
    bend : BentLaplace, optional
        The Laplace approximation at ``mean`` bent along the prior-decided
        directions (:func:`~bayescal.bayes.bent_laplace.bent_laplace`): the t
        draws go through it instead of ``mean + chol(cov) z``.
    gaussian_weight : float
        In ``[0, 1)``: the proposal is this much the Gaussian (``df = inf``)
        and the rest the t, both through the same map (0: the t alone).

    Notes
    -----
    The proposal ``g`` does not depend on the current point, so the
    Metropolis-Hastings log ratio is ``log pi(x') - log pi(x) + log g(x) - log g(x')``;
    :meth:`get_proposal` returns ``log g(x) - log g(x')`` as emcee's
    ``log_factors``.  All walkers propose at once (one vectorised
    log-probability call per step).
    """

    def __init__(self, mean: ArrayLike, cov: ArrayLike, *, df: float = T_DOF, scale: float = 1.0,
                 bend: BentLaplace | None = None, gaussian_weight: float = 0.0):
        self.mean = np.asarray(mean, dtype=float).ravel()
        d = self.mean.size
        cov = np.asarray(cov, dtype=float).reshape(d, d)
        # the proposal is t(0, scale^2 I) pushed through x = map(w): linear, or bent along the prior-decided directions
        self.map = BentLaplace.linear(self.mean, np.linalg.cholesky(0.5 * (cov + cov.T))) if bend is None else bend
        if self.map.x0.shape != (d,) or not np.allclose(self.map.x0, self.mean, rtol=1e-12, atol=0.0):
            raise ValueError("bend: expected a map centred at mean (the MAP the bend was fitted at)")
        self.scale = float(scale)
        self.df = float(df)
        if not self.df > 0:
            raise ValueError(f"df: expected > 0, got {df}")
        self.gaussian_weight = float(gaussian_weight)
        if not 0.0 <= self.gaussian_weight < 1.0:
            raise ValueError(f"gaussian_weight: expected 0 <= weight < 1 (the t must keep some weight), got {gaussian_weight}")
        super().__init__(self._propose, ndim=d)

    def log_density(self, x: np.ndarray) -> np.ndarray:
        """Log proposal density at points ``x`` (k, d), including its constant."""
        d = self.mean.size
        z = self.map.to_w(x) / self.scale
        m2 = np.sum(z**2, axis=1)
        logdet = self.map.log_det + d * np.log(self.scale)  # the bend's Jacobian is that of its linear part
        gauss = -0.5 * m2 - logdet - 0.5 * d * np.log(2 * np.pi)
        if np.isinf(self.df):
            return gauss
        nu = self.df
        t = (special.gammaln(0.5 * (nu + d)) - special.gammaln(0.5 * nu) - 0.5 * d * np.log(nu * np.pi)
             - logdet - 0.5 * (nu + d) * np.log1p(m2 / nu))
        if self.gaussian_weight == 0.0:
            return t
        return np.logaddexp(np.log(self.gaussian_weight) + gauss, np.log1p(-self.gaussian_weight) + t)

    def draw(self, k: int, random) -> np.ndarray:
        """``k`` independent draws (k, d) of the proposal; ``random`` a ``numpy.random.RandomState``."""
        z = random.standard_normal((k, self.mean.size))
        if not np.isinf(self.df):
            chi = np.sqrt(self.df / random.chisquare(self.df, size=k))
            if self.gaussian_weight > 0.0:
                # the mixture: each draw is the Gaussian's with probability gaussian_weight, else the t's
                chi[random.random_sample(k) < self.gaussian_weight] = 1.0
            z *= chi[:, None]
        return self.map.to_x(self.scale * z)

    def _propose(self, x0: np.ndarray, random) -> tuple[np.ndarray, np.ndarray]:
        new = self.draw(x0.shape[0], random)
        return new, self.log_density(x0) - self.log_density(new)


def default_moves(mean: ArrayLike | None = None, cov: ArrayLike | None = None, *,
                  bend: BentLaplace | None = None, gaussian_weight: float = 0.0) -> list:
    """The sampler's moves.

    Without a Laplace approximation: ``DEMove`` 0.8 and the corrected snooker
    move 0.2.  With ``mean`` and ``cov`` (the MAP and its Laplace covariance):
    :class:`IndependenceMove` (through ``bend`` if given, its Gaussian mixed
    in with ``gaussian_weight``, as :func:`choose_proposal` decides)
    ``IMH_WEIGHT``, ``DEMove`` ``DE_WEIGHT``, snooker ``SNOOKER_WEIGHT``.
    """
    if mean is None or cov is None:
        return [(DEMove(), 0.8), (SnookerMove(), 0.2)]
    return [(IndependenceMove(mean, cov, bend=bend, gaussian_weight=gaussian_weight), IMH_WEIGHT),
            (DEMove(), DE_WEIGHT), (SnookerMove(), SNOOKER_WEIGHT)]


def _log_weights(log_prob, move: IndependenceMove, k: int, random) -> tuple[np.ndarray, np.ndarray]:
    """``k`` draws of ``move``'s proposal and their log posterior (``-inf`` where it is zero or not finite)."""
    x = move.draw(int(k), random)
    lp = np.asarray(log_prob(x), dtype=float)
    return x, np.where(np.isfinite(lp), lp, -np.inf)


def _efficiency(lw: np.ndarray) -> float:
    """``(sum w)^2 / (k sum w^2)`` of log weights ``lw`` (``-inf``: weight 0)."""
    if not np.isfinite(lw).any():
        return 0.0
    w = np.exp(lw - lw.max())
    return float(w.sum() ** 2 / (w.size * np.sum(w**2)))


def importance_efficiency(log_prob, move: IndependenceMove, k: int, random) -> float:
    """How well an independence proposal matches the posterior: the importance-sampling ESS fraction of ``k`` draws.

    ``(sum w)^2 / (k sum w^2)`` with ``w = pi(x) / g(x)`` for ``x`` drawn
    from ``g`` (1: the proposal is the posterior; about the independence
    sampler's acceptance rate in practice).  ``log_prob`` is the vectorised
    ``(k, d) -> (k,)`` log posterior; ``random`` a ``numpy.random.RandomState``.
    Draws of zero posterior density count as weight 0.
    """
    x, lp = _log_weights(log_prob, move, k, random)
    return _efficiency(lp - move.log_density(x))


def largest_weights(x: np.ndarray, lp: np.ndarray, t: IndependenceMove, mixture: IndependenceMove) -> tuple[float, float]:
    """Log of the largest normalised importance weight ``pi / (Z q)`` over draws ``x`` of ``t``, for ``q`` the t and the mixture.

    The independence sampler with proposal ``q`` converges at least as fast
    as ``(1 - 1/M)^n``, ``M = sup pi / (Z q)`` (Mengersen & Tweedie 1996);
    the largest weight over draws of the heavy-tailed t estimates ``M``
    where the t reaches, which is further out than the posterior.  ``Z`` is
    the posterior's normalising constant, estimated from the same weights
    (their mean).  ``lp`` is the log posterior at ``x`` (``-inf``: zero).
    """
    lw_t = lp - t.log_density(x)
    if not np.isfinite(lw_t).any():
        return np.inf, np.inf
    log_z = special.logsumexp(lw_t) - np.log(lw_t.size)
    return float(np.max(lw_t) - log_z), float(np.max(lp - mixture.log_density(x)) - log_z)


def choose_proposal(log_prob, mean: ArrayLike, cov: ArrayLike, bend: BentLaplace | None, k: int, random, *,
                    gaussian_weight: float = GAUSSIAN_WEIGHT) -> tuple[BentLaplace, dict]:
    """The independence proposal's map (bent or straight) and whether its Gaussian is mixed in.

    **Bent or straight.**  The bend is the second-order shift of the
    conditional mode measured one sigma out; where the valley is not
    quadratic (an effect's mass times its compliances, a gravity direction)
    its extrapolation can put the proposal's tails far off the posterior,
    worse than no bend.  So the bent map is used if its t proposal matches
    the posterior at least as well as the straight one's, each judged by
    the importance efficiency of ``k`` draws (both with the same
    ``random``); with ``bend`` None (or not bent) only the straight map is
    drawn.

    **Gaussian mixed in.**  Where the posterior is nearly the map's Gaussian
    (the 3-PRS example, the positioner), the t's heavy tails only waste
    proposals: a proposal that is ``gaussian_weight`` the Gaussian and the
    rest the t is accepted far more often (0.9 against 0.5 on both), and
    keeps the t's tails (its weights are at most ``1 / (1 - gaussian_weight)``
    times the t's).  Where the posterior's tails are heavier than the
    Gaussian's (a banana), the mixture visits them less often and mixes
    worse there.  The mixture is used when, over the same draws, its largest
    normalised weight (:func:`largest_weights`, the bound on the
    independence sampler's convergence) is at most ``GAUSSIAN_GAIN`` times
    the t's; else the t alone, as before.

    Returns
    -------
    BentLaplace
        ``bend`` or the straight map ``BentLaplace.linear(mean, chol(cov))``.
    dict
        ``{"draws": k, "straight": ..., "bent": ... (None if not tried),
        "largest_weight_t": ..., "largest_weight_mixture": ..., "gaussian_weight": ...}``:
        the efficiencies, the log largest weights of the chosen map and the
        Gaussian weight used (0: the t alone).
    """
    mean = np.asarray(mean, dtype=float).ravel()
    straight = BentLaplace.linear(mean, np.linalg.cholesky(np.asarray(cov, dtype=float)))
    maps = [straight] if bend is None or not bend.bent else [straight, bend]
    tried = []
    for m in maps:
        move = IndependenceMove(mean, cov, bend=m)
        x, lp = _log_weights(log_prob, move, k, random)
        tried.append((m, move, x, lp, _efficiency(lp - move.log_density(x))))
    best = tried[-1] if tried[-1][4] >= tried[0][4] else tried[0]
    m, move, x, lp, _ = best
    mixture = IndependenceMove(mean, cov, bend=m, gaussian_weight=gaussian_weight)
    sup_t, sup_mix = largest_weights(x, lp, move, mixture)
    use = gaussian_weight > 0 and sup_mix <= sup_t + np.log(GAUSSIAN_GAIN)
    finite = np.isfinite(sup_t) and np.isfinite(sup_mix)  # the answer's JSON has no infinities
    return m, {"draws": int(k), "straight": tried[0][4], "bent": tried[1][4] if len(tried) > 1 else None,
               "largest_weight_t": sup_t if finite else None, "largest_weight_mixture": sup_mix if finite else None,
               "gaussian_weight": gaussian_weight if use else 0.0}
