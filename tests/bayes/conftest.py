"""Fixtures shared by the posterior tests."""

from __future__ import annotations

import numpy as np
import pytest

from bayescal.bayes import linearise, prior_from_machine
from bayescal.measurement import MeasurementModel

#: The parameters the linear problem samples.
LINEAR_FREE = ["chain1.link_length", "chain2.link_length", "chain3.link_length", "chain1.sphere_center.x"]


@pytest.fixture(scope="module")
def linear_problem(prs3, sim6):
    """Linear model over 6 poses, position only, 4 free parameters: posterior N(m, C) in closed form."""
    model = MeasurementModel.from_recording(prs3, sim6.recording, dof=3).subset(np.arange(6))
    lin = linearise(model)
    rng = np.random.default_rng(17)
    prior = prior_from_machine(prs3)
    idx = np.sort(prs3.layout.indices(LINEAR_FREE))  # the sampler keeps the layout order
    theta = np.zeros(prs3.n_params)
    theta[idx] = prior.std[idx] * rng.normal(size=idx.size)
    lin = lin.with_measured(lin.predict(theta).y + rng.normal(size=lin.y0.shape) * lin.sigma)
    # closed form: x ~ N(m, C), C = (P0^-1 + A^T A)^-1, m = C (P0^-1 mu + A^T z)
    A = (lin.J[:, :, idx] / lin.sigma[None, :, None]).reshape(-1, idx.size)
    z = ((lin.y_measured - lin.y0) / lin.sigma).reshape(-1)
    P0inv = np.diag(1 / prior.std[idx] ** 2)
    C = np.linalg.inv(P0inv + A.T @ A)
    return lin, idx, C @ (A.T @ z), C, LINEAR_FREE
