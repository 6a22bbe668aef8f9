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
    from bayescal.machines import load_machine

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


@pytest.mark.parametrize("base", [False, True])
def test_sensor_rows_jacobian_matches_finite_differences(tmp_path, base):
    m = _machine(tmp_path)
    q = poses(9, 3)
    rng = np.random.default_rng(4)
    aux, tool = _readings(JOINTS, q, [1, 2], [np.eye(3), Rotation.from_rotvec([0.1, 0.5, -0.3]).as_matrix()])
    if base:
        for i, a in enumerate("xyz"):
            aux[f"accel.base.{a}"] = rng.normal(size=9) * 0.01 + (9.81 if a == "z" else 0.0)
    model = MeasurementModel.from_recording(m, Recording(q=q, position=tool, aux=aux))
    assert model.machine.layout.names[-2].startswith("sensor.base.mount" if base else "gravity.tilt")
    th = rng.normal(size=model.n_params) * model.machine.tolerance * 3
    pred = model.predict(th)
    J = model.jacobian(th, pred)
    h = 1e-6
    for p in range(model.n_params):
        d = np.zeros(model.n_params)
        d[p] = h
        fd = (model.predict(th + d).y[:, 3:] - model.predict(th - d).y[:, 3:]) / (2 * h)
        np.testing.assert_allclose(J[:, 3:, p], fd, atol=1e-7, err_msg=model.machine.layout.names[p])


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
