"""Two simulated sessions of the telescopic-column machine, as a real set-up delivers them (docs/real-setup.md).

``examples/telescope/machine.toml`` (a two-stage telescopic column with a
turning arm and a belt-coupled wrist: mimic joints) is measured by a total
station that was moved once during each session (column ``station``), with
every fourth row held out (``role = check``) and a tilt sensor on the mobile
base (``accel.base.x/y/z``, m/s^2 as an accelerometer reads it, with noise).

The physics that the kinematic model leaves out is written here from first
principles, not with bayescal's effect code: the column is a cantilever
whose free length is its extension ``L = 2 q1 + 350 mm`` (two stages), loaded
at its top by the arm and payload (``m = 12 kg``, centre of mass ``r`` along
the arm), so it bends under

* the moment of the load's offset, ``M = m g r``: tip deflection
  ``M L^2 / (2 E I)`` and tip rotation ``M L / (E I)``, towards the arm;
* the lateral part of gravity when the base is tilted, ``F = m g sin(tilt)``:
  tip deflection ``F L^3 / (3 E I)``, rotation ``F L^2 / (2 E I)``, downhill,

with ``E I = 2.0e11 N mm^2`` (a steel tube), which moves the tool by up to
about 0.15 mm, thirty times the instrument noise.  The tool point then follows the tip's rotation
over its height above the tip.  The true geometry is drawn from the machine
file's tolerances (seeded).  The files are simulated, and say so in their
first comment of the README; they are examples, not real recordings.

    python studies/make_telescope_sessions.py        # writes examples/telescope/session_{a,b}.csv
"""

from __future__ import annotations

import argparse
from dataclasses import replace
from pathlib import Path

import numpy as np

from bayescal.geometry import so3_exp
from bayescal.io.recording import Recording, write_recording
from bayescal.machines.files import load_machine
from bayescal.machines.framed import Frame
from bayescal.simulate import draw_errors, draw_poses

ROOT = Path(__file__).resolve().parents[1]
FOLDER = ROOT / "examples" / "telescope"
G = 9.81  # m/s^2
MASS_KG, COM_MM, EI = 12.0, 250.0, 2.0e11  # load at the column top, its offset along the arm; N mm^2 (a steel tube)
#: the column-tip inclinometer of session b: mounted 3 and 2 mrad off the upper stage's axes, 1e-5 rad per axis
TIP_MOUNT = so3_exp(np.array([0.003, -0.002, 0.0]))
TIP_NOISE = 1.0e-5


def _bending(q, tilt_xy):
    """The column's free length (mm), the arm's direction, downhill per unit g, and the tip's slope (rad), per pose."""
    L = 2.0 * q[:, 0] + 350.0  # free length of the column, mm
    arm = np.column_stack([np.cos(q[:, 1]), np.sin(q[:, 1]), np.zeros(len(q))])  # the arm's direction
    g_lat = np.column_stack([np.sin(tilt_xy[:, 1]), -np.sin(tilt_xy[:, 0]), np.zeros(len(q))])  # downhill, per unit g
    F_moment = MASS_KG * G * COM_MM  # N mm
    slope = (F_moment * L / EI)[:, None] * arm + (MASS_KG * G * L**2 / (2 * EI))[:, None] * g_lat
    return L, arm, g_lat, slope


def bent_tool(machine, theta, q, tilt_xy):
    """True tool points (mm): the rigid machine, then the column's bending written above."""
    poses = machine.forward(q, theta)
    p = poses.position.copy()
    L, arm, g_lat, slope = _bending(q, tilt_xy)
    F_moment = MASS_KG * G * COM_MM  # N mm
    defl = (F_moment * L**2 / (2 * EI))[:, None] * arm + (MASS_KG * G * L**3 / (3 * EI))[:, None] * g_lat
    top = np.column_stack([np.zeros(len(q)), np.zeros(len(q)), L + 20.0])  # the arm's pivot, base frame
    rot = tip_rotation(q, tilt_xy)
    return defl + top + np.einsum("nij,nj->ni", rot, p - top), rot @ poses.rotation


def tip_rotation(q, tilt_xy):
    """The column tip's rotation (n, 3, 3), base frame: the slope about the axis perpendicular to it; the tool
    and everything else above the tip turn with it."""
    slope = _bending(q, tilt_xy)[3]
    return so3_exp(np.cross(np.array([0.0, 0.0, 1.0]), slope))


def tip_readings(machine, theta, q, tilt_xy, up, rng) -> np.ndarray:
    """The column-tip inclinometer's readings (m/s^2): up (base frame, unit) in the upper stage's frame, its
    rigid orientation (the true geometry) turned by the tip's bending, read through the sensor's mounting."""
    R_rigid, _ = machine.body_rotations(q, theta, [machine.body_frame("joint2")])
    R_tip = tip_rotation(q, tilt_xy) @ R_rigid[:, 0]
    u = np.einsum("ji,nkj,nk->ni", TIP_MOUNT, R_tip, up)  # mount^T R_tip^T up
    return G * (u + rng.normal(scale=TIP_NOISE, size=u.shape))


def session(seed: int, n: int, frames: dict[str, Frame], theta, tip: bool = False) -> Recording:
    machine = load_machine(FOLDER / "machine.toml")
    rng = np.random.default_rng([2026, 29, seed])
    q = draw_poses(machine, n, rng, theta)
    tilt = rng.normal(scale=np.radians(1.0), size=(n, 2))  # the mobile base, about x and y
    p, _ = bent_tool(machine, theta, q, tilt)
    p = p + rng.normal(scale=machine.noise.sigma_position, size=p.shape)
    # the base accelerometer reads -g in the (tilted) base frame, with 0.02 m/s^2 noise (session b: 1e-5 g)
    acc = np.column_stack([-G * np.sin(tilt[:, 1]), G * np.sin(tilt[:, 0]), G * np.cos(tilt[:, 0]) * np.cos(tilt[:, 1])])
    # session b's base carries a precision inclinometer like its column tip (1e-5 rad), session a's an accelerometer
    acc = acc + rng.normal(scale=G * TIP_NOISE if tip else 0.02, size=acc.shape)
    labels = list(frames)
    st = np.where(q[:, 1] < 0, labels[0], labels[1])  # each station sees one side of the arm's sweep
    for k, f in frames.items():
        s = st == k
        p[s] = f.to_instrument(p[s])
    role = np.where(np.arange(n) % 4 == 3, "check", "fit")
    aux = {"accel.base.x": acc[:, 0], "accel.base.y": acc[:, 1], "accel.base.z": acc[:, 2]}
    if tip:  # drawn last: the other columns are those of the session without the tip sensor
        up = np.column_stack([-np.sin(tilt[:, 1]), np.sin(tilt[:, 0]), np.cos(tilt[:, 0]) * np.cos(tilt[:, 1])])
        up /= np.linalg.norm(up, axis=1, keepdims=True)
        t = tip_readings(machine, theta, q, tilt, up, rng)
        aux.update({"accel.joint2.x": t[:, 0], "accel.joint2.y": t[:, 1], "accel.joint2.z": t[:, 2]})
    return Recording(q=q, position=p, aux=aux, station=tuple(st), role=tuple(role))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", default=str(FOLDER))
    args = ap.parse_args(argv)
    machine = load_machine(FOLDER / "machine.toml")
    theta = draw_errors(machine, np.random.default_rng([2026, 29]))
    out = Path(args.out)
    a = session(1, 240, {"north": Frame.from_rotation_vector([1500.0, -800.0, -400.0], [0.0, 0.0, 0.7]),
                         "south": Frame.from_rotation_vector([-1200.0, 900.0, -380.0], [0.01, -0.02, 2.6])}, theta)
    b = session(2, 120, {"east": Frame.from_rotation_vector([900.0, 1400.0, -420.0], [0.0, 0.01, -1.2]),
                         "west": Frame.from_rotation_vector([-1600.0, -300.0, -410.0], [-0.01, 0.0, 1.9])}, theta,
                tip=True)
    for name, rec in (("session_a.csv", a), ("session_b.csv", b)):
        path = write_recording(out / name, replace(rec, path=str(out / name)))
        print(f"wrote {path} ({rec.n_poses} poses, stations {', '.join(rec.stations)})")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
