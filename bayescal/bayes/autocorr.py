"""The integrated autocorrelation time of an ensemble chain, emcee's estimator computed for all series at once.

emcee's :func:`emcee.autocorr.integrated_time` (3.1) loops in Python over
parameters and walkers, one FFT per series: 70 ms for a chain of 88 steps,
74 walkers and 36 parameters (2,664 FFTs of 256 points), which made the
autocorrelation time the most expensive part of the checks of a run that
stops at its ESS (:mod:`bayescal.bayes.stopping`) and a tenth of a short
run; and it slows down a long chain's summary.  :func:`integrated_time` is the same estimator (Sokal's automatic
window, ``c = 5``, the walkers' normalised autocorrelation functions
averaged) with the FFTs of all walkers taken in one call per block of
parameters, each series contiguous along its steps: the same numbers to
rounding (tests/bayes/test_autocorr.py compares them with emcee's), 14 ms
at 88 steps, 94 ms at 800 and 360 ms at 3,200 of 74 walkers and 36
parameters (emcee's loop: 69, 194 and 767 ms), in about 2.5 times the
chain's memory.  A walker that never moved
makes the parameter's time NaN, as in emcee (where it is 0 / 0), whatever
the rounding of its mean: a stuck walker fails the convergence checks.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

__all__ = ["integrated_time"]

#: Parameters transformed together: a block's padded FFT is (walkers, _BLOCK, 2 n) wide.
_BLOCK = 8


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
        Computed a block of parameters at a time (memory about 2.5 times the chain's).

    Notes
    -----
    Unlike emcee it does not warn or raise when the chain is shorter than
    50 autocorrelation times: the caller checks the chain length
    (:func:`bayescal.bayes.mcmc.sample_posterior` reports it).
    """
    x = np.asarray(x, dtype=float)
    if x.ndim != 3 or x.shape[0] < 1:
        raise ValueError(f"integrated_time: expected a chain (n_steps, n_walkers, n_params), got shape {x.shape}")
    n_t, n_w, n_d = x.shape
    n = 1 << max(n_t - 1, 0).bit_length()  # the next power of two >= n_t: emcee's FFT length is 2 n
    rho = np.empty((n_t, n_d))
    # each series contiguous along the steps (the FFTs' axis), a few parameters at a time: the padded transform of
    # a block is (walkers, BLOCK, n + 1) complex, not a copy of the whole chain several times over
    for lo in range(0, n_d, _BLOCK):
        series = np.ascontiguousarray(np.moveaxis(x[:, :, lo:lo + _BLOCK], 0, -1))  # (n_w, block, n_t)
        stuck = np.ptp(series, axis=-1) == 0  # a walker that never moved: 0 / 0 in emcee, NaN here explicitly
        series -= series.mean(axis=-1, keepdims=True)
        f = np.fft.rfft(series, n=2 * n, axis=-1)
        acf = np.fft.irfft(f.real**2 + f.imag**2, n=2 * n, axis=-1)[..., :n_t]  # |F|^2: the same as F conj(F)
        with np.errstate(invalid="ignore", divide="ignore"):
            acf = acf / acf[..., :1]
        acf[stuck] = np.nan
        rho[:, lo:lo + _BLOCK] = acf.mean(axis=0).T
    taus = 2.0 * np.cumsum(rho, axis=0) - 1.0
    inside = np.arange(n_t)[:, None] < c * taus
    # emcee's auto_window: the first lag outside the window (argmin of `inside`; lag 0 if every lag is inside, as
    # emcee's), the last lag when no lag is inside (a NaN tau)
    window = np.where(inside.any(axis=0), np.argmin(inside, axis=0), n_t - 1)
    return taus[window, np.arange(n_d)]
