"""The model discrepancy: its marginal likelihood, its gauge against the geometry, what it recovers, its table."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
from scipy import stats

from bayescal.discrepancy import fit as F
from bayescal.discrepancy import fit_discrepancy
from bayescal.discrepancy.kernel import farthest_points, nystrom_features, se_kernel
from bayescal.identify.calibrate import calibrate
from bayescal.machines.files import machine_from_text
from bayescal.measurement import MeasurementModel
from bayescal.simulate import simulate_recording


def _bump(q):
    """A smooth error of the tool point no geometric parameter describes, written here (not the GP's formula)."""
    z = (q - 500.0) / 50.0
    return 0.03 * np.column_stack([np.sin(1.3 * z[:, 0]) * z[:, 1], np.cos(z[:, 2]) * z[:, 0], z[:, 1] ** 2 - 1])


@pytest.fixture(scope="module")
def bumped(prs3):
    sim = simulate_recording(prs3, 180, seed=21, dof=3)
    rec = replace(sim.recording, position=sim.recording.position + _bump(sim.recording.q))
    return MeasurementModel.from_recording(prs3, rec), sim


def test_nystrom_kernel_is_the_kernel_on_the_inducing_points(rng):
    U = rng.normal(size=(12, 3))
    ls = np.array([0.7, 1.3, 2.0])
    phi, _ = nystrom_features(U, U, ls)
    np.testing.assert_allclose(phi @ phi.T, se_kernel(U, U, ls), atol=1e-5)
    X = rng.normal(size=(40, 3)) * 4
    phi_x, _ = nystrom_features(X, U, ls)
    assert np.all(np.sum(phi_x**2, axis=1) <= 1 + 1e-6)  # the inducing points carry at most the prior's variance


def test_farthest_points_are_spread_and_distinct(rng):
    X = rng.uniform(size=(200, 2))
    idx = farthest_points(X, 10)
    assert len(set(idx.tolist())) == 10
    P = X[idx]
    d = np.sqrt(((P[:, None] - P[None]) ** 2).sum(-1)) + np.eye(10)
    assert d.min() > 0.1  # far apart, unlike 10 random points of 200 (typically ~0.02)


def test_marginal_likelihood_equals_the_dense_gaussian(bumped):
    model, _ = bumped
    sub = model.subset(np.arange(40))
    res = calibrate(sub, method="map", prior_scale="tolerance", robust="off", noise="stated").result
    inputs, outputs = ("q1", "q2", "q3"), ("x", "y", "z")
    X = F.discrepancy_inputs(sub, inputs)
    idx = np.flatnonzero(res.free)
    sd = sub.machine.tolerance[idx]
    shift = -res.theta[idx]
    prob = F._Problem(sub, res.theta, sub.predict(res.theta), idx, inputs, outputs, X.mean(0), X.std(0), sd, shift)
    U = prob.Z[farthest_points(prob.Z, 8)]
    ls, s, c = np.array([0.8, 1.5, 3.0]), np.array([0.02, 0.03, 0.01]) / 0.005, 1.3
    phi, _ = nystrom_features(prob.Z, U, ls)
    M, b = prob.pieces(phi, s)
    nll = F._neg_log_ml(M, b, float(prob.r @ prob.r), prob.N, c)
    # dense: y - h(theta_map) = A dtheta + F v + e with dtheta ~ N(-theta_map, C0), v ~ N(0, I), e ~ N(0, c I)
    sig = sub.row_sigma
    pred = sub.predict(res.theta)
    r = ((sub.y_measured - pred.y) / sig).reshape(-1)
    A = (sub.jacobian(res.theta, pred)[:, :, idx] / sig[:, :, None]).reshape(r.size, -1)
    G = np.zeros((sub.n_poses, 3, 3)) + np.eye(3) / sig[:, :, None]
    Fd = np.einsum("nao,o,nj->naoj", G, s, phi).reshape(r.size, -1)
    cov = c * np.eye(r.size) + (A * sd**2) @ A.T + Fd @ Fd.T
    dense = stats.multivariate_normal(A @ shift, cov).logpdf(r)
    assert -nll - 0.5 * r.size * math.log(2 * math.pi) == pytest.approx(dense, abs=1e-6 * abs(dense))


def test_on_a_clean_recording_the_discrepancy_takes_nothing(prs3):
    # the gauge is decided by the priors: where geometric errors explain the recording, the discrepancy's
    # scale collapses and the geometry is the MAP's
    sim = simulate_recording(prs3, 120, seed=12, dof=3)
    model = MeasurementModel.from_recording(prs3, sim.recording)
    off = calibrate(model, method="map", prior_scale="tolerance", robust="off", noise="stated")
    on = calibrate(model, method="map", prior_scale="tolerance", robust="off", noise="stated", discrepancy="on")
    free = off.result.free
    z = (on.result.theta - off.result.theta)[free] / off.result.std[free]
    assert np.max(np.abs(z)) < 0.5 and np.sqrt(np.mean(z**2)) < 0.15  # well within the geometry's own uncertainty
    pred = model.predict(on.result.theta)
    mean = on.discrepancy.discrepancy.rows(model, on.result.theta, pred)[0]
    # forced on, it fits a little of the noise (a quarter of its size at most), and its evidence says it is not there
    assert np.sqrt(np.mean(mean**2)) < 0.25 * 0.005
    assert not on.discrepancy.supported


def test_discrepancy_recovers_a_smooth_error_out_of_sample(prs3):
    sim = simulate_recording(prs3, 240, seed=4, dof=3)
    rec = replace(sim.recording, position=sim.recording.position + _bump(sim.recording.q))
    model = MeasurementModel.from_recording(prs3, rec)
    tr, te = model.subset(np.arange(160)), model.subset(np.arange(160, 240))
    errs = {}
    for mode in ("off", "on"):
        cal = calibrate(tr, method="map", prior_scale="tolerance", robust="off", discrepancy=mode)
        res = cal.result
        pred = te.predict(res.theta)
        y = pred.y
        if cal.discrepancy is not None:
            y = y + cal.discrepancy.discrepancy.rows(te, res.theta, pred)[0]
        errs[mode] = float(np.sqrt(np.mean(np.sum((te.y_measured - y) ** 2, axis=1))))
    assert cal.discrepancy.supported
    assert errs["on"] < 0.7 * errs["off"]


def test_clean_recording_gives_no_supported_discrepancy(prs3):
    # a single seed, not a rate: the rate on clean recordings is measured by studies/discrepancy_coverage.py
    sim = simulate_recording(prs3, 120, seed=9, dof=3)
    model = MeasurementModel.from_recording(prs3, sim.recording)
    res = calibrate(model, method="map", prior_scale="tolerance", robust="off", noise="stated").result
    fitted = fit_discrepancy(model, res.theta, res.free, prs3.tolerance[res.free])
    assert not fitted.supported
    assert fitted.discrepancy.log_evidence_gain < F.MIN_EVIDENCE_GAIN


def test_far_from_the_data_the_variance_returns_to_the_prior(bumped):
    model, _ = bumped
    cal = calibrate(model, method="map", prior_scale="tolerance", robust="off", discrepancy="on")
    disc = cal.discrepancy.discrepancy
    far = replace(disc, center=disc.center + 1e3 * disc.scale)  # every pose now sits far outside the inducing inputs
    _, Fr, var = far.rows(model, cal.result.theta, model.predict(cal.result.theta))
    np.testing.assert_allclose(np.einsum("nii->ni", var), np.broadcast_to(disc.output_scales**2, (model.n_poses, 3)),
                               rtol=1e-6)
    assert np.abs(Fr).max() < 1e-12


def test_discrepancy_table_round_trips(prs3, bumped, tmp_path):
    from bayescal.discrepancy.table import discrepancy_toml

    model, _ = bumped
    cal = calibrate(model, method="map", prior_scale="tolerance", robust="off", discrepancy="on")
    disc = cal.discrepancy.discrepancy
    text = prs3.to_toml(None) + "\n" + discrepancy_toml(disc)
    back = machine_from_text(text).discrepancy
    th = cal.result.theta
    pred = model.predict(th)
    for a, b in zip(disc.rows(model, th, pred), back.rows(model, th, pred)):
        np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-15)


def test_simulated_machine_carries_its_discrepancy(prs3, bumped):
    """The simulator's tool offset (tool_offset, from q and channels) is the rows' mean (rows, from the model)."""
    from bayescal.discrepancy.model import DiscrepancyTransform
    from bayescal.simulate import measure

    model, _ = bumped
    cal = calibrate(model, method="map", prior_scale="tolerance", robust="off", discrepancy="on")
    disc, th = cal.discrepancy.discrepancy, cal.result.theta
    mean = disc.rows(model, th, model.predict(th))[0]
    offset = DiscrepancyTransform(disc).pose_offset(model.q, None, {}, None)
    np.testing.assert_allclose(offset[:, :3], mean, rtol=1e-10, atol=1e-14)
    rec = measure(prs3, model.q, th, 3, None, effects=[DiscrepancyTransform(disc)])
    np.testing.assert_allclose(rec.position, model.predict(th).y + mean, atol=1e-9)


@pytest.mark.parametrize("fit_noise,dof", [(True, 3), (False, 3), (True, 6)])
def test_marginal_likelihood_gradient_matches_central_differences(bumped, prs3, fit_noise, dof):
    # the optimiser's analytic gradient (length scales through the Nystrom features and their Cholesky
    # factor, output scales, noise factor) against central differences of the likelihood itself; 6-DOF:
    # six outputs in two scale groups, rotation rows coupling outputs
    if dof == 3:
        sub = bumped[0].subset(np.arange(60))
    else:
        sim = simulate_recording(prs3, 60, seed=5, dof=6)
        rec = replace(sim.recording, position=sim.recording.position + _bump(sim.recording.q))
        sub = MeasurementModel.from_recording(prs3, rec)
    res = calibrate(sub, method="map", prior_scale="tolerance", robust="off", noise="stated").result
    inputs = ("q1", "q2", "q3")
    outputs = F._outputs(sub.dof)
    X = F.discrepancy_inputs(sub, inputs)
    idx = np.flatnonzero(res.free)
    sd = sub.machine.tolerance[idx]
    prob = F._Problem(sub, res.theta, sub.predict(res.theta), idx, inputs, outputs, X.mean(0), X.std(0), sd,
                      -res.theta[idx])
    U = prob.Z[farthest_points(prob.Z, 10)]
    groups = F._groups(outputs)
    n_groups = int(groups.max()) + 1
    rr = float(prob.r @ prob.r)
    x = np.array([math.log(0.8), math.log(1.7), math.log(0.5), math.log(3.0), math.log(0.2)][: 3 + n_groups]
                 + ([math.log(1.4)] if fit_noise else []))

    def unpack(xx):
        return F._unpack(xx, 3, n_groups, groups, fit_noise)

    value, grad = F._neg_log_ml_and_gradient(prob, U, x, 3, n_groups, groups, fit_noise, rr)
    ls, s, c = unpack(x)
    assert value == pytest.approx(F._neg_log_ml(*prob.pieces(nystrom_features(prob.Z, U, ls)[0], s), rr, prob.N, c),
                                  rel=1e-12)

    def f(xx):
        lsx, sx, cx = unpack(xx)
        return F._neg_log_ml(*prob.pieces(nystrom_features(prob.Z, U, lsx)[0], sx), rr, prob.N, cx)

    h = 1e-5
    fd = np.array([(f(x + h * e) - f(x - h * e)) / (2 * h) for e in np.eye(x.size)])
    assert np.all(np.abs(fd) > 1e-3)  # every hyperparameter moves the likelihood here: the check has teeth
    np.testing.assert_allclose(grad, fd, rtol=1e-5, atol=1e-6 * np.abs(fd).max())


def test_a_missing_discrepancy_channel_says_how_to_give_it(bumped):
    # "(give the channel)" did not say how; a grid from a written machine failed with it
    from dataclasses import replace as dc_replace

    from bayescal.errors import InputError

    model, _ = bumped
    disc = calibrate(model, method="map", prior_scale="tolerance", robust="off", discrepancy="on").discrepancy.discrepancy
    inputs = list(disc.inputs)
    with_temp = dc_replace(disc, inputs=tuple(["temp_C"] + inputs[1:]))
    with pytest.raises(InputError, match=r"discrepancy input 'temp_C': .*expected its value \(for a grid: --aux temp_C=VALUE\)"):
        with_temp.tool_offset(model.q, {})
    assert np.all(np.isfinite(with_temp.tool_offset(model.q, {"temp_C": 21.0})))
    with pytest.raises(InputError, match=r"discrepancy input 'q9': the machine has actuators q1..q3"):
        dc_replace(disc, inputs=tuple(["q9"] + inputs[1:])).tool_offset(model.q, {})


def test_default_inputs_leave_out_body_sensor_readings_but_keep_the_base_sensors():
    """A reading of a sensor on a body is a measurement of the outcome (docs/formats.md section 8), not an input."""
    from types import SimpleNamespace

    from bayescal.discrepancy.fit import default_inputs

    rng = np.random.default_rng(0)
    aux = {k: rng.normal(size=5) for k in ("accel.base.x", "accel.joint2.x", "accel.upper_link.z", "temp_C", "pose_id")}
    model = SimpleNamespace(pose_q=np.zeros((5, 2)), aux=aux)
    assert default_inputs(model) == ("q1", "q2", "accel.base.x", "temp_C")


@pytest.mark.parametrize("dof", [3, 6])
def test_fold_fits_are_the_fits_of_each_training_subset_number_for_number(prs3, bumped, dof):
    """fold_fits solves the recording once and takes each fold's training rows from it: the same numbers, bit for
    bit, as fit_discrepancy on model.subset(train) (every piece but the sums over rows is the pose's own)."""
    if dof == 3:
        model = bumped[0]
    else:
        sim = simulate_recording(prs3, 150, seed=22, dof=6)
        model = MeasurementModel.from_recording(prs3, replace(sim.recording, position=sim.recording.position
                                                               + _bump(sim.recording.q)))
    theta = calibrate(model, method="map", prior_scale="tolerance", robust="off", noise="stated").result.theta
    free = np.ones(model.n_params, dtype=bool)
    sd = np.asarray(prs3.tolerance, dtype=float)
    hyper = fit_discrepancy(model, theta, free, sd, seed=1)
    folds = [np.sort(np.random.default_rng(3).permutation(model.n_poses)[i::5]) for i in range(5)]
    got = F.fold_fits(model, theta, free, sd, hyper.discrepancy, hyper.noise_factor, folds)
    assert len(got) == len(folds)
    for test, f in zip(folds, got):
        train = np.setdiff1d(np.arange(model.n_poses), test)
        ref = fit_discrepancy(model.subset(train), theta, free, sd, hyper=hyper.discrepancy,
                              noise_factor=hyper.noise_factor)
        assert np.array_equal(f.dtheta, ref.dtheta)
        assert np.array_equal(f.discrepancy.weights, ref.discrepancy.weights)
        assert np.array_equal(f.covariance, ref.covariance)
        assert f.chi2 == ref.chi2 and f.effective_params == ref.effective_params
        assert f.discrepancy.explained == ref.discrepancy.explained
    # and a fold's fit is not the full fit's (the training rows matter)
    assert not np.allclose(got[0].dtheta, F.fit_discrepancy(model, theta, free, sd, hyper=hyper.discrepancy,
                                                            noise_factor=hyper.noise_factor).dtheta)
