"""Point constructions for geometric starts of forward kinematics, batched over poses.

Circle-circle intersection, trilateration and Kabsch's rotation fit: the
closed-form pieces from which a machine builds a Newton start on its
assembly branch.  Where a construction has no real solution the result is
NaN; callers fall back to another start.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from ..geometry import so3_exp

__all__ = ["rotate_vectors", "circle_intersections", "trilaterate", "kabsch"]


def _sqrt_or_nan(x: NDArray) -> NDArray:
    return np.sqrt(np.where(x >= 0, x, np.nan))


def rotate_vectors(a: NDArray, b: NDArray, *, matrix: bool = False) -> NDArray:
    """The smallest rotation taking unit ``a`` (3,) to unit ``b`` (n, 3): its matrix, or ``R e_z``."""
    wv = np.cross(a, b)
    s = np.linalg.norm(wv, axis=1, keepdims=True)
    ang = np.arctan2(s[:, 0], b @ a)
    R = so3_exp(np.where(s > 1e-12, wv / np.maximum(s, 1e-300), 0.0) * ang[:, None])
    return R if matrix else R[:, :, 2]


def circle_intersections(c1: NDArray, r1: NDArray, c2: NDArray, r2: NDArray, normal: NDArray) -> NDArray:
    """Both intersections of two coplanar circles (plane normal ``normal``); NaN where none. Shape (n, 2, 3)."""
    dv = c2 - c1
    D = np.linalg.norm(dv, axis=1)
    e1 = dv / D[:, None]
    e2 = np.cross(normal, e1)
    x = (r1**2 - r2**2 + D**2) / (2 * D)
    y = _sqrt_or_nan(r1**2 - x**2)
    base = c1 + x[:, None] * e1
    return np.stack([base + y[:, None] * e2, base - y[:, None] * e2], axis=1)


def trilaterate(p1: NDArray, r1: NDArray, p2: NDArray, r2: NDArray, p3: NDArray, r3: NDArray) -> NDArray:
    """Both points at distances ``r1, r2, r3`` (n,) from ``p1, p2, p3`` (n, 3); NaN where none.

    Returns shape (n, 2, 3): the two mirror images in the plane of the centres.
    """
    ex = p2 - p1
    d = np.linalg.norm(ex, axis=1)
    ex = ex / d[:, None]
    i = np.einsum("ni,ni->n", ex, p3 - p1)
    ey = p3 - p1 - i[:, None] * ex
    j = np.linalg.norm(ey, axis=1)
    ey = ey / j[:, None]
    ez = np.cross(ex, ey)
    x = (r1**2 - r2**2 + d**2) / (2 * d)
    y = (r1**2 - r3**2 + i**2 + j**2 - 2 * i * x) / (2 * j)
    z = _sqrt_or_nan(r1**2 - x**2 - y**2)
    base = p1 + x[:, None] * ex + y[:, None] * ey
    return np.stack([base + z[:, None] * ez, base - z[:, None] * ez], axis=1)


def kabsch(src: NDArray, dst: NDArray) -> NDArray:
    """Rotations taking point sets ``src`` (n, k, 3) onto ``dst`` (n, k, 3) in least squares."""
    bad = ~np.isfinite(dst).all(axis=(1, 2))
    dst = np.where(bad[:, None, None], src, dst)
    a = src - src.mean(axis=1, keepdims=True)
    b = dst - dst.mean(axis=1, keepdims=True)
    H = np.einsum("nki,nkj->nij", a, b)
    U, _, Vt = np.linalg.svd(H)
    dsign = np.sign(np.linalg.det(np.swapaxes(Vt, 1, 2) @ np.swapaxes(U, 1, 2)))
    D = np.zeros_like(H)
    D[:, 0, 0] = D[:, 1, 1] = 1.0
    D[:, 2, 2] = np.where(dsign == 0, 1.0, dsign)
    R = np.swapaxes(Vt, 1, 2) @ D @ np.swapaxes(U, 1, 2)
    R[bad] = np.nan
    return R

