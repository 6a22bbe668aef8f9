"""Rounding the relaxed design and exchanging on a pool: exact designs against exhaustive enumeration and the bound."""

from itertools import combinations_with_replacement

import numpy as np
import pytest

from bayescal.design import design_mse, design_mse_bound, local_search, output_weight, round_weights
from bayescal.design.rounding import distinct_start, pool_from_bound
from bayescal.errors import InputError


def _problem(seed, N=8, k=2, L=3):
    rng = np.random.default_rng(seed)
    blocks = rng.normal(size=(N, k, L)) * rng.uniform(0.2, 2.0, size=(N, 1, L))
    Q = output_weight(rng.normal(size=(20, 3, L)) * np.array([3.0, 1.0, 0.3]))
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
