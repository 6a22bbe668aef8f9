"""Std of the redundant module's BIC grid nodes, checked on simulated machines."""

import numpy as np
import pytest

from bayescal.errors import InputError
from bayescal.machines.files import load_machine
from bayescal.redundant import PoseModel, TrueModule
from bayescal.redundant.grid_std import predicted_grid
from bayescal.redundant.models import ZeroPosition
from bayescal.redundant.steps import INSTRUMENTS, design_rm1, identify_step, measure_relative
from tests.conftest import ROOT


@pytest.fixture(scope="module")
def raspm():
    return load_machine(ROOT / "examples" / "raspm" / "machine.toml")


def _machine_run(m, rng):
    """A simulated machine from the tolerance prior (model-exact: equal AJ stiffnesses, no bow), RM1/SI1."""
    inst = INSTRUMENTS["dial_gauge"]
    truth = TrueModule(m, rng.normal(size=m.n_params) * m.tolerance, stiffness=np.full(4, 3e4))
    x0 = m._home_x()
    ctrl = PoseModel(m, zero=ZeroPosition(x0=x0, q0=truth.command_for(x0[None])[0]))
    th0 = ctrl.complete(np.zeros(m.n_params))
    xf, xt, _ = design_rm1(m.pose_range, 7, 5)
    rec = measure_relative(truth, ctrl, th0, xf, xt, ("dx", "dz"), inst, rng)
    step = identify_step(ctrl, [(rec, np.full(2, inst.sigma))], th0, step="SI1")
    return truth, ctrl, th0, step


def _true_node_error(truth, ctrl, theta_cmd, grid):
    m = truth.machine
    X, Z = np.meshgrid(grid.xs, grid.zs)
    xn = np.column_stack([X.ravel(), Z.ravel(), np.zeros(X.size)])
    x0 = ctrl.zero.x0
    y, _, _ = truth.tool(m.inverse_planar(np.vstack([x0[None], xn]), theta_cmd))
    return (y[1:] - y[0]) - (xn[:, :2] - x0[:2])


def test_standardised_node_errors_are_standard_normal(raspm):
    rng = np.random.default_rng(1)
    z, z_small = [], []
    for _ in range(12):
        truth, ctrl, th0, step = _machine_run(raspm, rng)
        # the nominal controller compensated by the grid the SI1 model predicts
        g = predicted_grid(ctrl, step.theta_after, step.covariance, theta_cmd=th0)
        e_true = _true_node_error(truth, ctrl, th0, g)
        sd = g.std.reshape(-1, 2)
        ok = sd > 1e-9  # the zero pose itself: exactly known by construction
        assert ok.sum() == sd.size - 2
        d = (e_true - g.error.reshape(-1, 2))[ok]
        z.append(d / sd[ok])
        z_small.append(d / (0.5 * sd[ok]))
        assert np.abs(g.error).max() > 10 * sd.max()  # the grid does predict something
    z = np.concatenate(z)
    assert abs(z.mean()) < 0.2 and 0.8 < z.std() < 1.2, (z.mean(), z.std())
    # an std half as large would be caught
    assert np.concatenate(z_small).std() > 1.5


def test_grid_with_the_identified_controller_predicts_zero(raspm, tmp_path):
    rng = np.random.default_rng(2)
    truth, ctrl, th0, step = _machine_run(raspm, rng)
    g = predicted_grid(ctrl, step.theta_after, step.covariance)
    assert np.abs(g.error).max() < 1e-8
    assert np.all(np.isfinite(g.std)) and g.std.max() > 0
    # the same std as with the nominal controller, to first order
    g0 = predicted_grid(ctrl, step.theta_after, step.covariance, theta_cmd=th0)
    assert np.allclose(g.std, g0.std, rtol=0.05, atol=1e-6)
    with pytest.raises(InputError, match="covariance"):
        predicted_grid(ctrl, step.theta_after, np.eye(3))
    from bayescal.compensation import read_grid, write_grid
    from bayescal.plots.redundant import plot_grid_std

    back = read_grid(write_grid(tmp_path / "g.csv", g0))
    assert np.allclose(back.std, g0.std, rtol=1e-15) and np.allclose(back.error, g0.error, rtol=1e-15)
    assert plot_grid_std(g0, tmp_path / "std.png").stat().st_size > 1000


def test_step_covariance_is_noise_in_kept_and_prior_elsewhere(raspm):
    rng = np.random.default_rng(3)
    _, ctrl, _, step = _machine_run(raspm, rng)
    C = step.covariance
    assert np.allclose(C, C.T) and np.linalg.eigvalsh(C).min() > -1e-12 * np.abs(C).max()
    off = ctrl.offsets
    assert np.all(C[off] == 0) and np.all(C[:, off] == 0)
    tol2 = raspm.tolerance[ctrl.free_index] ** 2
    var = np.diag(C)[ctrl.free_index]
    assert np.all(var <= tol2 * (1 + 1e-9))  # a step never adds spread
    assert np.any(var < 0.2 * tol2)  # and learns something
