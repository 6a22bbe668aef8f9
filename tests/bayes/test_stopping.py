"""A posterior run that stops at the ESS asked for: the same draws as the full run, the closed form, the refusals."""

from __future__ import annotations

import numpy as np
import pytest

from bayescal.bayes.mcmc import sample_posterior
from bayescal.bayes.stopping import EssStop, checked_ess
from bayescal.errors import InputError


@pytest.fixture(scope="module")
def full_and_stopped(linear_problem):
    lin, idx, m, C, free = linear_problem
    stopped = sample_posterior(lin, free=free, n_walkers=16, n_steps=1500, seed=5, ess=2000)
    full = sample_posterior(lin, free=free, n_walkers=16, n_steps=stopped.n_steps, seed=5)
    return full, stopped


def test_a_run_stops_once_the_ess_is_reached_with_the_full_runs_first_draws(full_and_stopped):
    full, stopped = full_and_stopped
    assert full.success and stopped.success, (full.message, stopped.message)
    assert stopped.n_steps < 1500
    assert np.min(stopped.ess_bulk) >= 2000 and np.min(stopped.ess_tail) >= 2000
    assert stopped.min_ess == 2000 and full.min_ess == 400
    # no check draws a random number: the stopped run is the run of that many steps, bit for bit
    np.testing.assert_array_equal(stopped.tree["posterior"]["theta"].values, full.tree["posterior"]["theta"].values)
    np.testing.assert_array_equal(stopped.mean, full.mean)
    # the summary took the last check's R-hat and ESS: those the full run computes for the same chain
    for name in ("rhat", "ess_bulk", "ess_tail", "tau"):
        np.testing.assert_array_equal(getattr(stopped, name), getattr(full, name))
    # the burn-in is a fifth of what was run, and the answer says what the run had to reach
    assert stopped.burn == stopped.n_steps // 5
    assert stopped.to_dict()["convergence"]["min_ess"] == 2000.0
    assert "(>= 2000)" in stopped.report()


def test_the_summary_does_not_compute_the_last_checks_diagnostics_again(linear_problem, monkeypatch):
    import bayescal.bayes.mcmc as mcmc

    lin, _, _, _, free = linear_problem
    calls = []
    diagnostics, summarise = mcmc._diagnostics, mcmc._summarise
    monkeypatch.setattr(mcmc, "_diagnostics", lambda tree: calls.append("checks") or diagnostics(tree))
    monkeypatch.setattr(mcmc, "_summarise", lambda *a, **k: calls.append("summary") or summarise(*a, **k))
    res = sample_posterior(lin, free=free, n_walkers=16, n_steps=1500, seed=5, ess=2000)
    assert res.success and "checks" in calls and calls[-1] == "summary"


def test_the_stopped_posterior_matches_the_closed_form(full_and_stopped, linear_problem):
    _, stopped = full_and_stopped
    _, _, m, C, _ = linear_problem
    sd = np.sqrt(np.diag(C))
    # Monte Carlo error of the mean: sd / sqrt(ESS); 4 of them is a seeded, generous bound
    assert np.all(np.abs(stopped.mean - m) < 4 * sd / np.sqrt(stopped.ess_bulk))
    # the sd of a sample sd is about sd / sqrt(2 ESS): 2,000 effective draws put it within 1.6 %; 6 % is 4 of them
    np.testing.assert_allclose(np.sqrt(np.diag(stopped.covariance)), sd, rtol=0.06)


def test_an_ess_out_of_reach_within_n_steps_is_not_converged(linear_problem):
    lin, _, _, _, free = linear_problem
    res = sample_posterior(lin, free=free, n_walkers=16, n_steps=120, seed=5, ess=50_000)
    assert res.n_steps == 120 and not res.success
    assert "ESS" in res.message and "< 50000" in res.message and res.more_steps > 0
    assert np.all(np.isnan(res.std))


@pytest.mark.parametrize("killed_at", [-1, -3, "check"])
def test_a_killed_run_resumed_stops_where_the_uninterrupted_run_stopped(full_and_stopped, linear_problem, tmp_path,
                                                                       killed_at):
    # review: a resumed run checked its whole saved chain at once and stopped there, not where the uninterrupted
    # run stopped; now the checks before the saved length are the ones that failed when it ran
    lin, _, _, _, free = linear_problem
    _, stopped = full_and_stopped
    from bayescal.bayes.stopping import EssStop

    rule = EssStop(ess=2000, n_walkers=16, tau_factor=50, burn=lambda s: s // 5, passes=None, tau=None)
    checks = [rule.first_check()]
    while checks[-1] < stopped.n_steps:
        checks.append(rule.next_check(checks[-1]))
    assert checks[-1] == stopped.n_steps  # it stops at a check
    at = checks[-2] if killed_at == "check" else stopped.n_steps + killed_at  # a failed check's length, or between
    ck = tmp_path / "c.npz"
    first = sample_posterior(lin, free=free, n_walkers=16, n_steps=at, seed=5, checkpoint=ck, ess=2000)
    assert first.n_steps == at  # "killed": the chain saved at ``at`` steps (its own summary may pass or not)
    assert killed_at != "check" or not first.success  # that check failed when the uninterrupted run made it
    again = sample_posterior(lin, free=free, n_walkers=16, n_steps=1500, seed=5, checkpoint=ck, resume=True, ess=2000)
    assert again.success and again.n_steps == stopped.n_steps
    np.testing.assert_array_equal(again.tree["posterior"]["theta"].values, stopped.tree["posterior"]["theta"].values)


def test_a_resumed_chain_already_at_its_cap_adds_no_step(linear_problem, tmp_path):
    lin, _, _, _, free = linear_problem
    ck = tmp_path / "c.npz"
    first = sample_posterior(lin, free=free, n_walkers=16, n_steps=600, seed=3, checkpoint=ck)
    again = sample_posterior(lin, free=free, n_walkers=16, n_steps=600, seed=3, checkpoint=ck, resume=True, ess=1000)
    assert first.success and again.success and again.n_steps == 600
    np.testing.assert_array_equal(again.tree["posterior"]["theta"].values, first.tree["posterior"]["theta"].values)


def test_the_progress_bar_of_a_run_that_stops_ends_full(linear_problem, capfd):
    # emcee's bar would restart at every check; ours runs over the steps and ends at the step the run stopped
    lin, _, _, _, free = linear_problem
    res = sample_posterior(lin, free=free, n_walkers=16, n_steps=1500, seed=5, ess=2000, progress=True)
    err = capfd.readouterr().err
    last = err.strip().split("\r")[-1]  # what the bar shows when it closes
    assert "sampling (stops at its ESS)" in last and f"{res.n_steps}/{res.n_steps}" in last and "100%" in last


def test_a_generous_cap_reserves_no_storage_it_does_not_use(linear_problem, monkeypatch):
    # review: emcee sized its storage for the whole cap before the first step (2 GB for a cap of 3,000,000 steps)
    import emcee

    lin, _, _, _, free = linear_problem
    grown = []
    grow = emcee.backends.Backend.grow
    monkeypatch.setattr(emcee.backends.Backend, "grow", lambda self, n, blobs: grown.append(n) or grow(self, n, blobs))
    res = sample_posterior(lin, free=free, n_walkers=16, n_steps=200_000, seed=5, ess=2000)
    assert res.success and sum(grown) == res.n_steps < 1000


class _Chain:
    """A stand-in for emcee's sampler: only its iteration."""

    def __init__(self, iteration: int):
        self.iteration = iteration


def _rule(tau: float, passes=lambda s, b: True, ess: float = 1000.0, n_walkers: int = 10) -> tuple[EssStop, list]:
    calls = []

    def full(sampler, burn):
        calls.append((sampler.iteration, burn))
        return passes(sampler, burn)

    rule = EssStop(ess=ess, n_walkers=n_walkers, tau_factor=50.0, burn=lambda steps: steps // 5, passes=full,
                   tau=lambda sampler, burn: np.array([tau, tau / 2]))
    return rule, calls


def test_the_checks_grow_by_a_tenth_from_the_length_independent_draws_would_need():
    rule, _ = _rule(1.0, ess=1000.0, n_walkers=10)
    first = rule.first_check()
    # 100 kept steps of 10 walkers are 1,000 draws; a fifth more is burnt
    assert first - first // 5 >= 100 and (first - 10) - (first - 10) // 5 < 100
    assert rule.next_check(50) == 60 and rule.next_check(200) == 220 and rule.next_check(1000) == 1100
    # review: it stepped by 10 from 50, minutes for an ESS of 1e12; now a few jumps, the same smallest length
    big, _ = _rule(1.0, ess=1e12, n_walkers=10)
    steps = big.first_check()
    assert steps - steps // 5 >= 1e11 > (steps - 10) - (steps - 10) // 5 and steps % 10 == 0
    fixed = EssStop(ess=1000.0, n_walkers=10, tau_factor=50.0, burn=lambda s: 30, passes=None, tau=None)
    assert fixed.first_check() == 130  # 100 kept steps after a burn-in of 30
    assert fixed.check_from(0) == 130 and fixed.check_from(131) == 143 and fixed.check_from(143) == 143


@pytest.mark.parametrize("steps, tau, expect_full, expect", [
    (100, 1.0, False, False),    # 80 kept steps: 800 draws, below 1,000 at any tau
    (200, 1.0, True, True),      # 160 kept steps x 10 walkers / tau 1 = 1,600: the full checks decide
    (200, 2.0, False, False),    # 160 < 50 tau = 100 is fine, but 1,600 / 2 = 800 < 1,000
    (200, 4.0, False, False),    # 160 kept steps < 50 x 4
    (200, np.nan, False, False),  # no autocorrelation time yet
])
def test_the_cheap_estimate_gates_the_full_checks(steps, tau, expect_full, expect):
    rule, calls = _rule(tau)
    assert rule(_Chain(steps)) is expect
    assert bool(calls) is expect_full
    if calls:
        assert calls == [(steps, steps // 5)]


def test_the_full_checks_have_the_last_word():
    rule, calls = _rule(1.0, passes=lambda s, b: False)
    assert rule(_Chain(200)) is False and len(calls) == 1


@pytest.mark.parametrize("bad", [0, -5, float("inf"), float("nan"), True, "400", [400]])
def test_bad_ess_is_refused_by_name(bad):
    with pytest.raises(InputError, match=r"ess \(--ess\): expected a positive effective sample size"):
        checked_ess(bad)


def test_good_ess_is_a_float():
    assert checked_ess(None) is None and checked_ess(4000) == 4000.0 and isinstance(checked_ess(np.int64(5)), float)


@pytest.mark.slow
def test_stopping_at_the_ess_keeps_the_stated_monte_carlo_error(linear_problem):
    # a run that stops when its diagnostics first pass could report an ESS its draws do not have: over 40 seeds
    # the stopped means' errors, in units of sd / sqrt(ESS), must have variance about 1 (160 values: the variance's
    # sampling sd is about 0.11, so 0.7-1.45 is 3-4 of them; the review measured 1.05)
    lin, _, m, C, free = linear_problem
    sd = np.sqrt(np.diag(C))
    z = []
    for seed in range(100, 140):
        res = sample_posterior(lin, free=free, n_walkers=16, n_steps=3000, seed=seed, ess=2000)
        assert res.success, res.message
        z.append((res.mean - m) / (sd / np.sqrt(res.ess_bulk)))
    assert 0.7 < np.var(np.array(z)) < 1.45, np.var(np.array(z))


def test_an_ess_below_the_usual_400_is_400(linear_problem):
    lin, _, _, _, free = linear_problem
    res = sample_posterior(lin, free=free, n_walkers=16, n_steps=1500, seed=5, ess=100)
    assert res.success and res.min_ess == 400.0 and min(res.ess_bulk.min(), res.ess_tail.min()) >= 400
