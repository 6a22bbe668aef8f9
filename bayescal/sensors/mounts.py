"""A machine's parameter layout extended by its body sensors' mountings (and the level of up).

The measurement model's machine when a recording has body sensors: what
identification reads (``layout``, ``tolerance``, ``n_params``, ``to_toml``)
covers the geometry and the sensors' parameters, appended last; the
kinematics are the machine's, which the mountings do not move.  Like the
ballbar pivots (:class:`bayescal.constraints.model.PivotAugmented`), the
sensors' parameters are nuisance: :attr:`geometry_part` leaves them out and
the calibrated machine file does not hold them.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..machines.appended import AppendedParameters
from ..machines.base import Machine
from ..params import ParamSpec

__all__ = ["SensorMounts", "sensor_base"]


@dataclass(frozen=True, eq=False)
class SensorMounts(AppendedParameters):
    """``base`` (a machine, not an instrument frame: that wraps this view) with ``names`` (rad) appended to its parameters.

    ``tolerances``: one-sigma of each appended parameter (rad): the machine
    file's ``[measurement] sensor_mount`` for tilts, ``sensor_turn`` for a
    sensor's turn about its reading.
    """

    names: tuple[str, ...] = ()
    tolerances: tuple[float, ...] = ()

    def base_machine(self) -> Machine:
        """The machine under the mountings: a sensor's mounting is the measurement's, not the machine's."""
        return self.base.base_machine()

    def without_sensor_mounts(self) -> Machine:
        return self.base

    def appended(self):
        return tuple(ParamSpec(n, "rad", "sensor_mount") for n in self.names), np.asarray(self.tolerances, dtype=float)


def sensor_base(machine) -> Machine:
    """The machine under a :class:`SensorMounts` view (the machine itself otherwise)."""
    return machine.without_sensor_mounts()
