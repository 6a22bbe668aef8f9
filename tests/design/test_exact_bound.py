"""The exact-design bound against enumeration of every design and an independent solve of each relaxation."""

import itertools

import numpy as np
import pytest
import scipy.optimize

from bayescal.design import design_mse, design_mse_bound
from bayescal.design.exact_bound import cell_relaxation, exact_design_bound, orthant_cells
from bayescal.errors import InputError


def problem(seed: int, N: int = 9, k: int = 2, L: int = 5, m: int = 2):
    rng = np.random.default_rng(seed)
    lim = np.array([[-1.0, 1.0]] * m)
    q = np.concatenate([np.array(list(itertools.product(*lim))), rng.uniform(-1, 1, (N - 2**m, m))])
    # blocks that vary smoothly with q, larger towards the corners (as on a real actuator box)
    W = rng.normal(size=(k, L, m + 1))
    blocks = np.einsum("klm,nm->nkl", W, np.c_[np.ones(N), q]) * (1 + np.sum(q**2, axis=1))[:, None, None]
    C = rng.normal(size=(L, L))
    return blocks, C @ C.T / L, q, lim


def all_designs(blocks, Q, n):
    return np.array([design_mse(blocks, Q, S) for S in itertools.combinations_with_replacement(range(len(blocks)), n)])


@pytest.mark.parametrize("seed", range(6))
@pytest.mark.parametrize("n", [2, 3, 5])
def test_below_every_exact_design_and_above_the_relaxation(seed, n):
    blocks, Q, q, lim = problem(seed)
    exact = all_designs(blocks, Q, n)
    b = exact_design_bound(blocks, Q, n, orthant_cells(q, lim))
    relaxed = design_mse_bound(blocks, Q, n, rtol=1e-9, iters=2000, inner=2000)
    assert b.lower_mse <= exact.min() * (1 + 1e-9)
    assert b.lower_mse >= relaxed.lower_mse * (1 - 1e-9)
    assert sum(b.cell_counts) == n


@pytest.mark.parametrize("seed", range(6))
@pytest.mark.parametrize("n", [2, 4])
def test_one_cell_per_candidate_gives_the_exact_optimum(seed, n):
    blocks, Q, *_ = problem(seed, N=7)
    exact = all_designs(blocks, Q, n)
    b = exact_design_bound(blocks, Q, n, np.arange(len(blocks)))
    assert b.lower_mse == pytest.approx(exact.min(), rel=1e-6)


def test_tighter_than_the_relaxation_somewhere():
    # the point of the method: on some of these problems the relaxed bound is strictly below the exact
    # optimum and the cell bound closes part of that gap
    gains = []
    for seed in range(12):
        blocks, Q, q, lim = problem(seed)
        relaxed = design_mse_bound(blocks, Q, 3, rtol=1e-9, iters=2000, inner=2000).lower_mse
        exact = all_designs(blocks, Q, 3).min()
        b = exact_design_bound(blocks, Q, 3, orthant_cells(q, lim)).lower_mse
        if exact > relaxed * (1 + 1e-4):
            gains.append((b - relaxed) / (exact - relaxed))
    assert gains and max(gains) > 0.3


@pytest.mark.parametrize("seed", range(4))
def test_cell_relaxation_against_slsqp(seed):
    blocks, Q, q, lim = problem(seed, N=8)
    BB = np.einsum("nki,nkj->nij", blocks, blocks)
    groups = orthant_cells(q, lim)
    totals = np.array([2.0, 1.0, 0.0, 1.5])
    lower, f, w = cell_relaxation(BB, Q, groups, totals)
    L = Q.shape[0]

    def obj(v):
        return float(np.trace(np.linalg.solve(np.eye(L) + np.tensordot(v, BB, 1), Q)))

    cons = [{"type": "eq", "fun": (lambda v, g=g: v[groups == g].sum() - totals[g])} for g in range(4)]
    x0 = np.array([totals[g] / np.sum(groups == g) for g in groups])
    r = scipy.optimize.minimize(obj, x0, method="SLSQP", bounds=[(0, None)] * len(x0), constraints=cons,
                                options={"ftol": 1e-14, "maxiter": 1000})
    assert r.success
    assert lower <= r.fun * (1 + 1e-9)
    assert f == pytest.approx(r.fun, rel=1e-5)
    assert np.allclose(np.bincount(groups, w, 4), totals)


def test_orthant_cells_and_errors():
    lim = np.array([[0.0, 2.0], [10.0, 20.0], [-1.0, 1.0]])
    corners = np.array(list(itertools.product(*lim)))
    assert sorted(orthant_cells(corners, lim)) == list(range(8))
    with pytest.raises(InputError, match="q_limits"):
        orthant_cells(corners, lim[:2])
    blocks, Q, q, lim2 = problem(0)
    with pytest.raises(InputError, match="cells"):
        exact_design_bound(blocks, Q, 3, np.zeros(3, int))
    with pytest.raises(InputError, match="Q"):
        exact_design_bound(blocks, Q[:2, :2], 3, orthant_cells(q, lim2))
    lower, _, _ = cell_relaxation(np.einsum("nki,nkj->nij", blocks, blocks), Q, np.zeros(len(blocks), int),
                                  np.array([2.0, 1.0]))
    assert lower == np.inf  # a cell that must take a pose but has no candidate: no design has these counts


def test_counts_by_the_callers_labels_and_bad_arguments():
    blocks, Q, q, lim = problem(1)
    cells = 10 * orthant_cells(q, lim) + 3  # sparse labels: 3, 13, 23, 33
    b = exact_design_bound(blocks, Q, 3, cells)
    assert len(b.cell_counts) == 34 and sum(b.cell_counts) == 3
    assert all(c == 0 for i, c in enumerate(b.cell_counts) if i % 10 != 3)
    assert b.lower_mse == pytest.approx(exact_design_bound(blocks, Q, 3, orthant_cells(q, lim)).lower_mse, rel=1e-9)
    with pytest.raises(InputError, match="whole number"):
        exact_design_bound(blocks, Q, 2.5, cells)
    with pytest.raises(InputError, match="rtol"):
        exact_design_bound(blocks, Q, 2, cells, rtol=-1.0)
    # rtol = 0 runs to the iteration limits without failing: where the best pair's difference is rounding the
    # line search has no descent to find (brentq raised before)
    BB = np.einsum("nki,nkj->nij", blocks, blocks)
    lower, f, _ = cell_relaxation(BB, Q, np.zeros(len(blocks), int), np.array([2.0]), rtol=0.0, outer=20, inner=400)
    assert lower <= all_designs(blocks, Q, 2).min() * (1 + 1e-9) and f >= lower
