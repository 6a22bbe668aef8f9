"""The augmented measurement model ``h(q + dq(eta), theta)`` (its tool poses moved by ``dx(eta)`` of the
effects that move the tool) and its joint MAP fit.

Unknowns are the geometric errors ``theta`` (prior ``N(0, tolerance^2)``)
and the effect parameters ``eta`` (prior ``N(mean, sd^2)`` per
:class:`~bayescal.effects.EffectParam`).  In the scaled coordinates
``phi = (theta / tolerance, (eta - 0) / sd)`` the fit minimises

    |W (y - h)|^2 + |phi - phi_prior|^2

by Gauss-Newton with step halving (the loop of :mod:`bayescal.iteration`,
its stop tests blind to cost no parameter can reduce): with no effect this is exactly
``identify(model, method="ridge", lam=1, free="all")`` (the MAP estimate
under the tolerance prior); a thin reimplementation here because the
effect parameters need their own prior means and their Jacobian columns
``(d h / d q) (d dq / d eta)`` plus, for an effect that moves the tool, the
rows of ``d dx / d eta`` (:func:`bayescal.measurement.pose_offset_rows`).  The Laplace approximation at the MAP gives
the posterior covariance ``(A^T A + I)^-1`` and the log marginal likelihood

    log Z = -(chi2 + |phi - phi_prior|^2) / 2 - log det(A^T A + I) / 2 + const.
"""

from __future__ import annotations

import weakref
from dataclasses import dataclass, field
from typing import Sequence

import numpy as np
from numpy.typing import NDArray

from ..contract import jacobian_into, whiten
from ..errors import KinematicsError
from ..iteration import ROUNDOFF, Proposal, StepControl, gauss_newton
from ..machines.base import ToolPoses, map_state
from ..measurement import MeasurementModel, Prediction, pose_offset_rows
from .base import Effect, EffectParam, Features

__all__ = ["EffectFit", "fit_map", "joint_system", "joint_information", "linear_fold_residuals", "effect_residual",
           "actuator_residual", "effect_jacobian", "actuator_rows_jacobian"]


@dataclass(frozen=True)
class EffectFit:
    """A joint MAP fit of geometry and effects.

    Attributes
    ----------
    theta : ndarray, shape (P,)
        Geometric errors (mm, rad).
    eta : ndarray, shape (K,)
        Effect parameters, in their units.
    params : tuple of EffectParam
        Names, units and priors of ``eta``.
    effect_slices : tuple of (str, slice)
        Which entries of ``eta`` belong to which effect.
    cov_eta : ndarray, shape (K, K)
        Laplace posterior covariance of ``eta`` (unit noise scale).
    residual : ndarray, shape (n_poses, dof)
        ``y - h`` at the fit, mm and rad.
    chi2 : float
        Whitened sum of squared residuals.
    prior_term : float
        ``|phi - phi_prior|^2``.
    singular_values : ndarray
        Of the whitened, scaled Jacobian ``A`` at the fit.
    n_rows : int
    success : bool
    message : str
    iterations : int
    covariance : ndarray, shape (P + K, P + K), or None
        Laplace posterior covariance of ``(theta, eta)`` together, in their
        units (unit noise scale): how far the geometry trades off against
        the effects (:mod:`bayescal.diagnose.confound`).
    system : tuple of ndarray, or None
        ``(A, rw)``: the whitened, scaled Jacobian at the fit (rows, P + K)
        and the whitened residual, when :func:`fit_map` was asked to keep
        them (``keep_system``); None otherwise.  Large (rows times
        parameters): drop it (``dataclasses.replace(fit, system=None)``)
        once used.
    """

    theta: NDArray
    eta: NDArray
    params: tuple[EffectParam, ...]
    effect_slices: tuple[tuple[str, slice], ...]
    cov_eta: NDArray
    residual: NDArray
    chi2: float
    prior_term: float
    singular_values: NDArray
    n_rows: int
    success: bool
    message: str
    iterations: int
    covariance: NDArray | None = None
    system: tuple | None = None

    @property
    def edf(self) -> float:
        """Effective number of fitted parameters, ``sum s^2 / (s^2 + 1)``."""
        s2 = self.singular_values**2
        return float(np.sum(s2 / (s2 + 1.0)))

    def log_evidence(self, noise_scale2: float = 1.0) -> float:
        """Laplace log marginal likelihood (up to a constant shared by all models of the same data).

        Parameters
        ----------
        noise_scale2 : float
            Factor on the instrument variance (1: as stated in the machine file).
        """
        s2 = self.singular_values**2 / noise_scale2
        return float(-0.5 * (self.chi2 / noise_scale2 + self.prior_term) - 0.5 * np.sum(np.log1p(s2)))

    def std_eta(self, noise_scale2: float = 1.0) -> NDArray:
        """One-sigma of ``eta`` in its units."""
        return np.sqrt(np.clip(np.diag(self.cov_eta), 0, None) * noise_scale2)


def _dq(effects: Sequence[tuple[Effect, Features]], slices, eta: NDArray, shape, theta: NDArray | None = None) -> NDArray:
    """``sum_e dq_e``; at the geometry ``theta`` for effects whose ``dq`` depends on it (Effect.geometry_dependent)."""
    dq = np.zeros(shape)
    for (eff, f), sl in zip(effects, slices):
        dq += eff.delta_q(f, eta[sl]) if theta is None else eff.delta_q_at(f, eta[sl], theta)
    return dq


def _dx(effects: Sequence[tuple[Effect, Features]], slices, eta: NDArray, n: int) -> NDArray | None:
    """``sum_e dx_e`` of the effects that move the tool, shape (n, 6), or None when none does."""
    out = None
    for (eff, f), sl in zip(effects, slices):
        if eff.moves_tool:
            out = (0.0 if out is None else out) + eff.delta_x(f, eta[sl])
    return out


def _bend(effects: Sequence[tuple[Effect, Features]], slices, eta: NDArray, model: MeasurementModel) -> NDArray | None:
    """``sum_e w_e``: how the effects that bend the structure turn the bodies of ``model``'s sensors, (n, S, 3) or None."""
    if model.sensors is None:
        return None
    out = None
    for (eff, f), sl in zip(effects, slices):
        w = model.sensors.per_sensor(eff.body_rotation(f, eta[sl])) if eff.bends_bodies else None
        if w is not None:
            out = w if out is None else out + w
    return out


def _bend_rows(model: MeasurementModel, theta: NDArray, eff: Effect, f: Features, eta: NDArray) -> NDArray | None:
    """``d (sensor rows) / d eta`` of an effect that bends bodies, (n, 2 S, k), or None."""
    if model.sensors is None or not eff.bends_bodies:
        return None
    from ..sensors import sensor_rotation_rows

    rot = model.sensors.per_sensor(eff.body_rotation_jacobian(f, eta))
    if rot is None:
        return None
    return sensor_rotation_rows(model.machine, model.sensors, model.q, model.machine.check_theta(theta), rot)


def _at(model: MeasurementModel, q_eff: NDArray, dx: NDArray | None, *, keep_guess: bool = True,
        bend: NDArray | None = None) -> MeasurementModel:
    """``model`` at the solved poses' actuator positions ``q_eff`` with the tool perturbation ``dx`` added to its own
    (and its sensors' bodies turned by ``bend``)."""
    sub = model.with_pose_q(q_eff, keep_guess=keep_guess)
    if dx is not None:
        own = model.pose_offset
        sub = sub.with_pose_offset(dx if own is None else own + dx)
    if bend is not None:
        from dataclasses import replace

        sub = replace(sub, sensors=sub.sensors.with_bend(bend))
    return sub


def _effect_theta(model: MeasurementModel, theta: NDArray) -> NDArray:
    """The geometry the effects see (:meth:`MeasurementModel.effect_inputs`: a constraint model drops its pivots)."""
    return model.effect_inputs(np.asarray(theta, dtype=float), None)[1]


def _merge(pred: Prediction, other: Prediction) -> Prediction:
    """Per pose, ``pred`` where it converged, else ``other`` where that did."""
    take = ~pred.success & other.success
    if not take.any():
        return pred
    if take.shape[0] != pred.poses.position.shape[0]:
        # rows of several poses (a distance): no per-pose merge, take the better prediction whole
        return other if other.success.sum() > pred.success.sum() else pred
    st, ost = pred.poses.state, other.poses.state

    def pick(a, b):
        return np.where(take.reshape((-1,) + (1,) * (a.ndim - 1)), b, a)

    state = map_state(pick, st, ost)
    poses = ToolPoses(
        pick(pred.poses.position, other.poses.position), pick(pred.poses.rotation, other.poses.rotation),
        pred.success | take, tuple(o if t else m for m, o, t in zip(pred.poses.message, other.poses.message, take)), state,
    )
    return Prediction(y=pick(pred.y, other.y), poses=poses)


def _predict(model: MeasurementModel, q_eff: NDArray, theta: NDArray, guess, note: str = " (with the effect applied)",
             dx: NDArray | None = None, bend: NDArray | None = None) -> tuple[MeasurementModel, Prediction]:
    # q_eff: every solved pose's actuator positions (model.pose_q + dq), as effects act on poses, not rows;
    # dx: the tool perturbation of effects that move the tool (None: none); bend: their turn of sensor bodies
    sub = _at(model, q_eff, dx, bend=bend)
    pred = sub.predict(theta, guess=guess)
    if not pred.success.all():
        # Newton from a given start can miss a pose that a nearby start solves: retry from the
        # solution at the commanded q (effects move q by microns), then from the assembly-branch start
        base = model.predict(theta)
        if base.success.any():
            pred = _merge(pred, sub.predict(theta, guess=base.poses))
        if not pred.success.all():
            pred = _merge(pred, _at(model, q_eff, dx, keep_guess=False, bend=bend).predict(theta, guess=None))
    if not pred.success.all():
        i = int(np.flatnonzero(~pred.success)[0])
        raise KinematicsError(f"pose {i + 1}: {pred.poses.message[i]}{note}")
    return sub, pred


def effect_residual(
    model: MeasurementModel, effects: Sequence[tuple[Effect, Features]], theta: NDArray, eta: NDArray
) -> NDArray:
    """``y - h(q + dq(eta), theta)``, shape (n_poses, dof): prediction on (held-out) poses.

    The features are those of the model's solved poses (:attr:`MeasurementModel.pose_q`).
    """
    slices = _slices(effects, model)
    eta = np.asarray(eta, float)
    q_eff = model.pose_q + _dq(effects, slices, eta, model.pose_q.shape, _effect_theta(model, theta))
    _, pred = _predict(model, q_eff, theta, None, dx=_dx(effects, slices, eta, model.pose_q.shape[0]),
                       bend=_bend(effects, slices, eta, model))
    return model.residual(pred)


def actuator_residual(model: MeasurementModel, theta: NDArray, residual: NDArray, prediction: Prediction) -> NDArray:
    """Residuals mapped to actuator space: per row the ``dq`` (mm) of its own pose that best explains them (whitened LS).

    Returns an array of shape (n_poses, n_actuators): the change of the row's
    first pose (``model.q``); a row's other poses (a distance's pose b) are
    held, so that the answer is one actuator vector per row.
    """
    Jq = actuator_rows_jacobian(model, theta, prediction, own_pose_only=True)
    Jw = whiten(model, Jq)
    rw = whiten(model, residual)
    return np.stack([np.linalg.lstsq(Jw[i], rw[i], rcond=None)[0] for i in range(model.n_poses)])


def actuator_rows_jacobian(model: MeasurementModel, theta: NDArray, prediction: Prediction, *, own_pose_only: bool = False) -> NDArray:
    """``d rows / d q`` of every solved pose, per pose, shape (n_solved, 6, N) before the rows map.

    Returns the rows' derivative, shape (n_poses, dof, N), with respect to a
    common change of every solved pose's actuator positions; with
    ``own_pose_only`` only the rows' first poses move.
    """
    machine, th, poses = model.effect_inputs(theta, prediction)
    Ja = machine.actuator_jacobian(model.pose_q, th, poses)
    if own_pose_only:
        Ja = Ja.copy()
        Ja[model.n_poses :] = 0.0
    return _sensor_rows_added(model, theta, model.rows_jacobian(Ja, prediction), None)


def _sensor_rows_added(model: MeasurementModel, theta: NDArray, rows: NDArray, dq_jacobian: NDArray | None) -> NDArray:
    """``rows`` (n, dof, k) with the body sensors' tilt rows filled in: ``d tilt / d q`` (times ``dq_jacobian``).

    :meth:`MeasurementModel.rows_jacobian` maps a tool-pose derivative, which leaves the sensors' rows at
    zero; an effect's ``dq`` turns the bodies the sensors sit on as it moves the tool (recordings with body
    sensors are one pose per row).
    """
    if model.sensors is None:
        return rows
    from ..sensors import sensor_actuator_jacobian

    Sq = sensor_actuator_jacobian(model.machine, model.sensors, model.q, model.machine.check_theta(theta))
    rows = rows.copy()
    rows[:, model.tool_dof :] = Sq if dq_jacobian is None else np.einsum("pmn,pnk->pmk", Sq, dq_jacobian)
    return rows


def effect_columns(model: MeasurementModel, theta: NDArray, prediction: Prediction, effects, slices, eta) -> tuple[list[NDArray], NDArray | None]:
    """The effects' Jacobian columns by the chain rule through every solved pose's ``dq``.

    Returns
    -------
    columns : list of ndarray
        Per effect, ``d rows / d eta``, shape (n_poses, dof, k).
    geometric : ndarray or None
        What ``dq``'s dependence on the geometry adds to the geometric columns,
        ``(d rows / d q) (d dq / d theta)``, shape (n_poses, dof, P) (zero for
        nuisance parameters the effects do not see); None when no effect is
        :attr:`~bayescal.effects.base.Effect.geometry_dependent`.
    """
    machine, th, poses = model.effect_inputs(theta, prediction)
    Ja = machine.actuator_jacobian(model.pose_q, th, poses)
    cols, extra = [], None
    for (eff, f), sl in zip(effects, slices):
        dq_jac = eff.delta_q_jacobian_at(f, eta[sl], th)
        col = _sensor_rows_added(model, theta, model.rows_jacobian(np.einsum("pmn,pnk->pmk", Ja, dq_jac), prediction), dq_jac)
        if eff.moves_tool:
            # the tool perturbation reaches the rows through each pose's measurement rotation
            col = col + pose_offset_rows(model, theta, prediction, eff.delta_x_jacobian(f, eta[sl]))
        bent = _bend_rows(model, theta, eff, f, eta[sl])
        if bent is not None:
            col = col.copy()
            col[:, model.tool_dof :] += bent
        cols.append(col)
        Jt = eff.delta_q_theta_jacobian(f, eta[sl], th)
        if Jt is not None:
            add = _sensor_rows_added(model, theta, model.rows_jacobian(np.einsum("pmn,pnk->pmk", Ja, Jt), prediction), Jt)
            P = model.machine.n_params
            if add.shape[2] < P:
                # the effects see the leading geometry only; nuisance parameters (pivots) come last
                add = np.concatenate([add, np.zeros(add.shape[:2] + (P - add.shape[2],))], axis=2)
            extra = add if extra is None else extra + add
    return cols, extra


def effect_jacobian(model: MeasurementModel, theta: NDArray, prediction: Prediction, effects, slices, eta) -> list[NDArray]:
    """Per effect, ``d rows / d eta``, shape (n_poses, dof, k) (:func:`effect_columns`)."""
    return effect_columns(model, theta, prediction, effects, slices, eta)[0]


def _slices(effects, model) -> list[slice]:
    out, k = [], 0
    for eff, f in effects:
        n = len(eff.params(model.machine, f))
        out.append(slice(k, k + n))
        k += n
    return out


#: Rows from which ``A^T A`` is BLAS's: below, einsum (a threaded BLAS spin-waits on a shared machine for
#: matrices this small); above, einsum's unblocked loop costs five to seven times BLAS (at 1,000 poses and more).
_GRAM_BLAS_ROWS = 4_000


def _gram(A: NDArray) -> NDArray:
    """``A^T A``."""
    return A.T @ A if A.shape[0] >= _GRAM_BLAS_ROWS else np.einsum("ij,ik->jk", A, A)


@dataclass(frozen=True)
class _Joint:
    """The joint fit's pieces for a model and its effects: prior scales and means, and the whitened system."""

    model: MeasurementModel
    effects: tuple
    slices: tuple
    params: tuple
    scale: NDArray
    mu: NDArray
    #: The system's buffer and the state whose system it holds (:meth:`system`); per fit, never compared.
    workspace: dict = field(default_factory=dict, compare=False, repr=False)

    @classmethod
    def of(cls, model: MeasurementModel, effects) -> "_Joint":
        effects = tuple(effects)
        params: list[EffectParam] = []
        for eff, f in effects:
            params += list(eff.params(model.machine, f))
        P = model.machine.n_params
        scale = np.concatenate([model.machine.tolerance, [p.prior_sd for p in params]])
        mu = np.concatenate([np.zeros(P), [p.prior_mean for p in params]]) / scale
        return cls(model, effects, tuple(_slices(effects, model)), tuple(params), scale, mu)

    @property
    def P(self) -> int:
        return self.model.machine.n_params

    @property
    def K(self) -> int:
        return len(self.params)

    def evaluate(self, theta, eta, guess):
        """``(model at the effects, prediction, residual, whitened residual, chi2, prior term)`` at ``(theta, eta)``."""
        model, effects, slices = self.model, self.effects, self.slices
        q_eff = model.pose_q + _dq(effects, slices, eta, model.pose_q.shape, _effect_theta(model, theta))
        sub, pred = _predict(model, q_eff, theta, guess, " (with the effect applied)" if self.K else "",
                             dx=_dx(effects, slices, eta, model.pose_q.shape[0]), bend=_bend(effects, slices, eta, model))
        r = model.residual(pred)
        rw = whiten(model, r).reshape(-1)
        phi = np.concatenate([theta, eta]) / self.scale
        return sub, pred, r, rw, float(rw @ rw), float(np.sum((phi - self.mu) ** 2))

    def system(self, sub, pred, theta, eta, owner=None):
        """The whitened Jacobian in the scaled coordinates, shape (rows, P + K).

        With ``owner`` (a :class:`_State`) the answer is written into this fit's one buffer, which ``owner`` then
        holds (:meth:`_State.system`): the values of ``whiten(concatenate([Jg + Jt] + Je)).reshape(-1, P + K) *
        scale``, bit for bit.  At 100,000 poses each fresh (rows x parameters) array costs its page faults
        again (about 3 ns an element against 1 for the arithmetic; glibc gives arrays above 32 MB back to the
        kernel when freed and reuses smaller ones, so this cost grows faster than the poses from 10,000 on);
        one buffer for every iteration of a fit pays them once.
        """
        Je, Jt = effect_columns(sub, theta, pred, self.effects, self.slices, eta) if self.K else ([], None)
        J = self._buffer((sub.n_poses, sub.dof, self.P + self.K), owner)
        k = self.P
        jacobian_into(sub, theta, pred, J[:, :, :k])  # written into the system: a model's own J is not touched
        if Jt is not None:
            J[:, :, :k] += Jt
        for c in Je:
            J[:, :, k : k + c.shape[2]] = c
            k += c.shape[2]
        whiten(self.model, J, out=J)
        A = J.reshape(-1, self.P + self.K)
        A *= self.scale
        return A

    def _buffer(self, shape: tuple, owner) -> NDArray:
        """This fit's system buffer of ``shape``, now ``owner``'s (a new array without an owner)."""
        if owner is None:
            return np.empty(shape)
        held = self.workspace.get("system")
        if held is None or held.shape != shape:
            held = self.workspace["system"] = np.empty(shape)
        self.workspace["owner"] = weakref.ref(owner)
        return held

    def owns(self, state: "_State") -> bool:
        """Whether the buffer holds ``state``'s system (no other state's was written into it since)."""
        ref = self.workspace.get("owner")
        return ref is not None and ref() is state

    def state(self, theta, eta, guess) -> tuple[float, "_State"]:
        """The cost (chi-square plus prior term) and the state at ``(theta, eta)``; KinematicsError if a pose fails."""
        sub, pred, r, rw, chi2, prior = self.evaluate(theta, eta, guess)
        return chi2 + prior, _State(self, theta, eta, sub, pred, r, rw, chi2, prior)

    def at(self, x: NDArray, current: "_State") -> tuple[float, "_State"]:
        """:meth:`state` at ``x = (theta, eta)``, warm-started from the current state's poses."""
        return self.state(x[: self.P], x[self.P :], current.pred.poses)

    def propose(self, x: NDArray, current: "_State") -> Proposal:
        """The Gauss-Newton step of ``|r - A d|^2 + |mu - phi - d|^2`` and the decrease it predicts.

        Normal equations of ``[A; I] d ~ [r; mu - phi]``: ``H = A^T A + I`` is
        well conditioned (>= I).  The predicted decrease ``d^T g`` (``g`` the
        right-hand side) is the gradient in the metric of ``H``: no row the
        parameters do not move enters it.
        """
        A = current.system()
        phi = x / self.scale
        g = np.einsum("ij,i->j", A, current.rw) + (self.mu - phi)
        d = np.linalg.solve(_gram(A) + np.eye(self.P + self.K), g)
        return Proposal(step=d * self.scale, predicted=float(d @ g))


@dataclass
class _State:
    """The joint fit at one point: the model at the effects, its prediction and residuals; the system on demand."""

    joint: _Joint
    theta: NDArray
    eta: NDArray
    sub: MeasurementModel
    pred: Prediction
    r: NDArray
    rw: NDArray
    chi2: float
    prior: float
    _A: NDArray | None = None

    def system(self) -> NDArray:
        """:meth:`_Joint.system` here, computed once (a trial the line search refuses never needs it).

        In the fit's one buffer: computed again if another state's system has been written into it since.
        """
        if self._A is None or not self.joint.owns(self):
            self._A = self.joint.system(self.sub, self.pred, self.theta, self.eta, owner=self)
        return self._A


def joint_information(model: MeasurementModel, effects: Sequence[tuple[Effect, Features]], theta: NDArray,
                      eta: NDArray) -> tuple[NDArray, NDArray]:
    """The joint fit's whitened Jacobian at ``(theta, eta)`` and the prior scales of its columns.

    Parameters
    ----------
    model : MeasurementModel
    effects : sequence of (Effect, Features)
    theta, eta : ndarray
        Geometric errors (mm, rad) and effect parameters (their units).

    Returns
    -------
    A : ndarray, shape (rows, P + K)
        ``d (W r) / d phi`` in the prior-scaled coordinates ``phi = (theta, eta) / scale``:
        the posterior precision of ``phi`` is ``A^T A + I`` (:func:`fit_map`).
    scale : ndarray, shape (P + K,)
        The prior standard deviations (tolerances, then the effect parameters' ``prior_sd``).

    Raises
    ------
    KinematicsError
        A pose does not assemble at ``(theta, eta)``.
    """
    return joint_system(model, effects, theta, eta)[0], _Joint.of(model, effects).scale


#: The joint fit's step control: a step must not raise the cost, halved up to 7 times (8 trials), each
#: iteration starting from twice the share the last one took.  Where full steps lower the cost this is the
#: plain iteration; in a curved valley (an effect that multiplies two unknowns, a compliance and a mass) the
#: step is cut alike every time, and starting near that cut saves the evaluations of halving down to it
#: again (1,000 poses: 5 evaluations per iteration -> 2).
MAP_STEP_CONTROL = StepControl(descent=True, halvings=7, remember=True)
#: The joint fit has converged when a Gauss-Newton step predicts a decrease of the cost below this (chi-square
#: units): the linearised optimum within ``sqrt(MAP_DTOL)`` = 0.03 posterior standard deviations, the log
#: evidence within half this.  Absolute: the test it replaces, a decrease below 1e-7 of the total cost, let rows
#: no parameter moves (an effect the model lacks) stop fits far from their optimum (0.24 chi-square above it in
#: tests/effects/test_model.py).  At a few thousand well-fitted rows this takes about the old test's iterations
#: (the diagnosis benchmark at 1,000 poses: 144 against 141); 1e-4 took 28 % more there, 1e-6 a third more over
#: the diagnosis tests, for changes of the cost below 1e-3.
MAP_DTOL = 1e-3
#: Poses from which :func:`fit_map` with effects starts from a fit of every :data:`COARSE_STRIDE`-th row
#: (:func:`_coarse_start`) where the full Gauss-Newton step from its start raises the cost (:func:`_curved`;
#: elsewhere the coarse fit only cost time: at 100,000 poses the periodic-screw fit took 11, 8 and 8
#: iterations from it, 39 s of CPU, and 6 from its own start, 24 s; the thermal one 17 s against 14 s).
#: An effect that multiplies two unknowns (a compliance and a mass) makes the cost a
#: curved valley whose width shrinks like one over the root of the poses, and Gauss-Newton crawls along it in
#: steps that shrink alike: on the 3-PRS recording of benchmarks/diagnose_speed.py (backlash concealed) the
#: joint-compliance fit took 24 iterations at 10,000 poses, about 32 at 20,000 and 40,000, and did not converge
#: in 40 (189 s of CPU, a third of the diagnosis) at 100,000.  A quarter of the rows crawls most of the valley
#: at a quarter of the cost: at 40,000 poses the full fit then took 19 iterations (29 s CPU, after 6 s for the
#: coarse fit) instead of about 32.  Below this the fit is unchanged (every test and the 1,000 and 10,000 pose
#: benchmark diagnoses give identical answers).
COARSE_START_POSES = 20_000
#: Every how many rows the coarse start fits (a quarter of the rows, spread over the whole recording).
COARSE_STRIDE = 4


def fit_map(
    model: MeasurementModel,
    effects: Sequence[tuple[Effect, Features]] = (),
    *,
    theta0: NDArray | None = None,
    eta0: NDArray | None = None,
    max_iter: int = 40,
    xtol: float = 1e-4,
    coarse: bool = True,
    keep_system: bool = False,
) -> EffectFit:
    """Joint MAP fit of geometric errors and effect parameters (see the module docstring).

    Parameters
    ----------
    model : MeasurementModel
        With measured values.
    effects : sequence of (Effect, Features)
        The effects switched on, with their features for the model's poses.
    theta0, eta0 : ndarray, optional
        Start; zeros and the parameters' :attr:`EffectParam.start_value` by default.
    max_iter : int
    xtol : float
        Convergence when the largest Gauss-Newton step is below this many
        prior sigmas; the fit also stops when a step predicts a decrease of
        the cost below :data:`MAP_DTOL` (:func:`bayescal.iteration.gauss_newton`,
        with :data:`MAP_STEP_CONTROL`).  ``success`` is False when no step
        lowers the cost from a point that is not converged, or after
        ``max_iter`` iterations.
    coarse : bool
        From :data:`COARSE_START_POSES` poses on, start from a fit of every
        :data:`COARSE_STRIDE`-th row (:func:`_coarse_start`); False starts
        from ``theta0, eta0`` themselves, for a start already nearer the
        optimum than the coarse fit's (a fit of nearly the same rows).
    keep_system : bool
        Keep the whitened system at the fit in :attr:`EffectFit.system` (for
        :func:`linear_fold_residuals`, which then need not evaluate it again).

    Returns
    -------
    EffectFit

    Notes
    -----
    The physical lower bounds :attr:`EffectParam.lower` are deliberately not
    enforced here.  A parameter fitted significantly below its bound (a
    negative compliance, a screw that shrinks when warmed) says that the
    effect's shape fits some other mismatch; the diagnosis rejects such a fit
    (:meth:`Effect.nonphysical`, docs/diagnose.md "Physical signs").  Clamped
    at the bound the test could never fire, and the effect's other
    parameters would pass as a detection of an effect that is not there
    (tests/physics/test_thermal_growth.py, tests/diagnose/test_diagnose.py::
    test_negative_compliance_is_not_reported_as_a_detection).  Values within
    a few sigma below the bound are noise and reported as fitted (unbiased).
    """
    joint = _Joint.of(model, effects)
    P, K = joint.P, joint.K
    theta = np.zeros(P) if theta0 is None else np.asarray(theta0, float).copy()
    eta = np.array([p.start_value for p in joint.params]) if eta0 is None else np.asarray(eta0, float).copy()
    start = joint.state(theta, eta, None)
    if coarse and K and model.n_poses >= COARSE_START_POSES and _curved(joint, theta, eta, start):
        theta, eta = _coarse_start(model, effects, theta, eta, max_iter, xtol)
        start = joint.state(theta, eta, None)
    out = gauss_newton(np.concatenate([theta, eta]), start, joint.at, joint.propose,
                       control=MAP_STEP_CONTROL, scale=joint.scale, max_iter=max_iter, xtol=xtol, dtol=MAP_DTOL,
                       unit="prior sigmas", failures=(KinematicsError,))
    state = out.state
    theta, eta = out.x[:P], out.x[P:]
    A = state.system()
    AtA = _gram(A)
    s = np.sqrt(np.clip(np.linalg.eigvalsh(AtA), 0, None))[::-1]
    full = np.linalg.inv(AtA + np.eye(P + K)) * np.outer(joint.scale, joint.scale)
    cov = full[P:, P:]
    names = tuple((eff.name, sl) for (eff, _), sl in zip(effects, joint.slices))
    return EffectFit(
        theta=theta, eta=eta, params=joint.params, effect_slices=names, cov_eta=cov, residual=state.r,
        chi2=state.chi2, prior_term=state.prior, singular_values=s, n_rows=state.rw.size, success=out.success,
        message=out.message, iterations=out.iterations, covariance=full,
        system=(A, state.rw) if keep_system else None,
    )


def _curved(joint: "_Joint", theta: NDArray, eta: NDArray, start: tuple) -> bool:
    """Whether the full Gauss-Newton step from ``start`` (``joint.state`` at ``theta, eta``) raises the cost.

    The sign of a curved valley (:data:`COARSE_START_POSES`): where the first full step lowers the cost the
    fit is left to Gauss-Newton from its own start.  The system computed here stays in the start's state for
    the fit's first step.
    """
    cost, state = start
    x = np.concatenate([theta, eta])
    try:
        prop = joint.propose(x, state)
        if prop.predicted < MAP_DTOL:
            return False
        trial, _ = joint.at(x + prop.step, state)
    except (KinematicsError, np.linalg.LinAlgError):
        return True
    return not trial <= cost * (1.0 + ROUNDOFF)


def _coarse_start(model: MeasurementModel, effects: Sequence[tuple[Effect, Features]], theta: NDArray, eta: NDArray,
                  max_iter: int, xtol: float) -> tuple[NDArray, NDArray]:
    """Where :func:`fit_map` of a large recording starts: the fit of every :data:`COARSE_STRIDE`-th row from ``(theta, eta)``.

    That fit starts from a fit of a quarter of its rows in turn while it has
    :data:`COARSE_START_POSES` rows or more.  The start from it is only a
    start: the full fit iterates to the same tests.  Its answer differs by
    the convergence tolerance where the cost has one minimum; where it has
    several, the full fit may settle in the one the coarse fit found.  The
    start is given back unchanged when a pose of the coarse fit does not
    assemble (the full fit then reports it its own way).
    """
    rows = np.arange(0, model.n_poses, COARSE_STRIDE)
    poses = model.poses_of(rows)
    try:
        fit = fit_map(model.subset(rows), [(e, f.subset(poses)) for e, f in effects], theta0=theta, eta0=eta,
                      max_iter=max_iter, xtol=xtol)
    except KinematicsError:
        return theta, eta
    if not (np.all(np.isfinite(fit.theta)) and np.all(np.isfinite(fit.eta))):
        return theta, eta
    return fit.theta, fit.eta


def joint_system(model: MeasurementModel, effects: Sequence[tuple[Effect, Features]], theta: NDArray,
                 eta: NDArray) -> tuple[NDArray, NDArray]:
    """The linear system of :func:`fit_map` at ``(theta, eta)``: what a test of the joint fit's poses needs.

    Parameters
    ----------
    model : MeasurementModel
        The recording with the noise the system is whitened by.
    effects : sequence of (Effect, Features)
    theta : ndarray, shape (P,)
        Geometric errors (mm, rad).
    eta : ndarray, shape (K,)
        The effects' parameters (their units).

    Returns
    -------
    A : ndarray, shape (n_poses * dof, P + K)
        The whitened Jacobian in the prior-scaled coordinates (per prior std).
    r : ndarray, shape (n_poses * dof,)
        The whitened residual (dimensionless).
    """
    joint = _Joint.of(model, effects)
    theta, eta = np.asarray(theta, dtype=float), np.asarray(eta, dtype=float)
    sub, pred, _, rw, _, _ = joint.evaluate(theta, eta, None)
    return joint.system(sub, pred, theta, eta), rw


def linear_fold_residuals(model: MeasurementModel, effects: Sequence[tuple[Effect, Features]], theta: NDArray,
                          eta: NDArray, folds: Sequence[NDArray], system: tuple | None = None) -> list[NDArray]:
    """Held-out residuals of a K-fold cross-validation, each fold's fit one Gauss-Newton step from the full fit.

    At the full fit ``(theta, eta)`` (the MAP of every row) the whitened
    system ``A``, ``r`` is evaluated once; a fold's fit on the other rows is
    the step ``(A_t^T A_t + I)^-1 (A_t^T r_t + mu - phi)`` (``t`` the
    training rows: the full Gram matrix less the fold's), and its held-out
    residual ``r_f - A_f step``.  This is the first iteration
    :func:`fit_map` takes on the fold from the same start, without the
    iterations after it and with the held-out rows linearised: the
    difference is second order in the step, which is a fraction of a
    standard deviation when a fold leaves out a fifth of many poses.

    Parameters
    ----------
    model : MeasurementModel
    effects : sequence of (Effect, Features)
        Features for the model's poses (all of them).
    theta, eta : ndarray
        The full fit.
    folds : sequence of ndarray of int
        Held-out rows of each fold.
    system : (ndarray, ndarray), optional
        The whitened system ``(A, rw)`` at ``(theta, eta)`` when the caller
        has it (:attr:`EffectFit.system` of the full fit); evaluated here
        otherwise (the two differ by the kinematics' round-off: the fit's
        poses were solved from its last iterate's, these from scratch).

    Returns
    -------
    list of ndarray, shape (len(fold), dof)
        ``y - h`` of each fold's held-out rows after its fit, mm and rad.
    """
    joint = _Joint.of(model, effects)
    theta, eta = np.asarray(theta, float), np.asarray(eta, float)
    if system is None:
        sub, pred, _, rw, _, _ = joint.evaluate(theta, eta, None)
        A = joint.system(sub, pred, theta, eta)
    else:
        A, rw = system
    dof = model.dof
    prior = joint.mu - np.concatenate([theta, eta]) / joint.scale
    G, g, eye = _gram(A), A.T @ rw, np.eye(A.shape[1])
    out = []
    for test in folds:
        test = np.asarray(test, dtype=int)
        rows = (test[:, None] * dof + np.arange(dof)[None, :]).reshape(-1)
        At, rt = A[rows], rw[rows]
        step = np.linalg.solve(G - _gram(At) + eye, g - At.T @ rt + prior)
        out.append((rt - At @ step).reshape(-1, dof) * model.row_sigma[test])
    return out
