"""Klipper's own delta calibration, re-implemented as a baseline for studies.

``DELTA_CALIBRATE`` (``klippy/extras/delta_calibrate.py``, described in our
own words) minimises

    w * sum_heights (z(pos) - height)^2 + sum_distances (|x(pos1) - x(pos2)| - distance)^2

over ``delta_radius``, ``angle_a``, ``angle_b`` and the three
``position_endstop`` (``angle_c`` is the reference), plus the three
``arm_length`` when distances exist ("enhanced" calibration).  The heights'
weight is ``w = n_distances / (0.5 n_probed)`` with distances, else 1, where
``n_probed`` counts the probed heights (not the manual ones: aux channel
``klipper_manual``).
Klipper searches by coordinate descent; the minimum of the same objective is
found here with ``scipy.optimize.least_squares`` on the residual vector
whose sum of squares is that objective (the team's check reproduced
Klipper's stored values to four decimals this way), with the nozzle
positions from bayescal's linear-delta model of the same geometry.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray

from ..constraints.model import ConstraintModel
from ..io.constraints import ConstraintRecording
from .printer import KlipperDelta, klipper_machine

__all__ = ["KlipperFit", "klipper_residuals", "klipper_objective", "fit_klipper", "KLIPPER_PARAMS", "MEASURE_WEIGHT"]

#: How much Klipper prefers a distance over a height (its ``MEASURE_WEIGHT``).
MEASURE_WEIGHT = 0.5
#: Klipper's adjusted parameters: basic, then the arms of the enhanced calibration.
KLIPPER_PARAMS = ("radius", "angle_a", "angle_b", "endstop_a", "endstop_b", "endstop_c", "arm_a", "arm_b", "arm_c")


@dataclass(frozen=True)
class KlipperFit:
    """Klipper's calibration of a recording.

    Attributes
    ----------
    delta : KlipperDelta
        The fitted geometry (Klipper's keys).
    objective : float
        Klipper's objective at the fit, mm^2.
    names : tuple of str
        The parameters that were adjusted.
    success : bool
    message : str
    """

    delta: KlipperDelta
    objective: float
    names: tuple[str, ...]
    success: bool
    message: str


def _with(kd: KlipperDelta, names, x) -> KlipperDelta:
    v = dict(zip(names, x))
    ang, pe, arm = kd.angle_deg.copy(), kd.position_endstop.copy(), kd.arm_length.copy()
    for i, a in enumerate("abc"):
        ang[i] = v.get(f"angle_{a}", ang[i])
        pe[i] = v.get(f"endstop_{a}", pe[i])
        arm[i] = v.get(f"arm_{a}", arm[i])
    return replace(kd, delta_radius=v.get("radius", kd.delta_radius), angle_deg=ang, position_endstop=pe, arm_length=arm)


def _values(kd: KlipperDelta, names) -> NDArray:
    get = {"radius": kd.delta_radius}
    for i, a in enumerate("abc"):
        get[f"angle_{a}"], get[f"endstop_{a}"], get[f"arm_{a}"] = kd.angle_deg[i], kd.position_endstop[i], kd.arm_length[i]
    return np.array([get[n] for n in names])


def klipper_residuals(kd: KlipperDelta, rec: ConstraintRecording) -> NDArray:
    """Residuals whose sum of squares is Klipper's objective: ``sqrt(w) (z - height)`` then ``d - distance``, mm.

    Rows in the recording's order; a geometry that cannot assemble a pose
    (or has no positive radius, or an arm not longer than it) gives a large residual, as
    Klipper's error function does.
    """
    if not (kd.delta_radius > 0 and np.all(kd.arm_length > kd.delta_radius)):
        return np.full(rec.n_rows, 1e5)  # no printer (Klipper's error function fails there too): the same penalty
    m = klipper_machine(kd, q_span=np.vstack([rec.qa, rec.qb[np.isfinite(rec.qb).all(axis=1)]]))
    model = ConstraintModel(base=m, measure=rec.measure, qa=rec.qa, qb=rec.qb, pivot=rec.pivot)
    pred = model.predict(None)
    r = pred.y[:, 0] - rec.value
    r = np.where(pred.success, r, 1e5)
    heights = np.array([mm == "height" for mm in rec.measure])
    n_d = int((~heights).sum())
    # Klipper divides by the number of probed heights; manual heights (DELTA_ANALYZE MANUAL_HEIGHT) do not count
    manual = rec.aux.get("klipper_manual")
    n_h = int(heights.sum() - (np.sum(manual[heights] > 0) if manual is not None else 0)) or int(heights.sum())
    w = n_d / (MEASURE_WEIGHT * n_h) if n_d and n_h else 1.0
    return np.where(heights, np.sqrt(w) * r, r)


def klipper_objective(kd: KlipperDelta, rec: ConstraintRecording) -> float:
    """Klipper's objective for a geometry and a recording, mm^2."""
    r = klipper_residuals(kd, rec)
    return float(r @ r)


def fit_klipper(kd: KlipperDelta, rec: ConstraintRecording, *, extended: bool | None = None) -> KlipperFit:
    """Minimise Klipper's objective from the geometry ``kd``, over Klipper's parameters.

    Parameters
    ----------
    kd : KlipperDelta
        Start (and the fixed values: ``angle_c``, the arms in a basic fit, step distances).
    rec : ConstraintRecording
        Heights and distances in Klipper's stable positions converted to ``q``
        with ``kd.step_dist`` (:func:`bayescal.klipper.klipper_recording`).
    extended : bool, optional
        Fit the arm lengths too; by default when the recording has distances, as Klipper does.
    """
    from scipy.optimize import least_squares

    has_d = any(m == "distance" for m in rec.measure)
    extended = has_d if extended is None else extended
    names = KLIPPER_PARAMS if extended else KLIPPER_PARAMS[:6]
    x0 = _values(kd, names)
    sol = least_squares(lambda x: klipper_residuals(_with(kd, names, x), rec), x0, x_scale=1.0, xtol=1e-12, ftol=1e-14, gtol=1e-12)
    fitted = _with(kd, names, sol.x)
    return KlipperFit(delta=fitted, objective=klipper_objective(fitted, rec), names=names, success=bool(sol.success), message=str(sol.message))
