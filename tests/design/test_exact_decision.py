"""The yes/no search for an exact design below a threshold, against enumeration of every design."""

import itertools

import numpy as np
import pytest

from bayescal.design import design_mse, design_mse_bound
from bayescal.design.exact_decision import exact_design_below
from bayescal.errors import InputError

from .test_exact_bound import all_designs, problem


@pytest.mark.parametrize("seed", range(8))
@pytest.mark.parametrize("n", [2, 3, 4])
def test_answers_as_enumeration_does(seed, n):
    # just above the optimum some design is below; just under it none is (and the search must prove it)
    blocks, Q, q, _ = problem(seed, N=12)
    best = all_designs(blocks, Q, n).min()
    yes = exact_design_below(blocks, Q, n, best * (1 + 1e-6), q)
    assert yes.below is True
    assert len(yes.design) == n
    assert yes.design_mse == pytest.approx(design_mse(blocks, Q, list(yes.design)), rel=1e-12)
    assert yes.design_mse < best * (1 + 1e-6)
    no = exact_design_below(blocks, Q, n, best * (1 - 1e-6), q)
    assert no.below is False and no.design is None
    assert no.closed >= 1


@pytest.mark.parametrize("seed", range(4))
def test_the_coordinates_change_the_route_not_the_answer(seed):
    blocks, Q, q, _ = problem(seed, N=12)
    best = all_designs(blocks, Q, 3).min()
    other = np.random.default_rng(seed).normal(size=(12, 3))  # coordinates unrelated to the blocks
    for factor, expected in ((1 + 1e-6, True), (1 - 1e-6, False)):
        assert exact_design_below(blocks, Q, 3, best * factor, other).below is expected


def test_repeats_are_designs():
    # here the optimum of 4 poses puts two on one candidate (the corners of the box are the informative
    # poses): the search must find that design and prove nothing lower exists
    blocks, Q, q, _ = problem(0, N=8)
    designs = list(itertools.combinations_with_replacement(range(8), 4))
    values = np.array([design_mse(blocks, Q, S) for S in designs])
    best_S = designs[int(np.argmin(values))]
    assert len(set(best_S)) < 4
    d = exact_design_below(blocks, Q, 4, values.min() * (1 + 1e-9), q)
    assert d.below is True and len(set(d.design)) < 4
    assert exact_design_below(blocks, Q, 4, values.min() * (1 - 1e-6), q).below is False


def test_between_the_relaxed_bound_and_the_optimum_it_proves_none():
    # thresholds the relaxed bound leaves open (between it and the exact optimum): the search proves them empty
    decided = 0
    for seed in range(12):
        blocks, Q, q, _ = problem(seed, N=12)
        best = all_designs(blocks, Q, 3).min()
        relaxed = design_mse_bound(blocks, Q, 3, rtol=1e-9, iters=2000, inner=2000).lower_mse
        if best > relaxed * (1 + 1e-4):
            d = exact_design_below(blocks, Q, 3, 0.5 * (relaxed + best), q)
            assert d.below is False and d.nodes > 1
            decided += 1
    assert decided >= 2


def test_threshold_below_the_relaxed_bound_is_closed_at_the_root():
    blocks, Q, q, _ = problem(1, N=12)
    relaxed = design_mse_bound(blocks, Q, 3, rtol=1e-9, iters=2000, inner=2000).lower_mse
    d = exact_design_below(blocks, Q, 3, 0.99 * relaxed, q)
    assert d.below is False and d.nodes == 1 and d.closed == 1


def test_node_budget_gives_no_answer():
    blocks, Q, q, _ = problem(2, N=12)
    best = all_designs(blocks, Q, 4).min()
    relaxed = design_mse_bound(blocks, Q, 4, rtol=1e-9, iters=2000, inner=2000).lower_mse
    assert best > relaxed * (1 + 1e-4)
    d = exact_design_below(blocks, Q, 4, best * (1 - 1e-6), q, max_nodes=1)
    assert d.below is None and d.nodes == 1
    assert d.to_dict()["below"] is None


@pytest.mark.parametrize("kwargs, word", [
    (dict(n=0), "n"), (dict(threshold_mse=-1.0), "threshold_mse"), (dict(threshold_mse=np.nan), "threshold_mse"),
    (dict(coords=np.zeros((3, 2))), "coords"), (dict(max_nodes=0), "max_nodes"), (dict(Q=np.eye(2)), "Q"),
])
def test_bad_arguments_are_named(kwargs, word):
    blocks, Q, q, _ = problem(0, N=12)
    args = dict(blocks=blocks, Q=Q, n=3, threshold_mse=1.0, coords=q) | kwargs
    with pytest.raises(InputError, match=word):
        exact_design_below(**args)


@pytest.mark.parametrize("coords", ["zeros", "coarse"])
def test_coordinates_that_tie_still_give_the_right_answer(coords):
    # candidates with equal coordinates are different poses: the search must still tell them apart
    blocks, Q, q, _ = problem(0, N=12)
    X = np.zeros((12, 1)) if coords == "zeros" else (q[:, :1] > 0).astype(float)
    best = all_designs(blocks, Q, 3).min()
    assert exact_design_below(blocks, Q, 3, best * (1 + 1e-6), X).below is True
    assert exact_design_below(blocks, Q, 3, best * (1 - 1e-6), X).below is False


def test_copies_of_one_pose_are_one_pose():
    # a cell of identical candidates is not split, and the search still ends
    blocks, Q, q, _ = problem(3, N=12)
    blocks = np.concatenate([blocks, blocks[:4]])
    q = np.concatenate([q, q[:4]])
    best = all_designs(blocks, Q, 3).min()
    assert exact_design_below(blocks, Q, 3, best * (1 - 1e-6), q).below is False
    assert exact_design_below(blocks, Q, 3, best * (1 + 1e-6), q).below is True


def test_stroke_fractions_are_zero_and_one_at_the_limits():
    from bayescal.design.exact_decision import stroke_fractions

    lim = np.array([[400.0, 600.0], [-1.0, 1.0]])
    u = stroke_fractions(np.array([[400.0, 1.0], [500.0, -0.5]]), lim)
    assert np.allclose(u, [[0.0, 1.0], [0.5, 0.25]])
    with pytest.raises(InputError, match="q_limits"):
        stroke_fractions(np.zeros((2, 2)), np.array([[1.0, 0.0], [0.0, 1.0]]))
