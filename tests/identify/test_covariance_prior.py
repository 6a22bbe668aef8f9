"""The covariance keeps the prior where the data do not see (issue #30, item 1), and the noise test.

Checked against the dense closed-form Gaussian posterior ``(J^T R^-1 J + P0^-1)^-1``
built with ``numpy.linalg.inv`` (not the SVD the solver uses) and against the
Kalman filter on the same poses.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from bayescal.bayes.kalman import kalman_filter
from bayescal.identify import identify
from bayescal.identify.calibrate import calibrate
from bayescal.identify.gauss_newton import data_determined
from bayescal.identify.noise import check_noise, distinct_rows
from bayescal.io import read_recording
from bayescal.machines.files import load_machine
from bayescal.measurement import MeasurementModel

EX = Path(__file__).resolve().parents[2] / "examples" / "prs3"


@pytest.fixture(scope="module")
def prs3():
    machine = load_machine(EX / "machine.toml")
    rec = read_recording(EX / "recording.csv")
    return machine, MeasurementModel.from_recording(machine, rec)


def _closed_form(model, theta):
    """Dense Gaussian posterior covariance under the tolerance prior, linearised at ``theta``."""
    pred = model.predict(theta)
    J = (model.jacobian(theta, pred) / model.row_sigma[:, :, None]).reshape(-1, model.n_params)
    P0_inv = np.diag(1.0 / model.machine.tolerance**2)
    return np.linalg.inv(J.T @ J + P0_inv)


@pytest.mark.parametrize("poses", [[0], [0, 7, 21], list(range(36))])
def test_map_covariance_is_the_closed_form_posterior(prs3, poses):
    _, model = prs3
    sub = model.subset(poses)
    res = identify(sub, method="map", free="all")
    assert res.success
    dense = _closed_form(sub, res.theta)
    sd_dense = np.sqrt(np.diag(dense))
    np.testing.assert_allclose(res.std, sd_dense, rtol=1e-6)
    np.testing.assert_allclose(res.covariance, dense, atol=1e-9 * np.max(np.abs(dense)))


def test_one_pose_std_is_near_the_tolerance_where_the_pose_does_not_see(prs3):
    machine, model = prs3
    one = identify(model.subset([0]), method="map", free="all")
    full = identify(model, method="map", free="all")
    # 6 components cannot pin 36 parameters: most stds stay near their tolerance, and
    # removing poses never shrinks an interval (the old thin-SVD covariance did: 0.0007 mm)
    assert np.all(one.std >= full.std * (1 - 1e-9))
    assert np.median(one.std / machine.tolerance) > 0.9
    i = machine.layout.index("chain1.sphere_center.x")
    assert one.std[i] > 0.9 * machine.tolerance[i]


@pytest.mark.parametrize("poses", [[0], [0, 7, 21]])
def test_map_agrees_with_the_kalman_filter(prs3, poses):
    _, model = prs3
    sub = model.subset(poses)
    res = identify(sub, method="map", free="all")
    kf = kalman_filter(sub, free="all")
    sd_kf = np.sqrt(np.diag(kf.covariances[-1]))
    # one linearisation (MAP) against one per pose (EKF): equal to well under a percent of a std
    np.testing.assert_allclose(res.std[kf.free], sd_kf, rtol=5e-3)


def test_identified_means_the_data_determine_it():
    rng = np.random.default_rng(1)
    A = rng.normal(size=(8, 5))
    A[:, 3] = 0.0  # no row sees parameter 3
    A[:, 4] = A[:, 0]  # parameters 0 and 4 form a gauge
    det, s = data_determined(A)
    assert det.tolist() == [False, True, True, False, False]
    assert s.size == 5


def test_unseen_parameter_is_estimated_but_not_identified(prs3):
    machine, model = prs3
    res = identify(model.subset([0, 1]), method="map", free="all")
    d = res.to_dict()
    flags = {p["name"]: (p["identified"], p["estimated"]) for p in d["parameters"]}
    assert all(e for _, e in flags.values())
    assert sum(i for i, _ in flags.values()) < 12  # 12 components cannot determine 36 parameters alone
    assert d["n_identified"] == sum(i for i, _ in flags.values())


def test_check_noise_tails():
    assert check_noise(100.0, 100.0).verdict == "consistent"
    up = check_noise(400.0, 100.0)
    assert up.verdict == "understated" and up.scale == pytest.approx(2.0)
    down = check_noise(2.0, 100.0)
    assert down.verdict == "overstated" and down.scale == pytest.approx(np.sqrt(0.02))
    # significant but under a factor of 2 in sigma: a shortfall is left alone
    assert check_noise(60.0, 100.0).verdict == "consistent"
    assert check_noise(1.0, 0.2).verdict == "untestable"


def test_distinct_rows_counts_copies_not_repeats():
    q = np.ones((4, 3))
    y = np.array([[1.0], [1.0], [1.0], [2.0]])
    assert distinct_rows(q, y) == 2  # three copies and one fresh repeat of the same pose


def _with_sigma(model, factor):
    return model.with_pose_sigma(np.asarray(model.row_sigma) * factor)


def test_overstated_noise_is_estimated_and_the_fit_uses_it(prs3):
    _, model = prs3
    right = calibrate(model, method="map", prior_scale="tolerance", robust="off")
    wrong = calibrate(_with_sigma(model, 100.0), method="map", prior_scale="tolerance", robust="off")
    stated = calibrate(_with_sigma(model, 100.0), method="map", prior_scale="tolerance", robust="off", noise="stated")
    assert right.noise.verdict == "consistent" and right.noise_scale == 1.0
    assert wrong.noise.verdict == "overstated"
    # the estimated sigma is what the residuals show at the right sigma (the example's reduced chi-square
    # is about 0.8) to 5 %, and the fit reaches what the right sigma reaches
    assert wrong.noise_scale * 100.0 == pytest.approx(np.sqrt(right.result.reduced_chi2), rel=0.05)
    pos = lambda c: c.result.rms_after["position"]  # noqa: E731
    assert pos(wrong) == pytest.approx(pos(right), rel=0.02)
    assert pos(stated) > 5 * pos(right)  # the stated sigma leaves the calibration to the prior


def test_understated_noise_widens_the_intervals(prs3):
    _, model = prs3
    right = calibrate(model, method="ls", robust="off")
    low = calibrate(_with_sigma(model, 1 / 3), method="ls", robust="off")
    assert low.noise.verdict == "understated"
    expected = np.sqrt(right.result.reduced_chi2)  # the residuals' own scale at the right sigma
    assert low.noise_scale / 3 == pytest.approx(expected, rel=1e-3)  # least squares: settles in one round
    # the estimate does not depend on a uniform sigma; the intervals follow the estimated one
    np.testing.assert_allclose(low.result.theta, right.result.theta, atol=1e-9)
    np.testing.assert_allclose(low.result.std[right.result.free], expected * right.result.std[right.result.free],
                               rtol=1e-3)
