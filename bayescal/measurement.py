"""Measurement models ``y = h(q, theta)`` and their Jacobians ``J = dh/dtheta``.

Per pose, the rows of ``y`` are

* position-only (3-DOF): the tool point, mm;
* 6-DOF: the tool point and the small rotation ``log(R R_ref^T)`` (rad) of
  the platform relative to a reference orientation ``R_ref`` (the measured
  one when the model comes from a recording, so the measured ``y`` is zero
  there and ``y - h`` is the orientation error ``log(R_meas R^T)``);
* 5-DOF: the tool point and two components ``t_k . n`` of the tool axis
  ``n = R e_z`` on a tangent basis ``t_1, t_2`` of the reference axis (rad to
  first order); the torsion about the tool axis is not observed.

Body sensors (docs/formats.md section 8; :mod:`bayescal.sensors`): a recording
with ``accel.<body>.x/y/z`` columns on bodies other than the base adds two
tilt rows (rad) per sensor after the tool rows of every pose, so ``dof`` (the
rows per pose) is ``tool_dof + 2 S``; the machine is then a
:class:`~bayescal.sensors.SensorMounts` view with the sensors' mounting
parameters appended.  Position summaries read ``[:, :3]`` as before.

Every consumer (solvers, filters, samplers, planning, diagnosis) works on
this object and never on a machine directly.
"""

from __future__ import annotations

import sys
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .errors import BayescalError, InputError, KinematicsError
from .geometry import left_jacobian_inverse, skew, so3_exp, so3_log, tangent_basis
from .io.recording import Recording
from .machines.base import Machine, ToolPoses, map_state, offset_poses

__all__ = ["MeasurementModel", "Prediction", "rows_per_pose", "offset_poses", "pose_offset_rows"]

#: Poses per block of the orientation rows' product in :meth:`MeasurementModel.rows_jacobian` (the same values
#: whatever the blocks; a block's product is memory the allocator reuses, a whole one of 100,000 poses fresh
#: pages at every call).
_ROWS_BLOCK = 4096
#: Size above which an array is fresh pages at every allocation: glibc hands blocks above its mmap threshold
#: (at most 32 MiB) back to the kernel when freed, so each new one pays its page faults again (at 100,000
#: poses a (n, 6, 36) Jacobian is 173 MB: its faults cost more than the arithmetic that fills it).  The
#: Jacobian of a recording above this is computed in pose blocks (:meth:`MeasurementModel.jacobian_columns`).
_FRESH_BYTES = 32 * 2**20


def rows_per_pose(dof: int) -> int:
    """Number of measured components per pose for a 6-, 5- or 3-DOF measurement."""
    if dof not in (3, 5, 6):
        raise InputError(f"dof: expected 6, 5 or 3, got {dof!r}")
    return dof


@dataclass(frozen=True)
class Prediction:
    """Model output at one parameter vector.

    Attributes
    ----------
    y : ndarray, shape (n_poses, dof)
        Predicted measurement rows.
    poses : ToolPoses
        The solved tool poses (warm start for the next call).
    """

    y: NDArray
    poses: ToolPoses

    @property
    def success(self) -> NDArray:
        return self.poses.success


@dataclass(frozen=True, eq=False)
class MeasurementModel:
    """``h(theta)`` for a fixed list of commanded poses.

    Parameters
    ----------
    machine : Machine
    q : ndarray, shape (n_poses, n_actuators)
        Commanded actuator positions.
    dof : int
        Rows per pose: the tool's 6, 5 or 3, plus two per body sensor (``sensors``).
    y_measured : ndarray, shape (n_poses, dof), optional
        The measurement in the same rows as ``h`` (zeros in the orientation
        rows for a recording; see the module docstring).
    R_ref : ndarray, shape (n_poses, 3, 3), optional
        Reference orientations (6-DOF) or orientations whose ``e_z`` is the
        reference axis (5-DOF).  Defaults to the nominal model's.
    aux : dict of str to ndarray, optional
        Auxiliary channels, carried for effects and diagnosis.
    guess : ToolPoses, optional
        Start for the forward kinematics (from the measurement).
    pose_sigma : ndarray, shape (n_poses, dof), optional
        One-sigma noise of every row of every pose (mm, then rad): the
        recording's ``sigma_position`` / ``sigma_angle`` columns, or weights
        of a robust fit.  Default: the machine's ``[measurement]`` noise for
        every pose (:attr:`sigma`).
    pose_offset : ndarray, shape (n_poses, 6), optional
        A tool-pose perturbation of every solved pose in the machine's base
        frame (mm, then a small rotation in rad) that the kinematics does
        not describe: what effects that move the tool
        (:attr:`bayescal.effects.Effect.moves_tool`, a link bending under
        gravity) add after the forward kinematics.  :meth:`predict` rotates
        it into each pose's measurement frame (:func:`offset_poses`); it
        does not depend on ``theta``.  None: no offset.
    sensors : SensorSet, optional
        Body tilt sensors (:mod:`bayescal.sensors`): two rows each, after the
        tool's; the machine must then carry their parameters
        (:func:`bayescal.sensors.attach_sensors`).
    """

    machine: Machine
    q: NDArray
    dof: int = 6
    y_measured: NDArray | None = None
    R_ref: NDArray | None = None
    aux: dict | None = None
    guess: ToolPoses | None = None
    pose_sigma: NDArray | None = None
    pose_offset: NDArray | None = None
    sensors: object | None = None

    def __post_init__(self) -> None:
        q = self.machine.check_q(self.q)
        if self.sensors is not None and self.sensors.u.shape[0] != q.shape[0]:
            raise InputError(f"sensors: {self.sensors.u.shape[0]} poses of readings for {q.shape[0]} poses")
        object.__setattr__(self, "q", q)
        if self.pose_offset is not None:
            off = np.asarray(self.pose_offset, dtype=float)
            if off.shape != (q.shape[0], 6) or not np.all(np.isfinite(off)):
                raise InputError(f"pose_offset: expected finite values of shape ({q.shape[0]}, 6), got {off.shape}")
            object.__setattr__(self, "pose_offset", off)
        rows_per_pose(self.tool_dof)
        if self.R_ref is None and self.tool_dof != 3:
            nominal = self.machine.forward(q, None, guess=self.guess)
            if not nominal.success.all():
                i = int(np.flatnonzero(~nominal.success)[0])
                raise KinematicsError(f"pose {i + 1} (q = {q[i].tolist()}): {nominal.message[i]}")
            object.__setattr__(self, "R_ref", nominal.rotation)
        if self.tool_dof == 5:
            object.__setattr__(self, "_tangent", tangent_basis(self.R_ref[:, :, 2]))
        if self.y_measured is not None:
            y = np.asarray(self.y_measured, dtype=float)
            if y.shape != (self.n_poses, self.dof):
                raise InputError(f"y_measured: expected shape ({self.n_poses}, {self.dof}), got {y.shape}")
            object.__setattr__(self, "y_measured", y)
        if self.pose_sigma is not None:
            ps = np.asarray(self.pose_sigma, dtype=float)
            if ps.shape != (self.n_poses, self.dof):
                raise InputError(f"pose_sigma: expected shape ({self.n_poses}, {self.dof}), got {ps.shape}")
            if not np.all(np.isfinite(ps)) or np.any(ps <= 0):
                raise InputError("pose_sigma: expected finite values > 0")
            object.__setattr__(self, "pose_sigma", ps)

    # ----------------------------------------------------------- construction
    @classmethod
    def from_recording(cls, machine: Machine, rec: Recording, *, dof: int | None = None,
                       sensors: bool = True) -> "MeasurementModel":
        """The model of a recording, optionally using fewer DOF than were measured.

        Parameters
        ----------
        machine : Machine
        rec : Recording
            Checked against the machine's actuator count and ``q_limits``.
        dof : int, optional
            6, 5 or 3; at most what the recording holds (a 6-DOF recording
            can be used as 5-DOF or position-only).  Default: the recording's.
        sensors : bool
            Take the recording's body sensors (``accel.<body>.x/y/z`` on a
            body other than the base, docs/formats.md section 8) as
            measurements (default); False: read them as auxiliary channels
            only (what ``predict`` does: a calibrated machine has no
            mountings to predict them with).

        Notes
        -----
        A machine that carries effects (``machine.effects``, the machine
        file's ``[effect.<name>]`` tables) has them applied here at their
        stored values, driven by the recording's auxiliary channels and
        measurement order: the model's ``q`` is then the commanded
        positions plus the effects' ``dq`` (:mod:`bayescal.effects.stored`).
        """
        rec.check_machine(machine.n_actuators, machine.q_limits, machine.source, machine.actuator_units)
        have = rec.dof
        dof = have if dof is None else dof
        rows_per_pose(dof)
        if dof > have:
            raise InputError(f"dof={dof} asked for, but {rec.path} holds a {have}-DOF measurement")
        R_meas = so3_exp(rec.rotvec) if rec.rotvec is not None else None
        guess = machine.guess_from_measurement(rec.q, rec.position, R_meas, rec.axis)
        q, guess, offset, bend = _with_stored_effects(machine, rec, guess, R_meas, sensors)
        # the mountings start from the commanded poses, as the joint fit of geometry and effects starts them (its
        # dq changes with the effects' values): one parametrisation whatever the tables hold
        machine, sensor_set = _attach_sensors(machine, rec) if sensors else (machine, None)
        if sensor_set is not None and (turns := sensor_set.per_sensor(bend)) is not None:
            sensor_set = sensor_set.with_bend(turns)
        tool_dof = dof
        dof = tool_dof + (0 if sensor_set is None else sensor_set.n_rows)
        n = rec.n_poses
        y = np.zeros((n, dof))
        y[:, :3] = rec.position
        R_ref = None
        if tool_dof == 6:
            R_ref = R_meas
        elif tool_dof == 5:
            axis = rec.axis if rec.axis is not None else R_meas[:, :, 2]
            # any rotation whose third column is the measured axis will do as a reference
            R_ref = _frame_with_z(axis)
        return cls(
            machine=machine, q=q, dof=dof, y_measured=y, R_ref=R_ref, aux=dict(rec.aux), guess=guess,
            pose_sigma=_recording_pose_sigma(machine, rec, tool_dof, dof, sensor_set), pose_offset=offset,
            sensors=sensor_set,
        )

    # ------------------------------------------------------------- properties
    @property
    def n_poses(self) -> int:
        return self.q.shape[0]

    @property
    def n_params(self) -> int:
        return self.machine.n_params

    def answer_extras(self, theta) -> dict:
        """JSON keys of the model's own nuisance parameters at ``theta`` for an answer: none here."""
        return {}

    @property
    def calibrated_machine(self) -> Machine:
        """The machine a calibration of this model reports and writes: :attr:`machine` (frame included)."""
        return self.machine

    @property
    def theta_start(self) -> None:
        """Where a search starts: None, the nominal (zero errors); a model with nuisance start values overrides it."""
        return None

    @property
    def tool_dof(self) -> int:
        """The tool's rows per pose (6, 5 or 3): :attr:`dof` without the body sensors' tilt rows."""
        return self.dof - (0 if self.sensors is None else self.sensors.n_rows)

    @property
    def sigma(self) -> NDArray:
        """The nominal one-sigma noise per row of a pose, shape (dof,): mm, then rad (tool angles, then sensor tilts)."""
        nz = self.machine.noise
        return np.array([nz.sigma_position] * 3 + [nz.sigma_angle] * (self.tool_dof - 3)
                        + [self.sensors.row_sigma(nz.sigma_tilt) if self.sensors is not None else 0.0]
                        * (self.dof - self.tool_dof))

    @property
    def row_sigma(self) -> NDArray:
        """One-sigma noise of every row of every pose, shape (n_poses, dof): mm then rad.

        Per-pose values where given (:attr:`pose_sigma`), else :attr:`sigma`
        for every pose.  Everything that whitens residuals divides by this.
        """
        if self.pose_sigma is not None:
            return self.pose_sigma
        # formed once (the model is immutable; a read-only view): every step of a fit whitens with it twice
        got = self.__dict__.get("_row_sigma")
        if got is None:
            got = np.broadcast_to(self.sigma, (self.n_poses, self.dof))
            object.__setattr__(self, "_row_sigma", got)
        return got

    def with_pose_sigma(self, pose_sigma: NDArray | None) -> "MeasurementModel":
        """The same model with other per-pose noise (None: the machine's)."""
        from dataclasses import replace

        return replace(self, pose_sigma=pose_sigma)

    def without_sensors(self) -> "MeasurementModel":
        """The tool's rows only (the body sensors' tilt rows left out), the parameters unchanged.

        What position and orientation summaries of a recording with body
        sensors are computed on (held-out ``check`` rows, predictions).
        """
        if self.sensors is None:
            return self
        from dataclasses import replace

        d = self.tool_dof
        return replace(self, dof=d, sensors=None,
                       y_measured=None if self.y_measured is None else self.y_measured[:, :d],
                       pose_sigma=None if self.pose_sigma is None else self.pose_sigma[:, :d])

    def subset(self, idx) -> "MeasurementModel":
        """The model restricted to poses ``idx`` (order kept)."""
        idx = np.asarray(idx)
        g = None if self.guess is None else self.guess.take(idx)
        return MeasurementModel(
            machine=self.machine.for_poses(idx),
            q=self.q[idx],
            dof=self.dof,
            y_measured=None if self.y_measured is None else self.y_measured[idx],
            R_ref=None if self.R_ref is None else self.R_ref[idx],
            aux=None if self.aux is None else {k: v[idx] for k, v in self.aux.items()},
            guess=g,
            pose_sigma=None if self.pose_sigma is None else self.pose_sigma[idx],
            pose_offset=None if self.pose_offset is None else self.pose_offset[idx],
            sensors=None if self.sensors is None else self.sensors.subset(idx),
        )

    # ------------------------------------------------- poses (what effects act on)
    # A measurement row may involve more than one pose (a distance: two); these say which poses the
    # model solves, so that effects (which act on actuator positions) and diagnostics work on every
    # model alike.  Here every row is one pose.
    @property
    def pose_q(self) -> NDArray:
        """Actuator positions of every pose the model solves, shape (n_solved, N): here ``q``.

        The first :attr:`n_poses` are the rows' own poses (``pose_q[:n_poses] == q``).
        """
        return self.q

    @property
    def pose_row(self) -> NDArray:
        """Measurement row of every solved pose, shape (n_solved,)."""
        return np.arange(self.n_poses)

    @property
    def pose_order(self) -> NDArray | None:
        """Time rank of every solved pose, or None when they are in measurement order (here: None)."""
        return None

    def poses_of(self, rows) -> NDArray:
        """Indices into :attr:`pose_q` of the poses of ``rows``, in the order ``subset(rows)`` solves them."""
        return np.arange(self.n_poses)[np.asarray(rows)]

    def with_pose_q(self, pose_q: NDArray, *, keep_guess: bool = True) -> "MeasurementModel":
        """The same model at other actuator positions of its solved poses (an effect's ``q + dq``)."""
        from dataclasses import replace

        return replace(self, q=pose_q, guess=self.guess if keep_guess else None)

    def with_pose_offset(self, pose_offset: NDArray | None) -> "MeasurementModel":
        """The same model with another base-frame tool-pose perturbation of its solved poses (None: none), shape (n_solved, 6)."""
        from dataclasses import replace

        return replace(self, pose_offset=pose_offset)

    def effect_inputs(self, theta: NDArray, prediction: Prediction | None) -> tuple[Machine, NDArray, ToolPoses | None]:
        """The machine, geometry and solved poses at which effects are evaluated (``features``, ``actuator_jacobian``).

        Without a prediction the poses are None (an effect's ``dq`` at a geometry needs no poses).
        """
        return self.machine, theta, None if prediction is None else prediction.poses

    def region(self, prediction: Prediction) -> NDArray:
        """Where each row was measured, shape (n_poses, 3), mm: the measured tool point (else the predicted one)."""
        if self.y_measured is not None:
            return self.y_measured[:, :3]
        return prediction.y[:, :3]

    # ---------------------------------------------------------------- the model
    def _rows(self, poses: ToolPoses) -> NDArray:
        """The tool's rows (n, tool_dof)."""
        d = self.tool_dof
        y = np.empty((poses.position.shape[0], d))
        y[:, :3] = poses.position
        if d == 6:
            y[:, 3:] = so3_log(poses.rotation @ np.swapaxes(self._tile(self.R_ref, y.shape[0]), -1, -2))
        elif d == 5:
            y[:, 3:] = np.einsum("nkj,nj->nk", self._tile(self._tangent, y.shape[0]), poses.rotation[:, :, 2])
        return y

    def _tile(self, arr: NDArray, n_rows: int) -> NDArray:
        reps = n_rows // arr.shape[0]
        return arr if reps == 1 else np.tile(arr, (reps,) + (1,) * (arr.ndim - 1))

    def predict(self, theta: ArrayLike | None = None, *, guess: ToolPoses | None = None) -> Prediction:
        """``h(theta)`` for every pose.

        Parameters
        ----------
        theta : array_like, shape (P,), (n_poses, P) or (n_sets * n_poses, P)
            Geometric errors.  With ``n_sets`` stacked blocks (one per
            walker or sigma point), ``q`` is tiled: this is how samplers
            evaluate many parameter vectors in one vectorised call.
        guess : ToolPoses, optional
            Warm start (an earlier prediction's ``poses``).

        Returns
        -------
        Prediction
            ``y`` of shape (n_rows, dof); check ``success`` per pose.
        """
        theta = np.asarray(theta if theta is not None else np.zeros(self.n_params), dtype=float)
        q = self.q
        if theta.ndim == 2 and theta.shape[0] != self.n_poses:
            if theta.shape[0] % self.n_poses:
                raise InputError(f"theta: {theta.shape[0]} rows is not a multiple of {self.n_poses} poses")
            q = np.tile(q, (theta.shape[0] // self.n_poses, 1))
        g = guess if guess is not None else self.guess
        if g is not None and g.position.shape[0] != q.shape[0]:
            g = _tile_poses(g, q.shape[0] // g.position.shape[0])
        poses = self.machine.forward(q, theta, guess=g)
        if self.pose_offset is not None:
            poses = offset_poses(self.machine, q, theta, poses, self.pose_offset)
        y = self._rows(poses)
        if self.sensors is not None:
            from .sensors import sensor_rows

            y = np.concatenate([y, sensor_rows(self.machine, self.sensors, q, theta)], axis=1)
        return Prediction(y=y, poses=poses)

    def jacobian(self, theta: ArrayLike | None, prediction: Prediction, *, out: NDArray | None = None) -> NDArray:
        """``dh/dtheta`` at ``theta``, shape (n_poses, dof, P), analytic.

        Orientation rows: ``J_l^{-1}(h_rot) J_w`` (6-DOF) and
        ``t_k . (J_w x n)`` = ``-t_k^T [n]x J_w`` (5-DOF), where ``J_w`` is the
        platform's small-rotation Jacobian.  ``out``: an array of that shape
        (a view of a larger system) to write into and return.
        """
        return self.jacobian_columns(theta, prediction, None, out=out)

    jacobian.writes_into = True  # bayescal.contract.jacobian_into: takes ``out``

    def jacobian_columns(self, theta: ArrayLike | None, prediction: Prediction, columns: NDArray | None, *,
                         out: NDArray | None = None) -> NDArray:
        """:meth:`jacobian`'s ``columns`` (increasing indices; None: all), shape (n_poses, dof, len(columns)).

        The same values as the whole Jacobian's; the machine computes only
        what the columns need (:meth:`Machine.tool_jacobian_columns`): a fit
        of the identifiable subset asks for these at every step.  ``out``:
        where to write them (returned).
        """
        k = self.n_params if columns is None else len(columns)
        if k >= 2 and np.ndim(theta) <= 1 and self.n_poses > _ROWS_BLOCK and self.n_poses * 6 * k * 8 > _FRESH_BYTES:
            return self._jacobian_blocks(theta, prediction, columns, np.empty((self.n_poses, self.dof, k))
                                         if out is None else out)
        J = self._jacobian_whole(theta, prediction, columns)
        if out is None:
            return J
        out[...] = J
        return out

    def _jacobian_whole(self, theta: ArrayLike | None, prediction: Prediction, columns: NDArray | None) -> NDArray:
        """:meth:`jacobian_columns` of every pose at once."""
        if columns is not None and len(columns) < 2:
            # with one column the rows' products below are matrix-vector ones, which numpy computes another way
            # (other round-off: seen on the UR10's last column); the whole Jacobian's column keeps the values
            return self.jacobian_columns(theta, prediction, None)[:, :, columns]
        if columns is None:
            Jt = self.machine.tool_jacobian(self.q, theta, prediction.poses)
        else:
            Jt = self.machine.tool_jacobian_columns(self.q, theta, prediction.poses, columns)
        J = self.rows_jacobian(Jt, prediction)
        if self.sensors is not None:
            from .sensors import sensor_jacobian

            th = self.machine.check_theta(theta)
            Js = sensor_jacobian(self.machine, self.sensors, self.q, th)
            J[:, self.tool_dof :] = Js if columns is None else Js[:, :, columns]
        return J

    def _jacobian_blocks(self, theta: ArrayLike | None, prediction: Prediction, columns: NDArray | None,
                         J: NDArray) -> NDArray:
        """:meth:`jacobian_columns` pose block by pose block, into ``J`` (shape (n_poses, dof, k)).

        Every pose's rows are its own (the sub-model of a block's poses gives them bit for bit), and a block's
        tool Jacobian and rows are memory the allocator reuses: the whole recording's (n_poses, 6, k) tool
        Jacobian and its rows would be two fresh arrays of pages at every call (:data:`_FRESH_BYTES`).
        """
        n = self.n_poses
        for start in range(0, n, _ROWS_BLOCK):
            b = slice(start, min(start + _ROWS_BLOCK, n))
            block = Prediction(prediction.y[b], prediction.poses.take(b))
            J[b] = self.subset(np.arange(b.start, b.stop)).jacobian_columns(theta, block, columns)
        return J

    def rows_jacobian(self, Jt: NDArray, prediction: Prediction) -> NDArray:
        """Measurement-row derivative from a tool-pose derivative.

        Parameters
        ----------
        Jt : ndarray, shape (n_poses, 6, k)
            Tool point (rows 0-2) and small platform rotation (rows 3-5) per
            unit of ``k`` variables (geometric errors, actuator positions, ...).
        prediction : Prediction
            At which the rows are linearised.

        Returns
        -------
        ndarray, shape (n_poses, dof, k)
            The body sensors' rows are zero: a tool-pose derivative does not
            say how the bodies turn (:meth:`jacobian` fills them for the
            geometric parameters; an effect's actuator derivative does not
            reach them).
        """
        n, d = Jt.shape[0], self.tool_dof
        J = np.zeros((n, self.dof, Jt.shape[2]))
        J[:, :3] = Jt[:, :3]
        if d == 6:
            L = left_jacobian_inverse(prediction.y[:, 3:6])
            # in blocks of poses: each pose's product is its own, and a block's product (unlike a whole one of
            # 100,000 poses) is memory the allocator reuses instead of fresh pages
            for k in range(0, n, _ROWS_BLOCK):
                J[k : k + _ROWS_BLOCK, 3:6] = L[k : k + _ROWS_BLOCK] @ Jt[k : k + _ROWS_BLOCK, 3:]
        elif d == 5:
            nvec = prediction.poses.rotation[:, :, 2]
            J[:, 3:5] = -np.einsum("nkj,nji,nip->nkp", self._tangent, skew(nvec), Jt[:, 3:])
        return J

    def residual(self, prediction: Prediction) -> NDArray:
        """``y_measured - h``, shape (n_poses, dof); mm then rad."""
        if self.y_measured is None:
            raise InputError("this measurement model has no measured values (y_measured)")
        return self.y_measured - prediction.y

    def errors(self, residual: NDArray) -> tuple[NDArray, NDArray | None]:
        """Per-pose position error norm (mm) and tool orientation error norm (rad, None for 3-DOF); sensor rows apart."""
        pos = np.linalg.norm(residual[:, :3], axis=1)
        ang = np.linalg.norm(residual[:, 3 : self.tool_dof], axis=1) if self.tool_dof > 3 else None
        return pos, ang

    def rms(self, residual: NDArray) -> dict[str, float | None]:
        """Root-mean-square of the per-pose error norms: ``{"position": mm, "angle": rad or None}``.

        With body sensors also ``"tilt"`` (rad): the RMS over poses and
        sensors of each reading's tilt error (the norm of its two rows).
        """
        pos, ang = self.errors(residual)
        out = {
            "position": float(np.sqrt(np.mean(pos**2))),
            "angle": None if ang is None else float(np.sqrt(np.mean(ang**2))),
        }
        if self.sensors is not None:
            tilt = self.sensors.tilt_errors(np.asarray(residual)[:, self.tool_dof :])
            out["tilt"] = float(np.sqrt(np.mean(tilt**2)))
        return out



def _attach_sensors(machine: Machine, rec: Recording):
    """:func:`bayescal.sensors.attach_sensors` at the commanded positions, skipped when it has nothing to do.

    No channel to read and no mounting to replace (a SensorMounts view
    exists only once its module is loaded): the machine unchanged, and the
    sensors package is not imported (a tenth of a small fit's time).
    """
    if not rec.aux and "bayescal.sensors.mounts" not in sys.modules:
        return machine, None
    from .sensors import attach_sensors

    return attach_sensors(machine, rec, rec.q)


def pose_offset_rows(model, theta, prediction, dX: NDArray) -> NDArray:
    """Measurement-row derivative of base-frame tool-pose perturbations of every solved pose.

    Parameters
    ----------
    model : MeasurementModel or ConstraintModel
    theta : ndarray
        The model's parameters (the measurement rotation depends on a fitted frame).
    prediction : Prediction
        At which the rows are linearised.
    dX : ndarray, shape (n_solved, 6, k)
        Base-frame tool displacement (mm) and small rotation (rad) per unit
        of ``k`` variables (an effect's parameters).

    Returns
    -------
    ndarray, shape (n_rows, dof, k)
        Through each pose's measurement rotation, then ``rows_jacobian`` (the
        map the geometric parameters go through).  The rotation the model
        already applies (its ``pose_offset``, ``phi`` in the measurement
        frame) turns a change ``dw`` into ``J_l(phi) dw`` (``exp([phi +
        dphi]x) = exp([J_l(phi) dphi]x) exp([phi]x)``).
    """
    Rm = model.machine.measurement_rotation(model.pose_q, theta)
    J = np.empty_like(np.asarray(dX, dtype=float))
    J[:, :3] = np.einsum("nij,njk->nik", Rm, dX[:, :3])
    J[:, 3:] = np.einsum("nij,njk->nik", Rm, dX[:, 3:])
    own = model.pose_offset
    if own is not None:
        phi = np.einsum("nij,nj->ni", Rm, own[:, 3:])
        J[:, 3:] = np.linalg.solve(left_jacobian_inverse(phi), J[:, 3:])
    return model.rows_jacobian(J, prediction)


def check_recording_solves(model: "MeasurementModel", rec: Recording) -> None:
    """Raise RecordingError naming the recording's line of the first pose the nominal machine cannot solve.

    Every identification and diagnosis starts at the nominal geometry, so a
    pose it cannot solve (a recording of another machine, actuator positions
    in other units, a pose outside the reachable workspace) stops it; this
    says so in terms of the files (docs/formats.md: name the file and the line).
    """
    from .errors import RecordingError

    pred = model.predict(None)
    if not pred.success.all():
        i = int(np.flatnonzero(~pred.success)[0])
        typo = _measured_far_off(model, rec, i)
        if typo is not None:
            raise typo
        raise RecordingError(
            rec.path, int(rec.lines[i]), None,
            f"the machine {model.machine.source} cannot assemble this pose (q = {model.q[i].tolist()}): "
            f"{pred.poses.message[i]}; expected a pose of this machine, in its units",
        )


def _measured_far_off(model: "MeasurementModel", rec: Recording, i: int):
    """A RecordingError naming the column, when pose ``i`` fails only because its measurement is far off, else None.

    The kinematics start each pose from its measurement: 12345.6 in one cell of x sent them nowhere, and the
    message blamed the machine ("cannot assemble this pose") for a pose it assembles from its own start.
    """
    from .errors import RecordingError

    if model.y_measured is None or model.pose_offset is not None:
        return None
    q_i = np.asarray(model.q)[i: i + 1]
    try:
        alone = model.machine.forward(q_i)
        if not alone.success.all():
            return None
        if rec.rotvec is not None or rec.axis is not None:
            # the start is the measured position and orientation: from the position alone the pose solves when
            # the orientation is what sent the kinematics off (the position's cells are then not to blame)
            start = model.machine.guess_from_measurement(q_i, np.asarray(rec.position, dtype=float)[i: i + 1])
            if start is not None and model.machine.forward(q_i, guess=start).success.all():
                return _orientation_far_off(model, rec, i)
    except (BayescalError, ValueError, ArithmeticError):
        return None
    d = np.asarray(model.y_measured, dtype=float)[i, :3] - alone.position[0]
    if not np.all(np.isfinite(d)):
        return None
    k = int(np.argmax(np.abs(d)))
    names = _file_names(rec, ("x", "y", "z"))
    return RecordingError(
        rec.path, int(rec.lines[i]), names[k],
        f"the measured tool point is {float(np.linalg.norm(d)):.4g} mm from where the machine {model.machine.source} "
        f"puts it at q = {model.q[i].tolist()} ({names[k]} off by {float(d[k]):.4g} mm), too far for its kinematics "
        "to start from; expected the measurement of this pose (a typo in the cell?)",
    )


def _file_names(rec: Recording, columns: tuple[str, ...]) -> tuple[str, ...]:
    """The columns as the recording's header names them (with a declared unit suffix, ``x_um``)."""
    units = getattr(rec, "declared_units", None) or {}
    return tuple(f"{c}_{units[c]}" if c in units else c for c in columns)


def _orientation_far_off(model: "MeasurementModel", rec: Recording, i: int):
    """The RecordingError for pose ``i`` when its measured orientation, not its position, keeps it from solving."""
    from .errors import RecordingError

    names = _file_names(rec, ("rx", "ry", "rz") if rec.rotvec is not None else ("nx", "ny", "nz"))
    return RecordingError(
        rec.path, int(rec.lines[i]), names[0],
        f"the measured orientation ({', '.join(names)}) keeps the kinematics of {model.machine.source} from solving "
        f"q = {model.q[i].tolist()}, which they solve from the measured position alone; expected the measurement of "
        "this pose (a typo in one of these cells?)",
    )


def _recording_pose_sigma(machine: Machine, rec: Recording, dof: int, width: int | None = None,
                          sensors=None) -> NDArray | None:
    """Per-pose noise from the recording's ``sigma_position`` / ``sigma_angle`` columns (docs/formats.md section 4).

    A missing column takes the machine's ``[measurement]`` value; a
    position-only model ignores ``sigma_angle``.  None when neither applies.
    ``dof`` is the tool's rows, ``width`` all rows (the body sensors' take their rows' sigma from ``sigma_tilt``).
    """
    width = dof if width is None else width
    sp, sa = getattr(rec, "sigma_position", None), getattr(rec, "sigma_angle", None)
    if sp is None and (sa is None or dof == 3):
        return None
    nz = machine.noise
    out = np.empty((rec.n_poses, width))
    out[:, :3] = (np.full(rec.n_poses, nz.sigma_position) if sp is None else sp)[:, None]
    if dof > 3:
        out[:, 3:dof] = (np.full(rec.n_poses, nz.sigma_angle) if sa is None else sa)[:, None]
    if sensors is not None:
        out[:, dof:] = sensors.row_sigma(nz.sigma_tilt)
    return out


def _frame_with_z(axis: NDArray) -> NDArray:
    t = tangent_basis(axis)
    return np.stack([t[:, 0], t[:, 1], axis], axis=-1)


def _tile_poses(p: ToolPoses, reps: int) -> ToolPoses:
    tiled = map_state(lambda a: np.tile(a, (reps,) + (1,) * (a.ndim - 1)), p.state)
    return ToolPoses(
        np.tile(p.position, (reps, 1)), np.tile(p.rotation, (reps, 1, 1)), np.tile(p.success, reps), p.message * reps, tiled
    )


def _with_stored_effects(machine: Machine, rec: Recording, guess, R_meas, sensors: bool):
    """The machine file's effects at their stored values: ``(q, guess, pose_offset, bend)`` of a recording.

    Without effects: the commanded ``q``, ``guess`` as given, no tool perturbation and no body turn.
    """
    q = rec.q
    if not machine.effects:
        return q, guess, None, {}
    bend = {}
    # the machine file's [effect.*] tables at their stored values: the kinematics sees the
    # actuator positions the effects make of the commanded ones, and the tool the perturbation
    # of those that move it, so every consumer applies them
    from .effects.stored import effect_delta_q_and_x
    if machine.framed:
        # loads and growth live in the base frame: evaluate the effects on the base machine
        # (started from its own assembly, since the measured poses are in the instrument frame)
        base = machine.base_machine()
        poses = base.forward(q, None)
        poses = poses if poses.success.all() else None
    else:
        base = machine
        poses = machine.forward(q, None, guess=guess) if guess is not None else None
    dq, offset = effect_delta_q_and_x(base, machine.effects, q, dict(rec.aux), poses=poses)
    if sensors:  # a structure that bends turns the bodies tilt sensors sit on (as the joint fit models it)
        from .effects.stored import effect_body_rotation

        bend = effect_body_rotation(base, machine.effects, q, dict(rec.aux), poses=poses)
    q = q + dq
    guess = machine.guess_from_measurement(q, rec.position, R_meas, rec.axis)
    return q, guess, offset, bend
