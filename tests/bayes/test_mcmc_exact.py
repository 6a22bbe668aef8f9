"""The default sampler on the EXACT-kinematics posterior against quadrature of that posterior (2 parameters).

``sample_posterior`` proposes from the Laplace approximation at the MAP but
targets the log posterior evaluated with the full nonlinear forward
kinematics.  The reference here does not use the sampler's code: the
unnormalised posterior is written out from ``model.predict`` and the prior
formula, evaluated on a dense grid (one stacked forward-kinematics call) and
integrated by the trapezoidal rule.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy import integrate

from bayescal.bayes import linearise, map_estimate
from bayescal.bayes.mcmc import sample_posterior
from bayescal.measurement import MeasurementModel

FREE = ["chain1.link_length", "chain2.rail_direction.tilt_x"]


def _log_density(model, idx, X):
    """Unnormalised exact log posterior at points ``X`` (k, 2): Gaussian likelihood of the nonlinear h, tolerance prior."""
    P, n = model.n_params, model.n_poses
    th = np.zeros((X.shape[0], P))
    th[:, idx] = X
    pred = model.predict(np.repeat(th, n, axis=0))
    assert pred.success.all()
    r = (pred.y.reshape(X.shape[0], n, model.dof) - model.y_measured[None]) / model.sigma
    tol = model.machine.tolerance[idx]
    return -0.5 * np.sum(r**2, axis=(1, 2)) - 0.5 * np.sum((X / tol) ** 2, axis=1)


@pytest.fixture(scope="module")
def case(prs3, sim6):
    model = MeasurementModel.from_recording(prs3, sim6.recording, dof=3).subset(np.arange(3))
    idx = np.sort(prs3.layout.indices(FREE))
    start = map_estimate(model, free=FREE)
    # quadrature on +-7 Laplace std around the MAP, in the Laplace principal axes
    m0, L = start.theta[idx], np.linalg.cholesky(start.covariance)
    u = np.linspace(-7.0, 7.0, 141)
    U = np.stack(np.meshgrid(u, u, indexing="ij"), axis=-1).reshape(-1, 2)
    X = m0 + U @ L.T
    lp = _log_density(model, idx, X)
    w = np.exp(lp - lp.max()).reshape(u.size, u.size)

    def integral(f):
        return integrate.trapezoid(integrate.trapezoid(w * f.reshape(u.size, u.size), u, axis=1), u)

    Z = integral(np.ones(len(X)))
    mean = np.array([integral(X[:, k]) for k in range(2)]) / Z
    D = X - mean
    cov = np.array([[integral(D[:, i] * D[:, j]) for j in range(2)] for i in range(2)]) / Z
    res = sample_posterior(model, free=FREE, n_walkers=8, n_steps=1500, seed=9)
    return model, idx, start, mean, cov, res


def test_exact_sampler_moments_match_quadrature(case):
    model, idx, start, mean, cov, res = case
    assert res.success, res.message
    sd = np.sqrt(np.diag(cov))
    # the mean within 4 Monte Carlo standard errors sd / sqrt(ESS) (ESS: arviz bulk, per parameter)
    assert np.all(np.abs(res.mean - mean) < 4 * sd / np.sqrt(res.ess_bulk)), (res.mean - mean) / sd
    # the std: its relative Monte Carlo error is about 1 / sqrt(2 ESS) (a few hundredths here)
    tol = 4 / np.sqrt(2 * res.ess_bulk)
    np.testing.assert_allclose(np.sqrt(np.diag(res.covariance)), sd, rtol=float(np.max(tol)))
    corr_q = cov[0, 1] / np.prod(sd)
    corr_s = res.covariance[0, 1] / np.sqrt(np.prod(np.diag(res.covariance)))
    assert abs(corr_s - corr_q) < 0.05
    assert abs(corr_q) > 0.05  # the two parameters are correlated: the check above is not trivial


def test_exact_sampler_targets_the_nonlinear_density(case):
    """The log posterior stored with every draw is the exact one (up to its constant), not the linearised one."""
    model, idx, start, _, _, res = case
    th = res.tree["posterior"]["theta"].values.reshape(-1, 2)
    lp = res.tree["sample_stats"]["lp"].values.reshape(-1)
    pick = np.random.default_rng(1).choice(th.shape[0], size=200, replace=False)
    diff = lp[pick] - _log_density(model, idx, th[pick])
    assert np.ptp(diff) < 1e-6  # a constant: the normalisation of likelihood and prior
    # the linearisation at the MAP differs from the exact density at these draws by more than that
    lin = linearise(model, start.theta).with_measured(model.y_measured)
    diff_lin = lp[pick] - _log_density(lin, idx, th[pick])
    assert np.ptp(diff_lin) > 100 * np.ptp(diff)
