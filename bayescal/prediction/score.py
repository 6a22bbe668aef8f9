"""Scoring predicted rows against measured ones: position error, the 90 % region, summaries by role.

A row is inside its 90 % predictive region when its measured position lies
in the ellipsoid ``e^T S^-1 e <= chi2_3(0.90)`` (``e`` the position error,
``S`` the predictive covariance of the three position components), the
region docs/formats.md section 8 asks for.  The summary of a set of rows gives
mean, median and 95th percentile of the position error (mm) and the share
of rows inside their region, over the rows whose prediction succeeded
(those that failed are counted apart).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from ..distributions import chi2_ppf

__all__ = ["RowScores", "score_rows", "summarise", "REGION_LEVEL"]

#: The level of the predictive region of each row.
REGION_LEVEL = 0.90


@dataclass(frozen=True)
class RowScores:
    """Per row: position error (mm), whether inside the 90 % region, and its Mahalanobis distance squared."""

    error_position: NDArray
    inside: NDArray
    mahalanobis2: NDArray


def score_rows(measured: NDArray, mean: NDArray, cov: NDArray, *, level: float = REGION_LEVEL) -> RowScores:
    """Score rows (position components 0-2 of ``measured``, ``mean`` (n, dof) and ``cov`` (n, dof, dof))."""
    e = np.asarray(measured, dtype=float)[:, :3] - np.asarray(mean, dtype=float)[:, :3]
    S = np.asarray(cov, dtype=float)[:, :3, :3]
    ok = np.all(np.isfinite(e), axis=1) & np.all(np.isfinite(S), axis=(1, 2))
    d2 = np.full(e.shape[0], np.nan)
    if ok.any():
        d2[ok] = np.einsum("ni,ni->n", e[ok], np.linalg.solve(S[ok], e[ok][:, :, None])[:, :, 0])
    err = np.linalg.norm(e, axis=1)
    inside = np.where(ok, d2 <= chi2_ppf(level, 3), False)
    return RowScores(err, inside.astype(bool), d2)


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
