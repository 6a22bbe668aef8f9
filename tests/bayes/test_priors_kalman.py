"""MAP == ridge(lam=1) with tolerance scaling; Kalman with Q = 0 == batch MAP; EKF == linear KF; UKF."""

from __future__ import annotations

import numpy as np
import pytest
from filterpy.kalman import KalmanFilter
from scipy import stats

from bayescal.bayes import kalman_filter, linearise, map_estimate, prior_from_machine
from bayescal.bayes.priors import GaussianPrior
from bayescal.errors import InputError
from bayescal.identify import identify
from bayescal.measurement import MeasurementModel
from bayescal.simulate import simulate_recording


@pytest.fixture(scope="module")
def model6(prs3, sim6):
    return MeasurementModel.from_recording(prs3, sim6.recording)


@pytest.fixture(scope="module")
def lin_model(prs3, model6):
    """A linear-Gaussian problem: the model linearised at nominal, data from it with noise."""
    lin = linearise(model6)
    rng = np.random.default_rng(5)
    theta_true = prior_from_machine(prs3).sample(1, rng)[0]
    y = lin.predict(theta_true).y + rng.normal(size=lin.y0.shape) * lin.sigma
    return lin.with_measured(y)


def batch_map(model, prior, idx):
    """solve(P0^-1 + A^T R^-1 A, P0^-1 x0 + A^T R^-1 z) on a linear model, state = theta[idx]."""
    sig = model.sigma
    A = (model.J[:, :, idx] / sig[None, :, None]).reshape(-1, idx.size)
    base = prior.mean.copy()
    z = ((model.y_measured - model.y0 + model.J @ model.theta_ref - model.J @ base) / sig).reshape(-1)
    z = z + A @ base[idx]
    P0inv = np.diag(1 / prior.std[idx] ** 2)
    return np.linalg.solve(P0inv + A.T @ A, P0inv @ prior.mean[idx] + A.T @ z), np.linalg.inv(P0inv + A.T @ A)


def test_map_equals_ridge_lam1_and_lam_is_variance_ratio(prs3, model6):
    m = map_estimate(model6)
    r = identify(model6, method="ridge", lam=1.0)
    assert m.method == "map" and m.success
    np.testing.assert_allclose(m.theta, r.theta, rtol=0, atol=1e-12)
    np.testing.assert_allclose(m.covariance, r.covariance, rtol=1e-9, atol=0)
    # ridge with lam == MAP with tolerances divided by sqrt(lam): lam is the noise-to-prior variance ratio
    lam = 4.0
    r4 = identify(model6, method="ridge", lam=lam, free=m.free_names)
    prior = prior_from_machine(prs3, scale=1 / np.sqrt(lam))
    m4 = map_estimate(model6, prior=prior, free=list(m.free_names))
    np.testing.assert_allclose(m4.theta, r4.theta, rtol=0, atol=1e-10)


def test_map_is_the_minimum_of_the_log_posterior(prs3, lin_model):
    """On a linear model, the MAP equals the closed-form posterior mean, also with a non-zero prior mean."""
    rng = np.random.default_rng(3)
    prior0 = prior_from_machine(prs3)
    prior = prior_from_machine(prs3, mean=prior0.sample(1, rng)[0] * 0.5)
    m = map_estimate(lin_model, prior=prior, free="all")
    idx = np.arange(prs3.n_params)
    x, C = batch_map(lin_model, prior, idx)
    np.testing.assert_allclose(m.theta, x, rtol=1e-7, atol=1e-12 * prior.std.max())
    np.testing.assert_allclose(m.covariance, C, rtol=1e-6, atol=1e-12 * prior.std.max() ** 2)


def test_map_rejects_other_lam(model6):
    with pytest.raises(InputError, match="lam"):
        identify(model6, method="map", lam=2.0)


@pytest.mark.parametrize("variant", ["ekf", "ukf"])
def test_kalman_q0_linear_equals_batch_map(prs3, lin_model, variant):
    prior = prior_from_machine(prs3)
    res = kalman_filter(lin_model, variant=variant)
    idx = np.flatnonzero(res.free)
    x, C = batch_map(lin_model, prior, idx)
    rel = np.linalg.norm(res.means[-1] - x) / np.linalg.norm(x)
    assert rel < 1e-9
    np.testing.assert_allclose(res.covariance, C, rtol=1e-6, atol=1e-9 * np.max(np.abs(C)))
    # history: prior first, one row per pose, std never grows without process noise
    assert res.means.shape == (lin_model.n_poses + 1, idx.size)
    assert np.all(np.diff(res.stds, axis=0) <= 1e-12)
    assert np.all(np.diff(res.workspace_accuracy) <= 1e-12)


def test_ekf_on_linear_model_equals_filterpy_linear_kf(prs3, lin_model):
    res = kalman_filter(lin_model, process_noise=0.05)
    idx = np.flatnonzero(res.free)
    prior = prior_from_machine(prs3)
    kf = KalmanFilter(dim_x=idx.size, dim_z=lin_model.dof)
    kf.x = prior.mean[idx].reshape(-1, 1).copy()
    kf.P = np.diag(prior.std[idx] ** 2)
    kf.R = np.diag(lin_model.sigma**2)
    kf.Q = np.diag(res.process_noise**2)
    kf.F = np.eye(idx.size)
    for i in range(lin_model.n_poses):
        if i > 0:
            kf.predict()
        H = lin_model.J[i][:, idx]
        # z - (h(x_ref) - H x_ref): the affine offset moved to the measurement
        z = lin_model.y_measured[i] - lin_model.y0[i] + lin_model.J[i] @ lin_model.theta_ref
        kf.update(z.reshape(-1, 1), H=H)
        np.testing.assert_allclose(np.ravel(kf.x), res.means[i + 1], rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(kf.P, res.covariances[i + 1], rtol=1e-7, atol=1e-15)
    # process noise lets the std grow between poses: final std above the static filter's
    static = kalman_filter(lin_model)
    assert np.all(res.stds[-1] >= static.stds[-1])


def test_filters_on_the_nonlinear_model_agree_with_map(model6):
    m = map_estimate(model6)
    for variant in ("ekf", "ukf"):
        res = kalman_filter(model6, variant=variant)
        assert res.success
        np.testing.assert_array_equal(res.free, m.free)
        # one relinearised pass: equal to the MAP well within its std
        assert np.max(np.abs((res.theta - m.theta)[m.free] / m.std[m.free])) < 0.05
        np.testing.assert_allclose(res.std[m.free], m.std[m.free], rtol=0.02)
        d = res.to_dict()
        assert d["method"] == "kalman" and len(d["parameters"]) == model6.n_params
        assert "workspace accuracy" in res.report()
        assert 2 < np.mean(res.nis) < 12


def test_prior_object(prs3):
    p = prior_from_machine(prs3)
    np.testing.assert_array_equal(p.std, prs3.tolerance)
    assert p.subset([0, 2]).names == (p.names[0], p.names[2])
    x = np.zeros(prs3.n_params)
    ref = -np.sum(np.log(p.std)) - 0.5 * prs3.n_params * np.log(2 * np.pi)
    assert p.logpdf(x) == pytest.approx(ref)
    with pytest.raises(InputError, match="mean"):
        prior_from_machine(prs3, mean=np.zeros(3))
    assert isinstance(p, GaussianPrior)


def test_prior_lower_bounds_truncate_the_density_and_the_draws(prs3):
    assert prior_from_machine(prs3).lower is None  # a plain machine's geometry has no bounds
    names = ("a", "b", "c")
    plain = GaussianPrior(names, np.array([0.0, 1.0, 2.0]), np.array([1.0, 2.0, 0.5]))
    cut = GaussianPrior(names, plain.mean, plain.std, np.array([-np.inf, 0.0, -np.inf]))
    x = np.array([[0.3, 0.5, 2.1], [0.3, -0.5, 2.1]])
    assert cut.logpdf(x)[0] == plain.logpdf(x)[0] and cut.logpdf(x)[1] == -np.inf
    assert cut.subset([1, 2]).lower.tolist() == [0.0, -np.inf]
    draws = cut.sample(20000, np.random.default_rng(0))
    assert draws[:, 1].min() >= 0.0
    # a normal truncated at mean - sd/2: mean mu + sd phi(-1/2) / (1 - Phi(-1/2))
    expect = 1.0 + 2.0 * stats.norm.pdf(-0.5) / stats.norm.sf(-0.5)
    assert abs(draws[:, 1].mean() - expect) < 4 * draws[:, 1].std() / np.sqrt(draws.shape[0])


@pytest.mark.parametrize("noise", [-0.1, float("nan"), 1e300, 101.0])
def test_process_noise_outside_its_range_is_refused(prs3, noise):
    # 1e300 overflowed the state covariance: a ValueError from scipy inside the update, a traceback
    model = MeasurementModel.from_recording(prs3, simulate_recording(prs3, 4, seed=1).recording)
    with pytest.raises(InputError, match=r"process_noise: expected finite values from 0 to 100"):
        kalman_filter(model, process_noise=noise)
