"""A BIC grid predicted from an identified model, with the std of every node value.

The redundant module's bilinear interpolation compensation grid
(:mod:`bayescal.compensation`) is either **measured** (the procedure reads
the residual error at each node with the dial gauge; the node std is then
the gauge's one-sigma, nothing else) or **predicted** from an identified
model, here.  For a controller commanding through geometry ``theta_cmd``
(the nominal model, or the current one), the residual planar position error
at node ``x = (x, z)`` (rotation 0), relative to the zero pose ``x0``, is
predicted by the model with geometry ``theta_hat``:

    e(x) = [t(q(x); theta_hat) - t(q(x0); theta_hat)] - (x - x0),      q(.) = IK(.; theta_cmd)

(``t``: the model's tool ``(x, z)``, :meth:`PoseModel.tool`).  Its std is
the linearised propagation of the covariance ``C`` of ``theta_hat``
(:attr:`StepResult.covariance`):

    std_e = sqrt(diag(G C G^T)),   G = d e / d theta = J_t(q(x)) - J_t(q(x0))

(``J_t`` the finite-difference tool Jacobian, offsets folded in through the
zero position).  A predicted node has no measurement noise.  Checked on
simulation in ``tests/redundant/test_grid_std.py``.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

from ..compensation import CompensationGrid
from ..errors import InputError
from .models import PoseModel

__all__ = ["predicted_grid"]


def predicted_grid(
    ctrl: PoseModel,
    theta_hat: ArrayLike,
    covariance: ArrayLike,
    *,
    theta_cmd: ArrayLike | None = None,
    n: int = 5,
    x_range: ArrayLike | None = None,
    z_range: ArrayLike | None = None,
) -> CompensationGrid:
    """Predicted residual error and its std at the nodes of an ``n x n`` grid.

    Parameters
    ----------
    ctrl : PoseModel
        The model (with its zero position: its ``x0`` is the reference).
    theta_hat : array_like, shape (P,)
        Identified geometry (mm, rad).
    covariance : array_like, shape (P, P)
        Covariance of ``theta_hat`` (mm^2, rad^2), e.g. ``StepResult.covariance``.
    theta_cmd : array_like, shape (P,), optional
        Geometry the controller commands with; default ``theta_hat`` (the
        predicted error is then zero up to the nonlinearity and the grid
        carries only the std).
    n : int
        Nodes along x and along z.
    x_range, z_range : (min, max), mm, optional
        Default the machine's ``pose_range``.

    Returns
    -------
    CompensationGrid
        ``error`` and ``std`` (mm), shape (n, n, 2).
    """
    m = ctrl.machine
    if ctrl.zero is None:
        raise InputError("ctrl: expected a PoseModel with a zero position (the grid is relative to it)")
    P = m.n_params
    C = np.asarray(covariance, dtype=float)
    if C.shape != (P, P) or not np.all(np.isfinite(C)):
        raise InputError(f"covariance: expected a finite ({P}, {P}) matrix, got shape {C.shape}")
    if int(n) != n or n < 2:
        raise InputError(f"n: expected an integer >= 2, got {n!r}")
    th_hat = ctrl.complete(m.check_theta(theta_hat))
    th_cmd = th_hat if theta_cmd is None else ctrl.complete(m.check_theta(theta_cmd))
    pr = m.pose_range
    if (x_range is None or z_range is None) and pr is None:
        raise InputError("x_range, z_range: required when the machine file has no [pose_range]")
    xs = np.linspace(*(pr[0] if x_range is None else x_range), int(n))
    zs = np.linspace(*(pr[1] if z_range is None else z_range), int(n))
    X, Z = np.meshgrid(xs, zs)
    x0 = ctrl.zero.x0
    xn = np.vstack([x0[None], np.column_stack([X.ravel(), Z.ravel(), np.zeros(X.size)])])
    q = m.inverse_planar(xn, th_cmd)
    t = ctrl.tool(q, th_hat)[:, :2]
    err = (t[1:] - t[0]) - (xn[1:, :2] - x0[:2])
    J = ctrl.tool_jacobian(q, th_hat)[:, :2]
    G = J[1:] - J[0]  # (k, 2, P)
    var = np.einsum("kip,pr,kir->ki", G, C, G)
    std = np.sqrt(np.maximum(var, 0.0))
    return CompensationGrid(xs=xs, zs=zs, error=err.reshape(zs.size, xs.size, 2), std=std.reshape(zs.size, xs.size, 2))
