"""Leave-one-measurement-out prediction on a Klipper delta recording: bayescal's MAP against Klipper's fit.

For each row ``i`` of a constraint recording (heights and distances), both
calibrations are re-fitted on the other rows and then predict row ``i``:

* **bayescal**: the MAP estimate of all the linear-delta parameters under
  the machine's tolerance prior (:func:`bayescal.bayes.priors.map_estimate`),
  the rows weighted by their ``sigma_position``;
* **Klipper**: ``DELTA_CALIBRATE``'s objective, weights and parameter set
  (:func:`bayescal.klipper_fit.fit_klipper`), started from the config's
  geometry.

The prediction error ``measured - predicted`` of the left-out row is what a
calibration gets wrong on a measurement it has not seen; comparing its RMS
with the in-sample residual RMS shows how much a fit over-fits.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from .bayes.priors import map_estimate, prior_from_machine
from .constraint_model import ConstraintModel
from .io.constraints import ConstraintRecording
from .klipper import KlipperDelta, klipper_machine
from .klipper_fit import fit_klipper
from .machines.base import Machine

__all__ = ["LooResult", "loo_bayescal", "loo_klipper", "klipper_predict", "rms"]


def rms(x: NDArray) -> float:
    """Root mean square, same unit as ``x``."""
    x = np.asarray(x, dtype=float)
    return float(np.sqrt(np.mean(x**2))) if x.size else float("nan")


@dataclass(frozen=True)
class LooResult:
    """Leave-one-out and in-sample errors of one method on one recording.

    Attributes
    ----------
    method : str
    measure : tuple of str
        Per row: ``height`` or ``distance``.
    loo_error : ndarray, shape (n,)
        Measured minus predicted value of each row by the fit without it, mm.
    in_sample : ndarray, shape (n,)
        Measured minus predicted value of each row by the fit on all rows, mm.
    """

    method: str
    measure: tuple[str, ...]
    loo_error: NDArray
    in_sample: NDArray

    def summary(self) -> dict[str, float]:
        """RMS of the LOO and in-sample errors, overall and per measurement type (mm)."""
        m = np.array(self.measure)
        out = {"loo_rms": rms(self.loo_error), "in_sample_rms": rms(self.in_sample)}
        for kind in ("height", "distance"):
            sel = m == kind
            if sel.any():
                out[f"loo_rms_{kind}"] = rms(self.loo_error[sel])
                out[f"in_sample_rms_{kind}"] = rms(self.in_sample[sel])
        return out


def _rows_without(n: int, i: int) -> NDArray:
    return np.delete(np.arange(n), i)


def _map_theta(machine: Machine, rec: ConstraintRecording, prior_scale: float) -> NDArray:
    model = ConstraintModel.from_recording(machine, rec)
    prior = prior_from_machine(model.machine, scale=prior_scale)
    return map_estimate(model, prior=prior, free="all").theta


def _predict(machine: Machine, rec: ConstraintRecording, theta: NDArray) -> NDArray:
    model = ConstraintModel.from_recording(machine, rec)
    pred = model.predict(theta)
    return np.where(pred.success, pred.y[:, 0], np.nan)


def loo_bayescal(machine: Machine, rec: ConstraintRecording, *, prior_scale: float = 1.0) -> LooResult:
    """bayescal's MAP calibration (tolerance prior, all parameters) left out one row at a time.

    Parameters
    ----------
    machine : Machine
        Nominal geometry (the prior mean) with ``[tolerance]`` (the prior std).
    rec : ConstraintRecording
        Heights and distances (no ballbar rows: a pivot needs its rows).
    prior_scale : float
        Multiplies every prior std (sensitivity studies).
    """
    n = rec.n_rows
    theta_all = _map_theta(machine, rec, prior_scale)
    in_sample = rec.value - _predict(machine, rec, theta_all)
    loo = np.empty(n)
    for i in range(n):
        theta = _map_theta(machine, rec.subset(_rows_without(n, i)), prior_scale)
        loo[i] = rec.value[i] - _predict(machine, rec.subset([i]), theta)[0]
    return LooResult("bayescal map", tuple(rec.measure), loo, in_sample)


def klipper_predict(kd: KlipperDelta, rec: ConstraintRecording) -> NDArray:
    """Klipper's model's prediction of every row (nozzle height or distance), mm."""
    m = klipper_machine(kd, q_span=np.vstack([rec.qa, rec.qb[np.isfinite(rec.qb).all(axis=1)]]))
    return _predict(m, rec, np.zeros(m.n_params))


def loo_klipper(kd: KlipperDelta, rec: ConstraintRecording) -> LooResult:
    """Klipper's ``DELTA_CALIBRATE`` fit (from the geometry ``kd``) left out one row at a time."""
    n = rec.n_rows
    full = fit_klipper(kd, rec)
    in_sample = rec.value - klipper_predict(full.delta, rec)
    loo = np.empty(n)
    for i in range(n):
        fit = fit_klipper(kd, rec.subset(_rows_without(n, i)))
        loo[i] = rec.value[i] - klipper_predict(fit.delta, rec.subset([i]))[0]
    return LooResult("klipper", tuple(rec.measure), loo, in_sample)
