"""The chi-square and F tail probabilities the outlier test and the noise check use, without ``scipy.stats``.

``scipy.stats`` costs one to two seconds to import (its whole distribution
catalogue), more than ``identify`` of a few hundred poses.  Its ``chi2`` and
``f`` evaluate these very ``scipy.special`` functions, so for ordinary
arguments (finite, inside the support, degrees of freedom positive) the
values here are its values, bit for bit (``tests/test_distributions.py``);
any other argument is handed to ``scipy.stats`` itself, so its conventions
at the edges (``sf = 1`` below the support, NaN for bad degrees of freedom)
stay exactly as they were.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

__all__ = ["chi2_sf", "chi2_cdf", "chi2_ppf", "chi2_median", "f_sf"]


def _ordinary(x: ArrayLike, *dfs: ArrayLike, upper: float = np.inf) -> bool:
    x = np.asarray(x, dtype=float)
    ok = bool(np.all(np.isfinite(x) & (x >= 0) & (x <= upper)))
    return ok and all(bool(np.all(np.isfinite(d) & (np.asarray(d, dtype=float) > 0))) for d in dfs)


def chi2_sf(x: ArrayLike, df: ArrayLike):
    """``scipy.stats.chi2.sf(x, df)``: P(X > x) for X chi-square with ``df`` degrees of freedom."""
    if _ordinary(x, df):
        from scipy import special

        return special.chdtrc(df, x)
    from scipy import stats

    return stats.chi2.sf(x, df)


def chi2_cdf(x: ArrayLike, df: ArrayLike):
    """``scipy.stats.chi2.cdf(x, df)``."""
    if _ordinary(x, df):
        from scipy import special

        return special.chdtr(df, x)
    from scipy import stats

    return stats.chi2.cdf(x, df)


def chi2_ppf(q: ArrayLike, df: ArrayLike):
    """``scipy.stats.chi2.ppf(q, df)``: the ``q`` quantile."""
    q_arr = np.asarray(q, dtype=float)
    if _ordinary(q_arr, df, upper=1.0) and bool(np.all((q_arr > 0) & (q_arr < 1))):
        from scipy import special

        return 2.0 * special.gammaincinv(np.asarray(df, dtype=float) / 2.0, q_arr)
    from scipy import stats

    return stats.chi2.ppf(q, df)


def chi2_median(df: ArrayLike):
    """``scipy.stats.chi2.median(df)``: the 0.5 quantile."""
    return chi2_ppf(0.5, df)


def f_sf(x: ArrayLike, dfn: ArrayLike, dfd: ArrayLike):
    """``scipy.stats.f.sf(x, dfn, dfd)``: P(X > x) for X F-distributed with ``(dfn, dfd)`` degrees of freedom."""
    if _ordinary(x, dfn, dfd):
        from scipy import special

        return special.fdtrc(dfn, dfd, x)
    from scipy import stats

    return stats.f.sf(x, dfn, dfd)
