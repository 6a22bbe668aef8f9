"""Scoring predicted rows against measured ones: position error, the 90 % region, summaries by role.

A row is inside its 90 % predictive region when its measured position lies
in the ellipsoid ``e^T S^-1 e <= chi2_3(0.90)`` (``e`` the position error,
``S`` the predictive covariance of the three position components), the
region docs/formats.md section 8 asks for.  A ``fit`` row's covariance is
its residual's after the session's refit (:mod:`bayescal.prediction.engine`),
which has no variance in a direction the row alone decides: there the
pseudo-inverse stands for ``S^-1`` and the region has the dimension of
``S``'s rank (:func:`mahalanobis2`).  The summary of a set of rows gives
mean, median and 95th percentile of the position error (mm) and the share
of rows inside their region, over the rows whose prediction succeeded
(those that failed are counted apart).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from ..distributions import chi2_ppf

__all__ = ["RowScores", "mahalanobis2", "score_rows", "summarise", "REGION_LEVEL"]

#: The level of the predictive region of each row.
REGION_LEVEL = 0.90


@dataclass(frozen=True)
class RowScores:
    """Per row: position error (mm), whether inside the 90 % region, and its Mahalanobis distance squared."""

    error_position: NDArray
    inside: NDArray
    mahalanobis2: NDArray


#: Eigenvalues of a row's covariance below this times its largest are no variance (a direction the row decided).
RANK_RTOL = 1e-9


def pinv_blocks(S: NDArray, rtol: float = RANK_RTOL, power: float = 1.0) -> tuple[NDArray, NDArray]:
    """``((S^+)^power, rank)`` of every symmetric positive semi-definite block ``S`` (n, k, k): eigenvalues at most
    ``rtol`` times the largest (round-off of a residual variance that is zero: leverage one) count as zero, so a
    singular block never blows up a distance."""
    lam, V = np.linalg.eigh(0.5 * (S + np.swapaxes(S, 1, 2)))
    top = lam[:, -1:] if lam.shape[1] else np.zeros((lam.shape[0], 1))
    kept = lam > rtol * np.clip(top, 0.0, None)
    inv = np.where(kept, np.where(kept, lam, 1.0) ** -power, 0.0)
    return (V * inv[:, None, :]) @ np.swapaxes(V, 1, 2), kept.sum(axis=1)


def mahalanobis2(e: NDArray, S: NDArray) -> tuple[NDArray, NDArray]:
    """``(e^T S^+ e, rank S)`` of every row, ``e`` (n, k) and ``S`` (n, k, k) finite (:func:`pinv_blocks`)."""
    P, rank = pinv_blocks(S)
    return np.einsum("ni,nij,nj->n", e, P, e), rank


def inside_region(d2: NDArray, rank: NDArray, level: float = REGION_LEVEL) -> NDArray:
    """Whether each squared distance lies inside the ``level`` region of a Gaussian of that rank (rank 0: inside,
    the residual is certain)."""
    rank = np.asarray(rank)
    q = chi2_ppf(level, np.maximum(rank, 1))
    return np.where(rank > 0, np.asarray(d2) <= q, True).astype(bool)


def score_rows(measured: NDArray, mean: NDArray, cov: NDArray, *, level: float = REGION_LEVEL) -> RowScores:
    """Score rows (position components 0-2 of ``measured``, ``mean`` (n, dof) and ``cov`` (n, dof, dof))."""
    e = np.asarray(measured, dtype=float)[:, :3] - np.asarray(mean, dtype=float)[:, :3]
    S = np.asarray(cov, dtype=float)[:, :3, :3]
    ok = np.all(np.isfinite(e), axis=1) & np.all(np.isfinite(S), axis=(1, 2))
    d2 = np.full(e.shape[0], np.nan)
    inside = np.zeros(e.shape[0], dtype=bool)
    if ok.any():
        d2[ok], rank = mahalanobis2(e[ok], S[ok])
        inside[ok] = inside_region(d2[ok], rank, level)
    err = np.linalg.norm(e, axis=1)
    return RowScores(err, inside, d2)


def summarise(scores: RowScores, rows: NDArray, failed: NDArray | None = None) -> dict:
    """The summary of the rows ``rows`` (bool mask): counts, error statistics (mm) and coverage.

    ``failed`` marks rows whose prediction failed: they are left out of the
    statistics and counted in ``n_failed``.
    """
    rows = np.asarray(rows, dtype=bool)
    failed = np.zeros_like(rows) if failed is None else np.asarray(failed, dtype=bool)
    use = rows & ~failed
    err = scores.error_position[use]
    out = {"n": int(use.sum()), "n_failed": int((rows & failed).sum())}
    if err.size:
        out.update({
            "mean_error_position_mm": float(np.mean(err)),
            "median_error_position_mm": float(np.median(err)),
            "p95_error_position_mm": float(np.percentile(err, 95)),
            "rms_error_position_mm": float(np.sqrt(np.mean(err**2))),
            "coverage_90": float(np.mean(scores.inside[use])),
        })
    else:
        out.update({k: None for k in ("mean_error_position_mm", "median_error_position_mm", "p95_error_position_mm",
                                      "rms_error_position_mm", "coverage_90")})
    return out
