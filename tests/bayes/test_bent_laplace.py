"""The bent Laplace map: closed-form bananas, its inverse, the gradient it is fitted from, and a real recording."""

from __future__ import annotations

from pathlib import Path

import emcee
import numpy as np
import pytest

from bayescal.bayes.bent_laplace import BentLaplace, bent_laplace, log_posterior_gradient
from bayescal.bayes.mcmc import log_posterior_function, sample_posterior
from bayescal.bayes.moves import IndependenceMove, default_moves
from bayescal.bayes.priors import map_estimate, prior_from_machine
from bayescal.errors import InputError

EXAMPLE = Path(__file__).resolve().parents[2] / "examples" / "positioner"


def _banana(b: float, sigma: float, a: float = 0.0):
    """log p(u, v) = log N(u; 0, 1) + log N(v; b u^2 + a u^3, sigma^2), normalised; and its gradient."""
    def logp(X):
        u, v = X[:, 0], X[:, 1]
        m = b * u**2 + a * u**3
        return -0.5 * u**2 - 0.5 * ((v - m) / sigma) ** 2 - np.log(2 * np.pi * sigma)

    def grad(x):
        u, v = x
        r = (v - b * u**2 - a * u**3) / sigma**2
        return np.array([-u + r * (2 * b * u + 3 * a * u**2), -r])

    return logp, grad


def test_the_bend_of_a_quadratic_valley_is_its_closed_form():
    b, sigma = 0.7, 0.05
    _, grad = _banana(b, sigma)
    # mode (0, 0), Laplace covariance diag(1, sigma^2); the prior decides u (std 1), the data v
    bend = bent_laplace(grad, [0.0, 0.0], np.diag([1.0, sigma**2]), [1.0, 100 * sigma])
    # whitened coordinates are in the eigenbasis: the prior-decided one is the parameter u
    assert bend.prior_decided.size == 1 and bend.data_decided.size == 1
    np.testing.assert_allclose(np.abs(bend.basis[:, bend.prior_decided].ravel()), [1.0, 0.0], atol=1e-12)
    # whitened v = v / sigma, so the conditional mode b u^2 is (b / sigma) u^2 = 1/2 G u^2
    np.testing.assert_allclose(abs(bend.G[0, 0, 0]), 2 * b / sigma, rtol=1e-9)
    assert bend.bent == 1
    w = np.zeros((2, 2))
    w[:, bend.prior_decided[0]] = [1.3, -2.0]
    x = bend.to_x(w)  # v = 0 in whitened units: the valley's floor
    np.testing.assert_allclose(x[:, 1], b * np.array([1.3, -2.0]) ** 2, rtol=1e-9)


def test_a_gaussian_proposal_through_the_exact_bend_is_the_banana_itself():
    # pushed through x = (u, sigma w + b u^2), N(0, I) is exactly N(u) N(v; b u^2, sigma^2): every proposal accepted
    b, sigma = 0.7, 0.05
    logp, grad = _banana(b, sigma)
    bend = bent_laplace(grad, [0.0, 0.0], np.diag([1.0, sigma**2]), [1.0, 100 * sigma])
    move = IndependenceMove([0.0, 0.0], np.diag([1.0, sigma**2]), df=np.inf, bend=bend)
    rng = np.random.default_rng(0)
    X = bend.to_x(rng.normal(size=(50, 2)) * 2)
    np.testing.assert_allclose(move.log_density(X), logp(X), rtol=1e-10, atol=1e-10)
    s = emcee.EnsembleSampler(8, 2, logp, vectorize=True, moves=[(move, 1.0)])
    s.run_mcmc(X[:8], 200)
    assert np.all(s.acceptance_fraction == 1.0)
    # the straight Laplace proposal accepts far less of the same banana
    s2 = emcee.EnsembleSampler(8, 2, logp, vectorize=True,
                               moves=[(IndependenceMove([0.0, 0.0], np.diag([1.0, sigma**2]), df=np.inf), 1.0)])
    s2.run_mcmc(X[:8], 200)
    assert s2.acceptance_fraction.mean() < 0.3


def test_a_scaled_t_through_the_bend_has_the_closed_form_density():
    # x = (u, v) = T(s z), z ~ N(0, I): u ~ N(0, s^2), v | u ~ N(b u^2, (s sigma)^2)
    b, sigma, sc = 0.7, 0.05, 1.3
    _, grad = _banana(b, sigma)
    bend = bent_laplace(grad, [0.0, 0.0], np.diag([1.0, sigma**2]), [1.0, 100 * sigma])
    move = IndependenceMove([0.0, 0.0], np.diag([1.0, sigma**2]), df=np.inf, scale=sc, bend=bend)
    X = move.draw(200, np.random.RandomState(4))
    u, v = X[:, 0], X[:, 1]
    ref = -0.5 * (u / sc) ** 2 - 0.5 * ((v - b * u**2) / (sc * sigma)) ** 2 - np.log(2 * np.pi * sc**2 * sigma)
    np.testing.assert_allclose(move.log_density(X), ref, rtol=1e-10, atol=1e-10)
    assert abs(np.std(u) / sc - 1) < 0.2
    with pytest.raises(ValueError, match="centred at mean"):
        IndependenceMove([0.1, 0.0], np.diag([1.0, sigma**2]), bend=bend)


def test_an_unsolvable_difference_point_loses_only_its_own_bend():
    # two prior-decided directions u1, u2 bending v; the gradient fails wherever u2 is pushed far: G keeps u1's bend
    b, sigma = 0.7, 0.05

    def grad(x):
        u1, u2, v = x
        if abs(u2) > 0.5:
            return np.full(3, np.nan)
        r = (v - b * u1**2) / sigma**2
        return np.array([-u1 + r * 2 * b * u1, -u2 / 0.8, -r])

    # distinct variances, so the eigenbasis is the parameter axes
    bend = bent_laplace(grad, np.zeros(3), np.diag([1.0, 0.8, sigma**2]), [1.0, 1.0, 100 * sigma])
    assert bend.prior_decided.size == 2 and np.all(np.isfinite(bend.G))
    assert bend.bent == 1
    np.testing.assert_allclose(np.abs(bend.G).max(), 2 * b / sigma, rtol=1e-9)


def _ensemble_after(move, logp, X0, steps, seed):
    s = emcee.EnsembleSampler(X0.shape[0], 2, logp, vectorize=True, moves=[(move, 1.0)])
    s.random_state = np.random.RandomState(seed).get_state()
    s.run_mcmc(X0, steps)
    return s.get_last_sample().coords, float(s.acceptance_fraction.mean())


def test_an_inexact_bend_leaves_the_target_invariant():
    # a cubic term the quadratic bend does not follow (E[u v] = 3 a, where the proposal has 0): walkers started on
    # exact draws of the target must stay on it, which takes the Hastings factor of the bent density
    b, sigma, a = 0.5, 0.1, 0.2
    logp, grad = _banana(b, sigma, a)
    bend = bent_laplace(grad, [0.0, 0.0], np.diag([1.0, sigma**2]), [1.0, 100 * sigma])
    rng = np.random.default_rng(1)
    n = 4000
    u = rng.normal(size=n)
    X0 = np.column_stack([u, b * u**2 + a * u**3 + sigma * rng.normal(size=n)])
    move = IndependenceMove([0.0, 0.0], np.diag([1.0, sigma**2]), bend=bend)
    X, acc = _ensemble_after(move, logp, X0, 30, seed=1)
    assert 0.2 < acc < 1.0  # the proposal is not the target: the factor matters
    uv = X[:, 0] * X[:, 1]
    se = uv.std() / np.sqrt(n)  # walkers are independent under this move
    assert abs(uv.mean() - 3 * a) < 4 * se, (uv.mean(), se)
    assert abs(np.mean(X[:, 0] ** 2) - 1.0) < 4 * np.sqrt(2.0 / n)

    class NoHastings(IndependenceMove):  # the same move with the factor dropped drifts to the proposal's shape
        def _propose(self, x0, random):
            new, _ = super()._propose(x0, random)
            return new, np.zeros(len(new))

    Xb, _ = _ensemble_after(NoHastings([0.0, 0.0], np.diag([1.0, sigma**2]), bend=bend), logp, X0, 30, seed=1)
    uvb = Xb[:, 0] * Xb[:, 1]
    assert abs(uvb.mean() - 3 * a) > 4 * uvb.std() / np.sqrt(n)


def test_to_w_inverts_to_x_and_no_prior_decided_direction_means_no_bend():
    rng = np.random.default_rng(2)
    d = 4
    A = rng.normal(size=(d, d))
    G = rng.normal(size=(2, 2, 2))
    G = G + G.transpose(0, 2, 1)
    bend = BentLaplace(rng.normal(size=d), A @ A.T + np.eye(d), np.array([0, 2]), np.array([1, 3]), G)
    W = rng.normal(size=(20, d))
    np.testing.assert_allclose(bend.to_w(bend.to_x(W)), W, atol=1e-10)
    with pytest.raises(InputError, match="splitting"):
        BentLaplace(np.zeros(d), np.eye(d), np.array([0, 2]), np.array([1, 2]), G)
    with pytest.raises(InputError, match="G expected shape"):
        BentLaplace(np.zeros(d), np.eye(d), np.array([0, 2]), np.array([1, 3]), G[:1])
    # every direction decided by the data: the plain Laplace map
    _, grad = _banana(0.7, 0.05)
    plain = bent_laplace(grad, [0.0, 0.0], np.diag([0.01, 0.05**2]), [1.0, 1.0])
    assert plain.prior_decided.size == 0 and plain.bent == 0
    with pytest.raises(InputError, match="prior_std"):
        bent_laplace(grad, [0.0, 0.0], np.eye(2), [1.0, -1.0])


def test_the_posterior_gradient_matches_finite_differences_of_the_log_posterior():
    from bayescal.io import read_recording
    from bayescal.instrument import prepare_model
    from bayescal.machines.files import load_machine

    machine, model, _ = prepare_model(load_machine(EXAMPLE / "machine.toml"),
                                      read_recording(EXAMPLE / "recording.csv"), frame="fit")
    model = model.subset(np.arange(0, model.n_poses, 10))
    prior = prior_from_machine(machine)
    idx = np.arange(len(prior.mean))
    rng = np.random.default_rng(3)
    # an offset of a tenth of the smaller of the tolerance and 1 (mm or rad) from the prior mean
    x = prior.mean + 0.1 * np.minimum(prior.std, 1.0) * rng.normal(size=idx.size)
    g = log_posterior_gradient(model, prior, idx)(x)
    lp = log_posterior_function(model, prior, idx)
    h = 1e-6 * np.maximum(np.abs(x), 1.0)
    E = np.diag(h)
    fd = (lp(x + E)[:, 0] - lp(x - E)[:, 0]) / (2 * h)
    np.testing.assert_allclose(g, fd, rtol=1e-4, atol=1e-6 * np.abs(fd).max())


def test_on_a_real_recording_the_bent_sampler_mixes_where_the_straight_one_sticks():
    # the bundled positioner (Apache-2.0) with the prior-decided parameters sampled too: 16 of 30 free
    from bayescal.io import read_recording
    from bayescal.instrument import prepare_model
    from bayescal.machines.files import load_machine

    machine, model, _ = prepare_model(load_machine(EXAMPLE / "machine.toml"),
                                      read_recording(EXAMPLE / "recording.csv"), frame="fit")
    model = model.subset(np.arange(0, model.n_poses, 5))
    prior = prior_from_machine(machine)
    bent = sample_posterior(model, prior=prior, free="auto", n_steps=400, seed=0)
    start = map_estimate(model, prior=prior, free="auto")
    idx = np.flatnonzero(start.free)
    straight = sample_posterior(model, prior=prior, free="auto", n_steps=400, seed=0,
                                moves=default_moves(start.theta[idx], start.covariance))
    assert idx.size == 30
    assert bent.success, bent.message
    assert bent.acceptance > 1.5 * straight.acceptance
