"""A machine with nuisance parameters appended to its layout (ballbar pivots, body sensors' mountings).

What identification reads (``layout``, ``tolerance``, ``n_params``,
``to_toml``) covers the machine's parameters and the appended ones, last;
the kinematics are the machine's, which the appended parameters do not move
(their columns of the tool Jacobian are zero; the rows that see them are
the view's own, e.g. a ballbar's radius or a sensor's tilt).
:attr:`geometry_part` leaves them out and the calibrated machine file does
not hold them.  The members no view changes are the machine's
(:data:`bayescal.machines.view.FORWARDED`); every other member of the
:class:`~bayescal.machines.base.Machine` interface is defined here.
"""

from __future__ import annotations

import dataclasses
from abc import abstractmethod
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..params import ParamLayout, ParamSpec
from .base import Machine, ToolPoses
from .view import Forwarded, MachineView

__all__ = ["AppendedParameters"]


@dataclass(frozen=True, eq=False)
class AppendedParameters(MachineView):
    """``base`` with the parameters :meth:`appended` gives after its own (subclasses say which)."""

    base: Machine

    @abstractmethod
    def appended(self) -> tuple[tuple[ParamSpec, ...], NDArray]:
        """The appended parameters (names and units) and their one-sigma tolerances (in those units)."""

    def __post_init__(self) -> None:
        specs, tol = self.appended()
        object.__setattr__(self, "layout", self.base.layout + ParamLayout(tuple(specs)))
        object.__setattr__(self, "tolerance", np.concatenate([self.base.tolerance, np.asarray(tol, dtype=float)]))

    @property
    def wrapped(self) -> Machine:
        return self.base

    #: the machine's start from a measurement: the appended parameters do not move the tool
    guess_from_measurement = Forwarded()

    @property
    def prior_mean(self):
        """The machine's prior mean, zero for the appended parameters (None when the machine's is zero)."""
        mean = self.base.prior_mean
        return None if mean is None else np.concatenate([mean, np.zeros(self.n_params - self.n_base)])

    @property
    def prior_lower(self):
        """The machine's lower bounds, none for the appended parameters (None when it has none)."""
        low = self.base.prior_lower
        return None if low is None else np.concatenate([low, np.full(self.n_params - self.n_base, -np.inf)])

    # A view is the measurement's: the machine given other effects, noise or a calibration record is the
    # machine's own copy, without the view (the next model built from a recording makes its view anew;
    # a calibrated machine file does not hold the appended parameters).
    def with_effects(self, effects) -> Machine:
        """The machine (without this view) carrying ``effects``."""
        return self.base.with_effects(effects)

    def with_noise(self, noise) -> Machine:
        """The machine (without this view) with the instrument noise ``noise``."""
        return self.base.with_noise(noise)

    def with_calibration(self, calibration=None, discrepancy=None) -> Machine:
        """The machine (without this view) carrying a calibration record and a model discrepancy."""
        return self.base.with_calibration(calibration, discrepancy)

    # the instrument frame's layer (Machine.framed ...): a view is inside any frame, never around one
    framed = False
    n_frame = 0
    instrument_frame = None
    #: the machine's redundant kinematics know its parameters, not the appended ones: none for the view
    redundancy = None

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

    def compatible_q(self, q, theta=None) -> NDArray:
        """The machine's :meth:`Machine.compatible_q` at its part of ``theta``."""
        return self.base.compatible_q(q, self.machine_theta(theta))

    def node_actuators(self, q, theta=None, aux=None):
        """The machine's :meth:`Machine.node_actuators`, zero columns for the appended parameters."""
        q_act, J = self.base.node_actuators(q, self.machine_theta(theta), aux)
        if J is None:
            return q_act, None
        return q_act, np.concatenate([J, np.zeros(J.shape[:2] + (self.n_params - self.n_base,))], axis=2)

    def node_tool_offset(self, q, theta=None, aux=None):
        """The machine's :meth:`Machine.node_tool_offset` (the appended parameters do not move the tool)."""
        return self.base.node_tool_offset(q, self.machine_theta(theta), aux)

    @property
    def geometry_part(self) -> tuple[Machine, NDArray]:
        """The machine whose geometry the parameters describe and their indices (the appended ones are nuisance)."""
        return self.base.geometry_part

    def to_toml(self, theta: ArrayLike | None = None) -> str:
        """The calibrated machine file (the appended parameters are not part of the machine)."""
        return self.base.to_toml(self.machine_theta(self.check_theta(theta)))
