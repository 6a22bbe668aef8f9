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
   poses (:mod:`bayescal.outliers.handling`);
3. the chi-square test of the stated noise (:mod:`bayescal.identify.noise`):
   where the data contradict it, the noise scale is estimated and the
   whole fit redone with it, until the scale settles, so that intervals are
   never narrower than the residuals justify and an overstated noise does
   not leave the calibration to the prior; before it, the position and the
   orientation rows are tested apart and, where they disagree, each
   contradicted sigma is rescaled on its own (:mod:`bayescal.identify.group_noise`);
4. with ``discrepancy="auto"`` or ``"on"``, a model discrepancy
   (:mod:`bayescal.discrepancy`) fitted to what the geometry leaves, off
   the span of the identification Jacobian; ``auto`` keeps it only where the
   marginal likelihood supports it.  The noise is then tested with the
   discrepancy accounted for, the geometry refitted at the noise that
   supports, and the discrepancy's weights refitted at that geometry.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np

from ..constants import BAYES_METHOD_OPTIONS, DETERMINISTIC_METHODS
from ..contract import scale_noise, whiten
from ..errors import InputError
from ..limits import check_lam, finite_real
from ..measurement import MeasurementModel
from .free import with_fixed
from .group_noise import group_report, group_scales, tool_group_checks, with_group_scales
from .noise import NoiseCheck, check_noise, distinct_rows
from .result import IdentificationResult

__all__ = ["Calibration", "calibrate", "noise_check_of", "DETERMINISTIC_METHODS"]

#: Rounds of noise-scale re-estimation at most (the scale settles in one for ls and tsvd).
MAX_NOISE_ROUNDS = 6
#: Smallest factor on a stated noise: residuals a thousand times below it come from a noise-free (simulated)
#: recording or from copied rows, and regions narrower than that would claim more than any instrument gives.
MIN_NOISE_SCALE = 1e-3
#: Smallest estimate of an unstated noise, relative to the row weights (the calibration record's lower bound).
MIN_UNSTATED_SCALE = 1e-6


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
    discrepancy : DiscrepancyFit or None
        The model discrepancy fitted with the geometry (``discrepancy="auto"`` / ``"on"``).
    variance_factor, loo_ratio : float
        The leave-one-pose-out factor on predictive covariances (:mod:`bayescal.prediction.loo`).
    model : MeasurementModel
        What was calibrated (for :meth:`write_machine` and held-out scoring).
    """

    result: IdentificationResult
    handling: object
    choice: object | None
    noise: NoiseCheck
    noise_scale: float = 1.0
    discrepancy: object | None = None
    discrepancy_note: str = ""
    variance_factor: float = 1.0
    loo_ratio: float = 1.0
    model: object = field(default=None, repr=False, compare=False)
    #: The plausibility verdict (:func:`bayescal.identify.answer.identify_answer` sets it): an implausible
    #: calibration is not written by :meth:`write_machine` unless forced.
    plausibility: object | None = None
    #: The machine :meth:`write_machine` writes by default (None: the model's); with effects fitted with the
    #: geometry, the file's machine carrying the fitted tables (:func:`bayescal.calibrate` sets it).
    machine: object | None = field(default=None, repr=False, compare=False)

    # ------------------------------------------------------------ the answer
    @property
    def parameters(self):
        """The parameters by name: value, std, unit, identified (:class:`ParameterEstimate`)."""
        return {p.name: p for p in self.result.parameters}

    def to_dict(self) -> dict:
        """The JSON answer of ``bayescal identify`` (docs/formats.md section 3), in JSON's own types.

        From :func:`bayescal.calibrate` (which passes it through
        :func:`bayescal.identify.answer.identify_answer`) it holds every key the
        command writes, the instrument frame, plausibility and held-out rows
        included: ``bayescal.io.answers.json_text(cal.to_dict())`` is the
        command's ``--json`` file, byte for byte.
        """
        from ..io.answers import to_jsonable

        return to_jsonable(self.result.to_dict())

    def report(self) -> str:
        """The report ``bayescal identify`` prints: fit, parameters, noise, discrepancy, outliers."""
        parts = [self.result.report(), self.noise_report(), self.discrepancy_report(), self.handling.report()]
        return "\n".join(p for p in parts if p)

    def _repr_html_(self) -> str:
        from html import escape

        rows = "".join(
            f"<tr><td>{escape(p.name)}</td><td>{p.value:.6g}</td><td>{'' if p.std is None else f'{p.std:.3g}'}</td>"
            f"<td>{escape(p.unit)}</td><td>{'data' if p.identified else 'prior'}</td></tr>"
            for p in self.result.parameters if p.estimated)
        r = self.result
        head = (f"<p><b>{escape(r.machine_name)}</b> ({escape(r.kind)}), {escape(r.method)}: "
                f"{'converged' if r.success else 'FAILED'}; RMS position {r.rms_before['position']:.4g} mm before, "
                f"{r.rms_after['position']:.4g} mm after; {escape(self.noise.message())}</p>")
        return head + ("<table><tr><th>parameter</th><th>value</th><th>std</th><th>unit</th><th>determined by</th></tr>"
                       f"{rows}</table>")

    def machine_with_record(self, machine=None):
        """The calibrated machine as it is written: ``nominal + theta`` folded later, its record and discrepancy attached."""

        if machine is None:
            machine = self.model.machine if self.machine is None else self.machine
        return machine.with_calibration(self.record(machine.base_machine()), self.discrepancy_model)

    def write_machine(self, path, machine=None, *, force: bool = False) -> list:
        """Write the calibrated machine file (geometry folded in, ``[calibration]``, ``[discrepancy]``), atomically.

        ``machine``: the machine that was calibrated (default: :attr:`machine`, else the model's).
        Returns the files written (a hybrid machine writes one per module).
        A calibration judged implausible (:attr:`plausibility`) is refused, as
        ``bayescal identify --write-machine`` refuses it, unless ``force``.
        """
        from ..machines.files import write_calibrated_machine_files
        from ..instrument.plausibility import refuse_implausible

        if not self.result.success:
            raise InputError(f"write_machine: the calibration did not succeed ({self.result.message})")
        refuse_implausible(self.plausibility, force)
        m = self.machine_with_record(machine)
        return write_calibrated_machine_files(path, m, self.result.theta[: m.n_params])

    @property
    def discrepancy_model(self):
        """The fitted :class:`~bayescal.discrepancy.Discrepancy` (None without one)."""
        return None if self.discrepancy is None else self.discrepancy.discrepancy

    @property
    def joint_covariance(self):
        """Covariance of the free parameters and the discrepancy's weights (None without either)."""
        if self.result.covariance is None:
            return None
        if self.discrepancy is None:
            return self.result.covariance
        return self.discrepancy.covariance

    def record(self, machine):
        """The ``[calibration]`` record of ``machine`` written from this calibration (None without a covariance)."""
        from ..discrepancy import weight_names
        from ..prediction.record import record_from_result

        res = self.result
        extra = weight_names(self.discrepancy.discrepancy.n_features) if self.discrepancy is not None else ()
        return record_from_result(machine, res.names, res.free, res.covariance, noise_scale=self.noise_scale,
                                  method=res.method, extra_names=extra,
                                  extra_cov=self.joint_covariance if self.discrepancy is not None else None,
                                  variance_factor=self.variance_factor, held=res.held + res.at_bound)

    def discrepancy_dict(self) -> dict:
        """The answer's ``discrepancy`` block ({} when none was considered)."""
        if self.discrepancy is None:
            return {"discrepancy": {"kept": False, "note": self.discrepancy_note}} if self.discrepancy_note else {}
        d = self.discrepancy.discrepancy
        return {"discrepancy": {
            "kept": True, "inputs": list(d.inputs), "relevance": d.relevance(), "outputs": list(d.outputs),
            "output_scales": d.output_scales.tolist(), "output_units": list(d.output_units),
            "log_evidence_gain": d.log_evidence_gain, "explained": d.explained,
            "effective_params": self.discrepancy.effective_params, "n_inducing": d.n_inducing,
            "note": self.discrepancy_note,
        }}

    def discrepancy_report(self) -> str:
        if self.discrepancy is None:
            return f"  discrepancy     {self.discrepancy_note}" if self.discrepancy_note else ""
        d = self.discrepancy.discrepancy
        rel = sorted(d.relevance().items(), key=lambda kv: -kv[1])
        shown = ", ".join(f"{k} {v:.2g}" for k, v in rel[:6])
        scales = ", ".join(f"{o} {s:.3g} {u}" for o, s, u in zip(d.outputs, d.output_scales, d.output_units))
        return (f"  discrepancy     kept: log Bayes factor {d.log_evidence_gain:.1f} over none; carries "
                f"{100 * d.explained:.0f} % of the residual; prior scale {scales}\n"
                f"                  relevance of its inputs (1 / length scale): {shown}")

    def noise_report(self) -> str:
        if not self.result.success:
            return "  noise           not assessed: the fit did not succeed, so its residuals do not test the noise"
        line = f"  noise           {self.noise.message()}"
        if self.noise_scale != 1.0:
            line += f"\n                  sigma used: {self.noise_scale:.3g} x the stated one"
        tilt = self.result.extras.get("tilt_noise")
        if tilt is not None:
            used = f"; sigma_tilt used: {tilt['scale_used']:.3g} x the stated one" if tilt["scale_used"] != 1.0 else ""
            line += (f"\n  sensor noise    tilt rows alone: reduced chi-square {tilt['reduced_chi2']:.3g} at the stated "
                     f"sigma_tilt ({tilt['verdict']}){used}")
        groups = group_report(self.result.extras.get("tool_noise"))
        if groups:
            line += "\n" + groups
        if self.variance_factor > 1.0:
            line += (f"\n  predictive      left-out poses predicted {self.loo_ratio:.3g} times worse (in variance) than "
                     f"the model's own intervals: predictions widen by {self.variance_factor:.3g} in variance")
        return line

    def noise_dict(self) -> dict:
        return {"noise": {**self.noise.to_dict(), "scale_used": self.noise_scale},
                "predictive": {"variance_factor": self.variance_factor, "loo_ratio": self.loo_ratio}}

    def with_variance_factor(self, model) -> "Calibration":
        """This calibration with its leave-one-pose-out variance factor (:mod:`bayescal.prediction.loo`) computed."""
        from ..prediction.loo import loo_variance_factor

        res = self.result
        if not res.success or res.covariance is None:
            return self
        scaled = scale_noise(model, self.noise_scale)
        # every pose at full weight (bayescal/prediction/loo.py says why)
        disc = self.discrepancy.discrepancy if self.discrepancy is not None else None
        try:
            kappa, ratio = loo_variance_factor(scaled, res.theta, self.joint_covariance,
                                               machine_index=np.flatnonzero(res.free), discrepancy=disc)
        except (np.linalg.LinAlgError, ValueError):
            return self
        cal = replace(self, variance_factor=kappa, loo_ratio=ratio)
        return replace(cal, result=replace(res, extras={**res.extras, **cal.noise_dict()}))


def noise_check_of(model: MeasurementModel, res) -> NoiseCheck:
    """The chi-square test of ``res`` (a fit of ``model``), degrees of freedom among the distinct rows."""
    n_distinct = distinct_rows(model.q, model.y_measured) * model.dof
    return check_noise(res.chi2, n_distinct - res.effective_params, stated=noise_stated(model))


def tilt_noise_check(model, res) -> NoiseCheck | None:
    """The chi-square test of the body sensors' tilt rows alone (None without body sensors or a fit).

    Their degrees of freedom are their rows less the parameters only they see (the sensors' mountings and
    the level of up: ``sensor.*``, ``gravity.tilt.*``).
    """
    tool = model.tool_dof
    if tool >= model.dof or not res.success or res.residuals_after is None:
        return None
    r = whiten(model, res.residuals_after)[:, tool:]
    names = model.machine.layout.names
    own = sum(1 for n, f in zip(names, res.free) if f and (n.startswith("sensor.") or n.startswith("gravity.tilt.")))
    return check_noise(float(np.sum(r**2)), r.size - own, stated=True)


def with_tilt_scale(model, scale: float):
    """``model`` with its body sensors' tilt rows' sigma multiplied by ``scale`` (the tool rows' unchanged)."""
    sigma = np.array(model.row_sigma, dtype=float)
    sigma[:, model.tool_dof:] *= max(float(scale), MIN_NOISE_SCALE)
    return model.with_pose_sigma(sigma)


def noise_stated(model) -> bool:
    """Whether the noise is stated: the machine file's ``[measurement]`` table.

    Without it, per-row sigma columns are relative weights (``bayescal klipper`` writes them so for a printer's
    heights and distances), and the evidence sets the prior against the noise.
    """
    return bool(model.machine.noise.given)


def _fit_once(model, method, *, lam, k, free, rule, prior_scale, max_iter, outlier_kw, fit_effects):
    from ..bayes.map_identify import identify_map
    from .choose import choose_regularisation
    from ..outliers.handling import fit_system, identify_with_outliers, robust_map_weights

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
        weighted = handling.weighted_model(model)
        order = canonical_order(weighted)
        # a batch answer must not depend on the order of the rows: the rules' folds and draws follow the rows,
        # so they see them in one canonical order (sorted by the commanded actuators, then the measurement)
        choice, res = choose_regularisation(weighted if order is None else weighted.subset(order), method, rule=rule,
                                            free=free, max_iter=max_iter)
        if order is not None:
            from .gauss_newton import identify

            chosen = {"lam": float(choice.value)} if method == "ridge" else {"k": int(choice.value)}
            res = replace(identify(weighted, method=method, free=free, max_iter=max_iter, **chosen), extras=res.extras)
        handling = handling.retested(model, res, fit_system(res))
        res = replace(res, extras={**res.extras, **handling.to_dict()})
    else:
        res, handling = identify_with_outliers(model, method=method, lam=lam, k=k, free=free, max_iter=max_iter,
                                               **outlier_kw)
    return res, handling, choice


#: Options of :func:`calibrate` passed on to the outlier handling (:mod:`bayescal.outliers.handling`).
OUTLIER_OPTIONS = ("nu", "alpha", "lines")


def calibrate(
    model: MeasurementModel,
    *,
    method: str = "map",
    lam: float | str | None = None,
    k: int | str | None = None,
    free="auto",
    fix=None,
    bounds=None,
    rule: str | None = None,
    prior_scale: str | None = None,
    max_iter: int = 50,
    robust: str = "auto",
    noise: str = "auto",
    fit_effects: bool = False,
    discrepancy: str = "off",
    discrepancy_inputs=None,
    **outlier_kw,
) -> Calibration:
    """Identify the errors of a recording as ``bayescal identify`` does (module docstring).

    Parameters
    ----------
    model : MeasurementModel or ConstraintModel
        With measured values (``bayescal.load`` or ``MeasurementModel.from_recording``).
    method : {"map", "ls", "ridge", "tsvd"}
    lam : float or "auto"
        Ridge parameter (dimensionless, 1 = MAP under the tolerance prior); required for ridge.
    k : int or "auto"
        TSVD rank; required for tsvd.
    free : "auto", "all" or names
    fix : sequence of str, optional
        Held at nominal (lmfit's ``vary=False``; zero variance in ``[calibration]``), ``auto`` choosing among the rest.
    bounds : mapping, optional
        ``{name: (lower, upper)}`` in the parameter's unit (lmfit's ``min`` / ``max``; ``None`` or an infinity for an
        open side): ls, ridge and map keep the answer inside, a parameter that ends on a bound is named in
        ``at_bound`` with no std (the others' covariance conditional on it; zero variance in ``[calibration]``).
        tsvd refuses them.
    rule : str, optional
        Rule for ``"auto"`` (:data:`bayescal.identify.choose.RULE_NAMES`).
    prior_scale : "empirical", "tolerance" or None
        map only (None: what :func:`bayescal.bayes.map_identify.default_prior_scale` chooses).
    max_iter : int
    robust : {"auto", "t", "huber", "off"}
        Outlier handling; ``nu``, ``alpha`` and ``lines`` pass through ``outlier_kw``.
    noise : {"auto", "stated"}
        ``auto``: the stated noise is tested and, where contradicted,
        replaced by the estimated scale; ``stated``: tested and reported only.
    fit_effects : bool
        The model's effect parameters are fitted (map: the prior scale stays the tolerances).
    discrepancy : {"off", "auto", "on"}
        A model discrepancy (module docstring, step 4).
    discrepancy_inputs : sequence of str, optional
        Its inputs (``q<i>``, auxiliary channels); default: every actuator and varying channel.

    Returns
    -------
    Calibration
    """
    _check_options(method, lam, k, rule, prior_scale, noise, discrepancy, outlier_kw)
    kw = dict(lam=lam, k=k, free=with_fixed(free, fix, bounds), rule=rule, prior_scale=prior_scale, max_iter=max_iter,
              outlier_kw={"robust": robust, **outlier_kw}, fit_effects=fit_effects)
    model, (res, handling, choice), blocks = _fit_with_row_groups(model, method, kw, noise)
    first = noise_check_of(model, res)
    res = replace(res, extras={**res.extras, **blocks})
    if discrepancy != "off" and res.success:
        got = _discrepancy_answer(model, method, kw, (res, handling, choice), first, discrepancy, discrepancy_inputs,
                                  noise)
        if got is not None:
            return got
        note = "considered, not supported by the data (--discrepancy auto)"
    else:
        note = ""
    res, handling, choice, scale = _noise_scaled(model, method, kw, noise, first, (res, handling, choice))
    cal = Calibration(result=res, handling=handling, choice=choice, noise=first, noise_scale=scale, discrepancy_note=note)
    cal = replace(cal, result=replace(res, extras={**res.extras, **blocks, **cal.noise_dict(), **cal.discrepancy_dict()}),
                  model=model)
    return cal.with_variance_factor(model)


def _noise_scaled(model, method, kw, noise: str, first: NoiseCheck, fit) -> tuple:
    """``fit`` (result, handling, choice) and the noise scale carried forward, refitted where the noise test says."""
    res = fit[0]
    if noise == "auto" and first.verdict == "not_stated" and res.success:
        # without a stated noise the sigmas are weights: the fit depends only on their ratio to the prior (which
        # the empirical prior scale estimates) and its covariance is already scaled; what is carried forward is
        # the noise the residuals support (the record's noise scale, every prediction's noise)
        return (*fit, max(first.scale, MIN_UNSTATED_SCALE))
    if noise == "auto" and first.contradicted and res.success:
        return _with_noise_scale(model, method, kw, max(first.scale, MIN_NOISE_SCALE), fit)
    return (*fit, 1.0)


def _fit_with_row_groups(model, method, kw, noise):
    """The first fit, with the body sensors' tilt sigma and the tool's position and angle sigmas rescaled apart.

    Returns the model (its row groups' sigmas as used), the fit ``(res, handling, choice)`` and the answer's
    ``tilt_noise`` / ``tool_noise`` blocks (the row groups' own tests, kept in the answer through every refit).
    """
    res, handling, choice = _fit_once(model, method, **kw)
    tilt = tilt_noise_check(model, res)
    if tilt is not None and noise == "auto" and tilt.contradicted and res.success:
        # the body sensors' sigma_tilt is contradicted by their own rows: rescaled on its own, and the fit redone,
        # before the noise test (one scale for every row let a default sigma_tilt twenty times too small raise the
        # position sigmas tenfold and spoil the geometry: held-out 0.044 against 0.0069 mm without the sensors)
        model = with_tilt_scale(model, tilt.scale)
        res, handling, choice = _fit_once(model, method, **kw)
    groups = tool_group_checks(model, res, stated=noise_stated(model), weights=None if handling is None else handling.weights)
    rescaled = {}
    if noise == "auto" and res.success and group_scales(groups):
        # sigma_position and sigma_angle contradicted apart (group_noise.py): one scale for every row would leave
        # the positions 10^4 times underweighted when only sigma_position is stated 100 times too large
        model, (res, handling, choice), rescaled = _with_group_scales(model, method, kw, group_scales(groups),
                                                                      (res, handling, choice))
    blocks = {}
    if tilt is not None:
        blocks["tilt_noise"] = {**tilt.to_dict(), "scale_used": tilt.scale if tilt.contradicted and noise == "auto"
                                else 1.0}
    if groups is not None:
        blocks["tool_noise"] = {**{name: c.to_dict() for name, c in groups.items()}, "scale_used": dict(rescaled)}
    return model, (res, handling, choice), blocks


def _discrepancy_answer(model, method, kw, fit, first, discrepancy, discrepancy_inputs, noise):
    """The calibration with a model discrepancy (step 4 of the module docstring); None when ``auto`` finds none."""
    # a noise not stated: the sigmas are weights and lam the noise-to-prior ratio; on the sigma the residuals
    # support, the geometry's prior is a prior (its std the tolerances times that scale over sqrt(lam)) before
    # it decides with the discrepancy's what each may take
    base = first.scale if first.verdict == "not_stated" and noise == "auto" else 1.0
    model_d = scale_noise(model, base)
    got = _with_discrepancy(model_d, method, kw, fit, discrepancy, discrepancy_inputs, noise, lam_scale=base**2)
    if got is not None and base != 1.0:
        got = replace(got, noise=first, noise_scale=got.noise_scale * base, model=model)
        got = replace(got, result=replace(got.result, extras={**got.result.extras, **got.noise_dict()}))
    return got


def _check_options(method, lam, k, rule, prior_scale, noise, discrepancy, outlier_kw) -> None:
    """Refuse an unknown method or option, or an option that does not go with the method (:func:`calibrate`)."""
    if method not in DETERMINISTIC_METHODS:
        raise InputError(f"method: expected one of {', '.join(DETERMINISTIC_METHODS)}, got {method!r}")
    bad = sorted(set(outlier_kw) - set(OUTLIER_OPTIONS))
    other = next(((n, m) for n in bad for m, o in BAYES_METHOD_OPTIONS.items() if n in o), None)
    if other is not None:  # an mcmc or kalman option (steps, ess, ...): say which method it goes with
        raise InputError(f"{other[0]}: goes with method {other[1]!r}; it does nothing with method {method!r}")
    if bad:
        raise InputError(f"calibrate: unknown option(s) {', '.join(bad)}; expected method, lam, k, free, fix, bounds, rule, "
                         f"prior_scale, max_iter, robust, noise, fit_effects, discrepancy, discrepancy_inputs, "
                         f"{', '.join(OUTLIER_OPTIONS)}")
    if lam is not None:
        check_lam(lam, auto=True)
    if k is not None and k != "auto" and not (finite_real(k) and float(k) == int(k)):
        raise InputError(f"k: expected a whole number or 'auto', got {k!r}")
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
    if discrepancy not in ("off", "auto", "on"):
        raise InputError(f"discrepancy: expected 'off', 'auto' or 'on', got {discrepancy!r}")


def canonical_order(model):
    """The rows sorted by commanded actuators, then by the measured values (None: already in that order).

    Only for a recording whose order carries no physics (no effects read the time order, one pose per
    row); otherwise None, and the rows stay as recorded.
    """
    if model.machine.effects or np.asarray(model.pose_q).shape[0] != model.n_poses or model.y_measured is None:
        return None
    keys = np.hstack([np.asarray(model.q, dtype=float), np.asarray(model.y_measured, dtype=float)])
    order = np.lexsort(keys.T[::-1])
    return None if np.array_equal(order, np.arange(order.size)) else order


def _with_discrepancy(model, method, kw, first_fit, mode, inputs, noise, lam_scale: float = 1.0):
    """Step 4 of the module docstring; None when ``auto`` finds the discrepancy unsupported."""
    from ..discrepancy import fit_discrepancy

    res, handling, choice = first_fit
    if not res.lam:
        raise InputError(f"discrepancy: the split between the geometry and a discrepancy is decided by the geometry's "
                         f"prior; method {method!r} has none (use method 'map', or 'ridge' with lam > 0)")
    idx = np.flatnonzero(res.free)
    machine = model.machine
    # lam relative to the model's sigma (lam_scale: the factor by which that sigma's variance was raised since)
    prior_sd = np.asarray(machine.tolerance, dtype=float)[idx] / math.sqrt(res.lam / lam_scale)
    mean = machine.prior_mean
    prior_mean = None if mean is None else np.asarray(mean, dtype=float)[idx]
    # the hyperparameters and the noise are estimated with the poses weighted as the geometry's robust fit weighted
    # them: one gross pose must not shorten the length scales and raise the noise (seen: 0.0088 -> 0.0138 mm)
    weighted = handling.weighted_model(model)
    df = fit_discrepancy(weighted, res.theta, res.free, prior_sd, prior_mean=prior_mean, inputs=inputs)
    if mode == "auto" and not df.supported:
        return None
    # the stated noise, tested with the discrepancy accounted for (the joint fit's effective parameters)
    n_distinct = distinct_rows(model.q, model.y_measured) * model.dof
    check = check_noise(df.chi2, n_distinct - df.effective_params, stated=noise_stated(model))
    scale = check.scale if (noise == "auto" and (check.contradicted or check.verdict == "not_stated")) else 1.0
    scale = max(scale, MIN_UNSTATED_SCALE if check.verdict == "not_stated" else MIN_NOISE_SCALE)
    scaled = scale_noise(model, scale)
    # the joint posterior at the noise used, on the poses weighted as the robust geometry fit weighted them (a
    # reference one gross pose cannot drag), relinearised at its own geometry; then every pose is judged against
    # it at full weight, and the joint fit is redone with only the poses that test names left out
    ref = handling.weighted_model(scaled)
    theta, df = _relinearised(ref, res.theta.copy(), res.free, prior_sd, prior_mean, df.discrepancy)
    handling, df, theta = _joint_outliers(scaled, res, theta, df, prior_sd, prior_mean, handling, kw["outlier_kw"])
    res = _joint_result(scaled, res, theta, df)
    note = ("fitted (--discrepancy on)" if mode == "on" else "supported by the data (--discrepancy auto)")
    cal = Calibration(result=res, handling=handling, choice=choice, noise=check, noise_scale=scale,
                      discrepancy=df, discrepancy_note=note, model=model)
    cal = replace(cal, result=replace(res, extras={**res.extras, **cal.noise_dict(), **cal.discrepancy_dict()}))
    return cal.with_variance_factor(model)


def _relinearised(model, theta, free, prior_sd, prior_mean, hyper, rounds: int = 2):
    """The joint posterior at fixed hyperparameters, relinearised ``rounds`` times at its own geometry."""
    from ..discrepancy import fit_discrepancy

    idx = np.flatnonzero(free)
    for _ in range(rounds):
        df = fit_discrepancy(model, theta, free, prior_sd, prior_mean=prior_mean, hyper=hyper)
        theta = theta.copy()
        theta[idx] += df.dtheta
        hyper = df.discrepancy
    return theta, fit_discrepancy(model, theta, free, prior_sd, prior_mean=prior_mean, hyper=hyper)


def _joint_outliers(model, res, theta, df, prior_sd, prior_mean, handling, outlier_kw):
    """The outlier test against the model with its discrepancy (:func:`bayescal.outliers.joint.joint_outlier_handling`)."""
    from ..discrepancy import fit_discrepancy
    from ..discrepancy.fit import joint_design
    from ..outliers import ALPHA
    from ..outliers.joint import joint_outlier_handling

    def refit(m, th, d, search):
        hyper = d.discrepancy
        if search:
            hyper = fit_discrepancy(m, th, res.free, prior_sd, prior_mean=prior_mean, inputs=hyper.inputs).discrepancy
        return _relinearised(m, th, res.free, prior_sd, prior_mean, hyper)

    got = joint_outlier_handling(model, theta, df, design=lambda m, th, d: joint_design(m, th, d, prior_sd),
                                 refit=refit, robust=outlier_kw.get("robust", "auto"),
                                 alpha=outlier_kw.get("alpha", ALPHA), lines=outlier_kw.get("lines"))
    return (handling, df, theta) if got is None else got


def _joint_result(model, res, theta, df):
    """The identification answer of the geometry fitted jointly with a discrepancy (at ``model``'s noise)."""
    p = int(np.sum(res.free))
    pred = model.predict(theta)
    after = model.residual(pred)
    if pred.success.all():
        after = after - df.discrepancy.rows(model, theta, pred)[0]
    return replace(
        res, theta=theta, covariance=df.covariance[:p, :p], residuals_after=after, rms_after=model.rms(after),
        chi2=float(np.sum(whiten(model, after) ** 2)),
        covariance_kind=res.covariance_kind + "; joint with the model discrepancy (its weights marginalised)",
    )


def _with_group_scales(model, method, kw, scales, fallback):
    """Refit with the position and orientation sigmas rescaled apart until each rescaled group's reduced chi-square is 1.

    Iterated as :func:`_with_noise_scale` iterates the one scale (fits without an outlier decision, within
    2 %): the first estimate comes from a fit the wrong sigma spoiled (0.13 where 0.015 is right).  Returns the
    model with the scales, the final fit and the scales (empty, the model and ``fallback`` when a fit fails).
    """
    plain = {**kw, "outlier_kw": {**kw["outlier_kw"], "robust": "off"}}
    auto = (method == "ridge" and kw["lam"] == "auto") or (method == "tsvd" and kw["k"] == "auto")
    for _ in range(0 if auto else MAX_NOISE_ROUNDS):
        trial = with_group_scales(model, scales, MIN_NOISE_SCALE)
        res_s = _fit_once(trial, method, **plain)[0]
        checks = tool_group_checks(trial, res_s, stated=True) if res_s.success else None
        if checks is None:
            break
        new = {name: max(s * math.sqrt(checks[name].reduced), MIN_NOISE_SCALE)
               if math.isfinite(checks[name].reduced) and checks[name].reduced > 0 else s for name, s in scales.items()}
        done = all(abs(math.log(new[n] / scales[n])) < math.log(1.02) for n in scales)
        scales = new
        if done:
            break
    scaled = with_group_scales(model, scales, MIN_NOISE_SCALE)
    got = _fit_once(scaled, method, **kw)
    if not got[0].success:
        return model, fallback, {}
    return scaled, got, scales


def _with_noise_scale(model, method, kw, scale, fallback):
    """Refit with the stated sigma times a scale at which the reduced chi-square is 1 (within 2 %).

    The scale is iterated on fits without an outlier decision, the poses weighted as the first fit weighted
    them: re-deciding the outliers at every sigma made the iteration oscillate (a 200-pose bent arm went
    weighted, unweighted, weighted for all six rounds, 0.07 to 0.12 mm).  The outliers are decided once, by
    the final fit at the scale found.
    """
    base_sigma = np.asarray(model.row_sigma, dtype=float)
    res, handling, choice = fallback
    weights = handling.weights
    relative = base_sigma if weights is None else base_sigma / np.sqrt(np.asarray(weights, dtype=float))[:, None]
    plain = {**kw, "outlier_kw": {**kw["outlier_kw"], "robust": "off"}}
    auto = (method == "ridge" and kw["lam"] == "auto") or (method == "tsvd" and kw["k"] == "auto")
    # the automatic rules choose lam or k for the sigma they see, so their answer and its reduced chi-square
    # scale with it: the first scale is the fixed point, and each rule run is costly
    good = scale
    for _ in range(0 if auto else MAX_NOISE_ROUNDS):
        trial = model.with_pose_sigma(relative * scale)
        res_s = _fit_once(trial, method, **plain)[0]
        if not res_s.success:
            scale = good  # a noise-free recording drives the scale to round-off: keep the last that fitted
            break
        good = scale
        check = noise_check_of(trial, res_s)
        if check.verdict == "untestable" or not math.isfinite(check.reduced) or check.reduced <= 0:
            break
        new = max(scale * math.sqrt(check.reduced), MIN_NOISE_SCALE)
        done = abs(math.log(new / scale)) < math.log(1.02)
        scale = new
        if done:
            break
    got = _fit_once(model.with_pose_sigma(base_sigma * scale), method, **kw)
    if not got[0].success:
        return res, handling, choice, 1.0  # keep the fit at the stated noise
    return (*got, scale)
