"""bayescal.distributions: scipy.stats' chi-square and F tails without importing scipy.stats, the same numbers."""

import numpy as np
import pytest
from scipy import stats

from bayescal.distributions import (
    chi2_cdf,
    chi2_median,
    chi2_ppf,
    chi2_sf,
    f_sf,
    weighted_chi2_sf,
)


def test_ordinary_arguments_give_scipy_stats_values_bit_for_bit():
    rng = np.random.default_rng(0)
    x = np.concatenate([rng.uniform(0, 60, 400), [0.0, 1e-300, 3.0]])
    df = rng.integers(1, 3000, x.size).astype(float) * rng.uniform(0.5, 1.0, x.size)  # non-integer dof too
    d2 = rng.uniform(1, 5000, x.size)
    assert np.array_equal(chi2_sf(x, df), stats.chi2.sf(x, df))
    assert np.array_equal(chi2_cdf(x, df), stats.chi2.cdf(x, df))
    assert np.array_equal(f_sf(x, df, d2), stats.f.sf(x, df, d2))
    q = rng.uniform(1e-6, 1 - 1e-6, x.size)
    assert np.array_equal(chi2_ppf(q, df), stats.chi2.ppf(q, df))
    for d in (1, 2, 3, 5, 6, 17.5):
        assert chi2_median(d) == stats.chi2.median(d)
    assert float(chi2_sf(3.0, 3)) == pytest.approx(0.3916251762710877, rel=1e-15)  # P(chi2_3 > 3), tables


@pytest.mark.parametrize("x, df", [(-1.0, 3.0), (0.0, 0.0), (np.inf, 0.0), (np.inf, np.inf), (np.nan, 2.0),
                                   (2.0, -1.0), ([1.0, -0.5], [3.0, 3.0])])
def test_edges_are_scipy_stats_own_conventions(x, df):
    """Below the support sf = 1 (scipy.special alone gives NaN there), bad degrees of freedom NaN."""
    for mine, theirs in ((chi2_sf(x, df), stats.chi2.sf(x, df)), (chi2_cdf(x, df), stats.chi2.cdf(x, df)),
                         (f_sf(x, df, 5.0), stats.f.sf(x, df, 5.0))):
        assert np.array_equal(mine, theirs, equal_nan=True)
    for p in (0.0, 1.0, 0.3):
        assert np.array_equal(chi2_ppf(p, df), stats.chi2.ppf(p, df), equal_nan=True)


@pytest.mark.parametrize("df", [1.0, 3.0, 10.0, 180.0, 49.9])
def test_weighted_chi2_sf_of_one_term_is_the_chi_square_tail(df):
    """One weight: the chi-square itself, to the saddlepoint's accuracy (4.5 % at df 1 out to 1e-4, less above)."""
    x = df + np.array([-0.8, -0.3, 0.0, 0.5, 3.0, 10.0]) * np.sqrt(2 * df)
    x = x[x > 0]
    got = np.array([weighted_chi2_sf(v, [2.0], [df]) for v in 2.0 * x])  # a weight scales the variable
    np.testing.assert_allclose(got, chi2_sf(x, df), rtol=0.05 if df < 3 else 0.015)


def test_weighted_chi2_sf_of_a_few_large_weights_is_monte_carlo_and_monotone():
    """Weights 14.5, 7.8, 4.9, 4.1 and 176 ones (the telescope's tip-sensor test): 10^6 draws, a tail of 1e-3 to
    3 % relative (1 sd), 12 % allowed; and the tail falls with x, to the last digit (a Newton step that left its
    bracket once returned a point that was not the saddlepoint, and the tail rose by 40 %)."""
    w = np.r_[14.5, 7.8, 4.9, 4.1, np.ones(176)]
    rng = np.random.default_rng(3)
    draws = (rng.standard_normal((10**6, 4)) ** 2) @ w[:4] + rng.chisquare(176, 10**6)  # the ones: chi2_176
    for x in (200.0, 260.0, 330.0):
        assert weighted_chi2_sf(x, w, np.ones(w.size)) == pytest.approx(np.mean(draws > x), rel=0.12)
    grid = np.linspace(150.0, 600.0, 901)
    tail = np.array([weighted_chi2_sf(v, w, np.ones(w.size)) for v in grid])
    assert np.all(np.diff(tail) < 0) and tail[0] < 1.0 and tail[-1] > 0.0
    assert weighted_chi2_sf(0.0, w, np.ones(w.size)) == 1.0
