"""compare --recording: every trial re-measures the user's relations on its true machine; a trial's
output error equals what `bayescal identify` gives on that trial's recording written out as a file."""

import json
from pathlib import Path

import numpy as np
import pytest

from bayescal.cli import main
from bayescal.compare import compare_methods
from bayescal.compare.trial import trial_rng
from bayescal.constraints.model import ConstraintModel
from bayescal.errors import InputError
from bayescal.io.constraints import ConstraintRecording, read_constraints, write_constraints
from bayescal.machines.files import load_machine
from bayescal.simulate import draw_poses
from bayescal.constraints.simulate import simulate_ballbar, simulate_distances

DELTA = Path(__file__).resolve().parents[2] / "examples" / "delta" / "machine.toml"


@pytest.fixture(scope="module")
def delta():
    return load_machine(DELTA)


def test_a_trial_is_identify_on_its_recording(delta, tmp_path):
    rec_path = tmp_path / "rec.csv"
    write_constraints(rec_path, simulate_distances(delta, 25, seed=3, heights=15).recording)
    cmp = compare_methods(delta, methods="ridge:lam=1", trials=2, recording=rec_path, free="all", n_eval=15, progress=False)
    label = cmp.labels[0]
    assert cmp.config["dof"] == 1 and cmp.config["n_poses"] == 40

    # trial 1 by hand: true machine, the same relations measured on it with noise, fresh poses
    rec = read_constraints(rec_path)
    model = ConstraintModel.from_recording(delta, rec)
    rng = trial_rng(0, 1)
    theta = rng.normal(size=model.n_params) * model.machine.tolerance
    y = model.predict(theta).y + model.row_sigma * rng.normal(size=(model.n_poses, 1))
    q_eval = draw_poses(delta, 15, rng, theta)
    trial = tmp_path / "trial1.csv"
    write_constraints(trial, ConstraintRecording(measure=rec.measure, qa=rec.qa, qb=rec.qb, value=y[:, 0]))
    out = tmp_path / "a.json"
    assert main(["identify", str(trial), "--machine", str(DELTA), "--method", "ridge", "--lam", "1", "--free", "all",
                 "--json", str(out), "--quiet"]) in (0, 1)
    theta_hat = np.array([p["value"] for p in json.loads(out.read_text())["parameters"]])
    err = np.linalg.norm(delta.forward(q_eval, theta_hat).position - delta.forward(q_eval, theta).position, axis=1)
    assert cmp.errors[label][1] == pytest.approx(float(np.sqrt(np.mean(err**2))), rel=1e-6)
    nominal = np.linalg.norm(delta.forward(q_eval).position - delta.forward(q_eval, theta).position, axis=1)
    assert cmp.nominal[1] == pytest.approx(float(np.sqrt(np.mean(nominal**2))), rel=1e-9)


def test_ballbar_pivots_are_nuisance(delta, tmp_path):
    rec_path = tmp_path / "bb.csv"
    write_constraints(rec_path, simulate_ballbar(delta, 40.0, n_points=12, planes=("xy", "xz"), pivot=[1, 2, 80], seed=1).recording)
    cmp = compare_methods(delta, methods="map", trials=2, recording=rec_path, n_eval=10, progress=False)
    assert np.all(np.isfinite(cmp.errors["map"])) and cmp.config["recording"] == str(rec_path)
    assert "recording_text" not in cmp.config
    assert "the 24 measurements of" in cmp.report()


def test_a_recording_of_poses_is_re_measured_too(tmp_path):
    prs3 = DELTA.parents[1] / "prs3"
    cmp = compare_methods(load_machine(prs3 / "machine.toml"), methods="ridge", trials=1, recording=prs3 / "recording.csv",
                          dof=3, n_eval=10, progress=False)
    assert cmp.config["dof"] == 3 and cmp.config["n_poses"] > 10 and np.isfinite(cmp.errors["ridge"][0])


def test_a_recording_of_another_machine_is_bad_input(delta, tmp_path):
    rec = tmp_path / "r.csv"
    rec.write_text("measure,a_q1,a_q2,value\nheight,1,2,3\n")
    with pytest.raises(InputError, match="r.csv"):
        compare_methods(delta, methods="map", trials=1, recording=rec, progress=False)
