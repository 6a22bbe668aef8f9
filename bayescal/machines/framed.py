"""A machine seen from an instrument's frame: the rigid transform between base and instrument.

A laser tracker, CMM or motion-capture system measures in its own frame.
:class:`InstrumentFrame` wraps any machine so that its tool poses come out
in that frame,

    p_inst = R^T (p_base - o),      R_inst = R^T R_base,

where ``(o, R)`` is the pose of the instrument frame in the base frame
(``p_base = R p_inst + o``, the ``[instrument]`` table of FORMATS.md
section 4).  With ``fit=True`` the frame is six more parameters placed
*first* in the layout: ``frame.origin.x/y/z`` (mm) and
``frame.rotation_vector.x/y/z`` (rad), a small correction of a start frame
``frame0``,

    o = o0 + d_o,      R = exp([d_phi]x) R0.

Every consumer (solvers, filters, samplers, planning, diagnosis) then sees
the frame as six more columns of the Jacobian.  Placing them first makes
the greedy identifiability analysis keep the frame and report the
machine's own base parameters that share its gauge (a common shift of all
rail origins, ...) as the unidentifiable combinations, by name.

"No tolerance prior": the frame parameters get the tolerances
:data:`FRAME_TOLERANCE` (100 mm and 0.1 rad around the closed-form start,
which is within about a millimetre and a milliradian), so wide that the
MAP, Kalman and MCMC answers do not depend on them (a test multiplies them
by 10 and compares).  They are not made strictly flat because every
consumer of the layout's tolerance (ridge, evidence, Kalman initial
covariance, MCMC prior, planning criteria) would need a special case.  Not
wider either: the columns are scaled by the tolerances, and a frame column
scaled by 1 m raises the condition number of the scaled matrix by 1e4 or
more, towards least squares' rank-deficiency threshold (1e-10).

With ``fit=False`` the frame is known (read from a machine file's
``[instrument]`` table) and adds no parameters.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial.transform import Rotation

from ..errors import InputError, MachineFileError
from ..geometry import left_jacobian_inverse, skew, so3_exp
from ..io.machine_file import format_toml_value
from ..params import ParamLayout, ParamSpec
from .base import Machine, ToolPoses

__all__ = ["Frame", "InstrumentFrame", "FRAME_NAMES", "FRAME_TOLERANCE", "base_machine", "instrument_toml"]

#: The frame parameters, in layout order (first in a fitted frame's layout).
FRAME_NAMES = (
    "frame.origin.x", "frame.origin.y", "frame.origin.z",
    "frame.rotation_vector.x", "frame.rotation_vector.y", "frame.rotation_vector.z",
)
#: One-sigma "tolerance" of the frame correction about its start: mm for the origin, rad for the rotation.
#: Wide enough to be flat (see the module docstring).
FRAME_TOLERANCE = {"frame_origin": 100.0, "frame_rotation": 0.1}


@dataclass(frozen=True)
class Frame:
    """Pose of the instrument frame in the base frame: ``p_base = rotation p_inst + origin``.

    Attributes
    ----------
    origin : ndarray, shape (3,)
        mm.
    rotation : ndarray, shape (3, 3)
        ``R_base_instrument``.
    """

    origin: NDArray
    rotation: NDArray

    @classmethod
    def identity(cls) -> "Frame":
        return cls(np.zeros(3), np.eye(3))

    @classmethod
    def from_rotation_vector(cls, origin: ArrayLike, rotation_vector: ArrayLike) -> "Frame":
        return cls(np.asarray(origin, dtype=float).reshape(3), Rotation.from_rotvec(np.asarray(rotation_vector, dtype=float)).as_matrix())

    @property
    def rotation_vector(self) -> NDArray:
        """Rotation vector of ``rotation`` (rad, norm in [0, pi]), valid up to 180 degrees."""
        return Rotation.from_matrix(self.rotation).as_rotvec()

    def to_base(self, p_inst: NDArray) -> NDArray:
        """Points (n, 3) from the instrument frame to the base frame, mm."""
        return np.asarray(p_inst) @ self.rotation.T + self.origin

    def to_instrument(self, p_base: NDArray) -> NDArray:
        """Points (n, 3) from the base frame to the instrument frame, mm."""
        return (np.asarray(p_base) - self.origin) @ self.rotation


def instrument_toml(frame: Frame) -> str:
    """The ``[instrument]`` table of a machine file (FORMATS.md section 4)."""
    f = format_toml_value
    return "\n".join(
        ["[instrument]", f"origin = {f(frame.origin)}", f"rotation_vector = {f(frame.rotation_vector)}", ""]
    )


def _frame_layout() -> ParamLayout:
    groups = ["frame_origin"] * 3 + ["frame_rotation"] * 3
    units = ["mm"] * 3 + ["rad"] * 3
    return ParamLayout(tuple(ParamSpec(n, u, g) for n, u, g in zip(FRAME_NAMES, units, groups)))


def _left_jacobian(phi: NDArray) -> NDArray:
    """Left Jacobian of SO(3), (..., 3, 3): ``exp(phi + e) = exp(J_l(phi) e) exp(phi)`` to first order."""
    return np.linalg.inv(left_jacobian_inverse(phi))


@dataclass(frozen=True, eq=False)
class InstrumentFrame(Machine):
    """``machine`` measured in an instrument frame (fitted or known).

    Parameters
    ----------
    machine : Machine
        The machine in its base frame.
    frame0 : Frame
        The instrument frame (``fit=False``) or the start of its fit.
    fit : bool
        True: six frame parameters first in the layout (see the module
        docstring); False: a fixed, known frame without parameters.
    frame_tolerance : dict, optional
        ``{"frame_origin": mm, "frame_rotation": rad}``; default
        :data:`FRAME_TOLERANCE`.

    Notes
    -----
    ``ToolPoses.state`` is the inner machine's state (for warm starts and
    for effects that need the pose in the base frame); base-frame poses are
    recovered with :meth:`to_base_poses`.
    """

    machine: Machine
    frame0: Frame = field(default_factory=Frame.identity)
    fit: bool = True
    frame_tolerance: dict | None = None

    def __post_init__(self) -> None:
        if isinstance(self.machine, InstrumentFrame):
            raise InputError("InstrumentFrame: the machine already has an instrument frame; wrap its base machine")

    # ----------------------------------------------------------- delegation
    @property
    def kind(self) -> str:  # type: ignore[override]
        return self.machine.kind

    @property
    def name(self) -> str:  # type: ignore[override]
        return self.machine.name

    @property
    def source(self) -> str:  # type: ignore[override]
        return self.machine.source

    @property
    def noise(self):  # type: ignore[override]
        return self.machine.noise

    @property
    def q_limits(self):  # type: ignore[override]
        return self.machine.q_limits

    @property
    def n_actuators(self) -> int:
        return self.machine.n_actuators

    @property
    def actuator_units(self) -> tuple[str, ...]:
        return self.machine.actuator_units

    @property
    def actuator_box_reachable(self) -> bool:
        return self.machine.actuator_box_reachable

    @property
    def effects(self) -> tuple:  # type: ignore[override]
        """The inner machine's stored effects: they act on the actuators, whatever frame measures the tool."""
        return self.machine.effects

    def with_effects(self, effects) -> "InstrumentFrame":
        from dataclasses import replace

        return replace(self, machine=self.machine.with_effects(effects))

    @property
    def n_frame(self) -> int:
        """Number of frame parameters: 6 when fitted, 0 when known."""
        return 6 if self.fit else 0

    @property
    def geometry_part(self) -> tuple[Machine, NDArray]:
        """The inner machine and the indices of its parameters (after the frame's, when fitted)."""
        return self.machine, np.arange(self.n_frame, self.n_params)

    @property
    def layout(self) -> ParamLayout:  # type: ignore[override]
        return _frame_layout() + self.machine.layout if self.fit else self.machine.layout

    @property
    def tolerance(self) -> NDArray:  # type: ignore[override]
        if not self.fit:
            return self.machine.tolerance
        t = dict(FRAME_TOLERANCE, **(self.frame_tolerance or {}))
        return np.concatenate([[t["frame_origin"]] * 3, [t["frame_rotation"]] * 3, self.machine.tolerance])

    def __getattr__(self, name):
        # kind-specific attributes (tolerance_groups, pose_range, ...) are the inner machine's
        if name.startswith("__") or name in ("machine", "frame0", "fit", "frame_tolerance"):
            raise AttributeError(name)
        return getattr(self.machine, name)

    def compatible_q(self, q: ArrayLike, theta: ArrayLike | None = None) -> NDArray:
        """The inner machine's :meth:`Machine.compatible_q` (the frame does not couple actuators)."""
        return self.machine.compatible_q(q, None if theta is None else self.split(theta)[1])

    # --------------------------------------------------------------- frame
    def split(self, theta: ArrayLike | None, n_poses: int | None = None) -> tuple[NDArray, NDArray]:
        """``(frame correction (..., 6), machine errors (..., P_machine))`` of ``theta``."""
        th = self.check_theta(theta, n_poses)
        k = self.n_frame
        return th[..., :k], th[..., k:]

    def frame_at(self, theta: ArrayLike | None = None) -> Frame:
        """The instrument frame at parameters ``theta`` (P,): ``frame0`` with the correction applied."""
        th = self.check_theta(theta)
        if th.ndim != 1:
            raise InputError("frame_at: expected one parameter vector (P,)")
        o, R = self._frame_arrays(th[: self.n_frame])
        return Frame(o, R)

    def _frame_arrays(self, tf: NDArray) -> tuple[NDArray, NDArray]:
        """Origin (..., 3) and rotation (..., 3, 3) for frame corrections (..., 6) (or none)."""
        if not self.fit:
            return self.frame0.origin, self.frame0.rotation
        return self.frame0.origin + tf[..., :3], so3_exp(tf[..., 3:]) @ self.frame0.rotation

    def to_base_poses(self, poses: ToolPoses, theta: ArrayLike | None) -> ToolPoses:
        """The same poses in the base frame (``p_base = R p_inst + o``), state kept."""
        tf, _ = self.split(theta, poses.position.shape[0] if np.ndim(theta) == 2 else None)
        o, R = self._frame_arrays(tf)
        p = np.einsum("...ij,...j->...i", R, poses.position) + o
        Rb = R @ poses.rotation
        return ToolPoses(p, Rb, poses.success, poses.message, poses.state)

    def _to_instrument(self, poses: ToolPoses, o: NDArray, R: NDArray) -> ToolPoses:
        Rt = np.swapaxes(R, -1, -2)
        p = np.einsum("...ij,...j->...i", Rt, poses.position - o)
        return ToolPoses(p, Rt @ poses.rotation, poses.success, poses.message, poses.state)

    # ------------------------------------------------------------- contract
    def forward(self, q: ArrayLike, theta: ArrayLike | None = None, *, guess: ToolPoses | None = None) -> ToolPoses:
        """Tool poses in the instrument frame; ``state`` is the inner machine's."""
        q = self.check_q(q)
        tf, tm = self.split(theta, q.shape[0] if np.ndim(theta) == 2 else None)
        g = None
        if guess is not None:
            # the inner kinds warm-start from guess.state; the pose is handed over in base coordinates
            g = ToolPoses(guess.position, guess.rotation, guess.success, guess.message, guess.state)
        poses = self.machine.forward(q, tm, guess=g)
        o, R = self._frame_arrays(tf)
        return self._to_instrument(poses, o, R)

    def tool_jacobian(self, q: ArrayLike, theta: ArrayLike | None, poses: ToolPoses) -> NDArray:
        """``(n, 6, P)``: the frame columns first, then the machine's rotated into the instrument frame.

        With ``R = exp([d_phi]x) R0`` and a perturbation ``e`` of ``d_phi``,
        ``R -> exp([J_l(d_phi) e]x) R``, so
        ``dp_inst/d(d_o) = -R^T``, ``dp_inst/de = R^T [p_base - o]x J_l``,
        ``dw_inst/de = -R^T J_l`` (``w``: small rotation in the instrument frame).
        """
        q = self.check_q(q)
        n = q.shape[0]
        tf, tm = self.split(theta, n if np.ndim(theta) == 2 else None)
        o, R = self._frame_arrays(tf)
        base = self.to_base_poses(poses, theta)
        Jm = self.machine.tool_jacobian(q, tm, base)
        Rt = np.broadcast_to(np.swapaxes(R, -1, -2), (n, 3, 3))
        J = np.empty((n, 6, self.n_params))
        k = self.n_frame
        J[:, :3, k:] = Rt @ Jm[:, :3]
        J[:, 3:, k:] = Rt @ Jm[:, 3:]
        if self.fit:
            Jl = np.broadcast_to(_left_jacobian(tf[..., 3:]), (n, 3, 3))
            J[:, :3, :3] = -Rt
            J[:, :3, 3:6] = Rt @ skew(base.position - o) @ Jl
            J[:, 3:, :3] = 0.0
            J[:, 3:, 3:6] = -Rt @ Jl
        return J

    def actuator_jacobian(self, q: ArrayLike, theta: ArrayLike | None, poses: ToolPoses) -> NDArray:
        """The inner machine's actuator Jacobian rotated into the instrument frame, (n, 6, n_actuators)."""
        q = self.check_q(q)
        tf, tm = self.split(theta, q.shape[0] if np.ndim(theta) == 2 else None)
        _, R = self._frame_arrays(tf)
        Ja = self.machine.actuator_jacobian(q, tm, self.to_base_poses(poses, theta))
        Rt = np.swapaxes(R, -1, -2)
        return np.concatenate([Rt @ Ja[:, :3], Rt @ Ja[:, 3:]], axis=1)

    @property
    def weight_body_names(self) -> tuple[str, ...]:
        return self.machine.weight_body_names

    @property
    def body_inertials(self):
        return self.machine.body_inertials

    def weight_bodies(self, q: ArrayLike, theta: ArrayLike | None, poses: ToolPoses):
        """The inner machine's weight bodies, in the base frame (gravity is stated in the base frame, not the instrument's)."""
        q = self.check_q(q)
        _, tm = self.split(theta, q.shape[0] if np.ndim(theta) == 2 else None)
        return self.machine.weight_bodies(q, tm, self.to_base_poses(poses, theta))

    def guess_from_measurement(self, q, position, rotation=None, axis=None):
        """The inner machine's start from the measurement taken to the base frame with ``frame0``."""
        f = self.frame0
        pb = f.to_base(position)
        Rb = None if rotation is None else f.rotation @ rotation
        ab = None if axis is None else axis @ f.rotation.T
        g = self.machine.guess_from_measurement(q, pb, Rb, ab)
        if g is None:
            return None
        return self._to_instrument(g, f.origin, f.rotation)

    def to_toml(self, theta: ArrayLike | None = None) -> str:
        """The inner machine's file of ``nominal + theta`` (base frame) plus the ``[instrument]`` table."""
        th = self.check_theta(theta)
        text = self.machine.to_toml(th[self.n_frame :])
        return text.rstrip("\n") + "\n\n" + instrument_toml(self.frame_at(th))

    @classmethod
    def from_toml(cls, table, path: str) -> "InstrumentFrame":
        raise MachineFileError(path, "instrument", "read through bayescal.machines.load_machine")


def base_machine(machine: Machine) -> Machine:
    """The machine in its base frame (the inner machine of an :class:`InstrumentFrame`)."""
    return machine.machine if isinstance(machine, InstrumentFrame) else machine


def read_instrument(doc, path: str) -> Frame | None:
    """The optional ``[instrument]`` table: ``origin`` (mm) and ``rotation_vector`` (rad)."""
    t = doc.table("instrument", required=False)
    if t is None:
        return None
    t.reject_unknown({"origin", "rotation_vector"})
    rv = t.vector("rotation_vector", default=[0.0, 0.0, 0.0])
    if np.linalg.norm(rv) > np.pi + 1e-9:
        raise t.error("rotation_vector", f"norm {np.linalg.norm(rv):.6g} above pi; expected radians (axis times angle, angle <= pi)")
    return Frame.from_rotation_vector(t.vector("origin", default=[0.0, 0.0, 0.0]), rv)
