"""``identify --method map`` as one function: robust pass, the prior-scale rule, MAP.

The command and the studies that measure what it does (leave-one-out on
Klipper recordings, ``studies/delta_klipper.py``) call the same code, so a
study's number is the number a user gets.

The prior-scale rule (docs/bayes.md, docs/delta-printers.md): one factor on
every tolerance, estimated from the evidence (empirical Bayes,
:func:`bayescal.bayes.priors.empirical_bayes_map`), when

* the recording has at least :data:`MIN_ROWS_PER_PARAM` measured components
  per parameter (enough to estimate a scale next to the parameters), or
* the noise is not stated (no ``[measurement]`` table): the stated sigmas
  are then only relative weights, the evidence estimates the ratio of the
  geometry's spread to the noise, and the MAP depends on nothing else.
  A fixed tolerance prior would fix that ratio by a guess instead.

Otherwise the tolerances stand: with the noise stated and few rows, a
scale estimated with the noise held fixed follows the noise's misstatement
(``studies/delta_klipper.py``: 1.3 to 1.4 times Klipper's left-out error
when the noise is five times larger than stated).
"""

from __future__ import annotations

from dataclasses import replace

from ..outliers.handling import map_system, robust_map_pass
from ..measurement import MeasurementModel
from .priors import map_estimate

__all__ = ["MIN_ROWS_PER_PARAM", "default_prior_scale", "identify_map"]

#: Measured components per parameter from which a prior scale is estimated with the noise stated.
MIN_ROWS_PER_PARAM = 3


def default_prior_scale(model: MeasurementModel) -> tuple[str, str | None]:
    """The prior scale ``identify --method map`` uses without ``--prior-scale``, and a note when it is the tolerances.

    Returns
    -------
    scale : {"empirical", "tolerance"}
    note : str or None
        For the report when the tolerances are used as they are.
    """
    from ..identify.noise import distinct_measurements

    # copied rows add components but no information: 36 copies of one pose must not set the scale
    n_distinct = distinct_measurements(model)
    n_rows = n_distinct * model.dof
    if n_rows >= MIN_ROWS_PER_PARAM * model.n_params or not model.machine.noise.given:
        return "empirical", None
    copies = f", {model.n_poses - n_distinct} copied rows not counted" if n_distinct < model.n_poses else ""
    return "tolerance", (
        f"prior scale: the machine file's tolerances ({n_rows} distinct measured components{copies} for "
        f"{model.n_params} parameters with the noise stated: too few to estimate a scale; --prior-scale empirical to try)"
    )


def identify_map(model: MeasurementModel, free, *, prior_scale: str | None = None, max_iter: int = 50,
                 robust: str = "auto", **outlier_kw):
    """MAP as ``identify --method map`` computes it; the result and the outlier handling.

    Parameters
    ----------
    model : MeasurementModel
        With measured values.
    free : "auto", "all", names or index array
    prior_scale : {"empirical", "tolerance"}, optional
        Default: :func:`default_prior_scale`.
    max_iter : int
        Gauss-Newton iterations per fit.
    robust : str
        Outlier handling (``--robust``), with ``nu``, ``alpha``, ``lines`` in ``outlier_kw``.

    Returns
    -------
    (IdentificationResult, OutlierHandling)
        The result carries the handling's JSON keys and, with the tolerances
        chosen by the rule, ``prior_scale_note`` in ``extras``.
    """
    # the prior scale is set on the poses weighted as a robust MAP pass weights them: one gross pose must not set it
    pass_fit, handling = robust_map_pass(model, free, max_iter=max_iter, robust=robust, **outlier_kw)
    scale, note = default_prior_scale(model)
    scale = prior_scale or scale
    # without weights the pass's fit is the first MAP below to the last bit (same model, tolerance prior,
    # start and free set): reused, not redone.  A view with a prior mean of its own (effects) starts
    # the MAP there instead of at the pass's start, so it is fitted anew
    same = handling.weights is None and model.machine.prior_mean is None
    res = map_estimate(handling.weighted_model(model), free=free, max_iter=max_iter, prior_scale=scale,
                       first=pass_fit if same else None)
    if prior_scale is None and note is not None:
        res = replace(res, extras={**res.extras, "prior_scale_note": note})
    handling = handling.retested(model, res, map_system(res))
    return replace(res, extras={**res.extras, **handling.to_dict()}), handling
