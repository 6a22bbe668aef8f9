"""An independent statics simulator for tests: a serial chain whose joints yield under the weight of its links.

Written from docs/formats.md section 5 alone, without bayescal's kinematics or
effect code: the machine file is parsed with ``tomllib`` and each joint's
transform ``T_i = Trans(origin) Rot(rpy) M(q_i)`` composed here with 4x4
matrices (``Rot(r, p, y) = Rz(y) Ry(p) Rx(r)``; ``M`` a Rodrigues rotation
about the axis, or a translation along it).

Statics from the potential energy: with ``d`` the unit gravity direction in
the base frame, a mass ``m`` at ``x`` has potential ``V = -m g d . x``, and
the generalised gravity force on joint ``i`` is ``tau_i = -dV/dq_i``, taken
here by central finite differences of the composed transforms (N mm per rad
for ``x`` in mm).  A joint of compliance ``c_i`` (urad/(N m)) turns by
``1e-9 c_i tau_i`` rad; the deflected pose is found by iterating (the
torques at the deflected pose, not linearised).
"""

from __future__ import annotations

import tomllib
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

G = 9.80665  # m/s^2


def _rot_rpy(rpy) -> NDArray:
    r, p, y = rpy
    Rx = np.array([[1, 0, 0], [0, np.cos(r), -np.sin(r)], [0, np.sin(r), np.cos(r)]])
    Ry = np.array([[np.cos(p), 0, np.sin(p)], [0, 1, 0], [-np.sin(p), 0, np.cos(p)]])
    Rz = np.array([[np.cos(y), -np.sin(y), 0], [np.sin(y), np.cos(y), 0], [0, 0, 1]])
    return Rz @ Ry @ Rx


def _rot_axis(a, angle: float) -> NDArray:
    a = np.asarray(a, float) / np.linalg.norm(a)
    K = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + np.sin(angle) * K + (1 - np.cos(angle)) * K @ K


def _frame(R=np.eye(3), p=np.zeros(3)) -> NDArray:
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, p
    return T


@dataclass(frozen=True)
class Chain:
    """A serial chain read from machine-file text (``[[joint]]`` tables and ``[tool]``)."""

    joints: tuple  # (type, origin, rpy, axis) per joint
    tool_point: NDArray
    tool_rpy: NDArray

    @classmethod
    def from_text(cls, text: str) -> "Chain":
        doc = tomllib.loads(text)
        joints = tuple((j["type"], np.array(j.get("origin", [0, 0, 0]), float), np.array(j.get("rpy", [0, 0, 0]), float),
                        np.array(j["axis"], float)) for j in doc["joint"])
        tool = doc["tool"]
        return cls(joints, np.array(tool["point"], float), np.array(tool.get("rpy", [0, 0, 0]), float))

    def link_frames(self, q: NDArray) -> list[NDArray]:
        """4x4 frame after each joint's motion (link k's frame), base frame, mm, at one joint vector ``q``."""
        T = np.eye(4)
        out = []
        for (kind, origin, rpy, axis), qi in zip(self.joints, q):
            T = T @ _frame(_rot_rpy(rpy), origin)
            if kind == "revolute":
                T = T @ _frame(_rot_axis(axis, qi))
            else:
                T = T @ _frame(p=np.asarray(axis, float) / np.linalg.norm(axis) * qi)
            out.append(T)
        return out

    def tool_frame(self, q: NDArray) -> NDArray:
        return self.link_frames(q)[-1] @ _frame(_rot_rpy(self.tool_rpy), self.tool_point)


@dataclass(frozen=True)
class Weights:
    """What gravity pulls on: link masses (kg) at centres of mass (mm, link frames), a payload at the tool."""

    link_mass_kg: NDArray
    link_com_mm: NDArray  # (m, 3)
    down: NDArray  # (3,) unit, base frame
    payload_offset_mm: NDArray = field(default_factory=lambda: np.zeros(3))  # tool frame, from the tool point


def potential(chain: Chain, q: NDArray, w: Weights, payload_kg: float) -> float:
    """Gravitational potential energy, N mm (up to a constant): ``-g d . sum m x``."""
    V = 0.0
    for T, m, c in zip(chain.link_frames(q), w.link_mass_kg, w.link_com_mm):
        V -= m * G * w.down @ (T[:3, :3] @ c + T[:3, 3])
    Tt = chain.tool_frame(q)
    V -= payload_kg * G * w.down @ (Tt[:3, :3] @ w.payload_offset_mm + Tt[:3, 3])
    return V


def gravity_torques(chain: Chain, q: NDArray, w: Weights, payload_kg: NDArray, h: float = 1e-5) -> NDArray:
    """``tau_i = -dV/dq_i`` (N mm per rad, or N per mm on a slider) by central differences, shape (n, m)."""
    q = np.atleast_2d(q)
    payload_kg = np.broadcast_to(np.asarray(payload_kg, float), (q.shape[0],))
    tau = np.zeros(q.shape)
    for n, (qq, mL) in enumerate(zip(q, payload_kg)):
        for i in range(q.shape[1]):
            e = np.zeros(q.shape[1])
            e[i] = h
            tau[n, i] = -(potential(chain, qq + e, w, mL) - potential(chain, qq - e, w, mL)) / (2 * h)
    return tau


@dataclass(frozen=True)
class CompliantJoints:
    """A :class:`bayescal.simulate.PoseTransform`: each joint turns by ``c_i tau_i`` under gravity (iterated statics).

    The chain is the true machine's file text (``Machine.to_toml(theta_true)``);
    the transform ignores the ``theta`` it is handed (the true geometry is in ``chain``).
    """

    chain: Chain
    compliance_urad_per_nm: NDArray
    weights: Weights

    def transform(self, q, theta, aux, order):
        payload = np.asarray(aux.get("payload_kg", np.zeros(q.shape[0])), float)
        qd = np.array(q, float)
        for _ in range(4):  # fixed point: the load at the deflected pose
            qd = q + 1e-9 * self.compliance_urad_per_nm[None, :] * gravity_torques(self.chain, qd, self.weights, payload)
        return qd, theta
