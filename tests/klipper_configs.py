"""Synthetic Klipper configs for the reader's tests: a delta printer as Klipper would leave it after
DELTA_CALIBRATE, a bed mesh and the other calibrations, SAVE_CONFIG, with includes and comments.

The saved stable positions are computed here from Klipper's documented inverse kinematics (carriage
height ``h_i = z + sqrt(L_i^2 - (x - X_i)^2 - (y - Y_i)^2)``, ``s_i = (E_i - h_i) / step_dist_i``,
``E_i = position_endstop_i + sqrt(L_i^2 - R^2)``), independently of bayescal's code, and written as
Klipper writes them (``%.3f``)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from bayescal.klipper.cfg import AUTOSAVE_HEADER

R = 100.123456
ANGLES = np.array([210.1, 329.8, 90.0])
ARMS = np.array([215.0, 215.5, 214.8])
ENDSTOPS = np.array([250.0, 250.5, 249.7])
STEP = 0.0125  # every stepper, reached three ways (plain, gear ratio, full steps)
Z_OFFSET = 1.234
#: The nozzle point of the one manual height (DELTA_ANALYZE MANUAL_HEIGHT).
MANUAL = np.array([10.0, -5.0, 0.5])


def probe_points(radius: float = 80.0) -> np.ndarray:
    """Klipper's DELTA_CALIBRATE pattern: the centre and six points at 90 + 60 k degrees."""
    scatter = [0.95, 0.90, 0.85, 0.70, 0.75, 0.80]
    pts = [(0.0, 0.0)] + [(radius * s * np.cos(np.radians(90 + 60 * k)), radius * s * np.sin(np.radians(90 + 60 * k)))
                          for k, s in enumerate(scatter)]
    return np.array([[x, y, Z_OFFSET + 0.01 * k] for k, (x, y) in enumerate(pts)])


def distance_pairs() -> tuple[np.ndarray, np.ndarray]:
    """Six pairs of nozzle points on the bed (z = 0), as on a printed calibration object."""
    ang = np.radians([210.0, 270.0, 330.0, 30.0, 90.0, 150.0])
    a = np.column_stack([4.5 * np.cos(ang), 4.5 * np.sin(ang), np.zeros(6)])
    r = 60.0 + 2.0 * np.arange(6)
    b = np.column_stack([r * np.cos(ang), r * np.sin(ang), np.zeros(6)])
    return a, b


def stable(points: np.ndarray) -> np.ndarray:
    """Klipper's stable positions (microsteps below each endstop) of nozzle points, closed form."""
    tx, ty = R * np.cos(np.radians(ANGLES)), R * np.sin(np.radians(ANGLES))
    E = ENDSTOPS + np.sqrt(ARMS**2 - R**2)
    h = points[:, 2:3] + np.sqrt(ARMS**2 - (points[:, :1] - tx) ** 2 - (points[:, 1:2] - ty) ** 2)
    return (E - h) / STEP


def _pos(s) -> str:
    return "%.3f,%.3f,%.3f" % tuple(s)


def calibration_block() -> list[str]:
    """The [printer], [stepper_*] and [delta_calibrate] sections DELTA_CALIBRATE saves (without '#*# ')."""
    out = ["[printer]", f"delta_radius = {R:.6f}", ""]
    for k, ab in enumerate("abc"):
        out += [f"[stepper_{ab}]", f"angle = {ANGLES[k]:.6f}", f"arm_length = {ARMS[k]:.6f}",
                f"position_endstop = {ENDSTOPS[k]:.6f}", ""]
    out += ["[delta_calibrate]", f"manual_height0 = {float(MANUAL[2])!r}",
            f"manual_height0_pos = {_pos(stable(MANUAL[None])[0])}"]
    pts = probe_points()
    for i, (p, s) in enumerate(zip(pts, stable(pts))):
        out += [f"height{i} = {float(p[2])!r}", f"height{i}_pos = {_pos(s)}"]
    a, b = distance_pairs()
    for i, (sa, sb, d) in enumerate(zip(stable(a), stable(b), np.linalg.norm(b - a, axis=1))):
        out += [f"distance{i} = {round(float(d), 3)!r}", f"distance{i}_pos1 = {_pos(sa)}", f"distance{i}_pos2 = {_pos(sb)}"]
    return out


OTHER_SAVED = """\
[bed_mesh default]
version = 1
points =
\t  0.012500, -0.025000, 0.000000
\t  0.050000, 0.037500, -0.012500
\t  -0.005000, 0.000000, 0.022500
x_count = 3
y_count = 3
mesh_x_pps = 2
mesh_y_pps = 2
algo = lagrange
tension = 0.2
min_x = -60.0
max_x = 60.0
min_y = -60.0
max_y = 60.0

[bed_mesh hot]
version = 1
points =
\t  0.1, 0.2
\t  0.3, 0.4
x_count = 2
y_count = 2

[probe]
z_offset = 1.234

[input_shaper]
shaper_type_x = mzv
shaper_freq_x = 52.4
shaper_type_y = ei
shaper_freq_y = 48.0

[extruder]
control = pid
pid_kp = 22.200
pid_ki = 1.080
pid_kd = 114.000

[endstop_phase stepper_a]
trigger_phase = 23/64

[skew_correction my_skew]
xy_skew = 0.0012
xz_skew = 0.0
yz_skew = 0.0

[axis_twist_compensation]
z_compensations = 0.010000, -0.020000, 0.010000
compensation_start_x = -60.0
compensation_end_x = 60.0

[bed_tilt]
x_adjust = 0.000100
y_adjust = -0.000200
z_adjust = 0.010000

[temperature_probe my_probe]
calibration_temp = 40.000000
drift_calibration =
\t1.0, 2.0, 3.0
\t4.0, 5.0, 6.0
drift_calibration_min_temp = 30.0

[probe_eddy_current eddy]
reg_drive_current = 15
calibrate =
\t0.050000:3300000.000,0.100000:3290000.000,0.150000:3280000.000,
\t0.200000:3270000.000
tap_z_offset = 0.050

[angle my_angle]
calibrate =
\t1.0,2.0,3.0,4.0,5.0,6.0,7.0,8.0,
\t9.0,10.0
"""

MAIN = """\
# A delta printer's printer.cfg, as a user keeps it
; semicolon comment line
[include macros/*.cfg]
[include steppers.cfg]   ; the steppers, in their own file

[printer]
kinematics: delta   # inline hash comment
max_velocity: 300 ; inline semicolon comment
max_accel: 3000
#delta_radius: 105  (commented out by SAVE_CONFIG)
print_radius: 90
minimum_z_position: -5

[delta_calibrate]
radius: 80
horizontal_move_z: 10

[bed_mesh]
mesh_radius: 75
round_probe_count: 5

[probe]
pin: PA11
#z_offset: 1.0

[gcode_macro START_PRINT]
gcode:
    G28
    G1 Z10 F3000 ; move up
    {% if params.T %}
      M104 S{params.T}
    {% endif %}
"""

STEPPERS = """\
[include more/tmc.cfg]
[stepper_a]
step_pin: PE3
microsteps: 16
rotation_distance: 40
endstop_pin: PA15
homing_speed: 50

[stepper_b]
step_pin: PE0
microsteps: 16
rotation_distance: 160
gear_ratio: 80:20
endstop_pin: PA12

[stepper_c]
step_pin: PB5
microsteps: 8
full_steps_per_rotation: 400
rotation_distance: 40
endstop_pin: PC4
"""


def saved_block(lines: list[str]) -> str:
    """Lines as Klipper's SAVE_CONFIG writes them: the header, then '#*# ' before each (bare '#*#' when empty)."""
    return "\n" + AUTOSAVE_HEADER + "\n".join(("#*# " + line).strip() for line in lines) + "\n"


def write_config(folder: Path, *, block: list[str] | None = None, main: str = MAIN) -> Path:
    """A printer.cfg with includes (a glob, a nested include) and a full SAVE_CONFIG block; its path."""
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "macros").mkdir(exist_ok=True)
    (folder / "more").mkdir(exist_ok=True)
    (folder / "macros" / "a.cfg").write_text("[gcode_macro A]\ngcode:\n  M117 a\n")
    (folder / "macros" / "b.cfg").write_text("[gcode_macro B]\ngcode:\n  M117 b  # comment\n")
    (folder / "steppers.cfg").write_text(STEPPERS)
    (folder / "more" / "tmc.cfg").write_text("[tmc2209 stepper_a]\nuart_pin: PC11\nrun_current: 0.8\n")
    lines = OTHER_SAVED.splitlines() + [""] + (calibration_block() if block is None else block)
    path = folder / "printer.cfg"
    path.write_text(main + saved_block(lines))
    return path
