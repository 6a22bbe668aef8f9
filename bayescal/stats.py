"""Paired statistics for comparing methods trial by trial.

Every method sees the same trials (same true machine, poses and noise), so
differences are paired: ``d_t = e_a(t) - e_b(t)`` over the trials where both
succeeded.  For each pair: the mean and median difference, a bootstrap
confidence interval of the mean difference (scipy.stats.bootstrap, BCa),
the Wilcoxon signed-rank test (scipy.stats.wilcoxon, two-sided, zero
differences dropped), the win rate of ``a`` (ties count one half), and
Holm's step-down correction over all pairs.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import asdict, dataclass
from itertools import combinations

import numpy as np
import scipy.stats
from numpy.typing import NDArray

from .errors import InputError

__all__ = ["PairedComparison", "paired_comparison", "holm_adjust", "compare_pairs", "summarise",
           "posterior_effective_params"]


@dataclass(frozen=True)
class PairedComparison:
    """Method ``a`` against method ``b`` on the trials both completed.

    Attributes
    ----------
    a, b : str
    n : int
        Trials where both succeeded.
    mean_diff, median_diff : float
        Of ``e_a - e_b`` (negative: ``a`` has the smaller error), metric units.
    ci_low, ci_high : float
        Bootstrap confidence interval of ``mean_diff``.
    confidence : float
    win_rate : float
        Fraction of trials where ``a`` has the smaller error (ties count 1/2).
    statistic, p_value : float
        Wilcoxon signed-rank statistic and two-sided p-value.
    p_holm : float
        Holm-adjusted p-value over all pairs of the comparison.
    significant : bool
        ``p_holm < alpha``.
    """

    a: str
    b: str
    n: int
    mean_diff: float
    median_diff: float
    ci_low: float
    ci_high: float
    confidence: float
    win_rate: float
    statistic: float
    p_value: float
    p_holm: float = float("nan")
    significant: bool = False

    def to_dict(self) -> dict:
        return asdict(self)


def paired_comparison(
    e_a: NDArray, e_b: NDArray, *, a: str = "a", b: str = "b", confidence: float = 0.95, n_resamples: int = 2000,
    rng: np.random.Generator | int | None = 0,
) -> PairedComparison:
    """Paired statistics of two error samples (NaN = the method failed in that trial)."""
    e_a, e_b = np.asarray(e_a, dtype=float), np.asarray(e_b, dtype=float)
    if e_a.shape != e_b.shape or e_a.ndim != 1:
        raise InputError(f"paired samples: expected two 1-D arrays of equal length, got {e_a.shape} and {e_b.shape}")
    ok = np.isfinite(e_a) & np.isfinite(e_b)
    d = e_a[ok] - e_b[ok]
    n = int(d.size)
    if n == 0:
        nan = float("nan")
        return PairedComparison(a, b, 0, nan, nan, nan, nan, confidence, nan, nan, nan)
    mean = float(np.mean(d))
    lo = hi = mean
    if n >= 3 and np.ptp(d) > 0:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # BCa on few distinct values warns; fall back below
            ci = scipy.stats.bootstrap((d,), np.mean, confidence_level=confidence, n_resamples=n_resamples,
                                       method="BCa", rng=np.random.default_rng(rng)).confidence_interval
        lo, hi = float(ci.low), float(ci.high)
        if not (np.isfinite(lo) and np.isfinite(hi)):
            ci = scipy.stats.bootstrap((d,), np.mean, confidence_level=confidence, n_resamples=n_resamples,
                                       method="percentile", rng=np.random.default_rng(rng)).confidence_interval
            lo, hi = float(ci.low), float(ci.high)
    win = float(np.mean((d < 0) + 0.5 * (d == 0)))
    if np.any(d != 0):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # normal approximation notices for small n / ties
            w = scipy.stats.wilcoxon(d)
        stat, p = float(w.statistic), float(w.pvalue)
    else:
        stat, p = 0.0, 1.0  # identical errors in every trial: no evidence of a difference
    return PairedComparison(a, b, n, mean, float(np.median(d)), lo, hi, confidence, win, stat, p)


def holm_adjust(p: NDArray) -> NDArray:
    """Holm's step-down adjusted p-values (family-wise error control); NaN stays NaN.

    ``p_(i) -> max_{j <= i} min(1, (m - j + 1) p_(j))`` over the sorted
    p-values (Holm 1979).  Written here because scipy only ships FDR control
    (``scipy.stats.false_discovery_control``).
    """
    p = np.asarray(p, dtype=float)
    out = np.full(p.shape, np.nan)
    ok = np.flatnonzero(np.isfinite(p))
    m = ok.size
    if m == 0:
        return out
    order = ok[np.argsort(p[ok], kind="stable")]
    adj = np.minimum(1.0, (m - np.arange(m)) * p[order])
    out[order] = np.maximum.accumulate(adj)
    return out


def compare_pairs(
    errors: dict[str, NDArray], *, alpha: float = 0.05, confidence: float = 0.95, n_resamples: int = 2000,
    seed: int = 0,
) -> tuple[PairedComparison, ...]:
    """Every pair of methods (in the given order), Holm-corrected over all pairs."""
    labels = list(errors)
    pairs = [
        paired_comparison(errors[x], errors[y], a=x, b=y, confidence=confidence, n_resamples=n_resamples,
                          rng=np.random.default_rng([seed, i]))
        for i, (x, y) in enumerate(combinations(labels, 2))
    ]
    adj = holm_adjust(np.array([pc.p_value for pc in pairs]))
    return tuple(
        PairedComparison(**{**pc.to_dict(), "p_holm": float(h), "significant": bool(np.isfinite(h) and h < alpha)})
        for pc, h in zip(pairs, adj)
    )


def summarise(e: NDArray) -> dict[str, float]:
    """Count, failures, mean, median, 5 %/95 % quantiles and max of an error sample (NaN = failure)."""
    e = np.asarray(e, dtype=float)
    ok = e[np.isfinite(e)]
    if ok.size == 0:
        nan = float("nan")
        return {"n": 0, "failures": int(e.size), "mean": nan, "median": nan, "q05": nan, "q95": nan, "max": nan}
    return {
        "n": int(ok.size),
        "failures": int(e.size - ok.size),
        "mean": float(ok.mean()),
        "median": float(np.median(ok)),
        "q05": float(np.quantile(ok, 0.05)),
        "q95": float(np.quantile(ok, 0.95)),
        "max": float(ok.max()),
    }


def posterior_effective_params(prior_cov: NDArray, post_cov: NDArray) -> float | None:
    """``n - tr(P_prior^-1 P_post)``, clipped to ``[0, n]``: how many parameters the data determine (None if not finite).

    For a linear-Gaussian model with whitened Jacobian ``J`` the posterior is ``(J^T J + P^-1)^-1`` and the
    trace of the hat matrix ``J P_post J^T`` is exactly this.
    """
    prior_cov, post_cov = np.atleast_2d(prior_cov), np.atleast_2d(post_cov)
    n = prior_cov.shape[0]
    if n == 0 or post_cov.shape != prior_cov.shape:
        return None
    t = float(np.trace(np.linalg.solve(prior_cov, post_cov)))
    return float(np.clip(n - t, 0.0, n)) if math.isfinite(t) else None
