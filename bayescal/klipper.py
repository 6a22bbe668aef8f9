"""Klipper's linear-delta printers: geometry and saved calibration data in, calibrated keys out.

Klipper's delta model (``klippy/kinematics/delta.py``, described in our own
words; docs/delta.md): tower ``i`` at angle ``angle_i`` and the common radius
``delta_radius``; an arm of ``arm_length_i`` from the carriage to the nozzle;
the carriage height at the endstop is ``E_i = position_endstop_i +
sqrt(arm_length_i^2 - delta_radius^2)``.  ``DELTA_CALIBRATE`` stores each
probed or printed point as a *stable position*: the microsteps ``s_i`` each
carriage is below its endstop, so that the carriage height is
``E_i - s_i step_dist_i`` with ``step_dist = rotation_distance /
(full_steps_per_rotation * microsteps)`` (times the gear ratio's inverse).

bayescal's linear-delta machine with ``zero_i = E_i`` and actuator
``q_i = -s_i step_dist_i`` (mm, carriage travel from the endstop, positive
up) is the same model; the stored heights and distances become a constraint
recording (FORMATS.md section 6).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .errors import InputError
from .io.constraints import ConstraintRecording
from .io.klipper_cfg import KlipperConfig
from .machines.base import MeasurementNoise
from .machines.linear_delta import LinearDelta

__all__ = [
    "KlipperDelta", "read_klipper_delta", "klipper_recording", "klipper_machine", "klipper_text",
    "KLIPPER_TOLERANCE", "STEPPERS",
]

STEPPERS = ("stepper_a", "stepper_b", "stepper_c")
_DEFAULT_ANGLES = (210.0, 330.0, 90.0)

#: One-sigma tolerances of a printer's geometry (printers are built and configured to about a
#: millimetre and half a degree; a Klipper config's nominal values are often an earlier calibration).
KLIPPER_TOLERANCE = {
    "tower_angle": 0.01, "tower_radius": 1.0, "tower_zero": 1.0, "tower_direction": 2.0e-3,
    "arm_length": 1.0, "tool_point": 1.0,
}
#: Default one-sigma noise of a probe height and of a caliper distance on a printed part, mm.
SIGMA_HEIGHT, SIGMA_DISTANCE = 0.02, 0.05


@dataclass(frozen=True)
class KlipperDelta:
    """A Klipper delta printer's geometry as its config states it.

    Attributes
    ----------
    delta_radius : float
        mm.
    angle_deg, arm_length, position_endstop : ndarray, shape (3,)
        Per stepper a, b, c (degrees, mm, mm).
    step_dist : ndarray, shape (3,)
        mm per microstep.
    print_radius, minimum_z : float
        mm (``[printer] print_radius``, ``minimum_z_position``).
    path : str
    """

    delta_radius: float
    angle_deg: NDArray
    arm_length: NDArray
    position_endstop: NDArray
    step_dist: NDArray
    print_radius: float
    minimum_z: float
    path: str = "<memory>"

    @property
    def endstop_height(self) -> NDArray:
        """Carriage height at the endstop ``E_i = position_endstop_i + sqrt(L_i^2 - R^2)``, mm."""
        return self.position_endstop + np.sqrt(self.arm_length**2 - self.delta_radius**2)

    def carriage_q(self, stable: ArrayLike) -> NDArray:
        """Stable positions (microsteps below the endstops, shape (n, 3)) as ``q = -s step_dist`` (mm)."""
        return -np.asarray(stable, dtype=float) * self.step_dist


def _gear_ratio(cfg: KlipperConfig, sec: str) -> float:
    if not cfg.has(sec, "gear_ratio"):
        return 1.0
    text = cfg.get(sec, "gear_ratio")
    ratio = 1.0
    for part in text.split(","):
        try:
            a, b = (float(x) for x in part.split(":"))
        except ValueError:
            raise cfg.error(sec, "gear_ratio", f"expected ratios such as '80:16, 48:16', got {text!r}") from None
        if a <= 0 or b <= 0:
            raise cfg.error(sec, "gear_ratio", f"expected positive ratios, got {text!r}")
        ratio *= a / b
    return ratio


def read_klipper_delta(cfg: KlipperConfig) -> KlipperDelta:
    """The delta geometry of a Klipper config (SAVE_CONFIG values applied), checked.

    Raises
    ------
    KlipperConfigError
        Naming the section and key of a missing or bad value.
    """
    kin = cfg.get("printer", "kinematics").strip()
    if kin != "delta":
        raise cfg.error("printer", "kinematics", f"expected 'delta' (a linear delta printer), got {kin!r}")
    R = cfg.getfloat("printer", "delta_radius", positive=True)
    arm_a = cfg.getfloat("stepper_a", "arm_length", positive=True)
    pe_a = cfg.getfloat("stepper_a", "position_endstop")
    ang, arms, pes, sd = [], [], [], []
    for k, sec in enumerate(STEPPERS):
        if not cfg.has(sec):
            raise cfg.error(sec, "", "missing section; a delta printer has [stepper_a], [stepper_b] and [stepper_c]")
        ang.append(cfg.getfloat(sec, "angle", _DEFAULT_ANGLES[k]))
        L = cfg.getfloat(sec, "arm_length", arm_a, positive=True)
        if L <= R:
            raise cfg.error(sec, "arm_length", f"expected an arm longer than [printer] delta_radius = {R}, got {L}")
        arms.append(L)
        pes.append(cfg.getfloat(sec, "position_endstop", pe_a))
        rd = cfg.getfloat(sec, "rotation_distance", positive=True)
        micro = cfg.getfloat(sec, "microsteps", positive=True)
        full = cfg.getfloat(sec, "full_steps_per_rotation", 200.0, positive=True)
        if micro != int(micro) or full != int(full):
            key = "microsteps" if micro != int(micro) else "full_steps_per_rotation"
            raise cfg.error(sec, key, "expected a whole number")
        sd.append(rd / (full * micro * _gear_ratio(cfg, sec)))
    return KlipperDelta(
        delta_radius=R, angle_deg=np.array(ang), arm_length=np.array(arms), position_endstop=np.array(pes),
        step_dist=np.array(sd), print_radius=cfg.getfloat("printer", "print_radius", R, positive=True),
        minimum_z=cfg.getfloat("printer", "minimum_z_position", 0.0), path=cfg.path,
    )


def klipper_recording(
    cfg: KlipperConfig, kd: KlipperDelta, *, sigma_height: float = SIGMA_HEIGHT, sigma_distance: float = SIGMA_DISTANCE,
) -> ConstraintRecording:
    """The saved ``[delta_calibrate]`` measurements as a constraint recording.

    Rows: ``manual_height<i>`` and ``height<i>`` (probe heights: nozzle z at the
    stable position ``..._pos``), then ``distance<i>`` (between ``_pos1`` and
    ``_pos2``), in Klipper's order.  Aux channel ``klipper_index`` is ``i``.

    Raises
    ------
    KlipperConfigError
        When the config has no saved calibration (``[delta_calibrate]
        height0``) or a saved entry is incomplete.
    """
    sec = "delta_calibrate"
    if not cfg.has(sec):
        raise cfg.error(sec, "", "missing section; expected the [delta_calibrate] block SAVE_CONFIG writes after DELTA_CALIBRATE")
    if not cfg.has(sec, "height0") and not cfg.has(sec, "manual_height0"):
        raise cfg.error(
            sec, "height0",
            "missing; the config holds no saved calibration (run DELTA_CALIBRATE and SAVE_CONFIG, which store "
            "height0, height0_pos, ... in the SAVE_CONFIG block at the end of printer.cfg)",
        )
    measure, qa, qb, value, sig, idx = [], [], [], [], [], []
    nan3 = [np.nan] * 3
    for prefix in ("manual_height", "height"):
        for i in range(999):
            if not cfg.has(sec, f"{prefix}{i}"):
                break
            measure.append("height")
            value.append(cfg.getfloat(sec, f"{prefix}{i}"))
            qa.append(cfg.getfloats(sec, f"{prefix}{i}_pos", 3))
            qb.append(nan3)
            sig.append(sigma_height)
            idx.append(i)
    for i in range(999):
        if not cfg.has(sec, f"distance{i}"):
            break
        d = cfg.getfloat(sec, f"distance{i}")
        if d <= 0:
            raise cfg.error(sec, f"distance{i}", f"expected a positive distance in mm, got {d}")
        measure.append("distance")
        value.append(d)
        qa.append(cfg.getfloats(sec, f"distance{i}_pos1", 3))
        qb.append(cfg.getfloats(sec, f"distance{i}_pos2", 3))
        sig.append(sigma_distance)
        idx.append(i)
    dist = np.array([m == "distance" for m in measure])
    qb_mm = np.where(dist[:, None], kd.carriage_q(np.where(dist[:, None], qb, 0.0)), np.nan)
    return ConstraintRecording(
        measure=tuple(measure), qa=kd.carriage_q(qa), qb=qb_mm, value=np.array(value),
        sigma=np.array(sig), aux={"klipper_index": np.array(idx, dtype=float)}, path=cfg.path,
    )


def klipper_machine(kd: KlipperDelta, *, name: str | None = None, q_span: ArrayLike | None = None) -> LinearDelta:
    """The linear-delta machine of a Klipper geometry (``zero = E_i``, ``q = -s step_dist``).

    ``q_limits``: up to the endstop (0) and down to where the carriage is
    with the nozzle at ``minimum_z_position`` at the far edge of
    ``print_radius``, widened to hold ``q_span`` (e.g. a recording's ``q``).
    """
    E = kd.endstop_height
    reach = kd.delta_radius + kd.print_radius
    low = kd.minimum_z + np.sqrt(np.maximum(kd.arm_length**2 - reach**2, 0.0)) - E
    if q_span is not None:
        q_span = np.asarray(q_span, dtype=float)
        low = np.minimum(low, np.nanmin(q_span, axis=0) - 1.0)
    return LinearDelta(
        angle=np.deg2rad(kd.angle_deg), radius=np.full(3, kd.delta_radius), zero=E, direction=np.tile([0.0, 0.0, 1.0], (3, 1)),
        arm_length=kd.arm_length.copy(), tool_point=np.zeros(3), name=name or f"Klipper delta ({kd.path})",
        # no [measurement] table: the rows' sigmas (SIGMA_HEIGHT, SIGMA_DISTANCE) are guesses that weight heights
        # against distances, not a stated noise; identify estimates the noise scale (docs/delta-printers.md)
        noise=MeasurementNoise(),
        q_limits=np.column_stack([low, np.zeros(3)]), tolerance_groups=dict(KLIPPER_TOLERANCE), source=kd.path,
    )


def klipper_values(machine: LinearDelta, theta: ArrayLike | None = None) -> tuple[dict, list[str]]:
    """Klipper's keys for the geometry ``nominal + theta``, and what they cannot represent.

    The nozzle offset ``t`` moves the towers by ``t`` (the effector only
    translates), so ``E_i + t_z`` is the endstop height; the horizontal part
    shifts the whole print on the bed, which Klipper's keys cannot hold and
    no height or distance sees.  Klipper has one radius: the mean of the
    towers' is written.  Tower tilts have no Klipper key.

    Returns
    -------
    values : dict
        ``{"delta_radius": R, "stepper_a": {"angle": deg, "arm_length": mm,
        "position_endstop": mm}, ...}``.
    notes : list of str
        What was approximated, with sizes.
    """
    if machine.kind != "linear-delta" or machine.n_actuators != 3:
        raise InputError(f"Klipper's delta keys describe a three-tower linear delta; got a {machine.kind} with {machine.n_actuators} actuators")
    g = machine.geometry_arrays(theta)
    notes = []
    tilt = np.degrees(np.arccos(np.clip(g["direction"][:, 2], -1, 1)))
    if np.any(tilt > 1e-9):
        notes.append(f"tower tilts of {', '.join(f'{v:.4f}' for v in tilt)} deg are not representable in Klipper; written as vertical")
    t = g["tool_point"]
    if np.hypot(t[0], t[1]) > 1e-9:
        notes.append(f"a horizontal nozzle offset of ({t[0]:.4f}, {t[1]:.4f}) mm shifts prints on the bed; Klipper has no key for it")
    R = float(np.mean(g["radius"]))
    spread = float(np.ptp(g["radius"]))
    if spread > 1e-9:
        notes.append(f"the towers' radii differ by {spread:.4f} mm; Klipper has one delta_radius, their mean is written")
    # direction is vertical up to the tilts reported above: E_i is the zero's height
    E = g["zero"] * g["direction"][:, 2] + t[2]
    L = g["arm_length"]
    out = {"delta_radius": R}
    for k, sec in enumerate(STEPPERS):
        out[sec] = {
            "angle": float(np.degrees(g["angle"][k]) % 360.0),
            "arm_length": float(L[k]),
            "position_endstop": float(E[k] - np.sqrt(L[k] ** 2 - R**2)),
        }
    return out, notes


def klipper_text(machine: LinearDelta, theta: ArrayLike | None = None) -> str:
    """The calibrated geometry as Klipper config sections, for the user to paste into printer.cfg."""
    values, notes = klipper_values(machine, theta)
    lines = [
        f"# Calibrated geometry of '{machine.name}' written by bayescal, in Klipper's keys.",
        "# Paste into printer.cfg: replace these keys in their sections, and in the SAVE_CONFIG block",
        "# at the end of the file if it holds them (that block overrides the sections above).",
    ]
    lines += [f"# note: {n}" for n in notes]
    lines += ["", "[printer]", f"delta_radius: {values['delta_radius']!r}", ""]
    for sec in STEPPERS:
        lines.append(f"[{sec}]")
        lines += [f"{k}: {v!r}" for k, v in values[sec].items()]
        lines.append("")
    return "\n".join(lines)
