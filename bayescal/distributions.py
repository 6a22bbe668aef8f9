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

__all__ = ["chi2_sf", "chi2_cdf", "chi2_ppf", "chi2_median", "f_sf", "weighted_chi2_sf"]


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


def weighted_chi2_sf(x: float, weights: ArrayLike, dofs: ArrayLike) -> float:
    """``P(sum_j w_j X_j > x)``, ``X_j`` independent chi-square with ``h_j`` (``dofs``, positive, any real) degrees
    of freedom and ``w_j`` (``weights``) positive: the Lugannani-Rice saddlepoint approximation.

    Exact in no case but close in every one, and in the far tail too (relative error of a few per cent at
    ``1e-10``, where a mean-and-variance match is off by orders of magnitude when a few weights dominate):
    the cumulant generating function ``K(s) = -1/2 sum_j h_j log(1 - 2 w_j s)`` is explicit, the saddlepoint
    ``K'(s) = x`` found by a safeguarded Newton iteration (``K'`` increases in ``s``).

    Parameters
    ----------
    x : float
        Where the upper tail starts, in the sum's units (a sum of squared whitened residuals: dimensionless).
    weights : array_like, shape (m,)
        ``w_j``; entries that are not positive (and their ``dofs``) are left out.
    dofs : array_like, shape (m,)
        ``h_j``.

    Returns
    -------
    float
        The tail probability, in [0, 1] (1 for ``x <= 0`` or no positive weight).
    """
    from scipy import special

    w, h = np.asarray(weights, dtype=float), np.asarray(dofs, dtype=float)
    keep = (w > 0) & (h > 0)
    w, h = w[keep], h[keep]
    if not w.size or not x > 0:
        return 1.0

    def cumulants(s):
        t = 1.0 - 2.0 * w * s
        return -0.5 * np.sum(h * np.log(t)), np.sum(h * w / t), np.sum(2.0 * h * w**2 / t**2)

    mean, var = float(np.sum(h * w)), float(np.sum(2.0 * h * w**2))
    if abs(x - mean) < 1e-8 * np.sqrt(var):  # at the mean the formula is 0/0: its limit
        return 0.5 - float(np.sum(8.0 * h * w**3)) / (6.0 * np.sqrt(2.0 * np.pi) * var**1.5)
    s = _saddlepoint(x, w, cumulants)
    K, _, K2 = cumulants(s)
    r = np.sign(s) * np.sqrt(max(2.0 * (s * x - K), 0.0))
    u = s * np.sqrt(K2)
    return float(min(max(special.ndtr(-r) + np.exp(-0.5 * r * r) / np.sqrt(2.0 * np.pi) * (1.0 / u - 1.0 / r), 0.0),
                     1.0))


def _saddlepoint(x: float, w: np.ndarray, cumulants) -> float:
    """The root ``s`` of ``K'(s) = x`` (``K'`` increasing on ``s < 1 / (2 max w)``), Newton kept in a bracket."""
    hi = 0.5 / w.max()
    lo = -1.0 / w.max()
    while cumulants(lo)[1] > x:
        lo *= 2.0
    s = 0.0 if lo < 0.0 < hi else 0.5 * (lo + hi)
    for _ in range(200):
        _, K1, K2 = cumulants(s)
        if abs(K1 - x) <= 1e-13 * x:
            break
        if K1 > x:
            hi = s
        else:
            lo = s
        step = s - (K1 - x) / K2
        s = step if lo < step < hi else 0.5 * (lo + hi)
        if hi - lo <= 1e-15 * max(abs(s), 1e-300):
            break
    return s
