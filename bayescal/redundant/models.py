"""The three error models of a redundantly actuated module, generic in m actuators and n DOF.

Linearised at a pose, with ``J_a = dq/dx`` (m x n), ``G = -dIK/dtheta``
(m x P: the joint-space error a geometric error causes at a fixed pose), geometric errors ``dtheta``, AJ following errors ``dq_f`` and
restrained deformations ``delta`` (all m-vectors in joint space):

1. **Geometric error model** (deformation as an error source)::

       J_a dx = G dtheta + dq_f + delta,    delta = C tau,   tau = N lam

   with ``C = K^-1`` the AJ compliances, ``N`` a basis of ``null(J_a^T)``
   (internal forces, equilibrium ``J_a^T tau = 0``) and ``lam`` the m - n
   internal-force magnitudes.  Square in ``(dx, lam)``; needs ``C``.

2. **Applicable error model** (projection): the deformation term ``M lam``
   with coefficient ``M = C N`` is removed by the projector onto the
   orthogonal complement of ``range(M)``, ``P = I - M M^+``::

       P J_a dx = P (G dtheta + dq_f)

   ``range(C N)`` does not change when every compliance is scaled, so
   ``P`` needs no stiffness value; with equal (or nominal-ratio)
   compliances ``M`` is ``N`` itself (``W^-1 N``) and ``P = J_a J_a^+``
   (``J_a (J_a^T W J_a)^-1 J_a^T W``).  Nonlinearly: the pose is the
   ``W``-weighted least-squares fit of the m inverse kinematics,
   :meth:`PoseModel.planar` with ``method="proposed"``.

3. **Practical error model** (model reduction): the following errors are
   removed by pitch compensation (laser interferometer), and the m zero
   offsets of the AJs by the calibrating zero position: there the module
   was aligned to the known pose ``x0`` at commanded ``q0``, so
   ``IK(x0; theta) = q0`` fixes the offsets from the other parameters.
   The identified vector is the geometry without the offsets, and no
   sensor on the AJs is needed.

The previous method for the corresponding non-redundant module (CNRPM)
ignores ``delta``: its pose follows from n actuators (``method="previous"``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..errors import InputError
from ..machines.raspm import Raspm
from .physics import internal_force_basis

__all__ = [
    "geometric_error_model",
    "projector_complement",
    "applicable_error_model",
    "practical_error_model",
    "ZeroPosition",
    "PoseModel",
]


def geometric_error_model(Ja: NDArray, e: NDArray, compliance: ArrayLike) -> tuple[NDArray, NDArray, NDArray]:
    """Solve the linearised geometric error model with restrained deformation.

    Parameters
    ----------
    Ja : ndarray, shape (n_poses, m, n)
    e : ndarray, shape (n_poses, m)
        Kinematic joint-space error ``G dtheta + dq_f``, mm.
    compliance : array_like, shape (m,)
        AJ compliances ``1 / k``, mm/N.

    Returns
    -------
    dx : ndarray, shape (n_poses, n)
        Pose error.
    delta : ndarray, shape (n_poses, m)
        Restrained deformations ``C N lam``, mm.
    lam : ndarray, shape (n_poses, m - n)
        Internal-force magnitudes, N.
    """
    Ja = np.asarray(Ja, dtype=float)
    n = Ja.shape[2]
    N = internal_force_basis(Ja)
    M = np.asarray(compliance, dtype=float)[None, :, None] * N
    A = np.concatenate([Ja, -M], axis=2)  # [J_a, -C N] (dx, lam) = e
    sol = np.linalg.solve(A, np.asarray(e, dtype=float)[..., None])[..., 0]
    dx, lam = sol[:, :n], sol[:, n:]
    return dx, np.einsum("nkj,nj->nk", M, lam), lam


def projector_complement(M: NDArray) -> NDArray:
    """``I - M M^+``: projector onto the orthogonal complement of ``range(M)``, shape (n_poses, m, m)."""
    M = np.asarray(M, dtype=float)
    return np.eye(M.shape[1])[None] - M @ np.linalg.pinv(M)


def applicable_error_model(Ja: NDArray, e: NDArray, weights: ArrayLike | None = None) -> tuple[NDArray, NDArray]:
    """Pose error of the projected (applicable) model, and the projector.

    Parameters
    ----------
    Ja : ndarray, shape (n_poses, m, n)
    e : ndarray, shape (n_poses, m)
        ``G dtheta + dq_f``, mm.
    weights : array_like, shape (m,), optional
        Nominal AJ stiffness *ratios* (equal by default); any common scale
        gives the same answer.

    Returns
    -------
    dx : ndarray, shape (n_poses, n)
        Least-squares solution of ``P J_a dx = P e`` (unique: ``P J_a`` has rank n).
    P : ndarray, shape (n_poses, m, m)
    """
    Ja = np.asarray(Ja, dtype=float)
    m = Ja.shape[1]
    w = np.ones(m) if weights is None else np.asarray(weights, dtype=float)
    M = internal_force_basis(Ja) / w[None, :, None]
    P = projector_complement(M)
    PJ = P @ Ja
    dx = np.einsum("nij,nj->ni", np.linalg.pinv(PJ), np.einsum("nij,nj->ni", P, e))
    return dx, P


def practical_error_model(
    Ja: NDArray, G: NDArray, G0: NDArray, offsets: ArrayLike, weights: ArrayLike | None = None
) -> NDArray:
    """Coefficient matrix of the practical (reduced) model: ``dx = H dtheta_r``.

    After pitch compensation (``dq_f = 0``) and the calibrating zero position
    (``IK(x0; theta) = q0``, the controller commanding with the offsets that
    this fixes), the zero offsets ``dtheta_o = -G0_o^-1 G0_r dtheta_r``
    follow from the rest, and the applicable model becomes

        P J_a dx = P (G_r - G_o G0_o^-1 G0_r) dtheta_r

    (``G0 = dIK/dtheta`` at the zero pose; ``_o`` / ``_r`` the offset / other
    columns): no stiffness, no following error, no sensor on the AJs; the
    pose error vanishes at the zero pose.

    Parameters
    ----------
    Ja : ndarray, shape (n_poses, m, n)
    G : ndarray, shape (n_poses, m, P)
    G0 : ndarray, shape (m, P)
        At the zero pose.
    offsets : array_like of int, shape (m,)
        Parameter index of each AJ's zero offset.
    weights : array_like, shape (m,), optional
        Nominal AJ stiffness ratios.

    Returns
    -------
    ndarray, shape (n_poses, n, P - m)
        Columns in the order of the non-offset parameters.
    """
    offsets = np.asarray(offsets, dtype=int)
    P = G.shape[2]
    rest = np.setdiff1d(np.arange(P), offsets)
    G0 = np.asarray(G0, dtype=float)
    reduced = G[:, :, rest] - G[:, :, offsets] @ np.linalg.solve(G0[:, offsets], G0[:, rest])
    n = Ja.shape[2]
    H = np.empty((G.shape[0], n, rest.size))
    for j in range(rest.size):
        H[:, :, j], _ = applicable_error_model(Ja, reduced[:, :, j], weights)
    return H


@dataclass(frozen=True)
class ZeroPosition:
    """The calibrating zero position: the module aligned at pose ``x0`` with commands ``q0``.

    Attributes
    ----------
    x0 : ndarray, shape (3,)
        Planar pose (mm, mm, rad).
    q0 : ndarray, shape (m,)
        Commanded AJ positions at which the module was found aligned, mm.
    """

    x0: NDArray
    q0: NDArray


@dataclass(frozen=True, eq=False)
class PoseModel:
    """The pose a model predicts for commanded actuator positions.

    Parameters
    ----------
    machine : Raspm
    method : {"proposed", "previous"}
        ``proposed``: the applicable (projected) model, every actuator with
        weight ``weights``; ``previous``: the corresponding non-redundant
        module (only the actuators ``subset``, ``machine.nonredundant`` by default).
    weights : ndarray, shape (m,), optional
        Nominal AJ stiffness ratios (equal by default); no stiffness value.
    zero : ZeroPosition, optional
        With it, the practical model: the AJ zero offsets are not free but
        follow from ``IK(x0; theta) = q0``.
    """

    machine: Raspm
    method: str = "proposed"
    weights: NDArray | None = None
    zero: ZeroPosition | None = None
    subset: tuple | None = None

    def __post_init__(self) -> None:
        if self.method not in ("proposed", "previous"):
            raise InputError(f"method: expected 'proposed' or 'previous', got {self.method!r}")
        if self.weights is not None:
            w = np.asarray(self.weights, dtype=float)
            if w.shape != (self.machine.n_actuators,) or np.any(w <= 0):
                raise InputError(f"weights: expected {self.machine.n_actuators} positive numbers, got {self.weights!r}")

    @property
    def offsets(self) -> NDArray:
        """Parameter indices fixed by the zero position (empty without one)."""
        return self.machine.offset_index() if self.zero is not None else np.zeros(0, dtype=int)

    @property
    def free_index(self) -> NDArray:
        """Indices of the parameters the model identifies."""
        return np.setdiff1d(np.arange(self.machine.n_params), self.offsets)

    def complete(self, theta: ArrayLike) -> NDArray:
        """``theta`` with the zero offsets solved from ``IK(x0; theta) = q0`` (rows (P,) or (k, P))."""
        theta = np.array(theta, dtype=float)
        if self.zero is None:
            return theta
        th = np.atleast_2d(theta).copy()
        x0 = np.tile(self.zero.x0, (th.shape[0], 1))
        idx = self.offsets
        for _ in range(4):  # IK is affine in the along-rail offset up to the rail tilt: converges in 2 steps
            r = self.machine.inverse_planar(x0, th) - self.zero.q0
            G = self.machine.ik_parameter_jacobian(x0, th)
            d = np.take_along_axis(G, idx[None, :, None].repeat(th.shape[0], 0), axis=2)[..., 0]
            th[:, idx] -= r / d
        return th.reshape(theta.shape)

    def planar(self, q: ArrayLike, theta: ArrayLike | None, *, x0: NDArray | None = None) -> tuple[NDArray, NDArray]:
        """Planar poses (n, 3) and success flags predicted for commanded ``q``."""
        return self._solve(q, self.complete(self.machine.check_theta(theta)), x0)

    def _solve(self, q, th, x0=None):
        if self.method == "previous":
            w = np.zeros(self.machine.n_actuators)
            w[list(self.machine.nonredundant if self.subset is None else self.subset)] = 1.0
        else:
            w = np.ones(self.machine.n_actuators) if self.weights is None else np.asarray(self.weights, dtype=float)
        return self.machine.fit_pose(q, th, w, x0=x0)

    def tool(self, q: ArrayLike, theta: ArrayLike | None) -> NDArray:
        """Tool ``(x mm, z mm, phi rad)`` per pose, shape (n, 3)."""
        q = self.machine.check_q(q)
        th = self.complete(self.machine.check_theta(theta))
        x, ok = self._solve(q, th)
        if not ok.all():
            i = int(np.flatnonzero(~ok)[0])
            raise InputError(f"pose {i + 1} (q = {q[i].tolist()}) cannot be solved by the {self.method} model")
        pos, _ = self.machine.tool_from_planar(x, th)
        return np.column_stack([pos[:, 0], pos[:, 2], x[:, 2]])

    def tool_jacobian(self, q: ArrayLike, theta: ArrayLike, *, h: float = 1e-3) -> NDArray:
        """``d tool / d theta`` (n, 3, P), by central differences in one vectorised solve.

        Finite differences because the weighted fit's exact derivative needs
        second derivatives of the inverse kinematics; the pose solve is
        closed-form per actuator and converged to 1e-11 mm, so a step of
        1e-3 mm (1e-6 rad) on a module of metres gives about 8 correct
        digits (truncation ~ h^2 / L^2, round-off ~ 1e-11 / h), far below
        the instruments' noise.  Columns of
        parameters fixed by the zero position are zero (they are functions
        of the others, folded in through :meth:`complete`).
        """
        q = self.machine.check_q(q)
        theta = np.asarray(theta, dtype=float)
        n, P = q.shape[0], self.machine.n_params
        free = self.free_index
        steps = np.where(np.array(self.machine.layout.units) == "rad", h * 1e-3, h)
        k = free.size
        th = np.tile(theta, (2 * k, 1))
        th[np.arange(k), free] += steps[free]
        th[k + np.arange(k), free] -= steps[free]
        th_rows = np.repeat(th, n, axis=0)
        q_rows = np.tile(q, (2 * k, 1))
        y = self.tool(q_rows, th_rows).reshape(2 * k, n, 3)
        J = np.zeros((n, 3, P))
        J[:, :, free] = np.moveaxis((y[:k] - y[k:]) / (2 * steps[free][:, None, None]), 0, 2)
        return J
