"""Scoring a body sensor's predicted readings against the recorded ones (docs/formats.md sections 8 and E6).

A tilt sensor on a body is a measurement (:mod:`bayescal.sensors`): two
tilt rows per sensor and pose, ``y_k = t_k . u`` with ``t_1, t_2`` the
tangent basis of the *recorded* reading, so the recorded rows are zero and
the predicted rows are the predicted reading's tilt away from the recorded
one (rad).  Per sensor and pose this module gives

* the predicted reading in the recording's own units (the predicted
  direction times the recorded reading's length) next to the recorded one;
* ``error_tilt_rad``, the angle between the two readings (rad);
* ``std``, the one-sigma predictive uncertainty of the two tilt rows (rad,
  along the recorded reading's tangent directions), from
  :func:`bayescal.prediction.engine.predictive_rows` like a tool row's;
* ``inside_90``: the recorded reading inside its 90 % predictive region,
  the ellipse ``e^T S^-1 e <= chi2_2(0.90)`` of the two tilt rows (its
  pseudo-inverse and rank where a fit row's residual has a direction
  without variance: :func:`bayescal.prediction.score.mahalanobis2`).

Summaries per sensor and role give the mean, median, 95th percentile and
RMS of the tilt error (rad), the coverage of the 90 % regions and the
sensor's one-sigma noise per tilt row (``sigma_tilt_rad``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from .score import REGION_LEVEL, inside_region, mahalanobis2

__all__ = ["SensorScores", "score_sensor_rows", "sensor_report_lines"]

_STATS = ("mean_error_tilt_rad", "median_error_tilt_rad", "p95_error_tilt_rad", "rms_error_tilt_rad", "coverage_90")


@dataclass(frozen=True)
class SensorScores:
    """Per pose and body sensor: the readings, their predictive std, the tilt error and the region test.

    Attributes
    ----------
    bodies : tuple of str
        The sensors' bodies, ``S`` of them.
    measured, predicted : ndarray, shape (n, S, 3)
        The recorded reading and the predicted one, in the recording's units (NaN where not predicted).
    std : ndarray, shape (n, S, 2)
        One-sigma predictive std of the two tilt rows, rad.
    error_tilt : ndarray, shape (n, S)
        Angle between the recorded and the predicted reading, rad.
    inside : ndarray of bool, shape (n, S)
        Whether the recorded reading lies inside its 90 % predictive region.
    sigma_tilt : float
        The sensors' one-sigma noise per tilt row, rad (:meth:`bayescal.sensors.SensorSet.row_sigma`).
    """

    bodies: tuple[str, ...]
    measured: NDArray
    predicted: NDArray
    std: NDArray
    error_tilt: NDArray
    inside: NDArray
    sigma_tilt: float

    def row(self, i: int) -> dict:
        """Row ``i``'s ``"sensors"`` block of the JSON answer: per body, the readings and their scores."""
        return {b: {"measured": self.measured[i, s].tolist(), "predicted": self.predicted[i, s].tolist(),
                    "std": self.std[i, s].tolist(), "error_tilt_rad": float(self.error_tilt[i, s]),
                    "inside_90": bool(self.inside[i, s])}
                for s, b in enumerate(self.bodies)}

    def summary(self, rows: NDArray, failed: NDArray) -> dict:
        """Per body, the scores of the rows ``rows`` (bool mask) less those ``failed`` (counted apart)."""
        use = np.asarray(rows, dtype=bool) & ~np.asarray(failed, dtype=bool)
        out = {}
        for s, b in enumerate(self.bodies):
            err = self.error_tilt[use, s]
            d = {"n": int(use.sum()), "n_failed": int((np.asarray(rows, dtype=bool) & failed).sum()),
                 "sigma_tilt_rad": float(self.sigma_tilt)}
            if err.size:
                d.update(zip(_STATS, (float(np.mean(err)), float(np.median(err)), float(np.percentile(err, 95)),
                                      float(np.sqrt(np.mean(err**2))), float(np.mean(self.inside[use, s])))))
            else:
                d.update({k: None for k in _STATS})
            out[b] = d
        return out


def sensor_report_lines(summary: dict, role: str) -> list[str]:
    """The report's lines of one role's per-sensor summary (:meth:`SensorScores.summary`), in mrad."""
    out = []
    for b, s in summary.items():
        if s["n"]:
            out.append(f"  {role:<6} {s['n']:>5} readings of the sensor on {b!r}: tilt error mean "
                       f"{1e3 * s['mean_error_tilt_rad']:.4g} mrad, median {1e3 * s['median_error_tilt_rad']:.4g}, "
                       f"p95 {1e3 * s['p95_error_tilt_rad']:.4g} (sigma {1e3 * s['sigma_tilt_rad']:.3g}); inside the "
                       f"90 % region: {100 * s['coverage_90']:.1f} %")
    return out


def score_sensor_rows(sensors, raw: NDArray, predicted_unit: NDArray, mean_rows: NDArray, cov_rows: NDArray,
                      sigma_tilt: float, *, level: float = REGION_LEVEL) -> SensorScores:
    """Score the body sensors' rows of a prediction (module docstring).

    Parameters
    ----------
    sensors : bayescal.sensors.SensorSet
        The recording's sensors (their recorded unit readings ``u``).
    raw : ndarray, shape (n, S, 3)
        The recorded readings as written (any unit).
    predicted_unit : ndarray, shape (n, S, 3)
        Predicted unit readings, sign as recorded (:func:`bayescal.sensors.predicted_readings`); NaN where not predicted.
    mean_rows : ndarray, shape (n, 2 S)
        Predictive mean of the tilt rows, rad (the recorded rows are zero).
    cov_rows : ndarray, shape (n, 2 S, 2 S)
        Their predictive covariance, rad^2.
    sigma_tilt : float
        One-sigma noise per tilt row, rad.
    level : float
        Of the predictive region.
    """
    n, S = raw.shape[0], sensors.n_sensors
    recorded = -sensors.u if sensors.flipped else sensors.u
    p = np.asarray(predicted_unit, dtype=float)
    cross = np.linalg.norm(np.cross(recorded, p), axis=2)
    err = np.arctan2(cross, np.einsum("nsi,nsi->ns", recorded, p))  # exact angle, fine at small angles too
    e = -np.asarray(mean_rows, dtype=float).reshape(n, S, 2)
    C = np.asarray(cov_rows, dtype=float)
    blocks = np.stack([C[:, 2 * s: 2 * s + 2, 2 * s: 2 * s + 2] for s in range(S)], axis=1)  # (n, S, 2, 2)
    ok = np.all(np.isfinite(e), axis=2) & np.all(np.isfinite(blocks), axis=(2, 3))
    d2 = np.full((n, S), np.nan)
    inside = np.zeros((n, S), dtype=bool)
    if ok.any():
        # a fit row's residual covariance is singular where the row alone decided its mounting: pseudo-inverse
        d2[ok], rank = mahalanobis2(e[ok], blocks[ok])
        inside[ok] = inside_region(d2[ok], rank, level)
    std = np.sqrt(np.clip(np.einsum("nsii->nsi", blocks), 0.0, None))
    length = np.linalg.norm(raw, axis=2, keepdims=True)
    return SensorScores(tuple(sensors.bodies), np.asarray(raw, dtype=float), p * length, std, err, inside,
                        float(sigma_tilt))
