"""What every machine kind provides: the interface all consumers rely on.

A machine is immutable.  Its geometry is the nominal geometry plus a
parameter vector ``theta`` of geometric errors (actual minus nominal), laid
out by :attr:`Machine.layout`.  ``theta`` may be one vector (shape ``(P,)``)
or one per pose (shape ``(n_poses, P)``): per-pose geometry is how physical
effects (thermal growth, ...) and vectorised samplers (one pose block per
walker) use the same kinematics.
"""

from __future__ import annotations

import dataclasses
from abc import ABC, abstractmethod
from dataclasses import dataclass
from operator import itemgetter
from typing import ClassVar, Protocol

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..errors import InputError, MachineFileError
from ..geometry import so3_exp, so3_log
from ..io.machine_file import toml_key
from ..params import ParamLayout
from .tolerance import ToleranceKeyError

__all__ = ["Machine", "RedundantKinematics", "ToolPoses", "MeasurementNoise", "map_state", "ActuatorUnit", "ACTUATOR_UNITS", "WeightBodies", "BodyInertials", "offset_poses", "KINDS", "machine_from_table"]


@dataclass(frozen=True)
class ActuatorUnit:
    """How small changes of one actuator's position are named, scaled and described (prismatic or revolute).

    Effects state their parameters through this (``Machine.actuator_unit_info``),
    never through the machine's kind, so a new kind with revolute drives gets
    revolute units everywhere by saying ``"rad"`` in :attr:`Machine.actuator_units`.

    Attributes
    ----------
    unit : str
        Unit of ``q``: ``"mm"`` or ``"rad"``.
    small : str
        Unit of small changes of ``q`` (effect amplitudes, dead bands): ``"um"`` or ``"urad"``.
    small_to_q : float
        ``q`` units per ``small`` unit: 1e-3 (um -> mm) or 1e-6 (urad -> rad).
    per_um : float
        Prior widths: an effect whose prior is ``w`` um on a slider gets
        ``per_um * w`` in ``small`` on this actuator.  1 for mm; 10 for rad
        (the angle that moves a point 100 mm from the joint axis by ``w`` um:
        a 30 um backlash prior becomes 300 urad, about 1 arcmin, the size of a
        gear train's lost motion).
    drive : str
        What carries the position, for messages: ``"screw or scale"`` or ``"gear or encoder"``.
    strain : str
        Unit of a relative change of ``q``'s own scale (1e-6): ``"um/m"`` or ``"urad/rad"``.
    load : str
        Unit of the generalised force on ``q`` (what does work ``load dq``): a
        force ``"N"`` on a slider, a torque ``"N m"`` on a revolute joint.
    load_scale : float
        ``load`` units per N mm per ``q`` unit: a force ``F`` (N) whose point
        moves by ``dx/dq`` (mm per ``q`` unit) does ``F . dx/dq`` N mm per ``q``
        unit, which is 1 N on a slider (mm/mm) and 1e-3 N m on a joint (mm/rad).
    compliance : str
        Unit of a drive's compliance, ``small`` per ``load``: ``"um/N"`` or ``"urad/(N m)"``.
    weight : str
        Unit of a compliance times a weight in N: ``"um"``, or ``"urad/m"`` on a
        joint (its deflection per metre of the weight's lever arm).
    """

    unit: str
    small: str
    small_to_q: float
    per_um: float
    drive: str
    strain: str
    load: str = "N"
    load_scale: float = 1.0
    compliance: str = "um/N"
    weight: str = "um"


#: The two actuator units of docs/formats.md section 2 (``q`` in mm for prismatic, rad for revolute joints).
ACTUATOR_UNITS = {
    "mm": ActuatorUnit("mm", "um", 1e-3, 1.0, "screw or scale", "um/m", "N", 1.0, "um/N", "um"),
    "rad": ActuatorUnit("rad", "urad", 1e-6, 10.0, "gear or encoder", "urad/rad", "N m", 1e-3, "urad/(N m)", "urad/m"),
}


@dataclass(frozen=True)
class MeasurementNoise:
    """The instrument's one-sigma noise.

    Attributes
    ----------
    sigma_position : float
        mm, per axis.
    sigma_angle : float
        rad, per component of the small orientation error.
    sigma_tilt : float
        rad, per tilt angle of a body sensor's reading (``[measurement] sigma_tilt``).
    sensor_mount : float
        rad, one-sigma tolerance of each of a body sensor's two mounting
        tilts (``[measurement] sensor_mount``).
    sensor_turn : float
        rad, one-sigma tolerance of a body sensor's turn about its reading
        (``[measurement] sensor_turn``).
    base_level : float
        rad, one-sigma tolerance of each of the two tilts of up in the base
        frame when there is no base sensor (``[measurement] base_level``):
        how well the base is levelled.  A base sensor's two mounting tilts
        take ``sensor_mount``.
    given : bool
        True when read from the machine file's ``[measurement]`` table, False
        for the documented defaults.
    """

    sigma_position: float = 0.005
    sigma_angle: float = 5.0e-5
    given: bool = False
    #: rad, per tilt angle of a body sensor's reading (docs/formats.md section 8)
    sigma_tilt: float = 1.0e-4
    #: rad, one-sigma tolerance of a body sensor's mounting (and of the base's level) about its start
    sensor_mount: float = 1.0e-3
    #: rad, one-sigma tolerance of a body sensor's turn about its reading (about up) from its start
    sensor_turn: float = 1.0e-2
    #: rad, one-sigma tolerance of the base's level (+z up) where body sensors are fitted without a base sensor
    #: (2e-5 rad = 0.02 mm/m, a machine tool's usual levelling)
    base_level: float = 2.0e-5


@dataclass(frozen=True)
class ToolPoses:
    """Solved tool poses, one per commanded actuator vector.

    Attributes
    ----------
    position : ndarray, shape (n_poses, 3)
        Tool point, base frame, mm.
    rotation : ndarray, shape (n_poses, 3, 3)
        Platform orientation ``R_base_platform``.
    success : ndarray of bool, shape (n_poses,)
        Whether the forward kinematics converged for each pose.
    message : tuple of str
        Per pose: ``""`` or why it failed.
    state : object
        Kind-specific solution (e.g. the platform pose) for warm starts and
        for the Jacobian.
    """

    position: NDArray
    rotation: NDArray
    success: NDArray
    message: tuple[str, ...]
    state: object = None

    @property
    def axis(self) -> NDArray:
        """Tool axis ``R e_z``, shape (n_poses, 3)."""
        return self.rotation[..., :, 2]

    def take(self, idx) -> "ToolPoses":
        """The poses ``idx`` (indices, a boolean mask or a slice), the kind's state indexed alike (:func:`map_state`).

        Only the taken poses' messages are read (a large recording's pose blocks take a few of many).
        """
        if isinstance(idx, slice):
            messages = tuple(self.message[idx])
        else:
            idx = np.asarray(idx)
            taken = np.flatnonzero(idx) if idx.dtype == bool else idx.reshape(-1)
            # itemgetter picks in C: a Python loop over every taken pose cost 1 s of a 100,000-pose screen
            messages = itemgetter(*taken.tolist())(self.message) if taken.size > 1 else tuple(
                self.message[i] for i in taken.tolist())
        return ToolPoses(self.position[idx], self.rotation[idx], self.success[idx], messages,
                         map_state(lambda a: a[idx], self.state))


@dataclass(frozen=True)
class WeightBodies:
    """The moving bodies that carry weight, per pose: each body's frame and its velocity per actuator.

    Attributes
    ----------
    origin : ndarray, shape (n_poses, n_bodies, 3)
        Origin of each body's frame, base frame, mm.
    rotation : ndarray, shape (n_poses, n_bodies, 3, 3)
        Orientation of each body's frame in the base frame.
    jacobian : ndarray, shape (n_poses, n_bodies, 6, n_actuators)
        Rows 0-2: velocity of the frame's origin (mm per unit of ``q_i``,
        mm or rad); rows 3-5: angular velocity of the body (rad per unit of
        ``q_i``), base frame.  A point ``x = origin + R c`` fixed to the body
        moves by ``v + w x (R c)`` per unit of ``q_i``.
    names : tuple of str
        One per body, for messages (``"platform"``, ``"link3"``, ...).
    """

    origin: NDArray
    rotation: NDArray
    jacobian: NDArray
    names: tuple[str, ...]


@dataclass(frozen=True)
class BodyInertials:
    """Known masses and centres of mass of a machine's weight bodies (e.g. from a URDF's ``<inertial>``).

    Attributes
    ----------
    mass_kg : ndarray, shape (n_bodies,)
        kg, in the order of :meth:`Machine.weight_bodies`.
    com_mm : ndarray, shape (n_bodies, 3)
        Centre of mass in the body's frame, from its origin, mm.
    source : str
        Where they were read (named in notes).
    """

    mass_kg: NDArray
    com_mm: NDArray
    source: str = ""


def map_state(fn, state, *others):
    """Apply ``fn`` to every per-pose array of a ``ToolPoses.state``, keeping its structure.

    A kind's state is a dataclass of arrays with the pose on the leading axis,
    or None; a hybrid machine's state nests its modules' states in dataclasses
    and tuples.  Consumers that select, tile or merge poses (measurement
    subsets, stacked parameter sets, effect fits) go through this function so
    that they never need to know which kind made the state.

    Parameters
    ----------
    fn : callable
        ``fn(array, *other_arrays) -> array``.
    state : object
        Dataclass, tuple, ndarray or None.
    *others : object
        States of the same structure whose arrays are passed alongside.

    Returns
    -------
    object
        Of the same structure; None stays None, other leaves are kept as they are.
    """
    if state is None:
        return None
    if dataclasses.is_dataclass(state) and not isinstance(state, type):
        return type(state)(**{
            f.name: map_state(fn, getattr(state, f.name), *(getattr(o, f.name) for o in others))
            for f in dataclasses.fields(state)
        })
    if isinstance(state, tuple):
        return tuple(map_state(fn, s, *(o[i] for o in others)) for i, s in enumerate(state))
    if isinstance(state, np.ndarray):
        return fn(state, *others)
    return state


def geometry_blocks(theta: NDArray) -> tuple[NDArray, NDArray] | None:
    """Where stacked geometries start in per-pose parameter rows, if they repeat in blocks.

    A sampler evaluates many parameter vectors in one call by repeating each
    over every pose (:meth:`bayescal.measurement.MeasurementModel.predict`):
    a kind's per-geometry arrays (tilted axes, fixed rotations) are then
    computed once per block and repeated (``np.repeat(a, runs, axis=0)``),
    not once per row.

    Parameters
    ----------
    theta : ndarray, shape (n, P)

    Returns
    -------
    (starts, runs) or None
        The first row of each run of equal rows and the run lengths, when
        there are at most a quarter as many runs as rows; else None.
    """
    n = theta.shape[0]
    if theta.ndim != 2 or n < 4:
        return None
    first = np.ones(n, dtype=bool)
    np.any(theta[1:] != theta[:-1], axis=1, out=first[1:])
    starts = np.flatnonzero(first)
    if 4 * starts.size > n:
        return None
    return starts, np.diff(np.append(starts, n))


#: Machine kinds by the ``kind`` string of the machine file; every subclass of :class:`Machine` that
#: sets a ``kind`` adds itself (a new kind plugs in by being defined).
KINDS: dict[str, type["Machine"]] = {}


class Machine(ABC):
    """A kinematic family with its nominal geometry.

    Subclasses set :attr:`kind` and implement :meth:`forward`,
    :meth:`tool_jacobian`, :meth:`to_toml` and :meth:`from_toml`.
    """

    kind: ClassVar[str] = ""

    def __init_subclass__(cls, **kwargs) -> None:
        super().__init_subclass__(**kwargs)
        kind = cls.__dict__.get("kind")
        if isinstance(kind, str) and kind:  # a view's kind is its machine's (forwarded): not a kind
            if kind in KINDS and KINDS[kind].__qualname__ != cls.__qualname__:
                raise TypeError(f"machine kind {kind!r} is already {KINDS[kind].__qualname__}")
            KINDS[kind] = cls

    #: Physical effects at fixed values, from the machine file's ``[effect.<name>]`` tables
    #: (docs/formats.md section 7; tuple of :class:`bayescal.effects.stored.StoredEffect`).  Not a
    #: dataclass field of the kinds: :meth:`with_effects` attaches them to a copy.
    effects: tuple = ()
    #: What a calibrated machine file keeps of its calibration (``[calibration]``: the parameters'
    #: covariance and the noise scale, :class:`bayescal.prediction.record.CalibrationRecord`) and its
    #: model discrepancy (``[discrepancy]``, :class:`bayescal.discrepancy.Discrepancy`); None when
    #: the file has none.  Attached by :meth:`with_calibration`, like the effects.
    calibration = None
    discrepancy = None
    #: Prior mean of ``theta``, shape (P,), or None: zero (the nominal geometry).  A view whose parameters
    #: are centred elsewhere states it (effect parameters at their priors' means,
    #: :class:`bayescal.effects.joint_model.EffectAugmented`).
    prior_mean = None
    #: Lower bounds of ``theta``'s prior, shape (P,) (``-inf``: none), or None: no parameter is bounded.
    #: A view with physical bounds states them (an effect's compliance or mass), and samplers truncate there.
    prior_lower = None

    name: str
    layout: ParamLayout
    tolerance: NDArray
    noise: MeasurementNoise
    q_limits: NDArray | None
    source: str

    @property
    @abstractmethod
    def n_actuators(self) -> int:
        """Number of actuated joints (columns q1..qN of a recording)."""

    @property
    def n_dof(self) -> int:
        """Degrees of freedom of the platform: the actuator count, unless actuation is redundant (more drives).

        A kind with redundant actuators overrides it, so that effects of
        position-controlled drives fighting through the closed loops
        (:mod:`bayescal.effects.redundancy_preload`) know how many there are.
        """
        return self.n_actuators

    @property
    def actuator_units(self) -> tuple[str, ...]:
        """Per actuator ``"mm"`` (prismatic) or ``"rad"`` (revolute): the unit of ``q``.

        Every shipped kind is prismatically actuated; a kind with revolute
        actuators overrides this, so that recordings are checked against it.
        """
        return ("mm",) * self.n_actuators

    @property
    def actuator_unit_info(self) -> tuple[ActuatorUnit, ...]:
        """Per actuator, the :class:`ActuatorUnit` of its ``q`` (from :attr:`actuator_units`)."""
        return tuple(ACTUATOR_UNITS[u] for u in self.actuator_units)

    @property
    def n_params(self) -> int:
        return len(self.layout)

    @property
    def geometry_part(self) -> tuple["Machine", NDArray]:
        """The machine whose geometry the parameters describe, and the indices of its parameters.

        A plain machine: itself and every parameter.  A view with nuisance
        parameters (a fitted instrument frame, ballbar pivots) gives the inner
        machine and where its parameters sit, so that a compensation grid or
        an output error is the geometry's alone.
        """
        return self, np.arange(self.n_params)

    # ------------------------------------------------- the instrument frame's layer
    # A machine measured in an instrument frame (bayescal.machines.framed.InstrumentFrame) is this
    # machine wrapped; consumers ask these members instead of checking the type.

    @property
    def framed(self) -> bool:
        """Whether an instrument frame wraps the machine (its parameters then lead ``theta``)."""
        return False

    @property
    def n_frame(self) -> int:
        """Number of instrument-frame parameters before the machine's own: 0 without a fitted frame."""
        return 0

    @property
    def instrument_frame(self):
        """The :class:`~bayescal.machines.framed.InstrumentFrame` the machine is measured in, or None without one.

        The frame itself, or the one under a view around it (effect
        parameters fitted with a framed geometry): its stations, whether it
        is fitted and its frame at ``theta`` are asked of it, its parameters
        leading ``theta``.
        """
        return None

    @property
    def inside(self) -> "Machine":
        """The machine under an instrument frame; a machine without one is its own inside."""
        return self

    @property
    def redundancy(self) -> "RedundantKinematics | None":
        """The redundantly actuated kinematics of :attr:`inside`, or None: a machine with no redundant drive.

        A kind with more drives than degrees of freedom and every drive's
        inverse kinematics in closed form (the RASPM) gives itself; an
        instrument frame gives its machine's (the parameters after the
        frame's :attr:`n_frame` are the machine's); a view with parameters
        of its own appended gives None.  Effects of drives preloaded against
        each other (:mod:`bayescal.effects.redundancy_preload`) ask it
        instead of the machine's type.
        """
        return None

    @property
    def serial_chain(self) -> "Machine | None":
        """The serial chain (``kind = "serial"``, a URDF's) this machine is, or None for every other kind.

        Effects of a chain's links under gravity and the URDF writer need its
        bodies and joints.  A view has none of its own (its parameters are
        not the chain's): ask the machine under it (:attr:`geometry_part`).
        """
        return None

    @property
    def written_modules(self) -> tuple["Machine", ...]:
        """The machines written to files of their own beside this machine's (docs/formats.md section 5).

        A hybrid's modules; () for every other kind and for a view (written
        whole by its :meth:`to_toml`; a framed hybrid's modules are asked of
        :attr:`inside`).
        """
        return ()

    def rewrapped(self, inner: "Machine") -> "Machine":
        """``inner`` in this machine's instrument frame (``inner`` itself without one)."""
        return inner

    def base_machine(self) -> "Machine":
        """The machine in its base frame, without nuisance views (instrument frame, body sensors' mountings)."""
        return self

    def without_sensor_mounts(self) -> "Machine":
        """This machine without a body-sensor mountings view around it (itself when it has none).

        A model built again for another recording replaces the sensors' parameters rather than appending a
        second set (:class:`bayescal.sensors.mounts.SensorMounts` overrides it).
        """
        return self

    def check_theta(self, theta: ArrayLike | None, n_poses: int | None = None) -> NDArray:
        """``theta`` as an array of shape ``(P,)`` or ``(n_poses, P)``; zeros if None."""
        if theta is None:
            return np.zeros(self.n_params)
        theta = np.asarray(theta, dtype=float)
        if theta.ndim not in (1, 2) or theta.shape[-1] != self.n_params:
            raise InputError(f"theta: expected shape ({self.n_params},) or (n_poses, {self.n_params}), got {theta.shape}")
        if theta.ndim == 2 and n_poses is not None and theta.shape[0] != n_poses:
            raise InputError(f"theta: {theta.shape[0]} rows for {n_poses} poses")
        return theta

    def for_poses(self, idx) -> "Machine":
        """The machine bound to a subset ``idx`` of the poses it is bound to (stations of a recording).

        A plain machine is bound to no poses: itself.  A view whose frames
        differ per pose (an instrument with several stations) rebinds.
        """
        return self

    def measurement_rotation(self, q: ArrayLike, theta: ArrayLike | None) -> NDArray:
        """Rotation taking base-frame vectors into the frame each pose is measured in, shape (n, 3, 3).

        The identity for a machine measured in its base frame; an instrument
        frame gives each pose its station's ``R^T``.  A quantity defined on
        the machine (a model discrepancy of the tool pose) reaches the
        measured rows through it.
        """
        n = self.check_q(q).shape[0]
        return np.broadcast_to(np.eye(3), (n, 3, 3)).copy()

    def check_q(self, q: ArrayLike) -> NDArray:
        q = np.atleast_2d(np.asarray(q, dtype=float))
        if q.ndim != 2 or q.shape[1] != self.n_actuators:
            raise InputError(f"q: expected shape (n_poses, {self.n_actuators}), got {np.shape(q)}")
        return q

    @abstractmethod
    def forward(self, q: ArrayLike, theta: ArrayLike | None = None, *, guess: ToolPoses | None = None) -> ToolPoses:
        """Tool poses for commanded actuator positions ``q`` (n_poses, n_actuators)."""

    @abstractmethod
    def tool_jacobian(self, q: ArrayLike, theta: ArrayLike | None, poses: ToolPoses) -> NDArray:
        """Derivative of the tool pose with respect to ``theta``.

        Returns
        -------
        ndarray, shape (n_poses, 6, P)
            Rows 0-2: tool point (mm per unit of each parameter); rows 3-5:
            small rotation of the platform in the base frame (rad per unit),
            ``R(theta + d) = exp([J_rot d]x) R(theta)``.
        """

    def tool_jacobian_columns(self, q: ArrayLike, theta: ArrayLike | None, poses: ToolPoses,
                              columns: NDArray) -> NDArray:
        """Columns ``columns`` of :meth:`tool_jacobian`, shape (n_poses, 6, len(columns)), the same values.

        ``columns``: indices into the layout, increasing.  What a fit of a
        subset of the parameters asks for at each step.  This default takes
        them from the whole Jacobian; a kind whose columns come in
        independent blocks computes only the blocks asked for
        (:class:`~bayescal.machines.serial.Serial`).
        """
        return self.tool_jacobian(q, theta, poses)[:, :, columns]

    def actuator_jacobian(self, q: ArrayLike, theta: ArrayLike | None, poses: ToolPoses) -> NDArray:
        """Derivative of the tool pose with respect to the actuator positions ``q``.

        The default is central finite differences of :meth:`forward` (step
        ``1e-4`` of the actuator's unit, warm-started at ``poses``), so that
        every kind has one; kinds override it with an analytic version.

        Returns
        -------
        ndarray, shape (n_poses, 6, n_actuators)
            Rows 0-2: tool point (mm per mm or per rad); rows 3-5: small
            rotation of the platform in the base frame, as in
            :meth:`tool_jacobian`.
        """

        q = self.check_q(q)
        n, m = q.shape
        h = 1e-4
        J = np.empty((n, 6, m))
        for i in range(m):
            dq = np.zeros(m)
            dq[i] = h
            plus = self.forward(q + dq, theta, guess=poses)
            minus = self.forward(q - dq, theta, guess=poses)
            J[:, :3, i] = (plus.position - minus.position) / (2 * h)
            J[:, 3:, i] = so3_log(plus.rotation @ np.swapaxes(minus.rotation, -1, -2)) / (2 * h)
        return J

    @property
    def weight_body_names(self) -> tuple[str, ...]:
        """Names of the bodies :meth:`weight_bodies` returns, in order (the platform alone by default)."""
        return ("platform",)

    @property
    def sensor_bodies(self) -> tuple[str, ...]:
        """Bodies a tilt sensor may be fixed to (docs/formats.md section 8): ``base`` alone by default.

        A kind that exposes its bodies (the serial chain) lists them and gives
        their orientations (``body_frame``, ``body_rotations``); a sensor on
        any other body of a kind that does not is refused by name.
        """
        return ("base",)

    @property
    def body_inertials(self) -> "BodyInertials | None":
        """Masses and centres of mass of the weight bodies the machine file states, or None (unknown, the default)."""
        return None

    def weight_bodies(self, q: ArrayLike, theta: ArrayLike | None, poses: ToolPoses) -> WeightBodies:
        """The moving bodies that carry weight at each pose (see :class:`WeightBodies`).

        The default is the platform alone: its frame's origin is the
        platform origin of the kind's state (``poses.state.p``; the tool
        point on kinds whose state has none), its orientation the measured
        one (``poses.rotation``), and its velocity the tool twist of
        :meth:`actuator_jacobian` moved to that origin.  Kinds whose
        intermediate bodies move (serial chains: every link) override this
        and :attr:`weight_body_names`.

        Parameters
        ----------
        q : array_like, shape (n_poses, n_actuators)
        theta : array_like, shape (P,) or (n_poses, P), optional
        poses : ToolPoses
            ``forward(q, theta)``.
        """
        J = self.actuator_jacobian(q, theta, poses)
        p = getattr(poses.state, "p", None)
        origin = np.asarray(p, float) if p is not None else np.asarray(poses.position, float)
        w = J[:, 3:]
        v = J[:, :3] + np.cross(w, (origin - poses.position)[:, :, None], axis=1)
        return WeightBodies(origin[:, None], np.asarray(poses.rotation, float)[:, None],
                            np.concatenate([v, w], axis=1)[:, None], self.weight_body_names)

    @abstractmethod
    def to_toml(self, theta: ArrayLike | None = None) -> str:
        """Machine file text of the geometry ``nominal + theta`` (errors folded in).

        The geometry only: :func:`bayescal.effects.stored.machine_file_text`
        adds the ``[effect.*]`` tables of :attr:`effects`.
        """

    @classmethod
    @abstractmethod
    def from_toml(cls, table, path: str) -> "Machine":
        """Build from a parsed machine file (:class:`bayescal.io.TomlTable`)."""

    def with_effects(self, effects) -> "Machine":
        """A copy of this machine carrying ``effects`` (``()``: the geometry alone).

        Every measurement model built from a recording applies them
        (:meth:`bayescal.measurement.MeasurementModel.from_recording`).
        """
        import copy

        out = copy.copy(self)
        object.__setattr__(out, "effects", tuple(effects))
        return out

    def with_noise(self, noise: "MeasurementNoise") -> "Machine":
        """A copy of this machine with the instrument noise ``noise`` (the noise the data support)."""
        import copy

        out = copy.copy(self)
        object.__setattr__(out, "noise", noise)
        return out

    def with_calibration(self, calibration=None, discrepancy=None) -> "Machine":
        """A copy carrying a calibration record and a model discrepancy (None: none).

        ``bayescal predict`` holds a calibrated machine fixed with the
        uncertainty the record gives; the discrepancy adds to every
        prediction.  Writing the machine writes both tables.
        """
        import copy

        out = copy.copy(self)
        object.__setattr__(out, "calibration", calibration)
        object.__setattr__(out, "discrepancy", discrepancy)
        return out

    def node_actuators(self, q: NDArray, theta: NDArray | None = None, aux: dict | None = None) -> tuple[NDArray, NDArray | None]:
        """Where the drives stand at grid nodes commanded to ``q``, and how that moves with the parameters.

        Parameters
        ----------
        q : ndarray, shape (n, n_actuators)
            Commanded actuator positions of the nodes (mm or rad).
        theta : ndarray, shape (P,), optional
            The parameters (a view may hold effect parameters among them).
        aux : dict, optional
            Auxiliary channels at the nodes (``{"payload_kg": 5.0}``).

        Returns
        -------
        q_actual : ndarray, shape (n, n_actuators)
            ``q`` plus the stored effects' ``dq`` under ``aux``, each node a
            session of its own (``bayescal.effects.stored.static_effect_delta_q``).
        dq_dtheta : ndarray, shape (n, n_actuators, P), or None
            None here: stored effects are fixed values, not parameters.  A
            view whose parameters include effect parameters gives their
            columns, so that a grid's std carries them.
        """
        if not self.effects:
            return q, None
        # the stored effects apply themselves (StoredEffect.static_delta_q): effects sit above machines
        return q + type(self.effects[0]).static_delta_q(self, self.effects, q, aux), None

    def node_tool_offset(self, q: NDArray, theta: NDArray | None = None, aux: dict | None = None) -> NDArray | None:
        """Base-frame tool displacement (mm) and rotation (rad) of the stored effects that move the tool, at grid nodes.

        Shape (n, 6), or None when no effect moves the tool (a link or
        column bending under gravity: :attr:`bayescal.effects.Effect.moves_tool`);
        a grid adds it to the tool point the drives reach
        (``bayescal.effects.stored.static_effect_delta_x``).  A machine
        that carries a model discrepancy (``[discrepancy]``) adds its mean at
        the nodes' actuators and channels (its std is not in the grid's).
        """
        out = None
        if self.effects:
            out = type(self.effects[0]).static_delta_x(self, self.effects, q, aux)
        if self.discrepancy is not None:
            d = self.discrepancy.tool_offset(q, aux)
            out = d if out is None else out + d
        return out

    def guess_from_measurement(
        self, q: NDArray, position: NDArray, rotation: NDArray | None = None, axis: NDArray | None = None
    ) -> ToolPoses | None:
        """A forward-kinematics start built from measured tool poses, or None.

        Starting Newton from the measurement keeps the solution on the
        branch the real machine is on, whatever the machine file's layout.
        """
        return None

    @property
    def actuator_box_reachable(self) -> bool:
        """Whether every actuator vector within ``q_limits`` assembles (nominally).

        True for a machine whose actuators move independently over their
        whole strokes.  A kind whose ``q_limits`` box holds vectors that do
        not assemble (a linear delta: the three carriages far apart pull the
        arms past their length) or whose actuators are coupled (redundant
        actuation) returns False, so that consumers spanning a grid over the
        box (``bayescal grid``) span the tool point instead.
        """
        return True

    def compatible_q(self, q: ArrayLike, theta: ArrayLike | None = None) -> NDArray:
        """The actuator vector that commands the pose ``forward(q, theta)`` with every actuator agreeing.

        ``q`` itself for a machine whose actuators move independently (the
        default).  A kind with coupled actuators (redundant actuation, whose
        forward kinematics reads a non-redundant subset) overrides it to set
        the others to what that pose requires, so that a consumer which
        solves for actuator positions through ``forward`` (the tool-space
        grid's inverse kinematics) commands a pose the machine can hold and
        effects that act on all actuators (redundancy preload) see it.

        Parameters
        ----------
        q : array_like, shape (n_poses, n_actuators)
            Actuator positions, mm (or rad).
        theta : array_like, optional
            Geometric errors (the machine file's geometry if omitted).

        Returns
        -------
        ndarray, shape (n_poses, n_actuators)
        """
        return self.check_q(q)

    def home_q(self) -> NDArray:
        """A reference actuator vector: the middle of ``q_limits``."""
        if self.q_limits is None:
            raise InputError(f"{self.source}: the machine file has no [workspace] q_limits; they are needed here")
        return self.q_limits.mean(axis=1)

    def sample_q(self, n: int, rng: np.random.Generator) -> NDArray:
        """``n`` actuator vectors drawn uniformly within ``q_limits``."""
        if self.q_limits is None:
            raise InputError(f"{self.source}: the machine file has no [workspace] q_limits; they are needed to draw poses")
        lo, hi = self.q_limits[:, 0], self.q_limits[:, 1]
        return lo + (hi - lo) * rng.random((n, self.n_actuators))


class RedundantKinematics(Protocol):
    """What :attr:`Machine.redundancy` offers: a planar machine's drives, some redundant, in closed form.

    Poses ``x`` are planar, shape (n, 3): ``(p_x mm, p_z mm, phi rad)``;
    ``theta`` the machine's parameters (:attr:`layout`), one vector or one per pose.
    """

    layout: ParamLayout
    tolerance: NDArray
    pose_range: NDArray | None

    @property
    def nonredundant(self) -> tuple[int, ...]:
        """0-based drives that fix the pose."""

    @property
    def redundant(self) -> tuple[int, ...]:
        """0-based drives the others' pose fixes (the preloaded ones)."""

    def offset_index(self) -> NDArray:
        """Per drive, the parameter that moves its zero along its rail, shape (m,)."""

    def inverse_planar(self, x: ArrayLike, theta: ArrayLike | None = None) -> NDArray:
        """Drive positions ``q`` (n, m) for the poses ``x``."""

    def ik_jacobian(self, x: ArrayLike, theta: ArrayLike | None = None) -> tuple[NDArray, NDArray]:
        """``q = IK(x)`` (n, m) and ``dq/dx`` (n, m, 3)."""

    def ik_parameter_jacobian(self, x: ArrayLike, theta: ArrayLike | None = None) -> NDArray:
        """``dq/dtheta`` (n, m, P) at fixed poses."""


def offset_poses(machine: Machine, q: NDArray, theta, poses: ToolPoses, offset: NDArray) -> ToolPoses:
    """Solved poses moved by base-frame tool-pose perturbations, in the frame the poses are measured in.

    Parameters
    ----------
    machine : Machine
        The machine ``poses`` were solved on (:meth:`Machine.measurement_rotation`
        takes the base-frame perturbation into each pose's measurement frame).
    q : ndarray, shape (n, N)
    theta : ndarray, shape (P,) or (n, P), or None
    poses : ToolPoses
        ``machine.forward(q, theta)``.
    offset : ndarray, shape (n_0, 6)
        Base-frame displacement of the tool point (mm) and small rotation of
        the tool frame (rad) per pose; tiled when ``n`` is a multiple of
        ``n_0`` (stacked parameter sets).

    Returns
    -------
    ToolPoses
        Position ``p + R_m dx``, rotation ``exp([R_m w]x) R`` with ``R_m`` the
        measurement rotation; the kind's state (warm start) is kept.
    """
    n = poses.position.shape[0]
    off = np.asarray(offset, dtype=float)
    if off.shape[0] != n:
        off = np.tile(off, (n // off.shape[0], 1))
    Rm = machine.measurement_rotation(q, theta)
    dp = np.einsum("nij,nj->ni", Rm, off[:, :3])
    w = np.einsum("nij,nj->ni", Rm, off[:, 3:])
    return ToolPoses(poses.position + dp, so3_exp(w) @ poses.rotation, poses.success, poses.message, poses.state)


def machine_from_table(doc, path: str) -> Machine:
    """The geometry of a machine-file table, built by the kind its ``kind`` key names (:data:`KINDS`).

    Raises
    ------
    MachineFileError
        Key ``kind``: unknown, naming the kinds there are.
    """
    kind = doc.string("kind")
    if kind not in KINDS:
        raise MachineFileError(path, "kind", f"unknown kind {kind!r}; expected one of: {', '.join(KINDS)}")
    try:
        return KINDS[kind].from_toml(doc, path)
    except ToleranceKeyError as e:
        # a per-parameter tolerance is checked against the parameters the geometry has, once it is built
        raise doc.error(f"tolerance.{toml_key(e.key)}", e.expected) from None
