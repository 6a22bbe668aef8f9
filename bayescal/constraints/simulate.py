"""Simulated constraint recordings: caliper distances, probe heights and ballbar circles.

The commanded actuator positions come from the *nominal* machine (what a
controller commands to reach a nominal tool point), the measured values from
the *true* machine at those positions plus instrument noise, as a real
measurement session does.  Tool points are turned into actuator positions by
:func:`solve_q_for_points`, a batched Newton solve on ``q`` with the
machine's ``actuator_jacobian``, so every kind gets it without an inverse
kinematics of its own.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..errors import InputError, KinematicsError
from ..io.constraints import DEFAULT_PIVOT, ConstraintRecording
from ..machines.base import Machine
from ..simulate import draw_errors, draw_poses

__all__ = ["solve_q_for_points", "simulate_distances", "simulate_ballbar", "ConstraintSimulation", "circle_points"]

_PLANES = {"xy": (0, 1), "xz": (0, 2), "yz": (1, 2)}


@dataclass(frozen=True)
class ConstraintSimulation:
    """A simulated constraint recording and the truth behind it."""

    recording: ConstraintRecording
    theta_true: NDArray
    pivots: dict
    seed: int | None

    def truth_dict(self, machine: Machine) -> dict:
        return {
            "seed": self.seed,
            "parameters": [{"name": n, "value": float(v)} for n, v in zip(machine.layout.names, self.theta_true)],
            "pivots": {k: list(map(float, v)) for k, v in self.pivots.items()},
        }


def solve_q_for_points(
    machine: Machine, points: ArrayLike, theta: ArrayLike | None = None, *, q0: ArrayLike | None = None,
    tol: float = 1e-10, max_iter: int = 50,
) -> NDArray:
    """Actuator positions that put the tool point at ``points`` (batched Newton on ``q``).

    Parameters
    ----------
    machine : Machine
    points : array_like, shape (n, 3)
        Tool points, base frame, mm.
    theta : array_like, optional
        Geometry (nominal if omitted).
    q0 : array_like, shape (N,) or (n, N), optional
        Start; the middle of ``q_limits`` by default.
    tol : float
        Tool-point error (mm) at which a point counts as reached.

    Returns
    -------
    ndarray, shape (n, N)
        With more actuators than three the minimum-norm step is taken.

    Raises
    ------
    KinematicsError
        If a point is not reached (out of the workspace).
    """
    pts = np.atleast_2d(np.asarray(points, dtype=float))
    n = pts.shape[0]
    q = np.broadcast_to(machine.home_q() if q0 is None else np.asarray(q0, dtype=float), (n, machine.n_actuators)).copy()
    poses = machine.forward(q, theta)
    for _ in range(max_iter):
        if not poses.success.all():
            break
        err = pts - poses.position
        if np.abs(err).max() < tol:
            return q
        J = machine.actuator_jacobian(q, theta, poses)[:, :3, :]
        dq = np.einsum("nij,nj->ni", np.linalg.pinv(J), err)
        # cap the step at a tenth of the stroke: far points are approached, not jumped to
        span = np.ptp(machine.q_limits, axis=1) if machine.q_limits is not None else np.full(q.shape[1], 100.0)
        fac = np.minimum(1.0, 0.1 / np.maximum(np.max(np.abs(dq) / span, axis=1), 1e-300))
        q = q + dq * fac[:, None]
        poses = machine.forward(q, theta, guess=poses)
    bad = np.flatnonzero(~poses.success | (np.abs(pts - poses.position).max(axis=1) >= tol))
    i = int(bad[0]) if bad.size else 0
    raise KinematicsError(
        f"tool point {pts[i].tolist()} cannot be reached by {machine.source} (Newton on q did not converge): "
        "outside the workspace, or in a direction the machine cannot move (a 2T1R or 2-DOF machine moves its tool "
        "point on a surface; for a ballbar circle choose a plane it moves in, e.g. --planes xz, or a smaller radius)"
    )


def circle_points(centre: ArrayLike, radius: float, plane: str, n: int, *, phase: float = 0.0) -> NDArray:
    """``n`` points evenly spaced on a circle of ``radius`` (mm) about ``centre`` in a base-frame plane (xy, xz, yz)."""
    if plane not in _PLANES:
        raise InputError(f"plane: expected one of {', '.join(_PLANES)}, got {plane!r}")
    a, b = _PLANES[plane]
    phi = phase + 2 * np.pi * np.arange(n) / n
    pts = np.broadcast_to(np.asarray(centre, dtype=float), (n, 3)).copy()
    pts[:, a] += radius * np.cos(phi)
    pts[:, b] += radius * np.sin(phi)
    return pts


def _theta_and_rng(machine, seed, theta, tolerance):
    rng = np.random.default_rng(seed)
    if theta is None:
        theta = draw_errors(machine, rng, tolerance=tolerance)
    return np.asarray(theta, dtype=float), rng


def simulate_ballbar(
    machine: Machine, radius: float, *, n_points: int = 24, pivot: ArrayLike | None = None,
    planes: tuple[str, ...] = ("xy",), seed: int | None = 0, theta: ArrayLike | None = None,
    tolerance: ArrayLike | None = None, sigma: float | None = None,
) -> ConstraintSimulation:
    """A ballbar session: circles of ``radius`` about a pivot, one per plane, read as distances.

    Parameters
    ----------
    machine : Machine
    radius : float
        Ballbar length, mm.
    n_points : int
        Readings per circle.
    pivot : array_like, shape (3,), optional
        Pivot (base frame, mm); the nominal tool point at the middle of ``q_limits`` by default.
    planes : tuple of {"xy", "xz", "yz"}
        One circle per plane through the pivot.
    seed : int
        Seeds the errors (if ``theta`` is None) and the noise.
    theta : array_like, optional
        True geometric errors; drawn from the tolerances if omitted.
    sigma : float, optional
        Noise of a reading (mm); the machine's ``sigma_position`` by default, 0 for noise-free.

    Raises
    ------
    InputError
        If a circle point cannot be commanded by the nominal machine within
        ``q_limits`` (unreachable, or actuator positions outside the limits):
        a ballbar test runs the whole circle, so no point is dropped.  The
        message names the radius, pivot and plane, how many points do not fit
        and about the largest radius that does.
    """
    if not radius > 0:
        raise InputError(f"ballbar radius: expected a positive length in mm, got {radius!r}")
    if not planes or len(set(planes)) != len(planes):
        # xy,xy ran the same circle twice, silently
        raise InputError(f"planes: expected distinct planes from {', '.join(_PLANES)}, got {','.join(planes)!r}")
    theta, rng = _theta_and_rng(machine, seed, theta, tolerance)
    if pivot is None:
        pivot = machine.forward(machine.home_q()[None]).position[0]
    pivot = np.asarray(pivot, dtype=float)
    if pivot.shape != (3,) or not np.isfinite(pivot).all():
        # a NaN pivot was blamed on the workspace ("the circle does not fit")
        raise InputError(f"pivot (--pivot): expected three finite numbers X,Y,Z in mm, got {pivot.tolist()}")
    pts = np.vstack([circle_points(pivot, radius, pl, n_points) for pl in planes])
    _check_circles_fit(machine, pivot, radius, planes, n_points)
    q = solve_q_for_points(machine, pts)
    true = machine.forward(q, theta)
    if not true.success.all():
        raise KinematicsError("the true machine cannot assemble a commanded ballbar pose")
    s = machine.noise.sigma_position if sigma is None else sigma
    value = np.linalg.norm(true.position - pivot, axis=1) + s * rng.normal(size=q.shape[0])
    n = q.shape[0]
    rec = ConstraintRecording(
        measure=("ballbar",) * n, qa=q, qb=np.full_like(q, np.nan), value=value, pivot=(DEFAULT_PIVOT,) * n,
    )
    return ConstraintSimulation(recording=rec, theta_true=theta, pivots={DEFAULT_PIVOT: pivot}, seed=seed)


def _circle_status(machine: Machine, pivot: NDArray, radius: float, plane: str, n: int) -> tuple[int, int, str]:
    """(points not reached, points reached outside ``q_limits``, first unreachable message) of one circle."""
    pts = circle_points(pivot, radius, plane, n)
    try:
        q = solve_q_for_points(machine, pts)
        unreached, why = np.zeros(n, dtype=bool), ""
    except KinematicsError as exc:
        # per point, to count them: the batch solve stops at the first pose that does not assemble
        q, unreached, why = np.full((n, machine.n_actuators), np.nan), np.zeros(n, dtype=bool), str(exc)
        for i in range(n):
            try:
                q[i] = solve_q_for_points(machine, pts[i : i + 1])[0]
            except KinematicsError:
                unreached[i] = True
    outside = np.zeros(n, dtype=bool)
    if machine.q_limits is not None:
        lo, hi = machine.q_limits[:, 0], machine.q_limits[:, 1]
        with np.errstate(invalid="ignore"):
            outside = ~unreached & ((q < lo) | (q > hi)).any(axis=1)
    return int(unreached.sum()), int(outside.sum()), why


def _largest_radius(machine: Machine, pivot: NDArray, radius: float, plane: str, n: int) -> float:
    """About the largest radius (mm, below ``radius``) whose ``n`` circle points all fit; 0 if none does.

    Bisection: the fitting radii need not be an interval, so this is a
    suggestion to try, not a bound.
    """
    lo, hi = 0.0, radius
    for _ in range(14):  # radius / 16384: finer than a ballbar's length is chosen
        mid = 0.5 * (lo + hi)
        unreached, outside, _ = _circle_status(machine, pivot, mid, plane, n)
        lo, hi = (mid, hi) if unreached + outside == 0 else (lo, mid)
    return lo


def _check_circles_fit(machine: Machine, pivot: NDArray, radius: float, planes: tuple[str, ...], n: int) -> None:
    """Refuse circles any of whose points the nominal machine cannot command within ``q_limits``.

    A real ballbar test runs the whole circle; a recording with readings the
    machine cannot command would be refused by every reader of it, and
    dropping those points would silently change the measurement plan.
    """
    problems = []
    for pl in planes:
        unreached, outside, why = _circle_status(machine, pivot, radius, pl, n)
        if unreached + outside == 0:
            continue
        parts = []
        if outside:
            parts.append(f"{outside} of {n} points need actuator positions outside [workspace] q_limits")
        if unreached:
            parts.append(f"{unreached} of {n} points cannot be reached ({why})")
        fit = _largest_radius(machine, pivot, radius, pl, n)
        hint = (f"at most about {np.floor(fit * 10) / 10:g} mm fits at this pivot in plane {pl}" if fit >= 0.1
                else "no circle fits about this pivot in this plane")
        problems.append(f"plane {pl}: {'; '.join(parts)} ({hint})")
    if problems:
        centre = ", ".join(f"{v:g}" for v in np.round(pivot, 6) + 0.0)  # no -0 or 1e-14 in the message
        raise InputError(
            f"ballbar circle of radius {radius:g} mm about the pivot ({centre}) mm does not fit the workspace of "
            f"{machine.source}: {'; '.join(problems)}. Choose a smaller radius (--ballbar), another pivot "
            "(--pivot) or other planes (--planes)"
        )


def simulate_distances(
    machine: Machine, n: int, *, seed: int | None = 0, theta: ArrayLike | None = None,
    tolerance: ArrayLike | None = None, sigma: float | None = None, heights: int = 0,
) -> ConstraintSimulation:
    """Caliper distances between random pairs of poses (and optionally probe heights).

    Poses are drawn within ``q_limits`` where the true machine assembles;
    ``heights`` adds that many rows of the tool point's z at further poses.
    """
    theta, rng = _theta_and_rng(machine, seed, theta, tolerance)
    if n < 1:
        raise InputError(f"distances: expected a positive number, got {n}")
    q = draw_poses(machine, 2 * n + heights, rng, theta)
    x = machine.forward(q, theta).position
    s = machine.noise.sigma_position if sigma is None else sigma
    dist = np.linalg.norm(x[:n] - x[n : 2 * n], axis=1)
    value = np.concatenate([dist, x[2 * n :, 2]]) + s * rng.normal(size=n + heights)
    qa = np.vstack([q[:n], q[2 * n :]])
    qb = np.vstack([q[n : 2 * n], np.full((heights, q.shape[1]), np.nan)])
    rec = ConstraintRecording(measure=("distance",) * n + ("height",) * heights, qa=qa, qb=qb, value=value)
    return ConstraintSimulation(recording=rec, theta_true=theta, pivots={}, seed=seed)
