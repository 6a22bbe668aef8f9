"""Lomb-Scargle periodograms over actuator position (unevenly sampled, so no FFT)."""

from __future__ import annotations

import hashlib
from collections import OrderedDict

import numpy as np
from numpy.typing import NDArray

__all__ = ["PITCH_RANGE_MM", "PITCH_RANGES", "MIN_PERIODS", "admissible_pitch_range", "pitch_grid", "periodogram", "n_independent_frequencies"]

#: Pitches searched for a periodic actuator error, mm (lead screws 2-40 mm; encoders' sub-periods).
PITCH_RANGE_MM = (1.0, 50.0)
#: Periods searched, by the unit of ``q`` (:data:`bayescal.machines.base.ACTUATOR_UNITS`): mm for a screw or
#: scale; rad for a revolute joint's gears or encoder (tooth mesh of gears with 13-600 teeth, 2 pi / z: 0.01-0.5
#: rad).  Longer periods on a revolute joint (once or twice per turn) are the joint's geometric errors.
PITCH_RANGES = {"mm": PITCH_RANGE_MM, "rad": (0.01, 0.5)}
#: Samples x frequencies per call of scipy's lombscargle (about 32 MB per array it builds).
_CHUNK = 4_000_000
#: Fewest full periods a pitch must fit within the recorded stroke to be admissible: with fewer, a
#: long-pitch sine is indistinguishable from a smooth (e.g. quadratic) error over the stroke.
MIN_PERIODS = 2.0


def admissible_pitch_range(q_span: float, pitch_range=PITCH_RANGE_MM) -> tuple[float, float] | None:
    """Pitches (mm) that fit at least :data:`MIN_PERIODS` full periods in the recorded stroke ``q_span`` (mm).

    Returns ``(pmin, min(pmax, q_span / MIN_PERIODS))``, or None when no pitch of
    ``pitch_range`` fits (a stroke shorter than ``MIN_PERIODS * pmin``).
    """
    pmax = min(float(pitch_range[1]), float(q_span) / MIN_PERIODS)
    if pmax <= pitch_range[0]:
        return None
    return (float(pitch_range[0]), pmax)


def pitch_grid(q_span: float, pitch_range=PITCH_RANGE_MM, oversample: float = 5.0) -> NDArray:
    """Spatial frequencies (cycles/mm) from ``1/pmax`` to ``1/pmin``, ``oversample`` per peak width ``1/q_span``."""
    fmin, fmax = 1.0 / pitch_range[1], 1.0 / pitch_range[0]
    step = 1.0 / (oversample * max(q_span, 1e-9))
    return np.arange(fmin, fmax + step, step)


def n_independent_frequencies(q_span: float, pitch_range=PITCH_RANGE_MM) -> float:
    """About how many independent peaks the searched band holds: ``span (fmax - fmin)``."""
    return max(q_span * (1.0 / pitch_range[0] - 1.0 / pitch_range[1]), 1.0)


#: Periodograms kept by content (:func:`periodogram`): a diagnosis asks for each actuator's twice, in the
#: location tests and for the periodic effect's start pitch, and at 100,000 poses each costs seconds.
_CACHE: OrderedDict = OrderedDict()
_CACHE_SIZE = 16


def _key(*arrays: NDArray) -> bytes:
    h = hashlib.blake2b(digest_size=20)
    for a in arrays:
        h.update(str(a.shape).encode())
        h.update(np.ascontiguousarray(a).tobytes())
    return h.digest()


def periodogram(q: NDArray, y: NDArray, freqs: NDArray) -> NDArray:
    """Normalised generalised Lomb-Scargle power (0..1) of ``y`` sampled at ``q``, per frequency (cycles/unit of q).

    The floating-mean form (Zechmeister and Kuerster 2009), so an offset
    left in ``y`` does not leak into the low frequencies.  The last few
    answers are kept by the content of ``q``, ``y`` and ``freqs`` (a copy is
    returned), so asking again for the same data costs a hash.
    """
    y = np.asarray(y, float)
    q, freqs = np.asarray(q, float), np.asarray(freqs, float)
    key = _key(q, y, freqs)
    if key in _CACHE:
        _CACHE.move_to_end(key)
        return _CACHE[key].copy()
    power = _periodogram(q, y, freqs)
    _CACHE[key] = power.copy()
    if len(_CACHE) > _CACHE_SIZE:
        _CACHE.popitem(last=False)
    return power


def _periodogram(q: NDArray, y: NDArray, freqs: NDArray) -> NDArray:
    if np.ptp(y) == 0:
        return np.zeros(len(freqs))
    w = 2 * np.pi * freqs
    if len(w) < 3 or not np.allclose(np.diff(w), w[1] - w[0], rtol=1e-9, atol=0.0):
        return _scipy_periodogram(q, y, w)
    return _uniform_grid_periodogram(q, y, w)


#: Rows (frequencies) of the cosine and sine blocks of :func:`_uniform_grid_periodogram`: about 16 MB each at
#: most, and each block starts again from the exact angles (the recurrence's round-off grows with its steps).
_ROWS_BYTES = 16 * 2**20
_MAX_ROWS = 64


def _uniform_grid_periodogram(q: NDArray, y: NDArray, w: NDArray) -> NDArray:
    """scipy's generalised Lomb-Scargle power (normalised, floating mean) on an evenly spaced grid ``w`` (rad/unit).

    Written here because scipy's ``lombscargle`` evaluates four sines or cosines of every (sample, frequency)
    pair and holds several such arrays; on an evenly spaced grid ``cos((w + dw) q)`` and ``sin((w + dw) q)``
    follow from the previous frequency's by one rotation through ``dw q`` (four products per sample), and
    the sums are matrix-vector products.  At 100,000 samples and 491 frequencies: 0.37 s against 5.4-5.9 s
    for scipy, powers within 4e-14 of its (tests/effects/test_periodogram.py compares every grid with
    scipy's).  The power is scipy's expression: the phase ``tau`` that removes the cosine-sine covariance,
    the rotated (centred) sums, their clamp at ``epsneg`` and ``(YC^2 / CC + YS^2 / SS) / YY``
    (Zechmeister and Kuerster 2009), with the rotation applied to the sums instead of the samples.
    """
    n = q.size
    y = y - y.mean()
    yy = float(y @ y) / n
    cd, sd = np.cos((w[1] - w[0]) * q), np.sin((w[1] - w[0]) * q)
    rows = int(max(2, min(_MAX_ROWS, _ROWS_BYTES // (8 * n))))
    c, s, tmp = np.empty((rows, n)), np.empty((rows, n)), np.empty(n)
    out = np.empty(len(w))
    for k in range(0, len(w), rows):
        m = min(rows, len(w) - k)
        np.cos(w[k] * q, out=c[0])
        np.sin(w[k] * q, out=s[0])
        for j in range(1, m):
            np.multiply(c[j - 1], cd, out=c[j])
            c[j] -= np.multiply(s[j - 1], sd, out=tmp)
            np.multiply(s[j - 1], cd, out=s[j])
            s[j] += np.multiply(c[j - 1], sd, out=tmp)
        out[k : k + m] = _power(c[:m], s[:m], y, yy)
    return out


def _power(c: NDArray, s: NDArray, y: NDArray, yy: float) -> NDArray:
    """Normalised power of the centred ``y`` (variance ``yy``) per row of the cosines ``c`` and sines ``s``."""
    n = y.size
    C, S = c.sum(axis=1) / n, s.sum(axis=1) / n
    c2 = np.einsum("ij,ij->i", c, c) / n
    cc, ss = c2 - C * C, (1.0 - c2) - S * S
    cs = np.einsum("ij,ij->i", c, s) / n - C * S
    yc, ys = c @ y / n, s @ y / n  # y is centred: the means' terms vanish
    tau = 0.5 * np.arctan2(2.0 * cs, cc - ss)
    ct, st = np.cos(tau), np.sin(tau)
    yc_t, ys_t = yc * ct + ys * st, ys * ct - yc * st
    eps = np.finfo(float).epsneg
    cc_t = np.maximum(cc * ct * ct + 2.0 * cs * ct * st + ss * st * st, eps)
    ss_t = np.maximum(ss * ct * ct - 2.0 * cs * ct * st + cc * st * st, eps)
    return (yc_t * yc_t / cc_t + ys_t * ys_t / ss_t) / yy


def _scipy_periodogram(q: NDArray, y: NDArray, w: NDArray) -> NDArray:
    """scipy's ``lombscargle`` (normalised, floating mean) at angular frequencies ``w``, in chunks."""
    # imported here: scipy.signal costs about 1 s of start-up, which every command's --help paid (issue 31)
    from scipy.signal import lombscargle

    # lombscargle holds several (samples x frequencies) arrays at once: 1.4 GB for 50,000 poses and
    # 500 frequencies.  Frequencies are independent (the normalisation is per data set), so chunks
    # of about _CHUNK elements give the same powers in bounded memory.
    step = max(1, _CHUNK // max(len(q), 1))
    return np.concatenate([
        # atleast_1d: scipy returns a 0-d power for a single frequency (a short stroke, e.g. in rad)
        np.atleast_1d(lombscargle(q, y, w[k:k + step], normalize=True, floating_mean=True)) for k in range(0, len(w), step)
    ]) if len(w) else np.zeros(0)
