"""Joint compliance: the actuated joints yield under the gravity load they carry."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from ..machines.base import Machine, ToolPoses
from .base import Effect, EffectParam, Features

__all__ = ["JointCompliance", "actuator_loads", "GRAVITY"]

#: Standard gravity, m/s^2.
GRAVITY = 9.80665


def actuator_loads(
    machine: Machine, q: NDArray, theta: NDArray, poses: ToolPoses, mass_kg: NDArray, *, down: NDArray = (0.0, 0.0, -1.0)
) -> NDArray:
    """Actuator forces (N) that hold the platform and payload against gravity.

    Static equilibrium by virtual work: for every motion the actuators can
    make, ``f . dq = w . dx``, with ``dx = J dq`` the tool twist (``J`` from
    :meth:`Machine.actuator_jacobian`), hence ``f = J^T w`` (the transpose
    of the inverse Jacobian's inverse: ``J^-T`` of the usual ``dq = J^-1 dx``).
    The wrench ``w`` of the weight ``m g`` acting at the platform origin,
    expressed at the tool point: force ``F = m g down``, moment
    ``(p - tool) x F``.

    Parameters
    ----------
    mass_kg : ndarray, shape (n_poses,)
        Platform plus payload mass per pose, kg.
    down : (3,)
        Gravity direction in the base frame (unit vector).

    Returns
    -------
    ndarray, shape (n_poses, n_actuators), N
        Generalised gravity force on each actuator coordinate (positive:
        gravity pushes ``q_i`` up).
    """
    J = machine.actuator_jacobian(q, theta, poses)
    F = np.asarray(mass_kg, float)[:, None] * GRAVITY * np.asarray(down, float)[None, :]
    origin = poses.state.p if hasattr(poses.state, "p") else poses.position
    M = np.cross(origin - poses.position, F)
    return np.einsum("nki,nk->ni", J[:, :3], F) + np.einsum("nki,nk->ni", J[:, 3:], M)


class JointCompliance(Effect):
    """Actuated joints (screw, nut, bearings, slider) yield under the load they carry.

    Physics: the weight of the platform (``platform_mass_kg``, default 30 kg,
    acting at the platform origin, gravity along ``-z`` of the base frame)
    and of the payload (channel ``payload_kg`` when recorded) loads each
    actuator with ``f_i = (J^T w)_i`` (:func:`actuator_loads`), which
    depends on the pose; a drive of compliance ``c_i`` gives way by

        dq_i = c_i f_i.

    Parameters ``compliance.q<i>`` in um/N.  Usual size on machine tools:
    ball-screw drives 0.002-0.02 um/N (50-500 N/um axial stiffness); with
    links, spherical joints and a lightweight frame the apparent compliance
    at the actuator reaches 0.05-1 um/N.  Without a payload channel only the
    pose-dependent part of the load is seen; the constant part is absorbed
    by the actuator offsets.
    """

    name = "joint_compliance"
    summary = "actuators yield under the gravity load of platform and payload (pose- and payload_kg-dependent)"
    magnitude_unit = "um/N"
    default_magnitude = 0.5
    needs_poses = True

    def __init__(self, *, platform_mass_kg: float = 30.0, down=(0.0, 0.0, -1.0)):
        self.platform_mass_kg = float(platform_mass_kg)
        self.down = np.asarray(down, float)

    def features(self, machine: Machine, q: NDArray, theta: NDArray, aux: dict, order, poses: ToolPoses | None) -> Features:
        if poses is None:
            poses = machine.forward(q, theta)
        mass = self.platform_mass_kg + np.asarray(aux.get("payload_kg", np.zeros(q.shape[0])), float)
        f = actuator_loads(machine, q, theta, poses, mass, down=self.down)
        return Features({"f": f}, {"platform_mass_kg": self.platform_mass_kg})

    def inadmissible(self, features: Features, eta: NDArray | None = None) -> str | None:
        # e.g. the RU-PUS-PRS: the platform origin is the centre of the passive post's universal joint,
        # so the post carries the weight and a drive compliance cannot show (evidence 0); the drives'
        # share is then round-off plus what geometric errors of a few 0.01 mm give (1e-4 of the weight)
        f = features.per_pose["f"]
        if f.size and np.max(np.abs(f)) <= 1e-3 * features.const["platform_mass_kg"] * GRAVITY:
            return "the actuators carry no gravity load at any pose (under 0.1 % of the weight: it acts at a passive joint)"
        return None

    def params(self, machine: Machine, features: Features) -> tuple[EffectParam, ...]:
        return tuple(EffectParam(f"compliance.q{i + 1}", "um/N", 1.0, lower=0.0) for i in range(machine.n_actuators))

    def delta_q(self, features: Features, eta: NDArray) -> NDArray:
        return 1e-3 * features.per_pose["f"] * np.asarray(eta)[None, :]

    def delta_q_jacobian(self, features: Features, eta: NDArray) -> NDArray:
        f = features.per_pose["f"]
        n, m = f.shape
        J = np.zeros((n, m, m))
        J[:, np.arange(m), np.arange(m)] = 1e-3 * f
        return J

    def simulated_values(self, machine: Machine, features: Features, magnitude: float, rng) -> NDArray:
        return magnitude * rng.uniform(0.6, 1.4, machine.n_actuators)
