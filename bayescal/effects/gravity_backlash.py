"""Gravity-side backlash: a joint's dead band taken up on the side its gravity load pushes."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from ..errors import InputError
from ..machines.base import Machine, ToolPoses
from .base import Effect, EffectParam, Features, measurement_sequence
from .gravity_field import chain_masses, gravity_loads, gravity_per_pose, serial_part
from .joint_compliance import DEFAULT_GRAVITY_DIRECTION, _unit

__all__ = ["GravityBacklash", "gravity_play"]


def gravity_play(x: NDArray, side: NDArray, half_band: NDArray) -> tuple[NDArray, NDArray]:
    """Follower positions of drives with play under gravity, and their derivative by the half band.

    In time order, per drive: the driver moves straight from ``x_{t-1}`` to
    ``x_t`` and drags the follower through the play, ``y = clip(y_prev, x_t -
    h, x_t + h)`` (the play operator, :func:`bayescal.effects.backlash.play_operator`);
    then, where the gravity load exceeds what friction holds (``side_t =
    +-1``, the sign of the load), the follower settles against the flank on
    that side, ``y = x_t + side_t h``.  Where it does not (``side_t = 0``)
    it stays where the move left it.  The first pose's history is unknown:
    the centre of the band unless gravity sets it.

    Parameters
    ----------
    x : ndarray, shape (n, m)
        Driver positions in time order.
    side : ndarray, shape (n, m)
        -1, 0 or +1 per pose and drive.
    half_band : ndarray, shape (m,)
        ``h >= 0`` physically; a negative ``h`` gives the odd extension
        (as :func:`bayescal.effects.backlash.play_operator`: value and
        derivative agree on both sides of zero).

    Returns
    -------
    y_minus_x, d_dh : ndarray, shape (n, m)
    """
    signed = np.asarray(half_band, float)
    flip = np.where(signed < 0, -1.0, 1.0)
    h = np.abs(signed)
    n, m = x.shape
    out = np.zeros((n, m))
    der = np.zeros((n, m))
    o, d = np.zeros(m), np.zeros(m)
    for t in range(n):
        if t:
            y = x[t - 1] + o
            lo, hi = x[t] - h, x[t] + h
            below, above = y < lo, y > hi
            o = np.where(below, lo, np.where(above, hi, y)) - x[t]
            d = np.where(below, -1.0, np.where(above, 1.0, d))
        s = side[t]
        o = np.where(s != 0, s * h, o)
        d = np.where(s != 0, s, d)
        out[t], der[t] = o, d
    return out * flip[None, :], der


class GravityBacklash(Effect):
    """Lost motion in each drive of a serial chain, taken up on the side the joint's gravity load pushes.

    Physics: as :class:`~bayescal.effects.backlash.Backlash`, the joint (the
    follower) has a play ``b_i`` (full width of the dead band) against its
    drive, whose position is the commanded one.  In an arm or a column the
    joint also carries the gravity load of every body beyond it: the
    generalised force ``tau_i = g d . (sum_b m_b dx_b / dq_i + m_L dx_t /
    dq_i)`` (virtual work, the bodies' centres of mass and the payload at
    the tool point, ``d`` the pose's gravity direction).  Where ``|tau_i|``
    exceeds the load the joint's friction holds (input ``holding_load``),
    gravity pushes the joint against the flank on its side whatever the
    approach:

        dq_i = +(b_i / 2) sign(tau_i)

    (positive ``tau_i``: gravity pushes ``q_i`` up, the joint stands half
    the band beyond the drive).  Where the load is smaller, friction keeps
    the joint where the last move left it: the approach direction decides
    as for ``backlash`` (the play operator in measurement order,
    :func:`gravity_play`).  The side flips across the workspace wherever
    the centre of mass of what the joint carries passes over its axis (an
    arm through the vertical, a linear axis through the horizontal), which
    the geometry cannot absorb; a drive whose load never changes sign shows
    a constant offset, absorbed by its zero.

    Loads: link masses and centres of mass stated (``link_mass_kg``,
    ``link_com_mm``), else the machine file's (a URDF's ``<inertial>``),
    else every link 10 kg at its middle (only the sign matters, and the
    threshold: state the masses for a real machine); the payload from
    ``payload_kg``.  Gravity: the input ``gravity`` (default ``[0, 0, -1]``)
    or, per pose, a base sensor (``accel.base.x/y/z``,
    :mod:`bayescal.effects.gravity_field`).  ``holding_load``: one value per
    actuator, N on a slider and N m on a joint (default 10 N and 1 N m).
    The loads are taken at the commanded pose (the play moves them by a
    fraction of the band).  Parameters: ``backlash.q<i>`` in um (urad on a
    revolute drive), ``>= 0``, prior as ``backlash``.  Usual size: gear
    trains 0.3-3 mrad (1-10 arcmin), worn screws and racks 20-100 um.
    Only serial chains (their bodies' loads).
    """

    name = "gravity_backlash"
    summary = "a dead band per drive taken up on the side of the joint's gravity load (by the approach where the load is small)"
    magnitude_unit = "um"
    default_magnitude = 30.0
    features_at_nominal = True
    settings_keys = ("gravity", "link_mass_kg", "link_com_mm", "holding_load")

    #: Default loads friction holds: N on a slider, N m on a joint.
    HOLDING = {"mm": 10.0, "rad": 1.0}
    DEFAULT_MASS_KG = 10.0

    def __init__(self, *, gravity=None, link_mass_kg=None, link_com_mm=None, holding_load=None):
        self.down = _unit(DEFAULT_GRAVITY_DIRECTION if gravity is None else gravity, "gravity_backlash gravity")
        if link_mass_kg is None and link_com_mm is not None:
            raise InputError("gravity_backlash link_com_mm: given without link_mass_kg; state the links' masses too")
        self.link_mass = None if link_mass_kg is None else np.asarray(link_mass_kg, float)
        self.link_com = None if link_com_mm is None else np.asarray(link_com_mm, float)
        self.holding = None if holding_load is None else np.asarray(holding_load, float).reshape(-1)
        if self.holding is not None and not (np.all(np.isfinite(self.holding)) and np.all(self.holding >= 0)):
            raise InputError(f"gravity_backlash holding_load: expected loads >= 0 (N on a slider, N m on a joint), got {self.holding.tolist()}")

    def not_applicable(self, machine: Machine, aux: dict) -> str | None:
        chain, _ = serial_part(machine, None)
        if chain is None:
            return f"the gravity side is modelled on serial chains (their links' loads); on a {machine.kind} machine see backlash"
        return None

    def implied_settings(self, machine: Machine) -> dict:
        chain, _ = serial_part(machine, None)
        if self.link_mass is not None or chain is None or chain.body_inertials is None:
            return {}
        known = chain.body_inertials
        return {"link_mass_kg": np.asarray(known.mass_kg, float).tolist(), "link_com_mm": np.asarray(known.com_mm, float).tolist()}

    def features(self, machine: Machine, q: NDArray, theta: NDArray, aux: dict, order, poses: ToolPoses | None) -> Features:
        chain, th = serial_part(machine, theta)
        if chain is None:
            raise InputError(self.not_applicable(machine, aux) or "gravity_backlash: not a serial chain")
        n = q.shape[0]
        mass, com, source = chain_masses(machine, chain, self.link_mass, self.link_com, "gravity_backlash")
        if mass is None or np.isnan(mass).any():
            mass = np.full(len(chain.joint_type), self.DEFAULT_MASS_KG) if mass is None else np.where(np.isnan(mass), self.DEFAULT_MASS_KG, mass)
            source = f"{source}; unknown links taken as {self.DEFAULT_MASS_KG:g} kg at their middles"
        down, sensor = gravity_per_pose(aux, self.down, n)
        payload = np.asarray(aux["payload_kg"], float) if "payload_kg" in aux else np.zeros(n)
        units = machine.actuator_unit_info
        tau = gravity_loads(chain, q, th, mass, com, down, payload) * np.array([u.load_scale for u in units])  # N, N m
        hold = np.array([self.HOLDING[u.unit] for u in units]) if self.holding is None else self.holding
        if hold.size != q.shape[1]:
            raise InputError(f"gravity_backlash holding_load: {hold.size} value(s) for {q.shape[1]} actuators; expected one per "
                             "actuator (N on a slider, N m on a joint)")
        side = np.where(np.abs(tau) > hold[None, :], np.sign(tau), 0.0)
        seq = measurement_sequence(order, n)
        rank = np.empty(n, dtype=int)
        rank[seq] = np.arange(n)
        to_q = np.array([u.small_to_q for u in units])
        # like backlash, the operator runs over the whole session in time order; a subset keeps that history
        return Features({"rank": rank, "side": side},
                        {"q_seq": np.asarray(q, float)[seq], "side_seq": side[seq], "to_q": to_q, "source": source, "sensor": sensor})

    def params(self, machine: Machine, features: Features) -> tuple[EffectParam, ...]:
        return tuple(EffectParam(f"backlash.q{i + 1}", u.small, 30.0 * u.per_um, lower=0.0)
                     for i, u in enumerate(machine.actuator_unit_info))

    def _play(self, features: Features, eta: NDArray) -> tuple[NDArray, NDArray]:
        y, d = gravity_play(features.const["q_seq"], features.const["side_seq"], 0.5 * features.const["to_q"] * np.asarray(eta, float))
        rank = features.per_pose["rank"]
        return y[rank], d[rank]

    def delta_q(self, features: Features, eta: NDArray) -> NDArray:
        return self._play(features, eta)[0]

    def delta_q_jacobian(self, features: Features, eta: NDArray) -> NDArray:
        _, d = self._play(features, eta)
        n, m = d.shape
        J = np.zeros((n, m, m))
        J[:, np.arange(m), np.arange(m)] = 0.5 * features.const["to_q"][None, :] * d
        return J

    def inadmissible(self, features: Features, eta: NDArray | None = None) -> str | None:
        side = features.per_pose["side"]
        flips = [(np.any(side[:, i] > 0) and np.any(side[:, i] < 0)) for i in range(side.shape[1])]
        if not any(flips):
            return ("no drive's gravity load changes sign over the recording: the gravity side is then a constant "
                    "offset (a zero), and where the load is small the effect is backlash")
        return None

    def model_note(self, features: Features) -> str:
        side = features.per_pose["side"]
        share = ", ".join(f"q{i + 1} {100 * np.mean(side[:, i] != 0):.0f}%" for i in range(side.shape[1]))
        note = f"poses held on the gravity side: {share}; link masses {features.const['source']}"
        if features.const["sensor"]:
            note += "; gravity per pose from the base sensor (accel.base.*)"
        return note

    def simulated_values(self, machine: Machine, features: Features, magnitude: float, rng) -> NDArray:
        return magnitude * rng.uniform(0.6, 1.4, machine.n_actuators)
