"""Changes of a session's conditions that can separate an effect from the geometry.

Where the data fix only the sum of an effect and the geometry (the constant
part of a gravity sag is an actuator zero offset), a second session under
other conditions can fix the split: a second payload changes the load the
sag responds to, a tilted mounting turns gravity against the machine, a
temperature step drives the growth.  An effect names the conditions that
drive it (:meth:`bayescal.effects.Effect.separating_conditions`); the
diagnosis weighs each by the information it would add
(:mod:`bayescal.diagnose.separate`).  A condition is a pure function of the
recording's channels: the channels the recorded session has *as the effect
reads them* (``baseline``: an absent payload channel is no payload) and
those of the proposed session (``session``), per pose, in the recording's
units (docs/formats.md section 2 for the channels, section 8 for the base
tilt sensor).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np
from numpy.typing import NDArray

from .gravity_field import BASE_SENSOR, gravity_per_pose, tilt_basis

__all__ = ["Condition", "second_payload", "temperature_step", "tilted_mounting", "PAYLOAD_KG", "TEMPERATURE_STEP_K",
           "TILT_DEG"]

#: Payload of a second session when the recording has none (kg): a tool, a test mass a person can mount.
PAYLOAD_KG = 10.0
#: Temperature step of a second session (K): a workshop's day against its night, a machine warmed up.
TEMPERATURE_STEP_K = 10.0
#: Tilt of a second session's mounting (degrees): shims under a base, a tilting table.
TILT_DEG = 10.0


@dataclass(frozen=True)
class Condition:
    """A second session under changed conditions.

    Attributes
    ----------
    key : str
        What changes (``payload``, ``temperature``, ``tilt_1``, ``tilt_2``); conditions of two effects with
        the same key are one session.
    advice : str
        What to do, for the report (units included).
    baseline : callable
        ``(aux, n) -> aux``: the recorded session's channels as the effect reads them.
    session : callable
        ``(aux, n) -> aux``: the proposed session's channels at the same poses.
    """

    key: str
    advice: str
    baseline: Callable[[dict, int], dict]
    session: Callable[[dict, int], dict]


def _payload(aux: dict, n: int) -> NDArray:
    return np.asarray(aux["payload_kg"], float) if "payload_kg" in aux else np.zeros(n)


def second_payload(aux: dict) -> Condition:
    """The poses again with a heavier payload: twice the heaviest recorded, or :data:`PAYLOAD_KG` without one.

    Parameters
    ----------
    aux : dict of str to ndarray
        The recording's channels (``payload_kg`` in kg, absent: no payload).
    """
    heaviest = float(np.max(aux["payload_kg"])) if "payload_kg" in aux and np.size(aux["payload_kg"]) else 0.0
    mass = 2.0 * heaviest if heaviest > 0 else PAYLOAD_KG
    return Condition(
        "payload",
        f"the recording's poses again with a payload of {mass:g} kg at the tool (channel payload_kg)",
        lambda a, n: {**a, "payload_kg": _payload(a, n)},
        lambda a, n: {**a, "payload_kg": np.full(n, mass)},
    )


def temperature_step(step_K: float = TEMPERATURE_STEP_K) -> Condition:
    """The poses again ``step_K`` kelvin above the recording's mean temperature (channel ``temp_C``)."""
    return Condition(
        "temperature",
        f"the recording's poses again {step_K:g} K warmer than its mean temperature (channel temp_C)",
        lambda a, n: dict(a),
        lambda a, n: {**a, "temp_C": np.full(n, float(np.mean(a["temp_C"])) + step_K)},
    )


def tilted_mounting(down: NDArray, axis: int, deg: float = TILT_DEG) -> Condition:
    """The poses again with the mounting tilted by ``deg`` degrees, read by a base tilt sensor.

    Parameters
    ----------
    down : ndarray, shape (3,)
        The effect's gravity direction (base frame, unit) when the recording has no base sensor.
    axis : int
        0 or 1: gravity tilted towards the first or second vector of
        :func:`bayescal.effects.gravity_field.tilt_basis` (the base axes most
        perpendicular to ``down``).
    deg : float
        Tilt, degrees.
    """
    e = tilt_basis(np.asarray(down, float))[axis]
    a = np.deg2rad(deg)
    k = int(np.argmax(np.abs(e)))
    towards = ("+" if e[k] > 0 else "-") + "xyz"[k]

    def session(aux: dict, n: int) -> dict:
        d, _ = gravity_per_pose(aux, down, n)
        # each pose's gravity turned by deg towards e (e made normal to that pose's direction: a recorded sensor's
        # reading need not be the mounting's nominal direction)
        ep = e - np.einsum("ij,j->i", d, e)[:, None] * d
        ep /= np.linalg.norm(ep, axis=1, keepdims=True)
        t = np.cos(a) * d + np.sin(a) * ep
        if all(c in aux for c in BASE_SENSOR):
            # as the recording's sensor reads: its magnitude (m/s^2, g, ...) and its sign (gravity or the specific force)
            v = np.column_stack([np.asarray(aux[c], float) for c in BASE_SENSOR])
            t = t * (np.linalg.norm(v, axis=1) * np.sign(np.einsum("ij,ij->i", v, d)))[:, None]
        out = {k: v for k, v in aux.items() if k not in BASE_SENSOR}
        # without a recorded sensor: the unit direction of gravity (gravity_per_pose takes either sign and any scale)
        return {**out, **{c: t[:, i] for i, c in enumerate(BASE_SENSOR)}}

    return Condition(
        f"tilt_{axis + 1}",
        f"the recording's poses again with the base tilted by {deg:g} deg (gravity towards base {towards}), "
        "read by a base tilt sensor (channels accel.base.x, accel.base.y, accel.base.z)",
        lambda aux, n: dict(aux),
        session,
    )
