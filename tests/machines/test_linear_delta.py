"""The linear delta: forward kinematics against an independent closed-form trilateration,
the analytic Jacobians against central differences, check_machine, machine-file errors."""

from pathlib import Path

import numpy as np
import pytest

from bayescal.errors import MachineFileError
from bayescal.machines import KINDS, LinearDelta
from bayescal.machines.check import check_machine
from bayescal.machines.files import load_machine, machine_from_text

EXAMPLE = Path(__file__).resolve().parents[2] / "examples" / "delta" / "machine.toml"


def trilaterate(c1, c2, c3, r1, r2, r3):
    """Lower intersection of three spheres, closed form (the textbook construction:
    a frame with c1 at the origin, c2 on its x axis, c3 in its xy plane)."""
    ex = (c2 - c1) / np.linalg.norm(c2 - c1)
    i = ex @ (c3 - c1)
    ey = c3 - c1 - i * ex
    ey /= np.linalg.norm(ey)
    ez = np.cross(ex, ey)
    d = np.linalg.norm(c2 - c1)
    j = ey @ (c3 - c1)
    x = (r1**2 - r2**2 + d**2) / (2 * d)
    y = (r1**2 - r3**2 + i**2 + j**2) / (2 * j) - i * x / j
    z = np.sqrt(r1**2 - x**2 - y**2)
    a, b = c1 + x * ex + y * ey + z * ez, c1 + x * ex + y * ey - z * ez
    return a if a[2] < b[2] else b


@pytest.fixture(scope="module")
def delta():
    return load_machine(EXAMPLE)


def test_registered_and_conforms(delta):
    assert KINDS["linear-delta"] is LinearDelta
    assert isinstance(delta, LinearDelta)
    assert delta.n_params == 21
    assert check_machine(delta) == []


def test_forward_matches_closed_form_trilateration(delta):
    rng = np.random.default_rng(3)
    q = delta.sample_q(20, rng)
    theta = rng.normal(size=delta.n_params) * delta.tolerance * 3
    poses = delta.forward(q, theta)
    assert poses.success.all()
    g = delta.geometry_arrays(theta)
    for k in range(q.shape[0]):
        # independent geometry: tower foot from angle and radius, carriage along the tower
        C = [
            np.array([g["radius"][i] * np.cos(g["angle"][i]), g["radius"][i] * np.sin(g["angle"][i]), 0.0])
            + (g["zero"][i] + q[k, i]) * g["direction"][i]
            for i in range(3)
        ]
        p = trilaterate(*C, *g["arm_length"])
        np.testing.assert_allclose(poses.position[k], p + g["tool_point"], atol=1e-9)
    np.testing.assert_array_equal(poses.rotation, np.broadcast_to(np.eye(3), (20, 3, 3)))


def test_klipper_nominal_centre_pose(delta):
    # README of the FLSUN data: equal carriages at 213.212 mm put the nozzle at z = 24.450 on the axis
    E = 219 + np.sqrt(216.0**2 - 105.0**2)
    m = machine_from_text(delta.to_toml().replace("407.762", repr(float(E))))
    h = E - 15564 * 0.0125
    p = m.forward(np.full((1, 3), h - E)).position[0]
    np.testing.assert_allclose(p, [0.0, 0.0, h - np.sqrt(216.0**2 - 105.0**2)], atol=1e-10)
    assert abs(p[2] - 24.450) < 1e-3


def _central_difference(f, x, h):
    cols = []
    for k in range(x.size):
        e = np.zeros(x.size)
        e[k] = h[k]
        cols.append((f(x + e) - f(x - e)) / (2 * h[k]))
    return np.stack(cols, axis=-1)


def test_tool_jacobian_central_differences_every_parameter(delta):
    rng = np.random.default_rng(5)
    q = delta.sample_q(6, rng)
    theta = rng.normal(size=delta.n_params) * delta.tolerance
    poses = delta.forward(q, theta)
    J = delta.tool_jacobian(q, theta, poses)
    fd = _central_difference(lambda th: delta.forward(q, th, guess=poses).position, theta, 1e-3 * delta.tolerance)
    for k, name in enumerate(delta.layout.names):
        np.testing.assert_allclose(J[:, :3, k], fd[:, :, k], rtol=1e-6, atol=1e-7, err_msg=name)
    assert np.all(J[:, 3:] == 0)


def test_actuator_jacobian_and_inverse(delta):
    rng = np.random.default_rng(6)
    q = delta.sample_q(5, rng)
    poses = delta.forward(q)
    Jq = delta.actuator_jacobian(q, None, poses)
    fd = _central_difference(lambda qq: delta.forward(qq.reshape(q.shape), guess=poses).position.ravel(), q.ravel(), np.full(q.size, 1e-4))
    fd = fd.reshape(5, 3, 5, 3)
    for k in range(5):
        np.testing.assert_allclose(Jq[k, :3], fd[k, :, k, :], rtol=1e-6, atol=1e-8)
    np.testing.assert_allclose(delta.inverse(poses.position), q, atol=1e-9)


FOUR = """
kind = "linear-delta"
[[tower]]
angle_deg = 0.0
radius = 100.0
zero = 400.0
arm_length = 220.0
[[tower]]
angle_deg = 90.0
radius = 100.0
zero = 400.0
arm_length = 220.0
[[tower]]
position = [-100.0, 0.0]
zero = 400.0
arm_length = 220.0
[[tower]]
angle_deg = 270.0
radius = 100.0
zero = 400.0
direction = [0.01, 0.0, 0.99995]
arm_length = 220.0
[workspace]
q_limits = [[-250.0, -30.0], [-250.0, -30.0], [-250.0, -30.0], [-250.0, -30.0]]
"""


def test_four_towers_least_squares_compromise_conforms():
    m = machine_from_text(FOUR)
    assert m.n_actuators == 4 and m.n_params == 27
    assert check_machine(m, n_poses=6) == []


@pytest.mark.parametrize(
    "text, key",
    [
        (FOUR.replace("position = [-100.0, 0.0]", "position = [-100.0, 0.0]\nradius = 3.0"), "tower[3].position"),
        (FOUR.replace("direction = [0.01, 0.0, 0.99995]", "direction = [1.0, 0.0, 0.0]"), "tower[4].direction"),
        (FOUR.replace("arm_length = 220.0\n[workspace]", "arm_length = -1.0\n[workspace]"), "tower[4].arm_length"),
        (FOUR.replace("zero = 400.0\narm_length = 220.0\n[[tower]]\nangle_deg = 90.0", "zro = 1.0\narm_length = 220.0\n[[tower]]\nangle_deg = 90.0"), "tower[1].zro"),
    ],
)
def test_machine_file_errors_name_the_key(text, key):
    with pytest.raises(MachineFileError) as exc:
        machine_from_text(text, path="m.toml")
    assert key in str(exc.value) and "m.toml" in str(exc.value)


def test_two_towers_refused():
    text = FOUR.split("[[tower]]\nangle_deg = 90.0")[0] + "[workspace]\nq_limits = [[-250.0, -30.0]]\n"
    with pytest.raises(MachineFileError, match="at least 3"):
        machine_from_text(text, path="m.toml")


def test_unreachable_pose_is_reported_not_raised(delta):
    q = np.array([[-150.0, -150.0, -150.0], [0.0, -600.0, -600.0]])
    poses = delta.forward(q)
    assert poses.success.tolist() == [True, False]
    assert poses.message[0] == "" and "cannot reach" in poses.message[1]
    assert np.isnan(delta.inverse([[500.0, 0.0, 0.0]])).any()  # farther from a tower than its arm
