"""The vectorised autocorrelation time against emcee's loop, and against the closed form of an AR(1) chain."""

from __future__ import annotations

import emcee
import numpy as np
import pytest

from bayescal.bayes.autocorr import integrated_time


def _ar1(phi: np.ndarray, n_steps: int, n_walkers: int, rng) -> np.ndarray:
    """AR(1) chains x_t = phi x_{t-1} + e_t, one phi per parameter: tau = (1 + phi) / (1 - phi)."""
    x = np.empty((n_steps, n_walkers, phi.size))
    x[0] = rng.standard_normal((n_walkers, phi.size)) / np.sqrt(1 - phi**2)
    for t in range(1, n_steps):
        x[t] = phi * x[t - 1] + rng.standard_normal((n_walkers, phi.size))
    return x


@pytest.mark.parametrize("n_steps", [1, 2, 7, 64, 65, 88, 300])
def test_the_same_numbers_as_emcees_loop(n_steps):
    rng = np.random.default_rng(n_steps)
    x = _ar1(np.array([-0.3, 0.0, 0.5, 0.9, 0.99]), n_steps, 12, rng) * [1.0, 1e-6, 3e3, 1.0, 1.0] + 5.0
    with np.errstate(invalid="ignore", divide="ignore"):
        ref = emcee.autocorr.integrated_time(x, quiet=True)
    got = integrated_time(x)
    np.testing.assert_allclose(got, ref, rtol=1e-9, atol=1e-12, equal_nan=True)


@pytest.mark.parametrize("value, n_steps", [(0.25, 50), (0.1, 33), (-7.3, 801), (1e-9, 64)])
def test_a_walker_that_never_moved_gives_nan_as_emcee_does(value, n_steps):
    # review: at 0.1 over 33 steps the mean along the steps was not exactly 0.1, and the time came out finite (a
    # stuck walker then passed every check); emcee's 0 / 0 is NaN whatever the rounding now
    x = _ar1(np.array([0.5, 0.5]), n_steps, 4, np.random.default_rng(1))
    x[:, 2, 1] = value
    with np.errstate(invalid="ignore", divide="ignore"):
        ref = emcee.autocorr.integrated_time(x, quiet=True)
    got = integrated_time(x)
    assert np.isfinite(got[0]) and np.isnan(got[1])
    np.testing.assert_allclose(got[0], ref[0], rtol=1e-9)


def test_more_parameters_than_a_block_and_an_odd_count():
    x = _ar1(np.linspace(0.0, 0.9, 19), 120, 6, np.random.default_rng(3))
    with np.errstate(invalid="ignore", divide="ignore"):
        ref = emcee.autocorr.integrated_time(x, quiet=True)
    np.testing.assert_allclose(integrated_time(x), ref, rtol=1e-9)


def test_ar1_chains_give_their_closed_form():
    # tau = (1 + phi) / (1 - phi): 1 at 0, 3 at 0.5, 9 at 0.8; 2,000 steps of 40 walkers put the estimator within
    # a few per cent (its window truncates the tail: a small downward bias).  Not for phi < 0: Sokal's window
    # stops at the first lag beyond c tau, where an alternating autocorrelation leaves the partial sum far off
    # (emcee's estimate of 1/3 at phi = -0.5 is about 0)
    phi = np.array([0.0, 0.5, 0.8])
    got = integrated_time(_ar1(phi, 2000, 40, np.random.default_rng(7)))
    np.testing.assert_allclose(got, (1 + phi) / (1 - phi), rtol=0.06)


def test_a_chain_of_the_wrong_shape_is_refused():
    with pytest.raises(ValueError, match=r"expected a chain \(n_steps, n_walkers, n_params\)"):
        integrated_time(np.zeros((10, 3)))
