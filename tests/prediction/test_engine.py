"""The predictive distribution of rows against Monte Carlo, and the calibration record's round trip."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from bayescal.identify import identify
from bayescal.instrument.prepare import prepare_session
from bayescal.machines.files import machine_from_text
from bayescal.machines.framed import Frame
from bayescal.measurement import MeasurementModel
from bayescal.prediction.engine import predictive_rows
from bayescal.prediction.record import CalibrationRecord, calibration_toml
from bayescal.prediction.score import score_rows
from bayescal.simulate import simulate_recording


def test_covariance_propagation_equals_monte_carlo(prs3, rng):
    """Parameters drawn from C, rows evaluated by the full (nonlinear) model: their spread is G C G^T + R."""
    sim = simulate_recording(prs3, 6, seed=2, dof=6)
    model = MeasurementModel.from_recording(prs3, sim.recording)
    theta = sim.theta_true
    idx = np.arange(prs3.n_params)
    C = np.diag((0.3 * prs3.tolerance) ** 2)
    pr = predictive_rows(model, theta, C, machine_index=idx, noise_factor=1.0)
    draws = theta + rng.normal(size=(3000, prs3.n_params)) * 0.3 * prs3.tolerance
    # one vectorised call: the parameter sets stacked in blocks of the model's poses
    ys = model.predict(np.repeat(draws, model.n_poses, axis=0)).y.reshape(3000, model.n_poses, -1)
    ys = ys + rng.normal(size=ys.shape) * model.row_sigma  # the instrument's noise
    emp = np.einsum("kni,knj->nij", ys - ys.mean(0), ys - ys.mean(0)) / (ys.shape[0] - 1)
    sd = np.sqrt(np.einsum("nii->ni", pr.cov))
    # variances within Monte Carlo error (3000 draws: ~2.6 % sd of a variance, 5 sigma allowed)
    np.testing.assert_allclose(np.einsum("nii->ni", emp), sd**2, rtol=0.15)
    np.testing.assert_allclose(ys.mean(0), pr.mean, atol=3 * np.max(sd) / np.sqrt(3000))


def test_refitted_frame_absorbs_what_it_can(prs3, rng):
    """Frames refitted per session: Monte Carlo of geometry draws, noise and a least-squares frame refit."""
    sim = simulate_recording(prs3, 24, seed=5, dof=3)
    f = Frame.from_rotation_vector([800.0, -300.0, 50.0], [0.2, -0.1, 0.9])
    rec = replace(sim.recording, position=f.to_instrument(sim.recording.position),
                  role=tuple(["fit"] * 16 + ["check"] * 8))
    session = prepare_session(prs3, rec, frame="fit")
    fm, model = session.machine, session.model
    fit_rows = ~rec.is_check
    base = identify(model.subset(np.flatnonzero(fit_rows)), method="ls", free=list(range(6)))
    theta0 = base.theta  # the frame fitted at the machine's file geometry
    geo = np.arange(6, fm.n_params)
    C = np.diag((0.5 * fm.tolerance[geo]) ** 2)
    pr = predictive_rows(model, theta0, C, machine_index=geo, session_index=np.arange(6), fit_rows=fit_rows)
    chk = np.flatnonzero(~fit_rows)
    errs = []
    for _ in range(150):
        t = theta0.copy()
        t[geo] += rng.normal(size=geo.size) * 0.5 * fm.tolerance[geo]
        y = model.predict(t).y + rng.normal(size=(model.n_poses, 3)) * model.row_sigma
        sess = replace(model, y_measured=y)
        refit = identify(sess.subset(np.flatnonzero(fit_rows)), method="ls", free=list(range(6)), theta0=theta0)
        pred = model.predict(refit.theta).y
        errs.append(y[chk] - pred[chk])
    errs = np.array(errs)
    emp = np.einsum("kni,knj->nij", errs, errs) / errs.shape[0]
    # 150 draws: a variance to ~12 % (1 sd); 35 % allowed
    np.testing.assert_allclose(np.einsum("nii->ni", emp), np.einsum("nii->ni", pr.cov[chk]), rtol=0.35)
    # without the refit's projection the geometry's uncertainty would count in full: much larger here
    raw = predictive_rows(model, theta0, C, machine_index=geo)
    assert np.mean(np.einsum("nii->ni", raw.cov[chk])) > 2 * np.mean(np.einsum("nii->ni", pr.cov[chk]))


def test_score_rows_counts_the_ellipsoid():
    mean = np.zeros((2, 3))
    cov = np.stack([np.eye(3), np.diag([1.0, 4.0, 9.0])])
    meas = np.array([[2.6, 0.0, 0.0], [0.0, 4.0, 0.0]])  # chi2_3(0.9) = 6.25: 2.6^2 = 6.76 out; (4/2)^2 = 4 in
    s = score_rows(meas, mean, cov)
    assert s.inside.tolist() == [False, True]
    np.testing.assert_allclose(s.error_position, [2.6, 4.0])


def test_score_rows_of_a_row_that_decided_a_direction_alone():
    """A fit row of leverage one has no residual variance along what it decided: the region is the ellipse of the
    other two components (chi2_2(0.9) = 4.61), the round-off left along the third is no distance, nothing blows
    up; a row with no residual variance at all is inside its (point) region."""
    mean = np.zeros((3, 3))
    cov = np.stack([np.diag([1.0, 1.0, 1e-30]), np.diag([1.0, 1.0, 0.0]), np.zeros((3, 3))])
    meas = np.array([[2.0, 0.0, 1e-13], [2.2, 0.0, 0.0], [0.0, 0.0, 1e-15]])
    s = score_rows(meas, mean, cov)
    np.testing.assert_allclose(s.mahalanobis2, [4.0, 4.84, 0.0])
    assert s.inside.tolist() == [True, False, True]


def test_calibration_record_round_trips(prs3, rng):
    A = rng.normal(size=(5, 5))
    C = A @ A.T * 1e-4
    names = prs3.layout.names[:5]
    rec = CalibrationRecord(tuple(names), C, 1.3, "map", 1.2)
    back = machine_from_text(prs3.to_toml(None) + "\n" + calibration_toml(rec)).calibration
    assert back.names == rec.names and back.noise_scale == 1.3 and back.variance_factor == 1.2
    np.testing.assert_array_equal(back.covariance, C)
    np.testing.assert_array_equal(back.covariance_for(names[::-1]), C[::-1, ::-1])


@pytest.mark.parametrize("bad,what", [
    ('covariance_f64le_b64 = "AAAA"', "bytes; expected"),
    ('covariance_f64le_b64 = "not base64!"', "not valid base64"),
    ("noise_scale = -1.0", "positive"),
])
def test_broken_calibration_table_is_named(prs3, bad, what):
    from bayescal.errors import MachineFileError

    good = calibration_toml(CalibrationRecord(("tool.point.x",), np.eye(1), 1.0, "map"))
    key = bad.split(" =")[0]
    text = "\n".join(bad if line.startswith(key + " ") else line for line in good.splitlines())
    with pytest.raises(MachineFileError, match=what) as exc:
        machine_from_text(prs3.to_toml(None) + "\n" + text)
    assert "calibration." in str(exc.value)


def _record_text(C, names, std=None):
    text = calibration_toml(CalibrationRecord(tuple(names), np.asarray(C, dtype=float), 1.0, "map"))
    if std is not None:
        text = "\n".join(f"std = {std}" if line.startswith("std ") else line for line in text.splitlines())
    return text


@pytest.mark.parametrize("C, std, key, what", [
    # a std of 1e150 mm passed the finite-and-symmetric check and ended in a singular-matrix traceback (a probe)
    ([[1e300, 0.0], [0.0, 1.0]], None, "covariance_f64le_b64", "'tool.point.x' has a std of 1e+150"),
    # variances 1 and 1 with covariance 2: correlation 2, an eigenvalue of -1
    ([[1.0, 2.0], [2.0, 1.0]], None, "covariance_f64le_b64", "not positive semi-definite (smallest eigenvalue -1"),
    (np.eye(2), "[-1.0, 1.0]", "std", "expected 2 finite non-negative numbers"),
    (np.eye(2), "[nan, 1.0]", "std", "expected 2 finite non-negative numbers"),
    (np.eye(2), "[1.0, 3.0]", "std", "'tool.point.y': 3.0 is not the square root of its variance"),
])
def test_calibration_covariance_no_calibration_writes_is_refused(prs3, C, std, key, what):
    from bayescal.errors import MachineFileError

    import re

    text = _record_text(C, ["tool.point.x", "tool.point.y"], std)
    with pytest.raises(MachineFileError, match=re.escape(what)) as exc:
        machine_from_text(prs3.to_toml(None) + "\n" + text)
    assert f"calibration.{key}" in str(exc.value)


def test_calibration_std_written_is_read_back(prs3):
    C = np.array([[4.0, 1.0], [1.0, 9.0]]) * 1e-6
    back = machine_from_text(prs3.to_toml(None) + "\n" + _record_text(C, ["tool.point.x", "tool.point.y"])).calibration
    np.testing.assert_allclose(back.std, [2e-3, 3e-3])


def test_per_component_factors_equal_one_factor_when_equal_and_act_apart(prs3):
    """noise_factor and variance_factor per measured component (a tool's scale, a sensor's 1): equal to the scalar
    when all are equal, and a factor on one component leaves the other components' variances alone."""
    sim = simulate_recording(prs3, 12, seed=4, dof=3)
    rec = replace(sim.recording, role=tuple(["fit"] * 8 + ["check"] * 4))
    session = prepare_session(prs3, rec, frame="fit")
    model = session.model
    geo = np.arange(6, model.n_params)
    C = np.diag((0.3 * model.machine.tolerance[geo]) ** 2)
    kw = dict(machine_index=geo, session_index=np.arange(6), fit_rows=~rec.is_check)
    a = predictive_rows(model, np.zeros(model.n_params), C, noise_factor=2.0, variance_factor=1.5, **kw)
    b = predictive_rows(model, np.zeros(model.n_params), C, noise_factor=np.full(3, 2.0),
                        variance_factor=np.full(3, 1.5), **kw)
    np.testing.assert_allclose(b.cov, a.cov, rtol=1e-12)
    # without a session fit the components' noises do not mix: a factor on z leaves x and y alone
    kw0 = dict(machine_index=geo)
    a0 = predictive_rows(model, np.zeros(model.n_params), C, noise_factor=2.0, variance_factor=1.5, **kw0)
    c = predictive_rows(model, np.zeros(model.n_params), C, noise_factor=[2.0, 2.0, 50.0],
                        variance_factor=[1.5, 1.5, 1.0], **kw0)
    np.testing.assert_allclose(c.cov[:, :2, :2], a0.cov[:, :2, :2], rtol=1e-12)
    sig2 = model.row_sigma[:, 2] ** 2
    np.testing.assert_allclose(c.cov[:, 2, 2], (a0.cov[:, 2, 2] - 3.0 * sig2) / 1.5 + 50.0 * sig2, rtol=1e-10)
    np.testing.assert_allclose(c.cov[:, :2, 2], a0.cov[:, :2, 2] / np.sqrt(1.5), rtol=1e-10)
