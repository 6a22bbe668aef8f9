import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from bayescal.geometry import so3_log
from bayescal.machines.files import machine_from_text


def test_symmetric_closed_form(prs3):
    """Equal slider positions on the symmetric head: pure translation, z from Pythagoras."""
    q = np.array([[500.0, 500.0, 500.0], [470.0, 470.0, 470.0]])
    poses = prs3.forward(q)
    assert poses.success.all()
    assert np.allclose(poses.rotation, np.eye(3), atol=1e-12)
    h = np.sqrt(400.0**2 - (300.0 - 150.0) ** 2)
    expected_z = q[:, 0] - h - 100.0  # platform below the sliders, tool 100 mm below the platform
    assert np.allclose(poses.position[:, 2], expected_z, atol=1e-10)
    assert np.allclose(poses.position[:, :2], 0.0, atol=1e-10)


@given(st.lists(st.floats(450.0, 550.0), min_size=3, max_size=3))
@settings(max_examples=40, deadline=None)
def test_forward_then_inverse_round_trip(prs3, q):
    q = np.array([q])
    theta = np.random.default_rng(3).normal(size=prs3.n_params) * prs3.tolerance * 5
    poses = prs3.forward(q, theta)
    assert poses.success.all()
    st_ = poses.state
    assert np.allclose(prs3.inverse(st_.p, st_.R, theta), q, atol=1e-8)


def test_constraints_hold_at_solution(prs3, rng):
    q = prs3.sample_q(20, rng)
    theta = rng.normal(size=prs3.n_params) * prs3.tolerance
    poses = prs3.forward(q, theta)
    g = prs3.geometry_arrays(theta)
    A = poses.state.p[:, None, :] + np.einsum("nij,kj->nki", poses.rotation, g["sphere_center"])
    C = g["rail_origin"][None] + q[:, :, None] * g["rail_direction"][None]
    d = A - C
    assert np.allclose(np.linalg.norm(d, axis=2), g["link_length"][None], atol=1e-9)
    assert np.allclose(np.einsum("nki,ki->nk", d, g["revolute_axis"]), 0.0, atol=1e-9)


def test_tool_jacobian_against_central_differences(prs3, rng):
    q = prs3.sample_q(8, rng)
    theta = rng.normal(size=prs3.n_params) * prs3.tolerance * 10
    poses = prs3.forward(q, theta)
    J = prs3.tool_jacobian(q, theta, poses)
    for k, unit in enumerate(prs3.layout.units):
        h = 1e-5 if unit == "mm" else 1e-7
        e = np.zeros(prs3.n_params)
        e[k] = h
        pp, pm = prs3.forward(q, theta + e, guess=poses), prs3.forward(q, theta - e, guess=poses)
        fd_pos = (pp.position - pm.position) / (2 * h)
        fd_rot = so3_log(pp.rotation @ np.swapaxes(pm.rotation, 1, 2)) / (2 * h)
        scale = np.abs(J).max()
        assert np.allclose(J[:, :3, k], fd_pos, atol=1e-7 * scale), prs3.layout.names[k]
        assert np.allclose(J[:, 3:, k], fd_rot, atol=1e-7 * scale), prs3.layout.names[k]


def test_unreachable_pose_is_reported_not_raised(prs3):
    q = np.array([[500.0, 500.0, 500.0], [0.0, 2000.0, 500.0]])
    poses = prs3.forward(q)
    assert poses.success.tolist() == [True, False]
    assert poses.message[1]


def test_written_machine_reproduces_the_model(prs3, rng):
    theta = rng.normal(size=prs3.n_params) * prs3.tolerance * 3
    again = machine_from_text(prs3.to_toml(theta))
    q = prs3.sample_q(15, rng)
    a, b = prs3.forward(q, theta), again.forward(q)
    assert np.allclose(a.position, b.position, atol=1e-10)
    assert np.allclose(a.rotation, b.rotation, atol=1e-12)
    assert again.q_limits.tolist() == prs3.q_limits.tolist()
    assert again.noise == prs3.noise


def test_theta_of_wrong_shape_is_an_input_error(prs3):
    from bayescal.errors import InputError

    for bad in (1.0, np.zeros(5), np.zeros((2, 2, prs3.n_params))):
        with pytest.raises(InputError, match="theta"):
            prs3.forward([[500.0, 500.0, 500.0]], bad)


@pytest.mark.parametrize("turn_deg", [90.0, 180.0, -135.0])
def test_platform_frame_turned_against_the_base_frame(prs3, rng, turn_deg):
    """docs/formats.md section 1 does not ask for the platform frame to be aligned with the base frame at home.

    The same physical machine described in a platform frame turned about z
    (sphere centres and tool point rotated back) must solve to the same tool
    points, with the platform orientation turned by the same rotation, from
    the default start and from position-only / tool-axis measurements.
    """
    from dataclasses import replace

    from bayescal.geometry import so3_exp
    from bayescal.io import Recording
    from bayescal.measurement import MeasurementModel

    Rz = so3_exp(np.array([0.0, 0.0, np.radians(turn_deg)]))
    turned = replace(prs3, sphere_center=prs3.sphere_center @ Rz, tool_point=Rz.T @ prs3.tool_point)
    q = prs3.sample_q(20, rng)
    a, b = prs3.forward(q), turned.forward(q)
    assert b.success.all()
    assert np.allclose(b.position, a.position, atol=1e-8) and np.allclose(b.rotation, a.rotation @ Rz, atol=1e-10)
    for axis in (None, a.axis):
        rec = Recording(q=q, position=a.position, axis=axis)
        model = MeasurementModel.from_recording(turned, rec)
        pred = model.predict(np.zeros(turned.n_params))
        assert pred.poses.success.all() and np.abs(model.residual(pred)).max() < 1e-8


def test_recording_of_the_other_assembly_branch_without_the_assembly_key(prs3, rng):
    """A file written from the contract alone (docs/formats.md section 1) has no ``assembly`` key: the measurement decides the branch.

    The example machine with its rails pointing the other way (q -> -q) has its
    links along the rails, while the file (no ``assembly``) says the default,
    against the rails; a recording of the real machine must still fit exactly.
    """
    from dataclasses import replace

    from bayescal.io import Recording
    from bayescal.measurement import MeasurementModel

    flipped = replace(prs3, rail_direction=-prs3.rail_direction, q_limits=-prs3.q_limits[:, ::-1])
    assert flipped.links_against_rail  # the default the file implies
    q = prs3.sample_q(15, rng)
    truth = prs3.forward(q)
    for rotvec in (None, so3_log(truth.rotation)):
        model = MeasurementModel.from_recording(flipped, Recording(q=-q, position=truth.position, rotvec=rotvec))
        pred = model.predict(None)
        assert pred.poses.success.all() and np.abs(model.residual(pred)).max() < 1e-8


def test_tangent_guesses_are_first_order_and_solve_to_the_same_poses(prs3, rng):
    q = prs3.sample_q(12, rng)
    theta0 = rng.normal(size=prs3.n_params) * prs3.tolerance
    guesses = prs3.tangent_guesses(q, theta0, prs3.forward(q, theta0))
    step = rng.normal(size=(3, prs3.n_params)) * prs3.tolerance  # three walkers, stacked as a sampler stacks them
    solved = [prs3.forward(np.tile(q, (3, 1)), np.repeat(theta0 + s * step, 12, axis=0)) for s in (1.0, 0.5)]
    err = []
    for s, exact in zip((1.0, 0.5), solved):
        g = guesses(theta0 + s * step)
        assert g.position.shape == (36, 3) and g.state.p.shape == (36, 3)
        err.append(max(np.abs(g.state.p - exact.state.p).max(), np.abs(g.position - exact.position).max(),
                       100.0 * np.abs(so3_log(g.rotation @ np.swapaxes(exact.rotation, 1, 2))).max()))
    moved = np.abs(solved[0].position - np.tile(prs3.forward(q, theta0).position, (3, 1))).max()
    # first order: far closer than the unmoved poses, and the error quarters when the step halves
    assert err[0] < 0.02 * moved
    assert 0.15 < err[1] / err[0] < 0.35, err
    # a start only: Newton from it reaches the cold solve's poses
    warm = prs3.forward(np.tile(q, (3, 1)), np.repeat(theta0 + step, 12, axis=0), guess=guesses(theta0 + step))
    assert warm.success.all()
    np.testing.assert_allclose(warm.position, solved[0].position, rtol=0, atol=1e-9)
    np.testing.assert_allclose(warm.rotation, solved[0].rotation, rtol=0, atol=1e-12)


def _tool_jacobian_unblocked(machine, q, theta, poses):
    """The tool Jacobian as it was computed before the blocks and the in-place steps (one array per step)."""
    from bayescal.geometry import skew
    from bayescal.machines.prs3 import _PER_CHAIN

    n = q.shape[0]
    g = machine._geometry(machine._theta_rows(theta, n))
    st = poses.state
    dx = machine._state_derivative(q, g, st)
    Rt = np.einsum("nij,nj->ni", st.R, g.t)
    J = np.empty((n, 6, machine.n_params))
    J[:, :3] = dx[:, :3] - skew(Rt) @ dx[:, 3:]
    J[:, :3, 3 * _PER_CHAIN :] += st.R
    J[:, 3:] = dx[:, 3:]
    return J


@pytest.mark.parametrize("per_pose", [False, True])
def test_tool_jacobian_in_blocks_is_the_whole_batchs_bit_for_bit(prs3, rng, monkeypatch, per_pose):
    """Poses in blocks (large recordings, ``_BLOCK``) and the in-place steps give the very same values as one
    batch of one array per step: every pose's Jacobian is its own."""
    import bayescal.machines.prs3 as mod

    q = prs3.sample_q(23, rng)
    shape = (23, prs3.n_params) if per_pose else (prs3.n_params,)
    theta = rng.normal(size=shape) * prs3.tolerance * 10
    poses = prs3.forward(q, theta)
    whole = prs3.tool_jacobian(q, theta, poses)
    monkeypatch.setattr(mod, "_BLOCK", 5)  # 23 poses: four blocks of 5 and one of 3
    blocked = prs3.tool_jacobian(q, theta, poses)
    assert np.array_equal(blocked, whole)
    assert np.array_equal(whole, _tool_jacobian_unblocked(prs3, q, theta, poses))
