"""End to end: a simulated column with tilt sensors (readings from an independent chain), identified with and without them."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from bayescal.geometry import so3_exp, so3_log
from bayescal.identify.calibrate import calibrate
from bayescal.io.recording import Recording
from bayescal.machines.files import load_machine
from bayescal.measurement import MeasurementModel

from .chain import JOINTS, machine_text, poses, transforms

# the column's axis tilted (tilt_x = 2e-4, tilt_y = 3e-4 rad in the parameters' convention), the arm's frame turned
TRUTH = (
    ("revolute", [0.0, 0.0, 200.0], [0.0, 0.0, 0.0], [3e-4, -2e-4, 1.0]),
    ("prismatic", [0.0, 0.0, 300.0], [0.0, 0.0, 0.0], [0.0, 0.0, 1.0]),
    ("revolute", [100.0, 0.0, 50.0], [0.3 + 2e-4, 0.0, 0.0], [0.0, 1.0, 0.0]),
)
WOBBLE = ({"joint1.axis.tilt_x": 1.0, "joint1.rpy.r": 1.0}, {"joint1.axis.tilt_y": 1.0, "joint1.rpy.p": 1.0})
WOBBLE_TRUE = (2e-4, 3e-4)
COLUMN_MOUNT = Rotation.from_rotvec([0.004, -0.003, 0.0]).as_matrix()
ARM_MOUNT = Rotation.from_rotvec([0.2, 1.0, -0.5]).as_matrix()
N = 30


@pytest.fixture(scope="module")
def machine(tmp_path_factory):
    p = tmp_path_factory.mktemp("sensors") / "column.toml"
    p.write_text(machine_text(JOINTS, sigma_tilt=1e-5, sigma_position=0.05))
    return load_machine(p)


def _recording(seed: int, *, base_tilt: float = 0.0, base_sensor: bool = False, sensors: bool = True) -> Recording:
    """Tool points (noise 0.05 mm) and sensor readings (noise 1e-5 per axis) from the independent chain.

    ``base_tilt``: the machine's base is tilted by that much (rad, one sigma per axis) differently at every pose;
    a base sensor (axes along the base's) reads it.
    """
    rng = np.random.default_rng(seed)
    q = poses(N, seed)
    frames, tool = transforms(TRUTH, q)
    position = tool + rng.normal(size=tool.shape) * 0.05  # drawn first: the same tool data with and without sensors
    up = np.einsum("nij,j->ni", so3_exp(np.column_stack([rng.normal(size=(N, 2)) * base_tilt, np.zeros(N)])),
                   [0.0, 0.0, 1.0])
    aux = {}
    if sensors:
        for k, Rs in ((1, COLUMN_MOUNT), (2, ARM_MOUNT)):
            Rb = np.array([f[k][:3, :3] for f in frames])
            u = np.einsum("ji,nkj,nk->ni", Rs, Rb, up) + rng.normal(size=(N, 3)) * 1e-5  # Rs^T Rb^T up
            aux.update({f"accel.joint{k + 1}.{a}": 9.81 * u[:, i] for i, a in enumerate("xyz")})
    if base_sensor:
        ub = up + rng.normal(size=(N, 3)) * 1e-5
        aux.update({f"accel.base.{a}": 9.81 * ub[:, i] for i, a in enumerate("xyz")})
    return Recording(q=q, position=position, aux=aux)


def _fit(machine, rec, **kw):
    model = MeasurementModel.from_recording(machine, rec)
    return model, calibrate(model, method="map", prior_scale="tolerance", **kw).result


def _combo(res, combo):
    names, allnames = list(res.free_names), list(res.names)
    c = np.zeros(len(names))
    value = 0.0
    for n, w in combo.items():
        c[names.index(n)] = w
        value += w * res.theta[allnames.index(n)]
    return value, float(np.sqrt(c @ res.covariance @ c))


def test_sensors_narrow_what_they_see_and_keep_the_position_summaries(machine):
    _, with_s = _fit(machine, _recording(11))
    _, without = _fit(machine, _recording(11, sensors=False))
    for combo, truth in zip(WOBBLE, WOBBLE_TRUE):
        v1, s1 = _combo(with_s, combo)
        v0, s0 = _combo(without, combo)
        assert s1 < 0.75 * s0  # the column's tilt against gravity: the sensors see it directly
        assert abs(v1 - truth) < 3 * s1
    assert with_s.tool_dof == 3 and with_s.dof == 7 and with_s.tilt_rows == 4
    # the position summary is the tool's alone; the tilt residual is reported apart, in rad, near the sensors' noise
    assert with_s.rms_before["position"] == pytest.approx(without.rms_before["position"], rel=1e-12)
    assert with_s.rms_after["position"] < 1.5 * 0.05 * np.sqrt(3)
    assert with_s.rms_after["tilt"] < 3e-5 < with_s.rms_before["tilt"]
    assert "tilt" not in without.rms_after
    d = with_s.to_dict()
    assert d["dof"] == 3 and d["tilt_rows_per_pose"] == 4
    assert "3-DOF + 2 body sensors" in with_s.report() and "RMS tilt" in with_s.report()


def test_the_mounting_is_recovered_within_its_std(machine):
    model, res = _fit(machine, _recording(12))
    S = model.sensors
    assert S.turn == (False, True)
    # the column sensor's true mounting relative to its start, on its two tilt axes (it has no fitted turn)
    d_true = so3_log(S.R0[0].T @ COLUMN_MOUNT)
    names = list(res.names)
    for k, name in enumerate(("sensor.joint2.mount.rx", "sensor.joint2.mount.ry")):
        p = res.parameters[names.index(name)]
        assert abs(p.value - S.E[0][:, k] @ d_true) < 3 * p.std
    assert abs(S.E[0][:, 2] @ d_true) < 1e-5  # hardly anything about the reading: the start holds the turn


def test_a_base_sensor_gives_every_pose_its_own_up(machine):
    """A base tilted differently at every pose (1e-4 rad): with its base sensor the tilt rows fit to the noise."""
    model_b, with_base = _fit(machine, _recording(13, base_tilt=1e-4, base_sensor=True))
    assert model_b.machine.layout.names[-2:] == ("sensor.base.mount.rx", "sensor.base.mount.ry")
    assert model_b.sigma[3:] == pytest.approx([np.sqrt(2) * 1e-5] * 4)  # up is a reading too: its noise in every row
    assert with_base.rms_after["tilt"] < 3e-5
    rec = _recording(13, base_tilt=1e-4, base_sensor=False)
    _, blind = _fit(machine, rec, noise="stated", robust="off")  # a misfit: no noise rescaling, no outlier passes
    assert blind.rms_after["tilt"] > 2 * with_base.rms_after["tilt"]
    for combo, truth in zip(WOBBLE, WOBBLE_TRUE):
        v, s = _combo(with_base, combo)
        assert abs(v - truth) < 3 * s


def test_a_misstated_sigma_tilt_is_rescaled_on_its_own(tmp_path):
    # the machine file says 1e-6 rad, the sensors have 1e-5: the tilt rows alone contradict it, their sigma is
    # rescaled by itself (about 10x) and the tool rows keep the stated noise, so the geometry and its position
    # uncertainty come out as with sigma_tilt stated right
    p = tmp_path / "column.toml"
    p.write_text(machine_text(JOINTS, sigma_tilt=1e-6, sigma_position=0.05))
    wrong = load_machine(p)
    q = tmp_path / "right.toml"
    q.write_text(machine_text(JOINTS, sigma_tilt=1e-5, sigma_position=0.05))
    rec = _recording(11)
    model_w = MeasurementModel.from_recording(wrong, rec)
    cal_w = calibrate(model_w, method="map", prior_scale="tolerance")
    cal_r = calibrate(MeasurementModel.from_recording(load_machine(q), rec), method="map", prior_scale="tolerance")
    tilt = cal_w.result.extras["tilt_noise"]
    assert tilt["verdict"] == "understated" and 6 < tilt["scale_used"] < 15
    assert cal_r.result.extras["tilt_noise"]["scale_used"] == 1.0
    assert cal_w.noise_scale == 1.0 and "sigma_tilt used" in cal_w.noise_report()
    # the same geometry to a small part of its uncertainty
    free = cal_r.result.free
    assert np.array_equal(free, cal_w.result.free)
    d = np.abs(cal_w.result.theta - cal_r.result.theta)[free] / np.sqrt(np.diag(cal_r.result.covariance))
    assert np.max(d) < 0.3


def test_diagnose_rescales_a_misstated_sigma_tilt(tmp_path):
    from bayescal.diagnose.core import _sensor_noise
    from bayescal.models import model_from_recording

    p = tmp_path / "column.toml"
    p.write_text(machine_text(JOINTS, sigma_tilt=1e-6, sigma_position=0.05))
    wrong = load_machine(p)
    rec = _recording(11)
    m2, model2 = _sensor_noise(wrong, rec, model_from_recording(wrong, rec, check=False))
    assert 6e-6 < m2.noise.sigma_tilt < 1.5e-5 and m2.noise.sigma_position == wrong.noise.sigma_position
    tool = model2.tool_dof
    assert np.allclose(model2.row_sigma[:, tool:], m2.noise.sigma_tilt)
    q = tmp_path / "right.toml"
    q.write_text(machine_text(JOINTS, sigma_tilt=1e-5, sigma_position=0.05))
    right = load_machine(q)
    assert _sensor_noise(right, rec, model_from_recording(right, rec, check=False))[0] is right
