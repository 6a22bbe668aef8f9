"""A machine seen from an instrument's frame: the rigid transform between base and instrument.

A laser tracker, CMM or motion-capture system measures in its own frame.
:class:`InstrumentFrame` wraps any machine so that its tool poses come out
in that frame,

    p_inst = R^T (p_base - o),      R_inst = R^T R_base,

where ``(o, R)`` is the pose of the instrument frame in the base frame
(``p_base = R p_inst + o``, the ``[instrument]`` table of docs/formats.md
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

**Stations** (docs/formats.md section 8).  A recording may come from several
set-ups of the instrument (a tracker moved to see another part of the
workspace, another day's session): ``stations`` names them and every
station has its own frame, six parameters each,
``frame.<station>.origin.x`` ... (with one station the names stay
``frame.origin.x`` ...).  Which station measured which pose is bound to the
poses the machine is evaluated on (``pose_station``, one index per pose;
:meth:`for_poses` rebinds it for a subset), so ``forward`` and
``tool_jacobian`` give each pose its own station's frame and the columns of
the other stations' frames are zero.  One geometry is shared by all.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..errors import InputError, MachineFileError
from ..geometry import left_jacobian, skew, so3_exp, so3_log
from ..io.machine_file import format_toml_value
from ..params import ParamLayout, ParamSpec
from .base import Machine, ToolPoses, geometry_blocks
from .view import Forwarded, MachineView

__all__ = ["Frame", "InstrumentFrame", "FRAME_NAMES", "FRAME_TOLERANCE", "instrument_toml",
           "frame_names", "is_frame_parameter"]

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
        return cls(np.asarray(origin, dtype=float).reshape(3), so3_exp(np.asarray(rotation_vector, dtype=float).reshape(3)))

    @property
    def rotation_vector(self) -> NDArray:
        """Rotation vector of ``rotation`` (rad, norm in [0, pi]), valid up to 180 degrees."""
        return so3_log(self.rotation)

    def to_base(self, p_inst: NDArray) -> NDArray:
        """Points (n, 3) from the instrument frame to the base frame, mm."""
        return np.asarray(p_inst) @ self.rotation.T + self.origin

    def to_instrument(self, p_base: NDArray) -> NDArray:
        """Points (n, 3) from the base frame to the instrument frame, mm."""
        return (np.asarray(p_base) - self.origin) @ self.rotation


def instrument_toml(frame: Frame) -> str:
    """The ``[instrument]`` table of a machine file (docs/formats.md section 4)."""
    f = format_toml_value
    return "\n".join(
        ["[instrument]", f"origin = {f(frame.origin)}", f"rotation_vector = {f(frame.rotation_vector)}", ""]
    )


def frame_names(stations: tuple[str, ...] = ("",)) -> tuple[str, ...]:
    """The frame parameters of ``stations``: :data:`FRAME_NAMES` for one, ``frame.<station>.origin.x`` ... for several."""
    if len(stations) == 1:
        return FRAME_NAMES
    return tuple(n.replace("frame.", f"frame.{s}.", 1) for s in stations for n in FRAME_NAMES)


def is_frame_parameter(name: str) -> bool:
    """Whether a parameter name is an instrument frame's (one station's or several's)."""
    return name.startswith("frame.")


def _frame_layout(stations: tuple[str, ...] = ("",)) -> ParamLayout:
    groups = (["frame_origin"] * 3 + ["frame_rotation"] * 3) * len(stations)
    units = (["mm"] * 3 + ["rad"] * 3) * len(stations)
    return ParamLayout(tuple(ParamSpec(n, u, g) for n, u, g in zip(frame_names(stations), units, groups)))


@dataclass(frozen=True, eq=False)
class InstrumentFrame(MachineView):
    """``machine`` measured in an instrument frame (fitted or known): a :class:`~bayescal.machines.view.MachineView`.

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
    stations: tuple[str, ...] = ("",)
    frames0: tuple[Frame, ...] = ()
    pose_station: NDArray | None = None

    def __post_init__(self) -> None:
        if self.machine.framed:
            raise InputError("InstrumentFrame: the machine already has an instrument frame; wrap its base machine")
        stations = tuple(str(s) for s in self.stations)
        if not stations or len(set(stations)) != len(stations):
            raise InputError(f"stations: expected distinct labels, got {self.stations!r}")
        frames0 = tuple(self.frames0) or (self.frame0,) * len(stations)
        if len(frames0) != len(stations):
            raise InputError(f"frames0: expected one start frame per station ({len(stations)}), got {len(frames0)}")
        if len(stations) > 1 and not self.fit:
            raise InputError("InstrumentFrame: several stations are fitted frames (fit=True); a known frame is one")
        object.__setattr__(self, "stations", stations)
        object.__setattr__(self, "frames0", frames0)
        object.__setattr__(self, "frame0", frames0[0])
        if self.pose_station is not None:
            ps = np.asarray(self.pose_station, dtype=int).reshape(-1)
            if ps.size and (ps.min() < 0 or ps.max() >= len(stations)):
                raise InputError(f"pose_station: expected indices 0..{len(stations) - 1}")
            object.__setattr__(self, "pose_station", ps)
        o0 = np.array([f.origin for f in frames0])
        R0 = np.array([f.rotation for f in frames0])
        object.__setattr__(self, "_o0", o0)
        object.__setattr__(self, "_R0", R0)

    @property
    def n_stations(self) -> int:
        return len(self.stations)

    def for_poses(self, idx) -> "InstrumentFrame":
        """The same frames bound to the poses ``idx`` of the current binding (a subset of the poses)."""
        if self.pose_station is None:
            return self
        from dataclasses import replace

        return replace(self, pose_station=self.pose_station[np.asarray(idx)])

    def with_pose_station(self, pose_station) -> "InstrumentFrame":
        """The same frames bound to other poses (``pose_station``: station index per pose)."""
        from dataclasses import replace

        return replace(self, pose_station=None if pose_station is None else np.asarray(pose_station, dtype=int))

    def _station_of(self, n: int, stacked: bool = False) -> NDArray | None:
        """Station index of each of ``n`` poses, or None for one station.

        ``stacked``: the poses are parameter sets stacked in blocks of the bound poses (per-pose ``theta`` of
        ``k n`` rows, as a sampler evaluates them), so the binding repeats; otherwise ``n`` must be the bound count:
        poses the stations were not bound to have no station, and tiling would give them one silently.
        """
        if self.n_stations == 1:
            return None
        ps = self.pose_station
        if ps is None:
            raise InputError("InstrumentFrame: several stations, but no station is bound to the poses (pose_station)")
        if n == ps.size:
            return ps
        if stacked and ps.size and n % ps.size == 0:
            return np.tile(ps, n // ps.size)
        raise InputError(f"InstrumentFrame: {n} poses, but stations are bound to {ps.size}; evaluate the machine's "
                         "geometry (Machine.geometry_part) at poses the recording did not measure")

    # ------------------------------------------ the interface (the rest is the machine's: MachineView)
    @property
    def wrapped(self) -> Machine:
        return self.machine

    def with_effects(self, effects) -> "InstrumentFrame":
        from dataclasses import replace

        return replace(self, machine=self.machine.with_effects(effects))

    def with_noise(self, noise) -> "InstrumentFrame":
        from dataclasses import replace

        return replace(self, machine=self.machine.with_noise(noise))

    def with_calibration(self, calibration=None, discrepancy=None) -> "InstrumentFrame":
        from dataclasses import replace

        return replace(self, machine=self.machine.with_calibration(calibration, discrepancy))

    @property
    def n_frame(self) -> int:
        """Number of frame parameters: 6 per station when fitted, 0 when known."""
        return 6 * self.n_stations if self.fit else 0

    @property
    def framed(self) -> bool:
        return True

    @property
    def instrument_frame(self) -> "InstrumentFrame":
        return self

    @property
    def inside(self) -> Machine:
        return self.machine

    #: the machine's: its parameters are the machine's own, after the frame's (:attr:`n_frame`)
    redundancy = Forwarded()

    def rewrapped(self, inner: Machine) -> "InstrumentFrame":
        from dataclasses import replace

        return replace(self, machine=inner)

    def base_machine(self) -> Machine:
        return self.machine.base_machine()

    @property
    def geometry_part(self) -> tuple[Machine, NDArray]:
        """The inner machine and the indices of its parameters (after the frame's, when fitted).

        Composed with the inner machine's own (a body sensors' view leaves its mountings out too).
        """
        inner, idx = self.machine.geometry_part
        return inner, self.n_frame + np.asarray(idx)

    @property
    def layout(self) -> ParamLayout:  # type: ignore[override]
        # composed once per frame (the view and its machine are immutable): an identification asks for it
        # about sixty times, and composing it each time was several percent of a small fit
        got = self.__dict__.get("_layout_memo")
        if got is None:
            got = _frame_layout(self.stations) + self.machine.layout if self.fit else self.machine.layout
            object.__setattr__(self, "_layout_memo", got)
        return got

    @property
    def tolerance(self) -> NDArray:  # type: ignore[override]
        if not self.fit:
            return self.machine.tolerance
        t = dict(FRAME_TOLERANCE, **(self.frame_tolerance or {}))
        one = [t["frame_origin"]] * 3 + [t["frame_rotation"]] * 3
        return np.concatenate([one * self.n_stations, self.machine.tolerance])

    @property
    def prior_mean(self):
        """The inner machine's prior mean after zeros for the frame (None when the inner machine's is zero)."""
        inner = self.machine.prior_mean
        return None if inner is None else np.concatenate([np.zeros(self.n_frame), inner])

    @property
    def prior_lower(self):
        """The inner machine's lower bounds after none for the frame (None when it has none)."""
        inner = self.machine.prior_lower
        return None if inner is None else np.concatenate([np.full(self.n_frame, -np.inf), inner])

    def compatible_q(self, q: ArrayLike, theta: ArrayLike | None = None) -> NDArray:
        """The inner machine's :meth:`Machine.compatible_q` (the frame does not couple actuators)."""
        return self.machine.compatible_q(q, None if theta is None else self.split(theta)[1])

    def node_actuators(self, q: NDArray, theta: NDArray | None = None, aux: dict | None = None):
        """The inner machine's :meth:`Machine.node_actuators` (the drives do not see the frame): zero frame columns."""
        q_act, J = self.machine.node_actuators(q, None if theta is None else self.split(theta)[1], aux)
        if J is None:
            return q_act, None
        return q_act, np.concatenate([np.zeros(J.shape[:2] + (self.n_frame,)), J], axis=2)

    def node_tool_offset(self, q: NDArray, theta: NDArray | None = None, aux: dict | None = None):
        """The inner machine's :meth:`Machine.node_tool_offset`: base frame, as every grid's."""
        return self.machine.node_tool_offset(q, None if theta is None else self.split(theta)[1], aux)

    # --------------------------------------------------------------- frame
    def split(self, theta: ArrayLike | None, n_poses: int | None = None) -> tuple[NDArray, NDArray]:
        """``(frame correction (..., 6), machine errors (..., P_machine))`` of ``theta``."""
        th = self.check_theta(theta, n_poses)
        k = self.n_frame
        return th[..., :k], th[..., k:]

    def frame_at(self, theta: ArrayLike | None = None, station: int = 0) -> Frame:
        """The instrument frame of ``station`` (index) at parameters ``theta`` (P,): its start with the correction applied."""
        th = self.check_theta(theta)
        if th.ndim != 1:
            raise InputError("frame_at: expected one parameter vector (P,)")
        if not 0 <= int(station) < self.n_stations:
            raise InputError(f"station: expected an index 0..{self.n_stations - 1}, got {station!r}")
        st = int(station)
        if not self.fit:
            return self.frames0[st]
        tf = th[6 * st: 6 * st + 6]
        return Frame(self._o0[st] + tf[:3], so3_exp(tf[3:]) @ self._R0[st])

    def _pose_frame_params(self, tf: NDArray, n: int) -> tuple[NDArray | None, NDArray | None]:
        """Each pose's own frame correction (n, 6) from all stations' (..., 6 S), and its station (n,) or None."""
        st = self._station_of(n, stacked=np.ndim(tf) == 2)
        if st is None:
            return tf, None
        tf = np.asarray(tf)
        cols = 6 * st[:, None] + np.arange(6)[None, :]
        if tf.ndim == 1:
            return tf[cols], st
        return np.take_along_axis(tf, cols, axis=-1), st

    def _remembered(self, what: str, tf: NDArray, n: int | None, compute):
        """``compute()``, remembered for the last frame corrections ``tf`` of one parameter vector (P,).

        A Gauss-Newton step asks for the frame at one point three times (the
        forward kinematics, the Jacobian and its base-frame poses): Rodrigues'
        formula each time was a tenth of a small fit's Jacobian.  Keyed by the
        corrections' bytes (and the pose count, which binds the stations);
        the arrays are read-only, so a caller that writes into them fails
        loudly instead of corrupting the next answer.
        """
        if np.ndim(tf) != 1:
            return compute()
        key = (n if self.n_stations > 1 else None, tf.dtype.str, tf.tobytes())
        memo = self.__dict__.get("_frame_memo")
        if memo is None or memo[0] != key:
            memo = (key, {})
            object.__setattr__(self, "_frame_memo", memo)
        got = memo[1].get(what)
        if got is None:
            got = compute()
            for a in (got if isinstance(got, tuple) else (got,)):
                a.setflags(write=False)
            memo[1][what] = got
        return got

    def _frame_arrays(self, tf: NDArray, n: int | None = None) -> tuple[NDArray, NDArray]:
        """Origin (..., 3) and rotation (..., 3, 3) of every pose's frame, from the frame corrections (..., 6 S) (or none)."""
        if not self.fit:
            return self.frame0.origin, self.frame0.rotation
        return self._remembered("arrays", tf, n, lambda: self._compute_frame_arrays(tf, n))

    def _compute_frame_arrays(self, tf: NDArray, n: int | None) -> tuple[NDArray, NDArray]:
        if self.n_stations == 1:
            blocks = geometry_blocks(tf) if np.ndim(tf) == 2 else None
            if blocks is not None:  # a sampler's walkers, each repeated over every pose: one rotation per walker
                o, R = self._frame_arrays(tf[blocks[0]])
                return np.repeat(o, blocks[1], axis=0), np.repeat(R, blocks[1], axis=0)
            return self.frame0.origin + tf[..., :3], so3_exp(tf[..., 3:]) @ self.frame0.rotation
        tfp, st = self._pose_frame_params(tf, n)
        return self._o0[st] + tfp[..., :3], so3_exp(tfp[..., 3:]) @ self._R0[st]

    def to_base_poses(self, poses: ToolPoses, theta: ArrayLike | None) -> ToolPoses:
        """The same poses in the base frame (``p_base = R p_inst + o``), state kept."""
        n = poses.position.shape[0]
        tf, _ = self.split(theta, n if np.ndim(theta) == 2 else None)
        return self._to_base(poses, *self._frame_arrays(tf, n))

    def _to_base(self, poses: ToolPoses, o: NDArray, R: NDArray) -> ToolPoses:
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
        o, R = self._frame_arrays(tf, q.shape[0])
        return self._to_instrument(poses, o, R)

    def tool_jacobian(self, q: ArrayLike, theta: ArrayLike | None, poses: ToolPoses) -> NDArray:
        """``(n, 6, P)``: the frame columns first, then the machine's rotated into the instrument frame.

        With ``R = exp([d_phi]x) R0`` and a perturbation ``e`` of ``d_phi``,
        ``R -> exp([J_l(d_phi) e]x) R``, so
        ``dp_inst/d(d_o) = -R^T``, ``dp_inst/de = R^T [p_base - o]x J_l``,
        ``dw_inst/de = -R^T J_l`` (``w``: small rotation in the instrument frame).
        """
        return self._jacobian(q, theta, poses, None)

    def tool_jacobian_columns(self, q: ArrayLike, theta: ArrayLike | None, poses: ToolPoses,
                              columns: NDArray) -> NDArray:
        """The frame's columns asked for, then the machine's (its own :meth:`Machine.tool_jacobian_columns`)."""
        return self._jacobian(q, theta, poses, np.asarray(columns, dtype=int))

    def _jacobian(self, q: ArrayLike, theta: ArrayLike | None, poses: ToolPoses, columns: NDArray | None) -> NDArray:
        """:meth:`tool_jacobian`, or its ``columns`` (increasing; None: all)."""
        k = self.n_frame
        if columns is not None and np.count_nonzero(columns >= k) == 1:
            # one machine column would make the rotations below matrix-vector products, which numpy may compute
            # another way (other round-off; the same numbers on the examples, but not promised): the whole
            # Jacobian's column keeps the values
            return self._jacobian(q, theta, poses, None)[:, :, columns]
        q = self.check_q(q)
        n = q.shape[0]
        tf, tm = self.split(theta, n if np.ndim(theta) == 2 else None)
        o, R = self._frame_arrays(tf, n)
        base = self._to_base(poses, o, R)
        if columns is None:
            fc, Jm = None, self.machine.tool_jacobian(q, tm, base)
        else:
            fc, Jm = columns[columns < k], self.machine.tool_jacobian_columns(q, tm, base, columns[columns >= k] - k)
        nf = k if fc is None else fc.size
        Rt = np.broadcast_to(np.swapaxes(R, -1, -2), (n, 3, 3))
        J = np.zeros((n, 6, nf + Jm.shape[2]))
        J[:, :3, nf:] = Rt @ Jm[:, :3]
        J[:, 3:, nf:] = Rt @ Jm[:, 3:]
        if self.fit and nf:
            self._frame_columns(J, tf, n, R, base.position - o, fc)
        return J

    def _frame_columns(self, J: NDArray, tf: NDArray, n: int, R: NDArray, arm: NDArray, fc: NDArray | None) -> None:
        """Write the frame's columns ``fc`` (None: all) into the first ``len(fc)`` columns of ``J`` (n, 6, .).

        ``R``: the frame's rotation, (3, 3) for one station (then ``R^T`` and
        ``J_l`` are one matrix each, and what depends on no pose is formed
        once and broadcast: the same products as pose by pose) or (n, 3, 3).
        """
        tfp, st = self._pose_frame_params(tf, n)
        Jl = self._remembered("left_jacobian", tf, n, lambda: left_jacobian(tfp[..., 3:]))
        Rt = np.swapaxes(R, -1, -2)
        k = self.n_frame
        whole = fc is None or fc.size == k
        # one station, all six columns: written in place (the zeros too)
        Jf = J[:, :, :6] if st is None and whole else np.zeros((n, 6, 6))
        Jf[:, :3, :3] = -Rt
        Jf[:, :3, 3:6] = np.broadcast_to(Rt, (n, 3, 3)) @ skew(arm) @ Jl
        Jf[:, 3:, 3:6] = -Rt @ Jl
        if st is not None:
            # each pose sees only its own station's frame columns
            F = J[:, :, :k] if whole else np.zeros((n, 6, k))
            rows = np.arange(n)
            for c in range(6):
                F[rows, :, 6 * st + c] = Jf[:, :, c]
            Jf = F
        if not whole:
            J[:, :, : fc.size] = Jf[:, :, fc]

    def actuator_jacobian(self, q: ArrayLike, theta: ArrayLike | None, poses: ToolPoses) -> NDArray:
        """The inner machine's actuator Jacobian rotated into the instrument frame, (n, 6, n_actuators)."""
        q = self.check_q(q)
        tf, tm = self.split(theta, q.shape[0] if np.ndim(theta) == 2 else None)
        _, R = self._frame_arrays(tf, q.shape[0])
        Ja = self.machine.actuator_jacobian(q, tm, self.to_base_poses(poses, theta))
        Rt = np.swapaxes(R, -1, -2)
        return np.concatenate([Rt @ Ja[:, :3], Rt @ Ja[:, 3:]], axis=1)

    def weight_bodies(self, q: ArrayLike, theta: ArrayLike | None, poses: ToolPoses):
        """The inner machine's weight bodies, in the base frame (gravity is stated in the base frame, not the instrument's)."""
        q = self.check_q(q)
        _, tm = self.split(theta, q.shape[0] if np.ndim(theta) == 2 else None)
        return self.machine.weight_bodies(q, tm, self.to_base_poses(poses, theta))

    def guess_from_measurement(self, q, position, rotation=None, axis=None):
        """The inner machine's start from the measurement taken to the base frame with each pose's start frame."""
        n = np.asarray(position).shape[0]
        st = self._station_of(n) if self.n_stations > 1 else np.zeros(n, dtype=int)
        o0, R0 = self._o0[st], self._R0[st]
        pb = np.einsum("nij,nj->ni", R0, np.asarray(position, dtype=float)) + o0
        Rb = None if rotation is None else R0 @ rotation
        ab = None if axis is None else np.einsum("nij,nj->ni", R0, np.asarray(axis, dtype=float))
        g = self.machine.guess_from_measurement(q, pb, Rb, ab)
        if g is None:
            return None
        return self._to_instrument(g, o0, R0)

    def measurement_rotation(self, q: ArrayLike, theta: ArrayLike | None) -> NDArray:
        """Rotation taking base-frame vectors into each pose's instrument frame, (n, 3, 3): ``R^T``."""
        q = self.check_q(q)
        n = q.shape[0]
        tf, _ = self.split(theta, n if np.ndim(theta) == 2 else None)
        _, R = self._frame_arrays(tf, n)
        return np.broadcast_to(np.swapaxes(R, -1, -2), (n, 3, 3)).copy()

    def to_toml(self, theta: ArrayLike | None = None) -> str:
        """The inner machine's file of ``nominal + theta`` (base frame), plus the ``[instrument]`` table of one station.

        Several stations belong to the session, not the machine (docs/formats.md section 8): no table then.
        """
        th = self.check_theta(theta)
        text = self.machine.to_toml(th[self.n_frame :])
        if self.n_stations > 1:
            return text
        return text.rstrip("\n") + "\n\n" + instrument_toml(self.frame_at(th))

    @classmethod
    def from_toml(cls, table, path: str) -> "InstrumentFrame":
        raise MachineFileError(path, "instrument", "read through bayescal.machines.files.load_machine")


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
