"""Gravity deflection of structures: links and telescopic columns bend under the weight they carry."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from ..errors import InputError
from ..geometry import skew
from ..machines.base import Machine, ToolPoses
from .base import Effect, EffectParam, Features
from .conditions import second_payload, tilted_mounting
from .gravity_field import chain_masses, gravity_per_pose, sensor_bodies, serial_part, tilt_basis, tilted_gravity
from .joint_compliance import DEFAULT_GRAVITY_DIRECTION, GRAVITY, _unit

__all__ = ["GravityDeflection", "member_response", "FLEX_PER_BENDING"]

#: ``1 / (E I)`` in 1/(N mm^2) per um/N of ``bending.*``: a member of bending compliance ``b`` deflects by
#: ``b`` um per N of lateral end load at 1 m free length, ``F L^3 / (3 E I)`` with ``L = 1000 mm``.
FLEX_PER_BENDING = 3e-12


def member_response(root: NDArray, axis: NDArray, length: NDArray, x: NDArray, own: NDArray, tool: NDArray) -> NDArray:
    """Tool displacement and rotation per unit flexibility ``1 / (E I)`` and unit force, for a cantilever and point loads.

    The member is a straight Euler-Bernoulli cantilever clamped at ``root``,
    along ``axis``, of free length ``L``.  A force ``F`` (N) at ``x`` enters
    it at ``s_c`` from the root: at the tip (``s_c = L``) for a body beyond
    the member, at ``x``'s projection clipped to the member for the member's
    own body.  The bending moment at ``s <= s_c`` is ``M(s) = (x - r(s)) x F
    = M_c + (s_c - s) a x F``, ``M_c = (x - r(s_c)) x F``; only its part
    normal to the axis bends (torsion and shear are left out), so the
    curvature is ``M_perp / (E I)`` and, integrating from the root,

        phi   = (M_c,perp s_c + (a x F) s_c^2 / 2) / (E I)
        delta = ((M_c,perp x a) (L s_c - s_c^2 / 2) + F_perp s_c^2 (3 L - s_c) / 6) / (E I)

    (an end load: ``F L^3 / (3 E I)`` and ``F L^2 / (2 E I)``; an end moment:
    ``M L^2 / (2 E I)`` and ``M L / (E I)``).  The tool moves with the tip:
    ``dx = delta + phi x (tool - tip)``, and turns by ``phi``.

    Parameters
    ----------
    root, axis : ndarray, shape (n, 3)
        Clamped end (mm) and unit axis, base frame.
    length : ndarray, shape (n,)
        Free length ``L``, mm (>= 0).
    x : ndarray, shape (n, B, 3)
        Where each load acts, mm.
    own : ndarray of bool, shape (B,)
        Loads that act on the member itself (their ``s_c`` clipped), else beyond its tip.
    tool : ndarray, shape (n, 3)
        Tool point, mm.

    Returns
    -------
    ndarray, shape (n, B, 6, 3)
        Rows 0-2: tool displacement (mm), rows 3-5: rotation (rad), per unit
        ``1 / (E I)`` (1/(N mm^2)) and per N of each force component.
    """
    L = np.asarray(length, float)
    tip = root + axis * L[:, None]
    proj = np.clip(np.einsum("nbi,ni->nb", x - root[:, None], axis), 0.0, L[:, None])
    s = np.where(np.asarray(own, bool)[None, :], proj, L[:, None])  # (n, B)
    arm = x - (root[:, None] + axis[:, None] * s[:, :, None])
    A1 = skew(arm)  # (n, B, 3, 3): F -> M_c
    Sa = skew(axis)[:, None]  # (n, 1, 3, 3)
    P = (np.eye(3)[None] - axis[:, :, None] * axis[:, None, :])[:, None]
    s2 = s[:, :, None, None]
    L2 = L[:, None, None, None]
    phi = s2 * (P @ A1) + 0.5 * s2**2 * Sa
    delta = -(L2 * s2 - 0.5 * s2**2) * (Sa @ A1) + (s2**2 * (3 * L2 - s2) / 6.0) * P
    dx = delta - skew(tool - tip)[:, None] @ phi
    return np.concatenate([dx, phi], axis=2)


class GravityDeflection(Effect):
    """Links and telescopic columns of a serial chain bend under the gravity load of every body beyond them.

    Physics: each structural member is an Euler-Bernoulli cantilever
    (:func:`member_response`) loaded by the weights ``m_b g d`` of the
    bodies beyond it (their centres of mass) and of the payload
    (``payload_kg``, at the tool point), with ``d`` the gravity direction of
    the pose.  Members of a serial chain:

    * every **prismatic stage**: the moving member of a prismatic joint is
      a cantilever clamped where it leaves its guide, with free length
      ``L = q_k + L0_k`` (``q_k`` the joint's position, mimic joints
      included, ``L0_k`` the input ``free_length_mm``, 0 by default: "the
      free length is the stroke").  A telescopic column whose upper stages
      mimic the lower one is one member with one parameter (its stages in
      series);
    * every **long link**: the straight beam from a link's frame origin to
      the next joint's origin (to the tool point on the last link), when at
      least ``min_link_length_mm`` long (150 by default).

    The member's tip deflects by ``delta`` and turns by ``phi``, which
    carries the tool point further out: ``dx = delta + phi x (tool - tip)``.
    That is no change of any actuator position: the effect moves the tool
    (:attr:`moves_tool`), ``dq = 0``.  Members superpose to first order (a
    deflection is evaluated on the undeflected chain; the second-order
    change is below 1e-3 of it for deflections under 0.1 % of the
    structure's size).  Own weight: a member's own body counts as a point
    load at its centre of mass projected on the member (a uniformly
    distributed weight would bend the tip by ``w L^4 / (8 E I)``, 1.2 times
    the point load at mid-length).  Torsion and shear deflection are left
    out.

    Parameters (names, units): ``bending.joint<k>`` (prismatic stage of
    joint ``k``, its mimic stages with it) and ``bending.link<k>`` (the
    link after joint ``k``), um/N: the tip deflection per N of lateral end
    load at 1 m free length, ``1e12 / (3 E I)`` with ``E I`` in N mm^2
    (``>= 0``, prior ``0 +- 30``).  A steel tube of 150 mm diameter and 10
    mm wall is 0.15 um/N, an aluminium robot link of 60 mm diameter 15
    um/N.  The link masses come from ``link_mass_kg`` and ``link_com_mm``
    (as for ``joint_compliance``), else the machine file's (a URDF's
    ``<inertial>``); otherwise the masses of the links that load some member
    are parameters ``mass.link<k>`` (kg, ``>= 0``, prior ``0 +- 100``,
    started at 20 kg) at the links' middles, and without a ``payload_kg``
    channel only their products with the bending compliances are
    determined.  ``gravity.tilt_1``, ``gravity.tilt_2``: the mounting's tilt
    from the stated direction (as for ``joint_compliance``; prior ``0 +-
    0.5``, or ``0 +- 0.02`` when ``gravity`` is stated or a base sensor
    gives it).  A base tilt sensor (``accel.base.x/y/z``) gives every pose
    its own direction (:mod:`bayescal.effects.gravity_field`).

    Usual size: a telescopic column of a few metres carrying a boom bends
    by millimetres at full extension; robot links of 0.3-0.5 m by tens of
    um under their own weight and the payload.
    """

    name = "gravity_deflection"
    summary = "links and telescopic columns of a serial chain bend under the weight of every body beyond them (moves the tool)"
    magnitude_unit = "um/N"
    default_magnitude = 5.0
    moves_tool = True
    bends_bodies = True
    features_at_nominal = True
    settings_keys = ("gravity", "link_mass_kg", "link_com_mm", "free_length_mm", "min_link_length_mm")

    BENDING_PRIOR = 30.0
    MASS_PRIOR_KG = 100.0
    MASS_START_KG = 20.0
    TILT_PRIOR = 0.5

    def __init__(self, *, gravity=None, link_mass_kg=None, link_com_mm=None, free_length_mm=None, min_link_length_mm=150.0):
        """
        Parameters
        ----------
        gravity : (3,), optional
            Gravity direction in the base frame; default ``[0, 0, -1]`` (tilt prior 0.5; stated: 0.02).
        link_mass_kg : (m,), optional
            Mass of every link (one per moving joint, mimic joints included, base outward), kg.
        link_com_mm : (m, 3) or (3 m,), optional
            Their centres of mass in their links' frames, mm (default: the frames' origins).
        free_length_mm : (n_prismatic,), optional
            Free length of every prismatic stage at joint position 0, mm, in chain order (default 0).
        min_link_length_mm : float
            Links at least this long (mm) are members (default 150).
        """
        self.gravity_stated = gravity is not None
        self.down = _unit(DEFAULT_GRAVITY_DIRECTION if gravity is None else gravity, "gravity_deflection gravity")
        if link_mass_kg is None and link_com_mm is not None:
            raise InputError("gravity_deflection link_com_mm: given without link_mass_kg; state the links' masses too")
        self.link_mass = None if link_mass_kg is None else np.asarray(link_mass_kg, float).reshape(-1)
        self.link_com = None if link_com_mm is None else np.asarray(link_com_mm, float)
        self.free_length = None if free_length_mm is None else np.asarray(free_length_mm, float).reshape(-1)
        if self.free_length is not None and not np.all(np.isfinite(self.free_length)):
            raise InputError(f"gravity_deflection free_length_mm: expected finite lengths in mm, got {self.free_length.tolist()}")
        self.min_link = float(np.asarray(min_link_length_mm, float).reshape(-1)[0])
        if not (np.isfinite(self.min_link) and self.min_link > 0):
            raise InputError(f"gravity_deflection min_link_length_mm: expected a length > 0 in mm, got {min_link_length_mm!r}")

    # ------------------------------------------------------------------ set-up
    def members(self, chain) -> list[tuple[str, str, tuple[int, ...]]]:
        """``(parameter name, "stage" or "link", joints)`` of every member of the chain (0-based joints)."""
        types, mimic = chain.joint_type, chain.mimic
        out = []
        for k, t in enumerate(types):
            if t != "prismatic":
                continue
            d = mimic[k][0] if mimic[k] is not None else None
            if d is not None and types[d] == "prismatic":
                continue  # a stage of its driver's column
            group = (k,) + tuple(j for j in range(len(types)) if mimic[j] is not None and mimic[j][0] == k and types[j] == "prismatic")
            out.append((f"bending.joint{k + 1}", "stage", group))
        nxt = np.concatenate([chain.origin[1:], chain.tool_point[None]], axis=0)
        for k in range(len(types)):
            if np.linalg.norm(nxt[k]) >= self.min_link:
                out.append((f"bending.link{k + 1}", "link", (k,)))
        return out

    @staticmethod
    def _loading_bodies(chain, members, com: NDArray) -> list[int]:
        """Links whose unknown mass is a parameter: those beyond some member, and a member's own link when its centre of mass is off the member's line.

        Decided from the machine file alone (the parameter set of a stored
        table must not depend on the recording's poses).
        """
        nxt = np.concatenate([chain.origin[1:], chain.tool_point[None]], axis=0)
        out = set()
        for _, kind, joints in members:
            for k in joints:
                out.update(range(k + 1, len(chain.joint_type)))
                line = chain.axis[k] if kind == "stage" else nxt[k] / np.linalg.norm(nxt[k])
                if np.linalg.norm(com[k] - (com[k] @ line) * line) >= 1.0:  # mm off the member's line
                    out.add(k)
        return sorted(out)

    def not_applicable(self, machine: Machine, aux: dict) -> str | None:
        chain, _ = serial_part(machine, None)
        if chain is None:
            return f"modelled on serial chains only (a {machine.kind} machine has no chain of links and stages to bend)"
        if not self.members(chain):
            return (f"the chain has no prismatic stage and no link of at least {self.min_link:g} mm "
                    "(min_link_length_mm) to bend")
        return None

    def implied_settings(self, machine: Machine) -> dict:
        """The link masses the machine file gives (a URDF's), written out with the table."""
        chain, _ = serial_part(machine, None)
        if self.link_mass is not None or chain is None or chain.body_inertials is None:
            return {}
        known = chain.body_inertials
        return {"link_mass_kg": np.asarray(known.mass_kg, float).tolist(), "link_com_mm": np.asarray(known.com_mm, float).tolist()}

    def _free_length(self, chain) -> NDArray:
        prismatic = [k for k, t in enumerate(chain.joint_type) if t == "prismatic"]
        out = np.zeros(len(chain.joint_type))
        if self.free_length is not None:
            if self.free_length.size != len(prismatic):
                raise InputError(f"gravity_deflection free_length_mm: {self.free_length.size} value(s) for the chain's "
                                 f"{len(prismatic)} prismatic joint(s); expected one per prismatic joint, base outward (mm)")
            out[prismatic] = self.free_length
        return out

    def features(self, machine: Machine, q: NDArray, theta: NDArray, aux: dict, order, poses: ToolPoses | None) -> Features:
        chain, th = serial_part(machine, theta)
        if chain is None:
            raise InputError(self.not_applicable(machine, aux) or "gravity_deflection: not a serial chain")
        fr = chain.chain_frames(q, th)
        n, m = q.shape[0], len(chain.joint_type)
        mass, com, source = chain_masses(machine, chain, self.link_mass, self.link_com, "gravity_deflection")
        # loads: every link's centre of mass, then the payload at the tool point
        x = np.concatenate([fr.link_origin + np.einsum("nbij,bj->nbi", fr.link_rotation, com), fr.tool_point[:, None]], axis=1)
        members = self.members(chain)
        L0 = self._free_length(chain)
        # the bodies carrying tilt sensors (accel.<body>.* channels; not the base, which no member turns) and the
        # joint whose frame each is fixed to
        bodies = sensor_bodies(chain, aux)
        at = [chain.body_frame(b)[0] for b in bodies]
        # rows: the tool's displacement and rotation, then each sensor body's rotation
        resp = np.zeros((n, len(members), m + 1, 6 + 3 * len(bodies), 3))
        for j, (_, kind, joints) in enumerate(members):
            for k in joints:
                if kind == "stage":
                    a = fr.joint_axis[:, k]
                    length = np.maximum(fr.joint_position[:, k] + L0[k], 0.0)
                    root = fr.link_origin[:, k] - a * length[:, None]
                else:
                    v = fr.next_point[:, k] - fr.link_origin[:, k]
                    length = np.linalg.norm(v, axis=1)
                    a, root = v / length[:, None], fr.link_origin[:, k]
                # bodies from link k outward load the member (link k itself along it), and the payload
                own = np.zeros(m + 1 - k, bool)
                own[0] = True
                seg = member_response(root, a, length, x[:, k:], own, fr.tool_point)
                resp[:, j, k:, :6] += seg
                # a body turns with the member's tip when its frame is beyond the tip: the frames of later
                # joints, and a stage's own frame (the moving stage's frame sits at its tip; a link's frame at
                # its root, which the link's bending does not turn)
                for s_, kb in enumerate(at):
                    if kb > k or (kb == k and kind == "stage"):
                        resp[:, j, k:, 6 + 3 * s_: 9 + 3 * s_] += seg[:, :, 3:]
        payload = np.asarray(aux["payload_kg"], float) if "payload_kg" in aux else np.zeros(n)
        down, sensor = gravity_per_pose(aux, self.down, n)
        basis = tilt_basis(self.down)
        K0 = payload[:, None, None, None] * resp[:, :, m]  # (n, J, 6, 3) the payload's load
        const = {"members": tuple(name for name, _, _ in members), "sensor": sensor, "basis": basis, "source": source,
                 "tilt_sd": 0.02 if (self.gravity_stated or sensor) else self.TILT_PRIOR, "n_actuators": q.shape[1],
                 "sensor_bodies": bodies}
        unknown = np.ones(m, bool) if mass is None else np.isnan(mass)
        K = K0 + np.einsum("b,njbac->njac", np.zeros(m) if mass is None else np.nan_to_num(mass), resp[:, :, :m])
        if not unknown.any():
            return Features({"K": K, "down": down}, {**const, "known": True, "bodies": ()})
        # the unknown masses of the links that load some member are parameters
        fit = np.array([b for b in self._loading_bodies(chain, members, com) if unknown[b]], dtype=int)
        return Features({"K": K, "Rb": resp[:, :, fit], "down": down},
                        {**const, "known": False, "bodies": tuple(f"link{b + 1}" for b in fit)})

    def params(self, machine: Machine, features: Features) -> tuple[EffectParam, ...]:
        known = features.const["known"]
        out = [EffectParam(name, "um/N", self.BENDING_PRIOR, lower=0.0, start=None if known else self.default_magnitude)
               for name in features.const["members"]]
        out += [EffectParam(f"mass.{b}", "kg", self.MASS_PRIOR_KG, lower=0.0, start=self.MASS_START_KG) for b in features.const["bodies"]]
        out += [EffectParam(f"gravity.tilt_{k}", "rad", features.const["tilt_sd"]) for k in (1, 2)]
        return tuple(out)

    # ---------------------------------------------------------------- the model
    def _terms(self, features: Features, eta: NDArray):
        eta = np.asarray(eta, float)
        J = len(features.const["members"])
        F = len(features.const["bodies"])
        flex = FLEX_PER_BENDING * eta[:J]
        masses = eta[J : J + F]
        d, dd = tilted_gravity(features.per_pose["down"], features.const["basis"], eta[J + F : J + F + 2])
        K = features.per_pose["K"]
        if F:
            K = K + np.einsum("f,njfac->njac", masses, features.per_pose["Rb"])
        return J, F, flex, d, dd, K

    def delta_q(self, features: Features, eta: NDArray) -> NDArray:
        """No actuator moves: the members bend (:meth:`delta_x`)."""
        return np.zeros((features.per_pose["down"].shape[0], features.const["n_actuators"]))

    def delta_q_jacobian(self, features: Features, eta: NDArray) -> NDArray:
        n = features.per_pose["down"].shape[0]
        return np.zeros((n, features.const["n_actuators"], len(np.asarray(eta))))

    def _all_rows(self, features: Features, eta: NDArray) -> NDArray:
        """The tool's ``dx`` rows, then every sensor body's rotation, (n, 6 + 3 S)."""
        _, _, flex, d, _, K = self._terms(features, eta)
        return GRAVITY * np.einsum("j,njac,nc->na", flex, K, d)

    def _all_rows_jacobian(self, features: Features, eta: NDArray) -> NDArray:
        J, F, flex, d, dd, K = self._terms(features, eta)
        n = d.shape[0]
        out = np.zeros((n, K.shape[2], J + F + 2))
        out[:, :, :J] = GRAVITY * FLEX_PER_BENDING * np.einsum("njac,nc->naj", K, d)
        if F:
            out[:, :, J : J + F] = GRAVITY * np.einsum("j,njfac,nc->naf", flex, features.per_pose["Rb"], d)
        out[:, :, J + F :] = GRAVITY * np.einsum("j,njac,nct->nat", flex, K, dd)
        return out

    def delta_x(self, features: Features, eta: NDArray) -> NDArray:
        return self._all_rows(features, eta)[:, :6]

    def delta_x_jacobian(self, features: Features, eta: NDArray) -> NDArray:
        return self._all_rows_jacobian(features, eta)[:, :6]

    def body_rotation(self, features: Features, eta: NDArray) -> dict[str, NDArray]:
        """The members' tip rotations every sensor body beyond them turns by (the tool's rotation rows' physics)."""
        rows = self._all_rows(features, eta)
        return {b: rows[:, 6 + 3 * s: 9 + 3 * s] for s, b in enumerate(features.const.get("sensor_bodies", ()))}

    def body_rotation_jacobian(self, features: Features, eta: NDArray) -> dict[str, NDArray]:
        jac = self._all_rows_jacobian(features, eta)
        return {b: jac[:, 6 + 3 * s: 9 + 3 * s] for s, b in enumerate(features.const.get("sensor_bodies", ()))}

    def inadmissible(self, features: Features, eta: NDArray | None = None) -> str | None:
        J, F = len(features.const["members"]), len(features.const["bodies"])
        unit = np.concatenate([np.full(J, 1.0), np.full(F, self.MASS_START_KG), np.zeros(2)])
        dx = self.delta_x(features, unit)
        if not np.any(np.abs(dx[:, :3]) > 1e-9):
            return "the members carry no lateral load at any pose (every weight acts along them) and no payload_kg bends them"
        return None

    def model_note(self, features: Features) -> str:
        parts = [f"members {', '.join(features.const['members'])}"]
        parts.append(f"link masses {features.const['source']}" if features.const["known"] else
                     f"link masses of {', '.join(features.const['bodies']) or 'no loading link'} unknown: fitted at the links' "
                     "middles (state link_mass_kg and link_com_mm, or give a URDF with <inertial> elements)")
        if features.const["sensor"]:
            parts.append("gravity per pose from the base sensor (accel.base.*)")
        return "; ".join(parts)

    def separating_conditions(self, aux: dict) -> tuple:
        """A heavier payload (a known load), and the mounting tilted either way (gravity turned against the machine)."""
        return (second_payload(aux), tilted_mounting(self.down, 0), tilted_mounting(self.down, 1))

    def confound_note(self) -> str:
        return ("gravity_deflection: the part of the bending that is constant or linear over the workspace is a change of "
                "link geometry (joint origins and tilts); with the link masses unknown and no payload_kg only the products "
                "of bending compliances and masses are determined. Stating link_mass_kg (or a URDF with <inertial>) and "
                "recording a changing payload_kg separates them.")

    def simulated_values(self, machine: Machine, features: Features, magnitude: float, rng) -> NDArray:
        """Bending compliances ``magnitude`` um/N (+-40 %), unknown link masses 10-30 kg, no tilt."""
        J, F = len(features.const["members"]), len(features.const["bodies"])
        return np.concatenate([magnitude * rng.uniform(0.6, 1.4, J), self.MASS_START_KG * rng.uniform(0.5, 1.5, F), np.zeros(2)])
