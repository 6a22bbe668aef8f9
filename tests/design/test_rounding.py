"""Rounding the relaxed design and exchanging on a pool: exact designs against exhaustive enumeration and the bound."""

from itertools import combinations, combinations_with_replacement

import numpy as np
import pytest

from bayescal.design import design_mse, design_mse_bound, local_search, output_weight, round_weights
from bayescal.design.rounding import distinct_start, greedy_fill, multistart_search, pool_from_bound
from bayescal.errors import InputError


def _problem(seed, N=8, k=2, L=3):
    rng = np.random.default_rng(seed)
    blocks = rng.normal(size=(N, k, L)) * rng.uniform(0.2, 2.0, size=(N, 1, L))
    Q = output_weight(rng.normal(size=(20, 3, L)) * np.geomspace(3.0, 0.3, L))
    return blocks, Q


def test_efficient_rounding_keeps_the_total_and_the_proportions():
    w = np.array([0.0, 2.5, 0.0, 1.25, 1.25, 5.0])  # sums to 10
    idx = round_weights(w, 10)
    counts = np.bincount(idx, minlength=w.size)
    assert counts.sum() == 10 and counts[0] == counts[2] == 0
    assert np.all(np.abs(counts - w) <= 1)  # efficient rounding: every count within one of n w_i
    # fewer poses than support points: the largest weights, one pose each
    assert sorted(round_weights(w, 2).tolist()) == [1, 5]
    with pytest.raises(InputError, match="positive"):
        round_weights(w, 0)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_rounded_design_lies_between_the_bound_and_the_start_and_near_the_exhaustive_best(seed):
    blocks, Q = _problem(seed)
    n = 5
    exhaustive = min(design_mse(blocks, Q, s) for s in combinations_with_replacement(range(blocks.shape[0]), n))
    b = design_mse_bound(blocks, Q, n, rtol=1e-8)
    start = round_weights(b.weights, n)
    idx = local_search(blocks, Q, start, np.arange(blocks.shape[0]))
    v = design_mse(blocks, Q, idx)
    assert len(idx) == n
    assert b.lower_mse <= exhaustive + 1e-12  # the bound holds for every design with repeats
    assert v <= design_mse(blocks, Q, start) + 1e-15  # exchanges never make it worse
    assert v <= 1.02 * exhaustive  # and here land within 2 % of the best of all 792 designs


def test_distinct_designs_have_no_repeats_and_design_mse_matches_the_formula():
    blocks, Q = _problem(4)
    b = design_mse_bound(blocks, Q, 4)
    pool = pool_from_bound(b.weights, blocks, Q, size=8)
    idx = local_search(blocks, Q, distinct_start(b.weights, blocks, Q, 4, pool), pool, repeats=False)
    assert len(set(idx.tolist())) == 4
    A = blocks[idx].reshape(-1, blocks.shape[2])
    assert design_mse(blocks, Q, idx) == pytest.approx(np.trace(np.linalg.inv(np.eye(3) + A.T @ A) @ Q), rel=1e-12)


def _brute_local_optimum(blocks, Q, S, pool, repeats):
    """No single exchange (remove one pose, add one pool candidate) lowers E[MSE]: every pair computed directly."""
    f = design_mse(blocks, Q, S)
    for a in set(S.tolist()):
        for j in pool:
            if not repeats and j in S:
                continue
            T = list(S)
            T[T.index(a)] = j
            assert design_mse(blocks, Q, T) >= f * (1 - 1e-10)


@pytest.mark.parametrize("repeats", [True, False])
def test_woodbury_exchange_ends_at_a_brute_force_local_optimum(repeats):
    blocks, Q = _problem(5, N=14, k=2, L=4)
    start = np.array([0, 1, 2, 3, 4])
    pool = np.arange(2, 14)
    S = local_search(blocks, Q, start, pool, repeats=repeats, max_moves=100)
    assert design_mse(blocks, Q, S) <= design_mse(blocks, Q, start)
    if not repeats:
        assert len(set(S.tolist())) == S.size
    # only pool candidates entered
    assert set(S.tolist()) - set(start.tolist()) <= set(pool.tolist())
    _brute_local_optimum(blocks, Q, S, pool, repeats)


def test_greedy_fill_adds_the_best_candidate_each_step():
    blocks, Q = _problem(6, N=9, k=2, L=4)
    S = greedy_fill(blocks, Q, 4, np.arange(9), start=[3], repeats=True)
    T = [3]
    for _ in range(3):
        T.append(min(range(9), key=lambda j: design_mse(blocks, Q, T + [j])))
    assert S.tolist() == T
    D = greedy_fill(blocks, Q, 9, np.arange(9), repeats=False)
    assert sorted(D.tolist()) == list(range(9))


@pytest.mark.parametrize("repeats", [True, False])
@pytest.mark.parametrize("shape", [(8, 2, 3, 5), (10, 1, 4, 6), (12, 2, 5, 4)])
def test_multistart_search_finds_the_exhaustive_optimum_and_stays_above_the_bound(shape, repeats):
    """Every design of n poses from N candidates (with or without repeats) enumerated: on 10 random problems
    per shape the search returns the best of them (a tolerance of 1e-9: round-off only)."""
    N, k, L, n = shape
    designs = list((combinations_with_replacement if repeats else combinations)(range(N), n))
    for seed in range(10):
        blocks, Q = _problem(100 + seed, N=N, k=k, L=L)
        best = min(design_mse(blocks, Q, s) for s in designs)
        b = design_mse_bound(blocks, Q, n, rtol=1e-8)
        idx, start = multistart_search(blocks, Q, b.weights, n, np.arange(N), repeats=repeats)
        v = design_mse(blocks, Q, idx)
        assert len(idx) == n and (repeats or len(set(idx.tolist())) == n)
        assert b.lower_mse <= v  # the plan is never below the bound
        assert v <= design_mse(blocks, Q, start)
        assert v <= best * (1 + 1e-9)


def test_multistart_search_leaves_a_local_optimum_that_single_exchanges_keep():
    """Seed 33 (12 candidates, 4 poses): single exchanges from the rounded relaxed design over all candidates
    stall 6 % above the best design; the two-pose exchanges reach it."""
    blocks, Q = _problem(33, N=12, k=2, L=5)
    best = min(design_mse(blocks, Q, s) for s in combinations_with_replacement(range(12), 4))
    b = design_mse_bound(blocks, Q, 4, rtol=1e-8)
    stalled = design_mse(blocks, Q, local_search(blocks, Q, round_weights(b.weights, 4), np.arange(12)))
    assert stalled > 1.05 * best
    idx, _ = multistart_search(blocks, Q, b.weights, 4, np.arange(12))
    assert design_mse(blocks, Q, idx) <= best * (1 + 1e-9)
