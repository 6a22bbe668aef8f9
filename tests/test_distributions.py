"""bayescal.distributions: scipy.stats' chi-square and F tails without importing scipy.stats, the same numbers."""

import numpy as np
import pytest
from scipy import stats

from bayescal.distributions import chi2_cdf, chi2_median, chi2_ppf, chi2_sf, f_sf


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
