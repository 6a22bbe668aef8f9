"""identify --fit-effects: a machine file's [effect.*] parameters identified with the geometry, end to end."""

import json

import numpy as np
import pytest

from bayescal.cli import main
from bayescal.effects.stored import StoredEffectsTransform
from bayescal.io.recording import write_recording
from bayescal.machines.files import load_machine
from bayescal.simulate import simulate_recording
from tests.conftest import PRS3_FILE

TABLE = '\n[effect.backlash]\n"backlash.q1" = 20.0\n"backlash.q2" = 30.0\n"backlash.q3" = 25.0\n'
NAMES = ["chain1.rail_origin.z", "chain2.rail_origin.z", "effect.backlash.backlash.q1", "effect.backlash.backlash.q2",
         "effect.backlash.backlash.q3"]


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    """A machine file with a backlash table and a recording of that machine with other backlash, nominal geometry."""
    d = tmp_path_factory.mktemp("fit_effects")
    machine = d / "m.toml"
    machine.write_text(PRS3_FILE.read_text() + TABLE)
    truth = d / "truth.toml"
    truth.write_text(PRS3_FILE.read_text() + TABLE.replace("20.0", "8.0").replace("30.0", "12.0").replace("25.0", "10.0"))
    m = load_machine(truth)
    sim = simulate_recording(m, 40, seed=21, effects=[StoredEffectsTransform(m, m.effects)], theta_true=np.zeros(m.n_params))
    return machine, write_recording(d / "rec.csv", sim.recording)


def test_map_fits_the_tables_and_writes_them(files, tmp_path, capsys):
    machine, rec = files
    out = tmp_path / "cal.toml"
    code = main(["identify", str(rec), "--machine", str(machine), "--method", "map", "--fit-effects",
                 "--json", str(tmp_path / "a.json"), "--write-machine", str(out)])
    text = capsys.readouterr().out
    assert code == 0, text
    assert "effects fitted with the geometry (--fit-effects)" in text
    answer = json.loads((tmp_path / "a.json").read_text())
    fitted = {p["name"]: p for p in answer["parameters"] if p["name"].startswith("effect.")}
    assert sorted(fitted) == NAMES[2:]
    assert all(p["unit"] == "um" and p["std"] > 0 for p in fitted.values())
    # the recording's machine has 8, 12, 10 um, the file 20, 30, 25: the fit moves to the recording's, within 4 sigma
    for name, true in zip(NAMES[2:], (8.0, 12.0, 10.0)):
        assert abs(fitted[name]["value"] - true) < 4 * fitted[name]["std"], (name, fitted[name])
    written = dict(load_machine(out).effects[0].values)
    for name in NAMES[2:]:
        assert written[name.split(".", 2)[2]] == pytest.approx(fitted[name]["value"], rel=1e-12)
    # held at the stored values instead, the same recording fits worse
    assert main(["identify", str(rec), "--machine", str(machine), "--method", "map", "--json", str(tmp_path / "b.json"),
                 "--quiet"]) == 0
    held = json.loads((tmp_path / "b.json").read_text())
    assert answer["rms_after"]["position"] < 0.9 * held["rms_after"]["position"]


def test_mcmc_samples_effects_with_the_geometry(files, tmp_path, capsys):
    machine, rec = files
    out = tmp_path / "cal.toml"
    code = main(["identify", str(rec), "--machine", str(machine), "--method", "mcmc", "--fit-effects", "--free",
                 ",".join(NAMES), "--steps", "600", "--seed", "3", "--json", str(tmp_path / "p.json"),
                 "--write-machine", str(out), "--quiet"])
    assert code == 0
    answer = json.loads((tmp_path / "p.json").read_text())
    assert answer["convergence"]["max_rhat"] < 1.05
    q = {r["name"]: r for r in answer["interval_90"]}
    assert set(q) == set(NAMES)
    for name, true in zip(NAMES[2:], (8.0, 12.0, 10.0)):
        sd = (q[name]["q95"] - q[name]["q05"]) / 3.29  # the 90 % interval of a near-Gaussian marginal
        assert abs(q[name]["q50"] - true) < 3 * sd, (name, q[name])
        assert q[name]["q05"] >= 0.0  # the prior is truncated at the physical bound
    values = {p["name"]: p["value"] for p in answer["parameters"]}
    written = dict(load_machine(out).effects[0].values)
    assert written["backlash.q2"] == pytest.approx(values["effect.backlash.backlash.q2"], rel=1e-12)


@pytest.mark.parametrize("args,message", [
    (["--method", "ls"], "(--fit-effects) goes with method map or mcmc"),
    (["--method", "map", "--prior-scale", "empirical"], "--prior-scale empirical does not go with --fit-effects"),
])
def test_fit_effects_refuses_what_it_cannot_do(files, capsys, args, message):
    machine, rec = files
    assert main(["identify", str(rec), "--machine", str(machine), "--fit-effects", *args]) == 2
    assert message in capsys.readouterr().err


def test_fit_effects_needs_tables(files, capsys):
    _, rec = files
    assert main(["identify", str(rec), "--machine", str(PRS3_FILE), "--method", "map", "--fit-effects"]) == 2
    assert "has no [effect.*] tables" in capsys.readouterr().err


def test_grid_fits_the_tables_and_refuses_kalman(files, tmp_path, capsys):
    machine, rec = files
    code = main(["grid", str(rec), "--machine", str(machine), "--fit-effects", "--nodes", "2", "--json", str(tmp_path / "g.json")])
    out = capsys.readouterr().out
    assert code == 0
    assert "backlash fitted with the geometry, applied at no auxiliary channel" in out
    answer = json.loads((tmp_path / "g.json").read_text())
    assert answer["effects_fitted"] is True and answer["effects"] == ["backlash"]
    assert main(["grid", str(rec), "--machine", str(machine), "--fit-effects", "--method", "kalman"]) == 2
    assert "(--fit-effects) goes with method map or mcmc" in capsys.readouterr().err


@pytest.mark.parametrize("command", ["identify", "grid"])
def test_fit_effects_on_a_constraint_recording_names_its_file(tmp_path, capsys, command):
    # grid passes the model without its recording: the refusal said "the recording is a constraint recording"
    from bayescal.constraints.simulate import simulate_distances
    from bayescal.io.constraints import write_constraints

    machine = tmp_path / "m.toml"
    machine.write_text(PRS3_FILE.read_text() + TABLE)
    rec = tmp_path / "heights.csv"
    write_constraints(rec, simulate_distances(load_machine(PRS3_FILE), 8, seed=1, heights=4).recording)
    assert main([command, str(rec), "--machine", str(machine), "--fit-effects", "--quiet"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and f"{rec} is a constraint recording" in err[0]
