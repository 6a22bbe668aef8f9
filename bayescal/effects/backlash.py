"""Backlash: a lost-motion dead band in each actuator."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from ..machines.base import Machine, ToolPoses
from .base import Effect, EffectParam, Features, approach_direction

__all__ = ["Backlash"]


class Backlash(Effect):
    """Lost motion between the drive and the slider (nut, coupling, gearbox).

    Physics: the slider lags the commanded position by half the dead band
    ``b_i`` on the side it came from, so

        dq_i = (b_i / 2) s_i,    s_i = sign(q_i[t] - q_i[t-1])

    with the approach direction ``s_i`` read from the measurement order
    (``0`` for the first pose, whose approach is unknown).  Parameters:
    ``backlash.q<i>`` in um (full width of the dead band).  Usual size on
    machine tools: 1-20 um with preloaded ball screws, up to 50-100 um on
    worn drives or belt/gear axes.
    """

    name = "backlash"
    summary = "a dead band per actuator, signed by the approach direction (measurement order)"
    magnitude_unit = "um"
    default_magnitude = 30.0

    def features(self, machine: Machine, q: NDArray, theta: NDArray, aux: dict, order, poses: ToolPoses | None) -> Features:
        return Features({"s": approach_direction(q, order)}, {"m": q.shape[1]})

    def params(self, machine: Machine, features: Features) -> tuple[EffectParam, ...]:
        return tuple(EffectParam(f"backlash.q{i + 1}", "um", 30.0, lower=0.0) for i in range(machine.n_actuators))

    def delta_q(self, features: Features, eta: NDArray) -> NDArray:
        return features.per_pose["s"] * (0.5e-3 * np.asarray(eta))[None, :]

    def delta_q_jacobian(self, features: Features, eta: NDArray) -> NDArray:
        s = features.per_pose["s"]
        n, m = s.shape
        J = np.zeros((n, m, m))
        J[:, np.arange(m), np.arange(m)] = 0.5e-3 * s
        return J

    def simulated_values(self, machine: Machine, features: Features, magnitude: float, rng) -> NDArray:
        return magnitude * rng.uniform(0.6, 1.4, machine.n_actuators)
