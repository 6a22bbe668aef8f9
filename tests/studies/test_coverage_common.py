"""studies/coverage_common.py, shared by the two coverage studies: the projected truth solves the least-squares
problem it stands for (finite-difference Jacobian), and the z scores match a direct computation."""

from __future__ import annotations

import sys
from types import SimpleNamespace

import numpy as np
import pytest

from bayescal.identify import resolve_free
from bayescal.measurement import MeasurementModel
from tests.bayes.test_accuracy import correlated_covariance, fd_tool_point_std
from tests.conftest import ROOT

sys.path.insert(0, str(ROOT / "studies"))
try:
    import coverage_common as cc
finally:
    sys.path.remove(str(ROOT / "studies"))


@pytest.fixture(scope="module")
def setup(prs3):
    rng = np.random.default_rng(8)
    model = MeasurementModel(prs3, prs3.sample_q(20, rng), dof=6)
    idx, _ = resolve_free(model, None, np.zeros(prs3.n_params))
    free = np.zeros(prs3.n_params, bool)
    free[idx] = True
    theta = rng.normal(0.0, 1.0, prs3.n_params) * prs3.tolerance
    return model, free, theta, rng


def whitened_fd_jacobian(model, P, h=1e-6):
    """d(h(theta) / sigma)/dtheta at nominal by central differences, shape (n_poses * dof, P)."""
    cols = []
    for p in range(P):
        e = np.zeros(P)
        e[p] = h
        cols.append(((model.predict(e).y - model.predict(-e).y) / model.sigma / (2 * h)).ravel())
    return np.array(cols).T


def test_projected_truth_solves_the_reduced_least_squares_problem(prs3, setup):
    model, free, theta, _ = setup
    assert not free.all()  # the 3-PRS has unidentifiable directions: the projection matters
    teq = cc.projected_truth(model, theta, free)
    J = whitened_fd_jacobian(model, prs3.n_params)
    Ji = J[:, free]
    # normal equations of min || J_idx x - J theta ||: the reduced parameters reproduce the truth's predictions
    scale = np.linalg.norm(Ji.T @ (J @ theta))
    assert np.linalg.norm(Ji.T @ (Ji @ teq - J @ theta)) < 1e-5 * scale
    # while the truth's own identifiable part does not
    assert np.linalg.norm(Ji.T @ (Ji @ theta[free] - J @ theta)) > 1e-2 * scale
    np.testing.assert_array_equal(cc.parameter_target(model, theta, free, all_params=True), theta[free])
    np.testing.assert_array_equal(cc.parameter_target(model, theta, free, all_params=False), teq)
    np.testing.assert_array_equal(cc.projected_truth(model, theta, np.ones(prs3.n_params, bool)), theta)


def test_z_scores_against_a_direct_computation(prs3, setup):
    model, free, theta, rng = setup
    k = int(free.sum())
    C = correlated_covariance(k, 0.2 * prs3.tolerance[free], rng)
    theta_hat = theta.copy()
    theta_hat[free] += rng.multivariate_normal(np.zeros(k), C)
    res = SimpleNamespace(theta=theta_hat, free=free, covariance=C)
    q = prs3.sample_q(5, rng)
    p_true = prs3.forward(q, theta).position
    target = theta[free]
    zp, zt = cc.z_scores(prs3, res, target, q, p_true)
    np.testing.assert_allclose(zp, (theta_hat[free] - target) / np.sqrt(np.diag(C)), rtol=1e-12)
    direct = (p_true - prs3.forward(q, theta_hat).position) / fd_tool_point_std(prs3, q, theta_hat, free, C)
    np.testing.assert_allclose(zt, direct, rtol=1e-5)


def test_fit_methods_in_the_order_asked(prs3, sim6):
    model = MeasurementModel.from_recording(prs3, sim6.recording)
    fits = cc.fit_methods(model, ("map_all", "ls"), sim6.recording.q[:3])
    assert list(fits) == ["map_all", "ls"], [(m, f.success, f.message) for m, f in fits.items()]
    assert all(f.success for f in fits.values()), [(m, f.message) for m, f in fits.items()]
    assert fits["map_all"].free.all() and not fits["ls"].free.all()
