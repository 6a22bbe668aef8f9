"""The integrated autocorrelation time of an ensemble chain, emcee's estimator computed for all series at once.

emcee's :func:`emcee.autocorr.integrated_time` (3.1) loops in Python over
parameters and walkers, one FFT per series: 70 ms for a chain of 88 steps,
74 walkers and 36 parameters (2,664 FFTs of 256 points), which made the
autocorrelation time the most expensive part of the checks of a run that
stops at its ESS (:mod:`bayescal.bayes.stopping`) and a tenth of a short
run.  :func:`integrated_time` is the same estimator (Sokal's automatic
window, ``c = 5``, the walkers' normalised autocorrelation functions
averaged) with the FFTs taken along the steps of the whole array in one
call: the same numbers to rounding (tests/bayes/test_autocorr.py compares
them with emcee's on chains of known autocorrelation), in about 2 ms.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

__all__ = ["integrated_time"]


def integrated_time(x: ArrayLike, c: float = 5.0) -> NDArray:
    """Integrated autocorrelation time per parameter of an ensemble chain, in steps.

    Parameters
    ----------
    x : array_like, shape (n_steps, n_walkers, n_params)
        The chain (emcee's ``get_chain()`` layout).
    c : float
        Window factor: the sum runs to the first lag ``M`` with ``M >= c tau(M)``.

    Returns
    -------
    ndarray, shape (n_params,)
        ``tau = 2 sum_{t < M} rho(t) - 1`` with ``rho`` the walkers' mean
        normalised autocorrelation function; NaN for a parameter one of
        whose walkers never moved (its autocorrelation is 0 / 0), as emcee's.

    Notes
    -----
    Unlike emcee it does not warn or raise when the chain is shorter than
    50 autocorrelation times: the caller checks the chain length
    (:func:`bayescal.bayes.mcmc.sample_posterior` reports it).
    """
    x = np.asarray(x, dtype=float)
    if x.ndim != 3 or x.shape[0] < 1:
        raise ValueError(f"integrated_time: expected a chain (n_steps, n_walkers, n_params), got shape {x.shape}")
    n_t = x.shape[0]
    n = 1 << max(n_t - 1, 0).bit_length()  # the next power of two >= n_t, emcee's FFT length is 2 n
    f = np.fft.rfft(x - x.mean(axis=0), n=2 * n, axis=0)
    acf = np.fft.irfft(f * np.conjugate(f), n=2 * n, axis=0)[:n_t]
    with np.errstate(invalid="ignore", divide="ignore"):
        acf = acf / acf[0]
    rho = acf.mean(axis=1)  # (n_t, n_params)
    taus = 2.0 * np.cumsum(rho, axis=0) - 1.0
    inside = np.arange(n_t)[:, None] < c * taus
    # the first lag outside the window, or the last lag when every lag is inside (emcee's auto_window)
    window = np.where(inside.any(axis=0), np.argmin(inside, axis=0), n_t - 1)
    return taus[window, np.arange(taus.shape[1])]
