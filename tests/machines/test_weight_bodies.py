"""Machine.weight_bodies on every example kind: the Jacobian is the body frames' derivative by finite differences."""

from pathlib import Path

import numpy as np
import pytest

from bayescal.geometry import so3_log
from bayescal.machines.files import load_machine
from bayescal.machines.framed import Frame, InstrumentFrame
from bayescal.simulate import draw_poses
from tests.conftest import ROOT

FILES = sorted(p for p in (ROOT / "examples").glob("*/machine.toml"))


def _bodies(m, q, theta, guess=None):
    return m.weight_bodies(q, theta, m.forward(q, theta, guess=guess))


@pytest.mark.parametrize("path", FILES, ids=lambda p: Path(p).parent.name)
def test_weight_body_velocities_are_the_frames_derivatives(path):
    m = load_machine(path)
    rng = np.random.default_rng(4)
    theta = rng.normal(size=m.n_params) * m.tolerance
    q = draw_poses(m, 4, rng, theta)
    poses = m.forward(q, theta)
    wb = m.weight_bodies(q, theta, poses)
    nb = len(m.weight_body_names)
    assert wb.names == m.weight_body_names
    assert wb.origin.shape == (4, nb, 3) and wb.rotation.shape == (4, nb, 3, 3) and wb.jacobian.shape == (4, nb, 6, m.n_actuators)
    for i, u in enumerate(m.actuator_units):
        h = 1e-6 if u == "rad" else 1e-4
        e = np.zeros(m.n_actuators)
        e[i] = h
        a, b = _bodies(m, q + e, theta, poses), _bodies(m, q - e, theta, poses)
        v = (a.origin - b.origin) / (2 * h)
        w = so3_log(a.rotation @ np.swapaxes(b.rotation, -1, -2)) / (2 * h)
        scale = max(1.0, np.abs(wb.jacobian[:, :, :3, i]).max())
        np.testing.assert_allclose(wb.jacobian[:, :, :3, i], v, atol=2e-5 * scale)
        np.testing.assert_allclose(wb.jacobian[:, :, 3:, i], w, atol=2e-6)


def test_serial_links_are_the_frames_after_each_joint_and_the_last_carries_the_tool():
    m = load_machine(ROOT / "examples" / "arm6" / "machine.toml")
    q = m.sample_q(3, np.random.default_rng(0))
    poses = m.forward(q)
    wb = m.weight_bodies(q, None, poses)
    assert wb.names == tuple(f"link{k}" for k in range(1, 7))
    # the tool is fixed in the last link's frame at tool.point
    np.testing.assert_allclose(wb.origin[:, -1] + wb.rotation[:, -1] @ m.tool_point, poses.position, atol=1e-9)
    # link k does not move with joints beyond k
    for k in range(6):
        assert np.all(wb.jacobian[:, k, :, k + 1 :] == 0)


def test_a_fitted_instrument_frame_leaves_the_bodies_in_the_base_frame():
    m = load_machine(ROOT / "examples" / "arm6" / "machine.toml")
    framed = InstrumentFrame(m, Frame.from_rotation_vector([100.0, -50.0, 30.0], [0.1, 0.2, -0.3]), fit=True)
    q = m.sample_q(3, np.random.default_rng(1))
    theta = np.zeros(framed.n_params)
    a = framed.weight_bodies(q, theta, framed.forward(q, theta))
    b = m.weight_bodies(q, None, m.forward(q))
    np.testing.assert_allclose(a.origin, b.origin, atol=1e-9)
    np.testing.assert_allclose(a.jacobian, b.jacobian, atol=1e-9)
    assert framed.weight_body_names == m.weight_body_names
