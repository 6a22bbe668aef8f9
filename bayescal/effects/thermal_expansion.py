"""Thermal expansion of the actuator screws/rails, driven by temperature or, failing that, by time."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from ..errors import InputError
from ..machines.base import Machine, ToolPoses
from .base import Effect, EffectParam, Features, measurement_sequence

__all__ = ["ThermalExpansion", "REFERENCE_TEMPERATURE_C", "warmup_temperature"]

#: ISO 1: the reference temperature of dimensional metrology, degC.
REFERENCE_TEMPERATURE_C = 20.0


def warmup_temperature(time_s: NDArray, *, rise_K: float = 5.0, tau_s: float = 1500.0, start_C: float = 20.0) -> NDArray:
    """A first-order warm-up curve ``T = start + rise (1 - exp(-t / tau))`` (degC)."""
    return start_C + rise_K * (1.0 - np.exp(-np.asarray(time_s, float) / tau_s))


class ThermalExpansion(Effect):
    """Lengths grow with temperature: actuator screws/scales, rails, links and frame.

    Physics: a screw fixed at its bearing expands by ``alpha dT`` per unit
    length, so the slider at commanded ``q_i`` is displaced by
    ``alpha dT q_i``; growth of the rail supports, links and frame adds a
    displacement along the actuator that does not depend on ``q_i``.  With
    ``q0`` the middle of ``q_limits`` (which decorrelates the two terms):

        dq_i = (T - 20 degC) (g_i + alpha_i (q_i - q0_i))      (channel ``temp_C``)

    Parameters ``drift.q<i>`` (um/K: the whole chain's growth at mid-stroke,
    e.g. 11.5 um/m/K x 0.5 m = 6 um/K for steel) and ``alpha.q<i>`` (um/m/K:
    steel 11-12, cast iron 10, aluminium 23; a screw warmed by its own nut
    shows an apparent 5-30 per degree of *air* temperature).  When only
    ``time_s`` is recorded, the temperature follows a warm-up curve from a
    cold start at the reference temperature,

        dq_i = (1 - exp(-t / tau)) (s_i + e_i (q_i - q0_i))

    with ``shift.q<i>`` (um), ``strain.q<i>`` (um/m) and ``tau`` (s, the
    warm-up time constant, 10-60 minutes on machine tools).
    """

    name = "thermal_expansion"
    summary = "actuator lengths grow with temp_C (or along a warm-up curve in time_s)"
    magnitude_unit = "um/m/K"
    default_magnitude = 12.0

    def not_applicable(self, machine: Machine, aux: dict) -> str | None:
        if "temp_C" not in aux and "time_s" not in aux:
            return "needs a temp_C or time_s channel in the recording"
        return None

    def features(self, machine: Machine, q: NDArray, theta: NDArray, aux: dict, order, poses: ToolPoses | None) -> Features:
        q0 = machine.home_q() if machine.q_limits is not None else q.mean(axis=0)
        if "temp_C" in aux:
            dT = np.asarray(aux["temp_C"], float) - REFERENCE_TEMPERATURE_C
            return Features({"x": dT, "q": q}, {"mode": "temperature", "q0": q0})
        if "time_s" in aux:
            t = np.asarray(aux["time_s"], float)
            t0 = t[measurement_sequence(order, len(t))[0]] if len(t) else 0.0
            span = float(np.ptp(t)) if len(t) else 1.0
            return Features({"t": t - t0, "q": q}, {"mode": "time", "span": max(span, 1.0), "q0": q0})
        raise InputError("thermal_expansion: the recording has neither a temp_C nor a time_s channel")

    def params(self, machine: Machine, features: Features) -> tuple[EffectParam, ...]:
        m = machine.n_actuators
        if features.const["mode"] == "temperature":
            return tuple(EffectParam(f"drift.q{i + 1}", "um/K", 10.0) for i in range(m)) + tuple(
                EffectParam(f"alpha.q{i + 1}", "um/m/K", 20.0, lower=0.0) for i in range(m)
            )
        span = features.const["span"]
        return (
            tuple(EffectParam(f"shift.q{i + 1}", "um", 50.0) for i in range(m))
            + tuple(EffectParam(f"strain.q{i + 1}", "um/m", 100.0, lower=0.0) for i in range(m))
            + (EffectParam("tau", "s", span, prior_mean=span / 2, lower=0.0),)
        )

    def _shape(self, features: Features, eta: NDArray):
        """Per-pose driving term x (K or warm-up fraction) and its derivative w.r.t. tau."""
        if features.const["mode"] == "temperature":
            return features.per_pose["x"], None
        t = features.per_pose["t"]
        tau = max(float(eta[-1]), 1e-3 * features.const["span"])  # keep the curve defined while iterating
        e = np.exp(-t / tau)
        return 1.0 - e, -e * t / tau**2

    @staticmethod
    def _growth(features: Features, eta: NDArray) -> NDArray:
        """Per unit of the driving term: ``g + alpha (q - q0)`` in mm (per K or per warm-up)."""
        q = features.per_pose["q"]
        m = q.shape[1]
        return 1e-3 * eta[None, :m] + 1e-6 * eta[None, m : 2 * m] * (q - features.const["q0"][None, :])

    def delta_q(self, features: Features, eta: NDArray) -> NDArray:
        eta = np.asarray(eta, float)
        x, _ = self._shape(features, eta)
        return x[:, None] * self._growth(features, eta)

    def delta_q_jacobian(self, features: Features, eta: NDArray) -> NDArray:
        eta = np.asarray(eta, float)
        x, dx = self._shape(features, eta)
        q = features.per_pose["q"]
        n, m = q.shape
        J = np.zeros((n, m, len(eta)))
        J[:, np.arange(m), np.arange(m)] = 1e-3 * x[:, None]
        J[:, np.arange(m), m + np.arange(m)] = 1e-6 * x[:, None] * (q - features.const["q0"][None, :])
        if dx is not None:
            J[:, :, 2 * m] = dx[:, None] * self._growth(features, eta)
        return J

    def simulated_values(self, machine: Machine, features: Features, magnitude: float, rng) -> NDArray:
        """Screws of expansion ``magnitude`` (um/m/K, +-30 %) fixed at ``q = 0``: drift ``alpha q0``."""
        alpha = magnitude * rng.uniform(0.7, 1.3, machine.n_actuators)
        drift = 1e-3 * alpha * features.const["q0"]  # um/m/K x mm -> um/K
        if features.const["mode"] == "time":
            # what a 5 K rise gives when warm; a 25-minute time constant
            return np.concatenate([5.0 * drift, 5.0 * alpha, [1500.0]])
        return np.concatenate([drift, alpha])
