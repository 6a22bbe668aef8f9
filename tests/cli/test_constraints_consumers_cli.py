"""diagnose, grid and compare on constraint recordings, for every machine kind (3-PRS, RU-PUS-PRS,
RASPM, serial, linear delta): ballbar circles from `simulate --ballbar` (distances and heights from
the constraint simulator where a 2-DOF machine cannot follow a circle).  The grid is checked node by
node against the geometry `identify` gives on the same recording (pivots left out)."""

import csv
import json
from pathlib import Path

import numpy as np
import pytest

from bayescal.cli import main
from bayescal.io.constraints import write_constraints
from bayescal.machines.files import load_machine
from bayescal.constraints.simulate import simulate_distances

EX = Path(__file__).resolve().parents[2] / "examples"
# kind: (machine file, simulate arguments or None for distances and heights)
KINDS = {
    "prs3": (EX / "prs3" / "machine.toml", ["--ballbar", "12", "--planes", "xy,xz", "--poses", "10"]),
    "rupus_prs": (EX / "rupus_prs" / "machine.toml", None),
    "raspm": (EX / "raspm" / "machine.toml", ["--ballbar", "100", "--planes", "xz", "--poses", "18"]),
    "serial": (EX / "arm6" / "machine.toml", ["--ballbar", "50", "--planes", "xy,xz", "--poses", "12"]),
    "delta": (EX / "delta" / "machine.toml", ["--ballbar", "40", "--planes", "xy", "--poses", "14", "--pivot", "1,2,80"]),
}


@pytest.fixture(scope="module", params=list(KINDS))
def case(request, tmp_path_factory):
    kind = request.param
    machine, sim = KINDS[kind]
    d = tmp_path_factory.mktemp(kind)
    rec = d / "rec.csv"
    if sim is None:
        write_constraints(rec, simulate_distances(load_machine(machine), 10, seed=2, heights=6).recording)
    else:
        assert main(["simulate", "--machine", str(machine), *sim, "--seed", "2", "--out", str(rec), "--quiet"]) == 0
    return kind, machine, rec, d


def test_diagnose_a_clean_constraint_recording_is_none(case):
    kind, machine, rec, d = case
    out = d / "diag.json"
    assert main(["diagnose", str(rec), "--machine", str(machine), "--effects", "backlash", "--json", str(out), "--quiet"]) == 0
    ans = json.loads(out.read_text())
    assert ans["verdict"] == "none", ans
    assert ans["outliers"] == []


def _grid_rows(path):
    with open(path, newline="") as fh:
        rows = list(csv.DictReader(fh))
    return rows


def test_grid_is_the_identified_geometry_without_the_pivots(case):
    kind, machine, rec, d = case
    ident, grid_csv, grid_json = d / "ident.json", d / "grid.csv", d / "grid.json"
    # few readings for many parameters: identify may call the fit not plausible (exit 1), its MAP is the grid's
    assert main(["identify", str(rec), "--machine", str(machine), "--method", "map", "--free", "all", "--json", str(ident), "--quiet"]) in (0, 1)
    # the default space, for every kind: a delta declares its q_limits box not all reachable and gets tool space
    assert main(["grid", str(rec), "--machine", str(machine), "--nodes", "3", "--out", str(grid_csv),
                 "--json", str(grid_json), "--quiet"]) == 0
    m = load_machine(machine)
    params = json.loads(ident.read_text())["parameters"]
    theta = np.array([p["value"] for p in params if not p["name"].startswith("pivot.")])
    assert theta.size == m.n_params and np.abs(theta).max() > 0
    rows = _grid_rows(grid_csv)
    q = np.array([[float(r[f"q{i + 1}"]) for i in range(m.n_actuators)] for r in rows])
    dx = np.array([[float(r[c]) for c in ("dx", "dy", "dz")] for r in rows])
    got = m.forward(q, theta).position
    if "x" in rows[0]:  # tool space: the correction commanded minus actual at the nominal inverse kinematics
        want = np.array([[float(r[c]) for c in "xyz"] for r in rows]) - got
    else:  # actuator space: the correction, nominal minus actual
        want = m.forward(q).position - got
    # (the CSV's 9 significant digits of a tool point of ~2 m are 1e-5 mm)
    np.testing.assert_allclose(dx, want, atol=3e-5)
    assert np.abs(dx).max() > 1e-4
    assert json.loads(grid_json.read_text())["method"] == "map"


def test_compare_re_measures_the_recording(case):
    kind, machine, rec, d = case
    out = d / "cmp.json"
    assert main(["compare", "--machine", str(machine), "--recording", str(rec), "--methods", "map", "--trials", "2",
                 "--eval-poses", "10", "--json", str(out), "--quiet"]) == 0
    ans = json.loads(out.read_text())
    n_rows = len(rec.read_text().splitlines()) - 1
    assert ans["config"]["recording"] == str(rec) and ans["config"]["n_poses"] == n_rows and ans["config"]["dof"] == 1
    assert ans["summary"]["map"]["n"] == 2


def test_compare_refuses_poses_with_a_recording(tmp_path, capsys):
    machine, _ = KINDS["delta"]
    rec = tmp_path / "r.csv"
    write_constraints(rec, simulate_distances(load_machine(machine), 4, seed=1).recording)
    assert main(["compare", "--machine", str(machine), "--recording", str(rec), "--poses", "20"]) == 2
    assert "--poses" in capsys.readouterr().err


@pytest.mark.parametrize("command", ["diagnose", "grid"])
def test_frame_fit_on_a_constraint_recording_is_refused(tmp_path, command, capsys):
    machine, _ = KINDS["delta"]
    rec = tmp_path / "r.csv"
    write_constraints(rec, simulate_distances(load_machine(machine), 4, seed=1).recording)
    assert main([command, str(rec), "--machine", str(machine), "--frame", "fit"]) == 2
    assert "constraint recording" in capsys.readouterr().err


def test_diagnose_figures_report_and_calibrated_machine(tmp_path):
    machine, sim = KINDS["delta"]
    rec = tmp_path / "bb.csv"
    assert main(["simulate", "--machine", str(machine), *sim, "--seed", "4", "--out", str(rec), "--quiet"]) == 0
    figs, report, cal = tmp_path / "figs", tmp_path / "d.html", tmp_path / "cal.toml"
    assert main(["diagnose", str(rec), "--machine", str(machine), "--effects", "backlash", "--figures", str(figs),
                 "--report", str(report), "--write-machine", str(cal), "--quiet"]) == 0
    assert (figs / "residuals_vs_channels.png").stat().st_size > 0 and report.stat().st_size > 0
    assert load_machine(cal).n_params == load_machine(machine).n_params  # the geometry, not the pivot
    assert main(["identify", str(rec), "--machine", str(cal), "--method", "map", "--quiet"]) in (0, 1)


@pytest.mark.parametrize("method", ["map", "kalman"])
@pytest.mark.parametrize("instrument", [False, True], ids=["plain", "instrument"])
def test_identify_writes_the_machine_of_a_ballbar_recording(tmp_path, method, instrument):
    # the answer's theta has the pivots after the machine's parameters: the written machine is the geometry
    # alone (kalman and mcmc passed the whole theta: exit 2 "theta: expected shape (21,)"), and a machine
    # file's [instrument] table (which a constraint recording does not see) is kept, not fitted
    machine = tmp_path / "m.toml"
    text = (EX / "delta" / "machine.toml").read_text()
    if instrument:
        text += "\n[instrument]\norigin = [10.0, 0.0, 0.0]\nrotation_vector = [0.0, 0.0, 0.1]\n"
    machine.write_text(text)
    rec = tmp_path / "bb.csv"
    assert main(["simulate", "--machine", str(machine), "--ballbar", "40", "--planes", "xy,xz", "--poses", "12",
                 "--pivot", "1,2,80", "--seed", "3", "--out", str(rec), "--quiet"]) == 0
    out = tmp_path / "cal.toml"
    code = main(["identify", str(rec), "--machine", str(machine), "--method", method, "--json", str(tmp_path / "a.json"),
                 "--write-machine", str(out), "--force", "--quiet"])
    assert code in (0, 1)
    answer = json.loads((tmp_path / "a.json").read_text())
    nominal = load_machine(machine)
    P = nominal.n_params
    names = [p["name"] for p in answer["parameters"]]
    assert names[:P] == list(nominal.layout.names) and all(n.startswith("pivot.") for n in names[P:])
    theta = np.array([p["value"] for p in answer["parameters"]])[:P]
    cal = load_machine(out)
    q = nominal.sample_q(8, np.random.default_rng(1))
    np.testing.assert_allclose(cal.forward(q).position, nominal.forward(q, theta).position, atol=1e-9)
    if instrument:
        assert answer["frame"]["fitted"] is False and answer["frame"]["origin"] == [10.0, 0.0, 0.0]


def test_kalman_writes_klipper_keys_as_the_other_methods(tmp_path):
    # --write-klipper was silently ignored by kalman and mcmc (exit 0, no file); the keys are the geometry's
    from bayescal.klipper.keys import klipper_text

    delta = EX / "delta"
    cfg = tmp_path / "k.cfg"
    code = main(["identify", str(delta / "recording.csv"), "--machine", str(delta / "machine.toml"), "--method", "kalman",
                 "--json", str(tmp_path / "a.json"), "--write-klipper", str(cfg), "--quiet"])
    assert code == 0
    m = load_machine(delta / "machine.toml")
    theta = np.array([p["value"] for p in json.loads((tmp_path / "a.json").read_text())["parameters"]])
    assert cfg.read_text() == klipper_text(m, theta)
