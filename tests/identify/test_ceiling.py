"""The attainable share of "within 10 % of the curve's best" (bayescal.identify.ceiling)."""

import numpy as np
import pytest

from bayescal.errors import InputError
from bayescal.identify.ceiling import choice_ceiling


def _problem(rng, N=30, p=6, spread=(1.5, -1.5)):
    A = rng.normal(size=(N, p)) * np.logspace(*spread, p) / np.sqrt(N)
    G = rng.normal(size=(40, p))
    return A, G


def test_bayes_rule_realises_the_ceiling_and_beats_fixed_values(rng):
    """With the right posterior, the predicted success rate equals the realised one (a calibration check)."""
    A, G = _problem(rng)
    lams = np.logspace(-2, 2, 17)
    c = choice_ceiling(A, G, "ridge", lams, fixed={"lambda=1": 1.0, "lambda=0.01": 0.01}, n_data=1500,
                       n_posterior=300, seed=3)
    se = np.sqrt(c.ceiling * (1 - c.ceiling) / c.n_data)
    assert abs(c.bayes_rule_rate - c.ceiling) < 4 * se + 0.02  # +0.02: the max of MC estimates is biased up
    for rate in c.fixed_rates.values():
        assert rate <= c.ceiling + 4 * se
    assert c.fixed_rates["lambda=0.01"] < c.fixed_rates["lambda=1"]  # the prior's own ratio is the better fixed value
    assert 0.0 < c.ceiling < 1.0 and "at most" in c.report()


def test_a_wrong_posterior_would_show(rng):
    """Control for the check above: rescaling the prior the truths come from breaks the agreement."""
    A, G = _problem(rng)
    ks = np.arange(1, 7)
    ok = choice_ceiling(A, G, "tsvd", ks, n_data=1500, n_posterior=300, seed=5)
    # truths 4x larger than the prior the posterior assumes: the predicted rate is no longer realised
    bad = choice_ceiling(A, G, "tsvd", ks, n_data=1500, n_posterior=300, seed=5, truth_scale=4.0)
    assert abs(ok.bayes_rule_rate - ok.ceiling) < 0.05
    assert bad.ceiling - bad.bayes_rule_rate > 0.1, (bad.ceiling, bad.bayes_rule_rate)
    assert ok.to_dict()["method"] == "tsvd"


def test_noise_free_limit_every_value_succeeds(rng):
    """When the data determine x almost exactly, every lambda in a moderate range gives the same estimate."""
    A = np.eye(4) * 1e5
    G = rng.normal(size=(12, 4))
    c = choice_ceiling(A, G, "ridge", np.logspace(-1, 1, 5), fixed={"lambda=1": 1.0}, n_data=50, n_posterior=50)
    assert c.ceiling == 1.0 and c.bayes_rule_rate == 1.0 and c.fixed_rates["lambda=1"] == 1.0


def test_unseen_directions_and_bad_input(rng):
    A = np.hstack([rng.normal(size=(20, 3)), np.zeros((20, 1))])  # the 4th parameter is never seen
    G = rng.normal(size=(10, 4))
    c = choice_ceiling(A, G, "tsvd", [1, 2, 3], n_data=300, n_posterior=200, seed=1)
    assert 0.0 < c.ceiling <= 1.0 and abs(c.bayes_rule_rate - c.ceiling) < 0.1
    with pytest.raises(InputError, match="k must be"):
        choice_ceiling(A, G, "tsvd", [0, 1])
    with pytest.raises(InputError, match="shapes"):
        choice_ceiling(A, G[:, :3], "ridge", [1.0])
    with pytest.raises(InputError, match="not one of"):
        choice_ceiling(A, G, "ridge", [0.5, 2.0], fixed={"lambda=1": 1.0})
    with pytest.raises(InputError, match="method"):
        choice_ceiling(A, G, "ls", [1.0])
