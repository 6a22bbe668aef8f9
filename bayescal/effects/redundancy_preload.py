"""Restrained deformation of a redundantly actuated module: position-controlled drives fight through the closed loops."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from ..machines.base import Machine, RedundantKinematics, ToolPoses
from .base import Effect, EffectParam, Features

__all__ = ["RedundancyPreload", "machine_dof", "orient_directions", "RATIO_PRIOR", "RATIO_PRIOR_MEAN", "OFFSET_PRIOR_MM", "offset_prior",
           "redundant_columns"]

#: Prior centre and one-sigma of a compliance ratio ``c_s / c_r`` (dimensionless).  Drives of one module are
#: of one size, so ratios of 0.3-3 are usual; zero (an infinitely compliant redundant drive) is "no preload".
#: The centre is also where the fit starts: the model is bilinear in the ratios and the incompatibility, and
#: from zero ratios Gauss-Newton can run into a minimum with negative compliances.
RATIO_PRIOR_MEAN = 1.0
RATIO_PRIOR = 2.0
#: Prior one-sigma of the redundant drive's offset from its compatible position, mm.  Wide on purpose: a
#: redundant drive may be commanded a deliberate preload offset of tenths of a millimetre.  On a revolute
#: drive (rad) it is scaled like every effect prior (``ActuatorUnit.per_um``): 0.01 rad.
OFFSET_PRIOR_MM = 1.0


def offset_prior(unit) -> float:
    """One-sigma of the redundant drive's offset in its ``q`` unit (an :class:`ActuatorUnit`): 1 mm, or 0.01 rad."""
    return OFFSET_PRIOR_MM * 1e3 * unit.per_um * unit.small_to_q


def machine_dof(machine: Machine) -> int:
    """Degrees of freedom of the platform (:attr:`Machine.n_dof`: the actuator count unless actuation is redundant)."""
    return int(machine.n_dof)


def orient_directions(nu: NDArray) -> NDArray:
    """Unit directions (n, m) given up to sign, flipped to one continuous orientation over the poses.

    Every ``nu`` is aligned with the principal direction of all of them
    (``nu . r >= 0``), and ``r`` is signed so that its largest component is
    positive.  (The restrained model below uses only products ``nu_k nu_r``,
    which do not depend on the sign; the orientation keeps reported
    directions readable.)
    """
    nu = np.asarray(nu, float)
    if nu.size == 0:
        return nu
    r = np.linalg.svd(nu, full_matrices=False)[2][0]
    r = r if r[int(np.argmax(np.abs(r)))] > 0 else -r
    return np.where((nu @ r)[:, None] >= 0, nu, -nu)


def _inner(machine: Machine) -> tuple[RedundantKinematics | None, int]:
    """The redundant kinematics (inside an instrument frame) and the number of frame parameters before its own."""
    return machine.redundancy, machine.n_frame


def _probe_planar(inner) -> NDArray:
    """A fixed set of planar poses (centre and corners of ``pose_range``) to find a parameter's reach structurally."""
    if inner.pose_range is None:
        return np.zeros((1, 3))
    lo, hi = inner.pose_range[:, 0], inner.pose_range[:, 1]
    grid = np.array(np.meshgrid(*[[0.1, 0.5, 0.9]] * 3, indexing="ij")).reshape(3, -1).T
    return lo + (hi - lo) * grid


def redundant_columns(inner) -> NDArray:
    """Geometric parameters that reach only the redundant drive's inverse kinematics (indices into ``inner``'s layout).

    The non-redundant model never reads them; through the preload they are
    the redundant drive's own geometric errors.  Found structurally (exact
    zeros of ``dIK_s / dtheta`` for every non-redundant drive ``s`` at fixed
    poses spread over ``pose_range``), so the set does not depend on a recording.
    """
    x = _probe_planar(inner)
    G = inner.ik_parameter_jacobian(x, None)
    s, r = list(inner.nonredundant), inner.redundant[0]
    reach_s = np.abs(G[:, s]).max(axis=(0, 1))
    reach_r = np.abs(G[:, r]).max(axis=0)
    return np.flatnonzero((reach_s == 0) & (reach_r > 0))


class RedundancyPreload(Effect):
    """Internal preload of a redundantly actuated module whose drives are all position controlled.

    Physics: with ``m`` drives for ``n = m - 1`` degrees of freedom, the
    commanded positions are compatible only for the exact geometry.  The
    redundant drive ``r`` (the one the non-redundant model does not read) is
    commanded ``g_r = IK_r(x0) - q_r`` away from where the others put the
    platform (``x0``, the non-redundant pose); the drives, compliances
    ``c_k``, settle at the least elastic energy ``sum_k (IK_k(x) - q_k)^2 /
    (2 c_k)`` with a self-equilibrated force ``tau = nu P`` (``nu``: unit
    basis of ``null(J_a^T)``, ``J_a = dq/dx``).  To first order in the
    deflections (``J_a dx = delta - g_r e_r`` and ``nu . J_a dx = 0``):

        P = nu_r g_r / sum_k c_k nu_k^2,        dq_k = c_k nu_k P = w_k nu_k nu_r g_r / sum_j w_j nu_j^2

    with ``w_k = c_k / c_r`` the compliance ratios (only ratios matter with
    no external load), and the incompatibility, linear in the geometry,

        g_r(x; theta) = g_r(x0; theta_f) + G_r(x) dtheta_r - offset_r + L_s(x) (theta_s - theta_f,s)

    ``G_r = dIK_r / dtheta_r`` for the redundant drive's own geometric
    errors ``dtheta_r`` (parameters of the effect: the non-redundant model
    never reads them), ``offset_r`` the redundant drive's offset along its
    rail (a commanded preload offset and its zero error are one number),
    and ``L_s = G_r - J_r J_s^-1 G_s`` how the geometry being fitted moves
    ``x0`` and so ``g_r`` (:attr:`geometry_dependent`).  The non-redundant
    model reads the deflected drives ``q_s + dq_s``.  The model is bilinear
    in the ratios and ``dtheta_r``; it vanishes with ``w = 0`` (an infinitely
    compliant redundant drive carries no force).

    Parameters: ``compliance_ratio.q<s>`` (``c_s / c_r``, dimensionless,
    >= 0, prior ``1 +- 2``), ``offset.q<r>`` (the drive's ``q`` unit: mm,
    prior ``0 +- 1``; rad on a revolute drive, prior ``0 +- 0.01``) and
    ``redundant.<parameter>`` (the redundant chain's geometric errors, mm or
    rad, priors their tolerances).  Usual size: 0.05 mm of tolerance errors
    leave incompatibilities of 0.1-0.5 mm, which drives of 150-500 N/um turn
    into internal forces of tens of kN and deflections of tens to hundreds
    of um.  Needs one redundant drive and the closed-form inverse
    kinematics of every drive (:attr:`Machine.redundancy`: the RASPM); not applicable to machines with as many actuators as
    degrees of freedom (the 3-PRS, serial arms and positioners).  Units follow
    the drives (:attr:`Machine.actuator_unit_info`): the formula holds in
    each drive's own ``q`` unit (``nu`` and ``c_k`` scale together), and on a
    module of revolute drives (compliances urad/(N m)) the ratios are still
    dimensionless; a module mixing sliders and revolute drives is not
    applicable, since a ratio of um/N to urad/(N m) has a dimension
    (1/m^2) and the "drives of one size" prior ``1 +- 2`` means nothing.
    """

    name = "redundancy_preload"
    summary = "position-controlled redundant drives preloaded against each other through the closed loops (redundant machines only)"
    magnitude_unit = "um"  # the redundant drive's commanded offset (urad on a revolute drive)
    default_magnitude = 100.0
    needs_poses = True
    geometry_dependent = True

    def not_applicable(self, machine: Machine, aux: dict) -> str | None:
        m, n = machine.n_actuators, machine_dof(machine.inside)
        if m <= n:
            return (
                f"not applicable: the {machine.kind} has {m} actuators for "
                f"{n} degrees of freedom (no redundant actuation, no internal preload)"
            )
        if m - n != 1 or machine.redundancy is None:
            return (
                f"not applicable: the restrained-preload model needs exactly one redundant drive and the closed-form inverse "
                f"kinematics of every drive (the {machine.kind} has {m} actuators for {n} degrees of freedom)"
            )
        units = sorted(set(machine.actuator_units))
        if len(units) > 1:
            return (
                f"not applicable: the {machine.kind}'s drives have different units ({', '.join(units)}): a compliance ratio "
                f"between a slider (um/N) and a revolute drive (urad/(N m)) is not dimensionless, and the restrained-preload "
                f"model's prior (drives of one size, ratio 1 +- 2) does not hold"
            )
        return None

    def features(self, machine: Machine, q: NDArray, theta: NDArray, aux: dict, order, poses: ToolPoses | None) -> Features:
        inner, k = _inner(machine)
        n = q.shape[0]
        th = np.broadcast_to(np.asarray(theta if theta is not None else np.zeros(machine.n_params), float), (n, machine.n_params))
        th_in = th[:, k:]
        if poses is None:
            poses = machine.forward(q, th)
        x = poses.state.x
        s, r = list(inner.nonredundant), inner.redundant[0]
        q_ik, Ja = inner.ik_jacobian(x, th_in)
        G = inner.ik_parameter_jacobian(x, th_in)
        from ..redundant.physics import internal_force_basis

        nu = orient_directions(internal_force_basis(Ja)[:, :, 0])
        cols = redundant_columns(inner)
        # L = dg_r/dtheta at fixed q: G_r - J_r J_s^-1 G_s (the geometry moves x0, which moves IK_r)
        c = np.linalg.solve(np.swapaxes(Ja[:, s], 1, 2), Ja[:, r][..., None])[..., 0]  # J_s^-T J_r
        L = G[:, r] - np.einsum("ni,nip->np", c, G[:, s])
        L[:, cols] = 0.0  # the redundant drive's own parameters are the effect's (dtheta_r)
        return Features(
            {"nu": nu, "g": q_ik[:, r] - q[:, r], "G_r": G[:, r][:, cols], "L": L, "theta_f": th.copy()},
            {"n_frame": k, "nonredundant": tuple(s), "redundant": r, "columns": tuple(int(j) for j in cols)},
        )

    def params(self, machine: Machine, features: Features) -> tuple[EffectParam, ...]:
        inner, _ = _inner(machine)
        s, r = features.const["nonredundant"], features.const["redundant"]
        out = [EffectParam(f"compliance_ratio.q{i + 1}", "1", RATIO_PRIOR, RATIO_PRIOR_MEAN, lower=0.0) for i in s]
        offset = int(inner.offset_index()[r])
        unit = machine.actuator_unit_info[r]
        for j in features.const["columns"]:
            spec = inner.layout.specs[j]
            if j == offset:
                # in the drive's q unit, as G_r = dIK_r / d offset (q per q) reads it
                out.append(EffectParam(f"offset.q{r + 1}", unit.unit, offset_prior(unit)))
            else:
                out.append(EffectParam("redundant." + spec.name.replace(".", "_"), spec.unit, float(inner.tolerance[j])))
        return tuple(out)

    # ------------------------------------------------------------------ the model
    def _parts(self, features: Features, eta: NDArray, theta: NDArray | None):
        """Ratios ``w`` (m,), ``nu``, ``D = sum w nu^2`` (n,), ``rho = w nu nu_r / D`` (n, m) and ``g_r`` (n,)."""
        f = features.per_pose
        s, r = list(features.const["nonredundant"]), features.const["redundant"]
        eta = np.asarray(eta, float)
        nu = f["nu"]
        w = np.ones(nu.shape[1])
        w[s] = eta[: len(s)]
        D = np.maximum(np.einsum("m,nm->n", w, nu**2), 1e-300)
        rho = w[None] * nu * nu[:, r : r + 1] / D[:, None]
        # the redundant drive's own deflection (nu_r^2 g_r / D) is left out: the non-redundant model never
        # reads q_r, and so w = 0 (no force) means no change at all
        rho[:, r] = 0.0
        g = f["g"] + f["G_r"] @ eta[len(s):]
        if theta is not None:
            k = features.const["n_frame"]
            dth = np.broadcast_to(np.asarray(theta, float), f["theta_f"].shape)[:, k:] - f["theta_f"][:, k:]
            g = g + np.einsum("np,np->n", f["L"], dth)
        return w, nu, D, rho, g

    def delta_q(self, features: Features, eta: NDArray) -> NDArray:
        """Deflections at the geometry the features were computed at (mm, or rad on a revolute drive)."""
        _, _, _, rho, g = self._parts(features, eta, None)
        return rho * g[:, None]

    def delta_q_at(self, features: Features, eta: NDArray, theta: NDArray) -> NDArray:
        _, _, _, rho, g = self._parts(features, eta, theta)
        return rho * g[:, None]

    def delta_q_jacobian(self, features: Features, eta: NDArray) -> NDArray:
        return self._jacobian(features, eta, None)

    def delta_q_jacobian_at(self, features: Features, eta: NDArray, theta: NDArray) -> NDArray:
        return self._jacobian(features, eta, theta)

    def _jacobian(self, features: Features, eta: NDArray, theta) -> NDArray:
        s, r = list(features.const["nonredundant"]), features.const["redundant"]
        w, nu, D, rho, g = self._parts(features, eta, theta)
        n, m = nu.shape
        J = np.zeros((n, m, len(eta)))
        # d/dw_j of w_k nu_k nu_r g / D = nu_k nu_r g (delta_kj D - w_k nu_j^2) / D^2
        for a, j in enumerate(s):
            col = -(w[None] * nu) * nu[:, j : j + 1] ** 2
            col[:, j] += nu[:, j] * D
            col[:, r] = 0.0
            J[:, :, a] = col * (nu[:, r] * g / D**2)[:, None]
        J[:, :, len(s):] = rho[:, :, None] * features.per_pose["G_r"][:, None, :]
        return J

    def delta_q_theta_jacobian(self, features: Features, eta: NDArray, theta: NDArray) -> NDArray:
        _, _, _, rho, _ = self._parts(features, eta, theta)
        L = features.per_pose["L"]
        k = features.const["n_frame"]
        out = np.zeros(rho.shape + (k + L.shape[1],))
        out[:, :, k:] = rho[:, :, None] * L[:, None, :]
        return out

    def simulated_values(self, machine: Machine, features: Features, magnitude: float, rng) -> NDArray:
        """Drive stiffnesses 150-500 N/um (ratios ``k_r / k_s``), the redundant drive ``magnitude`` um (urad) off (either sign).

        The redundant chain's own geometric errors are left at zero here: a
        simulated machine carries them in its drawn geometry, which the
        features read.
        """
        params = self.params(machine, features)
        s, r = features.const["nonredundant"], features.const["redundant"]
        k = rng.uniform(150.0, 500.0, machine.n_actuators)
        out = np.zeros(len(params))
        out[: len(s)] = k[r] / k[list(s)]
        names = [p.name for p in params]
        if f"offset.q{r + 1}" in names:
            out[names.index(f"offset.q{r + 1}")] = rng.choice([-1.0, 1.0]) * magnitude * machine.actuator_unit_info[r].small_to_q
        return out
