"""Simulated machines and recordings: the truth that tests and studies check against.

A true machine is the nominal one plus errors drawn from the tolerances.
Poses are drawn within ``q_limits``; the instrument adds Gaussian noise.
Physical effects plug in as :class:`PoseTransform` objects: each maps the
commanded actuator positions and the per-pose geometric errors (with the
auxiliary channels and the measurement order) to what the machine really
does, before the forward kinematics.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Protocol, Sequence

import numpy as np
from numpy.typing import NDArray

from .errors import InputError
from .geometry import so3_exp, so3_log, tangent_basis
from .io.recording import Recording
from .machines.base import Machine
from .measurement import rows_per_pose

__all__ = ["PoseTransform", "SimulatedRecording", "draw_errors", "draw_poses", "simulate_recording", "measure"]


class PoseTransform(Protocol):
    """A physical effect as seen by the simulator (see the module docstring).

    A transform may also have a method ``pose_offset(q, theta, aux, order)``
    returning a base-frame tool-pose perturbation (n, 6) (mm, then a small
    rotation in rad) or None, evaluated at the same inputs as
    :meth:`transform`: what the structure does after the kinematics (a link
    bending under gravity).  :func:`measure` adds it to the solved poses.
    """

    def transform(
        self, q: NDArray, theta: NDArray, aux: dict[str, NDArray], order: NDArray
    ) -> tuple[NDArray, NDArray]:
        """Return the actual ``q`` (n, m) and per-pose ``theta`` (n, P)."""


@dataclass(frozen=True)
class SimulatedRecording:
    """A recording with its truth.

    Attributes
    ----------
    recording : Recording
    theta_true : ndarray, shape (P,)
        Geometric errors of the true machine.
    seed : int
    names : tuple of str
    """

    recording: Recording
    theta_true: NDArray
    seed: int
    names: tuple[str, ...]
    info: dict = field(default_factory=dict)

    def truth_dict(self) -> dict:
        return {
            "seed": self.seed,
            "parameters": [{"name": n, "value": float(v)} for n, v in zip(self.names, self.theta_true)],
            **self.info,
        }


def draw_errors(machine: Machine, rng: np.random.Generator, *, tolerance: NDArray | None = None) -> NDArray:
    """Geometric errors ``N(0, tolerance^2)`` per parameter (mm or rad)."""
    from .limits import MAX_FILE_NUMBER

    tol = machine.tolerance if tolerance is None else np.asarray(tolerance, dtype=float)
    if not (np.all(np.isfinite(tol)) and np.all(tol >= 0) and np.all(tol <= MAX_FILE_NUMBER)):
        # --tolerance-scale 1e300 drew errors of 1e298 mm: the kinematics' SVD failed (a traceback)
        raise InputError(f"tolerance: expected one-sigma errors from 0 to {MAX_FILE_NUMBER:g} (mm or rad), got up to "
                         f"{float(np.nanmax(np.abs(tol))):g} (the machine file's [tolerance] times --tolerance-scale)")
    return rng.normal(size=machine.n_params) * tol


def draw_poses(machine: Machine, n: int, rng: np.random.Generator, theta: NDArray | None = None) -> NDArray:
    """``n`` actuator vectors within ``q_limits`` at which the machine (with ``theta``) can be solved.

    A number of poses whose arrays would not fit in memory is refused first
    (:func:`bayescal.limits.check_memory`).
    """
    from .limits import check_memory

    # per pose: the actuator vector, forward kinematics' state and its Jacobian, twice (draws are redrawn)
    check_memory(2.0 * n * 8 * (64 + 16 * machine.n_params), f"{int(n):,} poses",
                 "lower the number of poses (--poses, --eval-poses)")
    out: list[NDArray] = []
    for _ in range(50):
        q = machine.sample_q(max(2 * (n - len(out)), 8), rng)
        ok = machine.forward(q, theta).success
        out.extend(q[ok])
        if len(out) >= n:
            return np.array(out[:n])
    why = ""
    if theta is not None and np.any(theta) and machine.forward(machine.sample_q(16, rng)).success.any():
        why = ("; the nominal machine solves there, the true one drawn from the tolerances does not (tolerances, or "
               "--tolerance-scale, too large?)")
    raise InputError(f"{machine.source}: could not find {n} solvable poses within q_limits{why}")


def measure(
    machine: Machine,
    q: NDArray,
    theta: NDArray,
    dof: int,
    rng: np.random.Generator | None,
    *,
    aux: dict[str, NDArray] | None = None,
    effects: Sequence[PoseTransform] = (),
) -> Recording:
    """What the instrument reads at commanded ``q`` on the true machine ``theta``.

    Noise: ``N(0, sigma_position^2)`` per axis; orientation ``exp(N(0,
    sigma_angle^2 I)) R`` (6-DOF) or the axis tilted by ``N(0, sigma_angle^2)``
    in two tangent directions (5-DOF).  ``rng=None`` gives noise-free data.
    """
    rows_per_pose(dof)
    n = q.shape[0]
    aux = {} if aux is None else dict(aux)
    q_true, th = q, np.broadcast_to(theta, (n, machine.n_params)).copy()
    offset = None
    for eff in effects:
        off = eff.pose_offset(q_true, th, aux, np.arange(n)) if hasattr(eff, "pose_offset") else None
        if off is not None:
            offset = (0.0 if offset is None else offset) + np.asarray(off, dtype=float)
        q_true, th = eff.transform(q_true, th, aux, np.arange(n))
    poses = machine.forward(q_true, th)
    if not poses.success.all():
        i = int(np.flatnonzero(~poses.success)[0])
        raise InputError(f"simulated pose {i + 1} (q = {q[i].tolist()}) cannot be solved: {poses.message[i]}")
    if offset is not None:
        from .machines.base import offset_poses

        poses = offset_poses(machine, q_true, th, poses, offset)
    sp, sa = machine.noise.sigma_position, machine.noise.sigma_angle
    pos = poses.position.copy()
    R = poses.rotation
    if rng is not None:
        pos += rng.normal(size=pos.shape) * sp
    rotvec = axis = None
    if dof == 6:
        noise = rng.normal(size=(n, 3)) * sa if rng is not None else np.zeros((n, 3))
        rotvec = so3_log(so3_exp(noise) @ R)
    elif dof == 5:
        axis = R[:, :, 2].copy()
        if rng is not None:
            t = tangent_basis(axis)
            e = rng.normal(size=(n, 2)) * sa
            axis = axis + e[:, :1] * t[:, 0] + e[:, 1:] * t[:, 1]
            axis /= np.linalg.norm(axis, axis=1, keepdims=True)
    return Recording(q=q.copy(), position=pos, rotvec=rotvec, axis=axis, aux=aux)


def simulate_recording(
    machine: Machine,
    n_poses: int,
    *,
    seed: int,
    dof: int = 6,
    tolerance: NDArray | None = None,
    theta_true: NDArray | None = None,
    effects: Sequence[PoseTransform] = (),
    aux: dict[str, NDArray] | None = None,
    q: NDArray | None = None,
) -> SimulatedRecording:
    """Draw a true machine and poses, and simulate what the instrument records.

    Parameters
    ----------
    machine : Machine
        Nominal machine (with ``q_limits`` and the instrument noise).
    n_poses : int
    seed : int
        Seeds everything (errors, poses, noise).
    dof : {6, 5, 3}
    tolerance : ndarray, shape (P,), optional
        One-sigma errors to draw the true machine from; the machine's by default.
    theta_true : ndarray, shape (P,), optional
        Use these errors instead of drawing them.
    effects : sequence of PoseTransform
        Physics beyond the geometric model, applied before the kinematics.
    aux : dict, optional
        Auxiliary channels to record (each of shape (n_poses,)).
    q : ndarray, shape (n_poses, n_actuators), optional
        Commanded actuator positions (a planned pose file) instead of drawing them.

    Returns
    -------
    SimulatedRecording
    """
    if n_poses < 1:
        raise InputError(f"n_poses: expected at least 1, got {n_poses}")
    rng = np.random.default_rng(seed)
    theta = draw_errors(machine, rng, tolerance=tolerance) if theta_true is None else np.asarray(theta_true, float)
    if q is None:
        q = draw_poses(machine, n_poses, rng, theta)
    else:
        q = machine.check_q(q)
        if q.shape[0] != n_poses:
            raise InputError(f"q: expected {n_poses} poses, got {q.shape[0]}")
        reach = machine.forward(q, theta)
        if not reach.success.all():
            i = int(np.flatnonzero(~reach.success)[0])
            raise InputError(f"pose {i + 1} (q = {q[i].tolist()}) cannot be solved on the drawn true machine")
    rec = measure(machine, q, theta, dof, rng, aux=aux, effects=effects)
    return SimulatedRecording(recording=rec, theta_true=theta, seed=seed, names=machine.layout.names)
