"""The duality certificate of studies/choice_frontier.py: weak duality on random rules, and two instances decided by hand."""

import numpy as np

from tests.studies.conftest import load_study


def _mod():
    return load_study("choice_frontier")


def test_weak_duality_every_rule_pays_at_least_D():
    mod = _mod()
    rng = np.random.default_rng(5)
    n, V, r = 300, 7, 0.02
    phi = np.stack([rng.uniform(0, 1, (n, V)), 1 + rng.exponential(0.1, (n, V)), rng.uniform(0, 0.3, (n, V))], axis=2)
    C, F = phi[:, :, 0].max(axis=1).mean(), phi[:, :, 1].min(axis=1).mean()
    W = mod.simplex_grid(10)
    D = mod.dual_terms(phi, W, r).mean(axis=0)
    for _ in range(20):
        choice = rng.integers(0, V, n)
        d = np.arange(n)
        excess = np.array([C - 0.03 - phi[d, choice, 0].mean(), phi[d, choice, 1].mean() - F - r,
                           phi[d, choice, 2].mean() - mod.TAIL_SHARE])
        # a rule meeting every target has excess <= 0, so D <= 0 for every weight: weak duality
        assert np.all(W @ excess >= D - 1e-12)
        a = mod.achieved(phi, choice)
        assert np.isclose(a["gap"], C - phi[d, choice, 0].mean()) and np.isclose(a["tail"], phi[d, choice, 2].mean())


def test_conflicting_targets_are_certified_and_compatible_ones_are_not():
    mod = _mod()
    rng = np.random.default_rng(1)
    n = 400
    # candidate 0 always succeeds but is in the tail half the time; candidate 1 never succeeds, never in the tail
    base = np.array([[1.0, 1.0, 0.5], [0.0, 1.0, 0.0]])
    phi = np.repeat(base[None], n, axis=0) + rng.normal(0, 1e-3, (n, 2, 3)) * [0, 1, 0]
    res = mod.certify(phi, 0.02)
    assert res["certified"] and res["D"] > 0.1
    # one candidate meets everything: nothing to certify, and the compromise meets the targets
    good = np.array([[1.0, 1.0, 0.05], [0.95, 1.3, 0.4]])
    phi = np.repeat(good[None], n, axis=0)
    res = mod.certify(phi, 0.02)
    assert not res["certified"] and res["D"] <= 0
    c = res["compromise"]
    assert c["gap"] <= 1e-12 and c["tail"] <= 0.05 + 1e-12


def test_quick_run_writes_its_table(tmp_path):
    mod = _mod()
    assert mod.main(["--quick", "--out", str(tmp_path)]) == 0
    md = (tmp_path / "choice_frontier.md").read_text()
    assert "| 3-PRS 6-DOF | 0.5 | tsvd |" in md
    assert (tmp_path / "choice_frontier.json").exists()


def test_rules_blind_to_the_scale_weak_duality_and_two_instances():
    mod = _mod()
    rng = np.random.default_rng(2)
    n, S, V, r = 200, 2, 5, 0.02
    phi = np.stack([rng.uniform(0, 1, (n, S, V)), 1 + rng.exponential(0.1, (n, S, V)), rng.uniform(0, 0.3, (n, S, V))],
                   axis=3)
    w = rng.uniform(0, 2, (n, S))
    a = mod.agnostic_rows(phi, w, r)
    lam = mod.minimax_weights(a)[0]
    assert np.all(lam >= 0) and np.isclose(lam.sum(), 1)
    D = (a @ lam).min(axis=1).mean()
    # the LP optimum is at least as good as any vertex weight (one constraint alone)
    assert D >= max((a[:, :, k]).min(axis=1).mean() for k in range(a.shape[2])) - 1e-9
    for _ in range(10):  # weak duality: every rule's weighted excess is at least D
        choice = rng.integers(0, V, n)
        excess = a[np.arange(n), choice].mean(axis=0)
        assert excess @ lam >= D - 1e-9
    # the best candidate at one scale is the worst at the other
    good, bad = [1.0, 1.0, 0.0], [0.0, 2.0, 1.0]
    phi = np.array([[[good, bad], [bad, good]]] * n)
    # data that say nothing about the scale: no rule meets the targets at both
    res = mod.certify_agnostic(phi, np.ones((n, 2)), r, (1.0, 2.0))
    assert res["certified"]
    # data that reveal the scale (each data set possible under one scale only): the rule follows it
    w = np.repeat([[2.0, 0.0], [0.0, 2.0]], n // 2, axis=0)
    phi = np.concatenate([np.array([[[good, bad], [bad, good]]] * (n // 2))] * 2)
    res = mod.certify_agnostic(phi, w, r, (1.0, 2.0))  # even and odd data sets both hold both scales
    assert not res["certified"]
    assert all(c["gap"] <= 1e-12 and c["tail"] <= 1e-12 for c in res["compromise"])
