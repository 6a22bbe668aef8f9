"""A machine with nuisance parameters appended to its layout (ballbar pivots, body sensors' mountings).

What identification reads (``layout``, ``tolerance``, ``n_params``,
``to_toml``) covers the machine's parameters and the appended ones, last;
the kinematics are the machine's, which the appended parameters do not move
(their columns of the tool Jacobian are zero; the rows that see them are
the view's own, e.g. a ballbar's radius or a sensor's tilt).
:attr:`geometry_part` leaves them out and the calibrated machine file does
not hold them.  Everything else is forwarded to the machine.
"""

from __future__ import annotations

import dataclasses
from abc import ABC, abstractmethod
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..errors import InputError
from ..params import ParamLayout, ParamSpec
from .base import Machine, ToolPoses

__all__ = ["AppendedParameters"]


@dataclass(frozen=True, eq=False)
class AppendedParameters(ABC):
    """``base`` with the parameters :meth:`appended` gives after its own (subclasses say which)."""

    base: Machine

    @abstractmethod
    def appended(self) -> tuple[tuple[ParamSpec, ...], NDArray]:
        """The appended parameters (names and units) and their one-sigma tolerances (in those units)."""

    def __post_init__(self) -> None:
        specs, tol = self.appended()
        object.__setattr__(self, "layout", self.base.layout + ParamLayout(tuple(specs)))
        object.__setattr__(self, "tolerance", np.concatenate([self.base.tolerance, np.asarray(tol, dtype=float)]))

    def __getattr__(self, name):
        # everything else (name, kind, noise, q_limits, source, effects, ...) is the machine's
        if name == "base" or name.startswith("__"):
            raise AttributeError(name)  # not set yet (copy, pickle): no recursion
        return getattr(self.base, name)

    @property
    def n_params(self) -> int:
        return len(self.layout)

    # the instrument frame's layer (Machine.framed ...): a view is inside any frame, never around one
    framed = False
    n_frame = 0

    @property
    def inside(self):
        return self

    def rewrapped(self, inner):
        return inner

    def base_machine(self):
        """The view itself: its appended parameters belong to the measurement (a subclass may strip them)."""
        return self

    @property
    def n_base(self) -> int:
        """Parameters of the machine (before the appended ones)."""
        return self.base.n_params

    def for_poses(self, idx):
        """This view over the machine bound to the poses ``idx`` (stations: :meth:`Machine.for_poses`)."""
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
        """The machine's tool poses (the appended parameters do not move the tool)."""
        return self.base.forward(q, self.machine_theta(theta), guess=guess)

    def tool_jacobian(self, q, theta, poses) -> NDArray:
        """The machine's tool Jacobian with zero columns for the appended parameters, shape (n, 6, P + k)."""
        J = self.base.tool_jacobian(q, self.machine_theta(theta), poses)
        return np.concatenate([J, np.zeros(J.shape[:2] + (self.n_params - self.n_base,))], axis=2)

    def actuator_jacobian(self, q, theta, poses) -> NDArray:
        """The machine's ``d pose / d q`` (the appended parameters do not enter it)."""
        return self.base.actuator_jacobian(q, self.machine_theta(theta), poses)

    def weight_bodies(self, q, theta, poses):
        return self.base.weight_bodies(q, self.machine_theta(theta), poses)

    @property
    def geometry_part(self) -> tuple[Machine, NDArray]:
        """The machine whose geometry the parameters describe and their indices (the appended ones are nuisance)."""
        return self.base.geometry_part

    def to_toml(self, theta: ArrayLike | None = None) -> str:
        """The calibrated machine file (the appended parameters are not part of the machine)."""
        return self.base.to_toml(self.machine_theta(self.check_theta(theta)))
