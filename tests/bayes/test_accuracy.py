"""Tool-point std at given poses: against central finite differences of the forward kinematics and a loop over draws.

The helpers here compute the std directly, without :mod:`bayescal.bayes.accuracy`
(the Jacobian by finite differences of ``machine.forward``, the 3x3 covariance
``G C G^T`` formed in full, the draws pushed one by one); the grid tests use
them too.
"""

from __future__ import annotations

import numpy as np
import pytest

from bayescal.bayes.accuracy import tool_point_draws, tool_point_std_at
from bayescal.errors import InputError


def fd_tool_point_std(machine, q, theta, free, cov, rel_step=1e-3):
    """``sqrt(diag(G C G^T))`` per pose, ``G`` by central differences of ``forward(q, theta).position`` (mm)."""
    theta = np.asarray(theta, dtype=float)
    idx = np.flatnonzero(free)
    G = np.empty((q.shape[0], 3, idx.size))
    for j, p in enumerate(idx):
        h = rel_step * machine.tolerance[p]
        up, down = theta.copy(), theta.copy()
        up[p] += h
        down[p] -= h
        G[:, :, j] = (machine.forward(q, up).position - machine.forward(q, down).position) / (2 * h)
    full = np.stack([g @ cov @ g.T for g in G])  # (n, 3, 3), off-diagonals included
    return np.sqrt(np.diagonal(full, axis1=1, axis2=2))


def loop_draw_std(machine, q, theta, free, draws):
    """Sample std (ddof 1) of the tool point over draws of ``theta[free]``, one forward call per draw (mm)."""
    idx = np.flatnonzero(free)
    pos = []
    for d in draws:
        th = np.array(theta, dtype=float)
        th[idx] = d
        pos.append(machine.forward(q, th).position)
    return np.std(np.array(pos), axis=0, ddof=1)


def correlated_covariance(k, scale, rng):
    """A random SPD covariance with strong correlations (so the off-diagonal terms of G C G^T matter)."""
    A = rng.normal(size=(k, k))
    C = A @ A.T + 0.1 * np.eye(k)
    d = np.sqrt(np.diag(C))
    return (C / np.outer(d, d)) * np.outer(scale, scale)


@pytest.fixture(scope="module")
def case(prs3):
    rng = np.random.default_rng(41)
    theta = rng.normal(0.0, 0.5, prs3.n_params) * prs3.tolerance
    free = np.zeros(prs3.n_params, bool)
    free[rng.choice(prs3.n_params, 12, replace=False)] = True
    C = correlated_covariance(12, 0.3 * prs3.tolerance[free], rng)
    q = prs3.sample_q(7, rng)
    return theta, free, C, q, rng


def test_linearised_std_matches_finite_differences(prs3, case):
    theta, free, C, q, _ = case
    std, source = tool_point_std_at(prs3, q, theta, free, covariance=C)
    assert source == "linearised G C G^T" and std.shape == (7, 3)
    np.testing.assert_allclose(std, fd_tool_point_std(prs3, q, theta, free, C), rtol=1e-5)


def test_sample_std_matches_a_loop_over_draws(prs3, case):
    theta, free, C, q, rng = case
    draws = rng.multivariate_normal(theta[free], C, size=30)
    std, source = tool_point_std_at(prs3, q, theta, free, samples=draws)
    assert source == "sample std over 30 posterior draws"
    np.testing.assert_allclose(std, loop_draw_std(prs3, q, theta, free, draws), rtol=1e-8)
    # the draws win over a covariance given as well
    np.testing.assert_array_equal(tool_point_std_at(prs3, q, theta, free, samples=draws, covariance=C)[0], std)
    pos = tool_point_draws(prs3, q, theta, np.flatnonzero(free), draws)
    assert pos.shape == (30, 7, 3)
    th = theta.copy()
    th[free] = draws[4]
    np.testing.assert_allclose(pos[4], prs3.forward(q, th).position, atol=1e-9)


def test_wrong_shapes_and_no_uncertainty_are_input_errors(prs3, case):
    theta, free, C, q, _ = case
    with pytest.raises(InputError, match=r"covariance: expected shape \(12, 12\), got \(3, 3\)"):
        tool_point_std_at(prs3, q, theta, free, covariance=np.eye(3))
    with pytest.raises(InputError, match=r"samples: expected shape \(n_draws, 12\), got \(12,\)"):
        tool_point_std_at(prs3, q, theta, free, samples=np.zeros(12))
    with pytest.raises(InputError, match="my_grid: give a covariance or posterior samples"):
        tool_point_std_at(prs3, q, theta, free, caller="my_grid")
    # free defaults to all parameters
    with pytest.raises(InputError, match=rf"expected shape \({prs3.n_params}, {prs3.n_params}\)"):
        tool_point_std_at(prs3, q, theta, covariance=C)


def assert_grid_std_is_direct(machine, make_grid, free, seed, caller):
    """A grid's node std against the direct computations here, with a correlated C on ``free``.

    ``make_grid(theta, **kw)`` builds the grid (``q``: node actuator vectors, ``std``: per node and axis, mm)
    from ``covariance``/``samples``/``free``; ``caller`` is the function its message names.
    """
    rng = np.random.default_rng(seed)
    theta = rng.normal(0.0, 0.5, machine.n_params) * machine.tolerance
    C = correlated_covariance(int(free.sum()), 0.2 * machine.tolerance[free], rng)
    lin = make_grid(theta, covariance=C, free=free)
    np.testing.assert_allclose(lin.std.reshape(-1, 3), fd_tool_point_std(machine, lin.q, theta, free, C), rtol=1e-5)
    draws = rng.multivariate_normal(theta[free], C, size=20)
    smp = make_grid(theta, samples=draws, free=free)
    np.testing.assert_allclose(smp.std.reshape(-1, 3), loop_draw_std(machine, smp.q, theta, free, draws), rtol=1e-8)
    assert smp.source == "sample std over 20 posterior draws" and lin.source == "linearised G C G^T"
    with pytest.raises(InputError, match=f"{caller}: give a covariance or posterior samples"):
        make_grid(theta, free=free)
