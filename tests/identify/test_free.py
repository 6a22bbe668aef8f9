"""Parameters held fixed by name (``fix``, lmfit's ``vary=False``) with any ``free`` rule and method (issue 31).

Checked against closed forms built here: a MAP with a parameter held equals the dense Gaussian posterior of the
other parameters alone (``numpy.linalg.inv`` of ``J_r^T J_r + P0_r^-1``), and least squares with a parameter held
that the data see is the least-squares fit of the model without that column.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from bayescal.errors import InputError
from bayescal.identify import identify
from bayescal.identify.calibrate import calibrate
from bayescal.identify.free import Free, with_fixed
from bayescal.identify.probabilistic import calibrate_bayes
from bayescal.io import read_recording
from bayescal.machines.files import load_machine
from bayescal.measurement import MeasurementModel

EX = Path(__file__).resolve().parents[2] / "examples" / "prs3"
HELD = ("chain2.link_length", "chain1.rail_origin.z")


@pytest.fixture(scope="module")
def model():
    return MeasurementModel.from_recording(load_machine(EX / "machine.toml"), read_recording(EX / "recording.csv"))


@pytest.mark.parametrize("method, options", [("map", {}), ("ls", {}), ("ridge", {"lam": 1.0}), ("tsvd", {"k": 20})])
def test_held_parameters_stay_at_nominal_and_are_named_as_held(model, method, options):
    cal = calibrate(model, method=method, fix=list(HELD), robust="off", **options)
    res, names = cal.result, model.machine.layout.names
    assert res.success
    for name in HELD:
        j = names.index(name)
        assert res.theta[j] == 0.0 and not res.free[j] and np.isnan(res.std[j])  # not estimated: no std
    d = cal.to_dict()
    assert d["held"] == list(HELD) and not set(HELD) & set(d["fixed"])
    assert "held at nominal (fix): chain2.link_length, chain1.rail_origin.z" in cal.report()


@pytest.mark.parametrize("method, options", [("kalman", {}), ("mcmc", {"steps": 200, "surrogate": "linear"})])
def test_kalman_and_mcmc_hold_them_at_the_prior_mean(model, method, options):
    res = calibrate_bayes(model, method=method, fix=list(HELD), robust="off", **options).result
    j = model.machine.layout.index(HELD[0])
    assert res.theta[j] == 0.0 and not res.free[j] and res.held == HELD and HELD[0] not in res.fixed
    assert res.to_dict()["held"] == list(HELD) and "(fix): chain2.link_length, chain1.rail_origin.z" in res.report()


def test_map_with_a_parameter_held_is_the_posterior_of_the_others(model):
    sub = model.subset([0, 5, 11, 17, 23, 29])
    res = identify(sub, method="map", free=Free("all", HELD))
    keep = np.array([n not in HELD for n in sub.machine.layout.names])
    pred = sub.predict(res.theta)
    J = (sub.jacobian(res.theta, pred) / sub.row_sigma[:, :, None]).reshape(-1, sub.n_params)[:, keep]
    dense = np.linalg.inv(J.T @ J + np.diag(1.0 / sub.machine.tolerance[keep] ** 2))
    np.testing.assert_allclose(res.std[keep], np.sqrt(np.diag(dense)), rtol=1e-6)
    assert np.all(np.isnan(res.std[~keep]))


def test_least_squares_with_a_seen_parameter_held_fits_the_rest(model):
    # chain1.link_length is in the identifiable set least squares picks and in no gauge: held, its column is gone
    # and the set is one smaller; the fit must be the least-squares fit of the other parameters (checked by its
    # normal equations), and worse than the free fit by what the data see of the link length
    plain = identify(model, method="ls")
    names = model.machine.layout.names
    j = names.index("chain1.link_length")
    assert plain.free[j]
    held = identify(model, method="ls", free=Free("auto", ("chain1.link_length",)))
    assert held.success and not held.free[j] and held.theta[j] == 0.0
    assert int(held.free.sum()) == int(plain.free.sum()) - 1
    pred = model.predict(held.theta)
    r = (model.residual(pred) / model.row_sigma).reshape(-1)
    J = (model.jacobian(held.theta, pred) / model.row_sigma[:, :, None]).reshape(-1, model.n_params)[:, held.free]
    grad = J.T @ r
    assert np.max(np.abs(grad)) < 1e-6 * np.linalg.norm(J, axis=0).max() * np.linalg.norm(r)
    assert held.chi2 > plain.chi2 * (1 + 1e-6)


def test_holding_one_side_of_a_gauge_identifies_the_other(model):
    # chain1.sphere_center.x and tool.point.x look the same to the measurement (least squares keeps the first
    # and fixes the tool point); held, the tool point takes its place: as many parameters, the same fit
    plain = identify(model, method="ls")
    names = model.machine.layout.names
    a, b = names.index("chain1.sphere_center.x"), names.index("tool.point.x")
    assert plain.free[a] and not plain.free[b]
    held = identify(model, method="ls", free=Free("auto", ("chain1.sphere_center.x",)))
    assert held.free[b] and not held.free[a] and int(held.free.sum()) == int(plain.free.sum())
    assert held.chi2 == pytest.approx(plain.chi2, rel=1e-8)
    assert held.held == ("chain1.sphere_center.x",) and "tool.point.x" not in held.fixed


@pytest.mark.parametrize("free, fix, words", [
    ("auto", ["chain2.link_lenght"], "fix: unknown parameter 'chain2.link_lenght'; did you mean 'chain2.link_length'"),
    (["chain2.link_length", "tool.point.z"], ["tool.point.z"], "tool.point.z also listed in free"),
    ("all", ["tool.point.z", "tool.point.z"], "listed twice"),
])
def test_bad_fix_lists_are_refused(model, free, fix, words):
    with pytest.raises(InputError, match=words):
        calibrate(model, method="map", free=free, fix=fix, robust="off")


def test_fix_takes_a_list_not_a_string():
    with pytest.raises(InputError, match="fix: expected a list of parameter names"):
        with_fixed("auto", "tool.point.z")
    assert with_fixed("auto", None) == "auto" and with_fixed("all", []) == "all"


def test_nothing_left_to_identify_is_refused(model):
    sub = model.subset([0])
    names = sub.machine.layout.names
    with pytest.raises(InputError, match="free: expected at least one parameter"):
        identify(sub, method="map", free=Free("all", names))


@pytest.mark.parametrize("method, options", [("map", {}), ("ls", {})])
def test_the_written_record_states_held_parameters_known(model, method, options):
    # left out of [calibration], predict would give a held parameter its tolerance as its uncertainty
    cal = calibrate(model, method=method, fix=["chain2.link_length"], robust="off", **options)
    rec = cal.record(model.machine)
    j = rec.names.index("chain2.link_length")
    assert rec.covariance[j, j] == 0.0 and not np.any(rec.covariance[j])
    free = [n for n, f in zip(cal.result.names, cal.result.free) if f]
    assert set(free) <= set(rec.names)
