"""Names and defaults of the library's options, in a module that imports nothing.

The command line's parsers offer these as choices and print them in their
help; the modules that act on them (:mod:`bayescal.bayes.priors`,
:mod:`bayescal.identify.choose`, :mod:`bayescal.outliers.stats`,
:mod:`bayescal.effects.registry`, :mod:`bayescal.design`,
:mod:`bayescal.compare`) import them from here.  Kept apart so that
``bayescal COMMAND --help`` builds its parser without importing numpy or
scipy (issue 31: the help in well under half a second); each name is
defined once, here, and re-exported where it was always found.
"""

from __future__ import annotations

__all__ = [
    "PRIOR_SCALES", "RULES", "CALIBRATED_RULES", "RULE_NAMES", "DEFAULT_RULE", "OUTLIER_ALPHA", "DEFAULT_NU",
    "EFFECT_NAMES", "CRITERIA", "SCALINGS", "COMPARE_METHODS", "METRICS", "DETERMINISTIC_METHODS", "BAYES_METHODS",
    "GRID_METHODS", "BAYES_METHOD_OPTIONS",
]

# ---------------------------------------------------------------- identification methods (bayescal.identify)
#: The methods :func:`bayescal.identify.calibrate.calibrate` runs (a Gauss-Newton fit each).
DETERMINISTIC_METHODS: tuple[str, ...] = ("ls", "ridge", "tsvd", "map")
#: The methods :func:`bayescal.identify.probabilistic.calibrate_bayes` runs (the filter, the sampler).
BAYES_METHODS: tuple[str, ...] = ("kalman", "mcmc")
#: Options of one of :data:`BAYES_METHODS`, with their defaults (given with another method they are refused, not
#: ignored; :func:`~bayescal.identify.calibrate.calibrate` names the method they go with).
BAYES_METHOD_OPTIONS: dict[str, dict] = {
    "kalman": {"variant": "ekf", "process_noise": 0.0},
    "mcmc": {"steps": 1000, "walkers": None, "seed": 0, "progress": False, "surrogate": "none", "checkpoint": None,
             "checkpoint_every": 100, "resume": False, "ess": None},
}
#: The methods a compensation grid's std comes from (:func:`bayescal.bayes.recording_grid.recording_grid`).
GRID_METHODS: tuple[str, ...] = ("map",) + BAYES_METHODS

# ---------------------------------------------------------------- the prior (bayescal.bayes.priors)
#: Values of ``prior_scale`` in :func:`bayescal.bayes.priors.map_estimate`: "tolerance" (the machine
#: file's tolerances as they are) or "empirical" (one common factor on them,
#: estimated from the data by the evidence).
PRIOR_SCALES: tuple[str, ...] = ("tolerance", "empirical")

# ---------------------------------------------------------------- regularisation rules (bayescal.identify.choose)
#: Rules every call computes, in the order reports list them.
RULES: tuple[str, ...] = ("cv", "lcurve", "gcv", "discrepancy", "evidence", "risk", "success")

#: Rules that first calibrate on the problem's design (computed only when asked for).
CALIBRATED_RULES: tuple[str, ...] = ("targets",)

#: Every rule name a caller may ask for.
RULE_NAMES: tuple[str, ...] = RULES + CALIBRATED_RULES

#: Default rule per method, chosen by ``studies/choice_rules.py`` (400
#: linear-Gaussian data sets per situation and truth scale; docs/regularisation.md, "Which rule"):
#: for lambda the Bayes decision for the success event, the prior scale
#: integrated over :data:`bayescal.identify.scale_prior.DEFAULT_HYPERPRIOR`;
#: for k the ``targets`` compromise (success alone leaves a long tail of
#: the ratio where truths are better than the tolerances).
DEFAULT_RULE: dict[str, str] = {"ridge": "success", "tsvd": "targets"}

# ---------------------------------------------------------------- outlying poses (bayescal.outliers.stats)
#: Family-wise level of the outlier test over all poses of a recording (``bayescal.outliers.ALPHA``).
OUTLIER_ALPHA = 0.01
#: Degrees of freedom of the Student-t loss.
DEFAULT_NU = 4.0

# ---------------------------------------------------------------- physical effects (bayescal.effects.registry)
#: The library's effects by stable name (docs/formats.md section 3), in the order they are tried: each is the
#: ``name`` of its :class:`~bayescal.effects.base.Effect` class, and :data:`bayescal.effects.EFFECTS` maps
#: them to the classes in this order.
EFFECT_NAMES: tuple[str, ...] = (
    "joint_compliance", "thermal_expansion", "backlash", "screw_periodic_error", "redundancy_preload",
    "gravity_deflection", "gravity_backlash",
)

# ---------------------------------------------------------------- pose planning (bayescal.design)
#: All criteria, in the order reports list them.
CRITERIA: tuple[str, ...] = ("D", "A", "E", "O1", "O2", "O3", "O4", "O5", "EIG", "I")
#: Column scalings of the candidates' Jacobian.
SCALINGS: tuple[str, ...] = ("tolerance", "candidates")

# ---------------------------------------------------------------- comparisons (bayescal.compare)
#: The methods :mod:`bayescal.compare.methods` registers, by name, with their one-line description
#: (``bayescal compare --help`` lists them).
COMPARE_METHODS: dict[str, str] = {
    "ls": "Gauss-Newton least squares",
    "ridge": "ridge towards nominal (lam=1: MAP under the tolerance prior; lam=auto chooses lam by a rule, "
             "rule=evidence by default)",
    "map": "MAP as identify --method map computes it (prior scale, outliers, noise test)",
    "tsvd": "truncated SVD; k=snr keeps singular values > 1 of the tolerance-scaled matrix, k=auto chooses k by a "
            "rule (rule=cv|lcurve|gcv|discrepancy|evidence|risk)",
    "kalman": "recursive Kalman filter, one update per pose (variant=ekf|ukf)",
    "mcmc": "posterior mean by emcee (steps=400, surrogate=linear|none, ess=N: stop at that ESS); a trial whose "
            "chain has not converged counts as a failure",
}

#: Output-error metrics recorded per method and trial.
METRICS: tuple[str, ...] = ("rms_position", "max_position", "rms_angle")
