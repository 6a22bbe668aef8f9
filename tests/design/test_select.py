"""Greedy selection with rank-k updates against brute force; exchange never lowers the criterion."""

import numpy as np
import pytest

from bayescal.design import CRITERIA, PRIOR_BASED, brute_force_greedy, exchange_refine, greedy_select, output_weight, utility


def problem(seed=3, N=60, k=3, L=6):
    rng = np.random.default_rng(seed)
    # candidates of very different information content, so the choice matters
    blocks = rng.normal(size=(N, k, L)) * rng.uniform(0.2, 2.0, size=(N, 1, L))
    return blocks, 1e-9 * np.eye(L)


def output_weight_for(L, seed=4):
    """A full-rank, far from isotropic Q (criterion I), so I and A choose differently."""
    G = np.random.default_rng(seed).normal(size=(50, 3, L)) * np.geomspace(5.0, 0.1, L)
    return output_weight(G)


@pytest.mark.parametrize("criterion", CRITERIA)
def test_greedy_with_rank_updates_selects_what_brute_force_selects(criterion):
    blocks, M0 = problem()
    M0 = np.eye(blocks.shape[2]) if criterion in PRIOR_BASED else M0
    Q = output_weight_for(blocks.shape[2]) if criterion == "I" else None
    idx, M = greedy_select(blocks, 8, criterion, M0=M0, shortlist=blocks.shape[0], Q=Q)
    ref = brute_force_greedy(blocks, 8, criterion, M0=M0, Q=Q)
    np.testing.assert_array_equal(idx, ref)
    np.testing.assert_allclose(M, M0 + np.einsum("nki,nkj->ij", blocks[idx], blocks[idx]), rtol=1e-12)


@pytest.mark.parametrize("criterion", ["D", "A", "E", "O2", "O4", "O5", "EIG", "I"])
def test_exchange_never_lowers_the_criterion(criterion):
    blocks, M0 = problem(seed=5)
    M0 = np.eye(blocks.shape[2]) if criterion in PRIOR_BASED else M0
    Q = output_weight_for(blocks.shape[2]) if criterion == "I" else None
    rng = np.random.default_rng(0)
    start = rng.choice(blocks.shape[0], 6, replace=False)  # a poor start: exchange has work to do
    sel = exchange_refine(blocks, start, criterion, M0=M0, shortlist=blocks.shape[0], Q=Q)
    u0 = utility(criterion, M0 + np.einsum("nki,nkj->ij", blocks[start], blocks[start]), Q=Q)
    assert sel.greedy_utility == pytest.approx(u0)
    assert np.all(np.diff(sel.history) > 0)
    assert sel.utility >= u0
    assert sel.swaps == len(sel.history) - 1
    # the reported utility is the utility of the returned set, recomputed from scratch
    again = utility(criterion, M0 + np.einsum("nki,nkj->ij", blocks[sel.index], blocks[sel.index]), Q=Q)
    assert sel.utility == pytest.approx(float(again), rel=1e-9)
    assert len(set(sel.index.tolist())) == 6


def test_exchange_improves_a_random_start_for_d():
    blocks, M0 = problem(seed=7)
    start = np.arange(6)
    sel = exchange_refine(blocks, start, "D", M0=M0)
    assert sel.swaps > 0 and sel.utility > sel.greedy_utility


@pytest.mark.parametrize("criterion", ["D", "EIG", "E"])
def test_lazy_greedy_selects_what_full_reevaluation_selects(criterion):
    blocks, M0 = problem(seed=11, N=400, k=5, L=10)
    M0 = np.eye(10) if criterion == "EIG" else M0
    lazy, _ = greedy_select(blocks, 25, criterion, M0=M0, lazy=True, chunk=16)
    full, _ = greedy_select(blocks, 25, criterion, M0=M0, lazy=False)
    np.testing.assert_array_equal(lazy, full)


def test_i_optimal_selection_on_a_problem_with_a_known_answer():
    # two parameters (prior I), one-row candidates observing one parameter each with unit information;
    # the output depends 100x more (in variance) on parameter 1 than on parameter 2: Q = diag(100, 1).
    # Two poses: both on parameter 1 give 100/3 + 1 = 34.3, one each 100/2 + 1/2 = 50.5, both on 2
    # give 100 + 1/3.  I picks parameter 1 twice; D (and A, with Q = I) picks one of each.
    e1, e2 = np.array([[1.0, 0.0]]), np.array([[0.0, 1.0]])
    blocks = np.stack([e2, e1, e2, e1])
    Q = np.diag([100.0, 1.0])
    idx, M = greedy_select(blocks, 2, "I", M0=np.eye(2), Q=Q)
    assert sorted(idx.tolist()) == [1, 3]
    assert float(utility("I", M, Q=Q)) == pytest.approx(-(100 / 3 + 1))
    sel = exchange_refine(blocks, np.array([0, 1]), "I", M0=np.eye(2), Q=Q)
    assert sorted(sel.index.tolist()) == [1, 3] and sel.utility == pytest.approx(-(100 / 3 + 1))
    idx_d, _ = greedy_select(blocks, 2, "EIG", M0=np.eye(2))
    assert sorted(blocks[idx_d].sum(axis=0).ravel().tolist()) == [1.0, 1.0]


def test_greedy_with_repeats_matches_brute_force_and_can_repeat():
    from bayescal.design.select import brute_force_greedy, greedy_select
    from bayescal.errors import InputError

    rng = np.random.default_rng(5)
    N, k, L = 6, 2, 3
    blocks = rng.normal(size=(N, k, L))
    blocks[2] *= 4.0  # one pose far more informative than the rest: D-greedy measures it again
    M0 = 1e-3 * np.eye(L)
    for crit in ("D", "A"):
        fast, _ = greedy_select(blocks, 9, crit, M0=M0, repeats=True)
        slow = brute_force_greedy(blocks, 9, crit, M0=M0, repeats=True)
        assert np.array_equal(fast, slow)
        assert np.bincount(fast, minlength=N).max() > 1
    # 9 poses from 6 candidates only with repeats
    with pytest.raises(InputError):
        greedy_select(blocks, 9, "D", M0=M0)


def test_enriched_candidates_contain_the_box_corners(prs3):
    from bayescal.design import draw_candidates
    from bayescal.design.candidates import box_points

    lim = prs3.q_limits
    pts = box_points(lim)
    assert pts.shape == (27, 3)
    corners = np.array([[a, b, c] for a in lim[0] for b in lim[1] for c in lim[2]])
    for c in corners:
        assert np.any(np.all(np.isclose(pts, c), axis=1))
    cands = draw_candidates(prs3, 200, dof=6, rng=np.random.default_rng(0))
    assemblable = prs3.forward(corners).success
    for c in corners[assemblable]:
        assert np.any(np.all(np.isclose(cands.q, c), axis=1)), c
    # the uniform draws are unchanged by the enrichment (same random numbers, same first rows)
    plain = draw_candidates(prs3, 200, dof=6, rng=np.random.default_rng(0), box=False)
    assert np.array_equal(cands.q[: plain.n], plain.q)
    assert np.array_equal(cands.output_jacobian, plain.output_jacobian)
