"""Automatic lambda and k: every rule against a closed form or a brute-force implementation."""

import numpy as np
import pytest
from scipy.optimize import minimize_scalar
from scipy.stats import multivariate_normal

from bayescal.errors import InputError
from bayescal.identify import filter_factors, filtered_solve
from bayescal.identify.choose import (
    DEFAULT_RULE,
    RULES,
    _menger_curvature,
    choose_linear,
    choose_regularisation,
    linearised_problem,
)
from bayescal.measurement import MeasurementModel


# ---------------------------------------------------------------- filter factors
def test_filter_factors_closed_forms():
    s = np.array([10.0, 3.0, 1.0, 0.1, 1e-4])
    assert np.array_equal(filter_factors(s, "tsvd", k=3), [1, 1, 1, 0, 0])
    lam = 0.7
    np.testing.assert_allclose(filter_factors(s, "ridge", lam=lam), s**2 / (s**2 + lam), rtol=1e-15)
    assert np.array_equal(filter_factors(s, "ls"), np.ones(5))


def test_filtered_solve_matches_normal_equations_and_truncated_pinv(rng):
    A = rng.normal(size=(20, 6)) @ np.diag([5, 2, 1, 0.5, 0.1, 0.01])
    z = rng.normal(size=20)
    lam = 0.3
    x_re = filtered_solve(A, z, "ridge", lam=lam).x
    np.testing.assert_allclose(x_re, np.linalg.solve(A.T @ A + lam * np.eye(6), A.T @ z), rtol=1e-10)
    U, s, Vt = np.linalg.svd(A, full_matrices=False)
    A3 = (U[:, :3] * s[:3]) @ Vt[:3]
    np.testing.assert_allclose(filtered_solve(A, z, "tsvd", k=3).x, np.linalg.pinv(A3, rcond=1e-12) @ z, rtol=1e-9)
    np.testing.assert_allclose(filtered_solve(A, z, "tsvd", k=6).x, np.linalg.lstsq(A, z, rcond=None)[0], rtol=1e-9)


# ------------------------------------------------------- a problem with a known answer
def _stacked_identity(p=4, m=8, a=10.0, b=4.0):
    """A = [I_p; 0]: |z_1|^2 = a, |z_2|^2 = b.  With t = lam / (1 + lam):
    |r|^2 = t^2 a + b, N - sum f = m + p t."""
    A = np.vstack([np.eye(p), np.zeros((m, p))])
    z = np.concatenate([np.full(p, np.sqrt(a / p)), np.full(m, np.sqrt(b / m))])
    return A, z, p, m, a, b


def test_gcv_minimiser_closed_form():
    A, z, p, m, a, b = _stacked_identity()
    t = p * b / (a * m)  # d GCV / dt = 0  <=>  t a m = p b
    lam_star = t / (1 - t)
    grid = np.logspace(-3, 3, 6001)
    ch = choose_linear(A, z, "ridge", rule="gcv", grid=grid)
    assert ch.value == pytest.approx(lam_star, rel=3e-3)
    tt = grid / (1 + grid)
    np.testing.assert_allclose(ch.curves["gcv"], (tt**2 * a + b) / (m + p * tt) ** 2, rtol=1e-10)


def test_discrepancy_closed_form():
    A, z, p, m, a, b = _stacked_identity()
    t = (p + np.sqrt(p**2 - 4 * a * (b - m))) / (2 * a)  # t^2 a + b = m + p t, the positive root
    grid = np.logspace(-3, 3, 6001)
    ch = choose_linear(A, z, "ridge", rule="discrepancy", grid=grid)
    assert ch.value == pytest.approx(t / (1 - t), rel=3e-3)


def _brute_ridge(A, z, lam):
    p = A.shape[1]
    x = np.linalg.solve(A.T @ A + lam * np.eye(p), A.T @ z)
    H = A @ np.linalg.solve(A.T @ A + lam * np.eye(p), A.T)
    return x, H


def test_ridge_rules_against_dense_brute_force(rng):
    N, p = 40, 6
    A = rng.normal(size=(N, p)) * np.array([8, 4, 2, 1, 0.3, 0.05])
    z = A @ rng.normal(size=p) + rng.normal(size=N)
    grid = np.logspace(-4, 3, 71)
    ch = choose_linear(A, z, "ridge", grid=grid)
    gcv, ev = [], []
    for lam in grid:
        x, H = _brute_ridge(A, z, lam)
        r = z - A @ x
        gcv.append(r @ r / np.trace(np.eye(N) - H) ** 2)
        ev.append(multivariate_normal(np.zeros(N), np.eye(N) + A @ A.T / lam).logpdf(z))
        assert ch.curves["residual_norm"][len(gcv) - 1] == pytest.approx(np.linalg.norm(r), rel=1e-9)
        assert ch.curves["solution_norm"][len(gcv) - 1] == pytest.approx(np.linalg.norm(x), rel=1e-9)
    np.testing.assert_allclose(ch.curves["gcv"], gcv, rtol=1e-8)
    np.testing.assert_allclose(ch.curves["log_evidence"], ev, rtol=1e-9)
    assert ch.choices["gcv"] == grid[np.argmin(gcv)]
    assert ch.choices["evidence"] == grid[np.argmax(ev)]
    assert set(ch.choices) == set(RULES) and ch.value == ch.choices[DEFAULT_RULE["ridge"]]


def test_evidence_with_unknown_noise_profiles_the_scale():
    rng = np.random.default_rng(7)  # own generator: the answer must not depend on which tests ran before
    N, p = 30, 4
    A = rng.normal(size=(N, p))
    z = 3.0 * (A @ rng.normal(size=p) + rng.normal(size=N))  # noise sigma 3, not 1
    grid = np.logspace(-3, 3, 61)
    ch = choose_linear(A, z, "ridge", grid=grid, noise_known=False)
    brute = []
    for lam in grid:
        # dense Gaussian log density of z ~ N(0, s2 (I + A A^T / lam)), maximised numerically over log s2
        C = np.eye(N) + A @ A.T / lam
        quad, logdet = z @ np.linalg.solve(C, z), np.linalg.slogdet(C)[1]
        nll = lambda t: 0.5 * (quad * np.exp(-t) + N * t + logdet + N * np.log(2 * np.pi))  # noqa: E731
        brute.append(-minimize_scalar(nll, bounds=(-5.0, 10.0), method="bounded", options={"xatol": 1e-10}).fun)
    assert ch.choices["evidence"] == grid[np.argmax(brute)]
    np.testing.assert_allclose(ch.curves["log_evidence"], brute, atol=1e-6)


def test_ridge_lcurve_curvature_matches_finite_differences(rng):
    A = rng.normal(size=(50, 8)) * np.logspace(1, -3, 8)
    z = A @ rng.normal(size=8) + 0.01 * rng.normal(size=50)
    grid = np.logspace(-8, 3, 4001)
    ch = choose_linear(A, z, "ridge", grid=grid)
    t = np.log(grid)
    x, y = np.log(ch.curves["residual_norm"]), np.log(ch.curves["solution_norm"])
    x1, y1 = np.gradient(x, t), np.gradient(y, t)
    x2, y2 = np.gradient(x1, t), np.gradient(y1, t)
    fd = (x1 * y2 - x2 * y1) / (x1**2 + y1**2) ** 1.5
    i = np.argmax(ch.curves["curvature"])
    assert 10 < i < grid.size - 10
    sl = slice(i - 200, i + 200)
    np.testing.assert_allclose(ch.curves["curvature"][sl], fd[sl], rtol=2e-2, atol=1e-2 * abs(fd[i]))
    assert ch.curves["curvature"][i] > 0  # the L corner turns counter-clockwise as lambda grows


def test_menger_curvature_on_a_circle():
    ang = np.linspace(0, 1.5, 20)
    x, y = 2.0 * np.cos(ang), 2.0 * np.sin(ang)  # counter-clockwise, radius 2
    k = _menger_curvature(x, y)
    np.testing.assert_allclose(k[1:-1], 0.5, rtol=1e-10)
    assert np.isneginf(k[0]) and np.isneginf(k[-1])


def test_tsvd_rules_against_brute_force(rng):
    N, p = 36, 7
    A = rng.normal(size=(N, p)) * np.logspace(1, -3, p)
    z = A @ rng.normal(size=p) + rng.normal(size=N)
    ch = choose_linear(A, z, "tsvd")
    U, s, Vt = np.linalg.svd(A, full_matrices=False)
    res2, ev = [], []
    for k in range(1, p + 1):
        x = filtered_solve(A, z, "tsvd", k=k).x
        res2.append(np.sum((z - A @ x) ** 2))
        Ak = A @ Vt[:k].T
        ev.append(max(multivariate_normal(np.zeros(N), np.eye(N) + Ak @ Ak.T / lam).logpdf(z)
                      for lam in np.logspace(-4, 4, 161)))
    res2 = np.array(res2)
    ks = np.arange(1, p + 1)
    assert ch.choices["gcv"] == ks[np.argmin(res2 / (N - ks) ** 2)]
    ok = np.flatnonzero(res2 <= N - ks)
    assert ch.choices["discrepancy"] == (ks[ok[0]] if ok.size else ks[np.argmin(res2 - (N - ks))])
    np.testing.assert_allclose(ch.curves["log_evidence"], ev, atol=0.1)  # brute force maximises on a coarser grid
    assert ch.choices["evidence"] == ks[np.argmax(ev)]


@pytest.mark.parametrize("noise_known", [True, False])
def test_risk_rule_is_the_bayes_decision_under_the_evidence_prior(rng, noise_known):
    """Posterior risk against Bayesian linear regression written without the SVD.

    Prior x ~ N(0, sigma2 / lam_ev I) with lam_ev the ridge evidence choice;
    posterior N(m, Sigma), m = (A^T A + lam I)^-1 A^T z,
    Sigma = sigma2 (A^T A + lam I)^-1 (sigma2 = 1, or the profiled noise
    scale).  Risk of an estimate x_v: |x_v - m|^2 + tr Sigma.
    """
    N, p = 40, 8
    A = rng.normal(size=(N, p)) * np.logspace(1, -2, p)
    z = 2.0 * (A @ rng.normal(size=p) + rng.normal(size=N))  # noise scale 2: profiling matters
    ridge = choose_linear(A, z, "ridge", noise_known=noise_known)
    lam = ridge.choices["evidence"]
    H = A.T @ A + lam * np.eye(p)
    m = np.linalg.solve(H, A.T @ z)
    if noise_known:
        sigma2 = 1.0
    else:  # profiled: sigma2 = z^T (I + A A^T / lam)^-1 z / N
        sigma2 = z @ np.linalg.solve(np.eye(N) + A @ A.T / lam, z) / N
    trace = sigma2 * np.trace(np.linalg.inv(H))
    ch = choose_linear(A, z, "tsvd", noise_known=noise_known)
    assert ch.curves["risk_prior_ratio"] == pytest.approx(lam)
    brute = np.array([np.sum((filtered_solve(A, z, "tsvd", k=k).x - m) ** 2) + trace for k in range(1, p + 1)])
    np.testing.assert_allclose(ch.curves["posterior_risk"], brute, rtol=1e-8)
    s = np.linalg.svd(A, compute_uv=False)
    assert ch.choices["risk"] == np.argmin(brute) + 1 == np.sum(s**2 > lam)  # keep what beats the prior
    # ridge: the posterior mean is the ridge solution at lam_ev, so risk and evidence coincide
    assert ridge.choices["risk"] == ridge.choices["evidence"]
    i = int(np.argmin(np.abs(ridge.grid - lam)))
    assert ridge.curves["posterior_risk"][i] == pytest.approx(trace, rel=1e-9)


def test_cv_is_leave_one_pose_out_when_folds_equal_poses(rng):
    n_poses, dof, p = 8, 3, 4
    A = rng.normal(size=(n_poses * dof, p))
    z = A @ rng.normal(size=p) + rng.normal(size=n_poses * dof)
    groups = np.repeat(np.arange(n_poses), dof)
    grid = np.logspace(-2, 2, 9)
    ch = choose_linear(A, z, "ridge", groups=groups, folds=n_poses, grid=grid)
    brute = np.zeros(grid.size)
    for g in range(n_poses):
        te = groups == g
        for j, lam in enumerate(grid):
            x = np.linalg.solve(A[~te].T @ A[~te] + lam * np.eye(p), A[~te].T @ z[~te])
            brute[j] += np.sum((z[te] - A[te] @ x) ** 2)
    np.testing.assert_allclose(ch.curves["cv"], brute / z.size, rtol=1e-9)
    assert ch.folds == n_poses and ch.choices["cv"] == grid[np.argmin(brute)]


def test_bad_rule_and_method():
    A, z = np.eye(3), np.ones(3)
    with pytest.raises(InputError, match="rule"):
        choose_linear(A, z, "ridge", rule="magic")
    with pytest.raises(InputError, match="method"):
        choose_linear(A, z, "ls")


# ------------------------------------------------------------- on a machine
def test_ridge_choice_is_a_fixed_point_and_report(prs3, sim6):
    model = MeasurementModel.from_recording(prs3, sim6.recording)
    choice, res = choose_regularisation(model, "ridge", rule="gcv")
    assert res.success and res.lam == pytest.approx(choice.value)
    idx = np.flatnonzero(res.free)
    A, z, groups = linearised_problem(model, res.theta, idx, prs3.tolerance)
    again = choose_linear(A, z, "ridge", rule="gcv", groups=groups)
    assert abs(np.log(again.value / choice.value)) < np.log(1.1)  # rule and Gauss-Newton agree
    assert res.extras["regularisation"]["value"] == choice.value
    rep = choice.report()
    assert "gcv" in rep and "<- used" in rep and all(r in rep for r in RULES)


def test_tsvd_choice_uses_start_geometry(prs3, sim6):
    model = MeasurementModel.from_recording(prs3, sim6.recording)
    choice, res = choose_regularisation(model, "tsvd")
    assert res.success and res.k == choice.value == choice.choices["targets"]  # the TSVD default
    d = choice.to_dict()
    assert d["method"] == "tsvd" and len(d["curves"]["gcv"]) == choice.n_params
    # the calibration travels with the choice, and its scores pick the value
    assert d["target_rule"]["method"] == "tsvd" and set(d["target_rule"]["relaxed"]) == {"0.5", "1", "2", "4"}
    assert choice.grid[int(np.argmin(d["curves"]["targets_score"]))] == choice.value
    assert "targets" in choice.report() and "<- used" in choice.report()


@pytest.mark.parametrize("method", ["ridge", "tsvd"])
def test_no_stated_noise_and_nothing_to_estimate_it_from_is_refused(method):
    # one printer height (no [measurement]), or 19 copies of it: "Probabilities contain NaN", a traceback
    from bayescal.errors import InputError

    rng = np.random.default_rng(3)
    a = rng.normal(size=(1, 5))
    for A in (a, np.repeat(a, 19, axis=0)):
        z = np.full(A.shape[0], 0.7)
        with pytest.raises(InputError, match=r"'auto': no noise stated and no residual degrees of freedom .*\(1 distinct"):
            choose_linear(A, z, method, noise_known=False)
    A = rng.normal(size=(12, 5))
    assert choose_linear(A, A @ rng.normal(size=5) + 0.1 * rng.normal(size=12), method, noise_known=False) is not None
