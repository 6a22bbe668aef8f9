"""The diagnosis' last step: where no effect of the catalogue explains a located mismatch, model it anyway.

When the final model of a diagnosis (the geometry with the selected effects)
still fails the chi-square test or the location tests find a dependence, a
model discrepancy (:mod:`bayescal.discrepancy`) is fitted to what is left,
jointly with the geometry under its tolerance prior.  It is kept when its
marginal likelihood supports it (a log Bayes factor of at least
:data:`~bayescal.discrepancy.MIN_EVIDENCE_GAIN`) and it lowers the
cross-validated position RMS (the same folds as the effects; its
hyperparameters are those of the full fit, the geometry and weights refitted
on each training fold).  Its size, the inputs it depends on and the physics
it resembles (in words, from those inputs) are reported, and
``--write-machine`` writes it, so that ``unexplained`` is left only where even
a discrepancy does not predict held-out poses better.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

import numpy as np

from ..discrepancy import DiscrepancyFit, fit_discrepancy
from ..discrepancy.fit import fold_fits
from ..errors import InputError, KinematicsError

__all__ = ["DiscrepancyTrial", "try_discrepancy", "resembles"]


@dataclass(frozen=True)
class DiscrepancyTrial:
    """The discrepancy a diagnosis fitted.

    Attributes
    ----------
    fit : DiscrepancyFit
    kept : bool
        Supported by the evidence and better out of sample.
    rms_cv_before, rms_cv_after : float
        Cross-validated position RMS (mm) of the model without and with it.
    resembles : str
        The physics it resembles, in words.
    why : str
        Why it was not kept ("" when kept).
    """

    fit: DiscrepancyFit
    kept: bool
    rms_cv_before: float
    rms_cv_after: float
    resembles: str
    why: str = ""
    #: The geometry of the joint fit (the final model's, corrected with the discrepancy: ``theta + dtheta``).
    theta: object = None
    #: Per pose: the discrepancy's mean in the position rows (mm), the residual it was fitted to (mm: the final
    #: model without it), and its inputs' values; for the figure against its inputs.
    pose_mean: object = None
    pose_residual: object = None
    input_values: object = None

    def to_dict(self) -> dict:
        d = self.fit.discrepancy
        return {
            "kept": self.kept, "log_evidence_gain": d.log_evidence_gain, "explained": d.explained,
            "rms_before": self.rms_cv_before, "rms_after": self.rms_cv_after, "inputs": list(d.inputs),
            "relevance": d.relevance(), "outputs": list(d.outputs), "output_scales": d.output_scales.tolist(),
            "output_units": list(d.output_units), "noise_factor": self.fit.noise_factor, "resembles": self.resembles,
            "why_not_kept": self.why or None,
        }

    def report(self) -> str:
        d = self.fit.discrepancy
        rel = sorted(d.relevance().items(), key=lambda kv: -kv[1])
        shown = ", ".join(f"{k} {v:.2g}" for k, v in rel[:5])
        head = "model discrepancy KEPT" if self.kept else f"model discrepancy not kept ({self.why})"
        return (f"{head}: log Bayes factor {d.log_evidence_gain:.1f}; carries {100 * d.explained:.0f} % of the residual; "
                f"out-of-sample position RMS {1e3 * self.rms_cv_before:.1f} -> {1e3 * self.rms_cv_after:.1f} um\n"
                f"  depends on (1 / length scale): {shown}\n  resembles: {self.resembles}")


def try_discrepancy(model, theta, folds, rms_cv_before: float, *, location=None, units=None, seed: int = 0) -> DiscrepancyTrial | None:
    """Fit and judge a discrepancy on a diagnosis' final model (module docstring); None when it cannot be fitted.

    Parameters
    ----------
    model : MeasurementModel
        The final model's recording (effects applied at their fitted values; outliers' weights).
    theta : ndarray, shape (P,)
        Its geometry (every parameter free, tolerance prior, as the diagnosis fits it).
    folds : list of ndarray
        The diagnosis' cross-validation folds.
    rms_cv_before : float
        The final model's cross-validated position RMS, mm.
    location : Location, optional
        The location tests (to name the physics).
    units : tuple of str, optional
        Per actuator ``"mm"`` or ``"rad"``.
    """
    free = np.ones(model.n_params, dtype=bool)
    sd = np.asarray(model.machine.tolerance, dtype=float)
    try:
        fitted = fit_discrepancy(model, theta, free, sd, seed=seed)
        # the joint posterior's geometry, relinearised there once (the written machine's geometry)
        c = fitted.noise_factor
        joint = np.asarray(theta, dtype=float) + fitted.dtheta
        fitted = fit_discrepancy(model, joint, free, sd, hyper=fitted.discrepancy, noise_factor=c)
        joint = joint + fitted.dtheta
        fitted = fit_discrepancy(model, joint, free, sd, hyper=fitted.discrepancy, noise_factor=c)
        cv = _cv_rms(model, theta, free, sd, fitted, folds)
    except (InputError, KinematicsError, np.linalg.LinAlgError) as exc:
        del exc
        return None
    why = ""
    if not fitted.supported:
        why = f"evidence {fitted.discrepancy.log_evidence_gain:.1f} nats, below the bar"
    elif not cv < rms_cv_before:
        why = "no better out of sample"
    pred = model.predict(joint)
    mean = fitted.discrepancy.rows(model, joint, pred)[0][:, :3] if pred.success.all() else None
    residual = model.residual(pred)[:, :3] if pred.success.all() else None
    return DiscrepancyTrial(fitted, not why, rms_cv_before, cv, resembles(fitted.discrepancy, location, units), why,
                            theta=joint, pose_mean=mean, pose_residual=residual,
                            input_values=fitted.discrepancy.raw_inputs(model))


def _cv_rms(model, theta, free, sd, fitted: DiscrepancyFit, folds) -> float:
    """Leave-folds-out position RMS (mm) with the discrepancy: geometry and weights refitted on each training fold
    (:func:`bayescal.discrepancy.fit.fold_fits`: the recording solved once for all folds)."""
    sq, count = 0.0, 0
    idx = np.flatnonzero(free)
    for test, f in zip(folds, fold_fits(model, theta, free, sd, fitted.discrepancy, fitted.noise_factor, folds)):
        th = theta.copy()
        th[idx] += f.dtheta
        te = model.subset(test)
        pred = te.predict(th)
        r = te.residual(pred) - f.discrepancy.rows(te, th, pred)[0]
        sq += float(np.sum(r[:, :3] ** 2))
        count += len(test)
    return float(np.sqrt(sq / count))


_WORDS = (
    (re.compile(r"temp|therm|time|hour|minute|_s$|_min$|_h$|date", re.I),
     "a drift with time or temperature (thermal growth, warm-up)"),
    (re.compile(r"tilt|accel|incl|grav|level", re.I),
     "a deflection under gravity that changes with the machine's tilt (bending, joint or structure compliance)"),
    (re.compile(r"payload|load|mass|kg|force", re.I), "a deflection under load (compliance of links or joints)"),
)


def resembles(disc, location=None, units=None) -> str:
    """The physics a discrepancy resembles, in words, from the inputs it depends on (and the located channel)."""
    rel = disc.relevance()
    top = max(rel.values()) if rel else 0.0
    strong = [k for k, v in rel.items() if v >= 0.3 * top and v > 1.0 / 10.0]
    words = []
    for name in strong:
        for pattern, text in _WORDS:
            if pattern.search(name) and text not in words:
                words.append(text + f" ({name})")
    axes = [k for k in strong if k.startswith("q") and k[1:].isdigit()]
    if len(axes) == 1:
        i = int(axes[0][1:]) - 1
        rotary = units is not None and i < len(units) and units[i] == "rad"
        words.append(f"a position-dependent error of axis {axes[0]} ("
                     + ("encoder eccentricity, gear or bearing runout)" if rotary else "screw pitch error, rail straightness)"))
    elif len(axes) > 1:
        words.append(f"a smooth error of the pose ({', '.join(axes)}): bending or sag that grows with reach, "
                     "or a cable or hose force")
    if location is not None and getattr(location, "strongest", None) is not None and location.strongest.significant:
        words.append(f"located on {location.strongest.channel}")
    return "; ".join(words) if words else "a smooth error of the inputs it was given"
