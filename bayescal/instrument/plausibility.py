"""Calibrated results that refuse to be implausible, and the fitted frame in the answer.

The rule (docs/real-instruments.md): a calibration is **not plausible** when

1. any identified machine parameter (frame parameters excluded) lies more
   than :data:`PLAUSIBLE_SIGMAS` = 10 prior sigmas (tolerances) from
   nominal, ``|value| > 10 tolerance``; or
2. the fit has no residual degrees of freedom: distinct measured
   components (rows that exactly repeat another row's ``q`` and measured
   values add none) ``n_distinct * dof <= `` identified parameters (for a fit
   under a prior, ridge, TSVD, MAP, Kalman or MCMC, the *effective* number of
   parameters, the trace of its hat matrix: the filter factors summed, or
   ``n - tr(P_prior^-1 P_post)`` from the filter's or the sampler's
   covariance; a prior keeps what the data cannot determine near nominal,
   so 19 probe rows can carry 21 parameters under a prior but not by least
   squares).

Likely causes are named for each flagged case:

* *unidentifiable combination*: the parameter's scaled value lies mostly
  (more than half) along near-null directions of the whitened,
  tolerance-scaled identification matrix at the answer (singular values
  below 1: the data determine those directions worse than one tolerance);
* *wrong frame*: the rigid-transform check of the recording fires
  (:class:`~bayescal.instrument.alignment.FrameCheck`); *missing --frame
  fit*: a rigid transform is the best of the check's explanations but the
  tolerances hid it from the check (a tool point declared unknown, with a
  large tolerance);
* *wrong tool point*: an offset of the machine file's tool point beyond 10
  tolerances explains the recording best (a wrong tool length);
* *swapped columns*: two exchanged position columns explain the recording
  far better than any rigid transform;
* *wrong units*: none of these explains it, and the measured points spread
  more than 5 % more or less than the nominal machine's at the same poses;
  *one pose makes the spread* instead when leaving out the pose farthest
  from the nominal machine brings the spreads within 5 % (a mistyped cell,
  163 for 16.3 mm: wrong units scale every pose alike), naming its line and
  column;
* *outliers*: the worst 3 % of poses (at least one) carry more than half
  of the chi-square, with a reduced chi-square above 2.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from ..contract import whiten
from ..geometry import left_jacobian, left_jacobian_inverse
from ..machines.base import Machine
from ..machines.framed import InstrumentFrame, is_frame_parameter
from ..identify.noise import distinct_rows
from ..measurement import MeasurementModel
from .alignment import FrameCheck

__all__ = ["Plausibility", "assess_plausibility", "frame_answer", "judge_fit", "refuse_implausible", "PLAUSIBLE_SIGMAS"]

#: |value| above this many tolerances (prior sigmas) makes a calibration implausible.
PLAUSIBLE_SIGMAS = 10.0
#: Spreads of the measured and the nominal tool points that differ by more than this (log of their ratio, about
#: 5 %) name wrong units as a likely cause, unless leaving one pose out brings them within it.
UNITS_LOG_TOL = 0.05


@dataclass(frozen=True)
class Plausibility:
    """Whether a calibrated machine is believable, and why not.

    Attributes
    ----------
    plausible : bool
    reasons : tuple of str
        What broke the rule (empty when plausible).
    causes : tuple of str
        Likely causes, in words.
    parameters : tuple of dict
        The flagged parameters: name, value, unit, tolerance, sigmas.
    """

    plausible: bool
    reasons: tuple[str, ...] = ()
    causes: tuple[str, ...] = ()
    parameters: tuple[dict, ...] = ()

    def to_dict(self) -> dict:
        return {
            "plausible": self.plausible,
            "plausibility": {
                "rule": f"|value| > {PLAUSIBLE_SIGMAS:g} tolerances for an identified machine parameter, "
                "or no residual degrees of freedom",
                "reasons": list(self.reasons), "causes": list(self.causes), "parameters": list(self.parameters),
            },
        }

    def report(self) -> str:
        if self.plausible:
            return "  plausibility    plausible (no machine parameter beyond 10 tolerances; residual degrees of freedom left)"
        lines = ["  NOT PLAUSIBLE:"] + [f"    - {r}" for r in self.reasons]
        if self.causes:
            lines += ["  likely causes:"] + [f"    - {c}" for c in self.causes]
        return "\n".join(lines)


def assess_plausibility(
    model: MeasurementModel,
    theta: NDArray,
    free: NDArray,
    residuals: NDArray | None = None,
    *,
    check: FrameCheck | None = None,
    line_offset: int = 2,
    effective_params: float | None = None,
) -> Plausibility:
    """Judge a calibrated parameter vector by the rule of the module docstring.

    Parameters
    ----------
    model : MeasurementModel
        The model it was identified on (machine with frame, if fitted).
    theta : ndarray, shape (P,)
        Identified errors.
    free : ndarray of bool, shape (P,)
        Which were identified.
    residuals : ndarray, shape (n_poses, dof), optional
        ``y - h(theta)``; computed if not given.
    check : FrameCheck, optional
        The rigid-transform check of the recording (base frame only).
    line_offset : int
        CSV line of pose 0 (header = line 1).
    effective_params : float, optional
        For a regularised fit, the sum of its filter factors (the trace of
        its hat matrix); rule 2 compares the measured components with it
        instead of the number of identified parameters.
    """
    machine = model.machine
    names, units = machine.layout.names, machine.layout.units
    theta = np.asarray(theta, dtype=float)
    free = np.asarray(free, dtype=bool)
    tol = np.asarray(machine.tolerance, dtype=float)
    is_frame = np.array([is_frame_parameter(n) for n in names])
    ratio = np.abs(theta) / tol
    # effect parameters (identify --fit-effects, group joint_model.EFFECT_GROUP) have priors, not tolerances:
    # a large backlash is no wrong geometry
    is_effect = np.array([g == "effect" for g in (sp.group for sp in machine.layout.specs)])
    flagged = np.flatnonzero(free & ~is_frame & ~is_effect & (ratio > PLAUSIBLE_SIGMAS))
    reasons, causes, params = [], [], []
    # copied rows add no information: count the measured components that are not repeats
    n_distinct = distinct_rows(model.q, model.y_measured)
    n_rows, n_free = n_distinct * model.dof, int(free.sum())
    n_eff = float(n_free) if effective_params is None else float(effective_params)
    if flagged.size:
        reason, params = _beyond_tolerance(flagged, theta, ratio, tol, names, units)
        reasons.append(reason)
    if n_rows - n_eff < 1.0:  # less than one residual degree of freedom (a prior fits ~n_rows effective parameters)
        what = (f"{n_free} identified parameters" if effective_params is None
                else f"{n_eff:.1f} effective parameters (the hat matrix's trace under the prior, {n_free} estimated)")
        repeats = (f" ({model.n_poses - n_distinct} of {model.n_poses} rows repeat another row exactly)"
                   if n_distinct < model.n_poses else "")
        reasons.append(
            f"no residual degrees of freedom: {n_rows} distinct measured components{repeats} for {what}; "
            "the fit reproduces any recording, noise included"
        )
    if not reasons:
        return Plausibility(True)
    pred = model.predict(theta)
    if residuals is None:
        residuals = model.residual(pred)
    if flagged.size and pred.success.all():
        null = _near_null(model, theta, free, pred, flagged)
        if null:
            causes.append(
                "unidentifiable combination: " + ", ".join(null) + " lie(s) along near-null directions of the "
                "identification matrix (the data determine them worse than one tolerance); use --method ridge --lam auto, "
                "--method map or --free auto"
            )
    causes += _recording_causes(check)
    out = _outlier_cause(model, residuals, line_offset, n_rows - n_eff)
    if out:
        causes.append(out)
    return Plausibility(False, tuple(reasons), tuple(causes), tuple(params))


def _beyond_tolerance(flagged, theta, ratio, tol, names, units) -> tuple[str, list[dict]]:
    """The reason naming the ``flagged`` errors (the largest six, in tolerances) and their answer entries."""
    order = flagged[np.argsort(-ratio[flagged])]
    shown = ", ".join(f"{names[j]} = {theta[j]:.4g} {units[j]} ({ratio[j]:.0f} tolerances)" for j in order[:6])
    more = f" and {order.size - 6} more" if order.size > 6 else ""
    reason = f"{order.size} identified errors lie beyond {PLAUSIBLE_SIGMAS:g} tolerances: {shown}{more}"
    params = [
        {"name": names[j], "value": float(theta[j]), "unit": units[j], "tolerance": float(tol[j]), "sigmas": float(ratio[j])}
        for j in order
    ]
    return reason, params


def _recording_causes(check: FrameCheck | None) -> list[str]:
    """Causes the rigid-transform check names: a frame, a tool point, exchanged columns, units.

    A frame the check fires on is named as before; a tool-point offset, exchanged
    columns, or a frame the tolerances hid (a tool point declared unknown) are
    named when they explain the recording best (:attr:`FrameCheck.explanation`).
    Units are named only when none of these explains the recording: a tool
    length error also changes how far the measured points spread.
    """
    if check is None:
        return []
    if check.fires:
        return ["wrong frame: " + check.message()]
    cause = check.cause()
    if cause is not None:
        return [cause]
    if math.isfinite(check.scale) and abs(math.log(check.scale)) > UNITS_LOG_TOL:
        if math.isfinite(check.scale_one_out) and abs(math.log(check.scale_one_out)) <= UNITS_LOG_TOL:
            # wrong units scale every pose; a spread that one pose makes is a mistyped cell of that pose
            return [f"one pose makes the spread: the nominal machine's tool points spread {check.scale:.4g} times as "
                    f"far as the measured ones, {check.scale_one_out:.3f} times without CSV line {check.odd_line}; check "
                    f"that line's cells (column {check.odd_column} lies farthest from the nominal machine): a typo, "
                    "not the units"]
        return [f"wrong units: the nominal machine's tool points spread {check.scale:.4g} times as far as the measured "
                "ones at the same poses; check the units of x, y, z (suffixes _mm, _um, _m)"]
    return []


def _near_null(model, theta, free, pred, flagged) -> list[str]:
    idx = np.flatnonzero(free)
    S = np.asarray(model.machine.tolerance, dtype=float)[idx]
    J = whiten(model, model.jacobian(theta, pred)[:, :, idx])
    A = J.reshape(-1, idx.size) * S
    _, s, Vt = np.linalg.svd(A, full_matrices=False)
    V = Vt.T
    null = V[:, s < 1.0]
    if null.shape[1] == 0 and idx.size > s.size:
        null = np.zeros((idx.size, 0))
    phi = theta[idx] / S
    along = null @ (null.T @ phi)
    out = []
    pos = {j: i for i, j in enumerate(idx)}
    names = model.machine.layout.names
    for j in flagged:
        i = pos[j]
        # fewer rows than parameters: the directions beyond the rows are null by construction
        if idx.size > A.shape[0] or abs(along[i]) > 0.5 * abs(phi[i]):
            out.append(names[j])
    return out


def _outlier_cause(model, residuals, line_offset, dof_left) -> str | None:
    z2 = np.sum(whiten(model, residuals) ** 2, axis=1)
    total = float(z2.sum())
    n = z2.size
    if total <= 0 or dof_left <= 0 or total / dof_left <= 2.0:
        return None
    k = max(1, math.ceil(0.03 * n))
    worst = np.argsort(-z2)[:k]
    share = float(z2[worst].sum() / total)
    if share <= 0.5:
        return None
    lines = ", ".join(str(int(i) + line_offset) for i in sorted(worst))
    return f"outliers: {k} pose(s) (CSV line {lines}) carry {100 * share:.0f} % of the chi-square"


def frame_answer(machine: Machine, theta: NDArray, free: NDArray, covariance: NDArray | None) -> dict:
    """The ``"frame"`` block of the JSON answer (docs/formats.md section 4), ``"frames"`` for several stations (section 8).

    ``{}`` without an instrument frame.  ``std`` is that of the composed
    frame: the origin's is the correction's, the rotation vector's
    ``r = log(exp(d_phi) R0)`` is propagated through ``dr/de = J_l^-1(r) J_l(d_phi)``.
    """
    frame = machine.instrument_frame  # the frame, or the one under a view around it (fitted effects)
    if frame is None:
        return {}
    theta = np.asarray(theta, dtype=float)
    C = None
    if frame.fit and covariance is not None:
        P = np.asarray(free).size  # the model's parameters: the machine's, then its own (pivots, effects)
        C = np.full((P, P), np.nan)
        idx = np.flatnonzero(free)
        C[np.ix_(idx, idx)] = covariance
    blocks = [_one_frame(frame, theta, C, k) for k in range(frame.n_stations)]
    if frame.n_stations == 1:
        return {"frame": blocks[0]}
    return {"frames": dict(zip(frame.stations, blocks))}


def _one_frame(machine: InstrumentFrame, theta: NDArray, C: NDArray | None, k: int) -> dict:
    # a model's own parameters (ballbar pivots, effects) follow the machine's: the frame's lead them
    f = machine.frame_at(theta[: machine.n_params], k)
    rv = f.rotation_vector
    out = {"origin": f.origin.tolist(), "rotation_vector": rv.tolist(), "fitted": bool(machine.fit), "std": None}
    if C is not None:
        Cf = C[6 * k: 6 * k + 6, 6 * k: 6 * k + 6]
        std_o = np.sqrt(np.clip(np.diag(Cf[:3, :3]), 0, None))
        with np.errstate(all="ignore"):
            M = left_jacobian_inverse(rv) @ left_jacobian(theta[6 * k + 3: 6 * k + 6])
            std_r = np.sqrt(np.clip(np.diag(M @ Cf[3:, 3:] @ M.T), 0, None))
        clean = lambda v: [float(x) if np.isfinite(x) else None for x in v]  # noqa: E731
        out["std"] = {"origin": clean(std_o), "rotation_vector": clean(std_r)}
    return out


def judge_fit(machine, model, res, check=None) -> tuple[dict, "Plausibility"]:
    """The answer's ``frame``, ``plausible`` and ``frame_check`` entries of a fit, and the verdict.

    Parameters
    ----------
    machine : Machine
        As calibrated (an instrument frame's parameters lead ``res.theta``).
    model : Model
    res : bayescal.contract.Result
    check : FrameCheck, optional
        The rigid-transform check of a base-frame recording (``Session.check``).

    Returns
    -------
    (dict, Plausibility)
        The JSON keys every identify answer carries, and the verdict that decides whether a
        calibrated machine may be written.
    """
    theta = np.asarray(res.theta, dtype=float)
    if np.all(np.isfinite(theta)):
        plaus = assess_plausibility(model, theta, res.free, res.residuals_after, check=check,
                                    effective_params=res.prior_effective_params)
    else:
        plaus = Plausibility(False, ("the identified values are not finite",))
    if not res.success and plaus.plausible:
        # a failed fit is no calibration, whatever its values look like (an implausible one keeps its likely causes)
        plaus = Plausibility(False, ("the fit did not succeed (its message says why)",))
    extra = {**frame_answer(machine, theta, res.free, res.covariance), **plaus.to_dict()}
    if check is not None:
        extra["frame_check"] = check.to_dict()
    return extra, plaus


def refuse_implausible(plaus: Plausibility | None, force: bool = False, what: str = "write_machine") -> None:
    """InputError when a calibration judged implausible would be written (``force`` writes it anyway).

    ``what`` names the writer in the message (``write_machine``, a grid's ``write_csv``, ...).
    """
    from ..errors import InputError

    if plaus is not None and not plaus.plausible and not force:
        raise InputError(f"{what}: the calibration is not plausible (" + "; ".join(plaus.reasons)
                         + "); pass force=True to write it anyway")
