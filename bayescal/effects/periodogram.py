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
    # imported here: scipy.signal costs about 1 s of start-up, which every command's --help paid (issue 31)
    from scipy.signal import lombscargle

    if np.ptp(y) == 0:
        return np.zeros(len(freqs))
    w = 2 * np.pi * freqs
    # lombscargle holds several (samples x frequencies) arrays at once: 1.4 GB for 50,000 poses and
    # 500 frequencies.  Frequencies are independent (the normalisation is per data set), so chunks
    # of about _CHUNK elements give the same powers in bounded memory.
    step = max(1, _CHUNK // max(len(q), 1))
    return np.concatenate([
        # atleast_1d: scipy returns a 0-d power for a single frequency (a short stroke, e.g. in rad)
        np.atleast_1d(lombscargle(q, y, w[k:k + step], normalize=True, floating_mean=True)) for k in range(0, len(w), step)
    ]) if len(w) else np.zeros(0)
