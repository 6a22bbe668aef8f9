"""The Lomb-Scargle periodogram of actuator-space residuals (bayescal.effects.periodogram)."""

from __future__ import annotations

import numpy as np
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
