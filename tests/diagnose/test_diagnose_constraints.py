"""diagnose on constraint recordings (distances, heights, ballbar): noise gives "none", a gross reading
is named by its CSV line, and lost motion simulated by the independent nut-and-screw physics of
tests/physics (not bayescal's backlash effect) is named backlash, with dead bands near the truth;
the machine --write-machine writes reproduces the diagnosis's final misfit."""

from pathlib import Path

import numpy as np
import pytest

from bayescal.constraints.model import ConstraintModel
from bayescal.diagnose import diagnose
from bayescal.diagnose.calibrated import calibrated_machine
from bayescal.io.constraints import ConstraintRecording
from bayescal.machines.files import load_machine, machine_from_text
from bayescal.simulate import draw_errors, draw_poses
from bayescal.constraints.simulate import simulate_distances
from tests.physics.nut_screw import LostMotion

ROOT = Path(__file__).resolve().parents[2]
DELTA = ROOT / "examples" / "delta" / "machine.toml"
PRS3 = ROOT / "examples" / "prs3" / "machine.toml"


def _session(m, n_dist, n_height, seed, *, transform=None):
    """Distances then heights, one pose after the other in time order (a0 b0 a1 b1 ... h0 h1 ...).

    ``transform`` (a PoseTransform) turns the commanded actuator positions, in that time order, into
    the true ones; the values are measured on the true machine with the machine file's noise.
    """
    rng = np.random.default_rng(seed)
    theta = draw_errors(m, rng)
    q = draw_poses(m, 2 * n_dist + n_height, rng, theta)  # time order
    q_true = q if transform is None else transform.transform(q, np.broadcast_to(theta, (len(q), m.n_params)), {}, np.arange(len(q)))[0]
    x = m.forward(q_true, theta).position
    a, b = np.arange(0, 2 * n_dist, 2), np.arange(1, 2 * n_dist, 2)
    h = np.arange(2 * n_dist, 2 * n_dist + n_height)
    value = np.concatenate([np.linalg.norm(x[a] - x[b], axis=1), x[h, 2]])
    value = value + m.noise.sigma_position * rng.normal(size=value.size)
    qb = np.full((n_dist + n_height, m.n_actuators), np.nan)
    qb[:n_dist] = q[b]
    return ConstraintRecording(measure=("distance",) * n_dist + ("height",) * n_height,
                               qa=np.vstack([q[a], q[h]]), qb=qb, value=value), theta


@pytest.mark.parametrize("path", [DELTA, PRS3], ids=["delta", "prs3"])
def test_noise_alone_is_none(path):
    m = load_machine(path)
    rec = simulate_distances(m, 30, seed=5, heights=15).recording
    d = diagnose(m, rec, seed=1, effects=["backlash"])
    assert d.verdict == "none", d.report()
    assert d.p_geometric > 1e-3 and d.dof == 1 and d.n_poses == 45
    assert d.outliers is not None and d.outliers.outliers() == []
    assert abs(d.rms_noise - m.noise.sigma_position) < 1e-12  # a row measures one length


def test_a_gross_reading_is_named_by_its_line():
    m = load_machine(DELTA)
    sim = simulate_distances(m, 30, seed=6, heights=15)
    rec = sim.recording
    value = rec.value.copy()
    value[17] += 40 * m.noise.sigma_position
    bad = ConstraintRecording(measure=rec.measure, qa=rec.qa, qb=rec.qb, value=value, path="bad.csv")
    d = diagnose(m, bad, seed=1, effects=["backlash"])
    assert [o["line"] for o in d.outliers.outliers()] == [19]  # header is line 1, row 17 (0-based) line 19
    assert d.verdict == "none", d.report()
    assert "line 19" in d.report()


def test_lost_motion_of_an_independent_nut_screw_is_named_backlash():
    m = load_machine(PRS3)
    band = np.array([60.0, 45.0, 75.0])  # um
    rec, _ = _session(m, 70, 20, seed=8, transform=LostMotion(band, np.random.default_rng(9)))
    d = diagnose(m, rec, seed=1)
    assert d.verdict == "backlash" and d.selected[0] == "backlash", d.report()
    got = {p.name: p for p in next(e for e in d.effects if e.name == "backlash").parameters}
    for i, b in enumerate(band):
        p = got[f"backlash.q{i + 1}"]
        assert abs(p.value - b) < max(4 * p.std, 0.3 * b), (p, b)
    # the direction channel the location tests see is each row's first pose's approach from the
    # previous row's last pose (a distance's pose b), not from the previous row's pose a
    s = next(c for c in d.location.channels if c.channel == "direction_q1").values
    q_time = np.empty((2 * 70 + 20, 3))
    q_time[0:140:2], q_time[1:140:2], q_time[140:] = rec.qa[:70], rec.qb[:70], rec.qa[70:]
    step = np.sign(np.diff(q_time[:, 0]))
    np.testing.assert_array_equal(s[1:70], step[1:139:2])
    np.testing.assert_array_equal(s[70:], step[139:])
    # --write-machine: the calibrated geometry with the [effect.backlash] table, which the constraint
    # model applies to every solved pose: its misfit on the recording is the diagnosis's final one
    cal = machine_from_text(calibrated_machine(m, d).text, "<calibrated>")
    assert [e.name for e in cal.effects] == ["backlash"] and cal.n_params == m.n_params
    model = ConstraintModel.from_recording(cal, rec)
    r = model.residual(model.predict(None)) / model.row_sigma
    assert float(np.sum(r**2)) == pytest.approx(d.chi2_final, rel=1e-6)
    assert d.chi2_final < 0.2 * d.chi2_geometric


def test_clean_session_of_the_same_kind_is_none():
    # the control of the test above: the same session without lost motion
    m = load_machine(PRS3)
    rec, _ = _session(m, 70, 20, seed=8)
    d = diagnose(m, rec, seed=1, effects=["backlash"])
    assert d.verdict == "none", d.report()


def test_ballbar_session_with_lost_motion_reports_the_written_geometry():
    # a ballbar model carries its pivot's 3 coordinates after the machine's parameters: the written
    # geometry's uncertainty is of the machine's parameters alone, and the trade-off's effect components
    # are the effect's (before: machine.forward with the pivots' theta raised InputError)
    from bayescal.constraints.simulate import circle_points, solve_q_for_points

    m = load_machine(PRS3)
    rng = np.random.default_rng(3)
    theta = draw_errors(m, rng)
    pivot = m.forward(m.home_q()[None]).position[0]
    pts = np.vstack([c for pl in ("xy", "xz", "yz") for c in (circle_points(pivot, 15.0, pl, 24),) for c in (c, c[::-1])])
    q = solve_q_for_points(m, pts)
    band = np.array([60.0, 45.0, 75.0])
    q_true = LostMotion(band, np.random.default_rng(9)).transform(q, np.broadcast_to(theta, (len(q), m.n_params)), {},
                                                                   np.arange(len(q)))[0]
    value = np.linalg.norm(m.forward(q_true, theta).position - pivot, axis=1) + m.noise.sigma_position * rng.normal(size=len(q))
    rec = ConstraintRecording(measure=("ballbar",) * len(q), qa=q, qb=np.full_like(q, np.nan), value=value, pivot=("p",) * len(q))
    d = diagnose(m, rec, seed=1, effects=["backlash"])
    assert d.verdict == "backlash", d.report()
    assert d.theta_final.shape == (m.n_params,)
    c = d.confound
    assert c is not None and np.isfinite(c.tool_std_um) and c.tool_std_um > 0
    assert {name for name, _, _ in c.effect} <= {"backlash.q1", "backlash.q2", "backlash.q3"}
    assert all(u == "um" for _, _, u in c.effect)
    assert {name for name, _, _ in c.geometry} <= set(m.layout.names)
