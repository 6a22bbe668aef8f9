"""Rotations, small-rotation Jacobians and direction tilts, vectorised.

All functions accept stacked inputs: a rotation vector of shape ``(..., 3)``
and a rotation matrix of shape ``(..., 3, 3)``.  Angles are in radians.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

__all__ = [
    "rpy_matrix",
    "rpy_from_matrix",
    "skew",
    "so3_exp",
    "so3_log",
    "left_jacobian_inverse",
    "right_jacobian_inverse",
    "tilt_axes",
    "tilted_direction",
    "tangent_basis",
    "tilt_torsion_angles",
    "rotation_from_tilt_torsion",
]

_SMALL = 1e-8
#: The identity, read-only: added to every Rodrigues-type formula (the same values as a fresh ``np.eye(3)``).
_EYE = np.eye(3)
_EYE.setflags(write=False)
#: Angle (rad) above which so3_log reads the axis from the symmetric part of R.
_NEAR_PI = 3.0


def skew(w: ArrayLike) -> NDArray:
    """Cross-product matrix ``[w]x`` with ``[w]x v = w x v``; shape ``(..., 3, 3)``."""
    w = np.asarray(w, dtype=float)
    out = np.zeros(w.shape[:-1] + (3, 3))
    out[..., 0, 1], out[..., 0, 2] = -w[..., 2], w[..., 1]
    out[..., 1, 0], out[..., 1, 2] = w[..., 2], -w[..., 0]
    out[..., 2, 0], out[..., 2, 1] = -w[..., 1], w[..., 0]
    return out


def _norms(v: NDArray) -> NDArray:
    """``numpy.linalg.norm(v, axis=-1)`` for real ``v``: its arithmetic (the same values), without its dispatch."""
    return np.sqrt(np.add.reduce(v * v, axis=(-1,)))


def _branches(th: NDArray, small: NDArray) -> tuple[NDArray, int]:
    """``(th with 1 where small, how many entries are small)`` for :func:`_where_small`."""
    k = int(np.count_nonzero(small))
    return (np.where(small, 1.0, th) if 0 < k else th), k


def _where_small(small: NDArray, k: int, near_zero, away) -> NDArray:
    """``numpy.where(small, near_zero(), away())``, evaluating only the branches some entry takes.

    The values are the same bit for bit (``numpy.where`` copies the chosen
    branch); on the small arrays of a kinematic chain the branch no entry
    takes cost more numpy calls than the arithmetic of the other.
    ``k`` is the number of small entries (:func:`_branches`).
    """
    if k == 0:
        return away()
    if k == small.size:
        return near_zero()
    return np.where(small, near_zero(), away())


def so3_exp(w: ArrayLike) -> NDArray:
    """Rotation matrix of a rotation vector (axis times angle, rad), Rodrigues' formula."""
    w = np.asarray(w, dtype=float)
    th = _norms(w)[..., None, None]
    K = skew(w)
    small = th < _SMALL
    th_safe, k = _branches(th, small)
    # Taylor series below _SMALL keeps full precision where sin(th)/th cancels.
    a = _where_small(small, k, lambda: 1.0 - th**2 / 6.0, lambda: np.sin(th_safe) / th_safe)
    b = _where_small(small, k, lambda: 0.5 - th**2 / 24.0, lambda: (1.0 - np.cos(th_safe)) / th_safe**2)
    return _EYE + a * K + b * (K @ K)


def so3_log(R: ArrayLike) -> NDArray:
    """Rotation vector (rad) of a rotation matrix, angle in [0, pi], accurate up to a half turn."""
    R = np.asarray(R, dtype=float)
    tr = np.clip((np.trace(R, axis1=-2, axis2=-1) - 1.0) / 2.0, -1.0, 1.0)
    th = np.arccos(tr)
    v = np.stack(
        [R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]],
        axis=-1,
    )
    small = th < 1e-6
    th_safe, k = _branches(th, small)
    fac = _where_small(small, k, lambda: 0.5 + th**2 / 12.0, lambda: th_safe / (2.0 * np.sin(th_safe)))
    out = fac[..., None] * v
    near_pi = th > _NEAR_PI
    if np.any(near_pi):
        # Near pi the antisymmetric part vanishes and arccos loses half the digits: take the
        # angle from atan2 and the axis from the symmetric part, (R + R^T)/2 - cos(th) I = (1 - cos th) a a^T
        # (rotary tables and turntables reach half a turn routinely).
        Rn, vn, cn = R[near_pi], v[near_pi], tr[near_pi]
        thn = np.arctan2(0.5 * np.linalg.norm(vn, axis=-1), cn)
        B = 0.5 * (Rn + np.swapaxes(Rn, -1, -2)) - cn[:, None, None] * np.eye(3)
        j = np.argmax(np.einsum("nii->ni", B), axis=-1)
        a = B[np.arange(B.shape[0]), :, j]
        a /= np.linalg.norm(a, axis=-1, keepdims=True)
        a *= np.where(np.einsum("ni,ni->n", a, vn) < 0, -1.0, 1.0)[:, None]
        out[near_pi] = thn[:, None] * a
    return out


def left_jacobian(phi: ArrayLike) -> NDArray:
    """Left Jacobian of SO(3): ``exp([phi + d]x) = exp([J_l(phi) d]x) exp([phi]x) + O(d^2)``, shape (..., 3, 3)."""
    phi = np.asarray(phi, dtype=float)
    th = _norms(phi)[..., None, None]
    K = skew(phi)
    small = th < 1e-5
    ts, k = _branches(th, small)
    a = _where_small(small, k, lambda: 0.5 - th**2 / 24.0, lambda: (1.0 - np.cos(ts)) / ts**2)
    b = _where_small(small, k, lambda: 1.0 / 6.0 - th**2 / 120.0, lambda: (ts - np.sin(ts)) / ts**3)
    return _EYE + a * K + b * (K @ K)


def left_jacobian_inverse(phi: ArrayLike) -> NDArray:
    """Inverse left Jacobian of SO(3): ``log(exp(d) exp(phi)) = phi + J_l^-1(phi) d + O(d^2)``."""
    phi = np.asarray(phi, dtype=float)
    th = _norms(phi)[..., None, None]
    K = skew(phi)
    small = th < 1e-5
    th_safe, k = _branches(th, small)
    c = _where_small(
        small, k,
        lambda: 1.0 / 12.0 + th**2 / 720.0,
        lambda: 1.0 / th_safe**2 - (1.0 + np.cos(th_safe)) / (2.0 * th_safe * np.sin(th_safe)),
    )
    return _EYE - 0.5 * K + c * (K @ K)


def right_jacobian_inverse(phi: ArrayLike) -> NDArray:
    """Inverse right Jacobian of SO(3): ``log(exp(phi) exp(d)) = phi + J_r^-1(phi) d + O(d^2)``."""
    return left_jacobian_inverse(-np.asarray(phi, dtype=float))


def tilt_axes(u: ArrayLike) -> tuple[int, int]:
    """The two base axes about which a direction ``u`` is tilted.

    The axis along which ``u`` has its largest component is left out, so a
    vertical rail (along z) tilts about x and y, and a revolute axis along y
    tilts about x and z, as in the seeds' error models.
    """
    u = np.asarray(u, dtype=float)
    drop = int(np.argmax(np.abs(u)))
    keep = [i for i in range(3) if i != drop]
    return keep[0], keep[1]


def _cross_basis(i: int, u: NDArray) -> NDArray:
    """``e_i x u`` for a base axis ``e_i`` and ``u`` of shape (3,): ``numpy.cross``'s products written out.

    ``tilted_direction`` runs for every axis of a machine at every
    evaluation; ``numpy.cross`` on two 3-vectors costs far more than these
    six products (the values are the same: ``e_i`` has one 1 and two 0s).
    """
    e = (1.0 if i == 0 else 0.0, 1.0 if i == 1 else 0.0, 1.0 if i == 2 else 0.0)
    return np.array([e[1] * u[2] - e[2] * u[1], e[2] * u[0] - e[0] * u[2], e[0] * u[1] - e[1] * u[0]])


def tilted_direction(u0: ArrayLike, axes: tuple[int, int], tilt: ArrayLike) -> tuple[NDArray, NDArray]:
    """Unit direction tilted by two small angles, and its derivative.

    ``u = normalise(u0 + t1 (e_a x u0) + t2 (e_b x u0))``: to first order a
    rotation of ``u0`` by ``t1`` about base axis ``a`` and ``t2`` about ``b``.
    The normalised form is exact for any tilt, so a calibrated machine file
    stores ``u`` itself and any implementation reproduces it.

    Parameters
    ----------
    u0 : array_like, shape (3,)
        Nominal unit direction.
    axes : (int, int)
        Base axes of the two tilts (see :func:`tilt_axes`).
    tilt : array_like, shape (..., 2)
        Tilt angles, rad.

    Returns
    -------
    u : ndarray, shape (..., 3)
        Tilted unit direction.
    du : ndarray, shape (..., 3, 2)
        Derivative of ``u`` with respect to the two tilts.
    """
    u0 = np.asarray(u0, dtype=float)
    tilt = np.asarray(tilt, dtype=float)
    g = np.stack([_cross_basis(axes[0], u0), _cross_basis(axes[1], u0)], axis=-1)  # (3, 2)
    n = u0 + tilt @ g.T
    norm = np.linalg.norm(n, axis=-1)[..., None]
    u = n / norm
    P = (np.eye(3) - u[..., :, None] * u[..., None, :]) / norm[..., None]
    return u, P @ g


def tangent_basis(n: ArrayLike) -> NDArray:
    """Two unit vectors orthogonal to unit vectors ``n``; shape ``(..., 2, 3)``."""
    n = np.asarray(n, dtype=float)
    helper = np.zeros_like(n)
    idx = np.argmin(np.abs(n), axis=-1)
    np.put_along_axis(helper, idx[..., None], 1.0, axis=-1)
    t1 = np.cross(n, helper)
    t1 /= np.linalg.norm(t1, axis=-1, keepdims=True)
    t2 = np.cross(n, t1)
    return np.stack([t1, t2], axis=-2)


def rotation_from_tilt_torsion(phi: ArrayLike, theta: ArrayLike, psi: ArrayLike) -> NDArray:
    """Rotation of the tilt-and-torsion (T&T) convention of the seeds.

    ``R = Rz(phi) Ry(theta) Rz(psi - phi)``: tilt the z axis by ``theta``
    towards the azimuth ``phi``, then turn by the torsion ``psi``.
    """
    phi, theta, psi = (np.asarray(a, dtype=float) for a in (phi, theta, psi))

    def rz(a):
        c, s = np.cos(a), np.sin(a)
        z, o = np.zeros_like(a), np.ones_like(a)
        return np.stack([np.stack([c, -s, z], -1), np.stack([s, c, z], -1), np.stack([z, z, o], -1)], -2)

    c, s = np.cos(theta), np.sin(theta)
    z, o = np.zeros_like(theta), np.ones_like(theta)
    ry = np.stack([np.stack([c, z, s], -1), np.stack([z, o, z], -1), np.stack([-s, z, c], -1)], -2)
    return rz(phi) @ ry @ rz(psi - phi)


def tilt_torsion_angles(R: ArrayLike) -> NDArray:
    """Tilt-and-torsion angles ``(phi, theta, psi)`` (rad) of rotations ``R``.

    The inverse of :func:`rotation_from_tilt_torsion`.  ``theta`` is the
    angle between the platform normal and the base z axis; ``phi`` its
    azimuth (set to 0 when ``theta`` is 0); ``psi`` the torsion, which a
    5-DOF measurement does not observe.
    """
    R = np.asarray(R, dtype=float)
    theta = np.arccos(np.clip(R[..., 2, 2], -1.0, 1.0))
    phi = np.arctan2(R[..., 1, 2], R[..., 0, 2])
    phi = np.where(theta < 1e-12, 0.0, phi)
    # R = Rz(phi) Ry(theta) Rz(psi-phi): the third row gives psi - phi.
    psi_minus_phi = np.arctan2(R[..., 2, 1], -R[..., 2, 0])
    psi_minus_phi = np.where(theta < 1e-12, np.arctan2(R[..., 1, 0], R[..., 0, 0]) - phi, psi_minus_phi)
    psi = psi_minus_phi + phi
    psi = (psi + np.pi) % (2 * np.pi) - np.pi
    return np.stack([phi, theta, psi], axis=-1)


def rpy_matrix(rpy: ArrayLike) -> NDArray:
    """``Rz(y) Ry(p) Rx(r)`` for ``rpy = (r, p, y)`` (rad, URDF convention), shape ``(..., 3, 3)``."""
    rpy = np.asarray(rpy, dtype=float)
    cr, sr = np.cos(rpy[..., 0]), np.sin(rpy[..., 0])
    cp, sp = np.cos(rpy[..., 1]), np.sin(rpy[..., 1])
    cy, sy = np.cos(rpy[..., 2]), np.sin(rpy[..., 2])
    R = np.empty(rpy.shape[:-1] + (3, 3))
    R[..., 0, 0], R[..., 0, 1], R[..., 0, 2] = cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr
    R[..., 1, 0], R[..., 1, 1], R[..., 1, 2] = sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr
    R[..., 2, 0], R[..., 2, 1], R[..., 2, 2] = -sp, cp * sr, cp * cr
    return R


def rpy_from_matrix(R: ArrayLike) -> NDArray:
    """URDF ``(r, p, y)`` of a rotation matrix (one of the two solutions; ``|p| <= pi/2``).

    Written out rather than taken from scipy's ``as_euler``, which warns at
    gimbal lock (``p = +-pi/2``); there the roll is set to zero and the yaw
    carries the rotation about the common axis.
    """
    R = np.asarray(R, dtype=float)
    p = np.arctan2(-R[..., 2, 0], np.hypot(R[..., 0, 0], R[..., 1, 0]))
    locked = np.hypot(R[..., 0, 0], R[..., 1, 0]) < 1e-12
    r = np.where(locked, 0.0, np.arctan2(R[..., 2, 1], R[..., 2, 2]))
    y = np.where(locked, np.arctan2(-R[..., 0, 1], R[..., 1, 1]), np.arctan2(R[..., 1, 0], R[..., 0, 0]))
    return np.stack([r, p, y], axis=-1)
