"""The model contract: what every solver, filter, sampler, report and study may ask of a measurement model.

A *model* is ``h(theta)`` for a fixed list of measurements with its analytic
Jacobian: :class:`bayescal.measurement.MeasurementModel` (tool poses, body
sensors), :class:`bayescal.constraints.model.ConstraintModel` (heights, distances,
ballbar radii, with fitted pivots) and
:class:`bayescal.effects.joint_model.EffectModel` (geometry and physical
effects fitted together) are three.  :class:`Model` names the members they
share; :func:`check_model` checks one against finite differences and
against itself (a subset predicts its rows of the whole, a noise scale
scales the row sigma), as :func:`bayescal.machines.check.check_machine`
checks a machine kind.  A new model kind passes ``check_model(model) == []``
and every consumer takes it.

An *identification result* is what a method returns for a model:
:class:`Result` names the members every one provides (least squares, ridge,
TSVD and MAP's :class:`bayescal.identify.result.IdentificationResult`, the
Kalman filter's :class:`bayescal.bayes.kalman.FilterResult`, the sampler's
:class:`bayescal.bayes.mcmc.PosteriorResult`), so the plausibility judge, the
noise tests, the held-out scoring and the reports read them by name and never
probe; :func:`check_result` checks one against its model.
"""

from __future__ import annotations

from typing import Any, Protocol, runtime_checkable

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .errors import BayescalError

__all__ = ["Model", "check_model", "ModelCheckError", "JACOBIAN_RTOL", "whiten", "scale_noise", "Result",
           "check_result"]

#: Largest relative difference between the analytic Jacobian and central differences.
JACOBIAN_RTOL = 2e-4


@runtime_checkable
class Model(Protocol):
    """``h(theta)`` of ``n_poses`` measurements with ``dof`` rows each (mm for lengths, rad for angles).

    Attributes
    ----------
    machine : Machine
        The machine whose parameters ``theta`` are (a view carries nuisance
        parameters after the geometry's: instrument frames first, then
        pivots, sensor mountings or effect parameters).
    n_params : int
        ``P``, the length of ``theta``; ``machine.n_params``.
    n_poses, dof, tool_dof : int
        Measurements, rows per measurement, and the tool's rows among them
        (body sensors' tilt rows are the rest).
    q, pose_q : ndarray
        Commanded actuator positions of the measurements, and of every pose
        the model solves (a distance row solves two).
    y_measured : ndarray (n_poses, dof) or None
        The measured values in ``h``'s rows.
    sigma, row_sigma : ndarray
        Nominal one-sigma per row (dof,), and per row of every measurement
        (n_poses, dof): what whitens residuals.
    pose_sigma, pose_offset, aux, guess, sensors, theta_start
        Per-measurement sigma, tool-pose perturbation (n_poses, 6) in mm and
        rad, auxiliary channels, kinematic start, body sensors, and the
        parameter vector a search starts from; each may be None.
    """

    machine: Any
    dof: int
    y_measured: NDArray | None
    pose_sigma: NDArray | None
    pose_offset: NDArray | None
    aux: dict | None

    @property
    def n_params(self) -> int: ...
    @property
    def n_poses(self) -> int: ...
    @property
    def tool_dof(self) -> int: ...
    @property
    def q(self) -> NDArray: ...
    @property
    def pose_q(self) -> NDArray: ...
    @property
    def pose_row(self) -> NDArray: ...
    @property
    def pose_order(self) -> NDArray | None: ...
    @property
    def sigma(self) -> NDArray: ...
    @property
    def row_sigma(self) -> NDArray: ...
    @property
    def guess(self) -> Any: ...
    @property
    def sensors(self) -> Any: ...
    @property
    def theta_start(self) -> NDArray | None: ...

    def predict(self, theta: ArrayLike | None = None, *, guess: Any = None) -> Any:
        """``h(theta)``: an object with ``y`` (n_poses, dof) and ``success`` (n_poses,)."""

    def jacobian(self, theta: ArrayLike | None, prediction: Any) -> NDArray:
        """``d h / d theta`` at ``prediction``'s poses, shape (n_poses, dof, n_params)."""

    def rows_jacobian(self, Jt: NDArray, prediction: Any) -> NDArray:
        """Rows of ``h`` moved by tool-pose perturbations ``Jt`` of every solved pose."""

    def residual(self, prediction: Any) -> NDArray:
        """``y_measured - h``, shape (n_poses, dof)."""

    def errors(self, residual: NDArray) -> tuple[NDArray, NDArray | None]:
        """Per-measurement position error (mm) and tool orientation error (rad, or None)."""

    def rms(self, residual: NDArray) -> dict: ...

    def region(self, prediction: Any) -> NDArray: ...

    def poses_of(self, rows: Any) -> NDArray: ...

    def effect_inputs(self, theta: NDArray, prediction: Any) -> tuple: ...

    def subset(self, idx: Any) -> "Model": ...

    def with_pose_sigma(self, pose_sigma: NDArray | None) -> "Model": ...

    def with_pose_q(self, pose_q: NDArray, *, keep_guess: bool = True) -> "Model": ...

    def with_pose_offset(self, pose_offset: NDArray | None) -> "Model": ...

    def without_sensors(self) -> "Model": ...

    def answer_extras(self, theta: NDArray) -> dict:
        """JSON keys an answer carries for the model's own nuisance parameters (a ballbar's pivots)."""

    @property
    def calibrated_machine(self) -> Any:
        """The machine a calibration of this model reports and writes (its frame; not the model's pivots)."""


def jacobian_into(model, theta, prediction, out: NDArray) -> NDArray:
    """``model.jacobian(theta, prediction)`` written into ``out`` (shape (n_poses, dof, P); a view of a system).

    A model whose ``jacobian`` takes ``out`` (:class:`bayescal.measurement.MeasurementModel`) writes there
    directly, a large recording's pose block by pose block: no fresh (n_poses, dof, P) array, whose page
    faults cost more than its arithmetic at 100,000 poses.  Any other model's answer is copied.

    Parameters
    ----------
    model : Model
    theta : array_like, shape (P,)
        Parameters (mm, rad) at which ``prediction`` was made.
    prediction : object
        ``model.predict(theta)``.
    out : ndarray, shape (n_poses, dof, P)
        Where the rows' derivatives (mm or rad per parameter unit) are written; may be a strided view.

    Returns
    -------
    ndarray
        ``out``.
    """
    if getattr(model.jacobian, "writes_into", False):
        return model.jacobian(theta, prediction, out=out)
    out[...] = model.jacobian(theta, prediction)
    return out


def whiten(model, values: ArrayLike, *, out: NDArray | None = None) -> NDArray:
    """``values`` in units of each row's one-sigma noise: the one place rows are whitened.

    Parameters
    ----------
    model : Model
    values : array_like, shape (n_poses, dof) or (n_poses, dof, P)
        Residuals (mm, rad) or Jacobian rows (per parameter unit) of the model's rows.
    out : ndarray, optional
        Where to write the answer (``values`` itself for an array the caller owns: the same values, without
        a fresh array of that size, whose page faults cost more than the division at 100,000 poses).

    Returns
    -------
    ndarray
        ``values / row_sigma`` (dimensionless; per parameter unit for a Jacobian).
    """
    v = np.asarray(values, dtype=float)
    sigma = np.asarray(model.row_sigma, dtype=float)
    return np.divide(v, sigma[:, :, None] if v.ndim == 3 else sigma, out=out)


def scale_noise(model, factor):
    """``model`` with every row's one-sigma noise multiplied by ``factor`` (``model`` itself for 1).

    Parameters
    ----------
    model : Model
    factor : float or array_like, shape (n_poses,)
        One factor for every row (a noise scale), or one per measurement
        (``1 / sqrt(weight)`` of a robust fit's weights).
    """
    f = np.asarray(factor, dtype=float)
    if f.ndim == 0:
        if float(f) == 1.0:
            return model
        return model.with_pose_sigma(np.asarray(model.row_sigma, dtype=float) * float(f))
    return model.with_pose_sigma(np.asarray(model.row_sigma, dtype=float) * f.reshape(-1, 1))


@runtime_checkable
class Result(Protocol):
    """What every identification method answers for a model of ``P`` parameters.

    Attributes
    ----------
    method : str
        ``ls``, ``ridge``, ``tsvd``, ``map``, ``kalman`` or ``mcmc`` (or a method added later).
    names, units : tuple of str
        All ``P`` parameters of the model's machine.
    theta : ndarray, shape (P,)
        The estimate (mm, rad); parameters not estimated stay where the method held them.
    free : ndarray of bool, shape (P,)
        Which parameters the method estimated.
    covariance : ndarray, shape (n_free, n_free) or None
        Of the estimated parameters (None: the method gives none).
    success : bool
    message : str
    rms_before, rms_after : dict
        ``{"position": mm, "angle": rad or None}`` against the start and the estimate.
    dof, n_poses : int
        Rows per measurement and measurements.
    fixed, unidentifiable, decided_by_prior : tuple of str
        Parameters held at nominal, why, and the combinations the prior decided.
    held : tuple of str
        Parameters the user held fixed (``fix``), apart from ``fixed``.
    bounds : tuple of (str, float, float)
        The user's bounds the answer kept (``bounds``), ``(name, lower, upper)``.
    at_bound : tuple of str
        Parameters the answer put on one of its bounds (not estimated there), apart from ``fixed`` and ``held``.
    determined : ndarray of bool, shape (P,), or None
        Which estimated parameters the data determine alone (None: all of them).
    tool_dof : int or None
        The tool's rows per measurement (None: ``dof``, no body sensors).
    residuals_before, residuals_after : ndarray, shape (n_poses, dof), or None
        ``y - h`` (mm, rad) at the start and at the estimate; None when the method keeps none
        (a consumer then predicts them from the model).
    filter_factors : ndarray or None
        Of a regularised linear solve (None: not one).
    tolerance : ndarray, shape (P,), or None
        The tolerances the answer was judged against (None: the model's machine's).
    extras : dict
        Further JSON keys of the answer (``prior_scale`` of an empirical-Bayes MAP, the outlier handling's).
    effective_params : float
        Effective number of fitted parameters: the filter factors summed, else the free ones counted.
    prior_effective_params : float or None
        The trace of the hat matrix under the method's tolerance prior (ridge, TSVD, MAP: the filter
        factors summed; Kalman and MCMC: ``n - tr(P_prior^-1 P_post)``); None without a prior (least squares)
        or when it is not finite.
    """

    method: str
    names: tuple
    units: tuple
    theta: NDArray
    free: NDArray
    success: bool
    message: str
    rms_before: dict
    rms_after: dict
    dof: int
    fixed: tuple
    unidentifiable: tuple
    decided_by_prior: tuple
    held: tuple
    bounds: tuple
    at_bound: tuple
    determined: NDArray | None
    tool_dof: int | None

    @property
    def covariance(self) -> NDArray | None: ...
    @property
    def n_poses(self) -> int: ...
    @property
    def residuals_before(self) -> NDArray | None: ...
    @property
    def residuals_after(self) -> NDArray | None: ...
    @property
    def filter_factors(self) -> NDArray | None: ...
    @property
    def tolerance(self) -> NDArray | None: ...
    @property
    def extras(self) -> dict: ...
    @property
    def effective_params(self) -> float: ...
    @property
    def prior_effective_params(self) -> float | None: ...

    def poorly_determined(self, factor: float = ...) -> tuple[str, ...]:
        """Estimated parameters whose std exceeds ``factor`` times their tolerance (() without tolerances)."""

    def to_dict(self) -> dict:
        """The JSON answer (docs/formats.md section 3)."""

    def report(self) -> str:
        """The text report ``bayescal identify`` prints."""


def _result_members() -> list[str]:
    return sorted(n for n in Result.__protocol_attrs__ if not n.startswith("_"))


def check_result(result, model=None) -> list[str]:
    """What ``result`` does not provide that :class:`Result` asks; an empty list when it conforms.

    Checks every member is there and that the shapes agree with one another
    and with ``model`` (when given): ``theta``, ``free``, ``names`` and
    ``units`` of length ``P``; ``covariance`` square over the free
    parameters; residuals of ``(n_poses, dof)`` rows; the effective numbers
    of parameters within ``[0, n_free]``; and a ``to_dict()`` and ``report()``
    that run.

    Parameters
    ----------
    result : Result
    model : Model, optional
        The model the result was fitted to.
    """
    missing = [n for n in _result_members() if not hasattr(result, n)]
    if missing:
        return [f"missing member(s) of the result contract: {', '.join(missing)}"]
    problems: list[str] = []
    P = np.asarray(result.theta).shape[0]
    free = np.asarray(result.free)
    if free.dtype != bool or free.shape != (P,):
        problems.append(f"free: expected bool of shape ({P},), got {free.dtype} {free.shape}")
    if len(result.names) != P or len(result.units) != P:
        problems.append(f"names/units: {len(result.names)}/{len(result.units)} entries for {P} parameters")
    n_free = int(free.sum())
    if result.covariance is not None and np.shape(result.covariance) != (n_free, n_free):
        problems.append(f"covariance: shape {np.shape(result.covariance)}, expected ({n_free}, {n_free})")
    if model is not None:
        if P != model.n_params:
            problems.append(f"theta: {P} parameters, the model has {model.n_params}")
        if result.n_poses != model.n_poses or result.dof != model.dof:
            problems.append(f"n_poses, dof: ({result.n_poses}, {result.dof}), the model's ({model.n_poses}, {model.dof})")
    shape = (result.n_poses, result.dof)
    for key in ("residuals_before", "residuals_after"):
        r = result.residuals_before if key == "residuals_before" else result.residuals_after
        if r is not None and np.shape(r) != shape:
            problems.append(f"{key}: shape {np.shape(r)}, expected (n_poses, dof) = {shape}")
    if not 0.0 <= result.effective_params <= n_free + 1e-9:
        problems.append(f"effective_params {result.effective_params} not in [0, {n_free}]")
    pe = result.prior_effective_params
    if pe is not None and not 0.0 <= pe <= n_free + 1e-9:
        problems.append(f"prior_effective_params {pe} not in [0, {n_free}]")
    if result.tolerance is not None and np.shape(result.tolerance) != (P,):
        problems.append(f"tolerance: shape {np.shape(result.tolerance)}, expected ({P},)")
    if problems:  # the methods below read these shapes
        return problems
    if not isinstance(result.poorly_determined(), tuple):
        problems.append("poorly_determined() does not return a tuple")
    if not isinstance(result.to_dict(), dict) or not isinstance(result.report(), str):
        problems.append("to_dict() must return a dict and report() a str")
    return problems


class ModelCheckError(BayescalError):
    """A model fails :func:`check_model` (``strict=True``); ``problems`` lists why."""

    def __init__(self, problems: list[str]):
        self.problems = problems
        super().__init__("model check failed:\n  " + "\n  ".join(problems))


def _members() -> list[str]:
    return sorted(n for n in Model.__protocol_attrs__ if not n.startswith("_"))


def check_model(model, theta: ArrayLike | None = None, *, strict: bool = False, step: float = 1e-3) -> list[str]:
    """What ``model`` does not do that the contract (:class:`Model`) asks; an empty list when it conforms.

    Checks, each from first principles rather than from the model's own code:
    every member is there; ``n_params`` is the machine's; ``predict`` gives
    ``(n_poses, dof)`` finite rows; ``jacobian`` agrees with central
    differences of ``predict`` (steps of ``step`` times each parameter's
    tolerance); ``residual`` is ``y_measured - h``; ``row_sigma`` is positive
    of ``h``'s shape and scales with ``with_pose_sigma``; ``subset`` predicts
    its rows of the whole model.

    Parameters
    ----------
    model : Model
    theta : array_like, shape (n_params,), optional
        Where to check (default: :attr:`Model.theta_start` or zero, moved by a
        quarter of each tolerance with alternating signs so that no
        parameter sits at its start, and kept a quarter tolerance inside a
        physical lower bound, ``machine.prior_lower``).
    strict : bool
        Raise :class:`ModelCheckError` instead of returning the problems.
    step : float
        Central-difference step as a fraction of each parameter's tolerance.
    """
    problems: list[str] = []
    missing = [n for n in _members() if not hasattr(model, n)]
    if missing:
        problems.append(f"missing member(s) of the model contract: {', '.join(missing)}")
        return _done(problems, strict)
    P = model.n_params
    if P != model.machine.n_params:
        problems.append(f"n_params {P} is not the machine's {model.machine.n_params}")
    tol = np.asarray(model.machine.tolerance, dtype=float)
    tol = np.where(np.isfinite(tol) & (tol > 0), tol, 1.0)
    if theta is None:
        start = np.zeros(P) if model.theta_start is None else np.asarray(model.theta_start, dtype=float)
        theta = start + 0.25 * tol * np.where(np.arange(P) % 2, -1.0, 1.0)
        # a parameter with a physical bound (a dead band, a mass: prior_lower) is checked inside it
        low = model.machine.prior_lower
        low = np.full(P, -np.inf) if low is None else np.asarray(low, dtype=float)
        theta = np.where(np.isfinite(low), np.maximum(theta, low + 0.25 * tol), theta)
    theta = np.asarray(theta, dtype=float)
    pred = model.predict(theta)
    shape = (model.n_poses, model.dof)
    if pred.y.shape != shape:
        problems.append(f"predict: y has shape {pred.y.shape}, expected (n_poses, dof) = {shape}")
        return _done(problems, strict)
    if not np.all(pred.success) or not np.all(np.isfinite(pred.y)):
        problems.append("predict: not every measurement solved to finite rows at the check's theta")
        return _done(problems, strict)
    if not 0 < model.tool_dof <= model.dof:
        problems.append(f"tool_dof {model.tool_dof} not in 1..dof ({model.dof})")
    sig = np.asarray(model.row_sigma)
    if sig.shape != shape or not np.all(sig > 0):
        problems.append(f"row_sigma: expected positive values of shape {shape}, got shape {sig.shape}")
    else:
        scaled = model.with_pose_sigma(2.0 * sig).row_sigma
        if not np.allclose(scaled, 2.0 * sig, rtol=1e-12):
            problems.append("with_pose_sigma(2 row_sigma).row_sigma is not 2 row_sigma")
    if model.y_measured is not None:
        r = model.residual(pred)
        if not np.allclose(r, model.y_measured - pred.y, rtol=0, atol=1e-12 * (1 + np.abs(pred.y).max())):
            problems.append("residual is not y_measured - predict(theta).y")
    J = model.jacobian(theta, pred)
    if J.shape != shape + (P,):
        problems.append(f"jacobian: shape {J.shape}, expected (n_poses, dof, n_params) = {shape + (P,)}")
    else:
        problems += _jacobian_problems(model, theta, J, tol * step)
    problems += _subset_problems(model, theta, pred)
    return _done(problems, strict)


def _jacobian_problems(model, theta: NDArray, J: NDArray, h: NDArray) -> list[str]:
    out = []
    names = model.machine.layout.names
    for k in range(theta.size):
        e = np.zeros_like(theta)
        e[k] = h[k]
        plus, minus = model.predict(theta + e), model.predict(theta - e)
        fd = (plus.y - minus.y) / (2 * h[k])
        scale = max(float(np.abs(fd).max()), float(np.abs(J[..., k]).max()))
        err = float(np.abs(J[..., k] - fd).max())
        if err > JACOBIAN_RTOL * scale + 1e-9:
            out.append(f"jacobian: column {k} ({names[k]}) differs from central differences by {err:.3e} "
                       f"(largest entry {scale:.3e})")
    return out


def _subset_problems(model, theta: NDArray, pred) -> list[str]:
    n = model.n_poses
    if n < 2:
        return []
    idx = np.arange(n)[::-2][::-1]  # every other row, the last included
    sub = model.subset(idx)
    if sub.n_poses != idx.size:
        return [f"subset: {sub.n_poses} measurements, expected {idx.size}"]
    y = sub.predict(theta).y
    if not np.allclose(y, pred.y[idx], rtol=1e-9, atol=1e-9):
        return [f"subset: predicts its rows of the whole model differently (largest difference "
                f"{float(np.abs(y - pred.y[idx]).max()):.3e})"]
    return []


def _done(problems: list[str], strict: bool) -> list[str]:
    if strict and problems:
        raise ModelCheckError(problems)
    return problems
