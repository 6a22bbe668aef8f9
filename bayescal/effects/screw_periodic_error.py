"""Periodic error of a lead screw or encoder: repeats with actuator position at a fixed pitch."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from ..machines.base import Machine, ToolPoses
from .base import Effect, EffectParam, Features
from .periodogram import MIN_PERIODS, PITCH_RANGES, admissible_pitch_range, n_independent_frequencies, periodogram, pitch_grid

__all__ = ["ScrewPeriodicError", "START_PITCH"]

#: Pitch the fit starts from before the periodogram refines it, by the unit of ``q``.
START_PITCH = {"mm": 10.0, "rad": 0.1}


class ScrewPeriodicError(Effect):
    """A periodic error in actuator position with unknown pitch, amplitude and phase.

    Physics: lead-screw pitch errors (thread run-out, nut wobble) and
    encoder/scale interpolation errors repeat once per screw turn or scale
    period ``p``:

        dq_i = a_i sin(2 pi (q_i - q0_i) / p) + b_i cos(2 pi (q_i - q0_i) / p)

    with one pitch for all actuators (identical drives) and phases counted
    from the middle ``q0`` of ``q_limits`` (of the recorded ``q`` if the
    machine file has none).  Parameters:
    ``pitch`` (mm) and ``sin.q<i>``, ``cos.q<i>`` (um; amplitude
    ``sqrt(a^2 + b^2)``).  The pitch is found first by a Lomb-Scargle
    periodogram over ``q`` of the geometric fit's actuator-space residuals
    (summed over actuators), searched in 1-50 mm but only up to half the
    recorded stroke (the largest range of ``q`` over the actuators);
    amplitudes and phases then enter linearly and the pitch is refined with
    them.  A fitted pitch longer than half the recorded stroke makes the
    effect inadmissible: with fewer than two full periods in the stroke a
    sine is indistinguishable from a smooth error (a quadratic rail
    straightness error was named a screw error with pitches of about the
    stroke), so a periodic error is only claimed when it repeats.  Because the pitch is
    chosen by a search, the evidence pays a look-elsewhere penalty of
    ``ln(number of independent frequencies)``.  Usual size on machine
    tools: 1-5 um for ground ball screws, 10-30 um for rolled screws or
    worn nuts; pitches 5-20 mm.

    Revolute drives (``Machine.actuator_units`` ``"rad"``): the same model
    for the periodic error of a gear train or encoder, with ``pitch`` in rad
    (searched in 0.01-0.5 rad: tooth mesh of 13-600 teeth; once- or
    twice-per-turn errors are the joint's geometry) and amplitudes in urad
    (prior 200 urad; worm and strain-wave gears show 20-150 urad).  One pitch
    needs one unit: a machine with both kinds of drive cannot use the effect.
    """

    name = "screw_periodic_error"
    summary = "a periodic error in actuator position (unknown pitch, amplitude, phase)"
    magnitude_unit = "um"
    default_magnitude = 20.0

    def not_applicable(self, machine: Machine, aux: dict) -> str | None:
        if len(set(machine.actuator_units)) > 1:
            return "one pitch for all drives, but the machine has both prismatic (mm) and revolute (rad) actuators"
        return None

    def features(self, machine: Machine, q: NDArray, theta: NDArray, aux: dict, order, poses: ToolPoses | None) -> Features:
        # phases are counted from the middle of the workspace, which decorrelates them from the pitch
        q_ref = machine.home_q() if machine.q_limits is not None else q.mean(axis=0)
        units = machine.actuator_unit_info
        prange = PITCH_RANGES[units[0].unit]
        pitch0 = START_PITCH[units[0].unit]  # refined by the periodogram of the residuals (refine)
        return Features({"q": q}, {"pitch0": pitch0, "pitch_sd": 0.1 * pitch0, "span": float(np.ptp(q, axis=0).max()),
                                   "q_ref": q_ref, "pitch_range": prange, "unit": units[0].unit,
                                   "to_q": np.array([u.small_to_q for u in units])})

    def refine(self, features: Features, q: NDArray, dq_residual: NDArray) -> Features:
        """Start pitch from the summed periodogram of the actuator-space residuals."""
        span = float(np.ptp(q, axis=0).max())
        prange = admissible_pitch_range(span, features.const["pitch_range"])
        if prange is None:
            return Features(features.per_pose, {**features.const, "span": span})
        freqs = pitch_grid(span, prange)
        power = sum(periodogram(q[:, i], dq_residual[:, i], freqs) for i in range(q.shape[1]))
        f0 = freqs[int(np.argmax(power))]
        pitch0 = 1.0 / f0
        # the peak is about 1/span wide in frequency: pitch^2 / span in pitch
        const = {**features.const, "pitch0": pitch0, "pitch_sd": pitch0**2 / max(span, 1e-9), "span": span}
        return Features(features.per_pose, const)

    def inadmissible(self, features: Features, eta: NDArray | None = None) -> str | None:
        span, full, unit = features.const["span"], features.const["pitch_range"], features.const["unit"]
        prange = admissible_pitch_range(span, full)
        if prange is None:
            return f"recorded stroke {span:.3g} {unit} is shorter than {MIN_PERIODS:g} periods of the shortest pitch ({full[0]:g} {unit})"
        if eta is not None and not float(eta[0]) <= prange[1] * (1 + 1e-9):
            return (f"fitted pitch {float(eta[0]):.3g} {unit} does not fit {MIN_PERIODS:g} full periods in the recorded stroke "
                    f"{span:.3g} {unit} (a smooth error over the stroke, not a periodic one)")
        return None

    def occam_penalty(self, features: Features, q: NDArray) -> float:
        full = features.const["pitch_range"]
        prange = admissible_pitch_range(features.const["span"], full) or full
        return float(np.log(n_independent_frequencies(features.const["span"], prange)))

    def params(self, machine: Machine, features: Features) -> tuple[EffectParam, ...]:
        units = machine.actuator_unit_info
        out = [EffectParam("pitch", units[0].unit, features.const["pitch_sd"], prior_mean=features.const["pitch0"])]
        for i, u in enumerate(units):
            out += [EffectParam(f"sin.q{i + 1}", u.small, 20.0 * u.per_um), EffectParam(f"cos.q{i + 1}", u.small, 20.0 * u.per_um)]
        return tuple(out)

    @staticmethod
    def _phase(features: Features, eta: NDArray):
        q = features.per_pose["q"] - features.const["q_ref"][None, :]
        p = max(float(eta[0]), 1e-3)
        return q, 2 * np.pi * q / p, p

    def delta_q(self, features: Features, eta: NDArray) -> NDArray:
        eta = np.asarray(eta, float)
        q, ph, _ = self._phase(features, eta)
        a, b = eta[1::2] * features.const["to_q"], eta[2::2] * features.const["to_q"]
        return a[None, :] * np.sin(ph) + b[None, :] * np.cos(ph)

    def delta_q_jacobian(self, features: Features, eta: NDArray) -> NDArray:
        eta = np.asarray(eta, float)
        q, ph, p = self._phase(features, eta)
        n, m = q.shape
        k = features.const["to_q"]
        a, b = eta[1::2] * k, eta[2::2] * k
        s, c = np.sin(ph), np.cos(ph)
        J = np.zeros((n, m, 1 + 2 * m))
        J[:, :, 0] = (a[None, :] * c - b[None, :] * s) * (-ph / p)
        for i in range(m):
            J[:, i, 1 + 2 * i] = k[i] * s[:, i]
            J[:, i, 2 + 2 * i] = k[i] * c[:, i]
        return J

    def simulated_values(self, machine: Machine, features: Features, magnitude: float, rng) -> NDArray:
        m = machine.n_actuators
        amp = magnitude * rng.uniform(0.6, 1.4, m)
        phase = rng.uniform(0, 2 * np.pi, m)
        lo, hi = features.const["pitch_range"]
        out = [rng.uniform(4.0, 20.0) if hi > 4.0 else float(np.exp(rng.uniform(np.log(lo), np.log(hi))))]
        for i in range(m):
            out += [amp[i] * np.cos(phase[i]), amp[i] * np.sin(phase[i])]
        return np.array(out)
