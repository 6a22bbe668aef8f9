"""The linear solvers of one Gauss-Newton step, in the SVD form of the seed.

With the SVD ``A = U diag(s) V^T`` of the (whitened, column-scaled)
identification matrix, every solver returns

    x = sum_i f_i (u_i . z) / s_i  v_i

and differs only in its filter factors ``f_i``:

* least squares (LS):        f_i = 1
* ridge estimation (RE):     f_i = s_i^2 / (s_i^2 + lam)
* truncated SVD (TSVD):      f_i = 1 for i <= k, else 0

References
----------
The seed: "LS, RE and TSVD parameter identification", equations (9)-(14).
P. C. Hansen, *Rank-Deficient and Discrete Ill-Posed Problems*, SIAM 1998, ch. 4.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from ..errors import InputError

__all__ = ["filter_factors", "filtered_solve", "SvdSolve", "LS_RCOND"]

#: Relative singular value under which least squares calls the problem ill-posed.
LS_RCOND = 1e-10


def filter_factors(s: NDArray, method: str, *, lam: float | None = None, k: int | None = None) -> NDArray:
    """Filter factors of LS, ridge or TSVD for singular values ``s`` (descending).

    Parameters
    ----------
    s : ndarray, shape (r,)
        Singular values, descending.
    method : {"ls", "ridge", "tsvd"}
    lam : float
        Ridge parameter (same units as ``s**2``), required for ``"ridge"``.
    k : int
        Number of singular values kept, required for ``"tsvd"``.

    Returns
    -------
    ndarray, shape (r,)
    """
    s = np.asarray(s, dtype=float)
    if method == "ls":
        return np.ones_like(s)
    if method == "ridge":
        if lam is None or not np.isfinite(lam) or lam < 0:
            raise InputError(f"lam: expected a number >= 0 for ridge, got {lam!r}")
        return s**2 / (s**2 + lam)
    if method == "tsvd":
        if k is None or int(k) != k or not 1 <= k <= s.size:
            raise InputError(f"k: expected an integer from 1 to {s.size} for tsvd, got {k!r}")
        return (np.arange(s.size) < k).astype(float)
    raise InputError(f"method: expected 'ls', 'ridge' or 'tsvd', got {method!r}")


@dataclass(frozen=True)
class SvdSolve:
    """One filtered solve: the solution and what produced it."""

    x: NDArray
    s: NDArray
    f: NDArray
    V: NDArray
    Utz: NDArray

    def covariance(self) -> NDArray:
        """``V diag(f^2 / s^2) V^T``: noise covariance of ``x`` for unit-variance data.

        (For ridge, :func:`bayescal.identify.identify` reports the Bayesian
        posterior covariance ``(A^T A + lam I)^-1`` instead.)
        """
        w = np.where(self.s > 0, self.f**2 / np.where(self.s > 0, self.s, 1.0) ** 2, 0.0)
        return (self.V * w) @ self.V.T


def filtered_solve(A: NDArray, z: NDArray, method: str, *, lam: float | None = None, k: int | None = None) -> SvdSolve:
    """Solve ``A x ~ z`` with LS, ridge or TSVD filter factors.

    Raises
    ------
    numpy.linalg.LinAlgError
        Never for rank deficiency: LS on an ill-posed ``A`` is reported by
        the caller through :data:`LS_RCOND`; here tiny singular values with
        ``f = 1`` simply produce a huge ``x``.
    """
    U, s, Vt = np.linalg.svd(A, full_matrices=False)
    f = filter_factors(s, method, lam=lam, k=k)
    Utz = U.T @ z
    with np.errstate(divide="ignore", invalid="ignore"):
        if (s > 0).all():
            coef = f * Utz / s  # what the guarded form below gives when no singular value is zero (the usual case)
        else:
            coef = np.where(s > 0, f * Utz / np.where(s > 0, s, 1.0), 0.0)
    return SvdSolve(x=Vt.T @ coef, s=s, f=f, V=Vt.T, Utz=Utz)
