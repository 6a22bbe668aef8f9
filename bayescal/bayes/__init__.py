"""Geometric errors as random variables: priors, recursive Kalman updates, MCMC posteriors, grids.

Everything here works on the measurement-model interface
(:class:`bayescal.measurement.MeasurementModel` or the
:class:`~bayescal.bayes.linear.LinearisedModel`), never on a machine kind.
"""

from .kalman import FilterResult, kalman_filter
from .linear import LinearisedModel, linearise
from .priors import GaussianPrior, map_estimate, prior_from_machine

__all__ = [
    "FilterResult",
    "GaussianPrior",
    "LinearisedModel",
    "kalman_filter",
    "linearise",
    "map_estimate",
    "prior_from_machine",
]
