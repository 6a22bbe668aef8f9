"""A machine's parameter layout extended by its body sensors' mountings (and the level of up).

The measurement model's machine when a recording has body sensors: what
identification reads (``layout``, ``tolerance``, ``n_params``, ``to_toml``)
covers the geometry and the sensors' parameters, appended last; the
kinematics are the machine's, which the mountings do not move.  Like the
ballbar pivots (:class:`bayescal.constraint_model.PivotAugmented`), the
sensors' parameters are nuisance: :attr:`geometry_part` leaves them out and
the calibrated machine file does not hold them.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..errors import InputError
from ..machines.base import Machine, ToolPoses
from ..params import ParamLayout, ParamSpec

__all__ = ["SensorMounts", "sensor_base"]


@dataclass(frozen=True, eq=False)
class SensorMounts:
    """``base`` (a machine, not an instrument frame: that wraps this view) with ``names`` (rad) appended to its parameters.

    ``tolerances``: one-sigma of each appended parameter (rad): the machine
    file's ``[measurement] sensor_mount`` for tilts, ``sensor_turn`` for a
    sensor's turn about its reading.
    """

    base: Machine
    names: tuple[str, ...]
    tolerances: tuple[float, ...]

    def __post_init__(self) -> None:
        specs = [ParamSpec(n, "rad", "sensor_mount") for n in self.names]
        object.__setattr__(self, "layout", self.base.layout + ParamLayout(tuple(specs)))
        tol = np.concatenate([self.base.tolerance, np.asarray(self.tolerances, dtype=float)])
        object.__setattr__(self, "tolerance", tol)

    def __getattr__(self, name):
        # everything else (name, kind, noise, q_limits, source, effects, ...) is the machine's
        if name == "base" or name.startswith("__"):
            raise AttributeError(name)  # not set yet (copy, pickle): no recursion
        return getattr(self.base, name)

    @property
    def n_params(self) -> int:
        return len(self.layout)

    @property
    def n_base(self) -> int:
        """Parameters of the machine (before the sensors')."""
        return self.base.n_params

    def for_poses(self, idx) -> "SensorMounts":
        inner = self.base.for_poses(idx)
        return self if inner is self.base else dataclasses.replace(self, base=inner)

    def machine_theta(self, theta):
        """The machine's part of ``theta`` (None stays None)."""
        return None if theta is None else np.asarray(theta, dtype=float)[..., : self.n_base]

    def measurement_rotation(self, q, theta):
        return self.base.measurement_rotation(q, self.machine_theta(theta))

    def check_theta(self, theta, n_poses=None) -> NDArray:
        if theta is None:
            return np.zeros(self.n_params)
        theta = np.asarray(theta, dtype=float)
        if theta.ndim not in (1, 2) or theta.shape[-1] != self.n_params:
            raise InputError(f"theta: expected shape ({self.n_params},) or (n, {self.n_params}), got {theta.shape}")
        return theta

    def forward(self, q, theta=None, *, guess=None) -> ToolPoses:
        """The machine's tool poses (a sensor's mounting does not move the tool)."""
        return self.base.forward(q, self.machine_theta(theta), guess=guess)

    def tool_jacobian(self, q, theta, poses) -> NDArray:
        """The machine's tool Jacobian with zero columns for the sensors' parameters, shape (n, 6, P + k)."""
        J = self.base.tool_jacobian(q, self.machine_theta(theta), poses)
        return np.concatenate([J, np.zeros(J.shape[:2] + (self.n_params - self.n_base,))], axis=2)

    def actuator_jacobian(self, q, theta, poses) -> NDArray:
        return self.base.actuator_jacobian(q, self.machine_theta(theta), poses)

    def weight_bodies(self, q, theta, poses):
        return self.base.weight_bodies(q, self.machine_theta(theta), poses)

    @property
    def geometry_part(self) -> tuple[Machine, NDArray]:
        """The machine whose geometry the parameters describe and their indices (the sensors' are nuisance)."""
        return self.base.geometry_part

    def to_toml(self, theta: ArrayLike | None = None) -> str:
        """The calibrated machine file (the sensors' mountings are not part of the machine)."""
        return self.base.to_toml(self.machine_theta(self.check_theta(theta)))


def sensor_base(machine) -> Machine:
    """The machine under a :class:`SensorMounts` view (the machine itself otherwise)."""
    return machine.base if isinstance(machine, SensorMounts) else machine
