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
since each move does.
"""

from __future__ import annotations

import numpy as np
from emcee.moves import DEMove, DESnookerMove, MHMove
from numpy.typing import ArrayLike
from scipy import special

from .bent_laplace import BentLaplace

__all__ = ["SnookerMove", "IndependenceMove", "default_moves", "importance_efficiency", "choose_proposal"]

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

    Notes
    -----
    The proposal ``g`` does not depend on the current point, so the
    Metropolis-Hastings log ratio is ``log pi(x') - log pi(x) + log g(x) - log g(x')``;
    :meth:`get_proposal` returns ``log g(x) - log g(x')`` as emcee's
    ``log_factors``.  All walkers propose at once (one vectorised
    log-probability call per step).
    """

    def __init__(self, mean: ArrayLike, cov: ArrayLike, *, df: float = T_DOF, scale: float = 1.0,
                 bend: BentLaplace | None = None):
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
        super().__init__(self._propose, ndim=d)

    def log_density(self, x: np.ndarray) -> np.ndarray:
        """Log proposal density at points ``x`` (k, d), including its constant."""
        d = self.mean.size
        z = self.map.to_w(x) / self.scale
        m2 = np.sum(z**2, axis=1)
        logdet = self.map.log_det + d * np.log(self.scale)  # the bend's Jacobian is that of its linear part
        if np.isinf(self.df):
            return -0.5 * m2 - logdet - 0.5 * d * np.log(2 * np.pi)
        nu = self.df
        return (special.gammaln(0.5 * (nu + d)) - special.gammaln(0.5 * nu) - 0.5 * d * np.log(nu * np.pi)
                - logdet - 0.5 * (nu + d) * np.log1p(m2 / nu))

    def draw(self, k: int, random) -> np.ndarray:
        """``k`` independent draws (k, d) of the proposal; ``random`` a ``numpy.random.RandomState``."""
        z = random.standard_normal((k, self.mean.size))
        if not np.isinf(self.df):
            z *= np.sqrt(self.df / random.chisquare(self.df, size=k))[:, None]
        return self.map.to_x(self.scale * z)

    def _propose(self, x0: np.ndarray, random) -> tuple[np.ndarray, np.ndarray]:
        new = self.draw(x0.shape[0], random)
        return new, self.log_density(x0) - self.log_density(new)


def default_moves(mean: ArrayLike | None = None, cov: ArrayLike | None = None, *,
                  bend: BentLaplace | None = None) -> list:
    """The sampler's moves.

    Without a Laplace approximation: ``DEMove`` 0.8 and the corrected snooker
    move 0.2.  With ``mean`` and ``cov`` (the MAP and its Laplace covariance):
    :class:`IndependenceMove` (through ``bend`` if given) ``IMH_WEIGHT``,
    ``DEMove`` ``DE_WEIGHT``, snooker ``SNOOKER_WEIGHT``.
    """
    if mean is None or cov is None:
        return [(DEMove(), 0.8), (SnookerMove(), 0.2)]
    return [(IndependenceMove(mean, cov, bend=bend), IMH_WEIGHT), (DEMove(), DE_WEIGHT),
            (SnookerMove(), SNOOKER_WEIGHT)]


def importance_efficiency(log_prob, move: IndependenceMove, k: int, random) -> float:
    """How well an independence proposal matches the posterior: the importance-sampling ESS fraction of ``k`` draws.

    ``(sum w)^2 / (k sum w^2)`` with ``w = pi(x) / g(x)`` for ``x`` drawn
    from ``g`` (1: the proposal is the posterior; about the independence
    sampler's acceptance rate in practice).  ``log_prob`` is the vectorised
    ``(k, d) -> (k,)`` log posterior; ``random`` a ``numpy.random.RandomState``.
    Draws of zero posterior density count as weight 0.
    """
    x = move.draw(int(k), random)
    lw = np.asarray(log_prob(x), dtype=float) - move.log_density(x)
    lw = np.where(np.isfinite(lw), lw, -np.inf)
    if not np.isfinite(lw).any():
        return 0.0
    w = np.exp(lw - lw.max())
    return float(w.sum() ** 2 / (w.size * np.sum(w**2)))


def choose_proposal(log_prob, mean: ArrayLike, cov: ArrayLike, bend: BentLaplace, k: int, random) -> tuple[BentLaplace, dict]:
    """The bent map if its t proposal matches the posterior at least as well as the straight one, else the straight map.

    Why: the bend is the second-order shift of the conditional mode measured
    one sigma out; where the valley is not quadratic (an effect's mass times
    its compliances, a gravity direction) its extrapolation can put the
    proposal's tails far off the posterior, worse than no bend.  Each is
    judged by :func:`importance_efficiency` of ``k`` draws (both with the
    same ``random``).

    Returns
    -------
    BentLaplace
        ``bend`` or the straight map ``BentLaplace.linear(mean, chol(cov))``.
    dict
        ``{"draws": k, "straight": ..., "bent": ...}``, the two efficiencies.
    """
    mean = np.asarray(mean, dtype=float).ravel()
    straight = BentLaplace.linear(mean, np.linalg.cholesky(np.asarray(cov, dtype=float)))
    eff = [importance_efficiency(log_prob, IndependenceMove(mean, cov, bend=b), k, random) for b in (straight, bend)]
    return (bend if eff[1] >= eff[0] else straight), {"draws": int(k), "straight": eff[0], "bent": eff[1]}
