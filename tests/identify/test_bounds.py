"""Bounds on parameters (lmfit's ``min`` / ``max``) for every method that can keep them (issue 31).

Checked against an independent solver: the bounded MAP and least squares equal
``scipy.optimize.least_squares`` (trust-region reflective, finite-difference Jacobian) on the same objective built
here from the model's residuals; the MCMC posterior truncated at a bound has the marginal of the truncated
univariate normal of the unbounded Laplace posterior (``scipy.stats.truncnorm``), to its Monte Carlo error.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy.optimize import least_squares
from scipy.stats import truncnorm

from bayescal.cli import main
from bayescal.contract import whiten
from bayescal.errors import InputError
from bayescal.identify import identify
from bayescal.identify.calibrate import calibrate
from bayescal.identify.free import Free, parse_bounds, same_free, with_fixed
from bayescal.identify.probabilistic import calibrate_bayes
from bayescal.io import read_recording
from bayescal.machines.files import load_machine
from bayescal.measurement import MeasurementModel

EX = Path(__file__).resolve().parents[2] / "examples" / "prs3"
NAME = "chain3.sphere_center.z"  # the MAP puts it at -0.122 mm (2.4 tolerances): a bound at -0.06 is reached


@pytest.fixture(scope="module")
def model():
    return MeasurementModel.from_recording(load_machine(EX / "machine.toml"), read_recording(EX / "recording.csv"))


def _scipy_bounded(model, free_mask, lo, hi, *, prior: bool):
    """The bounded fit by scipy's trust-region reflective solver on ``[W r; (theta - 0) / tol]`` (prior) or ``W r``."""
    idx = np.flatnonzero(free_mask)
    tol = model.machine.tolerance

    def residuals(x):
        theta = np.zeros(model.n_params)
        theta[idx] = x * tol[idx]
        r = whiten(model, model.residual(model.predict(theta))).reshape(-1)
        return np.concatenate([r, x]) if prior else r

    x0 = np.clip(np.zeros(idx.size), lo[idx] / tol[idx], hi[idx] / tol[idx])
    out = least_squares(residuals, x0, bounds=(lo[idx] / tol[idx], hi[idx] / tol[idx]), method="trf",
                        jac="3-point", diff_step=1e-5, x_scale="jac", xtol=1e-15, ftol=1e-15, gtol=1e-15)
    return out.x, float(out.fun @ out.fun), residuals


#: Least squares on the example is well posed for the sphere centres and the rails' directions (the other parameters
#: it identifies have stds of hundreds of tolerances, which no finite-difference solver reproduces to 1e-4)
WELL_POSED = tuple(f"chain{i}.{p}" for i in (1, 2, 3) for p in (
    "sphere_center.x", "sphere_center.y", "sphere_center.z", "rail_direction.tilt_x", "rail_direction.tilt_y"))


@pytest.mark.parametrize("method, free", [("map", "auto"), ("ls", WELL_POSED)])
def test_a_reached_bound_gives_the_independent_bounded_solvers_answer(model, method, free):
    bounds = {NAME: (-0.06, 0.06), "chain1.sphere_center.x": (-0.02, np.inf)}
    res = identify(model, method=method, free=with_fixed(free, None, bounds))
    names, tol = model.machine.layout.names, model.machine.tolerance
    assert res.success and NAME in res.at_bound and res.theta[names.index(NAME)] == -0.06
    solved = res.free.copy()
    solved[[names.index(n) for n in res.at_bound]] = True
    lo, hi = np.full(len(names), -np.inf), np.full(len(names), np.inf)
    for n, (a, b) in bounds.items():
        lo[names.index(n)], hi[names.index(n)] = a, b
    x, cost, residuals = _scipy_bounded(model, solved, lo, hi, prior=method == "map")
    # the same point, in tolerances (scipy's finite differences stop it within about 1e-4 of the minimum, its
    # cost above ours by 1e-8 of 180)
    mine = residuals(res.theta[solved] / tol[solved])
    assert float(mine @ mine) <= cost + 1e-7
    np.testing.assert_allclose(res.theta[solved] / tol[solved], x, atol=3e-4)
    # at the bound the gradient of the cost points out of the box: moving inside raises it (a true minimum)
    j = names.index(NAME)
    assert np.all(res.theta >= lo) and np.all(res.theta <= hi)
    assert res.std[j] != res.std[j]  # on the bound: no std
    assert res.chi2 > identify(model, method=method, free=free).chi2  # the bound costs fit


def test_a_bound_not_reached_changes_nothing_bit_for_bit(model):
    free = identify(model, method="map", free="auto")
    wide = identify(model, method="map", free=with_fixed("auto", None, {NAME: (-1.0, 1.0)}))
    assert wide.at_bound == () and np.array_equal(wide.theta, free.theta)
    assert np.array_equal(wide.covariance, free.covariance)
    assert "bounds kept, none reached" in wide.report()


def test_the_std_at_a_bound_is_the_fit_holding_the_parameter_there(model):
    """Conditional on the active bound: the covariance of the others is that of a fit with it held at the bound."""
    res = identify(model, method="map", free=with_fixed("auto", None, {NAME: (-0.06, None)}))
    theta0 = np.zeros(model.n_params)
    theta0[model.machine.layout.names.index(NAME)] = -0.06
    held = identify(model, method="map", free=Free("auto", (NAME,)), theta0=theta0)
    assert np.array_equal(res.free, held.free)
    np.testing.assert_allclose(res.theta, held.theta, atol=1e-9 * model.machine.tolerance.max())
    np.testing.assert_allclose(res.covariance, held.covariance, rtol=1e-7, atol=1e-16)


def test_calibrate_keeps_the_bound_through_its_refits_and_records_it_at_zero_variance(model, tmp_path):
    # the default map estimates the prior scale in rounds (same_free refits): the bound holds in every round
    cal = calibrate(model, method="map", bounds={NAME: (-0.06, None)})
    res = cal.result
    assert res.extras.get("prior_scale_rounds", 0) >= 1 and res.at_bound == (NAME,)
    assert res.theta[res.names.index(NAME)] == -0.06
    record = cal.record(model.machine)
    assert NAME in record.names and record.covariance[record.names.index(NAME)].max() == 0.0
    refit = same_free(res)
    assert isinstance(refit, Free) and refit.bounds == ((NAME, -0.06, np.inf),)
    assert res.names.index(NAME) in refit.base  # free again: a refit finds its own active set


def test_the_mcmc_posterior_is_truncated_at_the_bound(model):
    """Truncating one coordinate of a Gaussian leaves that coordinate's marginal a truncated univariate normal."""
    from bayescal.bayes.mcmc import sample_posterior
    from bayescal.bayes.priors import map_estimate

    un = map_estimate(model, free="auto")
    j = model.machine.layout.names.index(NAME)
    k = int(np.flatnonzero(np.flatnonzero(un.free) == j)[0])
    mu, sd = un.theta[j], np.sqrt(un.covariance[k, k])
    lo = mu + sd  # the unbounded MAP one std below the bound
    post = sample_posterior(model, free=with_fixed("auto", None, {NAME: (lo, None)}), surrogate="linear",
                            n_steps=2000, seed=3)
    assert post.success
    kk = int(np.flatnonzero(np.flatnonzero(post.free) == j)[0])
    x = post.samples[:, kk]
    assert x.min() >= lo
    expected = truncnorm((lo - mu) / sd, np.inf, loc=mu, scale=sd)
    se = x.std() / np.sqrt(post.ess_bulk[kk])
    assert abs(x.mean() - expected.mean()) < 4 * se
    assert abs(x.std() / expected.std() - 1) < 0.05  # about 6 standard errors of a std at this ESS
    assert post.to_dict()["bounds"] == {NAME: [lo, None]} and "truncated to" in post.report()


def test_mirrored_reflects_draws_into_the_bounds():
    from bayescal.bayes.mcmc import mirrored

    x = np.array([[-3.0, 5.0, 0.5, 12.0], [1.0, -7.0, 2.5, -0.5]])
    got = mirrored(x, np.array([-1.0, -np.inf, 0.0, 0.0]), np.array([np.inf, 2.0, 1.0, 10.0]))
    np.testing.assert_array_equal(got, [[1.0, -1.0, 0.5, 8.0], [1.0, -7.0, 0.5, 0.5]])


@pytest.mark.parametrize("bounds, match", [
    ({"chain3.sphere_centre.z": (0, 1)}, "unknown parameter 'chain3.sphere_centre.z'; did you mean 'chain3.sphere_center.z'"),
    ({"point.z": (0, 1)}, "unknown parameter 'point.z'; did you mean 'tool.point.z'"),  # its prefix left out
    ({NAME: (0.1, 0.1)}, "expected lower < upper"),
    ({NAME: (0.1, float("nan"))}, "expected numbers \\(or an open side\\)"),
    ({NAME: "wide"}, "expected name: \\(lower, upper\\) pairs"),
    ([(NAME, 0, 1), (NAME, 0, 2)], "bounded twice"),
])
def test_bad_bounds_are_refused_naming_them(model, bounds, match):
    with pytest.raises(InputError, match=match):
        calibrate(model, method="map", bounds=bounds)


def test_methods_that_cannot_keep_bounds_refuse_them(model):
    with pytest.raises(InputError, match="tsvd keeps the solution"):
        calibrate(model, method="tsvd", k=20, bounds={NAME: (-0.06, None)})
    with pytest.raises(InputError, match="Kalman filter"):
        calibrate_bayes(model, method="kalman", bounds={NAME: (-0.06, None)})
    with pytest.raises(InputError, match="also held fixed"):
        calibrate(model, method="map", fix=[NAME], bounds={NAME: (-0.06, None)})


def test_parse_bounds_takes_mappings_triples_and_open_sides():
    assert parse_bounds({"a": (None, 1)}) == (("a", -np.inf, 1.0),)
    assert parse_bounds([("a", 0, None)]) == (("a", 0.0, np.inf),)
    assert with_fixed("all", None, None) == "all"


@pytest.mark.parametrize("arg", ["chain3.sphere_center.z", "chain3.sphere_center.z=0.1", "=0:1", "x=a:1"])
def test_the_command_line_refuses_a_bound_it_cannot_read(tmp_path, capsys, arg):
    code = main(["identify", str(EX / "recording.csv"), "--machine", str(EX / "machine.toml"), "--bound", arg])
    assert code == 2 and "expected NAME=LO:HI" in capsys.readouterr().err


def test_before_is_nominal_even_where_a_bound_moves_the_start(model):
    free = calibrate(model, method="map").result
    far = calibrate(model, method="map", bounds={"chain1.link_length": (0.5, 1.0)}).result
    assert far.at_bound == ("chain1.link_length",) and far.rms_before == free.rms_before


def test_a_bound_settling_a_gauge_is_no_longer_left_to_the_prior(model):
    """tool.point.z and the sphere centres' z share a gauge: a bound on one settles it, the prior no longer does."""
    free = identify(model, method="map", free="auto")
    res = identify(model, method="map", free=with_fixed("auto", None, {NAME: (-0.06, None)}))
    assert any(d.startswith("tool.point.z:") for d in free.decided_by_prior)
    assert not any(d.startswith("tool.point.z:") for d in res.decided_by_prior)
    assert res.identified[res.names.index("tool.point.z")] and not free.identified[free.names.index("tool.point.z")]


def test_least_squares_names_a_parameter_it_leaves_on_a_bound_not_fixed_at_nominal(model):
    # tool.point.z is least squares' gauge parameter: not estimated, it stays at the start, which the bound moved
    res = identify(model, method="ls", free=with_fixed("auto", None, {"tool.point.z": (0.1, None)}))
    assert res.at_bound == ("tool.point.z",) and res.theta[res.names.index("tool.point.z")] == 0.1
    assert "tool.point.z" not in res.fixed and not any(u.startswith("tool.point.z:") for u in res.unidentifiable)
    assert "(lower bound)" in res.report()


def test_the_html_report_names_each_parameter_status():
    from bayescal.report.kinds import _status

    d = {"held": ["a"], "at_bound": ["b", "c"], "bounds": {"b": [0.0, None], "c": [None, 1.0]}}
    p = lambda n, v=0.0, e=True, i=True: {"name": n, "value": v, "estimated": e, "identified": i}  # noqa: E731
    assert _status(d, p("a", e=False, i=False)) == "held at nominal (fix)"
    assert _status(d, p("b", 0.0, False, False)) == "on its lower bound"
    assert _status(d, p("c", 1.0, False, False)) == "on its upper bound"
    assert _status(d, p("x", e=False, i=False)) == "fixed at nominal"
    assert _status(d, p("y", i=False)) == "decided by the prior in part" and _status(d, p("z")) == ""


def test_free_names_are_checked_with_the_closest_suggested(model):
    with pytest.raises(InputError, match="free: unknown parameter 'chain1.link_lenght'; did you mean 'chain1.link_length'"):
        identify(model, method="ls", free=["chain1.link_lenght"])
