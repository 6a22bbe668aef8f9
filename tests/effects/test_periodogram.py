"""The Lomb-Scargle periodogram of actuator-space residuals (bayescal.effects.periodogram)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.signal import lombscargle

from bayescal.effects.periodogram import periodogram, pitch_grid


def _sine(n=400, pitch=5.0, seed=0):
    rng = np.random.default_rng(seed)
    q = np.sort(rng.uniform(0.0, 100.0, n))
    return q, 0.003 * np.sin(2 * np.pi * q / pitch + 0.4) + 0.0007, pitch_grid(100.0, (1.0, 50.0))


def test_a_sine_peaks_at_its_pitch_with_scipy_floating_mean_power():
    q, y, f = _sine()
    p = periodogram(q, y, f)
    # an independent call of scipy (unchunked) on the same data
    np.testing.assert_allclose(p, lombscargle(q, y, 2 * np.pi * f, normalize=True, floating_mean=True), rtol=1e-10, atol=1e-12)
    assert abs(1.0 / f[np.argmax(p)] - 5.0) < 0.05
    assert p.max() > 0.99  # noise-free sine with an offset: the floating mean takes the offset


def test_a_repeated_call_is_served_by_content_and_never_stale():
    q, y, f = _sine(seed=1)
    first = periodogram(q, y, f)
    again = periodogram(q.copy(), y.copy(), f.copy())
    np.testing.assert_array_equal(first, again)
    again[:] = -1.0  # the caller's copy: the kept answer is not touched
    np.testing.assert_array_equal(periodogram(q, y, f), first)
    y2 = y.copy()
    y2[7] += 1e-3  # one sample changed: computed afresh
    changed = periodogram(q, y2, f)
    np.testing.assert_allclose(changed, lombscargle(q, y2, 2 * np.pi * f, normalize=True, floating_mean=True), rtol=1e-10, atol=1e-12)
    assert not np.array_equal(changed, first)


def _scipy(q, y, f):
    return lombscargle(q, y, 2 * np.pi * f, normalize=True, floating_mean=True)


@pytest.mark.parametrize("case", ["uniform", "clustered", "few_values", "rad", "long", "noise"])
def test_the_evenly_spaced_grid_recurrence_is_scipys_power(case, monkeypatch):
    """bayescal's own evaluation on evenly spaced grids (a rotation per frequency step instead of four sines and
    cosines per sample and frequency) gives scipy's powers, on samples of every shape a recording may give,
    with the cosine blocks restarted often (rows of 7 frequencies) and not."""
    import bayescal.effects.periodogram as pg

    rng = np.random.default_rng(["uniform", "clustered", "few_values", "rad", "long", "noise"].index(case))
    n, span, pr = 3000, 100.0, (1.0, 50.0)
    if case == "uniform":
        q = rng.uniform(0.0, span, n)
    elif case == "clustered":
        q = np.concatenate([rng.normal(10.0, 0.5, n // 2), rng.normal(80.0, 3.0, n - n // 2)])
    elif case == "few_values":
        q = rng.choice([0.0, 12.5, 40.0, 99.0], n)
    elif case == "rad":
        span, pr = 2.0, (0.01, 0.5)
        q = rng.uniform(-1.0, 1.0, n)
    elif case == "long":
        span = 900.0
        q = np.sort(rng.uniform(0.0, span, n))
    else:
        q = rng.uniform(0.0, span, n)
    y = 1e-3 * rng.normal(size=n) + (0.0 if case == "noise" else 2e-3 * np.sin(2 * np.pi * q / 7.1 + 1.0)) + 0.5
    f = pitch_grid(span, pr)
    want = _scipy(q, y, f)
    got = pg._periodogram(q, y, f)
    # four distinct positions: a sine, a cosine and a mean nearly interpolate them at some frequencies, where
    # the centred sums cancel and any two evaluations differ by round-off times that conditioning (3.7e-8 seen)
    rtol = 1e-6 if case == "few_values" else 1e-9
    np.testing.assert_allclose(got, want, rtol=rtol, atol=1e-12)
    assert np.argmax(got) == np.argmax(want)
    monkeypatch.setattr(pg, "_MAX_ROWS", 7)
    np.testing.assert_allclose(pg._periodogram(q, y, f), want, rtol=rtol, atol=1e-12)


def test_grids_not_evenly_spaced_or_too_short_go_to_scipy():
    import bayescal.effects.periodogram as pg

    rng = np.random.default_rng(9)
    q = rng.uniform(0.0, 50.0, 500)
    y = np.sin(q) + 0.1 * rng.normal(size=500)
    for f in (np.geomspace(0.05, 1.0, 40), np.array([0.2, 0.3]), np.array([0.25])):
        np.testing.assert_array_equal(pg._periodogram(q, y, f), np.atleast_1d(_scipy(q, y, f)))
    assert np.array_equal(pg._periodogram(q, np.full(500, 3.0), np.linspace(0.1, 1, 10)), np.zeros(10))
