"""The triangular factor of a tall, ridge-regularised system, computed without its orthogonal factor.

``R`` (upper triangular, ``p x p``) with ``R^T R = A^T diag(w) A + lam I`` for a tall ``A`` (rows ``N >> p``),
by Cholesky QR done twice (CholeskyQR2) on the augmented matrix ``[diag(sqrt(w)) A; sqrt(lam) I]``, a block
of rows at a time.  The first pass's factor ``R1`` (Cholesky of the Gram matrix) is as inaccurate as the Gram
matrix is ill-conditioned; the second pass factors the Gram matrix of ``[..] R1^-1``, which is the identity to
within that error, and ``R = R2 R1`` is as accurate as Householder QR's factor (backward error of order the unit
round-off) while the first Cholesky succeeds, which the rule of thumb puts at a condition number below about
``eps^-1/2`` = 1e8 (Yamamoto, Nakatsukasa, Yanagisawa and Fukaya 2015, "Roundoff error analysis of the
CholeskyQR2 algorithm", Electron. Trans. Numer. Anal. 44, 306-326; their sufficient condition, ``8 kappa
sqrt(m n u + n (n + 1) u) <= 1``, is far stricter: about 2.5e3 at 600,000 x 36).  The threshold used,
:data:`MAX_CONDITION`, is the rule of thumb's with a margin of ten and is checked by the tests against Householder
QR (tests/test_tallqr.py, condition up to 3e6 through blocks of rows), not by the theorem.  The ridge bounds that
condition number by ``sqrt(1 + s_max^2 / lam)``; above :data:`MAX_CONDITION` :func:`ridge_factor` declines
(None) and the caller takes the SVD.

Why not ``numpy.linalg.svd`` or ``qr``: both write an orthogonal factor as large as ``A``, and at 100,000 poses
(600,000 x 36) that array's memory traffic is most of their time: one SVD took 1.8 s of CPU where the 60,000-row
one took 0.09 s (20 times for 10 times the rows); these passes are products and a triangular solve of 36 x 36
matrices, in blocks that stay in the cache.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray
from scipy.linalg import solve_triangular

__all__ = ["ridge_factor", "ridge_solution", "MAX_CONDITION", "BLOCK_ROWS"]

#: The largest condition number of the augmented matrix (estimated from the first pass's factor) for which
#: :func:`ridge_factor` answers: a decade below CholeskyQR2's limit of about 1e8.
MAX_CONDITION = 1e7
#: Rows per block of the Gram matrices' sums (a 36-column block of 16,384 rows is 4.7 MB).
BLOCK_ROWS = 16_384


def _gram(A: NDArray, sw: NDArray | None, M: NDArray | None) -> NDArray:
    """``(S A M)^T (S A M)`` summed over blocks of rows (``S = diag(sw)``; ``M`` the identity when None)."""
    p = A.shape[1] if M is None else M.shape[1]
    G = np.zeros((p, p))
    for a in range(0, A.shape[0], BLOCK_ROWS):
        X = A[a : a + BLOCK_ROWS]
        if sw is not None:
            X = X * sw[a : a + BLOCK_ROWS, None]
        if M is not None:
            X = X @ M
        G += X.T @ X
    return G


def ridge_factor(A: NDArray, lam: float, row_scale: NDArray | None = None) -> NDArray | None:
    """``R`` upper triangular with ``R^T R = A^T diag(row_scale**2) A + lam I``, or None if too ill-conditioned.

    Parameters
    ----------
    A : ndarray, shape (N, p)
        The system (any units; its rows scaled by ``row_scale``).
    lam : float
        The ridge, > 0 (same units as ``A^T A``).
    row_scale : ndarray, shape (N,), optional
        Square roots of the row weights (default 1).

    Returns
    -------
    ndarray, shape (p, p), or None
        None when the Cholesky factorisation fails or the augmented matrix's condition number exceeds
        :data:`MAX_CONDITION`: then take the SVD.
    """
    A = np.asarray(A, dtype=float)
    if not lam > 0:
        raise ValueError(f"ridge_factor: expected lam > 0, got {lam!r}")
    p = A.shape[1]
    eye = np.eye(p)
    try:
        R1 = np.linalg.cholesky(_gram(A, row_scale, None) + lam * eye).T
    except np.linalg.LinAlgError:
        return None
    sv = np.linalg.svd(R1, compute_uv=False)
    if not np.all(np.isfinite(sv)) or sv[-1] <= 0 or sv[0] / sv[-1] > MAX_CONDITION:
        return None
    R1inv = solve_triangular(R1, eye)
    # the second pass: the Gram matrix of the augmented matrix times R1^-1 (its lower block is sqrt(lam) R1^-1)
    G2 = _gram(A, row_scale, R1inv) + lam * (R1inv.T @ R1inv)
    try:
        R2 = np.linalg.cholesky(G2).T
    except np.linalg.LinAlgError:
        return None
    return R2 @ R1


def ridge_solution(A: NDArray, b: NDArray, lam: float, row_scale: NDArray | None = None) -> NDArray:
    """``x`` minimising ``|diag(row_scale) (b - A x)|^2 + lam |x|^2``: by :func:`ridge_factor`, else by least squares.

    Parameters
    ----------
    A : ndarray, shape (N, p)
    b : ndarray, shape (N,)
    lam : float
        The ridge, > 0.
    row_scale : ndarray, shape (N,), optional
        Square roots of the row weights (default 1).

    Returns
    -------
    ndarray, shape (p,)
    """
    A = np.asarray(A, dtype=float)
    b = np.asarray(b, dtype=float).reshape(-1)
    sw = np.ones(A.shape[0]) if row_scale is None else np.asarray(row_scale, dtype=float)
    R = ridge_factor(A, lam, row_scale)
    if R is None:  # beyond CholeskyQR2's accuracy: Householder least squares of the augmented system
        aug = np.vstack([A * sw[:, None], np.sqrt(lam) * np.eye(A.shape[1])])
        return np.linalg.lstsq(aug, np.concatenate([sw * b, np.zeros(A.shape[1])]), rcond=None)[0]
    w = sw**2

    def normal(v):  # (R^T R)^-1 v
        return solve_triangular(R, solve_triangular(R, v, trans="T"))

    # the semi-normal equations lose accuracy like cond^2 even with an exact R (Bjorck 1987): one step of
    # refinement on the residual (the corrected semi-normal equations) brings the error to Householder's order
    # (a 300 x 6 system of condition 5e6 with a small residual: 3e-4 of x before, 1e-11 after; an extra pass
    # over A)
    x = normal(A.T @ (w * b))
    return x + normal(A.T @ (w * (b - A @ x)) - lam * x)
