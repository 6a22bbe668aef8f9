"""A conformance check every kinematic family can be run through.

``check_machine(machine)`` exercises the :class:`~bayescal.machines.base.Machine`
contract that all consumers (measurement models, solvers, filters, samplers,
studies) rely on, in the spirit of scikit-learn's ``check_estimator``:

* parameter names are unique and follow docs/formats.md section 3 (``chain<i>.<key>[.<component>]``
  or ``tool.point.<component>``), units are known, tolerances positive;
* ``forward`` succeeds on poses drawn within ``q_limits``, returns proper
  rotations, and is deterministic;
* ``tool_jacobian`` agrees with central finite differences for every
  parameter, for the tool point and for the small platform rotation;
* the machine file written by ``to_toml(theta)`` and read back predicts the
  same poses (the calibrated-machine contract of docs/formats.md section 3);
* a per-pose ``theta`` of shape ``(n_poses, P)`` gives what per-pose calls give;
* a forward-kinematics start from ``guess_from_measurement`` reaches the same
  solution as a cold start.

A new machine kind should pass it before it is registered in
:data:`bayescal.machines.KINDS`; its test module runs
``assert check_machine(machine) == []``.
"""

from __future__ import annotations

import re

import numpy as np
from numpy.typing import NDArray

from ..errors import BayescalError
from ..geometry import so3_log
from .base import Machine, ToolPoses
from .files import machine_from_text

__all__ = ["check_machine", "MachineCheckError", "KNOWN_UNITS", "PARAM_NAME"]

#: Units a geometric parameter may have (docs/formats.md: millimetres and radians).
KNOWN_UNITS = frozenset({"mm", "rad"})

#: Parameter names of docs/formats.md section 3: ``chain<i>.<key>[.<component>]`` or ``tool.point.<component>``;
#: serial chains (section 5) ``joint<i>.<key>[.<component>]`` and ``tool.rpy.<component>``; a
#: hybrid machine prefixes its modules' names with ``m<k>.``.
# chain<i>.<key>[.<component>]; a key may itself be a dotted path into a sub-table of the chain
# (the redundant module's `chain3.slider2.rail_origin.x`)
# (a linear delta names its chains `tower<i>`, as its machine file does)
PARAM_NAME = re.compile(
    r"^(m[1-9][0-9]*\.)*((chain|tower)[1-9][0-9]*(\.[a-z][a-z0-9_]*){1,3}|joint[1-9][0-9]*(\.[a-z][a-z0-9_]*){1,2}"
    r"|tool\.(point|rpy)\.[a-z][a-z0-9_]*)$"
)
#: The instrument frame's parameters (docs/formats.md section 4; bayescal.machines.framed).
FRAME_PARAM_NAME = re.compile(r"^frame\.(origin|rotation_vector)\.[xyz]$")

#: Agreement demanded of two solutions of the same pose (mm for positions, rad for rotations).
SAME_POSE_TOL = 1e-9
#: Relative agreement of the analytic Jacobian with central differences (per column).
JACOBIAN_RTOL = 1e-5


class MachineCheckError(BayescalError, AssertionError):
    """A machine failed :func:`check_machine` (``problems`` lists what)."""

    def __init__(self, problems: list[str]):
        self.problems = list(problems)
        super().__init__("machine check failed:\n  - " + "\n  - ".join(self.problems))


def _pose_difference(a: ToolPoses, b: ToolPoses) -> tuple[float, float]:
    """Largest tool-point difference (mm) and platform rotation difference (rad)."""
    dp = float(np.abs(a.position - b.position).max())
    dr = float(np.linalg.norm(so3_log(a.rotation @ np.swapaxes(b.rotation, -1, -2)), axis=-1).max())
    return dp, dr


def _check_layout(machine: Machine) -> list[str]:
    problems = []
    names, units = machine.layout.names, machine.layout.units
    if len(set(names)) != len(names):
        dup = sorted({n for n in names if names.count(n) > 1})
        problems.append(f"layout: duplicate parameter names {dup}")
    for n, u in zip(names, units):
        if not PARAM_NAME.match(n) and not FRAME_PARAM_NAME.match(n):
            problems.append(f"layout: parameter name '{n}' is not chain<i>.<key>[.<component>] or tool.point.<component>")
        if u not in KNOWN_UNITS:
            problems.append(f"layout: parameter '{n}' has unit '{u}', expected one of {sorted(KNOWN_UNITS)}")
    tol = np.asarray(machine.tolerance, dtype=float)
    if tol.shape != (machine.n_params,):
        problems.append(f"tolerance: expected shape ({machine.n_params},), got {tol.shape}")
    elif not np.all(np.isfinite(tol) & (tol > 0)):
        bad = [names[i] for i in np.flatnonzero(~(np.isfinite(tol) & (tol > 0)))]
        problems.append(f"tolerance: expected finite positive one-sigma values, not for {bad}")
    return problems


def _check_poses(poses: ToolPoses, n: int, what: str) -> list[str]:
    problems = []
    if poses.position.shape != (n, 3) or poses.rotation.shape != (n, 3, 3):
        return [f"{what}: expected position (n, 3) and rotation (n, 3, 3), got {poses.position.shape} and {poses.rotation.shape}"]
    if np.shape(poses.success) != (n,) or len(poses.message) != n:
        problems.append(f"{what}: expected one success flag and one message per pose")
    if not np.all(poses.success):
        i = int(np.flatnonzero(~np.asarray(poses.success))[0])
        problems.append(f"{what}: pose {i + 1} not solved ({poses.message[i]!r})")
    R = poses.rotation
    orth = np.abs(R @ np.swapaxes(R, 1, 2) - np.eye(3)).max()
    if not orth < 1e-10 or not np.all(np.linalg.det(R) > 0):
        problems.append(f"{what}: rotations are not proper rotation matrices (|R R^T - I| = {orth:.1e})")
    return problems


def _check_jacobian(machine: Machine, q: NDArray, theta: NDArray, poses: ToolPoses) -> list[str]:
    n, P = q.shape[0], machine.n_params
    J = np.asarray(machine.tool_jacobian(q, theta, poses))
    if J.shape != (n, 6, P):
        return [f"tool_jacobian: expected shape ({n}, 6, {P}), got {J.shape}"]
    problems = []
    tol = np.asarray(machine.tolerance, dtype=float)
    # columns scaled by the tolerances are comparable across units; floors per row block
    Js = J * tol
    floor_pos = 1e-7 * max(np.abs(Js[:, :3]).max(), 1e-300)
    floor_rot = 1e-7 * max(np.abs(Js[:, 3:]).max(), 1e-300)
    for k, name in enumerate(machine.layout.names):
        # a step of 1e-3 tolerances: truncation error ~1e-6 relative, round-off far below
        h = 1e-3 * tol[k]
        e = np.zeros(P)
        e[k] = h
        pp = machine.forward(q, theta + e, guess=poses)
        pm = machine.forward(q, theta - e, guess=poses)
        if not (np.all(pp.success) and np.all(pm.success)):
            problems.append(f"tool_jacobian: forward failed at theta +/- a small step of '{name}'")
            continue
        fd = np.concatenate(
            [(pp.position - pm.position) / (2 * h), so3_log(pp.rotation @ np.swapaxes(pm.rotation, 1, 2)) / (2 * h)],
            axis=1,
        )
        for rows, floor, label in ((slice(0, 3), floor_pos, "tool point"), (slice(3, 6), floor_rot, "rotation")):
            a, b = J[:, rows, k] * tol[k], fd[:, rows] * tol[k]
            err = float(np.abs(a - b).max())
            if err > JACOBIAN_RTOL * float(np.abs(b).max()) + floor:
                problems.append(
                    f"tool_jacobian: column '{name}' ({label} rows) differs from central differences by "
                    f"{err / tol[k]:.3e} per {machine.layout.units[k]} (largest entry {np.abs(b).max() / tol[k]:.3e})"
                )
    return problems


def _check_file_round_trip(machine: Machine, q: NDArray, theta: NDArray, poses: ToolPoses) -> list[str]:
    try:
        again = machine_from_text(machine.to_toml(theta), path=f"<{machine.kind} to_toml>")
    except BayescalError as exc:
        return [f"to_toml: the written machine file cannot be read back ({exc})"]
    problems = []
    if again.kind != machine.kind or again.n_actuators != machine.n_actuators:
        problems.append(f"to_toml: read back as kind {again.kind!r} with {again.n_actuators} actuators")
        return problems
    back = again.forward(q)  # cold start: the file alone must determine the poses
    problems += _check_poses(back, q.shape[0], "to_toml read back, forward")
    if not problems:
        dp, dr = _pose_difference(back, poses)
        if dp > SAME_POSE_TOL or dr > SAME_POSE_TOL:
            problems.append(
                f"to_toml: the machine file of nominal + theta predicts other poses (tool point {dp:.2e} mm, "
                f"rotation {dr:.2e} rad apart)"
            )
    if (machine.q_limits is None) != (again.q_limits is None) or (
        machine.q_limits is not None and not np.array_equal(machine.q_limits, again.q_limits)
    ):
        problems.append("to_toml: q_limits not written back unchanged")
    if machine.noise != again.noise:
        problems.append(f"to_toml: measurement noise read back as {again.noise}, expected {machine.noise}")
    return problems


def _check_per_pose_theta(machine: Machine, q: NDArray, thetas: NDArray) -> list[str]:
    n = q.shape[0]
    batch = machine.forward(q, thetas)
    problems = _check_poses(batch, n, "forward with per-pose theta")
    if problems:
        return problems
    Jb = machine.tool_jacobian(q, thetas, batch)
    for i in range(n):
        one = machine.forward(q[i : i + 1], thetas[i])
        dp, dr = _pose_difference(one, ToolPoses(batch.position[i : i + 1], batch.rotation[i : i + 1], batch.success[i : i + 1], batch.message[i : i + 1]))
        if dp > SAME_POSE_TOL or dr > SAME_POSE_TOL:
            problems.append(f"forward: theta of shape (n, P) differs from the per-pose call at pose {i + 1} ({dp:.2e} mm, {dr:.2e} rad)")
            break
        Ji = machine.tool_jacobian(q[i : i + 1], thetas[i], one)
        scale = np.abs(Ji).max()
        if np.abs(Ji[0] - Jb[i]).max() > 1e-8 * scale:
            problems.append(f"tool_jacobian: theta of shape (n, P) differs from the per-pose call at pose {i + 1}")
            break
    return problems


def _check_guess(machine: Machine, q: NDArray, theta: NDArray, poses: ToolPoses) -> list[str]:
    problems = []
    variants = {
        "position and rotation": dict(rotation=poses.rotation),
        "position and tool axis": dict(axis=poses.axis),
        "position only": {},
    }
    for label, extra in variants.items():
        guess = machine.guess_from_measurement(q, poses.position, **extra)
        if guess is None:
            continue
        sol = machine.forward(q, theta, guess=guess)
        bad = _check_poses(sol, q.shape[0], f"forward from guess_from_measurement ({label})")
        if bad:
            problems += bad
            continue
        dp, dr = _pose_difference(sol, poses)
        if dp > SAME_POSE_TOL or dr > SAME_POSE_TOL:
            problems.append(
                f"guess_from_measurement ({label}): leads to another solution ({dp:.2e} mm, {dr:.2e} rad from the cold start)"
            )
    return problems


def check_machine(machine: Machine, *, seed: int = 0, n_poses: int = 8, strict: bool = False) -> list[str]:
    """Run a machine through the conformance checks of the :class:`Machine` contract.

    Parameters
    ----------
    machine : Machine
        A machine with ``[workspace] q_limits`` (poses are drawn within them).
    seed : int
        Seeds the poses and the geometric errors used (errors of one
        tolerance, drawn ``N(0, tolerance^2)``).
    n_poses : int
        Poses per check.
    strict : bool
        Raise :class:`MachineCheckError` instead of returning the problems.

    Returns
    -------
    list of str
        One line per problem found; empty when the machine conforms.

    Raises
    ------
    MachineCheckError
        With ``strict=True``, if any problem was found.

    Examples
    --------
    >>> from bayescal.machines.check import check_machine
    >>> from bayescal.machines.files import load_machine
    >>> check_machine(load_machine("examples/prs3/machine.toml"))
    []
    """
    rng = np.random.default_rng(seed)
    problems = _check_layout(machine)
    if machine.q_limits is None:
        problems.append("q_limits: the machine has none; a conformance check needs [workspace] q_limits to draw poses")
    else:
        P = machine.n_params
        tol = np.asarray(machine.tolerance, dtype=float).reshape(-1)[:P]
        q = machine.sample_q(n_poses, rng)
        theta = rng.normal(size=P) * tol
        nominal = machine.forward(q)
        problems += _check_poses(nominal, n_poses, "forward (nominal)")
        poses = machine.forward(q, theta)
        bad = _check_poses(poses, n_poses, "forward (with errors)")
        problems += bad
        if not bad:
            again = machine.forward(q, theta)
            if not (np.array_equal(again.position, poses.position) and np.array_equal(again.rotation, poses.rotation)):
                problems.append("forward: two identical calls gave different answers (not deterministic)")
            problems += _check_jacobian(machine, q, theta, poses)
            problems += _check_file_round_trip(machine, q, theta, poses)
            problems += _check_per_pose_theta(machine, q, theta + rng.normal(size=(n_poses, P)) * tol)
            problems += _check_guess(machine, q, theta, poses)
    if strict and problems:
        raise MachineCheckError(problems)
    return problems
