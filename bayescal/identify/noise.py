"""Is the stated instrument noise what the fit shows?  The chi-square test and the estimated scale.

After a fit, the whitened residuals ``W (y - h)`` of a model that is right
and a noise that is stated right have a chi-square ``chi2`` with about
``dof = n_rows - p_eff`` degrees of freedom (``p_eff`` the effective number
of parameters, the trace of the hat matrix).  The two tails say:

* **understated** (``P(X >= chi2) < alpha``): the residuals are larger than
  the stated noise allows, because the instrument is noisier or because the
  model leaves physics out.  Intervals computed with the stated sigma are
  too narrow (on a real serial arm, 90 % regions held half the held-out
  points at a reduced chi-square of 7.5), so the noise scale is estimated,
  ``sigma_used = sigma sqrt(chi2 / dof)``, and every interval widens with it.
* **overstated** (``P(X <= chi2) < alpha`` and ``chi2 / dof`` below
  :data:`OVERSTATED_BELOW`): the residuals are far smaller than stated.
  With a prior, a noise stated 100 times too large makes the data look
  uninformative and the calibration does nothing (0.145 mm left where
  0.0073 mm is reachable); the scale is estimated here too.  A small
  shortfall is left alone (narrowing intervals needs clear evidence).

A fit whose rows are copies of each other carries no information about the
noise (its residuals vanish whatever the sigma): :func:`distinct_rows`
counts the measured components that are not repeats, and the test is only
made with residual degrees of freedom among those.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from ..distributions import chi2_cdf, chi2_sf

__all__ = ["NoiseCheck", "check_noise", "distinct_rows", "distinct_measurements", "ALPHA", "OVERSTATED_BELOW"]

#: Level of the two-sided chi-square test of the stated noise.
ALPHA = 1e-3
#: A reduced chi-square below this (and significant) calls the noise overstated: sigma at least 2 times too large.
OVERSTATED_BELOW = 0.25


@dataclass(frozen=True)
class NoiseCheck:
    """The chi-square test of the stated instrument noise after a fit.

    Attributes
    ----------
    chi2 : float
        Whitened sum of squared residuals.
    dof : float
        Residual degrees of freedom (distinct measured components less the
        effective number of parameters).
    verdict : {"consistent", "understated", "overstated", "untestable", "not_stated"}
        ``not_stated``: the machine file states no noise; the sigmas are
        weights and the noise variance is estimated from the fit anyway.
    p_value : float
        Of the tail in the verdict's direction (NaN when untestable).
    scale : float
        Factor on the stated sigma that the data support: ``sqrt(chi2 / dof)``
        where the verdict calls for it, else 1.
    """

    chi2: float
    dof: float
    verdict: str
    p_value: float
    scale: float

    @property
    def reduced(self) -> float:
        return self.chi2 / self.dof if self.dof > 0 else float("nan")

    @property
    def contradicted(self) -> bool:
        """Whether the stated noise is contradicted (and the estimated scale applies)."""
        return self.verdict in ("understated", "overstated")

    def message(self) -> str:
        if self.verdict == "understated":
            return (f"the residuals are larger than the stated noise allows (reduced chi-square {self.reduced:.3g} on "
                    f"{self.dof:.0f} degrees of freedom at the stated sigma, p = {self.p_value:.1e}): the instrument is "
                    "noisier than stated or the model leaves something out; the fit and its uncertainties use the "
                    "estimated noise")
        if self.verdict == "overstated":
            return (f"the stated sigma is too large: the residuals are far smaller (reduced chi-square {self.reduced:.3g} "
                    f"at the stated sigma, p = {self.p_value:.1e}); the fit and its uncertainties use the estimated noise")
        if self.verdict == "not_stated":
            return (f"no noise stated ([measurement] absent): the default sigmas are weights and the noise is estimated "
                    f"from the residuals ({math.sqrt(self.reduced):.3g} x the default)" if self.dof > 0 else
                    "no noise stated ([measurement] absent) and no residual degrees of freedom to estimate it")
        if self.verdict == "untestable":
            return ("the stated noise cannot be checked: no residual degrees of freedom among the distinct measured "
                    "components")
        return f"the stated noise fits (reduced chi-square {self.reduced:.3g} on {self.dof:.0f} degrees of freedom)"

    def to_dict(self) -> dict:
        return {"chi2": self.chi2, "dof": self.dof, "reduced_chi2": self.reduced if self.dof > 0 else None,
                "verdict": self.verdict, "p_value": None if math.isnan(self.p_value) else self.p_value,
                "scale": self.scale, "alpha": ALPHA, "message": self.message()}


def check_noise(chi2: float, dof: float, *, alpha: float = ALPHA, stated: bool = True) -> NoiseCheck:
    """Test a fit's chi-square against the stated noise (module docstring).

    Parameters
    ----------
    chi2 : float
        Whitened sum of squared residuals after the fit.
    dof : float
        Residual degrees of freedom; at or below 0.5 the noise is untestable.
    alpha : float
        Level of each tail.
    stated : bool
        Whether the noise was stated (a ``[measurement]`` table); if not,
        the verdict is ``not_stated`` and the scale the estimate.

    Returns
    -------
    NoiseCheck
    """
    chi2, dof = float(chi2), float(dof)
    if not stated:
        ok = dof > 0.5 and math.isfinite(chi2)
        return NoiseCheck(chi2, dof, "not_stated", float("nan"), math.sqrt(chi2 / dof) if ok else 1.0)
    if not (dof > 0.5 and math.isfinite(chi2) and chi2 >= 0):
        return NoiseCheck(chi2, dof, "untestable", float("nan"), 1.0)
    red = chi2 / dof
    p_high, p_low = float(chi2_sf(chi2, dof)), float(chi2_cdf(chi2, dof))
    if p_high < alpha:
        return NoiseCheck(chi2, dof, "understated", p_high, math.sqrt(red))
    if p_low < alpha and red < OVERSTATED_BELOW:
        return NoiseCheck(chi2, dof, "overstated", p_low, math.sqrt(red))
    return NoiseCheck(chi2, dof, "consistent", min(p_high, p_low), 1.0)


def distinct_rows(q: NDArray, y: NDArray | None) -> int:
    """Number of rows that are not exact repeats of an earlier row (same commanded ``q`` and measured ``y``).

    Repeated measurements of one pose with fresh noise count (their values
    differ); copied rows do not: they add rows but no information.
    """
    q = np.asarray(q, dtype=float)
    rows = q if y is None else np.hstack([q.reshape(q.shape[0], -1), np.asarray(y, dtype=float).reshape(q.shape[0], -1)])
    if rows.shape[0] == 0:
        return 0
    return int(np.unique(rows, axis=0).shape[0])


def distinct_measurements(model) -> int:
    """:func:`distinct_rows` of a model's rows: each row's (first) pose ``q`` and its measured values.

    A constraint model's ``q`` is each row's pose a: two distances from one
    pose a count once only if their readings agree to the last bit too.  NaN
    is compared as a value here.
    """
    q = model.q
    q = np.nan_to_num(np.asarray(q, dtype=float), nan=np.inf)
    y = None if model.y_measured is None else np.nan_to_num(np.asarray(model.y_measured, dtype=float), nan=np.inf)
    return distinct_rows(q, y)
