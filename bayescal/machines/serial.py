"""Serial chains (rotary tables, trunnions, positioners, wrists, arms) with URDF joint semantics.

Kinematics (docs/formats.md section 5), lengths in mm and angles in rad: joint
``i`` contributes

    T_i = Trans(origin_i) Rot(rpy_i) M_i(q_i + offset_i),
    Rot(r, p, y) = Rz(y) Ry(p) Rx(r),
    M = Rot(axis, q) (revolute)  or  Trans(axis q) (prismatic),

and the tool (measured) frame is ``T_1 ... T_n Trans(tool.point) Rot(tool.rpy)``;
its origin is the tool point and its orientation the measured orientation.

Mimic joints (docs/formats.md section 8; URDF ``<mimic>``): joint ``i`` with
``mimic = d`` moves by ``multiplier * q_d + offset`` (``q_d`` the position of
joint ``d``, which is no mimic joint itself).  A mimic joint is no actuator:
the actuators ``q_1 ... q_N`` are the non-mimic joints in order, and the
recordings have one ``q`` column each.  Every joint, mimic or not, keeps its
error parameters below; a mimic joint's ``joint<i>.offset`` is a zero offset
added to its position like any joint's.  The multiplier has no error
parameter: it is a transmission ratio, like the drives' own ratios, which
the geometric model takes as exact (a ratio error of the driving actuator,
e.g. a screw-pitch effect, reaches the mimic joint through the multiplier).

Error parameters, per joint ``i`` in this order (the order is the priority of
the automatic identifiable subset: earlier parameters are kept in
preference), then the tool:

* ``joint<i>.offset``: zero offset added to joint ``i``'s position (rad or mm);
* ``joint<i>.axis.tilt_<a>``, ``joint<i>.axis.tilt_<b>``: the unit axis tilted
  by two small rotations about the joint-frame axes ``a``, ``b`` it is most
  perpendicular to (``z`` axis: ``tilt_x``, ``tilt_y``), see
  :func:`bayescal.geometry.tilted_direction`; the normalised form is exact, so
  a calibrated machine file stores the tilted unit axis itself;
* ``joint<i>.origin.{x,y,z}`` (mm, parent frame), ``joint<i>.rpy.{r,p,y}``
  (rad, added to the rpy angles);
* ``tool.point.{x,y,z}`` (mm, last joint frame), ``tool.rpy.{r,p,y}`` (rad).

The Jacobian is analytic (product of exponentials): a perturbation of a
factor of the chain is a twist of the frame it acts in, carried to the base
frame by that frame's pose, so every column costs a cross product.
"""

from __future__ import annotations

import weakref
from dataclasses import dataclass, field, fields
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..errors import InputError
from ..geometry import _cross_basis, _norms, left_jacobian, rpy_from_matrix, rpy_matrix, so3_exp, tilt_axes, tilted_direction
from ..io.machine_file import TomlTable, format_toml_value
from ..params import ParamLayout, ParamSpec
from .base import BodyInertials, Machine, MeasurementNoise, ToolPoses, WeightBodies, geometry_blocks
from .common import common_toml, read_noise, read_q_limits, read_tolerance
from .tolerance import tolerance_vector
from .urdf import chain_from_urdf

__all__ = ["Serial", "ChainFrames", "SERIAL_TOLERANCE_DEFAULTS", "JOINT_TYPES", "rpy_matrix", "rpy_from_matrix", "mimic_problem"]

#: Documented one-sigma defaults of the ``[tolerance]`` table (mm or rad).
SERIAL_TOLERANCE_DEFAULTS: dict[str, float] = {
    "origin": 0.05,          # mm, joint frame origins
    "rpy": 2.0e-4,           # rad, joint frame orientations
    "axis": 2.0e-4,          # rad, tilt of the joint axes
    "offset_angle": 2.0e-4,  # rad, zero offsets of revolute joints
    "offset_length": 0.05,   # mm, zero offsets of prismatic joints
    "tool_point": 0.05,      # mm
    "tool_rpy": 2.0e-4,      # rad
}

JOINT_TYPES = ("revolute", "prismatic")
_XYZ = "xyz"
_RPY = "rpy"
_PER_JOINT = 9  # offset, 2 axis tilts, 3 origin, 3 rpy
#: The Jacobian's independent column blocks (:meth:`Serial.tool_jacobian_columns`), and the block of each of a
#: joint's nine columns.
_BLOCKS = ("offset", "axis tilt", "origin", "rpy", "tool point", "tool rpy")
_SLOT_BLOCK = (0, 1, 1, 2, 2, 2, 3, 3, 3)


def rpy_rates(rpy: NDArray) -> NDArray:
    """Angular velocity per unit rate of ``r``, ``p``, ``y``, in the frame the rotation acts in.

    ``d Rot(rpy) Rot(rpy)^T = [w]x`` with ``w = W[..., :, k]`` for a unit change
    of angle ``k``: ``Rz Ry e_x``, ``Rz e_y``, ``e_z``.  Shape ``(..., 3, 3)``.
    """
    cp, sp = np.cos(rpy[..., 1]), np.sin(rpy[..., 1])
    cy, sy = np.cos(rpy[..., 2]), np.sin(rpy[..., 2])
    W = np.zeros(rpy.shape[:-1] + (3, 3))
    W[..., 0, 0], W[..., 1, 0], W[..., 2, 0] = cy * cp, sy * cp, -sp
    W[..., 0, 1], W[..., 1, 1] = -sy, cy
    W[..., 2, 2] = 1.0
    return W


def mimic_problem(mimic: tuple, i: int) -> str | None:
    """Why joint ``i``'s mimic entry cannot be used, or None when it can.

    Parameters
    ----------
    mimic : tuple
        Per joint: None (an actuator) or ``(d, multiplier, offset)``, ``d`` the
        0-based index of the driving joint (offset mm or rad).
    i : int
        The joint (0-based) to check; messages number joints from 1, as the
        machine file does.
    """
    if mimic[i] is None:
        return None
    d, k, o = mimic[i]
    m = len(mimic)
    if isinstance(d, bool) or not isinstance(d, (int, np.integer)) or not 0 <= d < m:
        shown = d + 1 if isinstance(d, (int, np.integer)) and not isinstance(d, bool) else repr(d)
        return f"joint {i + 1} mimics joint {shown}; expected the index of another joint, 1..{m}"
    if d == i:
        return f"joint {i + 1} mimics itself; expected the index of the joint that drives it"
    if mimic[d] is not None:
        return (f"joint {i + 1} mimics joint {d + 1}, which mimics joint {mimic[d][0] + 1}; the driving joint must be "
                f"an actuator (no mimic joint itself)")
    if not (np.isfinite(k) and np.isfinite(o)):
        return f"joint {i + 1}: mimic multiplier and offset must be finite numbers, got {k!r} and {o!r}"
    return None


def _rotate(R: NDArray, v: NDArray) -> NDArray:
    """``R_i v_i`` for rotations (n, 3, 3) and vectors (n, 3) or (1, 3) (one vector for every pose), shape (n, 3)."""
    if v.shape[0] == 1 and R.shape[0] != 1:
        return np.einsum("nij,j->ni", R, v[0])  # one vector: no broadcast copy
    return np.einsum("nij,nj->ni", R, v)


def _cross(w: NDArray, a: NDArray) -> NDArray:
    """``w_i x a_i`` column by column: ``w`` (n, 3, c), ``a`` (n, 3); shape (n, 3, c).

    ``numpy.cross(w, a[:, :, None], axis=1)`` written out: the same products
    and differences, without its axis shuffling, which cost more than the
    arithmetic on the chain's small arrays.
    """
    a0, a1, a2 = a[:, 0, None], a[:, 1, None], a[:, 2, None]
    out = np.empty(np.broadcast_shapes(w.shape, a.shape[:2] + (1,)))
    out[:, 0] = w[:, 1] * a2 - w[:, 2] * a1
    out[:, 1] = w[:, 2] * a0 - w[:, 0] * a2
    out[:, 2] = w[:, 0] * a1 - w[:, 1] * a0
    return out


def _tilted_axes(u0: NDArray, G: NDArray, tilt: NDArray) -> tuple[NDArray, NDArray]:
    """:func:`~bayescal.geometry.tilted_direction` of every axis at once: ``u0`` (m, 3), ``G`` (m, 3, 2), ``tilt`` (g, m, 2).

    ``G`` holds each axis's two tilt directions (``e_a x u0``, ``e_b x u0``:
    ``tilted_direction``'s derivative at zero tilt); the arithmetic is
    ``tilted_direction``'s, one numpy call per step for all axes.
    """
    n = u0 + (tilt[..., None, :] @ np.swapaxes(G, -1, -2))[..., 0, :]
    norm = _norms(n)[..., None]
    u = n / norm
    P = (np.eye(3) - u[..., :, None] * u[..., None, :]) / norm[..., None]
    return u, P @ G


def _cross_joints(w: NDArray, a: NDArray) -> NDArray:
    """:func:`_cross` for every joint at once: ``w`` (n, m, 3, c), ``a`` (n, m, 3); shape (n, m, 3, c)."""
    a0, a1, a2 = a[..., 0, None], a[..., 1, None], a[..., 2, None]
    # the chain's arrays agree in all but the columns (numpy.broadcast_shapes costs more than the products here)
    out = np.empty(w.shape if w.shape[:-1] == a.shape else np.broadcast_shapes(w.shape, a.shape + (1,)))
    out[..., 0, :] = w[..., 1, :] * a2 - w[..., 2, :] * a1
    out[..., 1, :] = w[..., 2, :] * a0 - w[..., 0, :] * a2
    out[..., 2, :] = w[..., 0, :] * a1 - w[..., 1, :] * a0
    return out


def _put(Jj: NDArray, cols, pos: NDArray, rot: NDArray | None) -> None:
    """Write every joint's position (n, m, 3[, c]) and rotation rows into ``Jj`` (n, 6, m, 9) at columns ``cols``."""
    Jj[:, :3, :, cols] = pos.swapaxes(1, 2)  # (n, 3, m[, c]); swapaxes: no axis normalisation per call
    if rot is not None:
        Jj[:, 3:, :, cols] = rot.swapaxes(1, 2)


#: The last chain of each machine (:meth:`Serial._memo_chain`); weak, so a machine's memo goes with it.
_CHAINS: "weakref.WeakKeyDictionary" = weakref.WeakKeyDictionary()
#: Poses times joints up to which a chain is remembered (its frames: about 300 bytes per joint and pose).
_MEMO_MAX = 200_000


@dataclass(frozen=True)
class _Chain:
    """Frames of a solved chain, per pose (leading axis n) and joint (axis k)."""

    R_parent: NDArray  # (n, m, 3, 3) frame before joint k (base for k = 0)
    R_joint: NDArray  # (n, m, 3, 3) joint frame (after origin and rpy, before the motion)
    p_joint: NDArray  # (n, m, 3) joint frame origin, base frame
    rpy: NDArray  # (n, m, 3)
    axis: NDArray  # (n, m, 3) unit axis, joint frame
    daxis: NDArray  # (n, m, 3, 2) its derivative w.r.t. the two tilts
    qe: NDArray  # (n, m) q + offset
    R_end: NDArray  # (n, 3, 3) last joint frame (after the motion)
    R_after: NDArray  # (n, m, 3, 3) frame after joint k's motion (link k's frame)
    p_after: NDArray  # (n, m, 3) its origin, base frame
    tool_rpy: NDArray  # (n, 3)
    p_tool: NDArray  # (n, 3)
    R_tool: NDArray  # (n, 3, 3)
    rpy_all: NDArray  # (n, m + 1, 3): rpy, then tool_rpy (both are views of it)


_CHAIN_FIELDS = tuple(f.name for f in fields(_Chain))


@dataclass(frozen=True)
class ChainFrames:
    """The frames of a solved serial chain per pose, base frame (what structural effects need).

    Attributes
    ----------
    joint_origin : ndarray, shape (n, m, 3)
        Origin of joint ``k``'s frame before its motion, mm (where a
        prismatic stage stands at position 0).
    joint_axis : ndarray, shape (n, m, 3)
        Unit axis of joint ``k``, base frame.
    link_origin : ndarray, shape (n, m, 3)
        Origin of link ``k``'s frame (after joint ``k``'s motion), mm.
    link_rotation : ndarray, shape (n, m, 3, 3)
        Orientation of link ``k``'s frame.
    joint_position : ndarray, shape (n, m)
        Position of every joint (mimic joints included, zero offsets added), rad or mm.
    next_point : ndarray, shape (n, m, 3)
        Where link ``k`` carries the next joint (its origin) or, for the last link, the tool point, mm.
    tool_point : ndarray, shape (n, 3)
        mm.
    """

    joint_origin: NDArray
    joint_axis: NDArray
    link_origin: NDArray
    link_rotation: NDArray
    joint_position: NDArray
    next_point: NDArray
    tool_point: NDArray


def _read_joint_tables(joints: list[TomlTable]) -> tuple[list, list, list, list, list, tuple | None]:
    """Types, origins (mm), rpy (rad), unit axes, mimic entries and names of ``[[joint]]`` tables."""
    types, origin, rpy, axis, mimic, names = [], [], [], [], [], []
    for jt in joints:
        jt.reject_unknown({"type", "origin", "rpy", "axis", "name", "mimic", "multiplier", "offset", "mass", "com"})
        t = jt.string("type")
        if t not in JOINT_TYPES:
            raise jt.error("type", f"expected \"revolute\" or \"prismatic\", got {t!r}")
        types.append(t)
        origin.append(jt.vector("origin", default=np.zeros(3)))  # URDF: a missing origin is the identity
        rpy.append(jt.vector("rpy", default=np.zeros(3)))
        axis.append(jt.vector("axis", unit=True))
        names.append(jt.string("name") if jt.has("name") else None)
        if not jt.has("mimic"):
            for k in ("multiplier", "offset"):
                if jt.has(k):
                    raise jt.error(k, "only allowed together with mimic = <index of the driving joint>")
            mimic.append(None)
            continue
        d = jt.data["mimic"]
        if isinstance(d, bool) or not isinstance(d, int):
            raise jt.error("mimic", f"expected the index (1-based integer) of the driving joint, got {d!r}")
        mimic.append((d - 1, jt.number("multiplier", 1.0), jt.number("offset", 0.0)))
    for i, jt in enumerate(joints):
        if (why := mimic_problem(tuple(mimic), i)) is not None:
            raise jt.error("mimic", why)
    if all(n is None for n in names):
        return types, origin, rpy, axis, mimic, None
    # with any name given, an unnamed joint i is named joint<i>; the names must stay distinct
    full = tuple(n if n is not None else f"joint{i + 1}" for i, n in enumerate(names))
    for i, n in enumerate(full):
        if n in full[:i]:
            k = full.index(n)
            this = f"joint name {n!r}" if names[i] is not None else f"the default name {n!r} of this unnamed joint"
            that = f"joint {k + 1}'s name" if names[k] is not None else f"the default name of unnamed joint {k + 1}"
            raise joints[i].error("name", f"{this} is also {that}; expected distinct names")
    return types, origin, rpy, axis, mimic, full


def _read_inertials(joints: list[TomlTable]) -> tuple[NDArray | None, NDArray | None]:
    """``[[joint]] mass`` (kg) and ``com`` (mm, the frame after the joint): every joint's or none (bayescal's keys).

    Link ``k`` is what joint ``k`` moves up to joint ``k + 1``, as a URDF's
    ``<inertial>`` elements give it (:attr:`Serial.link_mass`): a machine
    written from a URDF keeps its weights, so that the gravity effects of a
    calibrated machine load its links as the URDF did.
    """
    given = [jt.has("mass") or jt.has("com") for jt in joints]
    if not any(given):
        return None, None
    for jt, g in zip(joints, given):
        for key in ("mass", "com"):
            if not jt.has(key):
                raise jt.error(key, "missing; expected every joint's mass (kg, 0 for a link that weighs nothing) "
                                    "and centre of mass com (mm, the frame after the joint), or none")
    mass = np.array([jt.number("mass") for jt in joints])
    for jt, m in zip(joints, mass):
        if m < 0:
            raise jt.error("mass", f"expected a mass >= 0 kg, got {m!r}")
    return mass, np.array([jt.vector("com") for jt in joints])


def _read_bodies(doc: TomlTable, n_joints: int) -> tuple:
    """``[[body]]`` tables (bayescal's): named bodies a sensor may be fixed to, as a URDF's links are.

    ``name``; ``joint``, the moving joint whose frame (after its motion) the
    body is fixed to, 1-based, 0 for the base; ``rpy``, its orientation in
    that frame (rad, default zero).  Returns :attr:`Serial.link_bodies`.
    """
    if not doc.has("body"):
        return ()
    out = []
    for bt in doc.array_of_tables("body"):
        bt.reject_unknown({"name", "joint", "rpy"})
        name = bt.string("name")
        k = bt.data.get("joint")
        if isinstance(k, bool) or not isinstance(k, int) or not 0 <= k <= n_joints:
            raise bt.error("joint", f"expected the index of a joint (1 to {n_joints}; 0: the base), got {k!r}")
        if name == "base" or (name.startswith("joint") and name[5:].isdigit()) or name in [b[0] for b in out]:
            raise bt.error("name", f"{name!r} is taken (base, joint<i> or another body); expected a distinct name")
        out.append((name, k - 1, rpy_matrix(bt.vector("rpy", default=np.zeros(3)))))
    return tuple(out)


@dataclass(frozen=True, eq=False)
class Serial(Machine):
    """A serial chain of revolute and prismatic joints with URDF joint semantics.

    Parameters
    ----------
    joint_type : tuple of str
        ``"revolute"`` or ``"prismatic"`` per joint, base outward; joint ``i`` is actuator ``q_i``.
    origin : ndarray, shape (m, 3)
        Joint frame origins in the previous frame, mm.
    rpy : ndarray, shape (m, 3)
        Fixed rotations of the joint frames, rad, ``Rz(y) Ry(p) Rx(r)``.
    axis : ndarray, shape (m, 3)
        Unit joint axes in the joint frames.
    tool_point : ndarray, shape (3,)
        Measured point in the last joint frame, mm.
    tool_rpy : ndarray, shape (3,)
        Orientation of the measured frame in the last joint frame, rad.
    name, noise, q_limits, tolerance_groups, source
        As for the other kinds; ``q_limits`` has one row per actuator (per non-mimic joint).
    mimic : tuple, optional
        Per joint: None (an actuator) or ``(d, multiplier, offset)``: the joint
        moves by ``multiplier * q_d + offset`` with ``d`` the 0-based index of its
        driving joint (no mimic itself); offset mm or rad.  Empty: no mimic joints.
    joint_names : tuple of str, optional
        The joints' names (a URDF's, or ``[[joint]] name``); None: ``joint1`` ...
    """

    kind = "serial"

    joint_type: tuple
    origin: NDArray
    rpy: NDArray
    axis: NDArray
    tool_point: NDArray
    tool_rpy: NDArray = field(default_factory=lambda: np.zeros(3))
    name: str = "serial chain"
    noise: MeasurementNoise = field(default_factory=MeasurementNoise)
    q_limits: NDArray | None = None
    tolerance_groups: dict = field(default_factory=lambda: dict(SERIAL_TOLERANCE_DEFAULTS))
    source: str = "<memory>"
    #: Known masses (kg, (m,)) and centres of mass (mm, (m, 3), link k's frame: the frame after joint k) of the
    #: moving links, from a URDF's ``<inertial>`` elements; None when the machine file does not state them.
    link_mass: NDArray | None = None
    link_com: NDArray | None = None
    mimic: tuple = ()
    joint_names: tuple | None = None
    #: URDF links along the chain (name, moving joint k it is fixed to (-1: base), orientation in that frame),
    #: from :attr:`bayescal.machines.urdf.UrdfChain.links`: the bodies a sensor may be named after
    link_bodies: tuple = ()

    def __post_init__(self) -> None:
        m = len(self.joint_type)
        self._set_mimic(m)
        for key, arr in (("origin", self.origin), ("rpy", self.rpy), ("axis", self.axis)):
            object.__setattr__(self, key, np.asarray(arr, dtype=float).reshape(m, 3))
        object.__setattr__(self, "axis", self.axis / np.linalg.norm(self.axis, axis=1, keepdims=True))
        object.__setattr__(self, "tool_point", np.asarray(self.tool_point, dtype=float).reshape(3))
        object.__setattr__(self, "tool_rpy", np.asarray(self.tool_rpy, dtype=float).reshape(3))
        object.__setattr__(self, "_tilt", tuple(tilt_axes(a) for a in self.axis))
        revolute = np.array([jt == "revolute" for jt in self.joint_type], dtype=bool)[None, :, None]  # (1, m, 1)
        revolute.setflags(write=False)
        object.__setattr__(self, "_revolute", revolute)
        object.__setattr__(self, "_all_revolute", bool(revolute.all()))
        # every axis's tilt directions (m, 3, 2), as tilted_direction forms them: the chain tilts all axes at once
        object.__setattr__(self, "_tilt_g", np.array([[_cross_basis(t[0], a), _cross_basis(t[1], a)] for a, t in
                                                      zip(self.axis, self._tilt)]).reshape(m, 2, 3).swapaxes(1, 2))
        specs = []
        for i, jt in enumerate(self.joint_type):
            j = f"joint{i + 1}"
            if jt == "revolute":
                specs.append(ParamSpec(f"{j}.offset", "rad", "offset_angle"))
            else:
                specs.append(ParamSpec(f"{j}.offset", "mm", "offset_length"))
            specs += [ParamSpec(f"{j}.axis.tilt_{_XYZ[k]}", "rad", "axis") for k in self._tilt[i]]
            specs += [ParamSpec(f"{j}.origin.{x}", "mm", "origin") for x in _XYZ]
            specs += [ParamSpec(f"{j}.rpy.{x}", "rad", "rpy") for x in _RPY]
        specs += [ParamSpec(f"tool.point.{x}", "mm", "tool_point") for x in _XYZ]
        specs += [ParamSpec(f"tool.rpy.{x}", "rad", "tool_rpy") for x in _RPY]
        object.__setattr__(self, "layout", ParamLayout(tuple(specs)))
        object.__setattr__(self, "tolerance", tolerance_vector(specs, self.tolerance_groups))

    def _set_mimic(self, m: int) -> None:
        """Check the mimic entries and build the joint positions' map ``q_joint = A q + b`` from the actuators."""
        mimic = tuple(self.mimic) or (None,) * m
        if len(mimic) != m:
            raise InputError(f"mimic: expected one entry per joint ({m}), got {len(mimic)}")
        mimic = tuple(None if x is None else (x[0], float(x[1]), float(x[2])) for x in mimic)
        for i in range(m):
            if (why := mimic_problem(mimic, i)) is not None:
                raise InputError(f"mimic: {why}")
        mimic = tuple(None if x is None else (int(x[0]), x[1], x[2]) for x in mimic)
        act = [i for i in range(m) if mimic[i] is None]
        A, b = np.zeros((m, len(act))), np.zeros(m)
        for i in range(m):
            if mimic[i] is None:
                A[i, act.index(i)] = 1.0
            else:
                A[i, act.index(mimic[i][0])], b[i] = mimic[i][1], mimic[i][2]
        if self.joint_names is not None:
            names = tuple(self.joint_names)
            if len(names) != m or len(set(names)) != m or not all(isinstance(x, str) and x for x in names):
                raise InputError(f"joint_names: expected {m} distinct non-empty names, got {names!r}")
            object.__setattr__(self, "joint_names", names)
        object.__setattr__(self, "mimic", mimic)
        object.__setattr__(self, "_actuated", tuple(act))
        object.__setattr__(self, "_q_map", A)
        object.__setattr__(self, "_q_shift", b)

    # ----------------------------------------------------------------- set-up
    @property
    def n_joints(self) -> int:
        """Moving joints, mimic joints included."""
        return len(self.joint_type)

    @property
    def serial_chain(self) -> "Serial":
        """The chain itself."""
        return self

    @property
    def n_actuators(self) -> int:
        """Non-mimic joints: one actuator (one ``q`` column) each."""
        return len(self._actuated)

    @property
    def actuated_joints(self) -> tuple[int, ...]:
        """The joint (0-based) of each actuator, in actuator order."""
        return self._actuated

    @property
    def actuator_units(self) -> tuple[str, ...]:
        return tuple("rad" if self.joint_type[i] == "revolute" else "mm" for i in self._actuated)

    def joint_positions(self, q: ArrayLike) -> NDArray:
        """Every joint's position (mimic joints included) for actuator positions ``q``.

        Parameters
        ----------
        q : array_like, shape (n_poses, n_actuators)
            Actuator positions, rad or mm.

        Returns
        -------
        ndarray, shape (n_poses, n_joints)
            rad (revolute) or mm (prismatic); a mimic joint's is ``multiplier * q_driver + offset``.
        """
        return self.check_q(q) @ self._q_map.T + self._q_shift

    @property
    def weight_body_names(self) -> tuple[str, ...]:
        """``link1`` ... ``link<m>``: link ``k`` is what joint ``k`` moves up to joint ``k + 1`` (the last one carries the tool).

        One link per joint, mimic joints included; each link's velocity per
        actuator sums the motions of the joints that actuator drives.
        """
        return tuple(f"link{k + 1}" for k in range(self.n_joints))

    @property
    def body_inertials(self) -> BodyInertials | None:
        """The links' masses and centres of mass read from the URDF's ``<inertial>`` elements, or None."""
        if self.link_mass is None:
            return None
        return BodyInertials(np.asarray(self.link_mass, float), np.asarray(self.link_com, float).reshape(-1, 3),
                             f"{self.source} (URDF <inertial>)")

    @classmethod
    def from_toml(cls, doc: TomlTable, path: str) -> "Serial":
        """Read ``[[joint]]`` tables, or ``urdf``/``base_link``/``tip_link`` standing in for them."""
        doc.reject_unknown(
            {"kind", "name", "joint", "body", "urdf", "base_link", "tip_link", "tool", "measurement", "workspace",
             "tolerance"}
        )
        limits = None
        if doc.has("urdf"):
            for k in ("joint", "body"):
                if doc.has(k):
                    raise doc.error(k, f"[[{k}]] tables and urdf are both given; the URDF's joints and links stand for them")
            urdf = doc.string("urdf")
            urdf_path = Path(urdf) if Path(urdf).is_absolute() else Path(path).parent / urdf
            chain = chain_from_urdf(urdf_path, doc.string("base_link"), doc.string("tip_link"), path=path)
            types, origin, rpy, axis = chain.joint_type, chain.origin, chain.rpy, chain.axis
            tail, limits, mimic, names = chain.tail, chain.q_limits, chain.mimic, chain.names
            inertial = (chain.link_mass, chain.link_com) if chain.link_mass is not None else (None, None)
            links = chain.links
        else:
            for k in ("base_link", "tip_link"):
                if doc.has(k):
                    raise doc.error(k, "only allowed together with urdf = \"...\"")
            joints = doc.array_of_tables("joint")
            types, origin, rpy, axis, mimic, names = _read_joint_tables(joints)
            inertial = _read_inertials(joints)
            links = _read_bodies(doc, len(joints))
            tail = None
        tool = doc.table("tool")
        tool.reject_unknown({"point", "rpy"})
        tp, tr = tool.vector("point"), tool.vector("rpy", default=np.zeros(3))
        if tail is not None:
            # fixed joints between the last moving joint and tip_link: the tool given in
            # tip_link's frame is carried into the last moving joint's frame
            R_tail, p_tail = tail
            tp, tr = p_tail + R_tail @ tp, rpy_from_matrix(R_tail @ rpy_matrix(tr))
        q_limits = read_q_limits(doc, sum(x is None for x in mimic))  # one row per actuator: mimic joints have none
        if q_limits is None and limits is not None:
            q_limits = limits
        return cls(
            joint_type=tuple(types), origin=np.array(origin), rpy=np.array(rpy), axis=np.array(axis),
            tool_point=tp, tool_rpy=tr, name=doc.string("name", "serial chain"), noise=read_noise(doc),
            q_limits=q_limits, tolerance_groups=read_tolerance(doc, SERIAL_TOLERANCE_DEFAULTS), source=path,
            link_mass=inertial[0], link_com=inertial[1], mimic=tuple(mimic), joint_names=names, link_bodies=links,
        )

    def geometry_arrays(self, theta: ArrayLike | None = None) -> dict[str, NDArray]:
        """The machine-file arrays of ``nominal + theta`` with the zero offsets folded in (theta of shape (P,))."""
        th = self.check_theta(theta)
        m = self.n_joints
        tj = th[: _PER_JOINT * m].reshape(m, _PER_JOINT)
        origin = self.origin + tj[:, 3:6]
        rpy = self.rpy + tj[:, 6:9]
        axis = np.array([tilted_direction(self.axis[i], self._tilt[i], tj[i, 1:3])[0] for i in range(m)])
        for i in range(m):
            # M(q + d) = M(d) M(q): a zero offset becomes part of the fixed transform
            if self.joint_type[i] == "revolute":
                rpy[i] = rpy_from_matrix(rpy_matrix(rpy[i]) @ so3_exp(axis[i] * tj[i, 0]))
            else:
                origin[i] = origin[i] + rpy_matrix(rpy[i]) @ axis[i] * tj[i, 0]
        return {
            "origin": origin, "rpy": rpy, "axis": axis,
            "tool_point": self.tool_point + th[_PER_JOINT * m : _PER_JOINT * m + 3],
            "tool_rpy": self.tool_rpy + th[_PER_JOINT * m + 3 :],
        }

    # ------------------------------------------------------------ kinematics
    def _chain(self, q: NDArray, theta: NDArray) -> _Chain:
        """The chain's frames for actuator positions ``q`` (n, N); mimic joints follow their drivers.

        ``theta`` of shape (P,) (one geometry for every pose, the usual case) or
        (n, P).  A shared geometry's fixed transforms, axes and tool are computed
        once, with a leading axis of length 1 that broadcasts against the poses'.
        """
        n, m = q.shape[0], self.n_joints
        th = theta[None] if theta.ndim == 1 else theta  # (g, P), g = 1 (shared) or n
        g = th.shape[0]
        tj = th[:, : _PER_JOINT * m].reshape(g, m, _PER_JOINT)
        ttool = th[:, _PER_JOINT * m :]
        origin = self.origin[None] + tj[:, :, 3:6]
        # the joints' rpy and the tool's in one array: one rpy_matrix call for all (elementwise, the same values)
        rpy_all = np.empty((g, m + 1, 3))
        np.add(self.rpy[None], tj[:, :, 6:9], out=rpy_all[:, :m])
        np.add(self.tool_rpy[None], ttool[:, 3:], out=rpy_all[:, m])
        rpy, tool_rpy = rpy_all[:, :m], rpy_all[:, m]
        blocks = geometry_blocks(th)
        if blocks is None:
            axis, daxis = _tilted_axes(self.axis, self._tilt_g, tj[:, :, 1:3])
            R_all = rpy_matrix(rpy_all)
        else:  # a sampler's walkers, each repeated over every pose: the geometry's rotations once per walker
            first, runs = blocks
            axis, daxis = (np.repeat(a, runs, axis=0) for a in _tilted_axes(self.axis, self._tilt_g, tj[first, :, 1:3]))
            R_all = np.repeat(rpy_matrix(rpy_all[first]), runs, axis=0)
        qe = q @ self._q_map.T + self._q_shift + tj[:, :, 0]
        R_fix = R_all[:, :m]
        R_parent = np.empty((n, m, 3, 3))
        R_joint = np.empty((n, m, 3, 3))
        p_joint = np.empty((n, m, 3))
        R_after = np.empty((n, m, 3, 3))
        p_after = np.empty((n, m, 3))
        R = np.broadcast_to(np.eye(3), (n, 3, 3))
        p = np.zeros((n, 3))
        # every revolute joint's rotation in one call (elementwise, the same values as one joint at a time)
        R_q = so3_exp(axis * qe[:, :, None])
        # each product is written straight into the frame it is (out=: the same products, no copy after each)
        for k in range(m):
            p = np.add(p, _rotate(R, origin[:, k]), out=p_joint[:, k])
            R = np.matmul(R, R_fix[:, k], out=R_joint[:, k])
            if self.joint_type[k] == "revolute":
                R = np.matmul(R, R_q[:, k], out=R_after[:, k])
                p_after[:, k] = p
            else:
                p = np.add(p, _rotate(R, axis[:, k] * qe[:, k, None]), out=p_after[:, k])
                R_after[:, k] = R
        if m:
            R_parent[:, 0] = np.eye(3)
            R_parent[:, 1:] = R_after[:, :-1]  # the frame before joint k is the one after joint k - 1
        p_tool = p + _rotate(R, self.tool_point[None] + ttool[:, :3])
        return _Chain(
            R_parent=R_parent, R_joint=R_joint, p_joint=p_joint, rpy=rpy, axis=axis, daxis=daxis, qe=qe,
            R_end=R, R_after=R_after, p_after=p_after, tool_rpy=tool_rpy, p_tool=p_tool, R_tool=R @ R_all[:, m],
            rpy_all=rpy_all,
        )

    def _memo_chain(self, q: NDArray, theta: NDArray) -> _Chain:
        """:meth:`_chain`, remembered for the last ``(q, theta)``.

        A Gauss-Newton step evaluates the forward kinematics and then the
        Jacobian at the same point; recomputing the chain for the Jacobian was
        half the cost of identifying a serial arm.  The frames are kept
        read-only, so a consumer that writes into them fails loudly instead of
        corrupting the next answer.
        """
        hit = _CHAINS.get(self)
        if (hit is not None and hit[0].shape == q.shape and hit[1].shape == theta.shape
                and np.array_equal(hit[0], q) and np.array_equal(hit[1], theta)):
            return hit[2]
        c = self._chain(q, theta)
        if q.shape[0] * max(self.n_joints, 1) <= _MEMO_MAX:
            for name in _CHAIN_FIELDS:
                getattr(c, name).setflags(write=False)
            _CHAINS[self] = (q.copy(), theta.copy(), c)
        return c

    def forward(self, q: ArrayLike, theta: ArrayLike | None = None, *, guess: ToolPoses | None = None) -> ToolPoses:
        """Tool poses by the product of the joint transforms (closed form; ``guess`` is not needed).

        Parameters
        ----------
        q : array_like, shape (n_poses, n_actuators)
            Actuator positions (the non-mimic joints'), rad (revolute) or mm (prismatic).
        theta : array_like, shape (P,) or (n_poses, P), optional
            Geometric errors; zeros if omitted.

        Returns
        -------
        ToolPoses
            ``position`` the tool point (mm, base frame), ``rotation`` the tool
            frame's orientation; every pose succeeds.
        """
        q = self.check_q(q)
        n = q.shape[0]
        c = self._memo_chain(q, self.check_theta(theta, n))
        ok = np.isfinite(c.p_tool).all(axis=1) & np.isfinite(c.R_tool).all(axis=(1, 2))
        msgs = ("",) * n if ok.all() else tuple("" if o else "non-finite joint positions or geometry" for o in ok)
        return ToolPoses(position=c.p_tool.copy(), rotation=c.R_tool.copy(), success=ok, message=msgs, state=None)

    def _motion_columns(self, c: _Chain, k: int) -> tuple[NDArray, NDArray]:
        """Tool-point and rotation rates per unit of joint ``k``'s motion (its offset or q)."""
        a_base = _rotate(c.R_joint[:, k], c.axis[:, k])
        if self.joint_type[k] == "revolute":
            return _cross(a_base[:, :, None], (c.p_tool - c.p_joint[:, k]))[:, :, 0], a_base
        return a_base, np.zeros_like(a_base)

    def tool_jacobian(self, q: ArrayLike, theta: ArrayLike | None, poses: ToolPoses) -> NDArray:
        """Identification Jacobian, analytic (frame twists carried to the base frame).

        A perturbation of a factor of ``T_1 ... T_n T_tool`` is a twist of the
        frame it acts in: an origin change a translation along the parent
        frame's axes, an rpy change a rotation about ``Rz Ry e_x``, ``Rz e_y``,
        ``e_z`` of the parent frame through the joint origin, an offset the
        joint's own motion, an axis tilt ``J_l(q a) q da`` (revolute; ``J_l``
        the left Jacobian of SO(3)) or ``q da`` (prismatic).  A rotation ``w``
        about a point ``c`` moves the tool point by ``w x (p - c)``.
        A mimic joint's columns are those of its own motion: its offset
        moves it, whatever drives it.
        Returns shape (n_poses, 6, P); see :meth:`Machine.tool_jacobian`.
        """
        return self._tool_jacobian(q, theta, (True,) * len(_BLOCKS))

    def tool_jacobian_columns(self, q: ArrayLike, theta: ArrayLike | None, poses: ToolPoses,
                              columns: NDArray) -> NDArray:
        """:meth:`tool_jacobian`'s ``columns`` (increasing), computing only the blocks they fall in.

        The blocks (:data:`_BLOCKS`: every joint's offsets, axis tilts,
        origins or rpy, the tool's point or rpy) are independent: a block no
        column falls in is not computed (an arm's rpy, say, which the
        identifiable set of a 6-DOF fit usually leaves out).  The values are
        :meth:`tool_jacobian`'s, bit for bit.
        """
        columns = np.asarray(columns, dtype=int)
        t = _PER_JOINT * self.n_joints
        blocks = {_SLOT_BLOCK[k] for k in (columns[columns < t] % _PER_JOINT).tolist()}
        blocks.update(4 if k < 3 else 5 for k in (columns[columns >= t] - t).tolist())
        return self._tool_jacobian(q, theta, tuple(b in blocks for b in range(len(_BLOCKS))))[:, :, columns]

    def _tool_jacobian(self, q: ArrayLike, theta: ArrayLike | None, need: tuple[bool, ...]) -> NDArray:
        """:meth:`tool_jacobian` with the blocks :data:`_BLOCKS` that ``need`` leaves out zero (not computed)."""
        q = self.check_q(q)
        n, m = q.shape[0], self.n_joints
        c = self._memo_chain(q, self.check_theta(theta, n))
        J = np.zeros((n, 6, self.n_params))
        t = _PER_JOINT * m
        # every joint at once (the joints' columns do not depend on one another): a Python loop over the
        # joints of small (n, 3, 3) products cost more in numpy's per-call overhead than the arithmetic
        Jj = J[:, :, :t].reshape(n, 6, m, _PER_JOINT)  # a view: writes land in J
        rev = self._revolute  # (1, m, 1)
        arm = c.p_tool[:, None] - c.p_joint  # (n, m, 3)
        if need[0]:
            a_base = np.einsum("nkij,nkj->nki", c.R_joint, np.broadcast_to(c.axis, c.p_joint.shape))
            turn = _cross_joints(a_base[..., None], arm)[..., 0]
            # an arm of revolute joints only (the usual case) takes its columns as they are: np.where copies them
            if self._all_revolute:
                _put(Jj, 0, turn, a_base)
            else:
                _put(Jj, 0, np.where(rev, turn, a_base), np.where(rev, a_base, 0.0))
        if need[1]:
            tilt = c.daxis * c.qe[:, :, None, None]  # (n, m, 3, 2)
            w = c.R_joint @ left_jacobian(c.axis * c.qe[:, :, None]) @ tilt
            if self._all_revolute:
                _put(Jj, slice(1, 3), _cross_joints(w, arm), w)
            else:
                rev4 = rev[..., None]
                _put(Jj, slice(1, 3), np.where(rev4, _cross_joints(w, arm), c.R_joint @ tilt), np.where(rev4, w, 0.0))
        if need[2]:
            _put(Jj, slice(3, 6), c.R_parent, None)
        if need[3] or need[5]:
            W = rpy_rates(c.rpy_all)  # the joints' and the tool's in one call (elementwise, the same values)
        if need[3]:
            w = c.R_parent @ W[:, :m]  # rpy rates' columns in the parent frame
            _put(Jj, slice(6, 9), _cross_joints(w, arm), w)
        if need[4]:
            J[:, :3, t : t + 3] = c.R_end
        if need[5]:
            J[:, 3:, t + 3 : t + 6] = c.R_end @ W[:, m]
        return J

    def chain_frames(self, q: ArrayLike, theta: ArrayLike | None = None) -> ChainFrames:
        """Every joint's and link's frame at actuator positions ``q`` (n, N) and geometric errors ``theta`` (:class:`ChainFrames`)."""
        q = self.check_q(q)
        n = q.shape[0]
        c = self._memo_chain(q, self.check_theta(theta, n))
        # a shared geometry's axes come with a leading axis of 1 (the chain computes them once)
        axis = np.einsum("nkij,nkj->nki", c.R_joint, np.broadcast_to(c.axis, c.R_joint.shape[:-1]))
        nxt = np.concatenate([c.p_joint[:, 1:], c.p_tool[:, None]], axis=1)
        return ChainFrames(c.p_joint, axis, c.p_after, c.R_after, c.qe, nxt, c.p_tool)

    @property
    def sensor_bodies(self) -> tuple[str, ...]:
        """Bodies a sensor may be fixed to (docs/formats.md section 8): ``base``, ``joint1`` ... ``joint<m>``, URDF link names.

        ``joint<i>`` is the body joint ``i`` moves (the frame after its
        motion, the URDF child link of that joint).
        """
        names = ["base"] + [f"joint{k + 1}" for k in range(self.n_joints)]
        return tuple(names + [n for n, _, _ in self.link_bodies if n not in names])

    def body_frame(self, name: str) -> tuple[int, NDArray]:
        """The moving joint (0-based, -1: the base) whose frame body ``name`` is fixed to, and its orientation in that frame."""
        if name == "base":
            return -1, np.eye(3)
        if name.startswith("joint") and name[5:].isdigit() and 1 <= int(name[5:]) <= self.n_joints:
            return int(name[5:]) - 1, np.eye(3)
        for n, k, R in self.link_bodies:
            if n == name:
                return int(k), np.asarray(R, dtype=float)
        raise InputError(f"body {name!r}: expected one of {', '.join(self.sensor_bodies)}")

    def body_rotations(self, q: ArrayLike, theta: ArrayLike | None, frames: list) -> tuple[NDArray, NDArray]:
        """Orientations of bodies in the base frame and their small-rotation Jacobian.

        Parameters
        ----------
        q : array_like, shape (n, N)
        theta : array_like, shape (P,) or (n, P), optional
        frames : list of (int, ndarray (3, 3))
            Per body, :meth:`body_frame`'s joint index and fixed orientation.

        Returns
        -------
        R : ndarray, shape (n, S, 3, 3)
            Body orientation ``R_after[k] R_fixed`` (the identity on the base).
        J : ndarray, shape (n, S, 3, P)
            ``R(theta + d) = exp([J d]x) R(theta)`` (rad per parameter unit):
            joint ``j <= k`` turns the body by its motion (offset, axis tilt:
            as in :meth:`tool_jacobian`) and its fixed rpy; origins and the
            tool do not turn it.
        """
        q = self.check_q(q)
        n = q.shape[0]
        c = self._chain(q, self.check_theta(theta, n))
        W = rpy_rates(c.rpy)
        cols = np.zeros((n, self.n_joints, 3, self.n_params))  # link k's rotation columns, built base outward
        acc = np.zeros((n, 3, self.n_params))
        for j in range(self.n_joints):
            o = _PER_JOINT * j
            acc[:, :, o + 6 : o + 9] = c.R_parent[:, j] @ W[:, j]
            if self.joint_type[j] == "revolute":
                acc[:, :, o] = _rotate(c.R_joint[:, j], c.axis[:, j])
                Jl = left_jacobian(c.axis[:, j] * c.qe[:, j, None])
                acc[:, :, o + 1 : o + 3] = c.R_joint[:, j] @ Jl @ (c.daxis[:, j] * c.qe[:, j, None, None])
            cols[:, j] = acc
        R = np.empty((n, len(frames), 3, 3))
        J = np.zeros((n, len(frames), 3, self.n_params))
        for s, (k, R_fix) in enumerate(frames):
            R[:, s] = (np.eye(3) if k < 0 else c.R_after[:, k]) @ np.asarray(R_fix, dtype=float)
            if k >= 0:
                J[:, s] = cols[:, k]
        return R, J

    def body_actuator_jacobian(self, q: ArrayLike, theta: ArrayLike | None, frames: list) -> NDArray:
        """Small rotation of bodies per unit actuator position: ``R(q + dq) = exp([J dq]x) R(q)``.

        Parameters
        ----------
        q : array_like, shape (n, N)
        theta : array_like, shape (P,) or (n, P), optional
        frames : list of (int, ndarray (3, 3))
            Per body, :meth:`body_frame`'s joint index and fixed orientation.

        Returns
        -------
        ndarray, shape (n, S, 3, N)
            rad per actuator unit: a revolute joint ``j <= k`` turns the body
            of joint ``k`` about its base-frame axis, a prismatic one does not;
            per actuator the joints' columns are summed through the mimic map.
        """
        q = self.check_q(q)
        n, m = q.shape[0], self.n_joints
        c = self._memo_chain(q, self.check_theta(theta, n))
        acc = np.zeros((n, m, 3, m))  # joint k's body: the axes of the revolute joints up to k
        for j in range(m):
            if self.joint_type[j] == "revolute":
                acc[:, j:, :, j] = _rotate(c.R_joint[:, j], c.axis[:, j])[:, None, :]
        J = np.zeros((n, len(frames), 3, m))
        for s, (k, _) in enumerate(frames):
            if k >= 0:
                J[:, s] = acc[:, k]
        return J @ self._q_map

    def weight_bodies(self, q: ArrayLike, theta: ArrayLike | None, poses: ToolPoses) -> WeightBodies:
        """Every moving link: link ``k`` in the frame after joint ``k``, moved by joints ``1 .. k`` (joint twists).

        Joint ``j <= k`` turns link ``k`` about its base-frame axis ``a_j``
        through the joint origin ``o_j`` (``v = a_j x (x_k - o_j)``, ``w =
        a_j``) or slides it along ``a_j`` (``v = a_j``, ``w = 0``); joints
        beyond ``k`` do not move it.  Per actuator the joints' columns are
        summed through the mimic map (a driver moves its mimic joints by
        ``multiplier`` per unit).
        """
        q = self.check_q(q)
        n, m = q.shape[0], self.n_joints
        c = self._memo_chain(q, self.check_theta(theta, n))
        J = np.zeros((n, m, 6, m))
        for j in range(m):
            a = _rotate(c.R_joint[:, j], c.axis[:, j])  # (n, 3) base frame
            for k in range(j, m):
                if self.joint_type[j] == "revolute":
                    J[:, k, :3, j] = _cross(a[:, :, None], c.p_after[:, k] - c.p_joint[:, j])[:, :, 0]
                    J[:, k, 3:, j] = a
                else:
                    J[:, k, :3, j] = a
        return WeightBodies(c.p_after, c.R_after, J @ self._q_map, self.weight_body_names)

    def actuator_jacobian(self, q: ArrayLike, theta: ArrayLike | None, poses: ToolPoses) -> NDArray:
        """Tool-pose derivative with respect to the actuator positions, analytic (the joint twists).

        Shape (n_poses, 6, n_actuators): each joint's twist, summed per actuator through the mimic map.
        """
        q = self.check_q(q)
        n, m = q.shape[0], self.n_joints
        c = self._memo_chain(q, self.check_theta(theta, n))
        J = np.empty((n, 6, m))
        for k in range(m):
            J[:, :3, k], J[:, 3:, k] = self._motion_columns(c, k)
        return J @ self._q_map

    # ------------------------------------------------------------------ output
    def to_toml(self, theta: ArrayLike | None = None) -> str:
        """Machine file of ``nominal + theta`` as ``[[joint]]`` tables (zero offsets folded into rpy/origin).

        A chain read from a URDF file is written out as ``[[joint]]`` tables
        (fixed joints already folded in, the URDF joint names kept as
        ``name``, its links' weights as ``mass`` and ``com``, its link names
        as ``[[body]]`` tables for the sensors named after them), so the file stands alone.  Mimic joints keep ``mimic``,
        ``multiplier`` and ``offset``; their zero offsets are folded like any
        joint's.
        """
        g = self.geometry_arrays(theta)
        f = format_toml_value
        out = ['kind = "serial"', f"name = {f(self.name)}", ""]
        for i, t in enumerate(self.joint_type):
            out += ["[[joint]]"] + ([f"name = {f(self.joint_names[i])}"] if self.joint_names is not None else [])
            out += [f'type = "{t}"', f"origin = {f(g['origin'][i])}", f"rpy = {f(g['rpy'][i])}", f"axis = {f(g['axis'][i])}"]
            if self.mimic[i] is not None:
                d, k, o = self.mimic[i]
                out += [f"mimic = {d + 1}", f"multiplier = {f(k)}", f"offset = {f(o)}"]
            if self.link_mass is not None:
                out += [f"mass = {f(float(self.link_mass[i]))}", f"com = {f(np.asarray(self.link_com)[i])}"]
            out.append("")
        for name, k, R in self.link_bodies:
            if name not in ("base", *(f"joint{j + 1}" for j in range(self.n_joints))):
                out += ["[[body]]", f"name = {f(name)}", f"joint = {k + 1}", f"rpy = {f(rpy_from_matrix(R))}", ""]
        out += ["[tool]", f"point = {f(g['tool_point'])}", f"rpy = {f(g['tool_rpy'])}", ""]
        return "\n".join(out) + common_toml(self, self.tolerance_groups)
