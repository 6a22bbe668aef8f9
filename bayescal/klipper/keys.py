"""Klipper's own keys for a calibrated linear delta: the block a user pastes into ``printer.cfg``.

Klipper's delta (``klippy/kinematics/delta.py`` and
``klippy/extras/delta_calibrate.py``, in our own words) has one
``[printer] delta_radius`` and, per ``[stepper_a/b/c]``, an ``angle``
(degrees; defaults 210, 330, 90), an ``arm_length`` and a
``position_endstop`` (mm).  ``DELTA_CALIBRATE`` adjusts ``delta_radius``,
the angles of steppers a and b, the three endstops and, with distances, the
three arms; it keeps stepper c's angle fixed, as the reference of the
printer's frame, and saves every value as ``%.6f``.

bayescal's linear delta has more freedom.  Where the difference is a gauge
(a change of the whole printer that no probe height or caliper distance
sees), it is re-expressed exactly:

* the nozzle's horizontal offset ``t_xy``: the effector only translates, so
  it is the same as moving the three towers by ``t_xy``; its vertical offset
  ``t_z`` raises every endstop height by ``t_z``;
* three tower positions (each tower's own radius and angle) always lie on
  one circle: Klipper's frame is centred on it (a shift of the whole printer
  in the bed plane) and its radius is ``delta_radius``;
* a rotation of the whole printer about z: the frame is turned so that
  stepper c keeps its configured angle.

So, without tower tilts, the written printer predicts the same heights and
distances as the calibrated one, and the same nozzle positions up to that
shift and turn (tested).  Tower tilts have no Klipper key: each tower is
written vertical through where its carriage is with the nozzle at the bed
centre, and the tilts are reported.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..errors import InputError
from .printer import STEPPERS
from ..machines.linear_delta import LinearDelta

__all__ = ["KlipperKeys", "klipper_keys", "klipper_values", "klipper_text"]

_TILT_SHOWN = 1e-6  # deg: Klipper's written precision (%.6f)
# a shift below a micrometre or a turn below 1e-4 deg (0.2 um at the towers) is not worth a note
_SHIFT_SHOWN, _TURN_SHOWN = 1e-3, 1e-4


@dataclass(frozen=True)
class KlipperKeys:
    """A calibrated delta in Klipper's keys.

    Attributes
    ----------
    delta_radius : float
        mm.
    angle_deg, arm_length, position_endstop : ndarray, shape (3,)
        Per stepper a, b, c (degrees, mm, mm).
    centre : ndarray, shape (2,)
        Klipper's origin in the calibrated machine's frame, mm.
    turn_deg : float
        Klipper's frame is the calibrated one shifted to ``centre`` and turned by ``turn_deg`` about z, degrees.
    notes : tuple of str
        What was re-expressed or approximated, with sizes.
    """

    delta_radius: float
    angle_deg: NDArray
    arm_length: NDArray
    position_endstop: NDArray
    centre: NDArray
    turn_deg: float
    notes: tuple[str, ...]


def _circle(P: NDArray) -> tuple[NDArray, float]:
    """Centre and radius of the circle through three points in the plane (rows of ``P``)."""
    A = 2.0 * (P[1:] - P[0])
    b = np.sum(P[1:] ** 2, axis=1) - np.sum(P[0] ** 2)
    if abs(np.linalg.det(A)) < 1e-9 * np.max(np.abs(A)) ** 2:
        raise InputError("Klipper's delta keys need three towers that are not in a line; the calibrated towers are")
    c = np.linalg.solve(A, b)
    return c, float(np.mean(np.linalg.norm(P - c, axis=1)))


def _tower_points(machine: LinearDelta, theta, g: dict) -> NDArray:
    """Where each tower axis is (x, y, mm) at the height of its carriage with the nozzle at the bed centre.

    A vertical tower is there at every height; a tilted one is written
    vertical through that point, where the printer works (its foot at z = 0
    when the centre cannot be reached).
    """
    base = np.column_stack([g["radius"] * np.cos(g["angle"]), g["radius"] * np.sin(g["angle"])])
    q0 = machine.inverse(np.zeros((1, 3)), theta)[0]
    if not np.all(np.isfinite(q0)):
        return base
    return base + ((g["zero"] + q0)[:, None] * g["direction"])[:, :2]


def _wrap(x: NDArray) -> NDArray:
    """Angles (rad) into (-pi, pi]."""
    return np.pi - np.mod(np.pi - np.asarray(x), 2.0 * np.pi)


def _notes(g: dict, centre: NDArray, turn: float, fixed_deg: float) -> list[str]:
    notes = []
    tilt = np.degrees(np.arccos(np.clip(g["direction"][:, 2], -1.0, 1.0)))
    if np.any(tilt > _TILT_SHOWN):
        notes.append(f"tower tilts of {', '.join(f'{v:.4f}' for v in tilt)} deg have no Klipper key; each tower is "
                     "written vertical through where its carriage is with the nozzle at the bed centre")
    if np.hypot(*centre) > _SHIFT_SHOWN:
        t = g["tool_point"]
        folded = " (the nozzle's horizontal offset folded in)" if np.hypot(t[0], t[1]) > _SHIFT_SHOWN else ""
        notes.append(f"Klipper's origin is the centre of the towers' circle{folded}, at ({centre[0]:.4f}, {centre[1]:.4f}) mm "
                     "in the calibrated frame: prints move that much on the bed, a shift no height or distance sees")
    if abs(np.degrees(turn)) > _TURN_SHOWN:
        notes.append(f"the printer's frame is turned by {-np.degrees(turn):.6f} deg about z so that stepper_c keeps its angle "
                     f"of {fixed_deg:.6f} deg, as DELTA_CALIBRATE keeps it (a rotation no height or distance sees)")
    return notes


def klipper_keys(machine: LinearDelta, theta: ArrayLike | None = None, *, fixed_angle_deg: float | None = None) -> KlipperKeys:
    """The geometry ``nominal + theta`` in Klipper's keys and gauge.

    Parameters
    ----------
    machine : LinearDelta
        Three towers: stepper a, b, c in order; possibly in an instrument
        frame (the keys are the geometry's: :attr:`Machine.geometry_part`).
    theta : array_like, optional
        Error parameters of ``machine`` (default zero).
    fixed_angle_deg : float, optional
        Stepper c's angle, degrees (default: the machine's nominal tower-3
        angle, i.e. the config's ``[stepper_c] angle``).

    Raises
    ------
    InputError
        Not a three-tower linear delta, or an arm not longer than
        ``delta_radius`` (Klipper refuses such a printer).
    """
    if machine.kind != "linear-delta" or machine.n_actuators != 3:
        raise InputError(f"Klipper's delta keys describe a three-tower linear delta; got a {machine.kind} with "
                         f"{machine.n_actuators} actuators")
    inner, idx = machine.geometry_part  # the delta under a view (an instrument frame), and its parameters
    machine, theta = inner, machine.check_theta(theta)[idx]
    g = machine.geometry_arrays(theta)
    t = g["tool_point"]
    feet = _tower_points(machine, theta, g) + t[:2]
    centre, R = _circle(feet)
    phi = np.arctan2(feet[:, 1] - centre[1], feet[:, 0] - centre[0])
    fixed_deg = float(np.degrees(machine.angle[2])) if fixed_angle_deg is None else float(fixed_angle_deg)
    turn = float(_wrap(phi[2] - np.radians(fixed_deg)))
    nominal = np.degrees(machine.angle)
    # each angle written near the configured one (not reduced to 0..360), stepper c exactly at its fixed value
    angle = nominal + np.degrees(_wrap(phi - turn - np.radians(nominal)))
    angle[2] = fixed_deg
    L = g["arm_length"]
    for sec, arm in zip(STEPPERS, L):
        if not arm > R:
            raise InputError(f"the calibrated [{sec}] arm_length {arm:.6f} mm is not longer than delta_radius {R:.6f} mm: "
                             "Klipper refuses such a printer; not written")
    E = g["zero"] * g["direction"][:, 2] + t[2]  # endstop heights; the towers are vertical up to the tilts noted
    return KlipperKeys(
        delta_radius=R, angle_deg=angle, arm_length=L.copy(), position_endstop=E - np.sqrt(L**2 - R**2),
        centre=centre, turn_deg=float(np.degrees(turn)), notes=tuple(_notes(g, centre, turn, fixed_deg)),
    )


def klipper_values(machine: LinearDelta, theta: ArrayLike | None = None) -> tuple[dict, list[str]]:
    """Klipper's keys and the notes of :func:`klipper_keys`, as plain values.

    Returns ``{"delta_radius": R, "stepper_a": {"angle": deg, "arm_length": mm,
    "position_endstop": mm}, ...}`` and the list of notes.
    """
    k = klipper_keys(machine, theta)
    out = {"delta_radius": k.delta_radius}
    for i, sec in enumerate(STEPPERS):
        out[sec] = {"angle": float(k.angle_deg[i]), "arm_length": float(k.arm_length[i]),
                    "position_endstop": float(k.position_endstop[i])}
    return out, list(k.notes)


def klipper_text(machine: LinearDelta, theta: ArrayLike | None = None) -> str:
    """The calibrated geometry as a block to paste into ``printer.cfg`` above its SAVE_CONFIG block.

    Values as Klipper writes them (``%.6f``, mm and degrees); comments say
    where to paste and what was re-expressed (:func:`klipper_keys`).
    """
    k = klipper_keys(machine, theta)
    lines = [
        f"# Calibrated geometry of '{machine.name}', written by bayescal in Klipper's keys (mm, degrees).",
        "# Paste this block into printer.cfg after your [printer] and [stepper_a/b/c] sections, just above",
        "# the SAVE_CONFIG block (the line '#*# <---------------------- SAVE_CONFIG ---------------------->'),",
        "# then send RESTART. Klipper takes these values over the same keys inside the SAVE_CONFIG block;",
        "# leave that block as it is. A later DELTA_CALIBRATE + SAVE_CONFIG comments these lines out.",
    ]
    lines += [f"# note: {n}" for n in k.notes]
    lines += ["", "[printer]", f"delta_radius: {k.delta_radius:.6f}", ""]
    for i, sec in enumerate(STEPPERS):
        lines += [f"[{sec}]", f"angle: {k.angle_deg[i]:.6f}", f"arm_length: {k.arm_length[i]:.6f}",
                  f"position_endstop: {k.position_endstop[i]:.6f}", ""]
    return "\n".join(lines)
