"""``identify`` as a user gets it: method dispatch, outliers, the prior scale and the noise check, in one call.

:func:`calibrate` is what ``bayescal identify`` runs for the deterministic
methods (``ls``, ``ridge``, ``tsvd``, ``map``), so a notebook, a study and the
command line get the same answer:

1. the method, with its policy: ``map`` scales the prior from the data by
   :func:`bayescal.bayes.map_identify.identify_map`'s rule; ``lam="auto"`` /
   ``k="auto"`` choose the regularisation by a rule on the recording weighted
   as a robust MAP pass weights it; fixed ``lam`` / ``k`` and ``ls`` fit
   directly;
2. the outlier test of every pose, and a Student-t refit where it flags
   poses (:mod:`bayescal.identify.robust`);
3. the chi-square test of the stated noise (:mod:`bayescal.identify.noise`):
   where the data contradict it, the noise scale is estimated and the
   whole fit redone with it, until the scale settles, so that intervals are
   never narrower than the residuals justify and an overstated noise does
   not leave the calibration to the prior.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from ..errors import InputError
from ..measurement import MeasurementModel
from .noise import NoiseCheck, check_noise, distinct_rows
from .result import IdentificationResult

__all__ = ["Calibration", "calibrate", "noise_check_of", "DETERMINISTIC_METHODS"]

DETERMINISTIC_METHODS = ("ls", "ridge", "tsvd", "map")
#: Rounds of noise-scale re-estimation at most (the scale settles in one for ls and tsvd).
MAX_NOISE_ROUNDS = 6


@dataclass(frozen=True)
class Calibration:
    """The answer of :func:`calibrate`.

    Attributes
    ----------
    result : IdentificationResult
        With the handling's and the noise check's JSON keys in ``extras``.
    handling : OutlierHandling
    choice : RegularisationChoice or None
        The rule's choice for ``lam="auto"`` / ``k="auto"``.
    noise : NoiseCheck
        The test at the stated noise (before any rescaling).
    noise_scale : float
        Factor on the stated sigma the answer uses (1 when the noise fits).
    """

    result: IdentificationResult
    handling: object
    choice: object | None
    noise: NoiseCheck
    noise_scale: float = 1.0

    def noise_report(self) -> str:
        line = f"  noise           {self.noise.message()}"
        if self.noise_scale != 1.0:
            line += f"\n                  sigma used: {self.noise_scale:.3g} x the stated one"
        return line

    def noise_dict(self) -> dict:
        return {"noise": {**self.noise.to_dict(), "scale_used": self.noise_scale}}


def noise_check_of(model: MeasurementModel, res) -> NoiseCheck:
    """The chi-square test of ``res`` (a fit of ``model``), degrees of freedom among the distinct rows."""
    n_distinct = distinct_rows(model.q, model.y_measured) * model.dof
    p_eff = float(np.sum(res.filter_factors)) if np.size(getattr(res, "filter_factors", [])) else float(np.sum(res.free))
    return check_noise(res.chi2, n_distinct - p_eff, stated=bool(model.machine.noise.given))


def _fit_once(model, method, *, lam, k, free, rule, prior_scale, max_iter, outlier_kw, fit_effects):
    from ..bayes.map_identify import identify_map
    from .choose import choose_regularisation
    from .robust import fit_system, identify_with_outliers, robust_map_weights

    choice = None
    auto = (method == "ridge" and lam == "auto") or (method == "tsvd" and k == "auto")
    if method == "map":
        scale = prior_scale
        if fit_effects:
            # one factor estimated for every prior would rescale the effects' priors with the geometry's tolerances
            if scale == "empirical":
                raise InputError("prior_scale: 'empirical' does not go with fitted effects: the effects' priors are "
                                 "not the machine file's tolerances (use 'tolerance')")
            scale = "tolerance"
        res, handling = identify_map(model, free, prior_scale=scale, max_iter=max_iter, **outlier_kw)
    elif auto:
        # the rules see the recording with the weights of a robust MAP pass: one gross pose must not choose lambda or k
        handling = robust_map_weights(model, free, max_iter=max_iter, **outlier_kw)
        choice, res = choose_regularisation(handling.weighted_model(model), method, rule=rule, free=free,
                                            max_iter=max_iter)
        handling = handling.retested(model, res, fit_system(res))
        res = replace(res, extras={**res.extras, **handling.to_dict()})
    else:
        res, handling = identify_with_outliers(model, method=method, lam=lam, k=k, free=free, max_iter=max_iter,
                                               **outlier_kw)
    return res, handling, choice


def calibrate(
    model: MeasurementModel,
    *,
    method: str = "map",
    lam: float | str | None = None,
    k: int | str | None = None,
    free="auto",
    rule: str | None = None,
    prior_scale: str | None = None,
    max_iter: int = 50,
    robust: str = "auto",
    noise: str = "auto",
    fit_effects: bool = False,
    **outlier_kw,
) -> Calibration:
    """Identify the errors of a recording as ``bayescal identify`` does (module docstring).

    Parameters
    ----------
    model : MeasurementModel or ConstraintModel
        With measured values (``bayescal.load`` or ``MeasurementModel.from_recording``).
    method : {"ls", "ridge", "tsvd", "map"}
    lam : float or "auto"
        Ridge parameter (dimensionless, 1 = MAP under the tolerance prior); required for ridge.
    k : int or "auto"
        TSVD rank; required for tsvd.
    free : "auto", "all" or names
    rule : str, optional
        Rule for ``"auto"`` (:data:`bayescal.identify.choose.RULE_NAMES`).
    prior_scale : {"empirical", "tolerance"}, optional
        map only (default: :func:`bayescal.bayes.map_identify.default_prior_scale`).
    max_iter : int
    robust : {"auto", "t", "huber", "off"}
        Outlier handling; ``nu``, ``alpha`` and ``lines`` pass through ``outlier_kw``.
    noise : {"auto", "stated"}
        ``auto``: the stated noise is tested and, where contradicted,
        replaced by the estimated scale; ``stated``: tested and reported only.
    fit_effects : bool
        The model's effect parameters are fitted (map: the prior scale stays the tolerances).

    Returns
    -------
    Calibration
    """
    if method not in DETERMINISTIC_METHODS:
        raise InputError(f"method: expected one of {', '.join(DETERMINISTIC_METHODS)}, got {method!r}")
    if method == "ridge" and lam is None:
        raise InputError("lam: required with method ridge (1: MAP under the tolerance prior, or 'auto')")
    if method == "tsvd" and k is None:
        raise InputError("k: required with method tsvd (a number, or 'auto')")
    if method != "ridge" and lam is not None and not (method == "map" and lam == 1):
        raise InputError(f"lam: goes with method ridge, got lam={lam!r} with method {method!r}")
    if method != "tsvd" and k is not None:
        raise InputError(f"k: goes with method tsvd, got k={k!r} with method {method!r}")
    if prior_scale is not None and method != "map":
        raise InputError("prior_scale: goes with method map")
    if rule is not None and not ((method == "ridge" and lam == "auto") or (method == "tsvd" and k == "auto")):
        raise InputError("rule: goes with method ridge, lam='auto' or method tsvd, k='auto'")
    if noise not in ("auto", "stated"):
        raise InputError(f"noise: expected 'auto' or 'stated', got {noise!r}")
    kw = dict(lam=lam, k=k, free=free, rule=rule, prior_scale=prior_scale, max_iter=max_iter,
              outlier_kw={"robust": robust, **outlier_kw}, fit_effects=fit_effects)
    res, handling, choice = _fit_once(model, method, **kw)
    first = noise_check_of(model, res)
    scale = 1.0
    # without a stated noise ([measurement] absent) the sigmas are weights and the covariance is already scaled
    if noise == "auto" and first.contradicted and res.success:
        res, handling, choice, scale = _with_noise_scale(model, method, kw, first.scale, (res, handling, choice))
    cal = Calibration(result=res, handling=handling, choice=choice, noise=first, noise_scale=scale)
    return replace(cal, result=replace(res, extras={**res.extras, **cal.noise_dict()}))


def _with_noise_scale(model, method, kw, scale, fallback):
    """Refit with the stated sigma times ``scale`` until the reduced chi-square at that sigma is 1 (within 2 %)."""
    base_sigma = np.asarray(model.row_sigma, dtype=float)
    res, handling, choice = fallback
    used = 1.0
    for _ in range(MAX_NOISE_ROUNDS):
        scaled = model.with_pose_sigma(base_sigma * scale)
        res_s, handling_s, choice_s = _fit_once(scaled, method, **kw)
        if not res_s.success:
            break  # keep the last successful fit
        res, handling, choice, used = res_s, handling_s, choice_s, scale
        check = noise_check_of(scaled, res_s)
        if check.verdict == "untestable" or not math.isfinite(check.reduced) or check.reduced <= 0:
            break
        new = scale * math.sqrt(check.reduced)
        if abs(math.log(new / scale)) < math.log(1.02):
            break
        scale = new
    return res, handling, choice, used
