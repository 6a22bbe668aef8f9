"""Constraint measurement model: Jacobian against central differences, noise-free identification of
what distances and heights can see, on the linear delta and the 3-PRS, and ballbar pivots."""

from pathlib import Path

import numpy as np
import pytest

from bayescal.constraints.model import ConstraintModel
from bayescal.identify import identify
from bayescal.identify.gauss_newton import whitened_system
from bayescal.io.constraints import ConstraintRecording
from bayescal.machines.files import load_machine
from bayescal.constraints.simulate import circle_points, simulate_ballbar, simulate_distances, solve_q_for_points

ROOT = Path(__file__).resolve().parents[2]
DELTA = ROOT / "examples" / "delta" / "machine.toml"
PRS3 = ROOT / "examples" / "prs3" / "machine.toml"


@pytest.fixture(scope="module", params=[DELTA, PRS3], ids=["delta", "prs3"])
def machine(request):
    return load_machine(request.param)


def _mixed_model(m, seed=1):
    """Distances, heights and ballbar readings with two pivots, on the nominal machine."""
    rng = np.random.default_rng(seed)
    q = m.sample_q(12, rng)
    x = m.forward(q).position
    c1, c2 = x[8] + [3.0, -2.0, 1.0], x[9] + [-1.0, 2.0, 4.0]
    rec = ConstraintRecording(
        measure=("distance",) * 4 + ("height",) * 3 + ("ballbar",) * 5,
        qa=np.vstack([q[:4], q[4:7], q[7:12]]),
        qb=np.vstack([q[[5, 6, 7, 8]], np.full((8, 3), np.nan)]),
        value=np.ones(12), pivot=("",) * 7 + ("a", "b", "a", "b", "a"),
    )
    return ConstraintModel.from_recording(m, rec), (c1, c2)


def test_jacobian_central_differences_every_parameter(machine):
    model, _ = _mixed_model(machine)
    rng = np.random.default_rng(2)
    tol = model.machine.tolerance
    theta = rng.normal(size=model.n_params) * tol
    pred = model.predict(theta)
    assert pred.success.all() and pred.y.shape == (12, 1)
    J = model.jacobian(theta, pred)
    assert J.shape == (12, 1, machine.n_params + 6)
    for k, name in enumerate(model.machine.layout.names):
        e = np.zeros(model.n_params)
        e[k] = 1e-3 * tol[k]
        fd = (model.predict(theta + e).y - model.predict(theta - e).y)[:, 0] / (2 * e[k])
        np.testing.assert_allclose(J[:, 0, k], fd, rtol=1e-5, atol=1e-7 * np.abs(J).max(), err_msg=name)


def test_stacked_parameter_sets_match_single_calls(machine):
    model, _ = _mixed_model(machine)
    rng = np.random.default_rng(3)
    thetas = rng.normal(size=(2, model.n_params)) * model.machine.tolerance
    stacked = np.repeat(thetas, model.n_poses, axis=0)
    pred = model.predict(stacked)
    J = model.jacobian(stacked, pred)
    for j in range(2):
        one = model.predict(thetas[j])
        sl = slice(j * model.n_poses, (j + 1) * model.n_poses)
        np.testing.assert_allclose(pred.y[sl], one.y, atol=1e-10)
        np.testing.assert_allclose(J[sl], model.jacobian(thetas[j], one), atol=1e-9)


def test_heights_are_z_and_distances_are_norms(machine):
    model, _ = _mixed_model(machine)
    pred = model.predict(None)
    x = machine.forward(model.qa).position
    xb = machine.forward(model.qb[:4]).position
    np.testing.assert_allclose(pred.y[:4, 0], np.linalg.norm(x[:4] - xb, axis=1), atol=1e-12)
    np.testing.assert_allclose(pred.y[4:7, 0], x[4:7, 2], atol=1e-12)


def test_distances_identify_what_they_see_noise_free(machine):
    sim = simulate_distances(machine, 60, seed=2, sigma=0.0)
    model = ConstraintModel.from_recording(machine, sim.recording)
    res = identify(model, method="ls")
    assert res.success and res.rms_after["position"] < 1e-9
    # the identified combinations predict any other distance of the true machine
    fresh = simulate_distances(machine, 40, seed=9, sigma=0.0, theta=sim.theta_true)
    pred = ConstraintModel.from_recording(machine, fresh.recording).predict(res.theta).y[:, 0]
    assert np.abs(pred - fresh.recording.value).max() < 1e-9
    # distances do not see where the machine stands: at least the 6 rigid motions are undetermined
    assert machine.n_params - res.free.sum() >= 6
    if machine.kind == "linear-delta":
        # a translating effector: a distance does not see the tool offset at all
        for c in "xyz":
            assert any(s.startswith(f"tool.point.{c} does not affect") for s in res.unidentifiable)


def test_heights_do_not_see_horizontal_translation():
    m = load_machine(DELTA)
    sim = simulate_distances(m, 20, seed=4, sigma=0.0, heights=40)
    model = ConstraintModel.from_recording(m, sim.recording)
    res = identify(model, method="ls")
    assert res.success and res.rms_after["position"] < 1e-9
    assert {"tool.point.x", "tool.point.y"} <= set(res.fixed)
    # 3 rigid motions the heights cannot see (x, y, rotation about z) and two tool offsets
    assert m.n_params - res.free.sum() == 6
    fresh = simulate_distances(m, 10, seed=11, sigma=0.0, heights=20, theta=sim.theta_true)
    pred = ConstraintModel.from_recording(m, fresh.recording).predict(res.theta).y[:, 0]
    assert np.abs(pred - fresh.recording.value).max() < 1e-9


def test_ballbar_recovers_the_pivot(machine):
    pivot = machine.forward(machine.home_q()[None]).position[0] + [0.7, -0.4, 0.3]
    sim = simulate_ballbar(machine, 5.0, n_points=12, pivot=pivot, planes=("xy", "xz"), sigma=0.0, theta=np.zeros(machine.n_params))
    model = ConstraintModel.from_recording(machine, sim.recording)
    P = machine.n_params
    res = identify(model, method="ls", free=list(model.machine.layout.names[P:]))
    assert res.success
    np.testing.assert_allclose(model.pivot_positions(res.theta)["1"], pivot, atol=1e-9)


def test_ballbar_circle_is_commanded_by_the_nominal_machine(machine):
    centre = machine.forward(machine.home_q()[None]).position[0]
    pts = circle_points(centre, 4.0, "xy", 8)
    q = solve_q_for_points(machine, pts)
    np.testing.assert_allclose(machine.forward(q).position, pts, atol=1e-9)
    np.testing.assert_allclose(np.linalg.norm(pts - centre, axis=1), 4.0)


def test_row_sigma_weights_rows():
    m = load_machine(DELTA)
    sim = simulate_distances(m, 10, seed=1, sigma=0.0)
    r = sim.recording
    sig = np.linspace(0.01, 0.1, 10)
    model = ConstraintModel.from_recording(m, ConstraintRecording(r.measure, r.qa, r.qb, r.value + 0.01, sigma=sig))
    pred = model.predict(None)
    rw, Jw = whitened_system(model, np.zeros(model.n_params), pred)
    np.testing.assert_allclose(rw, (model.residual(pred)[:, 0]) / sig)
    np.testing.assert_allclose(Jw, model.jacobian(None, pred)[:, 0] / sig[:, None])


def test_subset_keeps_the_parameter_layout():
    m = load_machine(DELTA)
    model, _ = _mixed_model(m)
    sub = model.subset(np.arange(6))  # no ballbar rows left
    assert sub.machine.layout == model.machine.layout
    theta = np.random.default_rng(0).normal(size=model.n_params) * model.machine.tolerance
    np.testing.assert_allclose(sub.predict(theta).y, model.predict(theta).y[:6])


def test_ballbar_on_a_2t1r_machine_in_the_plane_it_moves_in():
    # the RASPM-2T1R moves its tool point in x and z: a circle in xz, the pivot's x and z recovered
    m = load_machine(ROOT / "examples" / "raspm" / "machine.toml")
    pivot = m.forward(m.home_q()[None]).position[0] + [0.5, 0.0, -0.3]
    sim = simulate_ballbar(m, 3.0, n_points=10, pivot=pivot, planes=("xz",), sigma=0.0, theta=np.zeros(m.n_params))
    model = ConstraintModel.from_recording(m, sim.recording)
    res = identify(model, method="ls", free=["pivot.1.x", "pivot.1.z"])
    assert res.success
    got = model.pivot_positions(res.theta)["1"]
    np.testing.assert_allclose([got[0], got[2]], pivot[[0, 2]], atol=1e-9)
    with pytest.raises(Exception, match="plane it moves in"):
        simulate_ballbar(m, 3.0, n_points=4, planes=("xy",), sigma=0.0)


def test_a_machine_files_instrument_frame_does_not_move_heights():
    # docs/formats.md section 6: a height is z of the tool point in the base frame; a machine file's [instrument]
    # table (the pose recordings' frame) must not turn it into the instrument's z (before: heights were
    # predicted 48-50 mm off with this frame, and identify fitted nonsense)
    from bayescal.errors import InputError
    from bayescal.machines.files import machine_from_text
    from bayescal.machines.framed import Frame, InstrumentFrame

    path = PRS3
    m = load_machine(path)
    framed = machine_from_text(path.read_text() + "\n[instrument]\norigin = [100.0, 0.0, 50.0]\n"
                               "rotation_vector = [0.1, 0.0, 0.0]\n", "framed.toml")
    assert isinstance(framed, InstrumentFrame)
    rec = simulate_distances(m, 5, seed=1, heights=5, sigma=0.0, theta=np.zeros(m.n_params)).recording
    model = ConstraintModel.from_recording(framed, rec)
    np.testing.assert_allclose(model.residual(model.predict(None)), 0.0, atol=1e-9)
    assert model.n_params == m.n_params
    with pytest.raises(InputError, match="instrument frame"):
        ConstraintModel.from_recording(InstrumentFrame(m, Frame.identity(), fit=True), rec)


def test_a_pivot_with_fewer_than_four_readings_is_refused_for_identification(tmp_path, capsys):
    # one pivot per reading: Gauss-Newton's reduced system had no column ("zero-size array ..."), a traceback
    from bayescal.cli import main
    from bayescal.constraints.model import check_pivot_readings
    from bayescal.errors import RecordingError
    from bayescal.io.constraints import read_constraints

    text = "measure,a_q1,a_q2,a_q3,value,pivot\n" + "".join(
        f"ballbar,{-150 - i},{-140 + i},{-145 - 2 * i},40.{i},{p}\n" for i, p in enumerate(["a"] * 4 + ["b"] * 3))
    (tmp_path / "bb.csv").write_text(text)
    with pytest.raises(RecordingError, match=r"line 6, column 'pivot': pivot 'b' has 3 reading\(s\); .* at least 4"):
        check_pivot_readings(read_constraints(tmp_path / "bb.csv"))
    check_pivot_readings(read_constraints("ok.csv", text=text.replace(",b\n", ",a\n")))
    delta = Path(__file__).resolve().parents[2] / "examples" / "delta" / "machine.toml"
    assert main(["identify", str(tmp_path / "bb.csv"), "--machine", str(delta), "--method", "map"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "pivot 'b' has 3 reading(s)" in err[0]
