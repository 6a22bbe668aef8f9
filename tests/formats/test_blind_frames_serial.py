"""Blind run: instrument frames (docs/formats.md section 4), serial chains and hybrid machines (section 5).

Files written by ``handwritten.py``; truths from the spec's equations in numpy.
"""

from __future__ import annotations

import tomllib

import numpy as np
import pytest

from .blind import answer, check_identify_answer, diagnose_checked, identify_map, read_prs3, read_serial, run
from .handwritten import (
    Joint,
    Serial,
    draw_q,
    homogeneous,
    matrix_to_rotvec,
    pose_rows,
    positioner_nominal,
    prs3_nominal,
    prs3_perturbed,
    prs3_tool,
    prs3_tool_poses,
    prs3_toml,
    rotvec_to_matrix,
    rows_of,
    serial_perturbed,
    serial_toml,
    serial_transform,
    write_csv,
)

NOM = prs3_nominal()
TRUE = prs3_perturbed(NOM, 2)
Q = draw_q(NOM.q_limits, 40, 7)
PTS, ROTS = prs3_tool_poses(TRUE, Q)
# a tracker 2.5 m away, turned 30 degrees about a tilted axis
FRAME = (np.array([2500.0, -1200.0, 300.0]), np.array([0.1, -0.2, 0.5]))


def _tracker_recording(path, *, dof=6, crlf=False):
    cols = pose_rows(Q, PTS, ROTS, dof=dof, sigma=NOM.sigma_position, seed=8, frame=FRAME)
    header, rows = rows_of(cols)
    write_csv(path, header, rows, crlf=crlf)


@pytest.mark.parametrize("dof", [6, 3])
def test_frame_fit_recovers_the_tracker_pose(tmp_path, capsys, dof):
    (tmp_path / "m.toml").write_text(prs3_toml(NOM))
    _tracker_recording(tmp_path / "r.csv", dof=dof)
    # without --frame fit: refused or not plausible, with a message that suggests it
    rc, out, err = run(capsys, "identify", tmp_path / "r.csv", "--machine", tmp_path / "m.toml",
                       "--json", tmp_path / "base.json")
    assert rc in (1, 2) and "--frame fit" in out + err
    a = identify_map(capsys, tmp_path / "r.csv", tmp_path / "m.toml", tmp_path / "a.json", "--frame", "fit",
                     "--write-machine", tmp_path / "cal.toml")
    check_identify_answer(a, angle=dof == 6)
    fr = a["frame"]
    assert len(fr["origin"]) == 3 and len(fr["rotation_vector"]) == 3
    assert len(fr["std"]["origin"]) == 3 and len(fr["std"]["rotation_vector"]) == 3
    # --free auto holds the base parameters that share the frame's gauge at nominal, so the
    # frame is the true one only up to what the true base deviates (a few mm / mrad at 2.7 m)
    assert np.allclose(fr["origin"], FRAME[0], atol=5.0)
    assert np.allclose(fr["rotation_vector"], FRAME[1], atol=2e-3)
    assert a["rms_after"]["position"] < 2.5 * NOM.sigma_position
    # the calibrated machine carries [instrument]; its geometry is in the base frame
    d = tomllib.loads((tmp_path / "cal.toml").read_text())
    assert np.allclose(d["instrument"]["origin"], fr["origin"])
    assert np.allclose(d["instrument"]["rotation_vector"], fr["rotation_vector"])
    cal, _ = read_prs3(tmp_path / "cal.toml")
    r_inst = rotvec_to_matrix(d["instrument"]["rotation_vector"])
    q_test = draw_q(NOM.q_limits, 10, 71)
    # p_base = R p_instrument + origin: the calibrated machine plus its [instrument] predicts the tracker
    for q in q_test:
        p_true = prs3_tool(TRUE, q)[0]
        p_tracker = rotvec_to_matrix(FRAME[1]).T @ (p_true - FRAME[0])
        p_cal = r_inst.T @ (prs3_tool(cal, q)[0] - np.asarray(d["instrument"]["origin"]))
        assert np.linalg.norm(p_cal - p_tracker) < 0.03
    # --free all: the gauge is held by the tolerance prior, and the std covers the true frame
    identify_map(capsys, tmp_path / "r.csv", tmp_path / "m.toml", tmp_path / "all.json", "--frame", "fit", "--free",
                 "all")
    fr = answer(tmp_path / "all.json")["frame"]
    z = np.r_[(np.array(fr["origin"]) - FRAME[0]) / fr["std"]["origin"],
              (np.array(fr["rotation_vector"]) - FRAME[1]) / fr["std"]["rotation_vector"]]
    assert np.all(np.abs(z) < 4.0), z


def test_known_instrument_table_is_applied(tmp_path, capsys):
    """Section 4: [instrument] in the machine file, no --frame: the recording is in that frame."""
    (tmp_path / "m.toml").write_text(prs3_toml(NOM, instrument=FRAME))
    _tracker_recording(tmp_path / "r.csv", crlf=True)
    a = identify_map(capsys, tmp_path / "r.csv", tmp_path / "m.toml", tmp_path / "a.json")
    assert a["rms_after"]["position"] < 2.5 * NOM.sigma_position
    assert a["rms_before"]["position"] > 10 * NOM.sigma_position


def test_diagnose_frame_fit_on_a_clean_tracker_recording(tmp_path, capsys):
    (tmp_path / "m.toml").write_text(prs3_toml(NOM))
    _tracker_recording(tmp_path / "r.csv")
    a = diagnose_checked(capsys, tmp_path / "r.csv", tmp_path / "m.toml", tmp_path / "d.json", "--frame", "fit",
                         "--write-machine", tmp_path / "cal.toml")
    assert a["verdict"] == "none"
    assert np.allclose(a["frame"]["origin"], FRAME[0], atol=5.0)
    assert len(a["frame"]["std"]["rotation_vector"]) == 3
    assert "instrument" in tomllib.loads((tmp_path / "cal.toml").read_text())


# ---------------------------------------------------------------- serial


SER_NOM = positioner_nominal()
SER_TRUE = serial_perturbed(SER_NOM, 3)


@pytest.mark.parametrize("variant", ["plain", "shuffled", "tool_rpy"])
def test_serial_positioner(tmp_path, capsys, variant):
    nom, true = SER_NOM, SER_TRUE
    if variant == "tool_rpy":
        nom = Serial(nom.joints, nom.tool_point, (0.1, -0.2, 0.3), q_limits=nom.q_limits)
        true = Serial(true.joints, true.tool_point, (0.1004, -0.2003, 0.2996), q_limits=nom.q_limits)
    (tmp_path / "m.toml").write_text(serial_toml(nom, variant="shuffled" if variant == "shuffled" else "plain"))
    q = draw_q(nom.q_limits, 40, 11)
    t = np.array([serial_transform(true, qi) for qi in q])
    cols = pose_rows(q, t[:, :3, 3], t[:, :3, :3], dof=6, sigma=nom.sigma_position, seed=12)
    header, rows = rows_of(cols, ["x", "y", "z", "rx", "ry", "rz", "q3", "q2", "q1"])
    write_csv(tmp_path / "r.csv", header, rows, bom=True)
    a = identify_map(capsys, tmp_path / "r.csv", tmp_path / "m.toml", tmp_path / "a.json", "--write-machine",
                     tmp_path / "cal.toml")
    check_identify_answer(a)
    names = {p["name"] for p in a["parameters"]}
    assert {"joint1.offset", "joint2.origin.y", "joint3.rpy.r", "joint2.offset"} <= names | set(a.get("fixed", []))
    assert a["rms_after"]["position"] < 2.5 * nom.sigma_position
    cal, d = read_serial(tmp_path / "cal.toml")
    assert [j["type"] for j in d["joint"]] == ["prismatic", "revolute", "revolute"]
    q_test = draw_q(nom.q_limits, 10, 13)
    err_cal = max(np.linalg.norm(serial_transform(cal, qi)[:3, 3] - serial_transform(true, qi)[:3, 3]) for qi in q_test)
    err_nom = max(np.linalg.norm(serial_transform(nom, qi)[:3, 3] - serial_transform(true, qi)[:3, 3]) for qi in q_test)
    assert err_cal < 0.1 * err_nom
    if variant == "tool_rpy":
        r_cal = serial_transform(cal, q_test[0])[:3, :3]
        r_true = serial_transform(true, q_test[0])[:3, :3]
        assert np.linalg.norm(matrix_to_rotvec(r_cal.T @ r_true)) < 1e-4


# ---------------------------------------------------------------- hybrid


def _table(tool_point, true: bool) -> Serial:
    if true:
        j = Joint("revolute", (50.04, 29.97, -60.02), (3e-4, -2e-4, 0.0), (4e-4, -3e-4, 1.0))
    else:
        j = Joint("revolute", (50.0, 30.0, -60.0), (0.0, 0.0, 0.0), (0.0, 0.0, 1.0))
    tp = None if tool_point is None else tuple(np.asarray(tool_point) + (0.03 if true else 0.0))
    return Serial((j,), tp, None, name="rotary table", q_limits=((-3.0, 3.0),))


def _hybrid_pose(head, table, q):
    """Section 5: the tool (head on the base) relative to the table's last frame.

    bayescal reads "last frame" as the table module's tool frame; a table module without
    [tool] (tool_point None) has its last joint frame there, the other reading.
    """
    p, r = prs3_tool(head, q[:3])
    t_tool = homogeneous(r, p)
    t_table = serial_transform(table, q[3:])
    return np.linalg.inv(t_table) @ t_tool


@pytest.mark.parametrize("table_tool", [None, (10.0, -5.0, 20.0)])
def test_hybrid_head_over_rotary_table(tmp_path, capsys, table_tool):
    table_nom, table_true = _table(table_tool, False), _table(table_tool, True)
    (tmp_path / "modules").mkdir()
    (tmp_path / "modules" / "head.toml").write_text(prs3_toml(NOM, measurement=False))
    (tmp_path / "modules" / "table.toml").write_text(serial_toml(table_nom, measurement=False))
    (tmp_path / "m.toml").write_text(
        'kind = "hybrid"\nname = "head over table"\n\n'
        '[[module]]\nrole = "table"\nfile = "modules/table.toml"\n\n'
        '[[module]]\nfile = "modules/head.toml"\nrole = "tool"\n\n'
        "[measurement]\nsigma_position = 0.005\nsigma_angle = 5e-5\n"
    )
    # actuators are numbered through the modules in order: table first here (q1), head q2..q4
    qh = draw_q(NOM.q_limits, 40, 21)
    qt = draw_q(((-3.0, 3.0),), 40, 22)
    q = np.hstack([qt, qh])
    t = np.array([_hybrid_pose(TRUE, table_true, np.r_[qi[1:], qi[:1]]) for qi in q])
    cols = pose_rows(q, t[:, :3, 3], t[:, :3, :3], dof=6, sigma=0.005, seed=23)
    header, rows = rows_of(cols)
    write_csv(tmp_path / "r.csv", header, rows, crlf=True)
    a = identify_map(capsys, tmp_path / "r.csv", tmp_path / "m.toml", tmp_path / "a.json", "--write-machine",
                     tmp_path / "cal.toml")
    check_identify_answer(a)
    assert a["rms_after"]["position"] < 2.5 * 0.005 and a["rms_before"]["position"] > 0.05
    names = {p["name"] for p in a["parameters"]}
    assert any(n.startswith("m1.joint1.") for n in names) and any(n.startswith("m2.chain") for n in names)
    # the calibrated hybrid, read module by module with tomllib (section 5's file form),
    # predicts the true tool-on-table pose with the spec's kinematics alone
    d = tomllib.loads((tmp_path / "cal.toml").read_text())
    assert d["kind"] == "hybrid" and [m["role"] for m in d["module"]] == ["table", "tool"]
    table_cal, _ = read_serial(tmp_path / d["module"][0]["file"])
    head_cal, _ = read_prs3(tmp_path / d["module"][1]["file"])
    q_test = np.hstack([draw_q(((-3.0, 3.0),), 10, 24), draw_q(NOM.q_limits, 10, 25)])

    def worst(head, table):
        return max(np.linalg.norm(_hybrid_pose(head, table, np.r_[qi[1:], qi[:1]])[:3, 3]
                                  - _hybrid_pose(TRUE, table_true, np.r_[qi[1:], qi[:1]])[:3, 3]) for qi in q_test)

    assert worst(head_cal, table_cal) < 0.1 * worst(NOM, table_nom)



URDF = """<?xml version="1.0"?>
<robot name="positioner">
  <link name="world"/> <link name="base"/> <link name="lift"/> <link name="tilt"/> <link name="adapter"/>
  <link name="table"/> <link name="flange"/>
  <joint name="mount" type="fixed"><parent link="world"/><child link="base"/>
    <origin xyz="0 0 -1.0" rpy="0 0 0"/></joint>
  <joint name="j1" type="prismatic"><parent link="base"/><child link="lift"/>
    <origin xyz="0 0 0" rpy="0 0 0"/><axis xyz="0 0 1"/>
    <limit lower="0.0" upper="0.1" effort="100" velocity="0.1"/></joint>
  <joint name="j2" type="revolute"><parent link="lift"/><child link="tilt"/>
    <origin xyz="0 0 0.2" rpy="0 0 0"/><axis xyz="1 0 0"/>
    <limit lower="-1.2" upper="1.2" effort="100" velocity="1"/></joint>
  <joint name="spacer" type="fixed"><parent link="tilt"/><child link="adapter"/>
    <origin xyz="0 0 0.03" rpy="0 0 0"/></joint>
  <joint name="j3" type="revolute"><parent link="adapter"/><child link="table"/>
    <origin xyz="0 0 0.05" rpy="0 0 0"/><axis xyz="0 0 1"/>
    <limit lower="-3.0" upper="3.0" effort="100" velocity="1"/></joint>
  <joint name="plate" type="fixed"><parent link="table"/><child link="flange"/>
    <origin xyz="0 0 0.01" rpy="0 0 1.5707963267948966"/></joint>
</robot>
"""


def test_urdf_stands_in_for_the_joint_tables(tmp_path, capsys):
    """Section 5: urdf/base_link/tip_link; URDF's metres, fixed joints folded in, limits from the URDF."""
    (tmp_path / "robot.urdf").write_text(URDF)
    # tool given in tip_link's (flange) frame: flange = table frame moved 10 mm up and turned 90 deg about z
    tool_flange = np.array([30.0, -120.0, 40.0])
    (tmp_path / "m.toml").write_text(
        'kind = "serial"\nname = "positioner from URDF"\nurdf = "robot.urdf"\nbase_link = "base"\n'
        'tip_link = "flange"\n\n[tool]\npoint = [30.0, -120.0, 40.0]\n\n'
        "[measurement]\nsigma_position = 0.005\nsigma_angle = 5e-5\n"
    )
    r_plate = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    nom = SER_NOM
    true = Serial(SER_TRUE.joints, tuple(np.asarray(SER_TRUE.tool_point) - nom.tool_point
                                         + np.array([0, 0, 10.0]) + r_plate @ tool_flange),
                  None, q_limits=nom.q_limits)
    assert np.allclose(np.array([0, 0, 10.0]) + r_plate @ tool_flange, (120.0, 30.0, 50.0))
    q = draw_q(nom.q_limits, 40, 51)
    t = np.array([serial_transform(true, qi) for qi in q])
    cols = pose_rows(q, t[:, :3, 3], t[:, :3, :3], dof=3, sigma=0.005, seed=52)
    header, rows = rows_of(cols)
    write_csv(tmp_path / "r.csv", header, rows)
    a = identify_map(capsys, tmp_path / "r.csv", tmp_path / "m.toml", tmp_path / "a.json")
    check_identify_answer(a, angle=False)
    assert a["rms_after"]["position"] < 2.5 * 0.005 < 0.05 < a["rms_before"]["position"] < 1.0
