"""The diagnosis's yardstick: a stated tool noise that the residuals show far too large is re-estimated first.

Every test of the diagnosis (the chi-square of the geometric fit, the
location tests, the effects' evidence and their cross-validation) is judged
against the instrument's noise.  A noise stated 100 times too large makes
the data look uninformative: the geometric fit leans on the prior, no
effect beats the noise, and the verdict is "within the instrument noise"
whatever the machine does.  So, as ``identify`` does
(:mod:`bayescal.identify.calibrate`), the tool rows' sigma is multiplied by
the scale the geometric fit's residuals support, refitted at that sigma
until the scale settles, and the diagnosis runs at it.

Only a noise stated too *large* is re-estimated here: residuals larger
than the noise allows are what the diagnosis explains (a missing effect, a
discrepancy), not a wrong sigma.  The estimate comes from the geometry-only
fit, whose residuals carry any mismatch as well as the noise, so it is an
upper bound on the instrument's real noise and the tests at it stay on the
safe side.  The body sensors' tilt rows keep their own test
(``bayescal.diagnose.core._sensor_noise``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..effects.model import fit_map
from ..errors import KinematicsError
from ..identify.noise import NoiseCheck, check_noise, distinct_measurements

__all__ = ["NoiseSettling", "noise_test", "settle_overstated_noise", "with_tool_noise_scale", "MAX_ROUNDS", "MIN_SCALE"]

#: Refits at most while the scale settles (it settles within 2 % in two or three).
MAX_ROUNDS = 6
#: Smallest factor on a stated noise (residuals a thousand times below it are a noise-free simulation).
MIN_SCALE = 1e-3


@dataclass(frozen=True)
class NoiseSettling:
    """The stated noise tested by the geometric fit, and the factor the diagnosis uses on the tool rows' sigma.

    Attributes
    ----------
    check : NoiseCheck
        The chi-square test at the stated noise (before any rescaling).
    scale : float
        Factor on the tool rows' stated sigma the diagnosis runs at: 1 unless
        ``check`` calls the noise overstated.
    """

    check: NoiseCheck
    scale: float = 1.0

    @property
    def rescaled(self) -> bool:
        return self.scale != 1.0


def with_tool_noise_scale(model, scale: float):
    """``model`` with its tool rows' sigma multiplied by ``scale`` (body sensors' tilt rows unchanged)."""
    if scale == 1.0:
        return model
    sigma = np.array(model.row_sigma, dtype=float)
    sigma[:, : model.tool_dof] *= scale
    return model.with_pose_sigma(sigma)


def noise_test(model, fit, excluded_rows: int = 0) -> NoiseCheck:
    """The chi-square test of the stated noise on a geometric fit of ``model``.

    Parameters
    ----------
    model : Model
        The model fitted (rows of excluded outliers down-weighted to nothing).
    fit : EffectFit
        Its MAP fit (:func:`bayescal.effects.model.fit_map`).
    excluded_rows : int
        Measured components of excluded outliers: they add nothing to the
        chi-square, nor to its expectation.
    """
    # copied rows add rows but no information about the noise (bayescal.identify.noise.distinct_rows)
    rows = min(fit.n_rows, distinct_measurements(model) * model.dof) - excluded_rows
    return check_noise(fit.chi2, rows - fit.edf)


def settle_overstated_noise(model, first: NoiseCheck) -> NoiseSettling:
    """Where ``first`` calls the stated noise overstated, the factor on the tool rows' sigma the residuals support.

    Parameters
    ----------
    model : Model
        The geometry-only model of the recording (its rows' sigma as stated).
    first : NoiseCheck
        The test at the stated noise (:func:`noise_test` on the geometric fit).

    Returns
    -------
    NoiseSettling
        ``first`` and the factor: 1 unless ``first`` is ``overstated``; then
        the product of the rounds' estimates, each refit at the sigma so far,
        until a round changes it by less than 2 % (at least :data:`MIN_SCALE`,
        at most 1).
    """
    if first.verdict != "overstated":
        return NoiseSettling(first, 1.0)
    # the first estimate comes from a fit the wrong sigma spoiled (held by the prior, it leaves the geometry's
    # errors in the residuals): refit at the new sigma until the scale settles
    scale = max(first.scale, MIN_SCALE)
    for _ in range(MAX_ROUNDS):
        trial = with_tool_noise_scale(model, scale)
        try:
            fit = fit_map(trial)
        except KinematicsError:
            break
        red = noise_test(trial, fit).reduced
        if not (math.isfinite(red) and red > 0):
            break
        new = max(scale * math.sqrt(red), MIN_SCALE)
        done = abs(math.log(new / scale)) < math.log(1.02)
        scale = new
        if done:
            break
    # never above the stated noise: a noise found too large is not raised by its own re-estimate
    return NoiseSettling(first, min(scale, 1.0))
