"""The corrected DE snooker move and the independence MH move leave their targets invariant."""

from __future__ import annotations

import emcee
import numpy as np
from scipy import stats

import pytest

from bayescal.bayes.bent_laplace import bent_laplace
from bayescal.bayes.moves import IndependenceMove, SnookerMove, choose_proposal, default_moves, importance_efficiency


def _run(moves, d=8, walkers=20, steps=1500, seed=0):
    rng = np.random.default_rng(seed)
    s = emcee.EnsembleSampler(walkers, d, lambda X: -0.5 * np.sum(X**2, axis=1), vectorize=True, moves=moves)
    s.random_state = np.random.RandomState(seed).get_state()
    s.run_mcmc(rng.normal(size=(walkers, d)), steps)
    return s.get_chain(discard=300)


def test_snooker_move_samples_a_standard_normal():
    chain = _run([(SnookerMove(), 1.0)])
    flat = chain.reshape(-1, chain.shape[-1])
    # started from the target: a correct move keeps it (emcee 3.1.6's DESnookerMove shrinks it)
    np.testing.assert_allclose(flat.std(axis=0).mean(), 1.0, atol=0.06)
    # radius^2 of thinned draws is chi-square(d)
    r2 = np.sum(chain[::20].reshape(-1, chain.shape[-1]) ** 2, axis=1)
    assert stats.kstest(r2, stats.chi2(chain.shape[-1]).cdf).pvalue > 1e-3


def test_default_mix_samples_a_standard_normal():
    flat = _run(default_moves(), seed=1).reshape(-1, 8)
    np.testing.assert_allclose(flat.std(axis=0).mean(), 1.0, atol=0.06)
    assert abs(flat.mean()) < 0.1


def test_independence_move_log_density_is_the_multivariate_t():
    rng = np.random.default_rng(3)
    d = 5
    A = rng.normal(size=(d, d))
    cov = A @ A.T + d * np.eye(d)
    mean = rng.normal(size=d)
    move = IndependenceMove(mean, cov, df=7.0, scale=1.3)
    x = rng.normal(size=(4, d)) * 3
    ref = stats.multivariate_t(loc=mean, shape=1.3**2 * cov, df=7.0).logpdf(x)
    np.testing.assert_allclose(move.log_density(x), ref, rtol=1e-12)
    gauss = IndependenceMove(mean, cov, df=np.inf)
    np.testing.assert_allclose(gauss.log_density(x), stats.multivariate_normal(mean, cov).logpdf(x), rtol=1e-12)


def test_independence_move_alone_corrects_a_wrong_proposal():
    # proposal off-centre and too wide: without the Hastings factor the draws would follow it
    d = 10
    move = IndependenceMove(np.full(d, 0.4), 1.5**2 * np.eye(d))
    chain = _run([(move, 1.0)], d=d, walkers=16, steps=1500, seed=5)
    flat = chain.reshape(-1, d)
    assert abs(flat.mean()) < 0.05  # per-coordinate MC error ~0.02 (about 2000 effective draws)
    np.testing.assert_allclose(flat.std(axis=0).mean(), 1.0, atol=0.04)
    r2 = np.sum(chain[::10].reshape(-1, d) ** 2, axis=1)
    assert stats.kstest(r2, stats.chi2(d).cdf).pvalue > 1e-3


def _banana(X, a=3.0, b=0.05):
    """x1 ~ N(0, a^2), x2 = y + b (x1^2 - a^2) with y ~ N(0, 1), the rest N(0, 1): mean 0,
    var x2 = 1 + 2 b^2 a^4, skewness of x2 8 b^3 a^6 / var^1.5."""
    y = X[:, 1] - b * (X[:, 0] ** 2 - a**2)
    return -0.5 * (X[:, 0] ** 2 / a**2 + y**2 + np.sum(X[:, 2:] ** 2, axis=1))


def test_default_mix_with_laplace_samples_a_banana():
    # the Laplace approximation at the mode (0, -b a^2) is N(mode, diag(a^2, 1, ...)):
    # wrong mean for x2 (-0.45 instead of 0), wrong variance (1 instead of 1.41), no skew
    d, a, b, walkers = 4, 3.0, 0.05, 10
    mode = np.zeros(d)
    mode[1] = -b * a**2
    cov = np.eye(d)
    cov[0, 0] = a**2
    rng = np.random.default_rng(2)
    s = emcee.EnsembleSampler(walkers, d, _banana, vectorize=True, moves=default_moves(mode, cov))
    s.random_state = np.random.RandomState(2).get_state()
    s.run_mcmc(rng.multivariate_normal(mode, cov, size=walkers), 5000)
    chain = s.get_chain(discard=500)
    flat = chain.reshape(-1, d)
    # Monte Carlo errors from emcee's autocorrelation time (10-30 steps here: in the banana's
    # arms the Laplace proposal is poor and the DE moves do the work)
    tau = s.get_autocorr_time(discard=500)  # raises if the chain is shorter than 50 tau
    ess = chain.shape[0] * chain.shape[1] / tau
    x1, x2 = flat[:, 0], flat[:, 1]
    var2 = 1 + 2 * b**2 * a**4
    assert abs(x1.mean()) < 4 * a / np.sqrt(ess[0])
    assert abs(x2.mean()) < 4 * np.sqrt(var2 / ess[1])  # the proposal's centre is about 10 of these away
    for x, v, e in ((x1, a**2, ess[0]), (x2, var2, ess[1])):
        se_var = np.sqrt((np.mean((x - x.mean()) ** 4) - x.var() ** 2) / e)
        assert abs(x.var() - v) < 4 * se_var
    np.testing.assert_allclose(flat[:, 2:].std(axis=0), 1.0, atol=0.06)
    # skewness of x2: E[(b(x1^2 - a^2))^3] / var^1.5 = 8 b^3 a^6 / var^1.5 = 0.44 (the proposal's: 0)
    np.testing.assert_allclose(stats.skew(x2), 8 * b**3 * a**6 / var2**1.5, atol=0.15)


def test_importance_efficiency_of_a_wide_gaussian_is_its_closed_form():
    # p = N(0, I_d), g = N(0, s^2 I_d): E_g[(p/g)^2] = (s^2 / sqrt(2 s^2 - 1))^d, so the ESS fraction tends to its inverse
    d, s = 3, 1.5
    move = IndependenceMove(np.zeros(d), s**2 * np.eye(d), df=np.inf)
    eff = importance_efficiency(lambda X: -0.5 * np.sum(X**2, axis=1), move, 200_000, np.random.RandomState(0))
    assert abs(eff - (np.sqrt(2 * s**2 - 1) / s**2) ** d) < 0.01
    # a proposal that is the target: every weight equal
    exact = IndependenceMove(np.zeros(d), np.eye(d), df=np.inf)
    assert importance_efficiency(lambda X: -0.5 * np.sum(X**2, axis=1), exact, 1000, np.random.RandomState(0)) == pytest.approx(1.0)
    # draws of zero density weigh nothing: half the space cut away halves the efficiency of the exact proposal
    cut = importance_efficiency(lambda X: np.where(X[:, 0] > 0, -0.5 * np.sum(X**2, axis=1), -np.inf), exact, 100_000,
                                np.random.RandomState(1))
    assert abs(cut - 0.5) < 0.01


def test_choose_proposal_keeps_a_bend_only_where_it_helps():
    from tests.bayes.test_bent_laplace import _banana

    b, sigma = 0.7, 0.05
    cov = np.diag([1.0, sigma**2])
    banana, grad = _banana(b, sigma)
    bend = bent_laplace(grad, [0.0, 0.0], cov, [1.0, 100 * sigma])
    kept, check = choose_proposal(banana, [0.0, 0.0], cov, bend, 2000, np.random.RandomState(0))
    assert kept is bend and check["bent"] > 0.5 > 0.2 > check["straight"]
    # the same bend on a target with a straight valley (b = 0) is worse than none: the straight map is chosen
    straight_target, _ = _banana(0.0, sigma)
    chosen, check = choose_proposal(straight_target, [0.0, 0.0], cov, bend, 2000, np.random.RandomState(0))
    assert chosen is not bend and chosen.bent == 0 and check["straight"] > 0.5 > 0.2 > check["bent"]


def test_the_gaussian_and_t_mixture_has_the_closed_form_density_and_draws():
    rng = np.random.default_rng(4)
    d, w = 6, 0.9
    A = rng.normal(size=(d, d))
    cov = A @ A.T + d * np.eye(d)
    mean = rng.normal(size=d)
    move = IndependenceMove(mean, cov, df=7.0, scale=1.2, gaussian_weight=w)
    x = mean + rng.normal(size=(5, d)) * 4
    ref = np.logaddexp(np.log(w) + stats.multivariate_normal(mean, 1.2**2 * cov).logpdf(x),
                       np.log(1 - w) + stats.multivariate_t(loc=mean, shape=1.2**2 * cov, df=7.0).logpdf(x))
    np.testing.assert_allclose(move.log_density(x), ref, rtol=1e-12)
    # the draws' whitened radius^2 is chi2(d) with probability w, else d F(d, df): the mixture's CDF
    X = move.draw(20_000, np.random.RandomState(0))
    L = np.linalg.cholesky(1.2**2 * cov)
    r2 = np.sum(np.linalg.solve(L, (X - mean).T) ** 2, axis=0)
    cdf = lambda r: w * stats.chi2(d).cdf(r) + (1 - w) * stats.f(d, 7.0).cdf(r / d)  # noqa: E731
    assert stats.kstest(r2, cdf).pvalue > 1e-3
    # the t's share is seen in the tail: beyond the Gaussian's 0.999 quantile lie 0.1 % of its draws, about 0.6 % here
    q = stats.chi2(d).ppf(0.999)
    tail = w * 0.001 + (1 - w) * stats.f(d, 7.0).sf(q / d)
    assert tail > 0.005
    assert abs(np.mean(r2 > q) - tail) < 4 * np.sqrt(tail / r2.size)
    with pytest.raises(ValueError, match="gaussian_weight"):
        IndependenceMove(mean, cov, gaussian_weight=1.0)


def test_the_mixture_proposal_alone_corrects_a_wrong_proposal():
    d = 10
    move = IndependenceMove(np.full(d, 0.4), 1.5**2 * np.eye(d), gaussian_weight=0.9)
    chain = _run([(move, 1.0)], d=d, walkers=16, steps=1500, seed=6)
    flat = chain.reshape(-1, d)
    assert abs(flat.mean()) < 0.05
    np.testing.assert_allclose(flat.std(axis=0).mean(), 1.0, atol=0.04)
    r2 = np.sum(chain[::10].reshape(-1, d) ** 2, axis=1)
    assert stats.kstest(r2, stats.chi2(d).cdf).pvalue > 1e-3


def test_choose_proposal_mixes_the_gaussian_in_only_where_the_tails_are_not_heavier():
    # a posterior that is its Laplace approximation (30-D, as the 3-PRS example nearly is): the mixture's weights
    # are at most 1 / 0.9 of their mean (log 0.105), the t's far larger; the Gaussian is mixed in
    d = 30
    gauss = lambda X: -0.5 * np.sum(X**2, axis=1)  # noqa: E731
    _, check = choose_proposal(gauss, np.zeros(d), np.eye(d), None, 300, np.random.RandomState(0))
    assert check["bent"] is None and check["gaussian_weight"] == 0.9
    assert check["largest_weight_mixture"] < np.log(1 / 0.9) + 0.1 < 0.5 < check["largest_weight_t"]
    # the banana of test_default_mix_with_laplace_samples_a_banana: its arms are heavier than the Laplace
    # Gaussian's tails (a mixture there gave skewness 0.30 +- 0.09 over six seeds instead of 0.44): the t alone
    a, b = 3.0, 0.05
    mode, cov = np.array([0.0, -b * a**2, 0.0, 0.0]), np.diag([a**2, 1.0, 1.0, 1.0])
    for seed in range(6):
        _, check = choose_proposal(_banana, mode, cov, None, 200, np.random.RandomState(seed))
        assert check["gaussian_weight"] == 0.0, (seed, check)
