"""An independent multi-body statics simulator for tests: a serial chain of rigid bodies and elastic beams under gravity.

Written from docs/formats.md sections 5 and 8 (joint transforms, mimic joints) and
textbook beam statics, without bayescal's kinematics or effect code: the
machine file is parsed with ``tomllib``, each joint's transform
``T_i = Trans(origin) Rot(rpy) M(q_i)`` composed here with 4x4 matrices,
and a mimic joint moves by ``multiplier * q_driver + offset``.

Structure.  Members (given by the test) are straight elastic beams of
bending stiffness ``E I`` (N mm^2): the moving stage of a prismatic joint
(clamped at the joint frame's origin before the motion, free length the
joint position) or a link (from its frame's origin to the next joint's
origin, or to the tool point).  Each member is cut into many short
elements.  Everything else is rigid.

Statics, element by element from the base outward: at each element's middle
the bending moment is that of every gravity load beyond it (the bodies of
later links, the payload at the tool point, and the member's own body when
its centre of mass lies beyond the element along the member), in the
*current* (already deflected) configuration, ``M = sum (x - r) x F``; its
part normal to the element's axis turns the element by ``M_perp ds / (E I)``
(exact rotation matrix), and everything beyond (later elements, bodies, the
tool frame) is turned with it about the element's middle.  Small rotations
are thus compounded element by element; loads keep their direction.  No
closed-form beam formula is used.
"""

from __future__ import annotations

import tomllib
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

G = 9.80665  # m/s^2


def rot_rpy(rpy) -> NDArray:
    r, p, y = rpy
    Rx = np.array([[1, 0, 0], [0, np.cos(r), -np.sin(r)], [0, np.sin(r), np.cos(r)]])
    Ry = np.array([[np.cos(p), 0, np.sin(p)], [0, 1, 0], [-np.sin(p), 0, np.cos(p)]])
    Rz = np.array([[np.cos(y), -np.sin(y), 0], [np.sin(y), np.cos(y), 0], [0, 0, 1]])
    return Rz @ Ry @ Rx


def rodrigues(w) -> NDArray:
    """Rotation matrix of the rotation vector ``w`` (rad)."""
    w = np.asarray(w, float)
    t = np.linalg.norm(w)
    if t < 1e-300:
        return np.eye(3)
    a = w / t
    K = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + np.sin(t) * K + (1 - np.cos(t)) * K @ K


def cross(a, b) -> NDArray:
    """``a x b`` of two 3-vectors (numpy's general cross product is slow for single vectors)."""
    return np.array([a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]])


def rotvec(R) -> NDArray:
    """Rotation vector of a rotation matrix (angles below pi)."""
    c = np.clip((np.trace(R) - 1) / 2, -1.0, 1.0)
    t = np.arccos(c)
    v = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    return 0.5 * v if t < 1e-8 else t / (2 * np.sin(t)) * v


@dataclass(frozen=True)
class MimicChain:
    """A serial chain read from machine-file text, mimic joints included."""

    joints: tuple  # (type, origin, rpy, axis, mimic or None) per joint; mimic = (driver 0-based, multiplier, offset)
    tool_point: NDArray
    tool_rpy: NDArray

    @classmethod
    def from_text(cls, text: str) -> "MimicChain":
        doc = tomllib.loads(text)
        joints = []
        for j in doc["joint"]:
            mimic = (j["mimic"] - 1, j.get("multiplier", 1.0), j.get("offset", 0.0)) if "mimic" in j else None
            joints.append((j["type"], np.array(j.get("origin", [0, 0, 0]), float), np.array(j.get("rpy", [0, 0, 0]), float),
                           np.array(j["axis"], float) / np.linalg.norm(j["axis"]), mimic))
        tool = doc["tool"]
        return cls(tuple(joints), np.array(tool["point"], float), np.array(tool.get("rpy", [0, 0, 0]), float))

    @property
    def actuated(self) -> list[int]:
        return [k for k, j in enumerate(self.joints) if j[4] is None]

    def joint_values(self, q: NDArray) -> NDArray:
        """Every joint's position from the actuators' ``q`` (one pose)."""
        act = self.actuated
        out = np.zeros(len(self.joints))
        out[act] = q
        for k, j in enumerate(self.joints):
            if j[4] is not None:
                d, mult, off = j[4]
                out[k] = mult * out[d] + off
        return out

    def frames(self, q: NDArray):
        """Per joint: (frame before the motion, frame after it) as 4x4 matrices, and the tool frame, at actuators ``q``."""
        T = np.eye(4)
        before, after = [], []
        for (kind, origin, rpy, axis, _), v in zip(self.joints, self.joint_values(q)):
            F = np.eye(4)
            F[:3, :3], F[:3, 3] = rot_rpy(rpy), origin
            T = T @ F
            before.append(T.copy())
            M = np.eye(4)
            if kind == "revolute":
                M[:3, :3] = rodrigues(axis * v)
            else:
                M[:3, 3] = axis * v
            T = T @ M
            after.append(T.copy())
        Tt = np.eye(4)
        Tt[:3, :3], Tt[:3, 3] = rot_rpy(self.tool_rpy), self.tool_point
        return before, after, T @ Tt


@dataclass(frozen=True)
class Member:
    """An elastic member: ``("stage", k, free_length_at_zero)`` or ``("link", k, 0)``, of stiffness ``EI`` (N mm^2)."""

    kind: str
    joint: int  # 0-based
    EI: float
    free_at_zero: float = 0.0


def deflected_tool(chain: MimicChain, q: NDArray, members: list[Member], mass_kg: NDArray, com_mm: NDArray,
                   down: NDArray, payload_kg: float = 0.0, n_elements: int = 400, bodies=()):
    """Tool point and orientation of the rigid chain and of the deflected one, at one actuator vector ``q``.

    ``bodies``: joints (0-based) whose frames after the motion are also followed (a tilt sensor fixed there):
    a frame turns with every element it lies beyond (its origin further along the member, or on a later link).

    Returns
    -------
    p0, R0 : the rigid tool point (mm) and tool frame
    p1, R1 : deflected
    turns : ndarray (len(bodies), 3), only when ``bodies`` are given: each followed frame's rotation vector
        from rigid to deflected, base frame
    """
    before, after, Tt = chain.frames(q)
    m = len(chain.joints)
    values = chain.joint_values(q)
    # the points the structure carries, base frame: each link's centre of mass, the tool frame, and the
    # members' geometry (root and tip), all deformed together as the elements turn
    com = np.array([after[k][:3, :3] @ com_mm[k] + after[k][:3, 3] for k in range(m)])
    tool = Tt[:3, 3].copy()
    tool_R = Tt[:3, :3].copy()
    nxt = [before[k + 1][:3, 3] for k in range(m - 1)] + [tool]
    geo = []  # (root, tip, owner link) per member
    for mb in members:
        k = mb.joint
        if mb.kind == "stage":
            a = before[k][:3, :3] @ chain.joints[k][3]
            L = max(values[k] + mb.free_at_zero, 0.0)
            tip = after[k][:3, 3]
            geo.append([tip - a * L, tip.copy()])
        else:
            geo.append([after[k][:3, 3].copy(), np.array(nxt[k], float)])
    p0, R0 = tool.copy(), tool_R.copy()
    body_R = {b: after[b][:3, :3].copy() for b in bodies}
    body_o = {b: after[b][:3, 3].copy() for b in bodies}
    F = G * np.asarray(down, float)
    # members from the base outward: a member nearer the base is turned before those it carries
    order = sorted(range(len(members)), key=lambda i: (members[i].joint, members[i].kind != "stage"))
    for i in order:
        mb = members[i]
        root, tip = geo[i]
        L = np.linalg.norm(tip - root)
        if L == 0:
            continue
        ds = L / n_elements
        a0 = (tip - root) / L
        # which loads act beyond the member's elements: bodies of later links whole; the own link's body from its
        # projection on the member onward (fixed once, on the undeflected member)
        s_own = np.clip((com[mb.joint] - root) @ a0, 0.0, L)
        s_frame = {b: (body_o[b] - root) @ a0 for b in bodies}  # where a followed frame of this member's own link sits
        for e in range(n_elements):
            root, tip = geo[i]
            a = (tip - root) / np.linalg.norm(tip - root)
            s_mid = (e + 0.5) * ds
            r = root + a * s_mid
            M = np.zeros(3)
            for b in range(mb.joint, m):
                if b == mb.joint and s_own <= s_mid:
                    continue
                M += cross(com[b] - r, mass_kg[b] * F)
            M += cross(tool - r, payload_kg * F)
            Mp = M - (M @ a) * a
            Rd = rodrigues(Mp * ds / mb.EI)
            # everything beyond this element turns about its middle
            for b in range(m):
                if b > mb.joint or (b == mb.joint and s_own > s_mid):
                    com[b] = r + Rd @ (com[b] - r)
            tool = r + Rd @ (tool - r)
            tool_R = Rd @ tool_R
            for b in bodies:
                if b > mb.joint or (b == mb.joint and s_frame[b] > s_mid):
                    body_o[b] = r + Rd @ (body_o[b] - r)
                    body_R[b] = Rd @ body_R[b]
            geo[i][1] = r + Rd @ (geo[i][1] - r)
            for j in order[order.index(i) + 1 :]:
                geo[j] = [r + Rd @ (geo[j][0] - r), r + Rd @ (geo[j][1] - r)]
    if bodies:
        turns = np.array([rotvec(body_R[b] @ after[b][:3, :3].T) for b in bodies])
        return p0, R0, tool, tool_R, turns
    return p0, R0, tool, tool_R


def generalized_gravity(chain: MimicChain, q: NDArray, mass_kg: NDArray, com_mm: NDArray, down: NDArray,
                        payload_kg: float = 0.0, h: float = 1e-5) -> NDArray:
    """Gravity force on each actuator, ``-dV/dq_i`` by central differences of the potential (N, or N mm per rad)."""

    def V(qq):
        _, after, Tt = chain.frames(qq)
        x = [after[k][:3, :3] @ com_mm[k] + after[k][:3, 3] for k in range(len(chain.joints))]
        return -G * (sum(mk * np.asarray(down) @ xk for mk, xk in zip(mass_kg, x)) + payload_kg * np.asarray(down) @ Tt[:3, 3])

    out = np.zeros(len(q))
    for i in range(len(q)):
        e = np.zeros(len(q))
        e[i] = h
        out[i] = -(V(q + e) - V(q - e)) / (2 * h)
    return out
