import numpy as np
import pytest

from bayescal.errors import InputError
from bayescal.measurement import MeasurementModel
from bayescal.simulate import simulate_recording


@pytest.mark.parametrize("dof", [6, 5, 3])
def test_jacobian_against_central_differences_every_parameter(prs3, rng, dof):
    q = prs3.sample_q(10, rng)
    model = MeasurementModel(prs3, q, dof)
    theta = rng.normal(size=prs3.n_params) * prs3.tolerance * 10
    pred = model.predict(theta)
    J = model.jacobian(theta, pred)
    assert J.shape == (10, dof, prs3.n_params)
    for k, unit in enumerate(prs3.layout.units):
        h = 1e-5 if unit == "mm" else 1e-7
        e = np.zeros(prs3.n_params)
        e[k] = h
        fd = (model.predict(theta + e, guess=pred.poses).y - model.predict(theta - e, guess=pred.poses).y) / (2 * h)
        assert np.allclose(J[:, :, k], fd, rtol=1e-6, atol=1e-7 * np.abs(J).max()), prs3.layout.names[k]


def test_residual_is_zero_on_noise_free_truth(prs3):
    for dof in (6, 5, 3):
        sim = simulate_recording(prs3, 12, seed=4, dof=dof)
        clean = simulate_recording(prs3, 12, seed=4, dof=dof, theta_true=sim.theta_true)
        assert clean.recording.n_poses == 12
        from bayescal.simulate import measure

        rec = measure(prs3, sim.recording.q, sim.theta_true, dof, None)
        model = MeasurementModel.from_recording(prs3, rec)
        r = model.residual(model.predict(sim.theta_true))
        assert np.abs(r).max() < 1e-10


def test_stacked_parameter_sets_equal_separate_calls(prs3, rng):
    q = prs3.sample_q(5, rng)
    model = MeasurementModel(prs3, q, 6)
    thetas = rng.normal(size=(3, prs3.n_params)) * prs3.tolerance
    stacked = model.predict(np.repeat(thetas, 5, axis=0)).y
    for i in range(3):
        assert np.allclose(stacked[5 * i : 5 * i + 5], model.predict(thetas[i]).y, atol=1e-12)


def test_dof_beyond_recording_is_an_error(prs3):
    sim = simulate_recording(prs3, 5, seed=1, dof=3)
    with pytest.raises(InputError, match="3-DOF"):
        MeasurementModel.from_recording(prs3, sim.recording, dof=6)


def test_a_measured_cell_far_off_is_named_not_blamed_on_the_machine(prs3):
    # 12345.6 in one x cell: the kinematics, started from the measurement, failed and the message said the
    # machine "cannot assemble this pose" at a q it assembles from its own start
    from dataclasses import replace

    from bayescal.errors import RecordingError
    from bayescal.measurement import check_recording_solves

    rec = simulate_recording(prs3, 8, seed=4, dof=6).recording
    pos = rec.position.copy()
    pos[5, 0] = 12345.6
    bad = replace(rec, position=pos, path="r.csv")
    model = MeasurementModel.from_recording(prs3, bad)
    with pytest.raises(RecordingError, match=r"the measured tool point is 1\.2\d+e\+04 mm from where the machine .* "
                       r"puts it .*\(x off by 1\.2\d+e\+04 mm\).*a typo in the cell") as err:
        check_recording_solves(model, bad)
    assert (err.value.row, err.value.column) == (7, "x")
    check_recording_solves(MeasurementModel.from_recording(prs3, rec), rec)  # the clean recording solves


def test_a_measured_orientation_far_off_is_named_not_the_position(prs3):
    # review: a typo in rx, ry, rz (2, 2, 0.5 rad, under pi so not read as degrees) kept pose 6 of the bundled
    # 3-PRS recording from solving, and the message blamed column 'z' "0.1459 mm from where the machine puts it
    # ... too far for its kinematics to start from": the position was fine (the pose solves from it alone)
    from dataclasses import replace

    from bayescal.errors import RecordingError
    from bayescal.measurement import check_recording_solves

    rec = simulate_recording(prs3, 8, seed=4, dof=6).recording
    rv = rec.rotvec.copy()
    rv[5] = [2.0, 2.0, 0.5]
    bad = replace(rec, rotvec=rv, path="r.csv")
    model = MeasurementModel.from_recording(prs3, bad)
    assert not model.predict(None).success[5]  # the case: the orientation sends the kinematics off
    with pytest.raises(RecordingError, match=r"the measured orientation \(rx, ry, rz\) keeps the kinematics .* from "
                       r"solving .* from the measured position alone") as err:
        check_recording_solves(model, bad)
    assert (err.value.row, err.value.column) == (7, "rx")


def _blocked(model, theta, pred, monkeypatch, columns=None):
    """``jacobian_columns`` with the pose blocks forced on (blocks of 7 poses)."""
    import bayescal.measurement as mod

    monkeypatch.setattr(mod, "_ROWS_BLOCK", 7)
    monkeypatch.setattr(mod, "_FRESH_BYTES", 0)
    try:
        return model.jacobian_columns(theta, pred, columns)
    finally:
        monkeypatch.undo()


@pytest.mark.parametrize("dof", [6, 5, 3])
def test_jacobian_in_pose_blocks_is_the_whole_ones_bit_for_bit(prs3, rng, monkeypatch, dof):
    # a large recording's Jacobian is computed block by block (fresh pages otherwise): every pose's rows are
    # its own, so the blocks must give the very same values, columns asked for or not
    q = prs3.sample_q(30, rng)  # four blocks of 7 and one of 2
    model = MeasurementModel(prs3, q, dof)
    theta = rng.normal(size=prs3.n_params) * prs3.tolerance * 10
    pred = model.predict(theta)
    for cols in (None, np.array([0, 3, 17, 35])):
        whole = model.jacobian_columns(theta, pred, cols)
        blocked = _blocked(model, theta, pred, monkeypatch, cols)
        assert blocked.shape == whole.shape
        assert np.array_equal(blocked, whole)


def test_jacobian_in_pose_blocks_with_stations_and_a_body_sensor(monkeypatch):
    # rebinding per block: a station's frame per pose (machine.for_poses) and a body sensor's rows
    from bayescal.instrument.prepare import prepare_model
    from bayescal.machines.files import load_machine
    from dataclasses import replace
    from pathlib import Path

    machine = load_machine(Path(__file__).resolve().parents[1] / "examples" / "prs3" / "machine.toml")
    rec = simulate_recording(machine, 30, seed=4, dof=6).recording
    labels = np.where(np.arange(30) % 3 == 0, "east", "west")
    _, model, _ = prepare_model(machine, replace(rec, station=tuple(labels.tolist())), frame="fit")
    rng = np.random.default_rng(2)
    theta = rng.normal(size=model.n_params) * np.minimum(model.machine.tolerance, 1.0)
    pred = model.predict(theta)
    assert np.array_equal(_blocked(model, theta, pred, monkeypatch), model.jacobian(theta, pred))


def test_tool_poses_take_by_indices_mask_or_slice_is_one_selection(prs3, rng):
    # the one way poses are selected (a model's subset, a recording's pose blocks, an alignment's solved poses)
    q = prs3.sample_q(9, rng)
    p = prs3.forward(q)
    p = type(p)(p.position, p.rotation, p.success, tuple(f"m{i}" for i in range(9)), p.state)
    mask = np.zeros(9, dtype=bool)
    mask[2:5] = True
    for sel in (np.arange(2, 5), mask, slice(2, 5)):
        t = p.take(sel)
        assert t.message == ("m2", "m3", "m4")
        assert np.array_equal(t.position, p.position[2:5]) and np.array_equal(t.rotation, p.rotation[2:5])
        assert np.array_equal(t.state.p, p.state.p[2:5]) and np.array_equal(t.state.R, p.state.R[2:5])
    assert p.take(np.array([7, 1])).message == ("m7", "m1")
