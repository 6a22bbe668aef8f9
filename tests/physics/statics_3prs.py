"""An independent physics simulator for tests: a 3-PRS whose drives yield under gravity, by full statics.

Written from first principles, without bayescal's effect code (no
``delta_q``, no ``actuator_loads``, no actuator Jacobian): only the
machine's forward kinematics and its geometry arrays are used, as a black
box for "where is the platform when the sliders are here".

Mechanics.  Chain ``i``: a slider on rail ``u_i`` (drive along the rail),
a revolute joint about ``r_i`` at the slider centre ``C_i``, a massless link
to a spherical joint at ``A_i = p + R a_i`` on the platform.  The link is a
free body loaded at ``A_i`` by a force only (spherical joint) and at
``C_i`` by a force and a moment normal to ``r_i`` (revolute joint), so the
moment of the force about ``C_i`` has no component along ``r_i``:
``r_i . (L_i x F_i) = 0`` with ``L_i = A_i - C_i``.  As ``L_i . r_i = 0``
(the chain's constraint), the force the link puts on the platform lies in
``span(L_i / |L_i|, r_i)``: two unknowns per chain, six in all, fixed by the
platform's six equations of equilibrium under

* its weight ``m_p g d`` at the centre of mass ``p + R c`` (platform frame),
* the payload's weight ``m_L g d`` at the tool point ``p + R t`` (plus an
  optional offset),

with ``d`` the unit gravity direction in the base frame (a tilted mounting).
The drive carries the component of the link force along its rail: the
link pulls the slider with ``-F_i``, so the drive spring (compliance
``c_i``) lets the slider go to ``q_i = q_cmd_i + c_i (-F_i . u_i)``.  The
deflected pose is found by iterating statics and forward kinematics until
the slider positions stop changing (the load is taken at the deflected
pose, not linearised).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

G = 9.80665  # m/s^2


@dataclass(frozen=True)
class GravityLoad:
    """What gravity pulls on, in SI-ish units (kg, mm, unit vector)."""

    platform_mass_kg: float
    com_platform_mm: NDArray  # (3,) platform frame, from the platform origin
    down: NDArray  # (3,) unit, base frame
    payload_offset_mm: NDArray = field(default_factory=lambda: np.zeros(3))  # from the tool point, platform frame


def link_forces(geom: dict, p: NDArray, R: NDArray, q: NDArray, load: GravityLoad, payload_kg: float) -> NDArray:
    """Forces (N) the three links put on the platform at one pose, shape (3, 3) (chain, xyz).

    Parameters
    ----------
    geom : dict
        ``Prs3.geometry_arrays(theta)`` of the true machine.
    p, R : ndarray
        Platform origin (mm) and rotation at this pose.
    q : ndarray, shape (3,)
        Actual slider positions (mm).
    """
    A = p + geom["sphere_center"] @ R.T
    C = geom["rail_origin"] + q[:, None] * geom["rail_direction"]
    L = A - C
    Lh = L / np.linalg.norm(L, axis=1, keepdims=True)
    r = geom["revolute_axis"]
    # unknowns (alpha_i, beta_i): F_i = alpha_i Lh_i + beta_i r_i
    M = np.zeros((6, 6))
    for i in range(3):
        for k, e in enumerate((Lh[i], r[i])):
            M[:3, 2 * i + k] = e
            M[3:, 2 * i + k] = np.cross(A[i] - p, e)
    d = np.asarray(load.down, float) / np.linalg.norm(load.down)
    W_p = load.platform_mass_kg * G * d
    W_l = payload_kg * G * d
    x_c = R @ np.asarray(load.com_platform_mm, float)  # from p
    x_l = R @ (geom["tool_point"] + np.asarray(load.payload_offset_mm, float))
    rhs = -np.concatenate([W_p + W_l, np.cross(x_c, W_p) + np.cross(x_l, W_l)])
    ab = np.linalg.solve(M, rhs)
    return ab[0::2, None] * Lh + ab[1::2, None] * r


def deflected_q(machine, theta: NDArray, q_cmd: NDArray, compliance_um_per_N: NDArray, load: GravityLoad,
                payload_kg: NDArray, *, tol: float = 1e-11, max_iter: int = 50) -> NDArray:
    """Slider positions (mm) at static equilibrium, per pose, shape (n, 3).

    Fixed-point iteration ``q = q_cmd + c * axial_load(FK(q))``; the
    deflections are microns on a stiffness that barely changes with them, so
    it contracts fast (checked: raises if not converged).
    """
    geom = machine.geometry_arrays(theta)
    c = 1e-3 * np.asarray(compliance_um_per_N, float)  # mm/N
    u = geom["rail_direction"]
    q = np.array(q_cmd, float, copy=True)
    payload_kg = np.broadcast_to(np.asarray(payload_kg, float), (q.shape[0],))
    for _ in range(max_iter):
        poses = machine.forward(q, theta)
        if not poses.success.all():
            raise RuntimeError("a deflected pose cannot be solved")
        new = np.empty_like(q)
        for j in range(q.shape[0]):
            F = link_forces(geom, poses.state.p[j], poses.state.R[j], q[j], load, payload_kg[j])
            axial = -np.einsum("ik,ik->i", F, u)  # pull of the link on each slider along its rail, N
            new[j] = q_cmd[j] + c * axial
        step = np.max(np.abs(new - q))
        q = new
        if step < tol:
            return q
    raise RuntimeError(f"statics did not converge (last step {step:.2e} mm)")


class CompliantDrives:
    """A :class:`bayescal.simulate.PoseTransform` of the statics: commanded ``q`` -> deflected ``q``."""

    def __init__(self, machine, compliance_um_per_N, load: GravityLoad, payload_kg):
        self.machine, self.c, self.load, self.payload = machine, np.asarray(compliance_um_per_N, float), load, payload_kg

    def transform(self, q, theta, aux, order):
        th = np.asarray(theta)[0]
        return deflected_q(self.machine, th, q, self.c, self.load, self.payload), theta


def random_prs3_text(rng: np.random.Generator, *, sigma_position: float = 0.004, incline_deg: float = 0.0) -> str:
    """A 3-PRS with random radii, link length, chain angles, tool offset and stroke.

    ``incline_deg`` tilts every rail towards the machine's axis by that angle
    (a pyramid converging upwards; 0: vertical rails), with the rail origin
    moved out so that the slider sits at the drawn radius at mid-stroke.
    """
    rb, ra = rng.uniform(220, 400), rng.uniform(90, 200)
    link = rng.uniform(max(320.0, (rb - ra) * 1.3), 550.0)
    ang = np.deg2rad(np.array([0.0, 120.0, 240.0]) + rng.uniform(-8, 8, 3) + rng.uniform(0, 360))
    tool = [rng.uniform(-30, 30), rng.uniform(-30, 30), -rng.uniform(60, 220)]
    lo = rng.uniform(300, 500)
    stroke = rng.uniform(0.4, 0.7) * ra
    inc = np.deg2rad(incline_deg)
    mid = lo + stroke / 2
    lines = ['kind = "3-PRS"', 'name = "random 3-PRS"', ""]
    for a in ang:
        c, s = np.cos(a), np.sin(a)
        r0 = rb + mid * np.sin(inc)
        u = [-np.sin(inc) * c, -np.sin(inc) * s, np.cos(inc)]
        lines += ["[[chain]]", f"rail_origin = [{float(r0 * c)!r}, {float(r0 * s)!r}, 0.0]",
                  f"rail_direction = [{float(u[0])!r}, {float(u[1])!r}, {float(u[2])!r}]",
                  f"revolute_axis = [{float(-s)!r}, {float(c)!r}, 0.0]", f"link_length = {float(link)!r}",
                  f"sphere_center = [{float(ra * c)!r}, {float(ra * s)!r}, 0.0]", ""]
    lines += ["[tool]", f"point = [{float(tool[0])!r}, {float(tool[1])!r}, {float(tool[2])!r}]", ""]
    lines += ["[measurement]", f"sigma_position = {sigma_position!r}", "sigma_angle = 2.0e-5", ""]
    lines += ["[workspace]", "q_limits = [" + ", ".join([f"[{float(lo)!r}, {float(lo + stroke)!r}]"] * 3) + "]", ""]
    return "\n".join(lines)


def tilted_down(rng: np.random.Generator, max_tilt_deg: float) -> NDArray:
    """Gravity in the base frame of a machine mounted tilted by up to ``max_tilt_deg`` in a random direction."""
    tilt = np.deg2rad(rng.uniform(0.3, 1.0) * max_tilt_deg)
    az = rng.uniform(0, 2 * np.pi)
    return np.array([np.sin(tilt) * np.cos(az), np.sin(tilt) * np.sin(az), -np.cos(tilt)])
