"""Geometric errors as random variables: priors, recursive Kalman updates, MCMC posteriors, grids.

Everything here works on the measurement-model interface
(:class:`bayescal.measurement.MeasurementModel` or the
:class:`~bayescal.bayes.linear.LinearisedModel`), never on a machine kind.

Submodules not imported here (they pull in arviz/emcee or are rarely needed):
:mod:`~bayescal.bayes.mcmc` (``sample_posterior``, ``PosteriorResult``,
``write_posterior``), :mod:`~bayescal.bayes.grid` (``compensation_grid``),
:mod:`~bayescal.bayes.moves`, :mod:`~bayescal.bayes.accuracy`.  See docs/bayes.md.
"""

from .kalman import FilterResult, kalman_filter
from .linear import LinearisedModel, linearise
from .priors import PRIOR_SCALES, GaussianPrior, empirical_bayes_map, map_estimate, prior_from_machine

__all__ = [
    "FilterResult",
    "GaussianPrior",
    "LinearisedModel",
    "kalman_filter",
    "linearise",
    "map_estimate",
    "prior_from_machine",
    "empirical_bayes_map",
    "PRIOR_SCALES",
]
