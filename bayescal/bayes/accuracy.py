"""Predicted tool-point uncertainty: the parameter covariance pushed through the tool Jacobian."""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..errors import InputError
from ..machines.base import Machine
from ..simulate import draw_poses

__all__ = ["evaluation_poses", "tool_point_jacobian", "tool_point_std", "workspace_accuracy"]


def evaluation_poses(machine: Machine, n: int = 50, *, seed: int = 0, fallback: NDArray | None = None) -> NDArray:
    """``n`` actuator vectors spread over ``q_limits`` (or ``fallback``, e.g. the recording's q, without limits)."""
    if machine.q_limits is None:
        if fallback is None:
            raise InputError(f"{machine.source}: no [workspace] q_limits to draw evaluation poses from")
        return np.asarray(fallback, dtype=float)
    return draw_poses(machine, n, np.random.default_rng(seed))


def tool_point_jacobian(machine: Machine, q: ArrayLike, theta: ArrayLike, idx: ArrayLike) -> NDArray:
    """Tool-point rows of the machine's Jacobian, columns ``idx``: shape (n, 3, n_idx), mm per unit."""
    q = machine.check_q(q)
    poses = machine.forward(q, theta)
    if not poses.success.all():
        i = int(np.flatnonzero(~poses.success)[0])
        raise InputError(f"evaluation pose {i + 1} (q = {q[i].tolist()}) cannot be solved: {poses.message[i]}")
    return machine.tool_jacobian(q, theta, poses)[:, :3][:, :, np.asarray(idx, dtype=int)]


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
