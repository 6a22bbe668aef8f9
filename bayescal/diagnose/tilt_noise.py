"""The body sensors' yardstick in a diagnosis: ``sigma_tilt`` tested on their own rows, and retested with the effects.

A stated ``sigma_tilt`` far too small makes the tilt rows dominate every fit
and test (a bending the tool rows showed plainly was once called
"unexplained"), so the geometry-only fit's tilt rows test it first and the
diagnosis runs at the scale they support (:func:`sensor_noise`).  But the
geometry-only fit's tilt residuals also carry what the sensors see and the
geometry cannot explain: a column tip sensor reads the column's bending.
Rescaled on those residuals, the sensors would be weighted as if they were
as poor as the misfit, and would add nothing to the very diagnosis they
are the most direct measurement for.  So once effects are selected, the
effects are refitted with the tilt rows at the stated ``sigma_tilt`` and
the scale their residuals support is taken (:func:`tilt_scale_with_effects`);
where it is well below the first one, the diagnosis is run again at it.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from ..contract import whiten
from ..effects.model import fit_map
from ..errors import KinematicsError
from ..identify.noise import check_noise
from ..machines.base import Machine
from ..measurement import MeasurementModel
from ..models import model_from_recording

__all__ = ["sensor_noise", "tilt_scale_with_effects"]


def _own(model) -> int:
    """The parameters only the tilt rows see: the sensors' mountings and the level of up."""
    return sum(1 for n in model.machine.layout.names if n.startswith("sensor.") or n.startswith("gravity.tilt."))


def sensor_noise(machine: Machine, recording, model: MeasurementModel,
                 scale: float | None = None) -> tuple[Machine, MeasurementModel, float]:
    """``(machine, model, scale)`` with ``sigma_tilt`` multiplied by ``scale`` where the geometry-only fit's tilt rows
    contradict it (``scale`` 1 and the inputs unchanged where they do not, or without body sensors).

    ``scale`` given: that factor, untested (a rerun at the scale :func:`tilt_scale_with_effects` found).
    """
    if scale is not None:
        if scale == 1.0:
            return machine, model, 1.0
        return _scaled(machine, recording, scale)
    tool = model.tool_dof
    if tool >= model.dof:
        return machine, model, 1.0
    try:
        fit = fit_map(model)
    except KinematicsError:
        return machine, model, 1.0
    r = whiten(model, fit.residual)[:, tool:]
    check = check_noise(float((r**2).sum()), r.size - _own(model))
    if not check.contradicted:
        return machine, model, 1.0
    return _scaled(machine, recording, max(check.scale, 1e-3))


def _scaled(machine: Machine, recording, scale: float):
    scaled = machine.with_noise(replace(machine.noise, sigma_tilt=machine.noise.sigma_tilt * scale))
    return scaled, model_from_recording(scaled, recording, check=False), float(scale)


def tilt_scale_with_effects(model: MeasurementModel, effects, fit, scale: float) -> float:
    """The factor on the stated ``sigma_tilt`` that the tilt rows support once the effects are fitted with them.

    ``model``'s ``sigma_tilt`` is the stated one times ``scale``, at which the
    tilt rows weigh little; so the effects and the geometry are refitted with
    the tilt rows at the stated sigma (started from ``fit``), and the scale
    is what their residuals then support: 1 where the stated sigma fits
    (or is too large), ``sqrt(chi2 / dof)`` where it is still too small.

    Parameters
    ----------
    model : MeasurementModel
        With body sensors.
    effects : sequence of (Effect, Features)
        The effects selected.
    fit : EffectFit
        Their fit at the rescaled sigma (the start).
    scale : float
        The factor ``model``'s ``sigma_tilt`` carries over the stated one.

    Returns
    -------
    float
        ``scale`` itself when the refit fails or the model has no body sensors.
    """
    tool = model.tool_dof
    if tool >= model.dof:
        return scale
    sigma = np.array(model.row_sigma, dtype=float)
    sigma[:, tool:] /= scale
    stated = model.with_pose_sigma(sigma)
    try:
        refit = fit_map(stated, list(effects), theta0=fit.theta, eta0=fit.eta)
    except KinematicsError:
        return scale
    if not refit.success:
        return scale
    r = whiten(stated, refit.residual)[:, tool:]
    check = check_noise(float((r**2).sum()), r.size - _own(model))
    return float(check.scale) if check.verdict == "understated" else 1.0
