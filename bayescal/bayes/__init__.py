"""Geometric errors as random variables: priors, recursive Kalman updates, MCMC posteriors, grids.

Everything here works on the measurement-model interface
(:class:`bayescal.measurement.MeasurementModel` or the
:class:`~bayescal.bayes.linear.LinearisedModel`), never on a machine kind.

Submodules not imported here (they pull in arviz/emcee or are rarely needed):
:mod:`~bayescal.bayes.mcmc` (``sample_posterior``, ``PosteriorResult``,
``write_posterior``), :mod:`~bayescal.bayes.grid` (``compensation_grid``),
:mod:`~bayescal.bayes.moves`, :mod:`~bayescal.bayes.accuracy`.  See docs/bayes.md.
"""

from .._lazy import lazy_attributes

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

# imported on first use: the Kalman filter pulls in filterpy and with it scipy.stats (seconds), which
# ``identify --method map`` and the command line's start never need
__getattr__, __dir__ = lazy_attributes(__name__, {
    "FilterResult": ".kalman", "kalman_filter": ".kalman", "LinearisedModel": ".linear", "linearise": ".linear",
    **{name: ".priors" for name in ("PRIOR_SCALES", "GaussianPrior", "empirical_bayes_map", "map_estimate",
                                    "prior_from_machine")},
})
