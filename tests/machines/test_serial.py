"""The serial kind (docs/formats.md section 5): FK against an independent product of 4x4 transforms,
analytic Jacobian against central differences, conformance, identifiability, file errors."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from bayescal.errors import MachineFileError
from bayescal.identifiability import analyse_identifiability
from bayescal.machines import KINDS
from bayescal.machines.check import check_machine
from bayescal.machines.files import machine_from_text
from bayescal.machines.serial import Serial, rpy_from_matrix, rpy_matrix
from bayescal.measurement import MeasurementModel

ARM = """
kind = "serial"
name = "5R1P arm"
[[joint]]
type = "revolute"
origin = [0.0, 0.0, 400.0]
axis = [0.0, 0.0, 1.0]
[[joint]]
type = "revolute"
origin = [150.0, 0.0, 0.0]
rpy = [1.5707963267948966, 0.0, 0.0]
axis = [0.0, 0.0, 1.0]
[[joint]]
type = "revolute"
origin = [600.0, 0.0, 0.0]
rpy = [0.0, 0.0, 0.0]
axis = [0.0, 0.0, 1.0]
[[joint]]
type = "revolute"
origin = [100.0, 550.0, 0.0]
rpy = [-1.5707963267948966, 0.0, 0.0]
axis = [0.0, 0.0, 1.0]
[[joint]]
type = "revolute"
origin = [0.0, 0.0, 0.0]
rpy = [1.5707963267948966, 0.0, 0.0]
axis = [0.0, 0.0, 1.0]
[[joint]]
type = "prismatic"
origin = [0.0, 0.0, 0.0]
rpy = [-1.5707963267948966, 0.3, 0.0]
axis = [0.0, 0.6, 0.8]
[tool]
point = [10.0, 20.0, 120.0]
rpy = [0.1, 0.2, 0.3]
[workspace]
q_limits = [[-3.0, 3.0], [-1.5, 1.5], [-2.0, 2.0], [-3.0, 3.0], [-2.0, 2.0], [0.0, 100.0]]
"""

POSITIONER = """
kind = "serial"
name = "tilt and turn positioner"
[[joint]]
type = "revolute"
origin = [0.0, 0.0, 500.0]
rpy = [0.0, 0.0, 0.0]
axis = [1.0, 0.0, 0.0]
[[joint]]
type = "revolute"
origin = [0.0, 0.0, 150.0]
rpy = [0.0, 0.0, 0.0]
axis = [0.0, 0.0, 1.0]
[tool]
point = [200.0, 50.0, 30.0]
[workspace]
q_limits = [[-1.0, 1.0], [-3.14159, 3.14159]]
"""


@pytest.fixture(scope="module")
def arm():
    return machine_from_text(ARM)


@pytest.fixture(scope="module")
def positioner():
    return machine_from_text(POSITIONER)


def _homogeneous(R=np.eye(3), t=np.zeros(3)):
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t
    return T


def _independent_fk(m: Serial, q, theta):
    """Tool frame as the literal product Trans(o) Rot(rpy) M(q) ... Trans(t) Rot(rpy_t), written here
    with scipy rotations and 4x4 matrices; the perturbations applied as docs/formats.md section 5 names them."""
    E = np.eye(3)
    T = np.eye(4)
    for i, jt in enumerate(m.joint_type):
        th = theta[9 * i : 9 * i + 9]
        a0 = m.axis[i]
        drop = int(np.argmax(np.abs(a0)))
        ea, eb = [E[k] for k in range(3) if k != drop]
        a = a0 + th[1] * np.cross(ea, a0) + th[2] * np.cross(eb, a0)
        a /= np.linalg.norm(a)
        T = T @ _homogeneous(t=m.origin[i] + th[3:6])
        T = T @ _homogeneous(R=Rotation.from_euler("xyz", m.rpy[i] + th[6:9]).as_matrix())
        qi = q[i] + th[0]
        T = T @ (_homogeneous(R=Rotation.from_rotvec(a * qi).as_matrix()) if jt == "revolute" else _homogeneous(t=a * qi))
    tt = theta[9 * len(m.joint_type) :]
    T = T @ _homogeneous(t=m.tool_point + tt[:3]) @ _homogeneous(R=Rotation.from_euler("xyz", m.tool_rpy + tt[3:]).as_matrix())
    return T


def test_registered_and_units(arm):
    assert KINDS["serial"] is Serial
    assert arm.actuator_units == ("rad",) * 5 + ("mm",)
    assert arm.n_params == 9 * 6 + 6
    assert arm.layout.names[:4] == ("joint1.offset", "joint1.axis.tilt_x", "joint1.axis.tilt_y", "joint1.origin.x")
    assert arm.layout.units[9 * 5] == "mm"  # prismatic offset


@pytest.mark.parametrize("scale", [0.0, 1.0, 300.0])
def test_forward_matches_product_of_homogeneous_transforms(arm, scale):
    rng = np.random.default_rng(4)
    q = arm.sample_q(12, rng)
    theta = rng.normal(size=arm.n_params) * arm.tolerance * scale  # up to 6 cm / 0.06 rad: not only small errors
    poses = arm.forward(q, theta)
    for i in range(q.shape[0]):
        T = _independent_fk(arm, q[i], theta)
        assert np.allclose(poses.position[i], T[:3, 3], atol=1e-9)
        assert np.allclose(poses.rotation[i], T[:3, :3], atol=1e-12)


def test_rpy_convention_and_inverse():
    rng = np.random.default_rng(1)
    rpy = rng.uniform([-3, -1.5, -3], [3, 1.5, 3], size=(50, 3))
    assert np.allclose(rpy_matrix(rpy), Rotation.from_euler("xyz", rpy).as_matrix(), atol=1e-14)
    assert np.allclose(rpy_from_matrix(rpy_matrix(rpy)), rpy, atol=1e-12)
    locked = rpy_matrix(np.array([[0.3, np.pi / 2, -0.2], [0.3, -np.pi / 2, -0.2]]))
    assert np.allclose(rpy_matrix(rpy_from_matrix(locked)), locked, atol=1e-12)


@pytest.mark.parametrize("which", ["arm", "positioner"])
def test_jacobian_matches_central_differences_for_every_parameter(which, arm, positioner):
    m = arm if which == "arm" else positioner
    rng = np.random.default_rng(7)
    q = m.sample_q(10, rng)
    theta = rng.normal(size=m.n_params) * m.tolerance * 10
    poses = m.forward(q, theta)
    J = m.tool_jacobian(q, theta, poses)
    from bayescal.geometry import so3_log

    for k in range(m.n_params):
        h = 1e-6 if m.layout.units[k] == "rad" else 1e-4
        e = np.zeros(m.n_params)
        e[k] = h
        p, n = m.forward(q, theta + e), m.forward(q, theta - e)
        fd_p = (p.position - n.position) / (2 * h)
        fd_w = so3_log(p.rotation @ np.swapaxes(n.rotation, 1, 2)) / (2 * h)
        scale = 1.0 + np.abs(fd_p).max()
        assert np.abs(J[:, :3, k] - fd_p).max() < 1e-6 * scale, m.layout.names[k]
        assert np.abs(J[:, 3:, k] - fd_w).max() < 1e-7, m.layout.names[k]


def test_actuator_jacobian_matches_central_differences(arm):
    rng = np.random.default_rng(2)
    q = arm.sample_q(6, rng)
    theta = rng.normal(size=arm.n_params) * arm.tolerance
    poses = arm.forward(q, theta)
    from bayescal.machines.base import Machine

    fd = Machine.actuator_jacobian(arm, q, theta, poses)
    assert np.allclose(arm.actuator_jacobian(q, theta, poses), fd, atol=1e-6)


@pytest.mark.parametrize("which", ["arm", "positioner"])
def test_check_machine(which, arm, positioner):
    assert check_machine(arm if which == "arm" else positioner, seed=3) == []


def test_offsets_folded_into_the_written_file(arm):
    """A zero offset alone, written with to_toml: the file has no offsets, yet predicts the same poses."""
    theta = np.zeros(arm.n_params)
    theta[[9 * k for k in range(6)]] = [0.01, -0.02, 0.03, 0.04, -0.05, 2.5]
    again = machine_from_text(arm.to_toml(theta))
    q = arm.sample_q(5, np.random.default_rng(0))
    a, b = arm.forward(q, theta), again.forward(q)
    assert np.allclose(a.position, b.position, atol=1e-9) and np.allclose(a.rotation, b.rotation, atol=1e-12)
    assert not np.allclose(again.rpy, arm.rpy)  # the revolute offsets went into rpy
    assert np.allclose(again.origin[5] - arm.origin[5], rpy_matrix(arm.rpy[5]) @ arm.axis[5] * 2.5)


def _ida(m, dof, n=60):
    q = m.sample_q(n, np.random.default_rng(0))
    model = MeasurementModel(m, q, dof)
    J = (model.jacobian(None, model.predict(None)) / model.sigma[None, :, None]).reshape(-1, m.n_params)
    return analyse_identifiability(J, m.layout)


@pytest.mark.parametrize("dof,extra", [(6, 6), (3, 3)])
def test_identifiable_count_is_the_complete_minimal_model(arm, positioner, dof, extra):
    """Everett-Hsu-Roth count for a complete, minimal, parametrically continuous model: 4 per
    revolute joint, 2 per prismatic joint, plus the 6 of the tool frame (3 with positions only)."""
    assert _ida(positioner, dof).rank == 4 * 2 + extra
    assert _ida(arm, dof).rank == 4 * 5 + 2 * 1 + extra


def test_identifiability_names_the_redundant_combinations(positioner):
    ida = _ida(positioner, 6)
    text = "\n".join(ida.combinations)
    # joint 1 turns about x: a roll of its frame is its zero offset
    assert "joint1.rpy.r: a change of 1 rad looks the same to the measurement as changing joint1.offset by +1 rad" in text
    # moving joint 2 along x (along the tilt axis) is moving joint 1 along x
    assert "joint2.origin.x: a change of 1 mm looks the same to the measurement as changing joint1.origin.x by +1 mm" in text
    # the tool point along the turntable axis is the turntable's height
    assert "tool.point.z: a change of 1 mm looks the same to the measurement as changing joint2.origin.z by +1 mm" in text
    assert "joint1.offset" in ida.kept and "joint2.offset" in ida.fixed


@pytest.mark.parametrize(
    "edit,key",
    [
        (('type = "prismatic"', 'type = "spherical"'), "joint[6].type"),
        (("axis = [0.0, 0.6, 0.8]", "axis = [0.0, 0.6, 0.9]"), "joint[6].axis"),
        (("[tool]\n", "[tool]\nframe = 1\n"), "tool.frame"),
        (('name = "5R1P arm"', 'name = "x"\nbase_link = "a"'), "base_link"),
        (('name = "5R1P arm"', 'name = "x"\nurdf = "a.urdf"'), "joint"),
    ],
)
def test_bad_files_name_the_key(edit, key):
    with pytest.raises(MachineFileError) as err:
        machine_from_text(ARM.replace(*edit), "arm.toml")
    assert err.value.key == key and "arm.toml" in str(err.value)


def test_recording_units_checked_against_revolute_joints(positioner, tmp_path):
    from bayescal.errors import RecordingError
    from bayescal.io.recording import read_recording

    p = tmp_path / "r.csv"
    p.write_text("q1_mm,q2,x,y,z\n1,0.5,0,0,0\n")
    with pytest.raises(RecordingError, match="revolute"):
        MeasurementModel.from_recording(positioner, read_recording(p))


def test_identification_recovers_the_true_chain(arm):
    """End to end: simulated 6-DOF recording, automatic identifiable subset, LS; the calibrated
    chain predicts the true one on fresh poses to the noise level, though many of its 60
    parameters are not separately identifiable."""
    from bayescal.identify import identify
    from bayescal.simulate import simulate_recording

    sim = simulate_recording(arm, 200, seed=3, dof=6)
    res = identify(MeasurementModel.from_recording(arm, sim.recording), method="ls")
    assert res.success
    q = arm.sample_q(100, np.random.default_rng(9))
    a, b, nominal = arm.forward(q, res.theta), arm.forward(q, sim.theta_true), arm.forward(q)
    err = np.abs(a.position - b.position).max()
    assert err < 0.01 < np.abs(nominal.position - b.position).max() / 5


def test_one_geometry_for_every_pose_equals_one_row_per_pose(arm):
    """theta of shape (P,) is evaluated once per joint, broadcast over the poses (issue 32): the same numbers
    as the same geometry given row by row, for the poses, the identification Jacobian, the actuator Jacobian
    and the weight bodies; and per-pose geometries still give each pose its own chain."""
    rng = np.random.default_rng(8)
    q = arm.sample_q(9, rng)
    theta = rng.normal(size=arm.n_params) * arm.tolerance * 30.0
    rows = np.tile(theta, (9, 1))
    shared, per_pose = arm.forward(q, theta), arm.forward(q, rows)
    assert np.array_equal(shared.position, per_pose.position) and np.array_equal(shared.rotation, per_pose.rotation)
    assert np.array_equal(arm.tool_jacobian(q, theta, shared), arm.tool_jacobian(q, rows, per_pose))
    assert np.array_equal(arm.actuator_jacobian(q, theta, shared), arm.actuator_jacobian(q, rows, per_pose))
    wb, wr = arm.weight_bodies(q, theta, shared), arm.weight_bodies(q, rows, per_pose)
    assert np.array_equal(wb.jacobian, wr.jacobian) and np.array_equal(wb.origin, wr.origin)
    rows[4] = 0.0  # pose 5 at the nominal geometry, the others at theta
    mixed = arm.forward(q, rows)
    assert np.array_equal(mixed.position[4], arm.forward(q[4:5]).position[0])
    assert np.allclose(mixed.position[3], _independent_fk(arm, q[3], theta)[:3, 3], atol=1e-9)


def test_written_out_cross_product_is_numpys():
    from bayescal.machines.serial import _cross

    rng = np.random.default_rng(2)
    w, a = rng.normal(size=(7, 3, 4)), rng.normal(size=(7, 3))
    assert np.array_equal(_cross(w, a), np.cross(w, a[:, :, None], axis=1))


def test_columns_of_the_jacobian_are_the_whole_jacobians_bit_for_bit(arm, positioner, monkeypatch):
    """tool_jacobian_columns (issue 32: a fit asks only for its free columns) gives the whole Jacobian's values,
    bit for bit, for any subset (the whole one is checked against central differences above), shared or per-pose
    geometry, with a prismatic joint or revolute joints only; and a block no column falls in is not computed
    (the rpy rates are not even formed)."""
    from bayescal.machines import serial

    rng = np.random.default_rng(11)
    for m in (arm, positioner):
        q = m.sample_q(7, rng)
        theta = rng.normal(size=m.n_params) * m.tolerance * 30.0
        P, t = m.n_params, 9 * m.n_joints
        names = m.layout.names
        picks = [np.arange(P), np.array([3]), np.array([0, P - 1]), np.arange(t, P), np.arange(t, t + 3)]
        picks += [np.array([j for j, n in enumerate(names) if part in n]) for part in
                  ("offset", "tilt", "origin", "joint2.rpy", ".rpy.")]
        picks += [np.sort(rng.choice(P, size=rng.integers(2, P), replace=False)) for _ in range(10)]
        for th in (theta, np.tile(theta, (7, 1))):
            whole = m.tool_jacobian(q, th, m.forward(q, th))
            for cols in picks:
                got = m.tool_jacobian_columns(q, th, None, cols)
                assert got.shape == (7, 6, cols.size) and np.array_equal(got, whole[:, :, cols]), (m.name, cols)
    q, theta = arm.sample_q(5, rng), arm.tolerance * 20.0
    whole = arm.tool_jacobian(q, theta, None)
    no_rpy = np.array([j for j, n in enumerate(arm.layout.names) if ".rpy." not in n])

    def refuse(rpy):
        raise AssertionError("the rpy block was computed for columns that leave it out")

    monkeypatch.setattr(serial, "rpy_rates", refuse)
    assert np.array_equal(arm.tool_jacobian_columns(q, theta, None, no_rpy), whole[:, :, no_rpy])
    with pytest.raises(AssertionError, match="rpy block"):
        arm.tool_jacobian(q, theta, None)
