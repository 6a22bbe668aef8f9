"""bayescal.outliers.joint: the joint fit's outlier test, the fit passed in as callables."""

from __future__ import annotations

import numpy as np
import pytest

from bayescal.errors import InputError
from bayescal.measurement import MeasurementModel
from bayescal.outliers import EXCLUDE_FACTOR
from bayescal.outliers.joint import joint_outlier_handling
from bayescal.simulate import simulate_recording

N, P = 24, 5


@pytest.fixture()
def setup(prs3):
    model = MeasurementModel.from_recording(prs3, simulate_recording(prs3, N, seed=3, dof=6).recording)
    rng = np.random.default_rng(7)
    A = rng.normal(size=(N * model.dof, P))
    r = rng.normal(size=N * model.dof)  # whitened rows: unit noise
    return model, A, r


class _Fit:
    """Records how the joint fit is asked for, and answers the fixed design."""

    def __init__(self, A, r):
        self.A, self.r, self.calls = A, r, []

    def design(self, model, theta, fit):
        return self.A, self.r

    def refit(self, model, theta, fit, search):
        self.calls.append((search, np.asarray(model.row_sigma).copy()))
        return theta + 1.0, fit


def test_a_gross_pose_leaves_the_joint_fit_and_the_hyperparameters_are_searched_again(setup):
    model, A, r = setup
    r = r.copy()
    r[5 * model.dof: 6 * model.dof] += 40.0  # pose 5: 40 sigma in every row, no model explains it
    fit = _Fit(A, r)
    handling, got, theta = joint_outlier_handling(model, np.zeros(model.n_params), "fit", design=fit.design,
                                                  refit=fit.refit)
    assert got == "fit" and np.all(theta == 1.0)  # the refit's answer is returned
    assert np.flatnonzero(handling.test.flagged).tolist() == [5]
    assert handling.weights[5] == pytest.approx(EXCLUDE_FACTOR**-2) and np.all(np.delete(handling.weights, 5) == 1)
    (search, sigma), = fit.calls
    assert search  # poses left out: the hyperparameters are searched again, on the model without pose 5
    np.testing.assert_allclose(sigma[5], EXCLUDE_FACTOR * np.asarray(model.row_sigma)[5])
    assert handling.action.startswith("excluded from the joint fit (1 pose(s))")


def test_clean_poses_are_kept_and_robust_off_keeps_a_gross_one(setup):
    model, A, r = setup
    fit = _Fit(A, r)
    handling, _, _ = joint_outlier_handling(model, np.zeros(model.n_params), None, design=fit.design, refit=fit.refit)
    assert handling.weights is None and not handling.test.flagged.any()
    assert [c[0] for c in fit.calls] == [False]  # the joint fit redone at full weight, hyperparameters kept
    gross = r.copy()
    gross[:model.dof] += 40.0
    fit = _Fit(A, gross)
    handling, _, _ = joint_outlier_handling(model, np.zeros(model.n_params), None, design=fit.design,
                                            refit=fit.refit, robust="off")
    assert handling.weights is None and handling.test.flagged[0] and "--robust off" in handling.action


def test_no_design_no_decision(setup):
    model, _, _ = setup

    def design(*_):
        raise InputError("no joint design")

    assert joint_outlier_handling(model, np.zeros(model.n_params), None, design=design, refit=None) is None
