"""The solved-pose side of the constraint model (what effects act on): pose order, subsets, the rows'
derivative with respect to the poses' actuator positions against central differences, and effect
parameters through a distance's two poses."""

from pathlib import Path

import numpy as np
import pytest

from bayescal.constraints.model import ConstraintModel
from bayescal.effects import get_effect
from bayescal.effects.model import _slices, effect_jacobian, effect_residual
from bayescal.io.constraints import ConstraintRecording
from bayescal.machines.files import load_machine

ROOT = Path(__file__).resolve().parents[2]
DELTA = ROOT / "examples" / "delta" / "machine.toml"
PRS3 = ROOT / "examples" / "prs3" / "machine.toml"


@pytest.fixture(scope="module", params=[DELTA, PRS3], ids=["delta", "prs3"])
def model(request):
    """Rows: distance, height, distance, ballbar, height, distance, ballbar (measured values arbitrary)."""
    m = load_machine(request.param)
    rng = np.random.default_rng(4)
    q = m.sample_q(10, rng)
    measure = ("distance", "height", "distance", "ballbar", "height", "distance", "ballbar")
    qa = q[:7]
    qb = np.full_like(qa, np.nan)
    qb[[0, 2, 5]] = q[7:10]
    x = m.forward(q).position
    rec = ConstraintRecording(measure=measure, qa=qa, qb=qb, value=np.full(7, 5.0),
                              pivot=("", "", "", "p", "", "", "p"), aux={"temp_C": np.arange(7.0)})
    cm = ConstraintModel.from_recording(m, rec)
    assert np.allclose(cm.pivot_start[0], 0.5 * (x[3] + x[6]), atol=50)  # sanity of the fixture
    return cm


def test_solved_poses_are_rows_a_then_distance_b_in_time_order(model):
    n = model.n_poses
    assert model.pose_q.shape == (n + 3, model.base.n_actuators)
    np.testing.assert_array_equal(model.pose_q[:n], model.q)
    np.testing.assert_array_equal(model.pose_q[n:], model.qb[[0, 2, 5]])
    np.testing.assert_array_equal(model.pose_row, [0, 1, 2, 3, 4, 5, 6, 0, 2, 5])
    # time: a0 b0 a1 a2 b2 a3 a4 a5 b5 a6
    np.testing.assert_array_equal(model.pose_order, [0, 2, 3, 5, 6, 7, 9, 1, 4, 8])
    assert model.predict(None).poses.position.shape[0] == n + 3


@pytest.mark.parametrize("rows", [[5, 1, 2], [0, 3, 6], np.array([True, False, True, True, False, True, False])])
def test_poses_of_matches_the_subset(model, rows):
    sub = model.subset(rows)
    np.testing.assert_array_equal(sub.pose_q, model.pose_q[model.poses_of(rows)])


def test_with_pose_q_moves_both_poses_of_a_distance(model):
    dq = np.zeros_like(model.pose_q)
    dq[7] = 1.0  # pose b of row 0
    moved = model.with_pose_q(model.pose_q + dq)
    np.testing.assert_array_equal(moved.qa, model.qa)
    np.testing.assert_array_equal(moved.qb[0], model.qb[0] + 1.0)
    np.testing.assert_array_equal(moved.pivot_start, model.pivot_start)
    y0, y1 = model.predict(None).y, moved.predict(None).y
    assert abs(y1[0, 0] - y0[0, 0]) > 1e-3 and np.allclose(np.delete(y1, 0), np.delete(y0, 0))


def test_rows_jacobian_of_the_tool_jacobian_is_the_model_jacobian(model):
    theta = 0.3 * model.machine.tolerance * np.random.default_rng(1).normal(size=model.n_params)
    pred = model.predict(theta)
    Jt = model.machine.tool_jacobian(model.pose_q, theta, pred.poses)
    np.testing.assert_allclose(model.rows_jacobian(Jt, pred)[:, :, : model.base.n_params],
                               model.jacobian(theta, pred)[:, :, : model.base.n_params], rtol=1e-12, atol=1e-12)


def test_rows_derivative_in_actuator_positions_central_differences(model):
    # d rows / d q of every solved pose, against moving each pose's actuators by hand
    theta = np.zeros(model.n_params)
    pred = model.predict(theta)
    machine, th, poses = model.effect_inputs(theta, pred)
    Ja = machine.actuator_jacobian(model.pose_q, th, poses)
    h = 1e-5
    for p in range(model.pose_q.shape[0]):
        E = np.zeros((model.pose_q.shape[0], 3, 1))
        for k in range(model.pose_q.shape[1]):
            dq = np.zeros_like(model.pose_q)
            dq[p, k] = h
            fd = (model.with_pose_q(model.pose_q + dq).predict(theta).y - model.with_pose_q(model.pose_q - dq).predict(theta).y) / (2 * h)
            E[:] = 0.0
            E[p] = Ja[p, :3, k : k + 1]
            an = model.rows_jacobian(np.concatenate([E, np.zeros_like(E)], axis=1), pred)[:, :, 0]
            np.testing.assert_allclose(an, fd, atol=1e-7, rtol=1e-6)


def test_effect_parameters_act_on_both_poses_of_a_distance(model):
    # thermal expansion driven by the rows' temp_C: d rows / d eta against central differences of the residual
    eff = get_effect("thermal_expansion")
    theta = np.zeros(model.n_params)
    pred = model.predict(theta)
    m, th, poses = model.effect_inputs(theta, pred)
    aux = {k: v[model.pose_row] for k, v in model.aux.items()}
    f = eff.features(m, model.pose_q, th, aux, model.pose_order, poses)
    effects = [(eff, f)]
    slices = _slices(effects, model)
    eta = np.array([p.prior_mean for p in eff.params(m, f)]) + 5.0
    sub, pred = moved(model, effects, slices, theta, eta)
    J = effect_jacobian(sub, theta, pred, effects, slices, eta)[0]
    h = 1e-3
    for k in range(eta.size):
        d = np.zeros_like(eta)
        d[k] = h
        # residual = y - h: its derivative is minus the rows'
        fd = -(effect_residual(model, effects, theta, eta + d) - effect_residual(model, effects, theta, eta - d)) / (2 * h)
        np.testing.assert_allclose(J[:, :, k], fd, atol=1e-9, rtol=1e-5)


def moved(model, effects, slices, theta, eta):
    from bayescal.effects.model import _dq

    sub = model.with_pose_q(model.pose_q + _dq(effects, slices, eta, model.pose_q.shape))
    return sub, sub.predict(theta)


def test_region_is_the_measured_tool_point(model):
    pred = model.predict(None)
    reg = model.region(pred)
    x = pred.poses.position
    np.testing.assert_allclose(reg[1], x[1])
    np.testing.assert_allclose(reg[0], 0.5 * (x[0] + x[7]))
