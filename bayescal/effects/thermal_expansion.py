"""Thermal expansion of the actuator screws/rails, driven by temperature or, failing that, by time."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from ..errors import InputError
from ..machines.base import Machine, ToolPoses
from .base import Effect, EffectParam, Features, measurement_sequence
from .conditions import temperature_step

__all__ = ["ThermalExpansion", "REFERENCE_TEMPERATURE_C", "warmup_temperature", "link_factors"]

#: ISO 1: the reference temperature of dimensional metrology, degC.
REFERENCE_TEMPERATURE_C = 20.0


def warmup_temperature(time_s: NDArray, *, rise_K: float = 5.0, tau_s: float = 1500.0, start_C: float = 20.0) -> NDArray:
    """A first-order warm-up curve ``T = start + rise (1 - exp(-t / tau))`` (degC)."""
    return start_C + rise_K * (1.0 - np.exp(-np.asarray(time_s, float) / tau_s))


def link_factors(machine: Machine, q: NDArray, theta: NDArray, poses: ToolPoses) -> NDArray | None:
    """Per pose, the actuator motion equivalent to a growth of each actuator's link, shape (n, m, m), or None.

    ``K[n, i, j] = d q_i / d l_j`` at a fixed tool pose: the motions of the
    actuators that move the tool as a unit growth of link ``j`` does, by
    least squares on the tool pose (position rows in mm, rotation rows
    scaled by 1000 mm), from :meth:`Machine.tool_jacobian` (the
    ``chain<j>.link_length`` columns) and :meth:`Machine.actuator_jacobian`.
    On the 3-PRS it is diagonal and exact: ``1 / (L_hat_j . u_j)`` with the
    link's unit vector from slider to platform (about ``-1.1`` for links
    hanging below the sliders: a longer link lowers the platform).  None when
    the machine has no parameter ``chain<j>.link_length`` for every actuator
    ``j`` (the RASPM names its links per slider).
    """
    names = machine.layout.names
    want = [f"chain{j + 1}.link_length" for j in range(machine.n_actuators)]
    if not all(w in names for w in want):
        return None
    idx = [names.index(w) for w in want]
    w = np.array([1.0, 1.0, 1.0, 1e3, 1e3, 1e3])[None, :, None]
    Jq = machine.actuator_jacobian(q, theta, poses) * w
    Jl = machine.tool_jacobian(q, theta, poses)[:, :, idx] * w
    return np.linalg.pinv(Jq) @ Jl


def _reference_link_factors(machine: Machine, q0: NDArray, theta: NDArray, K: NDArray) -> NDArray:
    """``K_bar``: the link factors at the home pose ``q0`` (mean of ``K`` over the poses if it cannot be had).

    Why not the mean over the poses at hand: the link term's reference would
    then move with the poses evaluated, so one stored parameter set would
    predict differently on two recordings, and a lone grid node (its own
    mean) would lose the link growth altogether.
    """
    if machine.q_limits is not None:
        if theta is not None and np.ndim(theta) == 2:  # per-pose geometry (a growing machine): its mean
            theta = np.mean(theta, axis=0)
        # the home pose is the machine's, not a measured one: its geometry (no instrument station is bound to it)
        geo, gidx = machine.geometry_part
        th = None if theta is None else np.asarray(theta, dtype=float)[gidx]
        home = geo.forward(q0[None], th)
        if home.success.all():
            Kh = link_factors(geo, q0[None], th, home)
            if Kh is not None:
                return Kh[0]
    return K.mean(axis=0)


class ThermalExpansion(Effect):
    """Lengths grow with temperature: actuator screws or scales, links, rails and frame.

    Physics, part by part (``dT = T - T_ref``, ``T_ref`` = ``reference_C``):

    * **Screw or scale** (the element that measures ``q``): fixed at its
      bearing or datum ``s_i`` (unknown), it grows by ``alpha_i dT`` per
      unit length, so the slider commanded to ``q_i`` stands at
      ``s_i + (q_i - s_i)(1 + alpha_i dT)``: ``dq_i = alpha_i dT (q_i - s_i)
      = alpha_i dT (q_i - q0_i) + alpha_i dT (q0_i - s_i)``, ``alpha_i >= 0``
      whichever end the bearing is at.
    * **Links** (machines with a ``chain<i>.link_length`` per actuator):
      link ``j`` grows by ``lambda_j dT`` (``lambda_j = alpha_link l_j``,
      um/K, ``>= 0``), which moves the tool as the actuator motion
      ``K(x) lambda dT`` does (:func:`link_factors`; on the 3-PRS
      ``1 / (L_hat . u)``, which changes with the link's inclination).
    * **Rails, supports and frame**: a displacement along each actuator that
      does not depend on the pose, collected with the constant parts above
      in one drift per actuator.

    With ``q0`` the middle of ``q_limits`` and ``K_bar`` the value of ``K``
    at the home pose ``q0`` (both decorrelate the terms from the drift, and
    both are properties of the machine, not of the poses at hand, so a
    stored ``[effect.thermal_expansion]`` table means the same on every
    recording and at every node of a compensation grid; without
    ``q_limits``, or if the home pose does not assemble, ``K_bar`` is the
    mean of ``K`` over the poses):

        dq = dT (g + alpha (q - q0) + (K(x) - K_bar) lambda)      (channel ``temp_C``)

    Parameters ``drift.q<i>`` (um/K: the whole chain's growth at mid-stroke
    and mean link inclination, e.g. 11.5 um/m/K x 0.5 m = 6 um/K for steel;
    either sign), ``alpha.q<i>`` (um/m/K, ``>= 0``: steel 11-12, cast iron
    10, aluminium 23, glass scales 8; a screw warmed by its own nut shows an
    apparent 5-30 per degree of *air* temperature) and, where links are
    named, ``link.q<i>`` (um/K, ``>= 0``: a 400 mm steel link grows 4.6
    um/K).  When only ``time_s`` is recorded, the temperature follows a
    warm-up curve from a cold start at the reference temperature,

        dq = (1 - exp(-t / tau)) (s + e (q - q0) + (K(x) - K_bar) k)

    with ``shift.q<i>`` (um), ``strain.q<i>`` (um/m, ``>= 0``),
    ``link_shift.q<i>`` (um, ``>= 0``) and ``tau`` (s, the warm-up time
    constant, 10-60 minutes on machine tools).  Inputs with documented
    defaults (constructor arguments): ``reference_C = 20`` (ISO 1; the
    temperature at which the geometry and the screw leads are nominal; in
    time-only mode also the temperature at the start of the session).
    Hidden assumptions: one temperature for all parts (a screw warmed by its
    nut, or links warmer than the air, show as larger apparent
    coefficients); growth of the platform and of the base radii is seen only
    through its projection on the actuators (the drift).
    """

    name = "thermal_expansion"
    summary = "screws/scales, links and frame grow with temp_C (or along a warm-up curve in time_s)"
    magnitude_unit = "um/m/K"
    default_magnitude = 12.0
    needs_poses = True
    settings_keys = ("reference_C",)

    def __init__(self, *, reference_C: float = REFERENCE_TEMPERATURE_C):
        self.reference_C = float(reference_C)

    def separating_conditions(self, aux: dict) -> tuple:
        """A temperature step, where the recording has a temperature channel (a warm-up curve in time alone has none)."""
        return (temperature_step(),) if "temp_C" in aux else ()

    def not_applicable(self, machine: Machine, aux: dict) -> str | None:
        if "temp_C" not in aux and "time_s" not in aux:
            return "needs a temp_C or time_s channel in the recording"
        return None

    def features(self, machine: Machine, q: NDArray, theta: NDArray, aux: dict, order, poses: ToolPoses | None) -> Features:
        q0 = machine.home_q() if machine.q_limits is not None else q.mean(axis=0)
        if poses is None:
            poses = machine.forward(q, theta)
        K = link_factors(machine, q, theta, poses)
        per = {"q": q}
        # drifts and shifts are small changes of q: um on a slider, urad on a revolute joint
        const = {"q0": q0, "links": K is not None, "to_q": np.array([u.small_to_q for u in machine.actuator_unit_info])}
        if K is not None:
            per["K"] = K - _reference_link_factors(machine, q0, theta, K)[None]
        if "temp_C" in aux:
            per["x"] = np.asarray(aux["temp_C"], float) - self.reference_C
            return Features(per, {**const, "mode": "temperature"})
        if "time_s" in aux:
            t = np.asarray(aux["time_s"], float)
            t0 = t[measurement_sequence(order, len(t))[0]] if len(t) else 0.0
            span = float(np.ptp(t)) if len(t) else 1.0
            per["t"] = t - t0
            return Features(per, {**const, "mode": "time", "span": max(span, 1.0)})
        raise InputError("thermal_expansion: the recording has neither a temp_C nor a time_s channel")

    def params(self, machine: Machine, features: Features) -> tuple[EffectParam, ...]:
        m = machine.n_actuators
        links = features.const["links"]
        units = machine.actuator_unit_info
        if features.const["mode"] == "temperature":
            out = [EffectParam(f"drift.q{i + 1}", f"{u.small}/K", 10.0 * u.per_um) for i, u in enumerate(units)]
            out += [EffectParam(f"alpha.q{i + 1}", f"{units[i].strain}/K", 20.0, lower=0.0) for i in range(m)]
            if links:
                out += [EffectParam(f"link.q{i + 1}", "um/K", 10.0, lower=0.0) for i in range(m)]
            return tuple(out)
        span = features.const["span"]
        out = [EffectParam(f"shift.q{i + 1}", u.small, 50.0 * u.per_um) for i, u in enumerate(units)]
        out += [EffectParam(f"strain.q{i + 1}", units[i].strain, 100.0, lower=0.0) for i in range(m)]
        if links:
            out += [EffectParam(f"link_shift.q{i + 1}", "um", 50.0, lower=0.0) for i in range(m)]
        out.append(EffectParam("tau", "s", span, prior_mean=span / 2, lower=0.0))
        return tuple(out)

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
        """Per unit of the driving term: ``g + alpha (q - q0) + (K - K_bar) lambda`` in mm (per K or per warm-up)."""
        q = features.per_pose["q"]
        m = q.shape[1]
        out = features.const["to_q"][None, :] * eta[None, :m] + 1e-6 * eta[None, m : 2 * m] * (q - features.const["q0"][None, :])
        if features.const["links"]:
            out = out + 1e-3 * np.einsum("nij,j->ni", features.per_pose["K"], eta[2 * m : 3 * m])
        return out

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
        J[:, np.arange(m), np.arange(m)] = features.const["to_q"][None, :] * x[:, None]
        J[:, np.arange(m), m + np.arange(m)] = 1e-6 * x[:, None] * (q - features.const["q0"][None, :])
        if features.const["links"]:
            J[:, :, 2 * m : 3 * m] = 1e-3 * x[:, None, None] * features.per_pose["K"]
        if dx is not None:
            J[:, :, -1] = dx[:, None] * self._growth(features, eta)
        return J

    def simulated_values(self, machine: Machine, features: Features, magnitude: float, rng) -> NDArray:
        """Screws of expansion ``magnitude`` (um/m/K, +-30 %) fixed at ``q = 0``: drift ``alpha q0``; rigid links."""
        alpha = magnitude * rng.uniform(0.7, 1.3, machine.n_actuators)
        # um/m/K x mm -> um/K; on a revolute joint urad/rad/K x rad -> urad/K (the factor 1e-3 / to_q is 1 or 1000)
        drift = 1e-3 * alpha * features.const["q0"] * (1e-3 / features.const["to_q"])
        links = [np.zeros(machine.n_actuators)] if features.const["links"] else []
        if features.const["mode"] == "time":
            # what a 5 K rise gives when warm; a 25-minute time constant
            return np.concatenate([5.0 * drift, 5.0 * alpha, *links, [1500.0]])
        return np.concatenate([drift, alpha, *links])
