"""Convert the real two-axis positioner recording (industrial_calibration, Apache-2.0) to bayescal's files (docs/formats.md).

Source: ``../shared/data/real/positioner/`` (``measurements.yaml``,
``pose_initial_guesses.yaml``, ``LICENSE``, ``nominal.md``), copied
byte-for-byte from ros-industrial/industrial_calibration at commit
``fe62b7c9b7b347ee047a6fee6f417cd8427b2836``, ``examples/data/kinematic_calibration/``.

Writes ``examples/positioner/``:

* ``machine.toml``: ``kind = "serial"``, the source's nominal model
  (``createTwoAxisPositioner()``: classical DH rows ``[d, theta, r, alpha]``,
  ``T = Tz(d) Rz(theta + q) Tx(r) Rx(alpha)``, after
  ``base_offset = Trans(2.2, 0, 1.6) Rx(pi/2)``) as URDF joints in mm, with the
  source's initial guess of the target mount as the tool frame;
* ``recording.csv``: ``q1, q2`` (rad), the measured target pose in the sensor
  frame (``x, y, z`` mm, ``rx, ry, rz`` rotation vector), and the source keys;
* ``source/``: ``measurements.yaml`` and ``pose_initial_guesses.yaml`` byte
  for byte (the independent baselines of ``studies/positioner_source.py`` and
  the tests read them there, so they run on a fresh clone);
* ``README.md`` (attribution, conversion, what is known) and ``LICENSE``.

DH to URDF: a DH row is ``Tz(d_i) Rz(theta_i) Rz(q_i) Tx(r_i) Rx(alpha_i)``.  The
joint turns about z after ``Tz(d_i)``; ``Rz(theta_i)`` commutes with ``Rz(q_i)`` and
is moved after the joint, so that URDF joint ``i`` has the fixed transform
``Rz(theta_{i-1}) Tx(r_{i-1}) Rx(alpha_{i-1}) Tz(d_i)`` (``base_offset`` for
``i = 1``) and axis z, and the tool gets ``Rz(theta_n) Tx(r_n) Rx(alpha_n)``
followed by the target mount.  Keeping ``theta_2 = -pi/2`` before the joint would
put that joint's rpy at gimbal lock (pitch -pi/2), where roll and yaw errors
coincide.

Usage::

    python studies/convert_positioner.py [--source DIR] [--out DIR]
"""

from __future__ import annotations

import argparse
import shutil
import sys
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bayescal.io.answers import write_text_atomic  # noqa: E402
from bayescal.io.machine_file import format_toml_value  # noqa: E402
from bayescal.machines.serial import rpy_from_matrix  # noqa: E402

# the checkout sits beside shared/ (<clone>/../shared); a git worktree one level deeper
SOURCE = next(
    (p / "shared" / "data" / "real" / "positioner" for p in (ROOT.parent, ROOT.parent.parent) if (p / "shared").is_dir()),
    ROOT.parent / "shared" / "data" / "real" / "positioner",
)
OUT = ROOT / "examples" / "positioner"
COMMIT = "fe62b7c9b7b347ee047a6fee6f417cd8427b2836"
REPO = "https://github.com/ros-industrial/industrial_calibration"
SOURCE_PATH = "examples/data/kinematic_calibration"
#: The source files bundled in ``examples/positioner/source/`` and their git blob ids (the shared data set's README).
SOURCE_FILES = ("measurements.yaml", "pose_initial_guesses.yaml")
BLOBS = {"measurements.yaml": "eb9fc9cf0e2377c8b2fc0a85db4466ed3f13236a",
         "pose_initial_guesses.yaml": "41ee6fdce4d63ebc2f9bc6f0fae9725a2d82b911"}

#: ``createTwoAxisPositioner()``: DH rows [d (m), theta (rad), r (m), alpha (rad)], both revolute.
DH = np.array([[0.0, 0.0, 0.0, -np.pi / 2], [-0.475, -np.pi / 2, 0.0, 0.0]])
#: Joint limits of the source (rad).
LIMITS = [[-np.pi, np.pi], [-2 * np.pi, 2 * np.pi]]
M_TO_MM = 1000.0


def homogeneous(R=np.eye(3), p=(0.0, 0.0, 0.0)) -> np.ndarray:
    """4x4 transform from a rotation and a translation."""
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, p
    return T


def rot(axis: str, a: float) -> np.ndarray:
    return homogeneous(Rotation.from_euler(axis, a).as_matrix())


def trans(axis: str, s: float) -> np.ndarray:
    p = np.zeros(3)
    p["xyz".index(axis)] = s
    return homogeneous(p=p)


def base_offset() -> np.ndarray:
    """``Trans(2.2, 0, 1.6) Rx(pi/2)`` (m): the positioner's base in the world frame."""
    return homogeneous(p=(2.2, 0.0, 1.6)) @ rot("x", np.pi / 2)


def pose_to_matrix(p: dict) -> np.ndarray:
    """``Translation(x, y, z) Quaternion(qw, qx, qy, qz)`` (Eigen, Hamilton, scalar first), metres."""
    q = [p["qx"], p["qy"], p["qz"], p["qw"]]  # scipy: scalar last
    return homogeneous(Rotation.from_quat(q).as_matrix(), (p["x"], p["y"], p["z"]))


def urdf_chain(target_mount: np.ndarray) -> tuple[list[np.ndarray], np.ndarray]:
    """The fixed transforms of the two URDF joints and of the tool (m), from the DH rows."""
    fixed = []
    before = base_offset()
    for d, theta, r, alpha in DH:
        fixed.append(before @ trans("z", d))
        before = rot("z", theta) @ trans("x", r) @ rot("x", alpha)  # carried past the joint rotation
    return fixed, before @ target_mount


def _clean(v: np.ndarray) -> np.ndarray:
    """Round-off of the 4x4 products (1e-13 mm, -0.0) set to exact zeros, so the file reads as written by hand."""
    v = np.where(np.abs(v) < 1e-9, 0.0, v)
    return v + 0.0


def machine_text(target_mount: np.ndarray) -> str:
    f = lambda v: format_toml_value(_clean(np.asarray(v, dtype=float)))  # noqa: E731
    fixed, tool = urdf_chain(target_mount)
    out = [
        "# Two-axis part positioner (tilt j1, turntable j2) of the industrial_calibration example,",
        "# converted by studies/convert_positioner.py from its classical DH model (createTwoAxisPositioner,",
        "# base_offset = Trans(2.2, 0, 1.6) m Rx(pi/2)); see README.md.  Base frame = the source's world frame.",
        "# The tool frame is the measured target; its mounting is the source's initial guess",
        "# (target_mount_to_target_guess), not a measured value.",
        'kind = "serial"',
        'name = "two-axis positioner (industrial_calibration example)"',
        "",
    ]
    for i, T in enumerate(fixed):
        out += [
            f"[[joint]]                      # j{i + 1}: {'tilt' if i == 0 else 'turntable'}",
            'type = "revolute"',
            f"origin = {f(T[:3, 3] * M_TO_MM)}",
            f"rpy = {f(rpy_from_matrix(T[:3, :3]))}",
            "axis = [0.0, 0.0, 1.0]",
            "",
        ]
    out += [
        "[tool]",
        f"point = {f(tool[:3, 3] * M_TO_MM)}",
        f"rpy = {f(rpy_from_matrix(tool[:3, :3]))}",
        "",
        "[measurement]                  # noise floor of the sensor seen in nominal.md's residual analysis, not a sensor specification",
        "sigma_position = 0.5",
        "sigma_angle = 0.0009",
        "",
        "[workspace]                    # the source's joint limits",
        f"q_limits = {format_toml_value(np.array(LIMITS))}",
        "",
        "[tolerance]                    # the source's prior on DH offsets (0.005 m / rad); the target mount is unknown:",
        "                               # its nominal is the source's rough guess, so 1 m / 1 rad leave it effectively free",
        "origin = 5.0",
        "rpy = 0.005",
        "axis = 0.005",
        "offset_angle = 0.005",
        "offset_length = 5.0",
        "tool_point = 1000.0",
        "tool_rpy = 1.0",
        "",
    ]
    return "\n".join(out)


def recording_text(measurements: dict) -> str:
    keys = sorted(measurements, key=int)
    t0 = int(keys[0])
    lines = ["q1,q2,x,y,z,rx,ry,rz,source_key,time_s"]
    for k in keys:
        m = measurements[k]
        T = pose_to_matrix(m["pose"])
        rv = Rotation.from_matrix(T[:3, :3]).as_rotvec()
        q = m["target_joints"]
        vals = [float(q[0]), float(q[1]), *(T[:3, 3] * M_TO_MM), *rv]
        lines.append(",".join(repr(float(v)) for v in vals) + f",{int(k)},{int(k) - t0}")
    return "\n".join(lines) + "\n"


README = f"""# Real recording: two-axis part positioner

A two-axis (tilt + turntable) part positioner measured by a fixed metrology
sensor that reports the full 6-DOF pose of a target on the turntable: 205 poses,
13 tilt angles from -30 to +30 degrees times 16 turntable angles (less 3).

## Source and license

* Repository: {REPO}
* Commit: `{COMMIT}`
* Files: `{SOURCE_PATH}/measurements.yaml` (git blob `eb9fc9cf0e2377c8b2fc0a85db4466ed3f13236a`)
  and `{SOURCE_PATH}/pose_initial_guesses.yaml` (git blob `41ee6fdce4d63ebc2f9bc6f0fae9725a2d82b911`);
  nominal model from `examples/kinematic_calibration.cpp` (`createTwoAxisPositioner()`).
* License: Apache License 2.0, copied in [LICENSE](LICENSE) from the same commit.
  The two YAML files are in `source/`, byte for byte; `machine.toml` and `recording.csv`
  are derived from them by `studies/convert_positioner.py` (units and representation
  changed as described below; no measured value changed).

## Files

* `machine.toml`: `kind = "serial"`, two revolute joints with URDF semantics, mm and rad.
  The source's DH rows `[d, theta, r, alpha]` (`T = Tz(d) Rz(theta + q) Tx(r) Rx(alpha)`)
  after `base_offset = Trans(2.2, 0, 1.6) m Rx(pi/2)` are written as URDF joints:
  joint i's fixed transform is `Rz(theta_(i-1)) Tx(r_(i-1)) Rx(alpha_(i-1)) Tz(d_i)` (the
  base offset for i = 1), the axis is z, and the tool frame is
  `Rz(theta_2) Tx(r_2) Rx(alpha_2)` times the source's initial guess of the target mount
  (`target_mount_to_target_guess`; its quaternion, given to 6 digits, has norm 1 - 1.1e-7 and
  is normalised). `Rz(theta_i)` commutes with the joint rotation, so
  the chain is the same; moving it avoids a gimbal-locked rpy on joint 2.
  `[tolerance]` follows the source's prior on the DH offsets (0.005 m and 0.005 rad); the
  target mount gets tolerances of 1 m and 1 rad, which leave it effectively free (its nominal is
  only the source's rough guess: 18 mm and 0.18 rad from the mount a converged fit finds, so the
  earlier 50 mm / 0.1 rad would have pulled MAP towards a wrong mount).
  `[measurement]` (0.5 mm, 0.9 mrad) is the residual floor found in the data set's
  description (`nominal.md`), not a specification of the (unnamed) sensor.
* `recording.csv`: `q1, q2` (rad, `target_joints`), `x, y, z` (mm, the measured
  `camera_to_target` translation times 1000), `rx, ry, rz` (rotation vector of its
  quaternion, scalar first in the source; the measured quaternions are unit to 2e-16), `source_key` (the YAML key) and `time_s`
  (key minus the first key: the keys look like Unix seconds, 30 s apart, but the
  source does not say so). Rows are in the order of the keys, which is the order the
  positioner visited the poses.

## What to know before using it

* **The recording is in the sensor's frame**, not in the machine's base frame: the
  sensor pose in the world (`camera_mount_to_camera`) is unknown; the source's initial
  guess is `x 2.2, y 0.7, z 1.075` m with identity rotation. Fit the frame
  (`--frame fit`) together with the geometry.
* The target mount (tool frame) is a rough guess: after fitting only a rigid frame
  (Kabsch, positions), the nominal machine leaves about 12 mm mean position error.
  After fitting the sensor frame and the target mount (12 parameters, positions weighted
  by 0.5 mm and angles by 0.9 mrad), the nominal DH chain explains the recording to a
  mean position error of 0.42 mm (max 1.1 mm) and 0.82 mrad, the source's "static DH"
  case (0.45 mm, 0.81 mrad in `nominal.md` with the source's weighting), and the sensor
  sits at (2203.8, 585.5, 1007.6) mm in the world frame, rotation vector (-0.0032, 0.0032,
  -0.0108) rad (as `[instrument]` `origin` and `rotation_vector`), as `nominal.md` found.
  `tests/studies/test_convert_positioner.py` checks these numbers.
* Source results: calibrated DH mean position error 1.74 mm, static DH 3.82 mm
  (2020, Ceres); a tightly converged solve of the same cost reaches about 0.46 mm with
  almost no gain from the DH parameters (see `nominal.md` of the shared data set).
  The j1 `d` and `theta` offsets are exactly unidentifiable when the frame is fitted.

Regenerate with `python studies/convert_positioner.py`.
"""


def convert(source: Path, out: Path) -> None:
    """Read the source YAML files and write the example directory (``out/source`` may be ``source`` itself)."""
    import yaml  # PyYAML: only this one-off conversion needs it

    measurements = yaml.safe_load((source / "measurements.yaml").read_text())
    guesses = yaml.safe_load((source / "pose_initial_guesses.yaml").read_text())
    mount = pose_to_matrix(guesses["target_mount_to_target_guess"])
    out.mkdir(parents=True, exist_ok=True)
    write_text_atomic(out / "machine.toml", machine_text(mount))
    write_text_atomic(out / "recording.csv", recording_text(measurements))
    write_text_atomic(out / "README.md", README)
    keep = out / "source"
    if keep.resolve() != source.resolve():
        keep.mkdir(exist_ok=True)
        for name in SOURCE_FILES:
            shutil.copyfile(source / name, keep / name)
    licence = source / "LICENSE" if (source / "LICENSE").is_file() else source.parent / "LICENSE"
    if licence.resolve() != (out / "LICENSE").resolve():
        shutil.copyfile(licence, out / "LICENSE")


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--source", type=Path, default=SOURCE, help="the shared positioner data directory")
    p.add_argument("--out", type=Path, default=OUT, help="example directory to write")
    args = p.parse_args(argv)
    convert(args.source, args.out)
    print(f"wrote {args.out}/machine.toml, recording.csv, README.md, LICENSE, source/")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
