"""What a machine view is: a machine seen through a measurement, with parameters of the measurement's own.

A view wraps a machine (:attr:`MachineView.wrapped`) and is a :class:`Machine`
itself, so every consumer takes it unchanged: an instrument frame
(:class:`bayescal.machines.framed.InstrumentFrame`), nuisance parameters
appended after the machine's (:class:`bayescal.machines.appended.AppendedParameters`:
ballbar pivots, body sensors' mountings), effect parameters fitted with the
geometry (:class:`bayescal.effects.joint_model.EffectAugmented`).

Every member of the :class:`Machine` interface is decided here or in the
view, by name: the members a view does not change (:data:`FORWARDED`: the
machine's name, noise, actuators, stored effects, ...) are its machine's,
read through one :class:`Forwarded` descriptor each; every other member
(the layout, tolerances, kinematics, Jacobians, the instrument frame's layer)
is the view's own.  Nothing else is forwarded: a kind-specific member (a
serial chain's bodies, a redundant machine's inverse kinematics) is asked of
the machine under the views (:attr:`Machine.inside`,
:attr:`Machine.geometry_part`), or belongs in the interface.
``tests/machines/test_view.py`` checks, for every view over every kind, that
each interface member is forwarded with the machine's value or is the view's
own, and that an unknown attribute raises :class:`AttributeError`.
"""

from __future__ import annotations

from abc import abstractmethod

from ..errors import MachineFileError
from .base import Machine

__all__ = ["MachineView", "Forwarded", "FORWARDED"]


class Forwarded:
    """A member of the :class:`Machine` interface that a view reads from the machine it wraps (read-only)."""

    def __set_name__(self, owner, name: str) -> None:
        self.name = name
        self.__doc__ = f"The wrapped machine's :attr:`~bayescal.machines.base.Machine.{name}`."

    def __get__(self, view, owner=None):
        if view is None:
            return self
        return getattr(view.wrapped, self.name)

    def __set__(self, view, value) -> None:
        raise AttributeError(f"{self.name} is the wrapped machine's; set it there")


class MachineView(Machine):
    """A :class:`Machine` that wraps another: :data:`FORWARDED` is the machine's, the rest the view's own.

    Subclasses name their machine (:attr:`wrapped`) and implement the
    members that the view changes: ``layout``, ``tolerance``,
    :meth:`forward`, :meth:`tool_jacobian`, :meth:`to_toml`, and the rest of
    the interface that is not forwarded (the tests check that none is left
    to :class:`Machine`'s defaults, which describe a plain machine).
    """

    kind = Forwarded()  # a view's kind is its machine's: not a kind of its own
    name = Forwarded()
    source = Forwarded()
    noise = Forwarded()
    q_limits = Forwarded()
    n_actuators = Forwarded()
    n_dof = Forwarded()
    actuator_units = Forwarded()
    actuator_unit_info = Forwarded()
    actuator_box_reachable = Forwarded()
    #: stored effects act on the actuators, whatever measures the tool
    effects = Forwarded()
    #: a calibration record and a discrepancy describe the machine, whatever measures it
    calibration = Forwarded()
    discrepancy = Forwarded()
    weight_body_names = Forwarded()
    sensor_bodies = Forwarded()
    body_inertials = Forwarded()
    check_q = Forwarded()
    home_q = Forwarded()
    sample_q = Forwarded()

    @property
    @abstractmethod
    def wrapped(self) -> Machine:
        """The machine this view wraps (itself possibly a view)."""

    def without_sensor_mounts(self) -> Machine:
        """This view itself: only a body-sensor mountings view unwraps (its own override)."""
        return self

    @property
    def n_params(self) -> int:
        """Parameters of the view: its layout's (the machine's and the view's own)."""
        return len(self.layout)

    #: the machines' own check, against the view's parameter count
    check_theta = Machine.check_theta

    def tool_jacobian_columns(self, q, theta, poses, columns):
        """Columns of the view's own :meth:`tool_jacobian` (a view that can do better overrides it)."""
        return self.tool_jacobian(q, theta, poses)[:, :, columns]
    #: a view's parameters are not a serial chain's (ask the machine under it, :attr:`geometry_part`), and a
    #: view is written whole by its ``to_toml`` (a framed hybrid's modules are asked of :attr:`inside`)
    serial_chain = None
    written_modules = ()

    @classmethod
    def from_toml(cls, table, path: str) -> Machine:
        raise MachineFileError(path, "kind", "a machine view is not read from a machine file; read the machine "
                               "(bayescal.machines.files.load_machine) and wrap it")


#: Members of the :class:`Machine` interface that no view changes: every view reads them from its machine
#: (a view may forward more of them: :class:`Forwarded` in its own class).
FORWARDED = tuple(n for n, v in vars(MachineView).items() if isinstance(v, Forwarded))
