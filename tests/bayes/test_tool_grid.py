"""Tool-space grids: nominal inverse kinematics, node errors, and their std two ways."""

from __future__ import annotations

import numpy as np

from bayescal.bayes.tool_grid import solve_tool_points, tool_grid
from bayescal.machines.files import load_machine
from tests.conftest import ROOT


def test_inverse_kinematics_reaches_forward_points(prs3):
    q0 = prs3.sample_q(15, np.random.default_rng(3))
    target = prs3.forward(q0).position
    q, ok = solve_tool_points(prs3, target)
    assert ok.all()
    np.testing.assert_allclose(prs3.forward(q).position, target, atol=1e-6)
    # 3 actuators, 3 coordinates: the solution is the actuator vector that made the points
    np.testing.assert_allclose(q, q0, atol=1e-5)


def test_unreachable_point_is_reported_not_solved(prs3):
    far = prs3.forward(prs3.home_q()[None]).position + np.array([[500.0, 0.0, 0.0]])
    _, ok = solve_tool_points(prs3, far)
    assert not ok.any()


def test_node_error_and_std_linearised_vs_sampled(prs3):
    rng = np.random.default_rng(7)
    theta = rng.normal(0.0, 1.0, prs3.n_params) * prs3.tolerance
    C = np.diag((0.2 * prs3.tolerance) ** 2)
    lin = tool_grid(prs3, theta, covariance=C, n=2)
    draws = rng.multivariate_normal(theta, C, size=800)
    smp = tool_grid(prs3, theta, samples=draws, n=2)
    np.testing.assert_array_equal(lin.q, smp.q)
    # the sample std of the exact forward kinematics agrees with the first-order propagation
    np.testing.assert_allclose(smp.std, lin.std, rtol=0.12)
    # node error: what the machine with errors does at the nominally commanded q
    pts = lin.nodes
    actual = prs3.forward(lin.q, theta).position
    np.testing.assert_allclose(lin.error.reshape(-1, 3), actual - pts, atol=1e-6)


def test_planar_module_gets_a_bic_grid():
    m = load_machine(ROOT / "examples" / "raspm" / "machine.toml")
    g = tool_grid(m, np.zeros(m.n_params), covariance=np.diag(m.tolerance**2), n=3,
                  ranges={"x": (-100.0, 100.0), "z": (-400.0, -300.0)})
    assert g.planar and g.shape == (3, 1, 3)
    np.testing.assert_allclose(g.error, 0.0, atol=1e-7)  # the nominal machine has no error
    assert g.to_nc_csv().splitlines()[0] == "i,j,x,z,ex,ez,std_ex,std_ez"


def test_node_std_against_finite_differences_and_a_loop_over_draws(prs3):
    # as for the actuator grid, at the commanded actuator positions of every node (ToolGrid.q)
    from tests.bayes.test_accuracy import assert_grid_std_is_direct

    free = np.arange(prs3.n_params) % 3 == 1
    assert_grid_std_is_direct(prs3, lambda th, **kw: tool_grid(prs3, th, n=2, **kw), free, 6, "tool_grid")
