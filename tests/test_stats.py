"""Paired statistics against scipy.stats directly, and Holm's correction against a hand computation."""

import numpy as np
import pytest
import scipy.stats

from bayescal.errors import InputError
from bayescal.stats import compare_pairs, holm_adjust, paired_comparison, summarise


def test_paired_comparison_matches_scipy():
    rng = np.random.default_rng(4)
    a = rng.gamma(2.0, 1.0, size=40)
    b = a + rng.normal(0.3, 0.5, size=40)
    a[3] = np.nan  # a failure: the pair is dropped
    pc = paired_comparison(a, b, a="x", b="y", n_resamples=999, rng=11)
    ok = np.isfinite(a)
    d = a[ok] - b[ok]
    w = scipy.stats.wilcoxon(d)
    ci = scipy.stats.bootstrap((d,), np.mean, n_resamples=999, method="BCa",
                               rng=np.random.default_rng(11)).confidence_interval
    assert pc.n == 39
    assert pc.p_value == pytest.approx(w.pvalue, rel=1e-12)
    assert pc.statistic == pytest.approx(w.statistic)
    assert (pc.ci_low, pc.ci_high) == pytest.approx((ci.low, ci.high), rel=1e-12)
    assert pc.mean_diff == pytest.approx(d.mean()) and pc.median_diff == pytest.approx(np.median(d))
    assert pc.win_rate == pytest.approx(np.mean(d < 0))
    assert pc.ci_low < pc.mean_diff < pc.ci_high


def test_ties_count_half_and_identical_samples_give_p_one():
    a = np.array([1.0, 2.0, 3.0, 4.0])
    pc = paired_comparison(a, np.array([1.0, 3.0, 2.0, 5.0]))
    assert pc.win_rate == pytest.approx((0.5 + 1 + 0 + 1) / 4)
    same = paired_comparison(a, a)
    assert same.p_value == 1.0 and same.mean_diff == 0.0 and same.ci_low == same.ci_high == 0.0
    none = paired_comparison(np.array([np.nan, 1.0]), np.array([1.0, np.nan]))
    assert none.n == 0 and np.isnan(none.p_value)
    with pytest.raises(InputError):
        paired_comparison(np.ones(3), np.ones(4))


def test_holm_adjustment_by_hand():
    p = np.array([0.01, 0.04, 0.03, 0.005, np.nan])
    # sorted: 0.005*4 = 0.02, 0.01*3 = 0.03, 0.03*2 = 0.06, 0.04*1 = 0.04 -> running max 0.06
    np.testing.assert_allclose(holm_adjust(p), [0.03, 0.06, 0.06, 0.02, np.nan])
    assert np.all(holm_adjust(np.array([0.5, 0.9])) == 1.0)


def test_compare_pairs_applies_holm_over_all_pairs():
    rng = np.random.default_rng(0)
    base = rng.gamma(2.0, 1.0, 30)
    errs = {"a": base, "b": base + 0.5 + 0.1 * rng.normal(size=30), "c": base + 0.01 * rng.normal(size=30)}
    pairs = compare_pairs(errs, seed=1, n_resamples=500)
    assert [(p.a, p.b) for p in pairs] == [("a", "b"), ("a", "c"), ("b", "c")]
    np.testing.assert_allclose([p.p_holm for p in pairs], holm_adjust(np.array([p.p_value for p in pairs])))
    assert pairs[0].significant and pairs[0].win_rate == 1.0


def test_summarise_counts_failures():
    s = summarise(np.array([1.0, np.nan, 3.0]))
    assert s["n"] == 2 and s["failures"] == 1 and s["median"] == 2.0 and s["max"] == 3.0
