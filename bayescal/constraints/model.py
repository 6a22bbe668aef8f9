"""Measurement model of constraint recordings: distances, heights and ballbar readings.

One scalar row per measurement (``dof = 1``), for any machine kind:

    distance:  h = |x(q_a) - x(q_b)|
    height:    h = e_z . x(q_a)
    ballbar:   h = |x(q_a) - c_k|

with ``x(q)`` the tool point in the base frame and ``c_k`` the fitted pivot
of the row.  The parameter vector is the machine's geometric errors followed
by three coordinates per pivot (``pivot.<id>.x``, ``.y``, ``.z``, mm,
relative to the pivot's start estimate, :attr:`ConstraintModel.pivot_start`).
The Jacobian rows are the chain rule on the machine's analytic
``tool_jacobian``:

    distance:  n_ab^T (J_a - J_b),   n_ab = (x_a - x_b) / |x_a - x_b|
    height:    e_z^T J_a
    ballbar:   n^T J_a for the machine, -n^T for the pivot,  n = (x_a - c) / |x_a - c|

The model exposes what consumers use of
:class:`bayescal.measurement.MeasurementModel` (``predict``, ``jacobian``,
``residual``, ``sigma``, ``subset``, ``rms``, ``n_poses``, ``n_params``,
``q``, ``aux``, ``machine``), so identification works on it unchanged.  Its
``machine`` is a :class:`PivotAugmented` view: the machine's layout and
tolerances plus the pivots'.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..errors import InputError, RecordingError
from ..io.constraints import ConstraintRecording
from ..machines.appended import AppendedParameters
from ..machines.base import Machine, ToolPoses
from ..params import ParamSpec

__all__ = ["ConstraintModel", "ConstraintPrediction", "PivotAugmented", "PIVOT_TOLERANCE", "load_constraint_model",
           "check_pivot_readings", "MIN_PIVOT_READINGS"]

#: One-sigma scale (mm) of a pivot's correction to its start estimate: column scaling and ridge prior.
PIVOT_TOLERANCE = 1.0
_CODES = {"distance": 0, "height": 1, "ballbar": 2}


@dataclass(frozen=True, eq=False)
class PivotAugmented(AppendedParameters):
    """A machine's parameter layout extended by ballbar pivots (:class:`~bayescal.machines.appended.AppendedParameters`).

    ``base`` is the machine; the pivots' parameters are ``pivot.<id>.x/y/z`` (mm).
    """

    pivot_ids: tuple[str, ...] = ()

    def appended(self):
        specs = tuple(ParamSpec(f"pivot.{p}.{c}", "mm", "pivot") for p in self.pivot_ids for c in "xyz")
        return specs, np.full(len(specs), PIVOT_TOLERANCE)


@dataclass(frozen=True)
class ConstraintPrediction:
    """Model output: ``y`` (n_rows, 1) and the solved poses (a poses, then b poses of distance rows)."""

    y: NDArray
    poses: ToolPoses
    row_success: NDArray
    #: Per row, the unit vector along which the row measures its tool point(s), shape (n_sets * n_rows, 3):
    #: ``(x_a - x_b) / |x_a - x_b|``, ``e_z`` or ``(x_a - c) / |x_a - c|``.
    direction: NDArray | None = None

    @property
    def success(self) -> NDArray:
        """Per measurement row: both of its poses solved."""
        return self.row_success


@dataclass(frozen=True, eq=False)
class ConstraintModel:
    """``h(theta)`` for a list of distance, height and ballbar measurements.

    Parameters
    ----------
    base : Machine
        The machine measured; ``model.machine`` is it with the ballbar pivots'
        parameters appended (the model's ``theta``).
    measure : tuple of str
        ``distance``, ``height`` or ``ballbar`` per row.
    qa, qb : ndarray, shape (n, N)
        Actuator positions of poses a and b (qb used on distance rows only).
    pivot : tuple of str
        Pivot id per row (``""`` unless ballbar).
    pivot_start : ndarray, shape (K, 3), optional
        Start estimates of the pivots (mm, base frame), in the order of
        first appearance; estimated from the nominal machine if omitted.
    y_measured : ndarray, shape (n, 1), optional
    pose_sigma : ndarray, shape (n, 1) or (n,), optional
        Per-row one-sigma noise (the ``sigma_position`` column), mm; the
        machine's ``[measurement] sigma_position`` for every row by default.
    aux : dict, optional
    pivot_order : tuple of str, optional
        The pivots' order in the parameter vector (default: first appearance);
        subsets keep the full model's.
    """

    base: Machine
    measure: tuple[str, ...]
    qa: NDArray
    qb: NDArray
    pivot: tuple[str, ...]
    pivot_start: NDArray | None = None
    y_measured: NDArray | None = None
    pose_sigma: NDArray | None = None
    aux: dict = field(default_factory=dict)
    pivot_order: tuple[str, ...] = ()
    dof: int = 1
    #: Base-frame tool-pose perturbation of every solved pose (:attr:`pose_q` order), shape (n_solved, 6),
    #: or None: what effects that move the tool add after the kinematics (as
    #: :attr:`bayescal.measurement.MeasurementModel.pose_offset`).
    pose_offset: NDArray | None = None
    #: The machine as the caller gave it, when it differs from :attr:`base`: a machine file's known
    #: ``[instrument]`` frame, which the rows do not see (:meth:`from_recording`).
    given: Machine | None = None
    #: The recording's file (:attr:`ConstraintRecording.path`), named in messages; None for a model built in code.
    path: str | None = None

    def __post_init__(self) -> None:
        qa = self.base.check_q(self.qa)
        object.__setattr__(self, "qa", qa)
        object.__setattr__(self, "qb", np.asarray(self.qb, dtype=float).reshape(qa.shape))
        codes = np.array([_CODES[m] for m in self.measure], dtype=int)
        object.__setattr__(self, "_codes", codes)
        ids = self.pivot_order or tuple(dict.fromkeys(p for p in self.pivot if p))
        unknown = sorted({p for p in self.pivot if p} - set(ids))
        if unknown:
            raise InputError(f"pivot ids {unknown} are not in pivot_order {list(ids)}")
        object.__setattr__(self, "pivot_ids", ids)
        object.__setattr__(self, "_pivot_index", np.array([ids.index(p) if p else -1 for p in self.pivot], dtype=int))
        object.__setattr__(self, "machine", PivotAugmented(self.base, ids))
        object.__setattr__(self, "_dist", np.flatnonzero(codes == 0))
        if self.pivot_start is None:
            object.__setattr__(self, "pivot_start", self._estimate_pivots())
        if self.y_measured is not None:
            y = np.asarray(self.y_measured, dtype=float).reshape(self.n_poses, 1)
            object.__setattr__(self, "y_measured", y)
        if self.pose_sigma is not None:
            ps = np.asarray(self.pose_sigma, dtype=float).reshape(self.n_poses, 1)
            if not np.all(np.isfinite(ps)) or np.any(ps <= 0):
                raise InputError("pose_sigma: expected finite values > 0")
            object.__setattr__(self, "pose_sigma", ps)

    # ----------------------------------------------------------- construction
    @classmethod
    def from_recording(cls, machine: Machine, rec: ConstraintRecording, *, dof: int | None = None) -> "ConstraintModel":
        """The model of a constraint recording (checked against the machine's actuators and ``q_limits``).

        A machine that carries effects (``[effect.<name>]`` tables) has them
        applied at their stored values to every pose the rows measure, as
        :meth:`bayescal.measurement.MeasurementModel.from_recording` does.
        A machine file's ``[instrument]`` frame does not apply: heights are
        measured along the base z axis and distances do not see a frame
        (docs/formats.md section 6), so the model is of the machine in its base frame.
        """
        if dof not in (None, 1):
            raise InputError(f"--dof {dof}: a constraint recording has one scalar per measurement; leave --dof out")
        given = None
        if machine.framed:
            if machine.instrument_frame.fit:
                raise InputError("a constraint recording does not see an instrument frame (heights are along the base z "
                                 "axis, docs/formats.md section 6): there is no frame to fit")
            given, machine = machine, machine.inside
        rec.check_machine(machine.n_actuators, machine.q_limits, machine.source)
        model = cls(
            base=machine, measure=rec.measure, qa=rec.qa, qb=rec.qb, pivot=rec.pivot,
            y_measured=rec.value[:, None], pose_sigma=rec.sigma, aux=dict(rec.aux), given=given,
            path=rec.path,
        )
        if machine.effects:
            # the machine file's [effect.*] tables at their stored values (docs/formats.md section 7), as for pose
            # recordings: every solved pose moves by the effects' dq, driven by its row's channels, in time order
            from ..effects.stored import effect_delta_q_and_x

            pose_aux = {k: np.asarray(v)[model.pose_row] for k, v in model.aux.items()}
            dq, dx = effect_delta_q_and_x(machine, machine.effects, model.pose_q, pose_aux, order=model.pose_order)
            model = model.with_pose_q(model.pose_q + dq).with_pose_offset(dx)
        pred = model.predict(None)
        if not pred.success.all():
            i = int(np.flatnonzero(~pred.success)[0])
            raise RecordingError(
                rec.path, i + 2, None,
                f"the machine {machine.source} cannot assemble this row's pose(s) at its nominal geometry "
                f"({pred.poses.message[i]}); expected poses of this machine, in its units",
            )
        return model

    def _estimate_pivots(self) -> NDArray:
        """Start estimates: per pivot, the sphere through the nominal tool points with the measured radii.

        ``|x - c|^2 = rho^2`` is linear in ``(c, |c|^2)``; for points in one
        plane the pivot's offset from that plane is not seen (first order),
        and the minimum-norm solution about the points' centroid puts it in
        the plane.  Without measured radii the centroid is the start.
        """
        K = len(self.pivot_ids)
        out = np.zeros((K, 3))
        if K == 0:
            return out
        pos = self.base.forward(self.qa).position
        for k in range(K):
            rows = np.flatnonzero(self._pivot_index == k)
            x = pos[rows]
            m = x.mean(axis=0)
            if self.y_measured is None or rows.size < 4:
                out[k] = m
                continue
            xc = x - m
            rho = np.asarray(self.y_measured, dtype=float).reshape(-1)[rows]
            # 2 x.c - s = |x|^2 - rho^2, s = |c|^2 (coordinates about the centroid)
            A = np.column_stack([2 * xc, -np.ones(rows.size)])
            sol, *_ = np.linalg.lstsq(A, np.einsum("ij,ij->i", xc, xc) - rho**2, rcond=1e-10)
            out[k] = m + sol[:3] if np.all(np.isfinite(sol)) else m
        return out

    # ------------------------------------------------------------- properties
    @property
    def n_poses(self) -> int:
        """Number of measurement rows (the consumers' "poses")."""
        return self.qa.shape[0]

    @property
    def n_params(self) -> int:
        return self.machine.n_params

    @property
    def q(self) -> NDArray:
        """Actuator positions of pose a per row (for messages and pose-region diagnostics)."""
        return self.qa

    @property
    def guess(self) -> None:
        return None

    @property
    def sigma(self) -> NDArray:
        """The instrument's nominal one-sigma noise of a row, shape (1,), mm (``[measurement] sigma_position``)."""
        return np.array([self.base.noise.sigma_position])

    @property
    def row_sigma(self) -> NDArray:
        """One-sigma noise of every row, shape (n_rows, 1), mm: :attr:`pose_sigma` where given, else :attr:`sigma`.

        Everything that whitens residuals divides by this (as for
        :attr:`bayescal.measurement.MeasurementModel.row_sigma`).
        """
        if self.pose_sigma is not None:
            return self.pose_sigma
        return np.broadcast_to(self.sigma, (self.n_poses, 1))

    #: A relation has no body sensors' rows, and a search starts at the nominal geometry (the pivots'
    #: start estimates are the nominal of their parameters): the model contract's members, fixed here.
    sensors = None
    theta_start = None

    @property
    def tool_dof(self) -> int:
        """Rows of the measurement itself per row: :attr:`dof` (no sensor rows)."""
        return self.dof

    def without_sensors(self) -> "ConstraintModel":
        return self

    def answer_extras(self, theta) -> dict:
        """The answer's ``pivots``: each ballbar pivot's fitted position (mm), ``{}`` without ballbar rows."""
        return {"pivots": self.pivot_positions(theta)}

    @property
    def calibrated_machine(self) -> Machine:
        """The machine a calibration reports and writes: as given (its known ``[instrument]`` kept), without pivots.

        The rows do not see an instrument frame, so a calibration leaves a
        machine file's ``[instrument]`` table as it was: a later pose
        recording from that instrument still reads in its frame.
        """
        return self.base if self.given is None else self.given

    def with_pose_sigma(self, pose_sigma: NDArray | None) -> "ConstraintModel":
        """The same model with other per-row noise (None: the machine's)."""
        from dataclasses import replace

        return replace(self, pose_sigma=pose_sigma)

    @property
    def measure_codes(self) -> NDArray:
        return self._codes

    def subset(self, idx) -> "ConstraintModel":
        """The model restricted to rows ``idx`` (order kept; the pivots and their starts stay)."""
        idx = np.asarray(idx)
        rows = np.arange(self.n_poses)[idx]
        return ConstraintModel(
            base=self.base, measure=tuple(self.measure[i] for i in rows), qa=self.qa[idx], qb=self.qb[idx],
            pivot=tuple(self.pivot[i] for i in rows), pivot_start=self.pivot_start, pivot_order=self.pivot_ids,
            y_measured=None if self.y_measured is None else self.y_measured[idx],
            pose_sigma=None if self.pose_sigma is None else self.pose_sigma[idx],
            aux={k: v[idx] for k, v in self.aux.items()},
            pose_offset=None if self.pose_offset is None else self.pose_offset[self.poses_of(idx)],
        )

    # ---------------------------------------------------------------- the model
    def _split(self, theta: ArrayLike | None):
        """Machine theta per stacked pose, pivots per row, and the number of stacked blocks."""
        P, n = self.base.n_params, self.n_poses
        theta = np.zeros(self.n_params) if theta is None else np.asarray(theta, dtype=float)
        if theta.shape[-1] != self.n_params or theta.ndim not in (1, 2):
            raise InputError(f"theta: expected shape ({self.n_params},) or (n, {self.n_params}), got {theta.shape}")
        K = len(self.pivot_ids)
        if theta.ndim == 1:
            blocks = 1
            th_m = theta[:P]
            piv = np.broadcast_to(self.pivot_start + theta[P:].reshape(K, 3), (1, K, 3))
            return th_m, piv, blocks
        if theta.shape[0] % n:
            raise InputError(f"theta: {theta.shape[0]} rows is not a multiple of {n} measurements")
        blocks = theta.shape[0] // n
        th = theta.reshape(blocks, n, -1)
        rows = np.concatenate([np.arange(n), self._dist])
        th_m = th[:, rows, :P].reshape(-1, P)
        piv = self.pivot_start[None, None] + th[:, :, P:].reshape(blocks, n, K, 3)  # per row
        return th_m, piv, blocks

    def _stacked_q(self, blocks: int) -> NDArray:
        Q = np.vstack([self.qa, self.qb[self._dist]])
        return np.tile(Q, (blocks, 1)) if blocks > 1 else Q

    def _row_pivots(self, piv: NDArray, blocks: int) -> NDArray:
        """Pivot of each row, shape (blocks, n, 3) (zeros on non-ballbar rows)."""
        n = self.n_poses
        k = np.maximum(self._pivot_index, 0)
        if piv.ndim == 3:  # (1, K, 3): one pivot set
            out = np.broadcast_to(piv[0][k], (blocks, n, 3)) if len(self.pivot_ids) else np.zeros((blocks, n, 3))
        else:  # (blocks, n, K, 3): per-row parameter sets
            out = piv[:, np.arange(n), k] if len(self.pivot_ids) else np.zeros((blocks, n, 3))
        return out

    def predict(self, theta: ArrayLike | None = None, *, guess: ToolPoses | None = None) -> ConstraintPrediction:
        """``h(theta)``, shape (n_rows, 1) (``n_sets * n_rows`` for stacked parameter sets), mm.

        Parameters
        ----------
        theta : array_like, shape (P,), (n, P) or (n_sets * n, P)
            Machine errors then pivot corrections.
        guess : ToolPoses, optional
            An earlier prediction's ``poses`` (warm start).
        """
        th_m, piv, blocks = self._split(theta)
        Q = self._stacked_q(blocks)
        if guess is not None and guess.position.shape[0] != Q.shape[0]:
            guess = None
        poses = self.base.forward(Q, th_m, guess=guess)
        if self.pose_offset is not None:
            from ..machines.base import offset_poses

            poses = offset_poses(self.base, Q, th_m, poses, self.pose_offset)
        n, nd = self.n_poses, self._dist.size
        M = n + nd
        pos = poses.position.reshape(blocks, M, 3)
        ok = poses.success.reshape(blocks, M)
        xa = pos[:, :n]
        y = np.empty((blocks, n))
        c = self._codes
        row_ok = ok[:, :n].copy()
        if nd:
            xb = pos[:, n:]
            y[:, self._dist] = np.linalg.norm(xa[:, self._dist] - xb, axis=2)
            row_ok[:, self._dist] &= ok[:, n:]
        h = c == 1
        y[:, h] = xa[:, h, 2]
        b = c == 2
        if b.any():
            cp = self._row_pivots(piv, blocks)
            y[:, b] = np.linalg.norm(xa[:, b] - cp[:, b], axis=2)
        u = np.zeros((blocks, n, 3))
        u[:, h, 2] = 1.0
        if nd:
            d = xa[:, self._dist] - xb
            u[:, self._dist] = d / np.maximum(np.linalg.norm(d, axis=2, keepdims=True), 1e-300)
        if b.any():
            d = xa[:, b] - cp[:, b]
            u[:, b] = d / np.maximum(np.linalg.norm(d, axis=2, keepdims=True), 1e-300)
        msgs = list(poses.message)
        for j in range(blocks):
            for r, i in enumerate(self._dist):
                mb = poses.message[j * M + n + r]
                if mb and not msgs[j * M + i]:
                    msgs[j * M + i] = f"pose b: {mb}"
        poses = ToolPoses(poses.position, poses.rotation, poses.success, tuple(msgs), poses.state)
        return ConstraintPrediction(y=y.reshape(-1, 1), poses=poses, row_success=row_ok.reshape(-1), direction=u.reshape(-1, 3))

    def jacobian(self, theta: ArrayLike | None, prediction: ConstraintPrediction) -> NDArray:
        """``dh/dtheta``, shape (n_rows, 1, P + 3K), analytic (chain rule on ``tool_jacobian``)."""
        th_m, piv, blocks = self._split(theta)
        Q = self._stacked_q(blocks)
        Jt = self.base.tool_jacobian(Q, th_m, prediction.poses)[:, :3, :]
        n, nd, P = self.n_poses, self._dist.size, self.base.n_params
        M = n + nd
        Jt = Jt.reshape(blocks, M, 3, P)
        pos = prediction.poses.position.reshape(blocks, M, 3)
        xa, Ja = pos[:, :n], Jt[:, :n]
        J = np.zeros((blocks, n, self.n_params))
        c = self._codes
        if nd:
            d = xa[:, self._dist] - pos[:, n:]
            u = d / np.maximum(np.linalg.norm(d, axis=2, keepdims=True), 1e-300)
            J[:, self._dist, :P] = np.einsum("bri,brip->brp", u, Ja[:, self._dist] - Jt[:, n:])
        h = c == 1
        J[:, h, :P] = Ja[:, h, 2]
        b = np.flatnonzero(c == 2)
        if b.size:
            cp = self._row_pivots(piv, blocks)
            d = xa[:, b] - cp[:, b]
            u = d / np.maximum(np.linalg.norm(d, axis=2, keepdims=True), 1e-300)
            J[:, b, :P] = np.einsum("bri,brip->brp", u, Ja[:, b])
            for r, i in enumerate(b):
                k = self._pivot_index[i]
                J[:, i, P + 3 * k : P + 3 * k + 3] = -u[:, r]
        return J.reshape(-1, 1, self.n_params)

    # ------------------------------------------------- poses (what effects act on)
    @property
    def pose_q(self) -> NDArray:
        """Actuator positions of every pose the model solves, shape (n_rows + n_distances, N).

        The rows' poses a first (``pose_q[:n_poses] == q``), then the poses b
        of the distance rows in row order: the order of :meth:`predict`'s poses.
        """
        return np.vstack([self.qa, self.qb[self._dist]])

    @property
    def pose_row(self) -> NDArray:
        """Measurement row of every solved pose, shape (n_rows + n_distances,)."""
        return np.concatenate([np.arange(self.n_poses), self._dist])

    @property
    def pose_order(self) -> NDArray:
        """Time rank of every solved pose: row by row, pose a then (distance rows) pose b."""
        dist = self._codes == 0
        rank_a = np.arange(self.n_poses) + np.cumsum(dist) - dist
        return np.concatenate([rank_a, rank_a[self._dist] + 1])

    def poses_of(self, rows) -> NDArray:
        """Indices into :attr:`pose_q` of the poses of ``rows``, in the order ``subset(rows)`` solves them."""
        rows = np.arange(self.n_poses)[np.asarray(rows)]
        d = rows[self._codes[rows] == 0]
        return np.concatenate([rows, self.n_poses + np.searchsorted(self._dist, d)]).astype(int)

    def with_pose_q(self, pose_q: NDArray, *, keep_guess: bool = True) -> "ConstraintModel":
        """The same relations at other actuator positions of the solved poses (an effect's ``q + dq``)."""
        from dataclasses import replace

        pose_q = np.asarray(pose_q, dtype=float)
        n = self.n_poses
        qb = self.qb.copy()
        qb[self._dist] = pose_q[n:]
        return replace(self, qa=pose_q[:n], qb=qb, pivot_start=self.pivot_start, pivot_order=self.pivot_ids)

    def with_pose_offset(self, pose_offset: NDArray | None) -> "ConstraintModel":
        """The same relations with another base-frame tool-pose perturbation of the solved poses (None: none), shape (n_solved, 6)."""
        from dataclasses import replace

        off = None if pose_offset is None else np.asarray(pose_offset, dtype=float).reshape(-1, 6)
        return replace(self, pivot_start=self.pivot_start, pivot_order=self.pivot_ids, pose_offset=off)

    def effect_inputs(self, theta: NDArray, prediction: ConstraintPrediction | None) -> tuple[Machine, NDArray, ToolPoses | None]:
        """The machine, its geometry (pivots dropped) and the solved poses at which effects are evaluated (None without a prediction)."""
        return self.base, np.asarray(theta, dtype=float)[..., : self.base.n_params], None if prediction is None else prediction.poses

    def rows_jacobian(self, Jt: NDArray, prediction: ConstraintPrediction) -> NDArray:
        """Measurement-row derivative from a derivative of the solved poses.

        Parameters
        ----------
        Jt : ndarray, shape (n_rows + n_distances, 6, k)
            Tool point (rows 0-2) per unit of ``k`` variables, for every pose
            of :attr:`pose_q` (rows 3-5 are not used: the relations see points).
        prediction : ConstraintPrediction
            At which the rows are linearised (one parameter set).

        Returns
        -------
        ndarray, shape (n_rows, 1, k)
            ``u^T (J_a - J_b)`` for distances, ``u^T J_a`` otherwise (:attr:`ConstraintPrediction.direction`).
        """
        n = self.n_poses
        Jp = np.asarray(Jt)[:, :3]
        Jrow = Jp[:n].copy()
        if self._dist.size:
            Jrow[self._dist] -= Jp[n:]
        return np.einsum("ni,nik->nk", prediction.direction[:n], Jrow)[:, None, :]

    def region(self, prediction: ConstraintPrediction) -> NDArray:
        """Where each row was measured, shape (n_rows, 3), mm: the tool point of pose a (distances: the midpoint)."""
        n = self.n_poses
        pos = prediction.poses.position[: n + self._dist.size]
        out = pos[:n].copy()
        if self._dist.size:
            out[self._dist] = 0.5 * (out[self._dist] + pos[n:])
        return out

    def residual(self, prediction: ConstraintPrediction) -> NDArray:
        """``y_measured - h``, shape (n_rows, 1), mm."""
        if self.y_measured is None:
            raise InputError("this constraint model has no measured values")
        return self.y_measured - prediction.y

    def errors(self, residual: NDArray) -> tuple[NDArray, None]:
        """Per-row absolute error (mm) and no orientation error."""
        return np.abs(residual[:, 0]), None

    def rms(self, residual: NDArray) -> dict[str, float | None]:
        """``{"position": RMS of the row residuals (mm), "angle": None}`` (distances and heights are lengths)."""
        return {"position": float(np.sqrt(np.mean(residual[:, 0] ** 2))), "angle": None}

    def pivot_positions(self, theta: ArrayLike) -> dict[str, list[float]]:
        """Fitted pivot positions (base frame, mm) by id."""
        theta = np.asarray(theta, dtype=float)
        P = self.base.n_params
        return {p: (self.pivot_start[k] + theta[P + 3 * k : P + 3 * k + 3]).tolist() for k, p in enumerate(self.pivot_ids)}


#: Readings a ballbar pivot needs: its three coordinates are fitted, so three readings carry nothing else.
MIN_PIVOT_READINGS = 4


def check_pivot_readings(rec: ConstraintRecording) -> None:
    """RecordingError naming a pivot with fewer than :data:`MIN_PIVOT_READINGS` readings (a recording to identify from).

    A pivot per reading left no row for the geometry: Gauss-Newton's reduced system had no column and
    numpy raised on an empty array (a traceback).  Every command that identifies checks it
    (:func:`load_constraint_model`, :func:`bayescal.models.model_from_recording`); a planner's ``--given``
    rows need not (their pivots are marginalised).
    """
    pivots = [p for p, m in zip(rec.pivot, rec.measure) if m == "ballbar"]
    for pid in dict.fromkeys(pivots):
        n = pivots.count(pid)
        if n < MIN_PIVOT_READINGS:
            line = 2 + next(i for i, (p, m) in enumerate(zip(rec.pivot, rec.measure)) if m == "ballbar" and p == pid)
            raise RecordingError(rec.path, line, "pivot", f"pivot {pid!r} has {n} reading(s); its position is fitted "
                                 f"(3 coordinates), so a pivot needs at least {MIN_PIVOT_READINGS} readings")


def load_constraint_model(machine, path, *, frame: str = "base", dof: int | None = None):
    """The model of a constraint recording (docs/formats.md section 6) as every command makes it.

    Parameters
    ----------
    machine : Machine
    path : path or ConstraintRecording
        A recording with a ``measure`` column (distances, heights, ballbar radii), or one read.
    frame : {"base", "fit"}
        ``fit`` is refused: distances and radii see no instrument frame, heights are along the base z axis.
    dof : int, optional

    Returns
    -------
    (ConstraintRecording, ConstraintModel)
    """
    from ..errors import InputError
    from ..io.constraints import read_constraints

    if frame == "fit":
        raise InputError(
            f"frame fit: {getattr(path, 'path', path)} is a constraint recording; distances and ballbar radii do not see an "
            "instrument frame, and heights are measured along the base z axis (docs/formats.md section 6): "
            "use the base frame"
        )
    rec = path if isinstance(path, ConstraintRecording) else read_constraints(path)
    check_pivot_readings(rec)
    return rec, ConstraintModel.from_recording(machine, rec, dof=dof)
