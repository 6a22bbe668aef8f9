"""Klipper's linear-delta printers: a config's geometry and saved calibration as a machine and a recording.

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
recording (docs/formats.md section 6).  The calibrated geometry goes back
into Klipper's keys with :mod:`bayescal.klipper.keys`.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..errors import InputError
from ..io.constraints import ConstraintRecording
from .cfg import KlipperConfig
from ..machines.base import MeasurementNoise
from ..machines.linear_delta import LinearDelta

__all__ = [
    "KlipperDelta", "read_klipper_delta", "klipper_recording", "klipper_machine", "saved_counts",
    "KLIPPER_TOLERANCE", "STEPPERS", "MAX_LENGTH", "SAVED_MARGIN",
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


#: Lengths beyond this (mm) are no printer's: a value past it is a typo or a broken file.
MAX_LENGTH = 1.0e4
#: How far (mm) a saved point may lie outside the printer's travel as this config states it: the
#: measurements were taken under the geometry in force then, which calibration has since changed.
SAVED_MARGIN = 50.0
_ARM_WHY = "Klipper: longer than [printer] delta_radius"


def _gear_ratio(cfg: KlipperConfig, sec: str) -> float:
    if not cfg.has(sec, "gear_ratio"):
        return 1.0
    text = cfg.get(sec, "gear_ratio")
    ratio = 1.0
    for part in text.split(","):
        try:
            a, b = (float(x) for x in part.split(":"))
        except ValueError:
            raise cfg.error(sec, "gear_ratio", f"expected ratios such as '80:16, 48:16', got {text[:40]!r}") from None
        if not (0 < a <= MAX_LENGTH and 0 < b <= MAX_LENGTH):
            raise cfg.error(sec, "gear_ratio", f"expected positive finite ratios, got {text[:40]!r}")
        ratio *= a / b
    return ratio


def _whole(cfg: KlipperConfig, sec: str, key: str, default: float | None) -> float:
    v = cfg.getfloat(sec, key, default, lo=1.0, hi=65536.0)
    if v != int(v):
        raise cfg.error(sec, key, f"expected a whole number, got {cfg.get(sec, key)[:40]!r}")
    return v


def _stepper(cfg: KlipperConfig, k: int, R: float, arm_a: float, pe_a: float) -> tuple[float, float, float, float]:
    """Angle (deg), arm (mm), position_endstop (mm) and step distance (mm) of stepper ``k``, checked as Klipper does."""
    sec = STEPPERS[k]
    if not cfg.has(sec):
        raise cfg.error(sec, "", "missing section; a delta printer has [stepper_a], [stepper_b] and [stepper_c] "
                                 f"({cfg.sources_note()})")
    angle = cfg.getfloat(sec, "angle", _DEFAULT_ANGLES[k], lo=-720.0, hi=720.0)
    arm = cfg.getfloat(sec, "arm_length", arm_a, above=R, hi=MAX_LENGTH, why=_ARM_WHY)
    pe = cfg.getfloat(sec, "position_endstop", pe_a, lo=-MAX_LENGTH, hi=MAX_LENGTH)
    rd = cfg.getfloat(sec, "rotation_distance", above=0.0, hi=MAX_LENGTH)
    micro = _whole(cfg, sec, "microsteps", None)
    full = _whole(cfg, sec, "full_steps_per_rotation", 200.0)
    return angle, arm, pe, rd / (full * micro * _gear_ratio(cfg, sec))


def read_klipper_delta(cfg: KlipperConfig) -> KlipperDelta:
    """The delta geometry of a Klipper config (SAVE_CONFIG values applied), checked.

    Raises
    ------
    KlipperConfigError
        Naming the file, line, section and key of a missing, malformed,
        non-finite or out-of-range value (lengths within :data:`MAX_LENGTH`,
        angles within +-720 deg, arms longer than ``delta_radius`` as Klipper requires).
    """
    kin = cfg.get("printer", "kinematics").strip()
    if kin != "delta":
        raise cfg.error("printer", "kinematics", f"expected 'delta' (a linear delta printer), got {kin[:40]!r}")
    R = cfg.getfloat("printer", "delta_radius", above=0.0, hi=MAX_LENGTH)
    arm_a = cfg.getfloat("stepper_a", "arm_length", above=R, hi=MAX_LENGTH, why=_ARM_WHY)
    pe_a = cfg.getfloat("stepper_a", "position_endstop", lo=-MAX_LENGTH, hi=MAX_LENGTH)
    ang, arms, pes, sd = zip(*(_stepper(cfg, k, R, arm_a, pe_a) for k in range(3)))
    return KlipperDelta(
        delta_radius=R, angle_deg=np.array(ang), arm_length=np.array(arms), position_endstop=np.array(pes),
        step_dist=np.array(sd), print_radius=cfg.getfloat("printer", "print_radius", R, above=0.0, hi=MAX_LENGTH),
        minimum_z=cfg.getfloat("printer", "minimum_z_position", 0.0, lo=-MAX_LENGTH, hi=float(min(pes)),
                               why="Klipper: at most the lowest position_endstop"), path=cfg.path,
    )


_SAVED = "delta_calibrate"
_SAVED_KEY = re.compile(r"^(manual_height|height|distance)([0-9]+)(_pos[12]?)?$")
#: The keys DELTA_CALIBRATE's SAVE_CONFIG writes per entry <N> of each kind.
_SUFFIXES = {"manual_height": ("", "_pos"), "height": ("", "_pos"), "distance": ("", "_pos1", "_pos2")}
_MAX_SAVED = 999  # Klipper reads entries 0 .. 998 of each kind (at most 3 digits)
_MIN_PROBED = 3  # DELTA_CALIBRATE's least number of probe points


def _indices(cfg: KlipperConfig) -> dict:
    """The entry numbers present per (kind, suffix); keys of the saved kinds' form SAVE_CONFIG does not write are refused."""
    found = {(kind, suf): set() for kind, sufs in _SUFFIXES.items() for suf in sufs}
    for key in cfg.sections[_SAVED]:
        mo = _SAVED_KEY.match(key)
        if not mo:
            continue
        kind, idx, suf = mo.group(1), mo.group(2), mo.group(3) or ""
        if suf not in _SUFFIXES[kind] or len(idx) > 3 or idx != str(int(idx)) or int(idx) >= _MAX_SAVED:
            pos = " and ".join(f"{kind}<N>{s}" for s in _SUFFIXES[kind][1:])
            raise cfg.error(_SAVED, key, f"not a key SAVE_CONFIG writes; expected {kind}<N> and {pos} with N = 0, 1, 2, "
                                         "... (below 999)")
        found[(kind, suf)].add(int(idx))
    return found


def saved_counts(cfg: KlipperConfig) -> dict[str, int]:
    """How many ``manual_height``, ``height`` and ``distance`` entries the saved calibration holds.

    Klipper reads ``height0``, ``height1``, ... up to the first missing one;
    SAVE_CONFIG writes them without gaps, each with its stable positions.  A
    gap, or a position without its value (or the reverse), is refused: Klipper
    would silently read only the entries before it.
    """
    found, counts = _indices(cfg), {}
    for kind, sufs in _SUFFIXES.items():
        have = found[(kind, "")]
        n = max(have) + 1 if have else 0
        if (gap := next((i for i in range(n) if i not in have), None)) is not None:
            raise cfg.error_near(_SAVED, f"{kind}{gap}", f"{kind}{max(have)}", (
                f"missing, but {kind}{max(have)} is present: SAVE_CONFIG writes {kind}0, {kind}1, ... without gaps "
                f"(Klipper would read only the {gap} before the gap); the block is incomplete"))
        for suf in sufs[1:]:
            idx = found[(kind, suf)]
            if (lack := next((i for i in range(n) if i not in idx), None)) is not None:
                raise cfg.error_near(_SAVED, f"{kind}{lack}{suf}", f"{kind}{lack}",
                                     f"missing; expected 3 stable positions with {kind}{lack}")
            if extra := sorted(i for i in idx if i >= n):
                raise cfg.error(_SAVED, f"{kind}{extra[0]}{suf}", f"present without {kind}{extra[0]}; the block is incomplete")
        counts[kind] = n
    return counts


def _stable(cfg: KlipperConfig, kd: KlipperDelta, key: str) -> list[float]:
    """A stable position (microsteps below each endstop), checked to lie within the carriages' travel."""
    steps = cfg.getfloats(_SAVED, key, 3)
    travel = np.asarray(steps) * kd.step_dist
    top = kd.endstop_height + SAVED_MARGIN
    if np.any(travel < -SAVED_MARGIN) or np.any(travel > top):
        raise cfg.error(_SAVED, key, (
            f"expected 3 stable positions (microsteps below each endstop) within the carriages' travel of 0 to "
            f"{', '.join(f'{e:.0f}' for e in kd.endstop_height)} mm (+-{SAVED_MARGIN:g} mm), got "
            f"{', '.join(f'{t:.4g}' for t in travel)} mm"))
    return steps


def klipper_recording(
    cfg: KlipperConfig, kd: KlipperDelta, *, sigma_height: float = SIGMA_HEIGHT, sigma_distance: float = SIGMA_DISTANCE,
) -> ConstraintRecording:
    """The saved ``[delta_calibrate]`` measurements as a constraint recording.

    Rows: ``manual_height<i>`` and ``height<i>`` (probe heights: nozzle z at the
    stable position ``..._pos``), then ``distance<i>`` (between ``_pos1`` and
    ``_pos2``), in Klipper's order.  Aux channel ``klipper_index`` is ``i``;
    with manual heights, ``klipper_manual`` is 1 on their rows (Klipper's
    weight of heights against distances counts the probed ones only).

    Raises
    ------
    KlipperConfigError
        When the config has no saved calibration (``[delta_calibrate]
        height0``) or fewer than 3 probed heights (DELTA_CALIBRATE probes at
        least 3 points), when the saved entries are not complete and consecutive
        (:func:`saved_counts`), or a value is not finite or out of range:
        heights within ``minimum_z_position`` and the highest
        ``position_endstop`` (+- :data:`SAVED_MARGIN`), distances up to the
        print diameter (+ the margin), stable positions within the travel.
    """
    from ..limits import sigma_problem

    for flag, v in (("sigma_height (--sigma-height)", sigma_height), ("sigma_distance (--sigma-distance)", sigma_distance)):
        # 1e300 was written into the recording, which every consumer then refused
        if (problem := sigma_problem(v, "position")) is not None:
            raise InputError(f"{flag}: {problem}")
    if not cfg.has(_SAVED):
        raise cfg.error(_SAVED, "", "missing section; expected the [delta_calibrate] block SAVE_CONFIG writes after "
                                    f"DELTA_CALIBRATE ({cfg.sources_note()})")
    counts = saved_counts(cfg)
    if not counts["height"] and not counts["manual_height"]:
        raise cfg.error(_SAVED, "height0", (
            "missing; the config holds no saved calibration (run DELTA_CALIBRATE and SAVE_CONFIG, which store "
            f"height0, height0_pos, ... in the SAVE_CONFIG block at the end of printer.cfg; {cfg.sources_note()})"))
    if counts["height"] < _MIN_PROBED:
        n = counts["height"]
        raise cfg.error_near(_SAVED, f"height{n}", f"height{n - 1}" if n else "manual_height0", (
            f"missing; DELTA_CALIBRATE probes at least {_MIN_PROBED} points and SAVE_CONFIG stores each as "
            f"height<N> and height<N>_pos, N = 0, 1, 2, ...; this block holds {n}"))
    z_lo, z_hi = kd.minimum_z - SAVED_MARGIN, float(kd.position_endstop.max()) + SAVED_MARGIN
    d_hi = 2.0 * max(kd.print_radius, kd.delta_radius) + SAVED_MARGIN
    measure, qa, qb, value, sig, idx, manual = [], [], [], [], [], [], []
    nan3 = [np.nan] * 3
    for kind in ("manual_height", "height", "distance"):
        for i in range(counts[kind]):
            key = f"{kind}{i}"
            if kind == "distance":
                value.append(cfg.getfloat(_SAVED, key, above=0.0, hi=d_hi))
                qa.append(_stable(cfg, kd, f"{key}_pos1"))
                qb.append(_stable(cfg, kd, f"{key}_pos2"))
            else:
                value.append(cfg.getfloat(_SAVED, key, lo=z_lo, hi=z_hi))
                qa.append(_stable(cfg, kd, f"{key}_pos"))
                qb.append(nan3)
            measure.append("distance" if kind == "distance" else "height")
            sig.append(sigma_distance if kind == "distance" else sigma_height)
            idx.append(i)
            manual.append(float(kind == "manual_height"))
    dist = np.array([m == "distance" for m in measure])
    qb_mm = np.where(dist[:, None], kd.carriage_q(np.where(dist[:, None], qb, 0.0)), np.nan)
    aux = {"klipper_index": np.array(idx, dtype=float)}
    if counts["manual_height"]:
        aux["klipper_manual"] = np.array(manual)
    return ConstraintRecording(
        measure=tuple(measure), qa=kd.carriage_q(qa), qb=qb_mm, value=np.array(value),
        sigma=np.array(sig), aux=aux, path=cfg.path,
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
