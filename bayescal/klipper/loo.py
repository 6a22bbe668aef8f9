"""Leave-one-measurement-out prediction on a Klipper delta recording: bayescal's MAP against Klipper's fit.

For each row ``i`` of a constraint recording (heights and distances), both
calibrations are re-fitted on the other rows and then predict row ``i``:

* **bayescal**: ``identify --method map`` (:func:`bayescal.bayes.map_identify.identify_map`:
  the robust pass, the prior-scale rule, the MAP), or the MAP under the
  tolerance prior as it is (:func:`bayescal.bayes.priors.map_estimate`),
  the rows weighted by their ``sigma_position``;
* **Klipper**: ``DELTA_CALIBRATE``'s objective, weights and parameter set
  (:func:`bayescal.klipper.baseline.fit_klipper`), started from the config's
  geometry.

The prediction error ``measured - predicted`` of the left-out row is what a
calibration gets wrong on a measurement it has not seen; comparing its RMS
with the in-sample residual RMS shows how much a fit over-fits.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray

from ..bayes.map_identify import identify_map
from ..bayes.priors import map_estimate, prior_from_machine
from ..constraints.model import ConstraintModel
from ..errors import InputError
from ..io.constraints import ConstraintRecording
from .printer import KlipperDelta, klipper_machine
from .baseline import fit_klipper
from ..machines.base import Machine

__all__ = ["LooResult", "loo_bayescal", "noise_scale_map", "loo_klipper", "klipper_predict", "rms"]


def rms(x: NDArray) -> float:
    """Root mean square of the finite entries, same unit as ``x``."""
    x = np.asarray(x, dtype=float)
    x = x[np.isfinite(x)]
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


def _check_rows(rec: ConstraintRecording) -> None:
    if rec.n_rows < 2:
        raise InputError(f"{rec.path}: leave-one-out needs at least 2 measurements, got {rec.n_rows}")


def noise_scale_map(machine: Machine, rec: ConstraintRecording, *, prior_scale: float = 1.0, iterations: int = 20):
    """MAP with the rows' noise scaled by a factor estimated from the residuals; the result and the factor.

    The stated sigmas (a probe's repeatability, a caliper's resolution) miss
    what a printed part adds, so the factor ``s`` is estimated as the
    restricted residual variance: ``s^2 = sum (r_i / sigma_i)^2 / (n - p_eff)``
    with ``p_eff = sum f_i``, the filter factors of the MAP solution (the
    effective number of parameters the data determines), iterated to a
    fixed point.  ``s`` is never made smaller than 1: the stated noise is a
    floor, not a guess to be beaten.
    """
    scale = 1.0
    sigma = rec.sigma if rec.sigma is not None else np.full(rec.n_rows, machine.noise.sigma_position)
    for _ in range(iterations):
        model = ConstraintModel.from_recording(machine, replace(rec, sigma=sigma * scale))
        res = map_estimate(model, prior=prior_from_machine(model.machine, scale=prior_scale), free="all")
        r = np.asarray(res.residuals_after).reshape(-1) / sigma
        p_eff = float(np.sum(res.filter_factors))
        new = max(1.0, float(np.sqrt(np.sum(r**2) / max(rec.n_rows - p_eff, 1.0))))
        if abs(new - scale) < 1e-3 * scale:
            scale = new
            break
        scale = new
    return res, scale


def _map_theta(machine: Machine, rec: ConstraintRecording, prior_scale: float, noise: str = "identify",
               free: str = "all") -> NDArray:
    if noise == "identify":
        return identify_map(ConstraintModel.from_recording(machine, rec), free)[0].theta
    if noise == "estimated":
        return noise_scale_map(machine, rec, prior_scale=prior_scale)[0].theta
    if noise != "stated":
        raise InputError(f"noise: expected 'identify', 'stated' or 'estimated', got {noise!r}")
    model = ConstraintModel.from_recording(machine, rec)
    prior = prior_from_machine(model.machine, scale=prior_scale)
    return map_estimate(model, prior=prior, free=free).theta


def _predict(machine: Machine, rec: ConstraintRecording, theta: NDArray) -> NDArray:
    model = ConstraintModel.from_recording(machine, rec)
    pred = model.predict(theta)
    return np.where(pred.success, pred.y[:, 0], np.nan)


def loo_bayescal(
    machine: Machine, rec: ConstraintRecording, *, prior_scale: float = 1.0, noise: str = "identify", rows=None,
    free: str = "all",
) -> LooResult:
    """bayescal's MAP calibration left out one row at a time.

    Parameters
    ----------
    machine : Machine
        Nominal geometry (the prior mean) with ``[tolerance]`` (the prior std).
    rec : ConstraintRecording
        Heights and distances (no ballbar rows: a pivot needs its rows).
    prior_scale : float
        Multiplies every prior std (sensitivity studies; not with ``"identify"``).
    noise : {"identify", "stated", "estimated"}
        ``identify --method map`` as the command runs it (default: the
        prior-scale rule of :mod:`bayescal.bayes.map_identify`, the robust
        pass), the tolerance prior with the rows weighted by their stated
        sigma, or by it times a factor estimated from each fit's residuals
        (:func:`noise_scale_map`).
    rows : sequence of int, optional
        Rows to leave out (default all); ``loo_error`` is NaN for the others.
    free : {"all", "auto"}
        All parameters under the prior (``--free all``), or ``--free auto``:
        for MAP the same except the parameters the recording does not see at
        all, which stay at nominal (:func:`bayescal.identify.resolve_free`;
        before, auto fixed the least-squares identifiable set).
    """
    _check_rows(rec)
    n = rec.n_rows
    theta_all = _map_theta(machine, rec, prior_scale, noise, free)
    in_sample = rec.value - _predict(machine, rec, theta_all)
    loo = np.full(n, np.nan)
    for i in range(n) if rows is None else rows:
        theta = _map_theta(machine, rec.subset(_rows_without(n, i)), prior_scale, noise, free)
        loo[i] = rec.value[i] - _predict(machine, rec.subset([i]), theta)[0]
    return LooResult(f"bayescal map ({noise} noise)", tuple(rec.measure), loo, in_sample)


def klipper_predict(kd: KlipperDelta, rec: ConstraintRecording) -> NDArray:
    """Klipper's model's prediction of every row (nozzle height or distance), mm."""
    m = klipper_machine(kd, q_span=np.vstack([rec.qa, rec.qb[np.isfinite(rec.qb).all(axis=1)]]))
    return _predict(m, rec, np.zeros(m.n_params))


def loo_klipper(kd: KlipperDelta, rec: ConstraintRecording, *, rows=None) -> LooResult:
    """Klipper's ``DELTA_CALIBRATE`` fit (from the geometry ``kd``) left out one row at a time (``rows``: which)."""
    _check_rows(rec)
    n = rec.n_rows
    full = fit_klipper(kd, rec)
    in_sample = rec.value - klipper_predict(full.delta, rec)
    loo = np.full(n, np.nan)
    for i in range(n) if rows is None else rows:
        fit = fit_klipper(kd, rec.subset(_rows_without(n, i)))
        loo[i] = rec.value[i] - klipper_predict(fit.delta, rec.subset([i]))[0]
    return LooResult("klipper", tuple(rec.measure), loo, in_sample)
