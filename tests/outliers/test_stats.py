"""The per-pose outlier test and the IRLS weights (bayescal/outliers/stats.py)."""

from dataclasses import replace

import numpy as np
import pytest
from scipy import stats

from bayescal.identify import identify, whitened_system
from bayescal.measurement import MeasurementModel
from bayescal.outliers import (
    EXCLUDE_FACTOR,
    MAX_FRACTION,
    exclusion_weights,
    irls_weights,
    loss_weights,
    pose_test,
    pose_test_linear,
    recording_lines,
    weighted_model,
)
from bayescal.simulate import simulate_recording


def _refit_statistics(A, z, d, lam, w, extra=None):
    """Brute force: refit without each pose, deleted residual against its predictive covariance.

    ``extra`` (rows, p2): a part of the truth the fit does not estimate, prior N(0, I), added to the covariance.
    """
    n = A.shape[0] // d
    W = np.repeat(w, d)
    p = A.shape[1]
    M = A.T @ (W[:, None] * A) + lam * np.eye(p)
    x = np.linalg.solve(M, A.T @ (W * z))
    t, cook = np.empty(n), np.empty(n)
    trH = np.trace(A @ np.linalg.solve(M, A.T * W))
    for i in range(n):
        rows = slice(i * d, (i + 1) * d)
        keep = np.ones(A.shape[0], dtype=bool)
        keep[rows] = False
        Mi = A[keep].T @ (W[keep, None] * A[keep]) + lam * np.eye(p)
        xi = np.linalg.solve(Mi, A[keep].T @ (W[keep] * z[keep]))
        e = z[rows] - A[rows] @ xi
        cov = np.eye(d) + A[rows] @ np.linalg.solve(Mi, A[rows].T)
        if extra is not None:
            cov += extra[rows] @ extra[rows].T
        t[i] = e @ np.linalg.solve(cov, e)
        cook[i] = (x - xi) @ M @ (x - xi) / trH
    return z - A @ x, t, cook


@pytest.mark.parametrize("lam,weighted", [(0.0, False), (0.0, True), (1.0, False), (0.3, True)])
def test_statistic_and_cook_equal_refitting_without_the_pose(lam, weighted):
    rng = np.random.default_rng(3)
    n, d, p = 15, 3, 6
    A = rng.normal(size=(n * d, p))
    z = rng.normal(size=n * d)
    z[4 * d] += 8.0  # one gross pose
    w = rng.uniform(0.05, 1.0, n) if weighted else np.ones(n)
    r, t, cook = _refit_statistics(A, z, d, lam, w)
    res = pose_test_linear(A, r, d, lam=lam, weights=w)
    np.testing.assert_allclose(res.statistic, t, rtol=1e-8)
    np.testing.assert_allclose(res.cooks_distance, cook, rtol=1e-8)
    np.testing.assert_array_equal(res.lines, np.arange(n) + 2)
    assert res.flagged_index[0] == 4


def test_ridge_factor_and_svd_routes_agree(monkeypatch):
    # with a ridge the leverages come from a triangular factor (bayescal.tallqr); the SVD takes over where it declines
    import bayescal.outliers.stats as st

    rng = np.random.default_rng(8)
    n, d, p = 400, 3, 7
    A = rng.normal(size=(n * d, p)) * np.logspace(0, 3, p)
    z = rng.normal(size=n * d)
    w = rng.uniform(0.05, 1.0, n)
    fast = pose_test_linear(A, z, d, lam=0.5, weights=w)
    monkeypatch.setattr(st, "ridge_factor", lambda *a, **k: None)
    slow = pose_test_linear(A, z, d, lam=0.5, weights=w)
    np.testing.assert_allclose(fast.statistic, slow.statistic, rtol=1e-10)
    np.testing.assert_allclose(fast.leverage, slow.leverage, rtol=1e-10)
    np.testing.assert_allclose(fast.cooks_distance, slow.cooks_distance, rtol=1e-10)


def test_tsvd_statistic_is_least_squares_in_the_kept_subspace_plus_the_prior_of_the_dropped():
    rng = np.random.default_rng(4)
    n, d, p, k = 12, 3, 6, 4
    A = rng.normal(size=(n * d, p)) * np.array([10, 5, 2, 1, 1e-3, 1e-4])
    z = rng.normal(size=n * d)
    Vt = np.linalg.svd(A, full_matrices=False)[2]
    B = A @ Vt[:k].T
    r, t, _ = _refit_statistics(B, z, d, 0.0, np.ones(n), extra=A @ Vt[k:].T)
    res = pose_test_linear(A, r, d, k=k)
    np.testing.assert_allclose(res.statistic, t, rtol=1e-8)


def test_statistic_is_chi2_or_f_under_the_linear_gaussian_model():
    """Exact reference distributions: LS and ridge under its prior (chi2), unknown noise (F)."""
    rng = np.random.default_rng(5)
    n, d, p, lam = 30, 3, 8, 2.0
    A = rng.normal(size=(n * d, p))
    t_ls, t_ridge, f_unknown = [], [], []
    for _ in range(150):
        z = A @ rng.normal(size=p) * 5 + rng.normal(size=n * d)
        x = np.linalg.lstsq(A, z, rcond=None)[0]
        t_ls.append(pose_test_linear(A, z - A @ x, d).statistic)
        z = A @ (rng.normal(size=p) / np.sqrt(lam)) + rng.normal(size=n * d)  # prior x ~ N(0, I / lam)
        x = np.linalg.solve(A.T @ A + lam * np.eye(p), A.T @ z)
        t_ridge.append(pose_test_linear(A, z - A @ x, d, lam=lam).statistic)
        z = A @ rng.normal(size=p) + 3.0 * rng.normal(size=n * d)  # noise 3x the whitening sigma, unknown
        x = np.linalg.lstsq(A, z, rcond=None)[0]
        res = pose_test_linear(A, z - A @ x, d, noise_known=False)
        f_unknown.append(res.statistic)
    assert stats.kstest(np.ravel(t_ls), stats.chi2(d).cdf).pvalue > 1e-3
    assert stats.kstest(np.ravel(t_ridge), stats.chi2(d).cdf).pvalue > 1e-3
    assert res.distribution == "F" and res.dof == (d, n * d - p - d)
    assert stats.kstest(np.ravel(f_unknown), stats.f(d, n * d - p - d).cdf).pvalue > 1e-3
    # and the chi-square test with the wrong (too small) sigma would not have been uniform
    assert stats.kstest(9 * np.ravel(t_ls), stats.chi2(d).cdf).pvalue < 1e-6


def test_sidak_controls_the_family_wise_rate():
    rng = np.random.default_rng(6)
    n, d, p = 40, 3, 6
    A = rng.normal(size=(n * d, p))
    any_flag = []
    for _ in range(400):
        z = rng.normal(size=n * d)
        x = np.linalg.lstsq(A, z, rcond=None)[0]
        any_flag.append(pose_test_linear(A, z - A @ x, d, alpha=0.2).flagged.any())
    # binomial(400, 0.2): mean 80, sd 8
    assert 56 <= sum(any_flag) <= 104


def test_clean_recordings_give_fewer_than_one_false_outlier_per_thousand_poses(prs3):
    """3,000 poses of the nonlinear 3-PRS with MAP: the single-pose p-values are uniform, the family-wise
    level holds at alpha = 0.5, and at the default level at most 3 poses are flagged (<= 1 per 1,000)."""
    pvals, flagged, any_half = [], 0, 0
    for seed in range(30):
        rec = simulate_recording(prs3, 100, seed=seed).recording
        model = MeasurementModel.from_recording(prs3, rec)
        res = identify(model, method="map")
        t = pose_test(model, res.theta, res.free, lam=1.0)
        pvals.append(t.p_value)
        flagged += int(t.flagged.sum())
        any_half += bool(np.any(t.p_adjusted < 0.5))
    assert stats.kstest(np.ravel(pvals), "uniform").pvalue > 1e-3
    assert 7 <= any_half <= 23  # binomial(30, 0.5)
    assert flagged <= 3


def test_weights_scale_each_pose_sigma_by_one_over_root_w(prs3):
    """The one rule every outlier step weights poses by: sigma / sqrt(w); an excluded pose's sigma x 1e6."""
    model = MeasurementModel.from_recording(prs3, simulate_recording(prs3, 10, seed=0).recording)
    assert weighted_model(model, None) is model
    w = np.linspace(0.1, 1.0, 10)
    np.testing.assert_allclose(weighted_model(model, w).row_sigma, np.asarray(model.row_sigma) / np.sqrt(w)[:, None])
    excluded = np.zeros(10, dtype=bool)
    excluded[[2, 7]] = True
    np.testing.assert_array_equal(exclusion_weights(excluded), np.where(excluded, 1e-12, 1.0))
    sig = np.asarray(weighted_model(model, exclusion_weights(excluded)).row_sigma)
    np.testing.assert_allclose(sig[excluded], np.asarray(model.row_sigma)[excluded] * EXCLUDE_FACTOR)
    np.testing.assert_array_equal(sig[~excluded], np.asarray(model.row_sigma)[~excluded])


def test_too_many_is_more_than_the_share_of_a_model_mismatch():
    """40 poses: 4 flagged (10 %) are outliers, 5 are a model mismatch."""
    rng = np.random.default_rng(3)
    A, d = rng.normal(size=(120, 4)), 3
    z = rng.normal(size=120)
    base = pose_test_linear(A, z - A @ np.linalg.lstsq(A, z, rcond=None)[0], d)
    assert MAX_FRACTION == 0.1 and base.n_poses == 40
    for k, many in [(0, False), (4, False), (5, True)]:
        flagged = np.arange(40) < k
        assert replace(base, flagged=flagged).too_many is many


def test_loss_weights_by_hand():
    u = np.array([0.0, 6.0, 100.0])
    np.testing.assert_allclose(loss_weights(u, 6, loss="t", nu=4.0), [10 / 4, 10 / 10, 10 / 104])
    c = np.sqrt(stats.chi2.ppf(0.95, 6))
    np.testing.assert_allclose(loss_weights(u, 6, loss="huber"), [1.0, 1.0, c / 10.0])


def test_irls_fixed_point_is_stationary_for_the_student_t_posterior(prs3):
    """At convergence, the gradient of sum_i (nu + d) log(1 + u_i / nu) + |phi|^2 vanishes (MAP with a t likelihood)."""
    sim = simulate_recording(prs3, 40, seed=11)
    model = MeasurementModel.from_recording(prs3, sim.recording)
    y = model.y_measured.copy()
    y[7, :3] += [0.2, -0.1, 0.05]
    from dataclasses import replace

    model = replace(model, y_measured=y)
    nu = 4.0

    def fit(m):
        return identify(m, method="map", free="all")

    ir = irls_weights(model, fit, loss="t", nu=nu, tol=1e-7, max_rounds=200)
    assert ir.converged
    theta = ir.result.theta
    r, J = whitened_system(model, theta, model.predict(theta))
    rp = r.reshape(model.n_poses, model.dof)
    u = np.sum(rp**2, axis=1)
    w = (nu + model.dof) / (nu + u)
    S = prs3.tolerance
    grad = -2 * (J * S).T @ (np.repeat(w, model.dof) * r) + 2 * theta / S
    assert np.max(np.abs(grad)) < 1e-3 * np.max(np.abs((J * S).T @ r))
    assert ir.weights[7] < 0.05 and np.median(ir.weights) > 0.7


def test_recording_lines_default_and_given():
    np.testing.assert_array_equal(recording_lines(3), [2, 3, 4])

    class Rec:
        lines = [2, 5, 9]

    np.testing.assert_array_equal(recording_lines(3, Rec()), [2, 5, 9])


def test_truncated_tsvd_p_values_are_uniform_on_clean_recordings(prs3):
    """k = 15 of 33: the dropped directions' truncation bias is part of the reference (without it KS p ~ 1e-8)."""
    pvals = []
    for seed in range(12):
        rec = simulate_recording(prs3, 100, seed=100 + seed).recording
        model = MeasurementModel.from_recording(prs3, rec)
        res = identify(model, method="tsvd", k=15)
        pvals.append(pose_test(model, res.theta, res.free, k=15).p_value)
    assert stats.kstest(np.ravel(pvals), "uniform").pvalue > 1e-3
