"""Restrained deformation of a redundantly actuated module: actuators fight through the closed loops."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from ..machines.base import Machine, ToolPoses
from .base import NONPHYSICAL_Z, Effect, EffectParam, Features

__all__ = ["RedundancyPreload", "machine_dof", "orient_directions", "PRELOAD_PRIOR_UM"]

#: Prior one-sigma of a preload deflection, um.  Wide on purpose: the geometric parameters absorb about
#: 99 % of a preload's signature on the RASPM (docs/diagnose.md), so only deflections of a few hundred um
#: (kN preloads on apparent compliances of 0.1 um/N) are visible at all, and a narrow prior would rule
#: exactly those out.
PRELOAD_PRIOR_UM = 200.0


def machine_dof(machine: Machine) -> int:
    """Degrees of freedom of the platform: the machine's ``n_dof`` (or ``dof``) if it declares one, else its actuator count."""
    for attr in ("n_dof", "dof"):
        value = getattr(machine, attr, None)
        if isinstance(value, (int, np.integer)) and value > 0:
            return int(value)
    return machine.n_actuators


def orient_directions(nu: NDArray) -> NDArray:
    """Unit directions (n, m) given up to sign, flipped to one continuous orientation over the poses.

    A preload ``P`` pushes along the same internal-force direction at every
    pose, so the sign of ``nu`` must not jump between poses.  Fixing one
    component's sign (``nu_1 >= 0``) would flip the direction wherever that
    component passes through zero in the workspace; instead every ``nu`` is
    aligned with the principal direction of all of them (``nu . r >= 0``),
    and ``r`` is signed so that its largest component is positive.
    """
    nu = np.asarray(nu, float)
    if nu.size == 0:
        return nu
    r = np.linalg.svd(nu, full_matrices=False)[2][0]
    r = r if r[int(np.argmax(np.abs(r)))] > 0 else -r
    return np.where((nu @ r)[:, None] >= 0, nu, -nu)


class RedundancyPreload(Effect):
    """Internal preload of a redundantly actuated machine (more actuators than DOF).

    Physics: with ``m`` actuators for ``n < m`` degrees of freedom, the
    actuators can push against each other without moving the platform: the
    internal force lies in the ``m - n`` dimensional space of actuator
    motions that do not move the tool: ``null(J_a^T)``, ``J_a = dq/dx`` the
    inverse-kinematics Jacobian when the machine has one (``ik_jacobian``,
    the RASPM), else the null space of the actuator Jacobian ``d x / d q``).  A preload ``P`` along the unit
    direction ``nu(q)`` of that space deflects compliant drives by
    ``c_i P nu_i`` (sign as in ``joint_compliance``: ``dq_i = c_i f_i``, ``f_i`` the force
    pushing drive ``i`` towards larger ``q_i``); unequal compliances leave a deflection outside the null
    space, which moves the tool:

        dq_i = d_i nu_i(q)            (one redundant direction, oriented by :func:`orient_directions`)

    Parameters ``preload_deflection.q<i>`` (um, ``c_i P``; they share the
    sign of ``P``, so a fit with significantly opposite signs is rejected as
    non-physical).  Usual size: preloads of 100-1000 N on drives of 50-500
    N/um give 1-20 um; with links and frame, apparent compliances of 0.1-1
    um/N and kN preloads give hundreds of um.  On the RASPM about 99 % of
    the signature is absorbed by the geometric parameters (the constant and
    pose-linear parts of ``d_i nu_i(x)``; docs/diagnose.md), so only
    deflections of some hundred um are visible.  Not
    applicable to machines with as many actuators as degrees of freedom
    (the 3-PRS): there is no internal force to carry.
    """

    name = "redundancy_preload"
    summary = "actuators preloaded against each other through the closed loops (redundant machines only)"
    magnitude_unit = "um"
    default_magnitude = 20.0
    needs_poses = True

    def not_applicable(self, machine: Machine, aux: dict) -> str | None:
        if machine.n_actuators <= machine_dof(machine):
            return (
                f"not applicable: the {machine.kind} has {machine.n_actuators} actuators for "
                f"{machine_dof(machine)} degrees of freedom (no redundant actuation, no internal preload)"
            )
        return None

    def features(self, machine: Machine, q: NDArray, theta: NDArray, aux: dict, order, poses: ToolPoses | None) -> Features:
        if poses is None:
            poses = machine.forward(q, theta)
        x = getattr(poses.state, "x", None)
        if hasattr(machine, "ik_jacobian") and x is not None:
            # the internal forces are null(J_a^T), J_a = dq/dx of the full (redundant) inverse kinematics.
            # The forward kinematics of a redundant machine reads only a non-redundant subset of q, so
            # the null space of its dh/dq is just the ignored actuator, which would never move the tool.
            from ..redundant.physics import internal_force_basis

            _, Ja = machine.ik_jacobian(x, theta)
            return Features({"nu": orient_directions(internal_force_basis(Ja)[:, :, 0])}, {})
        J = machine.actuator_jacobian(q, theta, poses)  # (n, 6, m)
        n, _, m = J.shape
        k = m - machine_dof(machine)
        nu = np.zeros((n, m))
        for j in range(n):
            # the direction of actuator motion that moves the tool least: the internal-force direction
            nu[j] = np.linalg.svd(J[j])[2][-max(k, 1):][0]
        return Features({"nu": orient_directions(nu)}, {})

    def params(self, machine: Machine, features: Features) -> tuple[EffectParam, ...]:
        return tuple(EffectParam(f"preload_deflection.q{i + 1}", "um", PRELOAD_PRIOR_UM) for i in range(machine.n_actuators))

    def delta_q(self, features: Features, eta: NDArray) -> NDArray:
        return 1e-3 * features.per_pose["nu"] * np.asarray(eta)[None, :]

    def delta_q_jacobian(self, features: Features, eta: NDArray) -> NDArray:
        nu = features.per_pose["nu"]
        n, m = nu.shape
        J = np.zeros((n, m, m))
        J[:, np.arange(m), np.arange(m)] = 1e-3 * nu
        return J

    def nonphysical(self, params, eta: NDArray, std: NDArray) -> str | None:
        """Deflections of significantly opposite signs: ``d_i = c_i P`` with every compliance ``c_i > 0``."""
        eta, std = np.asarray(eta, float), np.asarray(std, float)
        z = eta / np.maximum(std, 1e-300)
        pos, neg = np.flatnonzero(z > NONPHYSICAL_Z), np.flatnonzero(z < -NONPHYSICAL_Z)
        if pos.size and neg.size:
            i, j = pos[0], neg[0]
            return (
                f"non-physical fit: {params[i].name} = {eta[i]:.3g} and {params[j].name} = {eta[j]:.3g} um have opposite "
                "signs (each is a positive compliance times the one preload force)"
            )
        return None

    def simulated_values(self, machine: Machine, features: Features, magnitude: float, rng) -> NDArray:
        """Deflections ``c_i P``: compliances within +-40 % of each other, one preload of either sign."""
        return rng.choice([-1.0, 1.0]) * magnitude * rng.uniform(0.6, 1.4, machine.n_actuators)
