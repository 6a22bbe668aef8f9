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

from dataclasses import dataclass

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

    #: The model contract's start (None: the nominal, as for the model linearised) and tool-pose
    #: perturbation (None: the linearisation holds it in ``y0``).
    theta_start = None
    pose_offset = None

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
