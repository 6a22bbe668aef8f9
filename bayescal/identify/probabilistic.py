"""``identify --method kalman | mcmc`` as a user gets it: the noise test, outliers, the filter or sampler, the answer.

:func:`calibrate_bayes` is what ``bayescal identify`` runs for the
probabilistic methods (``bayescal.calibrate(s, method="kalman")`` calls it
too), so a notebook and the command line get the same answer:

1. the stated noise, tested by the MAP the filter and the sampler start from
   (:func:`bayescal.identify.calibrate.calibrate`, method ``map``); where the
   data contradict it they run with the estimated noise (not with effects
   fitted with the geometry: their priors are not the tolerances the test
   scales against);
2. the outlier test of a robust MAP pass, whose weights the filter and the
   sampler see; the test redone at their answer;
3. the filter (:func:`bayescal.bayes.kalman.kalman_filter`) or the sampler
   (:func:`bayescal.bayes.mcmc.sample_posterior`, at least :data:`MIN_STEPS`
   steps: fewer cannot even estimate an autocorrelation time);
4. the instrument frame and the plausibility verdict
   (:func:`bayescal.instrument.plausibility.judge_fit`), and the ``check``
   rows of the session predicted and scored with the MAP's noise scale and
   leave-one-out factor (:func:`bayescal.prediction.recording.score_held_out`).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..constants import BAYES_METHOD_OPTIONS, BAYES_METHODS
from ..contract import scale_noise
from ..errors import InputError
from ..limits import finite_real
from ..outliers import ALPHA, DEFAULT_NU
from .free import bounds_of, with_fixed

__all__ = ["BayesCalibration", "calibrate_bayes", "BAYES_METHODS", "METHOD_OPTIONS", "MIN_STEPS"]

#: Options of one method, with their defaults (given with the other method they are refused, not ignored).
METHOD_OPTIONS = BAYES_METHOD_OPTIONS
#: Options of the deterministic methods (:func:`bayescal.identify.calibrate.calibrate`), and the methods they go with.
DETERMINISTIC_OPTIONS = {"lam": "'ridge'", "k": "'tsvd'", "rule": "'ridge' or 'tsvd'", "prior_scale": "'map'",
                         "discrepancy": "'map' or 'ridge'", "discrepancy_inputs": "'map' or 'ridge'"}
#: Fewest MCMC steps per walker (fewer cannot even estimate an autocorrelation time).
MIN_STEPS = 20


@dataclass(frozen=True)
class BayesCalibration:
    """The answer of :func:`calibrate_bayes`.

    Attributes
    ----------
    result : FilterResult or PosteriorResult
        The filter's state after the last pose, or the posterior (``report()``, ``theta``, ``covariance``).
    handling : OutlierHandling
        The robust MAP pass's weights, its test redone at ``result``.
    plausibility : Plausibility
    frame : dict
        The answer's instrument frame, ``plausible`` and ``frame_check`` keys.
    held_out : dict
        The session's ``check`` rows scored (``{}`` without them).
    noise : Calibration or None
        The MAP that tested the stated noise (None with effects fitted with the geometry).
    machine : Machine
        The calibrated machine as :meth:`write_machine` writes it (effects fitted with the geometry applied).
    model : Model
        The model fitted (its noise rescaled where the test asked for it).
    """

    result: object
    handling: object
    plausibility: object
    frame: dict
    held_out: dict
    noise: object | None
    machine: object
    model: object = field(default=None, repr=False, compare=False)

    @property
    def parameters(self) -> dict:
        """The parameters by name: value, std, unit, identified (as :attr:`Calibration.parameters`)."""
        return {p.name: p for p in self.result.parameters}

    def to_dict(self) -> dict:
        """The JSON answer of ``bayescal identify --method kalman | mcmc``, in JSON's own types.

        ``bayescal.io.answers.json_text(answer.to_dict())`` is the command's ``--json`` file, byte for byte.
        """
        from ..io.answers import to_jsonable

        answer = self.result.to_dict()
        for part in (self.handling.to_dict(), self.frame, self.held_out,
                     {} if self.noise is None else self.noise.noise_dict()):
            answer.update(part)
        return to_jsonable(answer)

    def report(self) -> str:
        """The fit, the noise, the outliers and the held-out rows, as ``bayescal identify`` prints them."""
        from ..prediction.recording import held_out_report

        parts = [self.result.report(), "" if self.noise is None else self.noise.noise_report(),
                 self.handling.report(), held_out_report(self.held_out)]
        return "\n".join(p for p in parts if p)

    def write_machine(self, path, *, force: bool = False) -> list:
        """Write the calibrated machine file (``nominal + theta``, its tables kept), atomically.

        A result that did not succeed is refused; so is one judged implausible unless ``force``, as
        ``bayescal identify --write-machine`` refuses it.  Returns the files written.
        """
        from ..instrument.plausibility import refuse_implausible
        from ..machines.files import write_calibrated_machine_files

        if not self.result.success:
            raise InputError(f"write_machine: the calibration did not succeed ({self.result.message})")
        refuse_implausible(self.plausibility, force)
        return write_calibrated_machine_files(path, self.machine, np.asarray(self.result.theta)[: self.machine.n_params])


def _method_options(method: str, options: dict) -> dict:
    """``options`` checked against the method's (:data:`METHOD_OPTIONS`), with the defaults filled in."""
    if method not in BAYES_METHODS:
        raise InputError(f"method: expected one of {', '.join(BAYES_METHODS)}, got {method!r}")
    own = METHOD_OPTIONS[method]
    for name in options:
        if name in own:
            continue
        other = next((m for m, o in METHOD_OPTIONS.items() if name in o), None)
        if other is not None:
            raise InputError(f"{name}: goes with method {other!r}; it does nothing with method {method!r}")
        if name in DETERMINISTIC_OPTIONS:
            raise InputError(f"{name}: goes with method {DETERMINISTIC_OPTIONS[name]}; it does nothing with method "
                             f"{method!r}")
        raise InputError(f"calibrate: unknown option {name!r} of method {method!r}; expected free, fix, bounds, max_iter, noise, "
                         f"robust, nu, alpha, lines, fit_effects, {', '.join(own)}")
    got = {**own, **options}
    if method == "mcmc":
        steps = got["steps"]
        if isinstance(steps, bool) or not isinstance(steps, (int, np.integer)) or steps < MIN_STEPS:
            raise InputError(f"steps (--steps): expected a whole number of at least {MIN_STEPS}, got {steps!r}")
        if got["resume"] and not got["checkpoint"]:
            raise InputError("resume (--resume): needs checkpoint (--checkpoint PATH), the checkpoint to continue")
    return got


def _run(model, method: str, free, o: dict):
    if method == "kalman":
        from ..bayes.kalman import kalman_filter

        return kalman_filter(model, variant=o["variant"], free=free, process_noise=o["process_noise"])
    from ..bayes.mcmc import sample_posterior

    return sample_posterior(model, free=free, n_steps=o["steps"], n_walkers=o["walkers"], seed=o["seed"],
                            progress=o["progress"], surrogate=o["surrogate"], checkpoint=o["checkpoint"],
                            checkpoint_every=o["checkpoint_every"], resume=o["resume"], ess=o["ess"])


def calibrate_bayes(model, *, method: str, free="auto", fix=None, bounds=None, max_iter: int = 50, noise: str = "auto",
                    robust: str = "auto", nu: float = DEFAULT_NU, alpha: float = ALPHA, lines=None,
                    fit_effects: bool = False, machine=None, check=None, session=None, **options) -> BayesCalibration:
    """Identify a recording's errors with the Kalman filter or the MCMC sampler, as ``bayescal identify`` does.

    Parameters
    ----------
    model : Model
        The ``fit`` rows' model (an effect model when ``fit_effects``).
    method : {"kalman", "mcmc"}
    free : "auto", "all" or names
    fix : sequence of str, optional
        Parameters held at nominal (:func:`bayescal.identify.calibrate.calibrate`).
    bounds : mapping, optional
        ``{name: (lower, upper)}``: mcmc samples the posterior truncated there (its MAP passes keep them); the
        Kalman filter refuses them.
    max_iter : int
        Gauss-Newton iterations of the MAP passes (noise test, outliers).
    noise : {"auto", "stated"}
        ``auto``: a stated noise the data contradict is replaced by the estimated one (module docstring).
    robust, nu, alpha, lines
        The outlier handling (:mod:`bayescal.outliers.handling`): mode, Student-t degrees of freedom,
        family-wise level, the poses' lines in the recording file.
    fit_effects : bool
        ``model`` identifies the machine file's effects with the geometry (mcmc).
    machine : Machine, optional
        The machine calibrated, in its instrument frame if one was fitted (default: the model's).
    check : FrameCheck, optional
        The rigid-transform check of a base-frame recording.
    session : Session, optional
        Its ``check`` rows are predicted and scored.
    **options
        kalman: ``variant`` ("ekf", "ukf"), ``process_noise`` (fraction of each prior std per pose);
        mcmc: ``steps``, ``walkers``, ``seed``, ``progress``, ``surrogate`` ("none", "linear"),
        ``checkpoint`` (path), ``checkpoint_every``, ``resume``.

    Returns
    -------
    BayesCalibration
    """
    from ..effects.joint_model import with_fitted_effects
    from ..instrument.plausibility import judge_fit
    from ..prediction.recording import score_held_out_result
    from .calibrate import calibrate
    from ..outliers.handling import map_system, robust_map_weights

    o = _method_options(method, options)
    free = with_fixed(free, fix, bounds)
    if bounds_of(free) and method == "kalman":
        raise InputError("bounds (--bound): the Kalman filter's answer is a Gaussian and cannot keep parameters "
                         "inside bounds; expected method map, ridge or ls (a bounded answer) or mcmc (the posterior "
                         "truncated there)")
    if noise not in ("auto", "stated"):
        raise InputError(f"noise: expected 'auto' or 'stated', got {noise!r}")
    if not (finite_real(alpha) and 0 < alpha < 1):
        raise InputError(f"alpha (--outlier-alpha): expected a level between 0 and 1, got {alpha!r}")
    if not (finite_real(nu) and nu > 0):
        raise InputError(f"nu (--nu): expected a number > 0, got {nu!r}")
    machine = model.machine if machine is None else machine
    okw = {"robust": robust, "nu": nu, "alpha": alpha, "lines": lines}
    noise_cal = None
    if not fit_effects:
        noise_cal = calibrate(model, method="map", max_iter=max_iter, noise=noise, free=free, **okw)
        if noise_cal.noise_scale != 1.0:
            model = scale_noise(model, noise_cal.noise_scale)
    handling = robust_map_weights(model, free, max_iter=max_iter, **okw)
    res = _run(handling.weighted_model(model), method, free, o)  # the robust MAP pass's weights (docs/outliers.md)
    handling = handling.retested(model, res, map_system(res))
    frame, plaus = judge_fit(machine, model, res, check)
    # the noise and the leave-one-out factor of the MAP the method started from (the same model and prior)
    scale, kappa = (1.0, 1.0) if noise_cal is None else (noise_cal.noise_scale, noise_cal.variance_factor)
    held_out = (score_held_out_result(res, session, noise_scale=scale, variance_factor=kappa)
                if session is not None and not fit_effects else {})
    written = with_fitted_effects(machine, model, res)
    return BayesCalibration(res, handling, plaus, frame, held_out, noise_cal,
                            _with_record(written, res, method, scale, kappa), model)


def _with_record(machine, res, method: str, scale: float, kappa: float):
    """The written machine carrying the filter's or the posterior's covariance as its ``[calibration]``.

    Without it ``predict`` took a Kalman or MCMC calibration as exact, the methods whose answer is the
    uncertainty. The noise scale and leave-one-out factor are those of the MAP the method started from.
    """
    from ..prediction.record import record_from_result

    cov = getattr(res, "covariance", None)
    if cov is None or not res.success:
        return machine
    record = record_from_result(machine.base_machine(), res.names, res.free, cov, noise_scale=scale, method=method,
                                variance_factor=kappa, held=tuple(res.held))
    return machine if record is None else machine.with_calibration(record, machine.discrepancy)
