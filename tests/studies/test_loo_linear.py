"""Closed-form leave-one-out errors of linear estimators (studies.loo_linear) against textbook identities."""

import numpy as np
from scipy.stats import multivariate_normal

from studies.loo_linear import expected_sq_error, log_evidence, loo_errors, loo_operator, map_gain, wls_gain


def _problem(seed=0, n=12, p=4):
    rng = np.random.default_rng(seed)
    return rng.normal(size=(n, p)), rng.normal(size=n)


def test_least_squares_loo_is_the_press_residual():
    # PRESS identity: the LOO error of ordinary LS is r_i / (1 - h_ii)
    J, y = _problem()
    H = J @ np.linalg.solve(J.T @ J, J.T)
    r = y - H @ y
    err = loo_errors(J, y, wls_gain(lambda rows: np.ones(rows.size)))
    np.testing.assert_allclose(err, r / (1 - np.diag(H)), rtol=1e-10)


def test_weighted_least_squares_loo_matches_a_refit():
    J, y = _problem(1)
    w = np.linspace(0.5, 3.0, y.size)
    err = loo_errors(J, y, wls_gain(lambda rows: w[rows]))
    for i in (0, 5, 11):
        keep = np.delete(np.arange(y.size), i)
        x = np.linalg.lstsq(J[keep] * np.sqrt(w[keep])[:, None], y[keep] * np.sqrt(w[keep]), rcond=None)[0]
        assert abs(err[i] - (y[i] - J[i] @ x)) < 1e-10


def test_map_gain_is_the_information_form_posterior_mean():
    J, y = _problem(2, n=6, p=9)  # more parameters than rows: only the prior makes it solvable
    sigma, tol = np.linspace(0.1, 0.3, 6), np.linspace(0.5, 2.0, 9)
    rows = np.arange(6)
    x = map_gain(sigma, tol)(J, rows) @ y
    A = J.T @ (J / sigma[:, None] ** 2) + np.diag(1 / tol**2)
    np.testing.assert_allclose(x, np.linalg.solve(A, J.T @ (y / sigma**2)), rtol=1e-9, atol=1e-12)


def test_expected_error_of_the_leave_one_out_mean():
    # y_i = theta + e_i, predicted by the mean of the others: err_i = e_i - mean(e_others),
    # E err_i^2 = sigma^2 (1 + 1/(n-1)) whatever theta's spread
    n, sigma = 8, 0.3
    J = np.ones((n, 1))
    M = loo_operator(J, wls_gain(lambda rows: np.ones(rows.size)))
    e2 = expected_sq_error(M, J, [5.0], np.full(n, sigma))
    np.testing.assert_allclose(e2, sigma**2 * (1 + 1 / (n - 1)), rtol=1e-12)


def test_log_evidence_is_the_gaussian_log_density():
    J, y = _problem(3, n=7, p=3)
    tol, sigma = np.array([1.0, 0.5, 2.0]), np.full(7, 0.4)
    cov = J @ np.diag(tol**2) @ J.T + np.diag(sigma**2)
    assert abs(log_evidence(J, y, tol, sigma) - multivariate_normal(np.zeros(7), cov).logpdf(y)) < 1e-9


def test_profiled_evidence_is_the_maximum_over_the_noise_scale():
    from scipy.optimize import minimize_scalar

    from studies.loo_linear import evidence_ratio, profiled_log_evidence

    J, y = _problem(4, n=9, p=3)
    tol, sigma = np.array([1.0, 0.5, 2.0]), np.linspace(0.2, 0.5, 9)
    for ratio in (0.3, 1.0, 4.0):
        best = minimize_scalar(lambda v: -log_evidence(J, y, ratio * np.exp(v) * tol, np.exp(v) * sigma),
                               bounds=(-6, 6), method="bounded", options={"xatol": 1e-10})
        assert abs(profiled_log_evidence(J, y, tol, sigma, ratio) + best.fun) < 1e-7
    # evidence_ratio is the maximiser: no better value either side of it (data with signal: an interior maximum)
    y = J @ np.array([1.5, -0.8, 2.5]) + sigma * np.random.default_rng(5).normal(size=9)
    r = evidence_ratio(J, y, tol, sigma)
    assert 0.06 < r < 19
    for f in (1.05, 1 / 1.05):
        assert profiled_log_evidence(J, y, tol, sigma, r) >= profiled_log_evidence(J, y, tol, sigma, r * f)
