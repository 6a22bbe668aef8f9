import numpy as np

from bayescal.machines.base import Machine


def test_prs3_actuator_jacobian_matches_finite_differences(prs3, rng):
    q = prs3.sample_q(15, rng)
    theta = rng.normal(size=prs3.n_params) * prs3.tolerance * 3
    poses = prs3.forward(q, theta)
    assert poses.success.all()
    analytic = prs3.actuator_jacobian(q, theta, poses)
    numeric = Machine.actuator_jacobian(prs3, q, theta, poses)  # the base class default: central differences
    assert analytic.shape == (15, 6, 3)
    np.testing.assert_allclose(analytic, numeric, atol=1e-7 * np.abs(analytic).max())


def test_actuator_jacobian_per_pose_theta(prs3, rng):
    q = prs3.sample_q(6, rng)
    theta = rng.normal(size=(6, prs3.n_params)) * prs3.tolerance
    poses = prs3.forward(q, theta)
    J = prs3.actuator_jacobian(q, theta, poses)
    for i in range(6):
        one = prs3.actuator_jacobian(q[i : i + 1], theta[i], prs3.forward(q[i : i + 1], theta[i]))
        np.testing.assert_allclose(J[i], one[0], atol=1e-10)


def test_raspm_actuator_jacobian_matches_finite_differences(rng):
    # analytic dx/dq_s = J_s^-1 of the non-redundant drives; the redundant drive's column is zero
    from bayescal.machines.files import load_machine
    from tests.conftest import ROOT

    m = load_machine(ROOT / "examples" / "raspm" / "machine.toml")
    q = m.sample_q(12, rng)
    theta = rng.normal(size=(12, m.n_params)) * m.tolerance * 3
    poses = m.forward(q, theta)
    assert poses.success.all()
    analytic = m.actuator_jacobian(q, theta, poses)
    numeric = Machine.actuator_jacobian(m, q, theta, poses)
    assert analytic.shape == (12, 6, 4)
    np.testing.assert_allclose(analytic, numeric, atol=1e-7 * np.abs(analytic).max())
    assert np.all(analytic[:, :, list(m.redundant)] == 0.0)
