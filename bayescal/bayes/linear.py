"""A measurement model linearised at a reference geometry: ``h(theta) ~ h(theta_ref) + J (theta - theta_ref)``.

It has the interface of :class:`bayescal.measurement.MeasurementModel`
(``predict`` with stacked theta, ``jacobian``, ``subset``, ``residual``,
``sigma``), so every filter and sampler runs on it unchanged.  Uses:

* exactness tests: on a linear model the Kalman filter with zero process
  noise equals the batch MAP solution, and the posterior is Gaussian in
  closed form, so MCMC can be checked against it;
* a fast surrogate for MCMC when the posterior is much narrower than the
  scale on which ``h`` bends (check with :func:`linearisation_error`).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..errors import InputError
from ..machines.base import Machine, ToolPoses
from ..measurement import MeasurementModel, Prediction

__all__ = ["LinearisedModel", "linearise", "linearisation_error"]


@dataclass(frozen=True, eq=False)
class LinearisedModel:
    """``y = y0 + J (theta - theta_ref)`` for a fixed list of poses.

    Attributes
    ----------
    machine : Machine
        Supplies the layout, tolerances and instrument noise.
    q : ndarray, shape (n_poses, n_actuators)
    dof : int
    y0 : ndarray, shape (n_poses, dof)
        ``h(theta_ref)``.
    J : ndarray, shape (n_poses, dof, P)
    theta_ref : ndarray, shape (P,)
    y_measured : ndarray, shape (n_poses, dof) or None
    """

    machine: Machine
    q: NDArray
    dof: int
    y0: NDArray
    J: NDArray
    theta_ref: NDArray
    y_measured: NDArray | None = None
    pose_sigma: NDArray | None = None
    noise_sigma: NDArray | None = None  # the linearised model's sigma when it is not MeasurementModel's (constraint rows)
    sensors: object | None = None  # a MeasurementModel's body sensors (their tilt rows follow the tool's)

    # the parts of MeasurementModel that only use rows, sigma and dof
    tool_dof = MeasurementModel.tool_dof
    @property
    def sigma(self) -> NDArray:
        return self.noise_sigma if self.noise_sigma is not None else MeasurementModel.sigma.fget(self)

    row_sigma = MeasurementModel.row_sigma
    residual = MeasurementModel.residual
    errors = MeasurementModel.errors
    rms = MeasurementModel.rms

    @property
    def n_poses(self) -> int:
        return self.q.shape[0]

    @property
    def n_params(self) -> int:
        return self.J.shape[2]

    @property
    def guess(self) -> None:
        return None

    #: The model contract's start (None: the nominal, as for the model linearised), tool-pose
    #: perturbation (None: the linearisation holds it in ``y0``) and auxiliary channels (none: effects
    #: are not evaluated on a linearisation).
    theta_start = None
    pose_offset = None
    aux = None

    # one solved pose per row, as MeasurementModel
    pose_q = MeasurementModel.pose_q
    pose_row = MeasurementModel.pose_row
    pose_order = MeasurementModel.pose_order
    poses_of = MeasurementModel.poses_of
    region = MeasurementModel.region
    effect_inputs = MeasurementModel.effect_inputs
    answer_extras = MeasurementModel.answer_extras

    @property
    def calibrated_machine(self) -> Machine:
        """The machine a calibration of this model reports and writes: :attr:`machine`."""
        return self.machine

    def with_pose_sigma(self, pose_sigma: NDArray | None) -> "LinearisedModel":
        """The same model with other per-pose noise (None: the machine's)."""
        return replace(self, pose_sigma=pose_sigma)

    def with_pose_q(self, pose_q: NDArray, *, keep_guess: bool = True) -> "LinearisedModel":
        """Refused: the rows are linear in ``theta`` at fixed poses and cannot follow moved actuators."""
        raise InputError("a linearised model cannot move its poses (an effect's q + dq); linearise the model at "
                         "the moved poses instead")

    def with_pose_offset(self, pose_offset: NDArray | None) -> "LinearisedModel":
        """Itself for None; any other perturbation is refused, as :meth:`with_pose_q`."""
        if pose_offset is None:
            return self
        raise InputError("a linearised model cannot perturb its tool poses; linearise the perturbed model instead")

    def rows_jacobian(self, Jt: NDArray, prediction: Prediction) -> NDArray:
        """:meth:`MeasurementModel.rows_jacobian` for a 3- or 6-DOF tool (a tool axis's tangent is not kept)."""
        if self.tool_dof == 5:
            raise InputError("a linearised 5-DOF model keeps no tool axis to differentiate; use the model itself")
        return MeasurementModel.rows_jacobian(self, Jt, prediction)

    def without_sensors(self) -> "LinearisedModel":
        """The tool's rows only (the body sensors' tilt rows left out), the parameters unchanged."""
        if self.sensors is None:
            return self
        d = self.tool_dof
        cut = lambda a: None if a is None else a[..., :d]  # noqa: E731  (rows of (n, dof) and of (dof,))
        return replace(self, dof=d, y0=self.y0[:, :d], J=self.J[:, :d], y_measured=cut(self.y_measured),
                       pose_sigma=cut(self.pose_sigma), noise_sigma=cut(self.noise_sigma), sensors=None)

    def predict(self, theta: ArrayLike | None = None, *, guess: ToolPoses | None = None) -> Prediction:
        """Rows ``y0 + J (theta - theta_ref)``; theta (P,), (n_poses, P) or stacked (k * n_poses, P)."""
        theta = np.zeros(self.n_params) if theta is None else np.asarray(theta, dtype=float)
        d = theta - self.theta_ref
        n = self.n_poses
        if d.ndim == 1:
            y = self.y0 + self.J @ d
        else:
            if d.shape[0] % n:
                raise InputError(f"theta: {d.shape[0]} rows is not a multiple of {n} poses")
            k = d.shape[0] // n
            y = (self.y0[None] + np.einsum("ndp,knp->knd", self.J, d.reshape(k, n, -1))).reshape(k * n, self.dof)
        m = y.shape[0]
        poses = ToolPoses(y[:, :3].copy(), np.broadcast_to(np.eye(3), (m, 3, 3)).copy(), np.ones(m, bool), ("",) * m)
        return Prediction(y=y, poses=poses)

    def jacobian(self, theta: ArrayLike | None, prediction: Prediction) -> NDArray:
        """The constant ``J``, shape (n_poses, dof, P)."""
        return self.J

    def subset(self, idx) -> "LinearisedModel":
        idx = np.asarray(idx)
        return LinearisedModel(
            self.machine, self.q[idx], self.dof, self.y0[idx], self.J[idx], self.theta_ref,
            None if self.y_measured is None else self.y_measured[idx],
            None if self.pose_sigma is None else self.pose_sigma[idx], self.noise_sigma,
            None if self.sensors is None else self.sensors.subset(idx),
        )

    def with_measured(self, y: ArrayLike) -> "LinearisedModel":
        """The same model with other measured rows (e.g. simulated linear-Gaussian data)."""
        y = np.asarray(y, dtype=float)
        if y.shape != self.y0.shape:
            raise InputError(f"y: expected shape {self.y0.shape}, got {y.shape}")
        return LinearisedModel(self.machine, self.q, self.dof, self.y0, self.J, self.theta_ref, y, self.pose_sigma,
                               self.noise_sigma, self.sensors)


def linearise(model, theta_ref: ArrayLike | None = None) -> LinearisedModel:
    """Linearise ``model`` (any measurement model) at ``theta_ref`` (zeros: nominal)."""
    ref = np.zeros(model.n_params) if theta_ref is None else np.asarray(theta_ref, dtype=float).reshape(model.n_params)
    pred = model.predict(ref)
    if not pred.success.all():
        i = int(np.flatnonzero(~pred.success)[0])
        raise InputError(f"pose {i + 1}: cannot be solved at the linearisation point")
    return LinearisedModel(
        model.machine, np.asarray(model.q), model.dof, pred.y, model.jacobian(ref, pred), ref, model.y_measured,
        model.pose_sigma,
        None if isinstance(model, MeasurementModel) else np.asarray(model.sigma),
        model.sensors,
    )


def linearisation_error(model, theta_ref: NDArray, samples: NDArray) -> float:
    """Largest ``|h(theta) - h_lin(theta)| / sigma`` over ``samples`` (n, P) and all rows.

    Well below 1 means the linearised model is as good as the exact one
    for the posterior these samples come from.
    """
    lin = linearise(model, theta_ref)
    samples = np.atleast_2d(samples)
    stacked = np.repeat(samples, model.n_poses, axis=0)
    exact = model.predict(stacked).y
    approx = lin.predict(stacked).y
    return float(np.max(np.abs(exact - approx) / np.tile(model.row_sigma, (samples.shape[0], 1))))
