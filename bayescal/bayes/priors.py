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

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..errors import InputError
from ..identify import IdentificationResult, identify
from ..machines.base import Machine
from ..measurement import MeasurementModel

__all__ = ["GaussianPrior", "prior_from_machine", "map_estimate"]


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
    """

    names: tuple[str, ...]
    mean: NDArray
    std: NDArray

    @property
    def covariance(self) -> NDArray:
        return np.diag(self.std**2)

    def subset(self, idx: ArrayLike) -> "GaussianPrior":
        """The marginal prior of parameters ``idx`` (independent, so just a selection)."""
        idx = np.asarray(idx, dtype=int)
        return GaussianPrior(tuple(self.names[i] for i in idx), self.mean[idx], self.std[idx])

    def logpdf(self, theta: ArrayLike) -> NDArray:
        """Log density at ``theta`` of shape (..., P) (normalised)."""
        z = (np.asarray(theta, dtype=float) - self.mean) / self.std
        return -0.5 * np.sum(z**2, axis=-1) - np.sum(np.log(self.std)) - 0.5 * self.std.size * np.log(2 * np.pi)

    def sample(self, n: int, rng: np.random.Generator) -> NDArray:
        """``n`` draws, shape (n, P)."""
        return self.mean + rng.normal(size=(n, self.std.size)) * self.std


def prior_from_machine(machine: Machine, *, mean: ArrayLike | None = None, scale: float = 1.0) -> GaussianPrior:
    """The tolerance prior of ``machine``.

    Parameters
    ----------
    machine : Machine
        Its ``tolerance`` (from ``[tolerance]`` or the kind's defaults) are the prior std.
    mean : array_like, shape (P,), optional
        Prior mean of the errors (e.g. a previous calibration); zeros by default.
    scale : float
        Multiplies every std (e.g. to test prior sensitivity).
    """
    P = machine.n_params
    mu = np.zeros(P) if mean is None else np.asarray(mean, dtype=float)
    if mu.shape != (P,):
        raise InputError(f"mean: expected shape ({P},), got {mu.shape}")
    if not scale > 0:
        raise InputError(f"scale: expected a positive number, got {scale!r}")
    return GaussianPrior(machine.layout.names, mu, np.asarray(machine.tolerance, dtype=float) * scale)


def map_estimate(
    model: MeasurementModel,
    *,
    prior: GaussianPrior | None = None,
    free: ArrayLike | str | None = None,
    max_iter: int = 50,
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

    Returns
    -------
    IdentificationResult
        ``method == "map"``, covariance ``(J^T R^-1 J + P0^-1)^-1`` at the MAP.
    """
    prior = prior_from_machine(model.machine) if prior is None else prior
    return identify(
        model, method="map", free=free, theta0=prior.mean, scale=prior.std, prior_mean=prior.mean, max_iter=max_iter
    )
