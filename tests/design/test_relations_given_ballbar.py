"""Planning from a given recording with ballbar rows: the pivots are nuisance parameters."""

import numpy as np

from bayescal.constraints.model import ConstraintModel
from bayescal.design.relations import _given_rows, plan_relations
from bayescal.io.constraints import read_constraints
from bayescal.machines.files import load_machine
from tests.conftest import PRS3_FILE


def _given(tmp_path):
    machine = load_machine(PRS3_FILE)
    q = machine.q_limits.mean(axis=1)
    rows = ["measure,a_q1,a_q2,a_q3,b_q1,b_q2,b_q3,value,pivot"]
    rng = np.random.default_rng(3)
    for i in range(12):
        qa = q + rng.uniform(-30, 30, 3)
        kind = ("ballbar", "height", "ballbar", "distance")[i % 4]
        qb = q + rng.uniform(-30, 30, 3) if kind == "distance" else None
        b = ",".join(f"{v:.4f}" for v in qb) if qb is not None else ",,"
        value = 25.0 if kind != "height" else 30.0
        rows.append(f"{kind},{qa[0]:.4f},{qa[1]:.4f},{qa[2]:.4f},{b},{value},{'P' + str((i // 4) % 2) if kind == 'ballbar' else ''}")
    (tmp_path / "g.csv").write_text("\n".join(rows) + "\n")
    return machine, read_constraints(tmp_path / "g.csv")


def test_given_ballbar_rows_marginalise_the_pivots(tmp_path):
    machine, given = _given(tmp_path)
    R = _given_rows(machine, given)
    P = machine.n_params
    # independent: the full posterior covariance over machine + pivots, its machine block
    model = ConstraintModel.from_recording(machine, given)
    J = model.jacobian(None, model.predict(None)).reshape(given.n_rows, -1)
    A = J * model.machine.tolerance[None, :] / model.row_sigma[:, 0][:, None]
    assert A.shape[1] == P + 6  # two pivots
    cov_full = np.linalg.inv(np.eye(A.shape[1]) + A.T @ A)[:P, :P]
    np.testing.assert_allclose(np.linalg.inv(np.eye(P) + R.T @ R), cov_full, rtol=1e-8, atol=1e-12)
    plan = plan_relations(machine, 3, measure="height", given=given, radius=15.0)
    assert np.all(plan.std_given <= plan.std_prior * (1 + 1e-12))
    assert np.all(plan.std_planned <= plan.std_given * (1 + 1e-12))
