"""Convert the real TIAGo motion-capture recording (figaroh-examples, Apache-2.0) to bayescal's files (docs/formats.md).

Source: ``../shared/data/real/tiago/`` (``qualysis_base_hand_calibration.csv``,
``tiago_config.yaml``, ``tiago_unified_config.yaml``, ``LICENSE``), copied
byte-for-byte from thanhndv212/figaroh-examples at commit
``c0b5c7f0fda10078be55104f9ee76ac106b7a5ee`` (``examples/tiago/``), and the
full Apache-2.0 text (``../positioner/LICENSE``).  The two TIAGo URDFs there
are CC BY-NC-ND 3.0 (PAL Robotics) and are **not** read: the nominal chain
is written from the parameter table of the data set's README (the kinematic
parameters of ``tiago_48_schunk.urdf``, the URDF FIGAROH's ``calibration.py``
loads, :data:`CHAIN`), as ``[[joint]]`` tables.

Writes ``examples/tiago/``:

* ``machine.toml``: ``kind = "serial"``, ``base_footprint`` to
  ``wrist_ft_tool_link``: the prismatic torso lift and the seven arm joints
  (fixed joints folded into the next moving joint, as bayescal folds a
  URDF's), the tool point at ``wrist_ft_tool_link``'s origin (the marker's
  position on the hand is unknown: its tolerance is 1 m);
* ``recording.csv``: ``q1`` (torso lift, mm), ``q2 .. q8`` (``arm_1_joint`` ..
  ``arm_7_joint``, rad), ``x, y, z`` (point 1 of the hand's rigid body, mm, in
  the motion-capture frame), rows in the source's order (its line numbers);
* ``source/``: the CSV and the two configs that describe it, byte for byte;
* ``README.md`` (attribution, conversion, what is known), ``LICENSE`` (the
  FIGAROH notice) and ``LICENSE-Apache-2.0.txt`` (the licence's text).

Usage::

    python studies/convert_tiago.py [--source DIR] [--out DIR]
"""

from __future__ import annotations

import argparse
import csv
import io
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
SHARED = next(
    (p / "shared" / "data" / "real" for p in (ROOT.parent, ROOT.parent.parent) if (p / "shared").is_dir()),
    ROOT.parent / "shared" / "data" / "real",
)
SOURCE = SHARED / "tiago"
OUT = ROOT / "examples" / "tiago"
COMMIT = "c0b5c7f0fda10078be55104f9ee76ac106b7a5ee"
REPO = "https://github.com/thanhndv212/figaroh-examples"
CSV_NAME = "qualysis_base_hand_calibration.csv"
CONFIGS = ("tiago_config.yaml", "tiago_unified_config.yaml")
#: Git blob ids of the bundled source files (the data set's README), checked by the tests.
BLOBS = {
    CSV_NAME: "35c01cc9820ef66f3297278616dd851ad0f6c2eb",
    "tiago_config.yaml": "4dc4e5cbf8cba3eb9b74bbb09bebbbdac73a8691",
    "tiago_unified_config.yaml": "c14356915130e67d1883bc042e4a7628e3236fe8",
    "LICENSE": "5f6320dbbea5167bc77e1798aa52e7df3f574522",
}
HALF_PI = np.pi / 2

#: The chain from ``base_footprint`` to ``wrist_ft_tool_link`` (the data set's README table, with the values in which
#: ``tiago_48_schunk.urdf`` differs from ``tiago.urdf``: arm_2 y = 0.0195, arm_3 z = -0.0015, and arm_5's rpy written
#: (pi/2, -pi/2, -pi/2), the same rotation as (0, -pi/2, 0)).  Per joint: name, type, URDF ``origin`` xyz (m), rpy
#: (rad), limits (m or rad; None for a fixed joint).  Every axis is local z.  The rpy are written to the machine file
#: as given: at a pitch of -pi/2 (arm_4, arm_5, arm_6) roll and yaw turn about one axis, and how a rotation is split
#: between them decides what the ``rpy`` error parameters perturb, so the split is kept as the URDF states it.
CHAIN = (
    ("base_footprint_joint", "fixed", (0.0, 0.0, 0.0985), (0.0, 0.0, 0.0), None),
    ("torso_fixed_joint", "fixed", (-0.062, 0.0, 0.193), (0.0, 0.0, 0.0), None),
    ("torso_lift_joint", "prismatic", (0.0, 0.0, 0.597), (0.0, 0.0, 0.0), (0.0, 0.35)),
    ("arm_1_joint", "revolute", (0.15505, 0.014, -0.151), (0.0, 0.0, -HALF_PI), (0.0, 2.74889357189)),
    ("arm_2_joint", "revolute", (0.125, 0.0195, -0.031), (HALF_PI, 0.0, 0.0), (-HALF_PI, 1.0908307825)),
    ("arm_3_joint", "revolute", (0.0895, 0.0, -0.0015), (-HALF_PI, 0.0, HALF_PI), (-3.53429173529, HALF_PI)),
    ("arm_4_joint", "revolute", (-0.02, -0.027, -0.222), (-HALF_PI, -HALF_PI, 0.0), (-0.392699081699, 2.35619449019)),
    ("arm_5_joint", "revolute", (-0.162, 0.02, 0.027), (HALF_PI, -HALF_PI, -HALF_PI), (-2.09439510239, 2.09439510239)),
    ("arm_6_joint", "revolute", (0.0, 0.0, 0.15), (0.0, -HALF_PI, -HALF_PI), (-1.41371669412, 1.41371669412)),
    ("arm_7_joint", "revolute", (0.0, 0.0, 0.0), (HALF_PI, 0.0, HALF_PI), (-2.09439510239, 2.09439510239)),
    ("arm_tool_joint", "fixed", (0.0, 0.0, 0.046), (HALF_PI, -HALF_PI, np.pi), None),
    ("wrist_ft_joint", "fixed", (0.00785, 0.0, 0.0), (HALF_PI, 0.0, HALF_PI), None),
    ("wrist_tool_joint", "fixed", (0.0, 0.0, 0.012725), (-HALF_PI, -HALF_PI, 0.0), None),
)
JOINTS = tuple(name for name, kind, *_ in CHAIN if kind != "fixed")
M_TO_MM = 1000.0
#: The recorded torso reaches 350.18 mm, past the URDF's 350 mm limit (an encoder reading beyond the soft limit):
#: the recording is the truth, so ``q_limits`` are the URDF's widened by 1 mm (torso) and 0.01 rad (arm).
WIDEN = (1.0, 0.01)
#: Nominal tolerances of the arm's geometry (one sigma; mm, rad): a few tenths of a degree and a millimetre or two
#: for a cast and machined arm.  The tool point (the virtual mocap point on the hand) is unknown: 1 m.
TOLERANCE = {"origin": 2.0, "rpy": 0.005, "axis": 0.005, "offset_angle": 0.005, "offset_length": 2.0,
             "tool_point": 1000.0, "tool_rpy": 1.0}
#: Position noise of the machine file (mm).  Not a specification: upstream quotes a median rigid-body point noise of
#: 0.2 mm for later, rebuilt sessions; this file's floor is its timing defect and the arm (README).
SIGMA_POSITION = 1.0


def transform(xyz, rpy) -> np.ndarray:
    """URDF ``origin``: ``Trans(xyz) Rot(rpy)``, ``Rot = Rz(y) Ry(p) Rx(r)`` (fixed axes x, y, z), 4x4, in m."""
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("xyz", rpy).as_matrix()
    T[:3, 3] = xyz
    return T


def folded_chain() -> tuple[list[tuple[str, str, np.ndarray, np.ndarray]], np.ndarray]:
    """The moving joints (name, type, 4x4 in m, rpy) with the fixed joints before each folded in, and the fixed tail.

    A moving joint keeps the table's rpy when no fixed joint before it turns (here: every one; the fixed joints
    before the torso only translate), else the rpy of the folded rotation.
    """
    joints, pending = [], np.eye(4)
    for name, kind, xyz, rpy, _ in CHAIN:
        T = pending @ transform(xyz, rpy)
        if kind == "fixed":
            pending = T
            continue
        turned = not np.array_equal(pending[:3, :3], np.eye(3))
        joints.append((name, kind, T, rpy_from_matrix(T[:3, :3]) if turned else np.asarray(rpy, dtype=float)))
        pending = np.eye(4)
    return joints, pending


def forward(q: np.ndarray) -> np.ndarray:
    """``wrist_ft_tool_link`` in ``base_footprint`` (4x4, mm) at actuator rows ``q`` (torso mm, arm rad).

    Written with 4x4 products and scipy's rotations, not bayescal's serial kinematics: the independent
    forward kinematics of the tests and of the study's registration baseline.
    """
    q = np.atleast_2d(np.asarray(q, dtype=float))
    out = np.empty((q.shape[0], 4, 4))
    for n, qi in enumerate(q):
        T = np.eye(4)
        for name, kind, xyz, rpy, _ in CHAIN:
            T = T @ transform(xyz, rpy)
            if kind == "prismatic":
                T = T @ transform((0.0, 0.0, qi[JOINTS.index(name)] / M_TO_MM), (0.0, 0.0, 0.0))
            elif kind == "revolute":
                T = T @ transform((0.0, 0.0, 0.0), (0.0, 0.0, qi[JOINTS.index(name)]))
        T[:3, 3] *= M_TO_MM
        out[n] = T
    return out


def _limits() -> np.ndarray:
    lim = []
    for name, kind, *_, li in CHAIN:
        if kind == "prismatic":
            lim.append([li[0] * M_TO_MM - WIDEN[0], li[1] * M_TO_MM + WIDEN[0]])
        elif kind == "revolute":
            lim.append([li[0] - WIDEN[1], li[1] + WIDEN[1]])
    return np.array(lim)


def _clean(v: np.ndarray, *, angle: bool = False) -> np.ndarray:
    """Round-off of the 4x4 products set to the numbers the table gives, so the file reads as written by hand.

    Lengths (mm) to 1e-9 mm (the table's metres have at most 6 decimals: 155.04999999999998 is 155.05);
    angles within 1e-12 rad of a multiple of pi/2 to that multiple; -0.0 to 0.0.
    """
    v = np.asarray(v, dtype=float)
    if angle:
        k = np.round(v / HALF_PI)
        v = np.where(np.abs(v - k * HALF_PI) < 1e-12, k * HALF_PI, v)
    else:
        v = np.round(v, 9)
    return v + 0.0


def machine_text() -> str:
    f = lambda v: format_toml_value(_clean(v))  # noqa: E731
    fa = lambda v: format_toml_value(_clean(v, angle=True))  # noqa: E731
    joints, tail = folded_chain()
    out = [
        "# PAL TIAGo: prismatic torso lift and 7-R arm, base_footprint to wrist_ft_tool_link, converted by",
        "# studies/convert_tiago.py from the kinematic parameters of tiago_48_schunk.urdf as tabled in the data set's",
        "# README (the URDF itself, CC BY-NC-ND 3.0, is not used or copied); see README.md.  Fixed joints are folded",
        "# into the next moving joint; the tool point is wrist_ft_tool_link's origin, since the motion-capture point",
        "# on the hand is unknown (tolerance 1 m).",
        'kind = "serial"',
        'name = "PAL TIAGo, torso + 7R arm (figaroh mocap set)"',
        "",
    ]
    for name, kind, T, rpy in joints:
        out += [
            "[[joint]]",
            f'name = "{name}"',
            f'type = "{kind}"',
            f"origin = {f(T[:3, 3] * M_TO_MM)}",
            f"rpy = {fa(rpy)}",
            "axis = [0.0, 0.0, 1.0]",
            "",
        ]
    out += [
        "[tool]                         # wrist_ft_tool_link's origin, in arm_7_link's frame (the fixed joints after arm_7)",
        f"point = {f(tail[:3, 3] * M_TO_MM)}",
        f"rpy = {fa(rpy_from_matrix(tail[:3, :3]))}",
        "",
        "[measurement]                  # not a specification: the floor the README describes (timing defect, arm)",
        f"sigma_position = {SIGMA_POSITION}",
        "sigma_angle = 0.001",
        "",
        "[workspace]                    # the URDF's limits, widened by 1 mm / 0.01 rad (the torso reads 350.18 mm)",
        f"q_limits = {format_toml_value(_limits())}",
        "",
        "[tolerance]                    # a cast and machined arm; the marker's position on the hand is unknown",
        *(f"{k} = {v}" for k, v in TOLERANCE.items()),
        "",
    ]
    return "\n".join(out)


def recording_text(source_csv: str) -> str:
    """``q1..q8, x, y, z`` (mm, rad) from the source's named columns, rows in the source's order."""
    rows = list(csv.DictReader(io.StringIO(source_csv)))
    lines = [",".join([f"q{i + 1}" for i in range(len(JOINTS))] + ["x", "y", "z"])]
    for row in rows:
        q = [float(row[j]) for j in JOINTS]
        q[0] *= M_TO_MM  # torso lift, m -> mm
        p = [M_TO_MM * float(row[c]) for c in ("x1", "y1", "z1")]
        lines.append(",".join(repr(v) for v in q + p))
    return "\n".join(lines) + "\n"


README = f"""# Real recording: PAL TIAGo arm, motion capture

34 static postures of a PAL Robotics TIAGo mobile manipulator (prismatic torso
lift and a 7-R arm), each with the eight joint positions read from the robot
and a point on the hand measured by a Qualisys motion-capture system, in a
frame fixed to the robot's base: a real position-only (3-DOF) recording with
an unknown instrument frame and an unknown tool point.

## Source and license

* Repository: {REPO}
* Commit: `{COMMIT}`
* Files (in `source/`, byte for byte):
  `examples/tiago/data/calibration/mocap/{CSV_NAME}` (git blob `{BLOBS[CSV_NAME]}`),
  `examples/tiago/config/tiago_config.yaml` (git blob `{BLOBS['tiago_config.yaml']}`: the legacy
  config whose `data_file` is this CSV) and `examples/tiago/config/tiago_unified_config.yaml`
  (git blob `{BLOBS['tiago_unified_config.yaml']}`: the config FIGAROH's `calibration.py` uses at this
  commit; its default task reads this CSV).
* License: Apache License 2.0. figaroh-examples has no LICENSE file; its `README.md` says it is
  "licensed under the same terms as the main FIGAROH package", and `examples/tiago/README.md`
  says "Licensed under the Apache License, Version 2.0". [LICENSE](LICENSE) is the notice of
  FIGAROH (thanhndv212/figaroh-plus @ `c3b5172849b744984b7181fd9d517c83fb4242e1`, git blob
  `{BLOBS['LICENSE']}`: Copyright 2021-2025 Thanh Nguyen, 2022-2023 CNRS, Toward SAS);
  [LICENSE-Apache-2.0.txt](LICENSE-Apache-2.0.txt) is the licence's text.
* **Not included**: the TIAGo URDFs of the same repository (`tiago.urdf`,
  `tiago_48_schunk.urdf`) are Copyright PAL Robotics, S.L., under Creative Commons
  Attribution-NonCommercial-NoDerivs 3.0, which does not allow them here. The machine file
  below is written from the table of the chain's kinematic parameters (joint origins, rotations,
  axes and limits), not from the URDF file.
* `machine.toml` and `recording.csv` are derived from these files by `studies/convert_tiago.py`
  (units and representation changed as described below; no measured value changed).

## Files

* `machine.toml`: `kind = "serial"` from `base_footprint` to `wrist_ft_tool_link` (the
  calibration task's `base_frame: universe` and `tool_frame` of the configs), mm and rad:
  `torso_lift_joint` (prismatic, q1 in mm) and `arm_1_joint` ... `arm_7_joint` (revolute, q2-q8
  in rad), every axis local z, with the parameters of `tiago_48_schunk.urdf` (the URDF
  `calibration.py` loads; it differs from `tiago.urdf` in arm_2's origin y, 19.5 mm against
  16.5 mm, and arm_3's origin z, -1.5 mm against +1.5 mm, and writes arm_5's rotation as
  rpy (pi/2, -pi/2, -pi/2) instead of (0, -pi/2, 0); the rpy are kept as written, since at a
  pitch of -pi/2 how a rotation is split between roll and yaw decides what the `rpy` error
  parameters perturb). The fixed joints before the torso
  lift (`base_footprint_joint`, `torso_fixed_joint`) are folded into its origin, and the fixed
  joints after arm_7 (`arm_tool_joint`, `wrist_ft_joint`, `wrist_tool_joint`) into the tool, as
  bayescal folds a URDF: `[tool] point` is `wrist_ft_tool_link`'s origin in `arm_7_link`'s frame.
  The measured point is somewhere on the hand: its tolerance is 1 m (unknown), the geometry's
  2 mm and 0.005 rad (a cast and machined arm; bayescal's choice, not the source's).
  `[workspace] q_limits` are the URDF's joint limits widened by 1 mm and 0.01 rad (the torso
  reads 350.18 mm, past its 350 mm limit). `[measurement]` 1 mm is not a specification (see
  below).
* `recording.csv`: `q1` (`torso_lift_joint` times 1000, mm), `q2` ... `q8` (`arm_1_joint` ...
  `arm_7_joint`, rad), `x, y, z` (point 1 of the hand's rigid body, `x1, y1, z1` times 1000,
  mm), one row per posture in the source's order, so that a line of this file is the same line
  of the source. FIGAROH uses this one point; points 2 and 3 are virtual points of the same
  tracked rigid body (their distances to point 1 are constant to print precision) and point 4
  repeats point 3, so they are left out.

## What to know before using it

* **The recording is in the motion-capture frame**, fixed to the robot's base but not its
  `base_footprint`: identify with `--frame fit` (the frame and the unknown tool point are
  registered together from the closed-form start).
* **Upstream declared this file superseded** after the snapshot: joints and markers were paired
  by raw timestamp with a 3.9 s mocap clock offset uncorrected, so 16 of the 34 rows were sampled
  after the arm had started moving, with errors up to 7.8 mm (worst: the source's row 29,
  0-based; line 31 here). It is a small demonstration set, not one for accuracy claims. Upstream
  later published four rebuilt, clock-corrected sessions with frozen training / validation /
  confirmation roles (not included).
* Registration only (the nominal chain, the frame and the tool point fitted) leaves 3.96 mm RMS,
  max 7.95 mm on line 31; fitting the geometry as well brings the in-sample RMS below 3 mm
  (upstream's full fit: 2.71 mm). `tests/studies/test_convert_tiago.py` and
  `tests/studies/test_real_recordings.py` check these numbers; `docs/real-recordings.md` has the
  study.

Regenerate with `python studies/convert_tiago.py` (reads `../shared/data/real/tiago/`).
"""


def convert(source: Path, out: Path, *, apache_text: Path | None = None) -> None:
    """Read the source folder and write the example folder (``out/source`` may be ``source`` itself)."""
    source_csv = (source / CSV_NAME).read_text(encoding="utf-8")
    out.mkdir(parents=True, exist_ok=True)
    write_text_atomic(out / "machine.toml", machine_text())
    write_text_atomic(out / "recording.csv", recording_text(source_csv))
    write_text_atomic(out / "README.md", README)
    keep = out / "source"
    if keep.resolve() != source.resolve():
        keep.mkdir(exist_ok=True)
        for name in (CSV_NAME, *CONFIGS):
            shutil.copyfile(source / name, keep / name)
    licence = source / "LICENSE" if (source / "LICENSE").is_file() else source.parent / "LICENSE"
    if licence.resolve() != (out / "LICENSE").resolve():
        shutil.copyfile(licence, out / "LICENSE")
    apache_text = apache_text or source.parent / "positioner" / "LICENSE"
    if apache_text.resolve() != (out / "LICENSE-Apache-2.0.txt").resolve():
        shutil.copyfile(apache_text, out / "LICENSE-Apache-2.0.txt")


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--source", type=Path, default=SOURCE, help="the shared TIAGo data directory")
    p.add_argument("--out", type=Path, default=OUT, help="example directory to write")
    args = p.parse_args(argv)
    convert(args.source, args.out)
    print(f"wrote {args.out}/machine.toml, recording.csv, README.md, LICENSE, LICENSE-Apache-2.0.txt, source/")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
