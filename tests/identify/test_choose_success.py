"""The ``success`` rule for lambda and k against a Bayes decision integrated in closed form.

With a single output row ``g`` the output error of candidate ``v`` is
``|a_v - t|`` with ``a_v = g . x_v`` and ``t = g . x`` Gaussian under the
posterior, so the probability that ``v`` is within ``r`` of the best is a
Gaussian probability of a union of intervals: ``|a_v - t| <= r |a_u - t|``
fails exactly for ``t`` between ``(r a_u + a_v) / (r + 1)`` and
``(r a_u - a_v) / (r - 1)``.
"""

import numpy as np
import pytest
from scipy.stats import multivariate_normal, norm

from bayescal.errors import InputError
from bayescal.identify.ceiling import success_probabilities
from bayescal.identify.choose import RULES, choose_linear, lambda_grid
from bayescal.identify.scale_prior import DEFAULT_HYPERPRIOR, FLAT_HYPERPRIOR, ScaleHyperprior


def exact_success(a: np.ndarray, mu: float, sd: float, r: float) -> np.ndarray:
    """P(|a_v - t| <= r min_u |a_u - t|), t ~ N(mu, sd^2), for every v: exact."""
    return exact_success_mixture(a, np.array([mu]), np.array([sd]), np.array([1.0]), r)


def exact_success_mixture(a: np.ndarray, mu: np.ndarray, sd: np.ndarray, w: np.ndarray, r: float) -> np.ndarray:
    """The same for t from the mixture sum_j w_j N(mu_j, sd_j^2) (the failure intervals depend on a only)."""
    out = np.empty(a.size)
    for v in range(a.size):
        iv = []
        for u in range(a.size):
            if a[u] == a[v]:
                continue
            e1, e2 = (r * a[u] + a[v]) / (r + 1), (r * a[u] - a[v]) / (r - 1)
            iv.append((min(e1, e2), max(e1, e2)))
        iv.sort()
        merged = []
        for lo, hi in iv:
            if merged and lo <= merged[-1][1]:
                merged[-1][1] = max(merged[-1][1], hi)
            else:
                merged.append([lo, hi])
        fail = sum(float(w @ (norm.cdf(hi, mu, sd) - norm.cdf(lo, mu, sd))) for lo, hi in merged)
        out[v] = float(w.sum()) - fail
    return out


def _default_log_hp(log_c: np.ndarray) -> np.ndarray:
    """The default hyperprior from scipy: a normal density of log c, truncated to [low, high]."""
    hp = DEFAULT_HYPERPRIOR
    assert hp.kind == "lognormal"
    inside = (np.exp(log_c) >= hp.low) & (np.exp(log_c) <= hp.high)
    return np.where(inside, norm.logpdf(log_c, np.log(hp.centre), hp.width), -np.inf)


def test_exact_formula_against_brute_force(rng):
    """The interval formula itself, against direct sampling (independent of bayescal)."""
    a = np.array([-1.0, 0.2, 0.3, 2.0])
    t = rng.normal(0.5, 0.8, 200_000)
    err = np.abs(a[None, :] - t[:, None])
    mc = (err <= 1.1 * err.min(axis=1, keepdims=True)).mean(axis=0)
    np.testing.assert_allclose(exact_success(a, 0.5, 0.8, 1.1), mc, atol=0.005)


def test_success_probabilities_match_closed_form(rng):
    """Posterior N(mean, diag(sd^2)) in 3 coordinates, one output row: Monte Carlo = exact."""
    mean, sd = np.array([0.4, -0.2, 1.0]), np.array([0.3, 0.7, 1.1])
    g = np.array([[1.0, 2.0, -0.5]])
    est = rng.normal(size=(6, 3))
    prob, exp_ratio = success_probabilities(est, mean, sd, g, ratio=1.1, n_posterior=40_000, seed=1)
    exact = exact_success(est @ g[0], float(g[0] @ mean), float(np.sqrt(np.sum((g[0] * sd) ** 2))), 1.1)
    np.testing.assert_allclose(prob, exact, atol=0.01)
    assert np.all(exp_ratio >= 1.0)
    with pytest.raises(InputError, match="shapes"):
        success_probabilities(est, mean[:2], sd[:2], g)


@pytest.mark.parametrize("method", ["tsvd", "ridge"])
def test_success_rule_is_the_exact_bayes_decision(rng, method):
    """On a linear problem with one output row, the rule picks the candidate the exact integral prefers."""
    N, p = 30, 6
    A = rng.normal(size=(N, p)) * np.logspace(0.8, -0.8, p)
    g = rng.normal(size=(1, p))
    grid = np.logspace(-2, 2, 9) if method == "ridge" else None
    checked = 0
    for trial in range(4):
        z = A @ rng.normal(size=p) + rng.normal(size=N)
        ch = choose_linear(A, z, method, rule="success", output_map=g, grid=grid, n_posterior=20_000, seed=trial,
                           integrate_scale=False)
        # the empirical-Bayes posterior the rule uses, rebuilt here from lam_ev
        lam = ch.curves["risk_prior_ratio"]
        U, s, Vt = np.linalg.svd(A, full_matrices=False)
        beta = U.T @ z
        m, sd = s * beta / (s**2 + lam), 1.0 / np.sqrt(s**2 + lam)
        F = (np.arange(p)[None, :] < ch.grid[:, None]) if method == "tsvd" else s**2 / (s**2 + ch.grid[:, None])
        a = (F * beta / s) @ (Vt @ g[0])
        gv = Vt @ g[0]
        exact = exact_success(a, float(gv @ m), float(np.sqrt(np.sum((gv * sd) ** 2))), 1.1)
        np.testing.assert_allclose(ch.curves["success_probability"], exact, atol=0.015)
        assert exact[list(ch.grid).index(ch.value)] >= exact.max() - 0.01
        checked += 1
    assert checked == 4 and "success" in RULES and ch.rule == "success"


@pytest.mark.parametrize("hyperprior, log_hp", [
    (FLAT_HYPERPRIOR, lambda log_c: np.zeros_like(log_c)),
    (DEFAULT_HYPERPRIOR, lambda log_c: _default_log_hp(log_c)),
    (ScaleHyperprior("loguniform", low=0.3, high=6.0),
     lambda log_c: np.where((log_c >= np.log(0.3)) & (log_c <= np.log(6.0)), 0.0, -np.inf)),
])
def test_success_rule_with_the_prior_scale_integrated_out(rng, hyperprior, log_hp):
    """integrate_scale=True: the posterior is a mixture over the lambda grid weighted by the evidence (computed here
    by scipy's dense Gaussian density) times the hyperprior of c = 1/sqrt(lam) (scipy's normal density of log c for
    the log-normal); its exact success probabilities, component by component, and the exact Bayes decision."""
    N, p = 25, 5
    A = rng.normal(size=(N, p)) * np.logspace(0.6, -0.6, p)
    g = rng.normal(size=(1, p))
    z = A @ (1.7 * rng.normal(size=p)) + rng.normal(size=N)
    ch = choose_linear(A, z, "tsvd", rule="success", output_map=g, n_posterior=30_000, seed=3, hyperprior=hyperprior)
    U, s, Vt = np.linalg.svd(A, full_matrices=False)
    beta, gv = U.T @ z, Vt @ g[0]
    lams = lambda_grid(s)
    log_ev = np.array([multivariate_normal(np.zeros(N), np.eye(N) + A @ A.T / lam).logpdf(z) for lam in lams])
    lp = log_ev + log_hp(-0.5 * np.log(lams))
    w = np.exp(lp - lp.max())
    w /= w.sum()
    a = ((np.arange(p)[None, :] < np.arange(1, p + 1)[:, None]) * beta / s) @ gv
    exact = np.zeros(p)
    for lam, wj in zip(lams, w):
        if wj < 1e-8:
            continue
        m, sd = s * beta / (s**2 + lam), 1.0 / np.sqrt(s**2 + lam)
        exact += wj * exact_success(a, float(gv @ m), float(np.sqrt(np.sum((gv * sd) ** 2))), 1.1)
    exact /= w[w >= 1e-8].sum()
    np.testing.assert_allclose(ch.curves["success_probability"], exact, atol=0.015)
    assert exact[ch.value - 1] >= exact.max() - 0.01


@pytest.mark.parametrize("seed", [11, 12, 13])
def test_hyperprior_changes_the_ridge_decision_as_the_exact_integral_does(seed):
    """Ridge, few weak rows, one output row: the exact Bayes decision under the flat and under the log-normal
    hyperprior differ, and the rule follows the exact decision in both cases (each within 0.01 of the exact best).

    Its own generator: with the session's, the problem drawn depended on which tests ran before, and some
    problems have no data set among the six where the two hyperpriors decide differently."""
    rng = np.random.default_rng(seed)
    N, p = 8, 5
    A = rng.normal(size=(N, p)) * np.logspace(0.3, -0.9, p)
    g = rng.normal(size=(1, p))
    grid = np.logspace(-2, 2, 9)
    U, s, Vt = np.linalg.svd(A, full_matrices=False)
    gv = Vt @ g[0]
    lams = lambda_grid(s)
    differ = 0
    for trial in range(6):
        z = A @ (0.5 * rng.normal(size=p)) + rng.normal(size=N)
        beta = U.T @ z
        log_ev = np.array([multivariate_normal(np.zeros(N), np.eye(N) + A @ A.T / lam).logpdf(z) for lam in lams])
        a = ((s**2 / (s**2 + grid[:, None])) * beta / s) @ gv
        picks = []
        for hp, log_hp in ((FLAT_HYPERPRIOR, 0.0), (DEFAULT_HYPERPRIOR, _default_log_hp(-0.5 * np.log(lams)))):
            lp = log_ev + log_hp
            w = np.exp(lp - lp.max())
            w /= w.sum()
            mus = (s * beta / (s[None, :] ** 2 + lams[:, None])) @ gv
            sds = np.sqrt(np.sum(gv**2 / (s[None, :] ** 2 + lams[:, None]), axis=1))
            exact = exact_success_mixture(a, mus, sds, w, 1.1)
            ch = choose_linear(A, z, "ridge", rule="success", output_map=g, grid=grid, n_posterior=20_000,
                               seed=trial, hyperprior=hp)
            assert exact[list(ch.grid).index(ch.value)] >= exact.max() - 0.01
            picks.append(int(np.argmax(exact)))
        differ += picks[0] != picks[1]
    assert differ >= 1  # the hyperprior is not a no-op here


def test_success_rule_realises_its_prediction(rng):
    """Truths from the prior: the rule's realised success rate matches its mean predicted probability,
    and is not below the risk rule's (the Bayes decision for the event beats a decision for another loss)."""
    N, p = 40, 8
    A = rng.normal(size=(N, p)) * np.logspace(1, -1.2, p) / 2
    G = rng.normal(size=(20, p))
    hits = {"success": [], "risk": []}
    pred = []
    for t in range(150):
        x = rng.normal(size=p)
        z = A @ x + rng.normal(size=N)
        ch = choose_linear(A, z, "tsvd", rule="success", output_map=G, n_posterior=300, seed=t)
        xs = {}
        U, s, Vt = np.linalg.svd(A, full_matrices=False)
        coef = (U.T @ z) / s
        errs = np.array([np.linalg.norm(G @ (Vt[:k].T @ coef[:k] - x)) for k in range(1, p + 1)])
        for r in hits:
            xs[r] = ch.choices[r]
            hits[r].append(errs[xs[r] - 1] <= 1.1 * errs.min())
        pred.append(ch.curves["success_probability"][ch.choices["success"] - 1])
    rate, predicted = np.mean(hits["success"]), np.mean(pred)
    se = np.sqrt(rate * (1 - rate) / 150)
    # the evidence estimate of the prior scale is noisy with 8 parameters: allow that beyond sampling error
    assert abs(rate - predicted) < 4 * se + 0.05, (rate, predicted)
    assert rate >= np.mean(hits["risk"]) - 3 * se, (rate, np.mean(hits["risk"]))
