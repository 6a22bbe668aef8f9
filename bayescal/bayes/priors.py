"""Gaussian priors on the geometric errors, from the machine file's tolerances.

The prior of every machine kind is

    theta ~ N(mu, diag(s^2)),

``s`` the one-sigma tolerance of each parameter's group (the machine file's
``[tolerance]`` table, documented defaults otherwise) and ``mu`` nominal
(zeros) unless a different mean is given.  With ``phi = (theta - mu) / s``
and the whitened, tolerance-scaled identification matrix ``A = W J S``
(``W`` = 1 / instrument sigma), the negative log-posterior of the linearised
model is

    |W (y - h)|^2 + |phi|^2,

which is ridge estimation with ``lam = 1``.  A general ``lam`` is the
ratio of noise variance to prior variance: ridge with ``lam`` is the MAP
estimate under the same prior with every tolerance divided by
``sqrt(lam)`` (or, equivalently, with every instrument sigma multiplied by
``sqrt(lam)``).  The MAP estimate therefore reuses the Gauss-Newton loop of
:func:`bayescal.identify.identify` (``method="map"``).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..constants import PRIOR_SCALES
from ..errors import InputError
from ..identify import IdentificationResult, identify
from ..identify.choose import evidence_lambda, linearised_problem
from ..identify.free import same_free
from ..machines.base import Machine
from ..measurement import MeasurementModel

__all__ = ["GaussianPrior", "prior_from_machine", "map_estimate", "empirical_bayes_map", "PRIOR_SCALES"]

# PRIOR_SCALES, the values of ``prior_scale`` in map_estimate, is defined in bayescal.constants (the command line
# offers them without importing numpy) and exported from here as before.

@dataclass(frozen=True)
class GaussianPrior:
    """``N(mean, diag(std^2))`` over a machine's parameter vector.

    Attributes
    ----------
    names : tuple of str
    mean : ndarray, shape (P,)
        mm or rad, per the layout's units.
    std : ndarray, shape (P,)
        One-sigma, same units.
    lower : ndarray, shape (P,), optional
        Physical lower bounds (``-inf``: none), e.g. a compliance or a mass
        that cannot be negative: the density is the Gaussian truncated there.
        Only :meth:`logpdf` (what samplers see) applies them; the MAP and its
        Laplace covariance are the untruncated Gaussian's (a diagnosis must be
        able to see a fit beyond a bound, docs/diagnose.md).
    upper : ndarray, shape (P,), optional
        Upper bounds (``inf``: none), the user's (:meth:`within`), applied as :attr:`lower` is.
    """

    names: tuple[str, ...]
    mean: NDArray
    std: NDArray
    lower: NDArray | None = None
    upper: NDArray | None = None

    @property
    def covariance(self) -> NDArray:
        return np.diag(self.std**2)

    def subset(self, idx: ArrayLike) -> "GaussianPrior":
        """The marginal prior of parameters ``idx`` (independent, so just a selection)."""
        idx = np.asarray(idx, dtype=int)
        return GaussianPrior(tuple(self.names[i] for i in idx), self.mean[idx], self.std[idx],
                             None if self.lower is None else self.lower[idx],
                             None if self.upper is None else self.upper[idx])

    def within(self, lower: NDArray, upper: NDArray) -> "GaussianPrior":
        """This prior truncated to ``lower <= theta <= upper`` as well (shape (P,) each, infinite: no bound)."""
        lo = lower if self.lower is None else np.maximum(self.lower, lower)
        hi = upper if self.upper is None else np.minimum(self.upper, upper)
        return GaussianPrior(self.names, self.mean, self.std, np.asarray(lo, dtype=float), np.asarray(hi, dtype=float))

    def logpdf(self, theta: ArrayLike) -> NDArray:
        """Log density at ``theta`` of shape (..., P): normalised without the bounds; ``-inf`` beyond them.

        With bounds the normalisation of the truncation (a constant) is left
        out: samplers use only differences.
        """
        theta = np.asarray(theta, dtype=float)
        z = (theta - self.mean) / self.std
        lp = -0.5 * np.sum(z**2, axis=-1) - np.sum(np.log(self.std)) - 0.5 * self.std.size * np.log(2 * np.pi)
        if self.lower is not None:
            lp = np.where(np.any(theta < self.lower, axis=-1), -np.inf, lp)
        if self.upper is not None:
            lp = np.where(np.any(theta > self.upper, axis=-1), -np.inf, lp)
        return lp

    def sample(self, n: int, rng: np.random.Generator) -> NDArray:
        """``n`` draws, shape (n, P) (of the truncated Gaussian where a bound is set: redrawn until within it)."""
        out = self.mean + rng.normal(size=(n, self.std.size)) * self.std
        if self.lower is not None or self.upper is not None:
            lo = -np.inf if self.lower is None else self.lower
            hi = np.inf if self.upper is None else self.upper
            for _ in range(1000):
                bad = (out < lo) | (out > hi)
                if not bad.any():
                    break
                out[bad] = (self.mean + rng.normal(size=out.shape) * self.std)[bad]
            else:
                raise InputError("GaussianPrior.sample: a bound lies too far from the mean to sample by redrawing")
        return out


def prior_from_machine(machine: Machine, *, mean: ArrayLike | None = None, scale: float = 1.0) -> GaussianPrior:
    """The tolerance prior of ``machine``.

    Parameters
    ----------
    machine : Machine
        Its ``tolerance`` (from ``[tolerance]`` or the kind's defaults) are the prior std.
    mean : array_like, shape (P,), optional
        Prior mean of the errors (e.g. a previous calibration); by default
        the machine's :attr:`~bayescal.machines.base.Machine.prior_mean`
        where a view states one (effect parameters centred on their prior,
        :mod:`bayescal.effects.joint_model`), else zeros.  Likewise the lower
        bounds are the machine's ``prior_lower`` (the effects' physical
        bounds), else none.
    scale : float
        Multiplies every std (e.g. to test prior sensitivity).
    """
    P = machine.n_params
    if mean is None:
        mean = machine.prior_mean
    mu = np.zeros(P) if mean is None else np.asarray(mean, dtype=float)
    if mu.shape != (P,):
        raise InputError(f"mean: expected shape ({P},), got {mu.shape}")
    if not scale > 0:
        raise InputError(f"scale: expected a positive number, got {scale!r}")
    lower = machine.prior_lower
    return GaussianPrior(machine.layout.names, mu, np.asarray(machine.tolerance, dtype=float) * scale,
                         None if lower is None else np.asarray(lower, dtype=float))


def map_estimate(
    model: MeasurementModel,
    *,
    prior: GaussianPrior | None = None,
    free: ArrayLike | str | None = None,
    max_iter: int = 50,
    prior_scale: str = "tolerance",
    theta0: ArrayLike | None = None,
    first: IdentificationResult | None = None,
) -> IdentificationResult:
    """Maximum a posteriori errors under a Gaussian prior (Gauss-Newton, Laplace covariance).

    Parameters
    ----------
    model : MeasurementModel
        With measured values.
    prior : GaussianPrior, optional
        Default: :func:`prior_from_machine` of the model's machine.
    free : "auto", "all" or names, optional
        As in :func:`bayescal.identify.identify`; with a prior, ``"all"`` is
        well posed (the prior decides what the data cannot).
    prior_scale : {"tolerance", "empirical"}
        "empirical": multiply every prior std by one factor estimated from
        the data (:func:`empirical_bayes_map`), for when the tolerances may
        be too tight or too loose.
    theta0 : array_like, shape (P,), optional
        Where Gauss-Newton starts; by default the model's ``theta_start``
        where it has one, else the prior mean.  A model whose
        parameters enter as products (an effect's mass times its
        compliances, :mod:`bayescal.effects.joint_model`) needs a start off
        the prior mean, where their gradient vanishes.
    first : IdentificationResult, optional
        This very MAP (``prior`` unscaled, from this start, with this
        ``free``), already computed by the caller; used instead of fitting
        it again (:func:`bayescal.bayes.map_identify.identify_map` has it
        from its robust pass).

    Returns
    -------
    IdentificationResult
        ``method == "map"``, covariance ``(J^T R^-1 J + P0^-1)^-1`` at the MAP.
    """
    prior = prior_from_machine(model.machine) if prior is None else prior
    if theta0 is None:
        theta0 = model.theta_start
    start = prior.mean if theta0 is None else np.asarray(theta0, dtype=float)
    if start.shape != prior.mean.shape:
        raise InputError(f"theta0: expected shape {prior.mean.shape}, got {start.shape}")
    if prior_scale == "empirical":
        return empirical_bayes_map(model, prior=prior, free=free, max_iter=max_iter, theta0=start, first=first)
    if prior_scale != "tolerance":
        raise InputError(f"prior_scale: expected one of {', '.join(PRIOR_SCALES)}, got {prior_scale!r}")
    if first is not None:
        return first
    return identify(
        model, method="map", free=free, theta0=start, scale=prior.std, prior_mean=prior.mean, max_iter=max_iter
    )


def empirical_bayes_map(
    model: MeasurementModel,
    *,
    prior: GaussianPrior | None = None,
    free: ArrayLike | str | None = None,
    max_iter: int = 50,
    max_rounds: int = 4,
    scale_bounds: tuple[float, float] = (0.05, 20.0),
    theta0: ArrayLike | None = None,
    first: IdentificationResult | None = None,
) -> IdentificationResult:
    """MAP and Laplace covariance with the prior's scale estimated from the data (empirical Bayes).

    The prior ``N(mean, (c std)^2)`` with one factor ``c`` for every
    parameter; ``c`` maximises the marginal likelihood (evidence) of the
    model linearised at the current MAP, ``c = 1 / sqrt(lam_ev)`` with
    ``lam_ev`` from :func:`bayescal.identify.choose.evidence_lambda` (the
    ``evidence`` rule of ridge).  MAP and evidence alternate until ``c``
    moves by less than 5 % (at most ``max_rounds`` times).  When the
    tolerances are right, ``c`` is near 1 and the result is the ordinary
    MAP; when the machine is 2 or 4 times worse (or better) than the
    tolerances say, the intervals widen (narrow) with it instead of being
    overconfident (needlessly wide).

    Parameters
    ----------
    model : MeasurementModel
        With measured values.
    prior : GaussianPrior, optional
        The prior to rescale (default: the tolerance prior).
    free : "auto", "all" or names, optional
        As in :func:`map_estimate`.
    max_iter : int
        Gauss-Newton iterations per MAP.
    max_rounds : int
        MAP / evidence alternations.
    scale_bounds : (float, float)
        ``c`` is kept within these factors (dimensionless): a handful of
        parameters cannot tell a scale of 1e-3 from 1e-4.
    theta0 : array_like, shape (P,), optional
        Where the first MAP starts (:func:`map_estimate`); the prior mean by default.
    first : IdentificationResult, optional
        The first MAP (scale 1, from ``theta0``, with ``free``) when the caller has it (:func:`map_estimate`).

    Returns
    -------
    IdentificationResult
        ``method == "map"``; ``extras["prior_scale"]`` is ``c`` and
        ``extras["prior_scale_rounds"]`` the rounds used.
    """
    prior = prior_from_machine(model.machine) if prior is None else prior
    lo, hi = scale_bounds
    if not 0 < lo <= 1 <= hi:
        raise InputError(f"scale_bounds: expected 0 < low <= 1 <= high, got {scale_bounds!r}")
    known = bool(model.machine.noise.given)

    def fit(c, start, free_now):
        std = prior.std * c
        return identify(model, method="map", free=free_now, theta0=start, scale=std, prior_mean=prior.mean,
                        max_iter=max_iter)

    if first is None:
        first = fit(1.0, prior.mean if theta0 is None else np.asarray(theta0, dtype=float), free)
    res = first
    c, rounds = 1.0, 0
    while res.success and rounds < max_rounds:
        rounds += 1
        idx = np.flatnonzero(res.free)
        # the deviation from the prior mean, tolerance-scaled: A x ~ z with x = (theta - mean) / std
        A, z, _ = linearised_problem(model, res.theta, idx, prior.std)
        z = z - A @ (prior.mean[idx] / prior.std[idx])
        c_new = float(np.clip(1.0 / np.sqrt(evidence_lambda(A, z, noise_known=known)), lo, hi))
        moved = abs(np.log(c_new / c)) >= np.log(1.05)
        c = c_new
        res = fit(c, res.theta, same_free(res))  # warm start; the covariance is the Laplace one at this c
        if not moved:
            break
    return _scaled_answer(res, first, c, rounds)


def _scaled_answer(res, first, c: float, rounds: int):
    """The last fit of :func:`empirical_bayes_map` labelled with its prior scale ``c`` (and, failed, only that)."""
    if not res.success:
        return replace(res, extras={**res.extras, "prior_scale": c, "prior_scale_rounds": rounds})
    # later rounds start from the earlier solution: report "before" against the start, and say which prior
    kind = res.covariance_kind.replace("under the tolerance prior", f"under the tolerance prior x {c:.3g} (empirical Bayes)")
    if kind == res.covariance_kind:
        kind += f" (prior: tolerances x {c:.3g}, empirical Bayes)"
    # lam relative to the tolerance scaling (as ridge's): the noise-to-prior variance ratio 1 / c^2
    # the rounds refit at the first fit's free set (indices): its account of what the data do not identify, of
    # what the prior decides and of what the user held is the answer's
    return replace(res, lam=1.0 / c**2, rms_before=first.rms_before, residuals_before=first.residuals_before,
                   covariance_kind=kind, fixed=first.fixed, held=first.held, unidentifiable=first.unidentifiable,
                   decided_by_prior=first.decided_by_prior,
                   extras={**res.extras, "prior_scale": c, "prior_scale_rounds": rounds})
