"""Planning heights and distances (plan --measure height|distance) on the example delta printer."""

from pathlib import Path

import numpy as np
import pytest

from bayescal.cli import main
from bayescal.constraints.model import ConstraintModel
from bayescal.design.relations import grid_points, plan_relations, relation_candidates
from bayescal.errors import RecordingError
from bayescal.io.constraints import read_constraints
from bayescal.machines.files import load_machine
from bayescal.constraints.simulate import simulate_distances

DELTA = Path(__file__).resolve().parents[2] / "examples" / "delta" / "machine.toml"


@pytest.fixture(scope="module")
def delta():
    return load_machine(DELTA)


def test_grid_points_lie_in_the_disc():
    p = grid_points(np.array([1.0, 2.0, 3.0]), 20.0, 10.0)
    # the 13 points of the spacing-10 lattice within radius 20 (|i|+|j| small enough)
    assert len(p) == 13
    assert np.all(np.hypot(p[:, 0] - 1, p[:, 1] - 2) <= 20 + 1e-9) and np.all(p[:, 2] == 3.0)


def test_candidates_are_at_their_points(delta):
    pts = grid_points(np.array([0.0, 0.0, 20.0]), 60.0, 30.0)
    h = relation_candidates(delta, "height", pts)
    np.testing.assert_allclose(delta.forward(h.qa).position, pts, atol=1e-8)
    d = relation_candidates(delta, "distance", pts, min_distance=40.0)
    assert d.n_rows == sum(np.linalg.norm(a - b) >= 40 for i, a in enumerate(pts) for b in pts[i + 1:])
    pred = ConstraintModel.from_recording(delta, d).predict(None).y[:, 0]
    np.testing.assert_allclose(pred, d.value, atol=1e-8)
    assert d.value.min() >= 40.0


def _fd_rows(machine, rec, sigma, h=1e-6):
    """Whitened, tolerance-scaled rows by central differences of the model's prediction (not its Jacobian)."""
    model = ConstraintModel.from_recording(machine, rec)
    tol = machine.tolerance
    cols = []
    for k in range(machine.n_params):
        e = np.zeros(machine.n_params)
        e[k] = h * tol[k]
        cols.append((model.predict(e).y[:, 0] - model.predict(-e).y[:, 0]) / (2 * h))
    return np.column_stack(cols) / sigma


def test_plan_adds_information_and_reports_it_exactly(delta):
    given = simulate_distances(delta, 6, seed=2, heights=4).recording
    plan = plan_relations(delta, 5, measure="distance", given=given, radius=60.0, sigma=0.05, min_distance=30.0)
    assert plan.recording.n_rows == 5 and np.all(plan.recording.sigma == 0.05)
    # information only adds: each posterior std shrinks or stays
    assert np.all(plan.std_given <= plan.std_prior + 1e-12) and np.all(plan.std_planned <= plan.std_given + 1e-12)
    assert np.any(plan.std_planned < 0.9 * plan.std_given)
    # the utility is log det(I + A^T A) of the given and planned rows, A from finite differences
    A = np.vstack([_fd_rows(delta, given, delta.noise.sigma_position), _fd_rows(delta, plan.recording, 0.05)])
    ld = np.linalg.slogdet(np.eye(delta.n_params) + A.T @ A)[1]
    assert abs(ld - plan.utility_planned) < 1e-4 * abs(ld)
    # distances never see the effector's offset: it stays undetermined
    assert {"tool.point.x", "tool.point.y", "tool.point.z"} <= set(plan.fixed_planned)


def test_first_pick_is_the_best_single_candidate(delta):
    pts = grid_points(np.array([0.0, 0.0, 20.0]), 60.0, 20.0)
    cands = relation_candidates(delta, "height", pts)
    plan = plan_relations(delta, 1, measure="height", centre=[0.0, 0.0, 20.0], radius=60.0, spacing=20.0, sigma=0.02)
    A = _fd_rows(delta, cands, 0.02)
    gains = np.log1p(np.sum(A**2, axis=1))  # log det(I + a a^T) = log(1 + |a|^2) from the prior alone
    best = int(np.argmax(gains))
    np.testing.assert_allclose(plan.recording.qa[0], cands.qa[best], atol=1e-9)


def test_cli_writes_a_recording_to_fill_in(delta, tmp_path, capsys):
    given = tmp_path / "given.csv"
    from bayescal.io.constraints import write_constraints

    write_constraints(given, simulate_distances(delta, 6, seed=3, heights=4).recording)
    out = tmp_path / "next.csv"
    code = main(["plan", "--machine", str(DELTA), "--measure", "height", "--given", str(given), "--n", "4",
                 "--centre", "0,0,10", "--radius", "60", "--sigma", "0.02", "--out", str(out), "--json", str(tmp_path / "p.json")])
    assert code == 0
    text = capsys.readouterr().out
    assert "what to measure" in text and "tower1.arm_length" in text
    lines = out.read_text().splitlines()
    assert lines[0].startswith("measure,a_q1,a_q2,a_q3,value,sigma_position,nominal,x_a,y_a,z_a") and len(lines) == 5
    with pytest.raises(RecordingError, match="value"):
        read_constraints(out)
    # entering the measured values makes it a recording
    filled = [lines[0]] + [",".join(c if k != 4 else "10.01" for k, c in enumerate(row.split(","))) for row in lines[1:]]
    out.write_text("\n".join(filled) + "\n")
    rec = read_constraints(out)
    assert rec.n_rows == 4 and np.all(rec.value == 10.01)
    with pytest.raises(SystemExit) as e:
        main(["plan", "--machine", str(DELTA), "--measure", "height", "--n", "2", "--centre", "0,0", "--out", str(out)])
    assert e.value.code == 2
    # a grid reaching outside the workspace is bad input, named
    assert main(["plan", "--machine", str(DELTA), "--measure", "height", "--n", "2", "--radius", "900", "--out", str(out)]) == 2
    assert "cannot be reached" in capsys.readouterr().err


def test_criterion_i_folds_the_given_information_into_the_bound(delta):
    """relaxed_relations whitens by M0 = C C^T: its design's E[MSE] is trace((M0 + A^T A)^-1 Q), checked directly."""
    from bayescal.design import design_mse
    from bayescal.design.relations import relaxed_relations

    rng = np.random.default_rng(0)
    P = 4
    A = rng.normal(size=(30, P))
    G = rng.normal(size=(50, 3, P))
    Q = np.einsum("eki,ekj->ij", G, G) / 50
    Ag = rng.normal(size=(3, P))
    M0 = np.eye(P) + Ag.T @ Ag
    idx = relaxed_relations(A, Q, 5, M0)
    direct = np.trace(np.linalg.inv(M0 + A[idx].T @ A[idx]) @ Q)
    Ci = np.linalg.inv(np.linalg.cholesky(M0))
    assert design_mse((A @ Ci.T)[:, None, :], Ci @ Q @ Ci.T, idx) == pytest.approx(direct, rel=1e-10)
    # and no single exchange of the result with any candidate lowers it
    for i in range(5):
        for j in range(30):
            alt = idx.copy()
            alt[i] = j
            assert np.trace(np.linalg.inv(M0 + A[alt].T @ A[alt]) @ Q) >= direct * (1 - 1e-9)
    plan = plan_relations(delta, 4, measure="height", criterion="I", radius=40.0)
    assert plan.recording.n_rows == 4 and plan.criterion == "I"


@pytest.mark.parametrize("kw, match", [({"sigma": 0.0}, r"sigma \(--sigma\): expected a one-sigma position noise"),
                                       ({"sigma": -1.0}, r"sigma \(--sigma\)"),
                                       ({"min_distance": -1.0}, r"min_distance \(--min-distance\): expected a length >= 0")])
def test_a_planned_noise_or_distance_that_is_no_length_is_refused(delta, kw, match):
    # --sigma 0, --sigma -1 and --min-distance -1 were planned without a word
    from bayescal.errors import InputError

    with pytest.raises(InputError, match=match):
        plan_relations(delta, 3, measure="distance", radius=40.0, **kw)
