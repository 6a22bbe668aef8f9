"""A stored thermal_expansion table predicts a pose the same whatever other poses are evaluated with it."""

import numpy as np

from bayescal.effects import get_effect
from bayescal.effects.thermal_expansion import link_factors


def test_link_term_reference_is_the_home_pose_not_the_batch(prs3, rng):
    eff = get_effect("thermal_expansion")
    theta = np.zeros(prs3.n_params)
    q = prs3.sample_q(12, rng)
    eta = np.concatenate([[3.0, -2.0, 1.0], [11.0, 18.0, 23.0], [40.0, 60.0, 50.0]])  # drift, alpha, link (large)

    def dq(rows):
        aux = {"temp_C": np.full(len(rows), 30.0)}
        return eff.delta_q(eff.features(prs3, rows, theta, aux, None, prs3.forward(rows, theta)), eta)

    batch, alone = dq(q), np.concatenate([dq(q[j : j + 1]) for j in range(len(q))])
    np.testing.assert_allclose(alone, batch, atol=1e-12)  # a grid node (its own session) keeps its link growth
    # the closed form at the home pose q0: dT (g + alpha (q - q0) + (K(x) - K(q0)) lambda)
    q0 = prs3.home_q()
    K = link_factors(prs3, q, theta, prs3.forward(q, theta))
    K0 = link_factors(prs3, q0[None], theta, prs3.forward(q0[None], theta))[0]
    want = 10.0 * (1e-3 * eta[:3] + 1e-6 * eta[3:6] * (q - q0) + 1e-3 * np.einsum("nij,j->ni", K - K0, eta[6:]))
    np.testing.assert_allclose(batch, want, atol=1e-12)
    assert np.abs(alone - 10.0 * (1e-3 * eta[:3] + 1e-6 * eta[3:6] * (q - q0))).max() > 1e-5  # the link term is there
