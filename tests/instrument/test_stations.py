"""Several instrument stations, one geometry (docs/formats.md section 8): frames at random poses metres apart."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from bayescal.errors import RecordingError
from bayescal.geometry import so3_exp, so3_log
from bayescal.identify.calibrate import calibrate
from bayescal.instrument.prepare import prepare_model
from bayescal.io.recording import read_recording, recording_to_csv
from bayescal.machines.files import load_machine
from bayescal.machines.framed import Frame
from bayescal.simulate import simulate_recording

EX = Path(__file__).resolve().parents[2] / "examples" / "prs3"


def _random_frame(rng) -> Frame:
    axis = rng.normal(size=3)
    angle = rng.uniform(0.2, 3.0)
    return Frame.from_rotation_vector(rng.uniform(-3000, 3000, size=3), axis / np.linalg.norm(axis) * angle)


def _stationed(rec, labels, frames):
    """The recording as stations in their own frames would have measured it (the truth is in the base frame)."""
    pos, rv = rec.position.copy(), rec.rotvec.copy()
    for k, f in frames.items():
        s = labels == k
        pos[s] = f.to_instrument(rec.position[s])
        rv[s] = so3_log(f.rotation.T @ so3_exp(rec.rotvec[s]))
    return replace(rec, position=pos, rotvec=rv, station=tuple(labels.tolist()))


@pytest.fixture(scope="module")
def setup():
    machine = load_machine(EX / "machine.toml")
    sim = simulate_recording(machine, 60, seed=3, dof=6)
    rec = sim.recording
    rng = np.random.default_rng(11)
    # each station sees a different part of the workspace (split by the first actuator)
    labels = np.where(rec.q[:, 0] < np.median(rec.q[:, 0]), "east", "west")
    frames = {"east": _random_frame(rng), "west": _random_frame(rng)}
    return machine, rec, _stationed(rec, labels, frames), frames


def test_stations_give_one_geometry_equal_to_one_frame(setup):
    machine, rec, stationed, frames = setup
    fm, model, _ = prepare_model(machine, stationed, frame="fit")
    assert fm.n_stations == 2 and fm.layout.names[0] == "frame.west.origin.x" or fm.layout.names[0] == "frame.east.origin.x"
    two = calibrate(model, method="map", prior_scale="tolerance", robust="off").result
    _, model1, _ = prepare_model(machine, rec, frame="fit")
    one = calibrate(model1, method="map", prior_scale="tolerance", robust="off").result
    assert two.success and one.success
    g2, g1 = two.theta[12:], one.theta[6:]
    z = (g2 - g1) / one.std[6:]
    # two frames instead of one cost a little information; the geometry is the same within noise
    assert np.max(np.abs(z)) < 2.0 and np.sqrt(np.mean(z**2)) < 0.5
    # every station's frame recovered (to the geometry's gauge: within a millimetre and a milliradian)
    for k, label in enumerate(fm.stations):
        f, t = fm.frame_at(two.theta, k), frames[label]
        assert np.linalg.norm(f.origin - t.origin) < 2.0
        assert np.linalg.norm(so3_log(f.rotation @ t.rotation.T)) < 2e-3
    assert two.rms_after["position"] < 1.2 * one.rms_after["position"]


def test_station_jacobian_matches_finite_differences(setup):
    machine, _, stationed, _ = setup
    fm, model, _ = prepare_model(machine, stationed.subset(np.arange(0, 60, 7)), frame="fit")
    rng = np.random.default_rng(2)
    theta = rng.normal(size=fm.n_params) * fm.tolerance * 0.01
    pred = model.predict(theta)
    J = model.jacobian(theta, pred)
    h = 1e-3 * fm.tolerance  # the 3-PRS forward kinematics solves to ~1e-10 mm: steps well above that
    for j in list(range(12)) + [12, 20, 30]:
        tp, tm = theta.copy(), theta.copy()
        tp[j] += h[j]
        tm[j] -= h[j]
        fd = (model.predict(tp, guess=pred.poses).y - model.predict(tm, guess=pred.poses).y) / (2 * h[j])
        np.testing.assert_allclose(J[:, :, j], fd, atol=1e-6 * max(1.0, np.abs(fd).max()), err_msg=fm.layout.names[j])
    # a pose sees only its own station's frame columns
    own = np.asarray(fm.pose_station)
    for i in range(model.n_poses):
        other = 1 - own[i]
        assert np.all(J[i, :, 6 * other: 6 * other + 6] == 0.0)


def test_subset_keeps_each_pose_with_its_station(setup):
    machine, _, stationed, _ = setup
    fm, model, _ = prepare_model(machine, stationed, frame="fit")
    rng = np.random.default_rng(0)
    theta = rng.normal(size=fm.n_params) * fm.tolerance * 0.01
    idx = np.array([5, 40, 2, 33])
    np.testing.assert_allclose(model.subset(idx).predict(theta).y, model.predict(theta).y[idx], atol=1e-9)


def test_station_and_role_columns_read_and_write():
    text = "q1,q2,q3,x,y,z,station,role\n" + "\n".join(
        f"500,500,500,1,2,3,{s},{r}" for s, r in (("a", "fit"), ("b", "check"), ("a", "fit")))
    rec = read_recording("r.csv", text=text)
    assert rec.stations == ("a", "b") and rec.station_index.tolist() == [0, 1, 0]
    assert rec.is_check.tolist() == [False, True, False]
    sub = rec.subset(rec.is_check)
    assert sub.lines.tolist() == [3] and sub.station == ("b",)
    back = read_recording("r.csv", text=recording_to_csv(rec))
    assert back.station == rec.station and back.role == rec.role


@pytest.mark.parametrize("cell,what", [("", "empty cell"), ("held", "expected 'fit' or 'check'")])
def test_bad_role_is_named(cell, what):
    text = "q1,q2,q3,x,y,z,role\n500,500,500,1,2,3,fit\n500,500,500,1,2,3," + cell + "\n"
    with pytest.raises(RecordingError, match=what) as exc:
        read_recording("r.csv", text=text)
    assert "line 3" in str(exc.value) and "role" in str(exc.value)


def test_station_with_too_few_poses_is_named(setup):
    machine, _, stationed, _ = setup
    labels = np.array(stationed.station, dtype=object)
    labels[7] = "lonely"
    bad = replace(stationed, station=tuple(labels))
    with pytest.raises(RecordingError, match="station .lonely. has 1 fit pose"):
        prepare_model(machine, bad, frame="fit")


def test_too_few_fit_poses_without_a_station_column_names_no_station(setup):
    machine, rec, _, _ = setup
    one = rec.subset(np.arange(1))
    with pytest.raises(RecordingError, match=r"1 fit pose\(s\); at least 2 \(orientations\) are needed to fit the "
                       r"instrument frame") as err:
        prepare_model(machine, one, frame="fit")
    assert err.value.column is None and "station ''" not in str(err.value)
