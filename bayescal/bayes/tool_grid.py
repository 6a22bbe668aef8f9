"""Cartesian (tool-point) compensation grids with uncertainty, for any machine kind.

Nodes span a box of nominal tool-point positions ``x`` (mm, base frame).
At each node the controller, commanding through the nominal geometry,
drives the actuators to ``q(x) = IK(x; 0)`` and the machine with the
identified errors ``theta_hat`` puts the tool point at
``p(q(x), theta_hat)``.  The node value is the residual error

    e(x) = p(q(x), theta_hat) - x        (mm; actual minus commanded),

what a bilinear/trilinear compensation table subtracts from the command
(the convention of :mod:`bayescal.compensation`).  Its std is the
linearised ``sqrt(diag(G C G^T))`` with ``G = dp/dtheta[idx]`` at
``q(x)`` (covariance ``C`` of the identified parameters), or the sample std
over posterior draws.  A machine that carries effects (``[effect.*]``
tables) has them applied at every node under the stated auxiliary channels
(``aux``: a payload, a temperature): ``q(x)`` is then replaced by
``q(x) + dq(q(x), aux)`` in ``p``, as in the actuator-space grid.

The inverse kinematics is numerical, so it works for every kind: a
task-priority Gauss-Newton on the nominal model (the tool point first, in
the minimum-norm sense; the orientation of the home pose ``q_limits``
middle second, in the null space of the position task).  A machine whose
tool point cannot move along an axis (a planar module: ``y``) gets one
node on that axis.  A node outside the reachable workspace, or reachable
only with actuators outside ``q_limits``, is an error naming the node and
the options that narrow the box.
"""

from __future__ import annotations

import itertools
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..errors import InputError
from ..geometry import so3_log
from ..io import write_text_atomic
from ..machines.base import Machine
from .accuracy import tool_point_std_at
from .grid import grid_summary

__all__ = ["ToolGrid", "tool_grid", "tool_box", "solve_tool_points", "NC_COLUMNS", "NC_COLUMNS_PLANAR"]

#: Columns of the NC-loadable CSV of a tool-space grid (``i`` fastest, then ``j``, then ``k``).
NC_COLUMNS = ("i", "j", "k", "x", "y", "z", "ex", "ey", "ez", "std_ex", "std_ey", "std_ez")
#: A grid with one node along y is written in the BIC format of :mod:`bayescal.compensation`.
NC_COLUMNS_PLANAR = ("i", "j", "x", "z", "ex", "ez", "std_ex", "std_ez")

_FLAT = 1e-6  # mm: a tool-point axis that moves less than this over the workspace gets one node


@dataclass(frozen=True)
class ToolGrid:
    """Residual tool-point error and its std at the nodes of a regular Cartesian grid.

    Attributes
    ----------
    machine_name : str
    axes : tuple of 3 ndarray
        Node coordinates along x, y, z (mm), increasing.
    q : ndarray, shape (n_nodes, n_actuators)
        Commanded actuator positions at each node (nominal inverse kinematics), C order over (x, y, z).
    error : ndarray, shape (n_x, n_y, n_z, 3)
        ``p(q(x), theta_hat) - x``, mm.
    std : ndarray, shape (n_x, n_y, n_z, 3)
        One-sigma of ``error`` per axis, mm.
    source : str
        How the std was obtained.
    points : ndarray, shape (n_nodes, 3)
        The nominal tool point commanded at each node, mm (equal to the node on the controlled axes).
    controlled : tuple of int
        The coordinates the actuators set (0: x, 1: y, 2: z); the others follow from them.
    """

    machine_name: str
    axes: tuple[NDArray, NDArray, NDArray]
    q: NDArray
    error: NDArray
    std: NDArray
    source: str
    points: NDArray | None = None
    controlled: tuple[int, ...] = (0, 1, 2)

    axis_names = ("x", "y", "z")
    axis_unit = "mm"

    @property
    def shape(self) -> tuple[int, ...]:
        return tuple(a.size for a in self.axes)

    @property
    def correction(self) -> NDArray:
        """What a controller adds to the command: ``-error``, mm."""
        return -self.error

    @property
    def nodes(self) -> NDArray:
        """Commanded nominal tool point per node, C order over (x, y, z), shape (n_nodes, 3), mm."""
        return np.array(list(itertools.product(*self.axes))) if self.points is None else self.points

    @property
    def planar(self) -> bool:
        """One node along y: the grid is a BIC grid over (x, z)."""
        return self.axes[1].size == 1 and self.axes[0].size >= 2 and self.axes[2].size >= 2

    def to_nc_csv(self) -> str:
        """The NC-loadable CSV (docs/formats.md section E8): BIC columns for a planar grid, else ``NC_COLUMNS``."""
        if self.planar:
            from ..compensation import CompensationGrid

            # (n_x, 1, n_z, 3) -> (n_z, n_x, 2) with (ex, ez)
            e = np.transpose(self.error[:, 0, :, :][..., [0, 2]], (1, 0, 2))
            s = np.transpose(self.std[:, 0, :, :][..., [0, 2]], (1, 0, 2))
            return CompensationGrid(self.axes[0], self.axes[2], e, s).to_csv()
        rows = [",".join(NC_COLUMNS)]
        pts = self.nodes.reshape(self.shape + (3,))
        for k in range(self.shape[2]):
            for j in range(self.shape[1]):
                for i in range(self.shape[0]):
                    vals = [*pts[i, j, k], *self.error[i, j, k], *self.std[i, j, k]]
                    rows.append(f"{i},{j},{k}," + ",".join(f"{v:.9g}" for v in vals))
        return "\n".join(rows) + "\n"

    def write_nc_csv(self, path: str | os.PathLike) -> Path:
        return write_text_atomic(path, self.to_nc_csv())

    def to_csv(self) -> str:
        """One row per node: x, y, z (mm), q1..qN, dx, dy, dz (correction, mm), sx, sy, sz (std, mm)."""
        nodes = self.nodes
        head = ["x", "y", "z"] + [f"q{i + 1}" for i in range(self.q.shape[1])] + ["dx", "dy", "dz", "sx", "sy", "sz"]
        vals = np.column_stack([nodes, self.q, self.correction.reshape(-1, 3), self.std.reshape(-1, 3)])
        return ",".join(head) + "\n" + "\n".join(",".join(f"{v:.9g}" for v in row) for row in vals) + "\n"

    def write_csv(self, path: str | os.PathLike) -> Path:
        return write_text_atomic(path, self.to_csv())

    def to_dict(self) -> dict:
        summary = grid_summary(self.error, self.std)  # the correction's size is the error's
        return {
            "machine": self.machine_name,
            "space": "tool",
            "axes": {n: a for n, a in zip(self.axis_names, self.axes)},
            "controlled_axes": [self.axis_names[a] for a in self.controlled],
            "n_nodes": int(np.prod(self.shape)),
            "std_source": self.source,
            "max_error_mm": summary["max_correction_mm"],
            "rms_error_mm": summary["rms_correction_mm"],
            **summary,
        }

    def report(self) -> str:
        d = self.to_dict()
        box = ", ".join(f"{n} {a[0]:g}..{a[-1]:g}" for n, a in zip(self.axis_names, self.axes))
        return "\n".join([
            f"bayescal tool-space compensation grid of '{self.machine_name}'",
            f"  nodes           {' x '.join(str(s) for s in self.shape)} over {box} (mm)",
            f"  error           max {d['max_error_mm']:.5f} mm, RMS {d['rms_error_mm']:.5f} mm (actual minus commanded)",
            f"  its std (3-D)   max {d['max_std_mm']:.5f} mm, RMS {d['rms_std_mm']:.5f} mm ({self.source})",
        ])


def tool_box(machine: Machine, *, n_samples: int = 2000, seed: int = 0, coverage: float = 0.8) -> NDArray:
    """A default box of tool points: the central ``coverage`` of nominal tool points over ``q_limits``.

    Returns
    -------
    ndarray, shape (3, 2)
        ``[lo, hi]`` per axis, mm; ``lo == hi`` (the mean) for an axis the tool point does not move along.
    """
    q = machine.sample_q(n_samples, np.random.default_rng(seed))
    poses = machine.forward(q, None)
    p = poses.position[poses.success]
    if p.shape[0] < 10:
        raise InputError(f"{machine.source}: too few poses within [workspace] q_limits can be solved to span a tool box")
    a = (1 - coverage) / 2
    box = np.quantile(p, [a, 1 - a], axis=0).T
    flat = (p.max(axis=0) - p.min(axis=0)) < _FLAT
    box[flat] = p[:, flat].mean(axis=0)[:, None]
    return box


def solve_tool_points(
    machine: Machine, targets: ArrayLike, *, axes: tuple[int, ...] = (0, 1, 2), max_iter: int = 60, tol: float = 1e-7
) -> tuple[NDArray, NDArray]:
    """Nominal inverse kinematics of tool points: actuator positions putting the nominal tool point at ``targets``.

    Task-priority Gauss-Newton from the middle of ``q_limits``: the tool
    point's coordinates ``axes`` in the minimum-norm sense, then the home
    pose's orientation in the null space of that task.

    Parameters
    ----------
    targets : array_like, shape (n, 3)
        Tool points, mm (only the coordinates ``axes`` are targets).
    axes : tuple of int
        The controlled coordinates (0: x, 1: y, 2: z).

    Returns
    -------
    q : ndarray, shape (n, n_actuators)
    ok : ndarray of bool, shape (n,)
        Converged (error of the controlled coordinates below ``tol`` mm) and within ``q_limits``.
    """
    X = np.atleast_2d(np.asarray(targets, dtype=float))
    ax = list(axes)
    home = machine.home_q()
    home_pose = machine.forward(home[None], None)
    if not home_pose.success.all():
        raise InputError(f"{machine.source}: the middle of [workspace] q_limits cannot be solved; no start for the grid")
    R0 = home_pose.rotation[0]
    n, m = X.shape[0], home.size
    q = np.tile(home, (n, 1))
    ok = np.zeros(n, bool)
    alive = np.ones(n, bool)
    span = np.ptp(machine.q_limits, axis=1) if machine.q_limits is not None else np.ones(m)
    for _ in range(max_iter):
        idx = np.flatnonzero(alive & ~ok)
        if idx.size == 0:
            break
        poses = machine.forward(q[idx], None)
        good = poses.success
        alive[idx[~good]] = False
        if not good.all():
            idx = idx[good]
            if idx.size == 0:
                break
            poses = machine.forward(q[idx], None)
        rp = X[idx][:, ax] - poses.position[:, ax]
        done = np.linalg.norm(rp, axis=1) < tol
        ok[idx[done]] = True
        J = machine.actuator_jacobian(q[idx], None, poses)
        Jp, Jr = J[:, ax], J[:, 3:]
        # the position task by SVD with a relative rank cut; its null space explicitly (a projector
        # I - pinv(Jp) Jp would be ~1e-16 instead of 0 and a second pinv would blow that up)
        U, sv, Vt = np.linalg.svd(Jp, full_matrices=True)
        k = sv.shape[1]
        keep = sv > 1e-9 * sv[:, :1]
        inv = np.where(keep, 1.0 / np.where(keep, sv, 1.0), 0.0)
        V = np.swapaxes(Vt, -1, -2)
        dq1 = np.einsum("nik,nk->ni", V[:, :, :k], inv * np.einsum("nji,nj->ni", U[:, :, :k], rp))
        null = np.ones((idx.size, m), bool)
        null[:, :k] = ~keep
        Nb = V * null[:, None, :]
        rr = so3_log(R0[None] @ np.swapaxes(poses.rotation, -1, -2))
        z = np.einsum("nij,nj->ni", np.linalg.pinv(Jr @ Nb, rcond=1e-9), rr - np.einsum("nij,nj->ni", Jr, dq1))
        dq = dq1 + np.einsum("nij,nj->ni", Nb, z)
        # damp long steps: Newton from far away can jump to another assembly branch
        scale = np.minimum(1.0, 0.25 / np.maximum(np.max(np.abs(dq) / span, axis=1), 1e-300))
        q[idx[~done]] += (dq * scale[:, None])[~done]
    # actuators the forward kinematics does not read (redundant drives) were left where they started:
    # command what the pose requires of them, as a controller does, and check them against q_limits too
    q = machine.compatible_q(q, None)
    if machine.q_limits is not None:
        lo, hi = machine.q_limits[:, 0], machine.q_limits[:, 1]
        ok &= np.all((q >= lo - 1e-9) & (q <= hi + 1e-9), axis=1)
    return q, ok


def controlled_axes(machine: Machine, box: NDArray) -> tuple[int, ...]:
    """The tool-point coordinates the actuators set: as many as the rank of the position Jacobian at home,
    those with the largest extent in ``box``."""
    home = machine.home_q()[None]
    Jp = machine.actuator_jacobian(home, None, machine.forward(home, None))[0, :3]
    sv = np.linalg.svd(Jp, compute_uv=False)
    r = int(np.sum(sv > 1e-9 * sv[0]))
    extent = box[:, 1] - box[:, 0]
    return tuple(sorted(np.argsort(-extent, kind="stable")[:r].tolist()))


def tool_grid(
    machine: Machine,
    theta: ArrayLike,
    *,
    covariance: ArrayLike | None = None,
    free: ArrayLike | None = None,
    samples: ArrayLike | None = None,
    n: int = 5,
    ranges: dict | None = None,
    aux: dict | None = None,
) -> ToolGrid:
    """The Cartesian grid of residual tool-point errors and their std for identified errors ``theta``.

    Parameters
    ----------
    machine : Machine
    theta : array_like, shape (P,)
    covariance : array_like, shape (k, k), optional
        Covariance of ``theta[free]``.
    free : array_like of bool, shape (P,), optional
    samples : array_like, shape (S, k), optional
        Posterior draws of ``theta[free]`` instead of a covariance.
    n : int
        Nodes per axis (an axis the tool point does not move along gets one).
    ranges : dict, optional
        ``{"x": (lo, hi), ...}`` in mm narrowing the default box (:func:`tool_box`).
    aux : dict of str to float, optional
        Auxiliary channels at which the machine's stored effects
        (``machine.effects``, ``[effect.*]`` tables) act at every node, e.g.
        ``{"payload_kg": 5.0, "temp_C": 25.0}``, exactly as in
        :func:`bayescal.bayes.grid.compensation_grid`: the drives commanded
        to ``q(x)`` stand at ``q(x) + dq(q(x), aux)``
        (:func:`bayescal.effects.stored.static_effect_delta_q`), so the
        node's error includes the effects.  A channel not given is absent
        (no payload); an effect that needs one (thermal expansion:
        ``temp_C``) is an InputError naming the machine file's table.

    Returns
    -------
    ToolGrid
    """
    theta = machine.check_theta(theta)
    from .grid import check_grid_size

    check_grid_size(machine, n, "tool", n_samples=0 if samples is None else len(samples))
    axes, nodes, q, ctrl = _reachable_nodes(machine, n, ranges)
    nominal = machine.forward(q, None)
    # where the drives really stand at each node under the stated aux (the same rule as the actuator grid)
    q_act, dq_dtheta = machine.node_actuators(q, theta, aux)
    est = machine.forward(q_act, theta, guess=nominal)
    if not est.success.all():
        i = int(np.flatnonzero(~est.success)[0])
        raise InputError(f"grid node {i + 1} (q = {q[i].tolist()}) cannot be solved with the identified errors; narrow the grid with --range")
    # against the nominal point actually commanded: equal to the node on the controlled axes, and the
    # right reference on an axis the actuators do not set (there the node coordinate is only a mean)
    error = est.position - nominal.position
    dx = machine.node_tool_offset(q, theta, aux)
    if dx is not None:  # effects that move the tool, not the drives (a column bending under its load)
        error = error + dx[:, :3]
    std, source = tool_point_std_at(machine, q_act, theta, free, covariance=covariance, samples=samples, caller="tool_grid",
                                    dq_dtheta=dq_dtheta)
    shape = tuple(a.size for a in axes) + (3,)
    return ToolGrid(machine.name, axes, q, error.reshape(shape), std.reshape(shape), source, nominal.position, ctrl)


def _reachable_nodes(machine, n: int, ranges: dict | None):
    """The grid's node axes, tool-point nodes (mm), their actuator positions and the controlled axes.

    The default box shrinks about its middle until every node is reachable; a range the user gave is kept
    (InputError naming the first node that cannot be reached).
    """
    box = tool_box(machine)
    for name, (lo, hi) in (ranges or {}).items():
        a = "xyz".index(name)
        if not lo <= hi:
            raise InputError(f"--range {name}={lo}:{hi}: expected LO <= HI")
        box[a] = (lo, hi)
    ctrl = controlled_axes(machine, box)
    given = set(ranges or {})
    for _ in range(6):
        axes = tuple(
            np.linspace(lo, hi, n) if a in ctrl and hi - lo >= _FLAT else np.array([0.5 * (lo + hi)])
            for a, (lo, hi) in enumerate(box)
        )
        nodes = np.array(list(itertools.product(*axes)))
        q, ok = solve_tool_points(machine, nodes, axes=ctrl)
        free_axes = [a for a in ctrl if "xyz"[a] not in given]
        if ok.all() or not free_axes:
            break
        # the workspace of a parallel machine is rarely a box: shrink the default box about its
        # middle (never a range the user gave) until every node is reachable
        for a in free_axes:
            mid, half = box[a].mean(), 0.5 * (box[a, 1] - box[a, 0])
            box[a] = (mid - 0.7 * half, mid + 0.7 * half)
    if not ok.all():
        i = int(np.flatnonzero(~ok)[0])
        raise InputError(
            f"grid node {i + 1} (tool point {np.round(nodes[i], 4).tolist()} mm) cannot be reached within [workspace] "
            f"q_limits; narrow the grid with --range x=LO:HI, --range y=LO:HI or --range z=LO:HI (mm; box now "
            + ", ".join(f"{c} {lo:.4g}:{hi:.4g}" for c, (lo, hi) in zip("xyz", box)) + ")"
        )
    return axes, nodes, q, ctrl
