"""MCMC on a linear-Gaussian problem vs the closed-form posterior; the arviz tree; refusal when not converged."""

from __future__ import annotations

import warnings

import arviz as az
import numpy as np
import pytest
from scipy import stats

from bayescal.bayes import linearise, prior_from_machine
from bayescal.bayes.mcmc import log_posterior_function, sample_posterior, write_posterior
from bayescal.errors import InputError
from bayescal.measurement import MeasurementModel

FREE = ["chain1.link_length", "chain2.link_length", "chain3.link_length", "chain1.sphere_center.x"]


@pytest.fixture(scope="module")
def problem(linear_problem):
    """Linear model over 6 poses, position only, the 4 parameters ``FREE``: posterior N(m, C) in closed form."""
    lin, idx, m, C, free = linear_problem
    assert free == FREE
    return lin, idx, m, C


@pytest.fixture(scope="module")
def posterior(problem):
    lin, *_ = problem
    return sample_posterior(lin, free=FREE, n_walkers=16, n_steps=1000, seed=4)


def test_posterior_matches_closed_form(problem, posterior):
    lin, idx, m, C = problem
    res = posterior
    assert res.success, res.message
    sd = np.sqrt(np.diag(C))
    # Monte Carlo error of the mean: sd / sqrt(ESS); 4 of them is a seeded, generous bound
    assert np.all(np.abs(res.mean - m) < 4 * sd / np.sqrt(res.ess_bulk))
    np.testing.assert_allclose(np.sqrt(np.diag(res.covariance)), sd, rtol=0.1)
    corr = res.covariance / np.outer(np.sqrt(np.diag(res.covariance)), np.sqrt(np.diag(res.covariance)))
    np.testing.assert_allclose(corr, C / np.outer(sd, sd), atol=0.08)
    # a KS test on a thinned marginal (about independent draws)
    thin = int(np.ceil(np.max(res.tau)))
    x = res.tree["posterior"]["theta"].values[:, ::thin, 0].ravel()
    assert stats.kstest(x, stats.norm(m[0], sd[0]).cdf).pvalue > 1e-3
    # the 90% interval of the draws matches the Gaussian one
    np.testing.assert_allclose(res.quantiles[[0, 2]], m + np.outer([-1.6449, 1.6449], sd), atol=0.15 * sd.max())
    np.testing.assert_array_equal(np.flatnonzero(res.free), np.sort(idx))


def test_tree_groups_dims_and_loo(tmp_path, posterior, problem):
    lin, idx, *_ = problem
    dt = posterior.tree
    for g in ("posterior", "log_likelihood", "sample_stats", "observed_data", "constant_data"):
        assert g in dt.children
    th = dt["posterior"]["theta"]
    assert th.dims == ("chain", "draw", "param")
    assert list(th["param"].values) == [lin.machine.layout.names[i] for i in idx]
    assert dt["log_likelihood"]["y"].dims == ("chain", "draw", "pose")
    assert dt["log_likelihood"]["y"].shape[2] == lin.n_poses
    # the pointwise log-likelihood is the Gaussian density of each pose at each draw
    draw = th.values[0, -1]
    theta = np.zeros(lin.n_params)
    theta[idx] = draw
    r = (lin.y_measured - lin.predict(theta).y) / lin.sigma
    ll = stats.norm.logpdf(r).sum(axis=1) - np.log(lin.sigma).sum()
    np.testing.assert_allclose(dt["log_likelihood"]["y"].values[0, -1], ll, rtol=1e-10)
    with warnings.catch_warnings():
        # 6 poses for 4 parameters: single poses are influential (Pareto k > 0.7 is a true finding here)
        warnings.simplefilter("ignore", UserWarning)
        loo = az.loo(dt)
    assert np.isfinite(loo.elpd)
    path = write_posterior(posterior, tmp_path / "post.nc", thin=1)
    back = az.from_netcdf(path)
    np.testing.assert_array_equal(back["posterior"]["theta"].values, th.values)
    thin = max(1, int(np.max(posterior.tau) // 4))
    back = az.from_netcdf(write_posterior(posterior, tmp_path / "thin.nc"))
    np.testing.assert_array_equal(back["posterior"]["theta"].values, th.values[:, ::thin])
    assert back["log_likelihood"]["y"].shape[1] == th.shape[1] // thin + (th.shape[1] % thin > 0)
    assert not list(tmp_path.glob(".*tmp"))
    d = posterior.to_dict()
    assert d["method"] == "mcmc" and len(d["interval_90"]) == len(FREE)
    assert "R-hat" in posterior.report()


def test_refuses_unconverged(problem, tmp_path):
    lin, *_ = problem
    res = sample_posterior(lin, free=FREE, n_walkers=16, n_steps=30, seed=1)
    assert not res.success
    assert "more steps" in res.message and res.more_steps > 0
    # the advice holds for the default burn-in, which grows with n_steps: following it keeps a chain of
    # at least TAU_FACTOR autocorrelation times (the tau estimate held fixed)
    from bayescal.bayes.mcmc import TAU_FACTOR

    advised = res.n_steps + res.more_steps
    assert advised - advised // 5 >= TAU_FACTOR * np.nanmax(res.tau) or not np.all(np.isfinite(res.tau))
    assert np.all(np.isnan(res.std))
    assert "NOT CONVERGED" in res.report()
    with pytest.raises(InputError, match="not converged"):
        write_posterior(res, tmp_path / "p.nc")


def test_vectorised_log_prob_matches_one_by_one(prs3, sim6):
    model = MeasurementModel.from_recording(prs3, sim6.recording).subset(np.arange(5))
    prior = prior_from_machine(prs3)
    idx = prs3.layout.indices(FREE)
    f = log_posterior_function(model, prior, idx)
    X = prior.sample(3, np.random.default_rng(0))[:, idx] * 0.3
    both = f(X)
    one = np.vstack([f(x[None]) for x in X])
    np.testing.assert_allclose(both, one, rtol=1e-10)
    assert both.shape == (3, 1 + model.n_poses)


def test_first_order_warm_starts_give_the_same_log_posterior(prs3, sim6):
    # what sample_posterior does on the 3-PRS: every walker's solve starts from the MAP's poses moved to first order
    from bayescal.bayes.mcmc import _warm_starts

    model = MeasurementModel.from_recording(prs3, sim6.recording).subset(np.arange(8))
    prior = prior_from_machine(prs3)
    idx = np.arange(prs3.n_params)
    theta0 = prior.sample(1, np.random.default_rng(1))[0] * 0.2
    pred = model.predict(theta0)
    warm = _warm_starts(model, theta0, pred)
    assert callable(warm)  # the 3-PRS offers them; a linearised model does not
    assert _warm_starts(linearise(model, theta0), theta0, pred) is pred.poses
    X = theta0 + prior.sample(5, np.random.default_rng(2)) * 0.3
    plain = log_posterior_function(model, prior, idx, guess=pred.poses, base=theta0)(X)
    tangent = log_posterior_function(model, prior, idx, guess=warm, base=theta0)(X)
    assert np.isfinite(plain).all()
    np.testing.assert_allclose(tangent, plain, rtol=1e-10)


def test_linear_surrogate_on_the_machine(prs3, sim6):
    model = MeasurementModel.from_recording(prs3, sim6.recording, dof=3).subset(np.arange(8))
    res = sample_posterior(model, free=FREE, n_walkers=10, n_steps=500, seed=2, surrogate="linear")
    assert "linearisation error" in res.message
    assert res.success, res.message


def test_an_existing_checkpoint_is_not_replaced_by_a_fresh_run(prs3, sim6, tmp_path):
    # --checkpoint c.npz without --resume started afresh and saved over the chain the file held
    model = MeasurementModel.from_recording(prs3, sim6.recording)
    ck = tmp_path / "c.npz"
    ck.write_bytes(b"a chain of many hours")
    with pytest.raises(InputError, match=r"--checkpoint .*c.npz: a file is there already; .* Expected --resume"):
        sample_posterior(model, n_steps=40, checkpoint=ck, surrogate="linear")
    assert ck.read_bytes() == b"a chain of many hours"


@pytest.mark.parametrize("options, match", [
    ({"surrogate": "quadratic"}, "surrogate: expected 'none' or 'linear'"),
    ({"resume": True}, "resume: give the checkpoint"),
    ({"checkpoint": "c.npz", "checkpoint_every": 0}, r"checkpoint_every \(--checkpoint-every\): expected a positive number"),
    ({"checkpoint": "missing.npz", "resume": True}, r"--resume: .*missing.npz: no checkpoint there"),
    ({"ess": 0}, r"ess \(--ess\): expected a positive effective sample size .*got 0"),
    ({"ess": float("nan")}, r"ess \(--ess\): expected a positive effective sample size .*got nan"),
    ({"ess": True}, r"ess \(--ess\): expected a positive effective sample size .*got True"),
    ({"ess": "4000"}, r"ess \(--ess\): expected a positive effective sample size .*got '4000'"),
])
def test_bad_run_options_are_refused_before_the_map(prs3, sim6, tmp_path, monkeypatch, options, match):
    # review: these were refused only after the MAP and the proposal check (seconds to minutes of work)
    import bayescal.bayes.mcmc as mcmc

    def no_map(*args, **kwargs):
        raise AssertionError("the MAP ran before the options were checked")

    monkeypatch.setattr(mcmc, "_map_start", no_map)
    monkeypatch.chdir(tmp_path)
    model = MeasurementModel.from_recording(prs3, sim6.recording)
    with pytest.raises(InputError, match=match):
        sample_posterior(model, n_steps=40, **options)
