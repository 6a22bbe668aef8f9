"""The corrected DE snooker move leaves a Gaussian target invariant."""

from __future__ import annotations

import emcee
import numpy as np
from scipy import stats

from bayescal.bayes.moves import SnookerMove, default_moves


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
