"""Predicted tool-point uncertainty: the parameter covariance pushed through the tool Jacobian, or posterior draws
pushed through the kinematics."""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..errors import InputError
from ..machines.base import Machine
from ..simulate import draw_poses

__all__ = [
    "evaluation_poses", "tool_point_jacobian", "tool_point_std", "workspace_accuracy", "tool_point_draws",
    "tool_point_std_at",
]


def evaluation_poses(machine: Machine, n: int = 50, *, seed: int = 0, fallback: NDArray | None = None) -> NDArray:
    """``n`` actuator vectors spread over ``q_limits`` (or ``fallback``, e.g. the recording's q, without limits)."""
    if machine.q_limits is None:
        if fallback is None:
            raise InputError(f"{machine.source}: no [workspace] q_limits to draw evaluation poses from")
        return np.asarray(fallback, dtype=float)
    # drawn on the geometry (a fitted instrument's stations are bound to the recording's poses, not these)
    return draw_poses(machine.geometry_part[0], n, np.random.default_rng(seed))


def tool_point_jacobian(machine: Machine, q: ArrayLike, theta: ArrayLike, idx: ArrayLike) -> NDArray:
    """Tool-point rows of the machine's geometry Jacobian, columns ``idx``: shape (n, 3, n_idx), mm per unit.

    Evaluated on the geometry part (:attr:`Machine.geometry_part`): the accuracy of the machine at poses
    it was not measured at, in its base frame; a fitted instrument frame (the session's) and other nuisance
    parameters get zero columns.
    """
    geo, gidx = machine.geometry_part
    q = geo.check_q(q)
    theta = np.asarray(theta, dtype=float)
    th = theta[..., gidx]
    poses = geo.forward(q, th)
    if not poses.success.all():
        i = int(np.flatnonzero(~poses.success)[0])
        raise InputError(f"evaluation pose {i + 1} (q = {q[i].tolist()}) cannot be solved: {poses.message[i]}")
    Jg = geo.tool_jacobian(q, th, poses)[:, :3]
    pos = {int(j): k for k, j in enumerate(gidx)}
    idx = np.asarray(idx, dtype=int)
    out = np.zeros((q.shape[0], 3, idx.size))
    for k, j in enumerate(idx):
        if int(j) in pos:
            out[:, :, k] = Jg[:, :, pos[int(j)]]
    return out


def tool_point_std(G: NDArray, cov: NDArray) -> NDArray:
    """Per pose and axis: the std of the predicted tool point, shape (n, 3), mm.

    ``G`` (n, 3, k) from :func:`tool_point_jacobian`, ``cov`` (k, k) or a
    stack (m, k, k) giving (m, n, 3).
    """
    # diag(G C G^T) without forming the 3x3 blocks' off-diagonals
    return np.sqrt(np.clip(np.einsum("nak,...kl,nal->...na", G, cov, G), 0.0, None))


def workspace_accuracy(G: NDArray, cov: NDArray) -> NDArray:
    """RMS over poses of the 3-D tool-point std ``sqrt(trace(G C G^T))``, mm; scalar or (m,) for a stack."""
    s = tool_point_std(G, cov)
    return np.sqrt(np.mean(np.sum(s**2, axis=-1), axis=-1))


def tool_point_draws(machine: Machine, q: ArrayLike, theta: ArrayLike, idx: ArrayLike, draws: ArrayLike,
                     dq_dtheta: NDArray | None = None) -> NDArray:
    """The tool point at every pose for every draw of ``theta[idx]``, shape (S, n, 3), mm.

    Parameters
    ----------
    machine : Machine
    q : array_like, shape (n, n_actuators)
        Actuator positions (mm or rad per actuator).
    theta : array_like, shape (P,)
        The parameters the draws leave as they are (those outside ``idx``).
    idx : array_like of int, shape (k,)
        The parameters the draws give.
    draws : array_like, shape (S, k)
        Draws of ``theta[idx]``, e.g. posterior samples.
    dq_dtheta : ndarray, shape (n, n_actuators, P), optional
        How the drives at ``q`` move with the parameters (effect parameters,
        :meth:`Machine.node_actuators`): each draw's ``q`` moves by
        ``dq_dtheta (draw - theta)``, linearised (the effects' ``dq`` are
        microns), its tool point from the exact kinematics.

    Returns
    -------
    ndarray, shape (S, n, 3)
        Tool points, mm, base frame.  Poses that cannot be solved are not
        flagged here (the callers solved them at ``theta`` already).
    """
    q = np.asarray(q, dtype=float)
    D = np.asarray(draws, dtype=float)
    th = np.tile(theta, (D.shape[0], 1))
    th[:, idx] = D
    qs = np.tile(q, (D.shape[0], 1))
    if dq_dtheta is not None:
        idx = np.asarray(idx, dtype=int)
        shift = np.einsum("nak,sk->sna", np.asarray(dq_dtheta)[:, :, idx], D - np.asarray(theta, dtype=float)[idx])
        qs = qs + shift.reshape(qs.shape)
    # one forward call for every draw at every pose
    pos = machine.forward(qs, np.repeat(th, q.shape[0], axis=0)).position
    return pos.reshape(D.shape[0], q.shape[0], 3)


def tool_point_std_at(
    machine: Machine,
    q: ArrayLike,
    theta: ArrayLike,
    free: ArrayLike | None = None,
    *,
    covariance: ArrayLike | None = None,
    samples: ArrayLike | None = None,
    caller: str = "tool_point_std_at",
    dq_dtheta: NDArray | None = None,
) -> tuple[NDArray, str]:
    """Per pose and axis the one-sigma std of the tool point, from posterior draws or a covariance.

    What every compensation grid reports at its nodes: with ``samples`` the
    sample std (``ddof=1``) of the exact forward kinematics over the draws
    (:func:`tool_point_draws`); else with ``covariance`` the linearised
    ``sqrt(diag(G C G^T))``, ``G = dp/dtheta[free]`` at ``theta``.

    Parameters
    ----------
    machine, q
        As for :func:`tool_point_draws`.
    theta : array_like, shape (P,)
        Identified errors (the linearisation point; the parameters outside ``free`` for the draws).
    free : array_like of bool, shape (P,), optional
        Which parameters ``covariance``/``samples`` refer to (default all).
    covariance : array_like, shape (k, k), optional
        Covariance of ``theta[free]``.
    samples : array_like, shape (S, k), optional
        Draws of ``theta[free]``; used instead of ``covariance`` when both are given.
    caller : str
        The function named in the message when neither is given.
    dq_dtheta : ndarray, shape (n, n_actuators, P), optional
        How the drives at ``q`` move with the parameters (effect parameters
        of a grid's nodes, :meth:`Machine.node_actuators`): their columns add
        ``(dp/dq) dq_dtheta`` to ``G`` (draws: :func:`tool_point_draws`).

    Returns
    -------
    std : ndarray, shape (n, 3)
        mm.
    source : str
        How it was obtained (for reports).

    Raises
    ------
    InputError
        ``samples`` or ``covariance`` of the wrong shape, or neither given.
    """
    idx = np.flatnonzero(np.ones(machine.n_params, bool) if free is None else np.asarray(free, dtype=bool))
    if samples is not None:
        S = np.asarray(samples, dtype=float)
        if S.ndim != 2 or S.shape[1] != idx.size:
            raise InputError(f"samples: expected shape (n_draws, {idx.size}), got {S.shape}")
        return (tool_point_draws(machine, q, theta, idx, S, dq_dtheta).std(axis=0, ddof=1),
                f"sample std over {S.shape[0]} posterior draws")
    if covariance is not None:
        C = np.asarray(covariance, dtype=float)
        if C.shape != (idx.size, idx.size):
            raise InputError(f"covariance: expected shape ({idx.size}, {idx.size}), got {C.shape}")
        G = tool_point_jacobian(machine, q, theta, idx)
        if dq_dtheta is not None:
            poses = machine.forward(machine.check_q(q), theta)
            Ja = machine.actuator_jacobian(machine.check_q(q), theta, poses)[:, :3]
            G = G + np.einsum("nia,nak->nik", Ja, np.asarray(dq_dtheta)[:, :, idx])
        return tool_point_std(G, C), "linearised G C G^T"
    raise InputError(f"{caller}: give a covariance or posterior samples for the std")
