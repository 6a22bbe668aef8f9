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
