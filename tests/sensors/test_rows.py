"""Body tilt sensors as rows: predicted readings against an independent chain, the Jacobian against finite differences."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from bayescal.io.recording import Recording
from bayescal.machines.serial import Serial
from bayescal.measurement import MeasurementModel
from bayescal.sensors import SensorMounts

from .chain import JOINTS, machine_text, poses, transforms

TRUTH = (
    ("revolute", [0.3, -0.2, 200.0], [2e-4, -1e-4, 0.0], [3e-4, -2e-4, 1.0]),
    ("prismatic", [0.0, 0.1, 300.0], [1e-4, 0.0, 0.0], [0.0, 1e-4, 1.0]),
    ("revolute", [100.0, 0.0, 50.0], [0.3, 2e-4, 0.0], [1e-4, 1.0, 0.0]),
)


def _machine(tmp_path, joints=JOINTS, **kw):
    from bayescal.machines.files import load_machine

    p = tmp_path / "m.toml"
    p.write_text(machine_text(joints, **kw))
    return load_machine(p)


def _readings(joints, q, bodies, mounts, base_up=None):
    """Unit readings (specific force, up) of sensors on ``bodies`` (joint indices) with mountings ``mounts`` (sensor to body)."""
    frames, tool = transforms(joints, q)
    n = q.shape[0]
    up = np.broadcast_to([0.0, 0.0, 1.0], (n, 3)) if base_up is None else base_up
    aux = {}
    for k, Rs in zip(bodies, mounts):
        Rb = np.array([f[k][:3, :3] for f in frames])
        u = np.einsum("ji,nkj,nk->ni", Rs, Rb, up)  # Rs^T Rb^T up
        for i, a in enumerate("xyz"):
            aux[f"accel.joint{k + 1}.{a}"] = 9.81 * u[:, i]
    return aux, tool


def test_body_rotations_match_an_independent_chain(tmp_path):
    m = _machine(tmp_path, TRUTH)
    q = poses(7, 1)
    frames, tool = transforms(TRUTH, q)
    R, _ = m.body_rotations(q, None, [m.body_frame(f"joint{k + 1}") for k in range(3)])
    for k in range(3):
        np.testing.assert_allclose(R[:, k], np.array([f[k][:3, :3] for f in frames]), atol=1e-12)
    np.testing.assert_allclose(m.forward(q).position, tool, atol=1e-9)


@pytest.mark.parametrize("mimic", [False, True])
def test_body_rotations_per_actuator_match_the_independent_chain(tmp_path, mimic):
    # d R_body / d q (what an effect's dq does to a sensor's body) against central differences of the
    # independent 4x4 chain; with a mimic, joint 3 turns by 0.5 q1 + 0.1 and has no actuator of its own
    text = machine_text(TRUTH)
    if mimic:
        text = text.replace('axis = [0.0001, 1.0, 0.0]', 'axis = [0.0001, 1.0, 0.0]\nmimic = 1\nmultiplier = 0.5\noffset = 0.1')
        text = text.replace("q_limits = [[-3.0, 3.0], [0.0, 500.0], [-1.0, 1.0]]", "q_limits = [[-3.0, 3.0], [0.0, 500.0]]")
    path = tmp_path / "m.toml"
    path.write_text(text)
    from bayescal.machines.files import load_machine

    m = load_machine(path)
    assert m.n_actuators == (2 if mimic else 3)
    q = poses(6, 3)[:, : m.n_actuators]
    J = m.body_actuator_jacobian(q, None, [m.body_frame(f"joint{k + 1}") for k in range(3)])

    def bodies(qa):
        qj = np.column_stack([qa, 0.5 * qa[:, 0] + 0.1]) if mimic else qa
        frames, _ = transforms(TRUTH, qj)
        return np.array([[f[k][:3, :3] for k in range(3)] for f in frames])

    h = 1e-6
    for i in range(m.n_actuators):
        e = np.zeros(m.n_actuators)
        e[i] = h
        Rp, Rm = bodies(q + e), bodies(q - e)
        fd = np.array([[Rotation.from_matrix(a @ b.T).as_rotvec() / (2 * h) for a, b in zip(rp, rm)] for rp, rm in zip(Rp, Rm)])
        np.testing.assert_allclose(J[..., i], fd, atol=1e-7)
    assert np.abs(J[:, 2, :, 0]).max() > 0.5  # joint 3's body turns with q1 (and by 1.5 q1 with the mimic)


def test_noise_free_readings_give_zero_rows_at_the_truth(tmp_path):
    """Readings from the independent chain: the model at the truth (sensor parameters at their start) reproduces them."""
    m = _machine(tmp_path, TRUTH)
    q = poses(25, 2)
    arm_mount = Rotation.from_rotvec([0.4, -1.2, 2.0]).as_matrix()  # any orientation: the arm turns, Wahba fixes it
    aux, tool = _readings(TRUTH, q, [1, 2], [np.eye(3), arm_mount])
    model = MeasurementModel.from_recording(m, Recording(q=q, position=tool, aux=aux))
    assert isinstance(model.machine, SensorMounts) and model.tool_dof == 3 and model.dof == 7
    assert model.sensors.turn == (False, True)
    names = model.machine.layout.names[-7:]
    assert names[:2] == ("sensor.joint2.mount.rx", "sensor.joint2.mount.ry")
    assert all(x.startswith("sensor.joint3.mount.r") for x in names[2:5]) and len(set(names[2:5])) == 3
    assert names[5:] == ("gravity.tilt.rx", "gravity.tilt.ry")
    r = model.residual(model.predict(None))
    np.testing.assert_allclose(r[:, :3], 0.0, atol=1e-8)
    np.testing.assert_allclose(r[:, 3:], 0.0, atol=1e-9)
    assert model.rms(r)["tilt"] < 1e-9


@pytest.mark.parametrize("base, dof", [(False, 3), (True, 3), (False, 6), (True, 5)])
def test_sensor_rows_jacobian_matches_finite_differences(tmp_path, base, dof):
    m = _machine(tmp_path)
    q = poses(9, 3)
    rng = np.random.default_rng(4)
    aux, tool = _readings(JOINTS, q, [1, 2], [np.eye(3), Rotation.from_rotvec([0.1, 0.5, -0.3]).as_matrix()])
    if base:
        for i, a in enumerate("xyz"):
            aux[f"accel.base.{a}"] = rng.normal(size=9) * 0.01 + (9.81 if a == "z" else 0.0)
    rotvec = None if dof == 3 else Rotation.from_matrix(m.forward(q).rotation).as_rotvec()
    model = MeasurementModel.from_recording(m, Recording(q=q, position=tool, rotvec=rotvec, aux=aux), dof=dof)
    assert model.tool_dof == dof and model.dof == dof + 4
    assert model.machine.layout.names[-2].startswith("sensor.base.mount" if base else "gravity.tilt")
    th = rng.normal(size=model.n_params) * model.machine.tolerance * 3
    pred = model.predict(th)
    J = model.jacobian(th, pred)
    h = 1e-6
    for p in range(model.n_params):
        d = np.zeros(model.n_params)
        d[p] = h
        fd = (model.predict(th + d).y - model.predict(th - d).y) / (2 * h)
        np.testing.assert_allclose(J[:, 3:, p], fd[:, 3:], atol=1e-7, err_msg=model.machine.layout.names[p])
        np.testing.assert_allclose(J[:, :3, p], fd[:, :3], atol=1e-5, err_msg=model.machine.layout.names[p])  # mm


def test_stacked_and_per_pose_theta_and_subsets(tmp_path):
    m = _machine(tmp_path)
    q = poses(6, 5)
    aux, tool = _readings(JOINTS, q, [1], [np.eye(3)])
    model = MeasurementModel.from_recording(m, Recording(q=q, position=tool, aux=aux))
    rng = np.random.default_rng(6)
    th = rng.normal(size=(2, model.n_params)) * model.machine.tolerance
    stacked = model.predict(np.repeat(th, 6, axis=0)).y
    np.testing.assert_allclose(stacked[:6], model.predict(th[0]).y, atol=1e-12)
    np.testing.assert_allclose(stacked[6:], model.predict(th[1]).y, atol=1e-12)
    sub = model.subset([1, 4])
    np.testing.assert_allclose(sub.predict(th[0]).y, model.predict(th[0]).y[[1, 4]], atol=1e-12)
    assert sub.row_sigma.shape == (2, 5) and sub.row_sigma[0, 3] == pytest.approx(2e-5)


def test_serial_lists_its_bodies_and_refuses_others(tmp_path):
    m = _machine(tmp_path)
    assert isinstance(m, Serial) and m.sensor_bodies == ("base", "joint1", "joint2", "joint3")
    with pytest.raises(Exception, match="joint4"):
        m.body_frame("joint4")


URDF = """<?xml version="1.0"?>
<robot name="column">
  <link name="floor"/><link name="pedestal"/><link name="column"/><link name="stage"/><link name="column_tip"/>
  <link name="arm"/>
  <joint name="bolt" type="fixed"><parent link="floor"/><child link="pedestal"/>
    <origin xyz="0 0 0.1" rpy="0.001 0 0.2"/></joint>
  <joint name="turn" type="revolute"><parent link="pedestal"/><child link="column"/>
    <origin xyz="0 0 0.2" rpy="0 0 0"/><axis xyz="0 0 1"/><limit lower="-3" upper="3" effort="1" velocity="1"/></joint>
  <joint name="lift" type="prismatic"><parent link="column"/><child link="stage"/>
    <origin xyz="0 0 0.3" rpy="0 0.002 0"/><axis xyz="0 0 1"/><limit lower="0" upper="0.5" effort="1" velocity="1"/></joint>
  <joint name="tip" type="fixed"><parent link="stage"/><child link="column_tip"/>
    <origin xyz="0 0 0.05" rpy="0.3 -0.2 1.0"/></joint>
  <joint name="swing" type="revolute"><parent link="column_tip"/><child link="arm"/>
    <origin xyz="0.1 0 0" rpy="0 0 0"/><axis xyz="0 1 0"/><limit lower="-1" upper="1" effort="1" velocity="1"/></joint>
</robot>
"""


def test_urdf_links_are_bodies_with_yourdfpy_orientations(tmp_path):
    """A sensor on a URDF link after fixed joints: its orientation is yourdfpy's transform (an independent chain)."""
    import yourdfpy

    from bayescal.machines.files import load_machine

    (tmp_path / "column.urdf").write_text(URDF)
    (tmp_path / "m.toml").write_text('kind = "serial"\nurdf = "column.urdf"\nbase_link = "floor"\ntip_link = "arm"\n\n'
                                     "[tool]\npoint = [100.0, 0.0, 0.0]\n")
    m = load_machine(tmp_path / "m.toml")
    assert m.sensor_bodies == ("base", "joint1", "joint2", "joint3", "floor", "pedestal", "column", "stage",
                               "column_tip", "arm")
    robot = yourdfpy.URDF.load(str(tmp_path / "column.urdf"), build_scene_graph=True, load_meshes=False)
    q = poses(5, 9)
    q[:, 1] = np.clip(q[:, 1], 0.0, 500.0)
    bodies = ["pedestal", "column", "column_tip", "joint2", "arm"]
    R, _ = m.body_rotations(q, None, [m.body_frame(b) for b in bodies])
    for i, qi in enumerate(q):
        robot.update_cfg({"turn": qi[0], "lift": qi[1] / 1000.0, "swing": qi[2]})
        for s, b in enumerate(bodies):
            link = "stage" if b == "joint2" else b
            np.testing.assert_allclose(R[i, s], robot.get_transform(link, "floor")[:3, :3], atol=1e-12, err_msg=b)


def test_readings_pointing_down_are_read_with_the_other_sign(tmp_path):
    """Sensors that report gravity (down) rather than the specific force: told by the base sensor, same rows."""
    m = _machine(tmp_path, TRUTH)
    q = poses(10, 8)
    aux, tool = _readings(TRUTH, q, [1, 2], [np.eye(3), Rotation.from_rotvec([0.3, 0.2, 0.1]).as_matrix()])
    rng = np.random.default_rng(9)
    for i, a in enumerate("xyz"):
        aux[f"accel.base.{a}"] = rng.normal(size=10) * 1e-3 + (9.81 if a == "z" else 0.0)
    up = MeasurementModel.from_recording(m, Recording(q=q, position=tool, aux=aux))
    down = MeasurementModel.from_recording(m, Recording(q=q, position=tool, aux={k: -v for k, v in aux.items()}))
    assert down.sensors.flipped and not up.sensors.flipped
    th = rng.normal(size=up.n_params) * up.machine.tolerance
    np.testing.assert_allclose(down.predict(th).y, up.predict(th).y, atol=1e-12)


@pytest.mark.parametrize("dof", [3, 6])
def test_sensor_rows_in_pose_blocks_are_the_whole_ones_bit_for_bit(tmp_path, monkeypatch, dof):
    # a large recording's Jacobian is computed in pose blocks (bayescal.measurement._FRESH_BYTES): the sensors'
    # rows of each block's sub-model must be the whole model's
    import bayescal.measurement as mod

    m = _machine(tmp_path)
    q = poses(23, 7)
    aux, tool = _readings(JOINTS, q, [1, 2], [np.eye(3), Rotation.from_rotvec([0.1, 0.5, -0.3]).as_matrix()])
    rotvec = None if dof == 3 else Rotation.from_matrix(m.forward(q).rotation).as_rotvec()
    model = MeasurementModel.from_recording(m, Recording(q=q, position=tool, rotvec=rotvec, aux=aux), dof=dof)
    th = np.random.default_rng(5).normal(size=model.n_params) * model.machine.tolerance * 3
    pred = model.predict(th)
    whole = model.jacobian(th, pred)
    monkeypatch.setattr(mod, "_ROWS_BLOCK", 5)
    monkeypatch.setattr(mod, "_FRESH_BYTES", 0)
    assert np.array_equal(model.jacobian(th, pred), whole)
