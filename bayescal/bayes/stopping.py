"""When a posterior run may stop: every convergence check passed with the effective sample size asked for.

A fixed number of steps is either too many (the 3-PRS example's default
1,000 steps of 74 walkers give a bulk ESS of about 43,000 where a few
thousand already put the Monte Carlo error of every mean below a
fiftieth of its posterior standard deviation) or too few (a hard posterior
ends "not converged: run about N more steps", and the run starts over).
:class:`EssStop` lets a run go on until the checks of
:func:`bayescal.bayes.mcmc.sample_posterior` pass with the bulk and tail ESS
asked for, with ``n_steps`` as the most it may take.

The checks run at growing lengths (each a tenth longer than the last, at
least 10 steps), so their cost is a small fraction of the sampling and the
run overshoots the length it needed by about a tenth at most; the chain is
grown from one check to the next, so emcee reserves no storage beyond it
(each growth copies the chain once; the caller's memory check still charges
the most steps, the worst case).  Each check first estimates the
ESS from emcee's integrated autocorrelation time (an FFT per parameter,
milliseconds), and only when that estimate reaches the target runs the
rank-normalised R-hat and the bulk and tail ESS of arviz that the answer
reports.  The chain of a run that stops is the first steps of the run with
the same seed that does not stop (the checks draw no random numbers).

Stopping when a diagnostic first passes selects, in principle, a run whose
diagnostics look better than its draws are: the cheap estimate is looked
at some twenty times in a run, arviz's R-hat and ESS once or twice.  The rule stops on the effective
sample size, which Vats, Flegal and Jones ("Multivariate output analysis
for Markov chain Monte Carlo", Biometrika 106, 2019) justify as a
sequential stopping rule; with a burn-in that grows with the chain and an
ESS in the thousands the selection is well inside the Monte Carlo error
the ESS states (on the linear-Gaussian test problem the stopped means'
errors over 40 seeds had a variance of 1.05 in units of that error).

A resumed run (a checkpoint) is checked where the uninterrupted run would
have been: the checks before the saved length are the ones that failed
when it ran, so it stops where that run stopped, with its draws.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from ..errors import InputError

__all__ = ["EssStop", "checked_ess"]

#: Each check is ``1 / GROWTH`` longer than the one before (a tenth).
GROWTH = 10
#: Fewest steps between two checks.
MIN_GAP = 10
#: Fewest steps before the first check (fewer cannot estimate an autocorrelation time).
MIN_FIRST = 50


def checked_ess(ess) -> float | None:
    """``ess`` as a float, or None; anything but a finite positive number is refused by name.

    Parameters
    ----------
    ess : float, int or None
        Effective sample size asked for (draws; bulk and tail), or None for none.

    Returns
    -------
    float or None

    Raises
    ------
    InputError
        Naming ``ess (--ess)`` for a bool, a string, zero, a negative, NaN or infinite value.
    """
    if ess is None:
        return None
    if isinstance(ess, bool) or not isinstance(ess, (int, float, np.integer, np.floating)) or not (
            math.isfinite(float(ess)) and float(ess) > 0):
        raise InputError(f"ess (--ess): expected a positive effective sample size (e.g. 4000), got {ess!r}")
    return float(ess)


@dataclass(frozen=True)
class EssStop:
    """Stop a run once ``passes(sampler, burn)`` holds with an ESS estimate of at least ``ess``.

    Parameters
    ----------
    ess : float
        Bulk and tail effective sample size asked for.
    n_walkers : int
    tau_factor : float
        The chain after burn-in must be this many autocorrelation times long.
    burn : Callable[[int], int]
        Burn-in (steps) of a chain of the given length: a fifth of it by default, or the caller's fixed one.
    passes : Callable[[emcee.EnsembleSampler, int], bool]
        The full checks (R-hat, bulk and tail ESS, chain length) of the chain after that burn-in.
    tau : Callable[[emcee.EnsembleSampler, int], ndarray]
        Integrated autocorrelation time per parameter (steps) after that burn-in.
    known : dict
        Where ``passes`` may keep what it computed, by ``(steps, burn)`` (the summary of a run that stops there
        takes its R-hat and ESS from it instead of computing them again).
    """

    ess: float
    n_walkers: int
    tau_factor: float
    burn: Callable[[int], int]
    passes: Callable
    tau: Callable
    known: dict = field(default_factory=dict, compare=False)

    def first_check(self) -> int:
        """Steps of the first check: the length that would reach ``ess`` with independent draws after burn-in."""
        kept = math.ceil(self.ess / self.n_walkers)
        steps = MIN_FIRST
        # a chain ``d`` steps longer keeps at most ``d`` more: jump the shortfall (a few jumps, whatever ``ess``)
        while (short := kept - (steps - self.burn(steps))) > 0:
            steps += MIN_GAP * math.ceil(short / MIN_GAP)
        return steps

    @staticmethod
    def next_check(steps: int) -> int:
        """Steps of the check after one at ``steps``."""
        return steps + max(MIN_GAP, steps // GROWTH)

    def check_from(self, steps: int) -> int:
        """The first check at ``steps`` or later (a resumed chain: the checks before it failed when it ran)."""
        check = self.first_check()
        while check < steps:
            check = self.next_check(check)
        return check

    def __call__(self, sampler) -> bool:
        """Whether the chain ``sampler`` holds may stop here."""
        steps = sampler.iteration
        burn = self.burn(steps)
        kept = steps - burn
        if kept < 2:
            return False
        tau = np.asarray(self.tau(sampler, burn), dtype=float)
        if not np.all(np.isfinite(tau)) or kept < self.tau_factor * np.max(tau):
            return False
        # the cheap estimate first; arviz's ranks and FFTs only once it is within reach
        if kept * self.n_walkers / max(float(np.max(tau)), 1.0) < self.ess:
            return False
        return bool(self.passes(sampler, burn))
