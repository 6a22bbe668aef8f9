"""Constraint recordings through the command line: simulate --ballbar, identify with every
deterministic method, --write-machine (diagnose, grid and compare: test_constraints_consumers_cli.py)."""

import json
from pathlib import Path

import numpy as np
import pytest

from bayescal.cli import main
from bayescal.machines.files import load_machine

DELTA = Path(__file__).resolve().parents[2] / "examples" / "delta" / "machine.toml"


@pytest.fixture(scope="module")
def ballbar(tmp_path_factory):
    d = tmp_path_factory.mktemp("bb")
    rec = d / "bb.csv"
    code = main([
        "simulate", "--machine", str(DELTA), "--ballbar", "40", "--planes", "xy,xz", "--poses", "16", "--seed", "3",
        "--pivot", "1,2,80", "--out", str(rec), "--quiet",
    ])
    assert code == 0
    return rec


def test_simulate_ballbar_writes_a_constraint_recording(ballbar):
    head = ballbar.read_text().splitlines()
    assert head[0] == "measure,a_q1,a_q2,a_q3,value" and len(head) == 33
    truth = json.loads(ballbar.with_suffix(".truth.json").read_text())
    assert truth["pivots"] == {"1": [1.0, 2.0, 80.0]}


@pytest.mark.parametrize("method", [["ridge", "--lam", "1"], ["tsvd", "--k", "6"], ["map"]])
def test_identify_takes_constraint_recordings(ballbar, tmp_path, method, capsys):
    out, cal = tmp_path / "a.json", tmp_path / "cal.toml"
    code = main(["identify", str(ballbar), "--machine", str(DELTA), "--method", *method, "--json", str(out), "--write-machine", str(cal)])
    assert code == 0
    ans = json.loads(out.read_text())
    assert ans["rms_after"]["position"] < ans["rms_before"]["position"]
    assert [p["name"] for p in ans["parameters"]][-3:] == ["pivot.1.x", "pivot.1.y", "pivot.1.z"]
    assert set(ans["pivots"]) == {"1"}
    assert load_machine(cal).n_params == 21  # the calibrated machine without the pivot
    assert "pivot.1" in capsys.readouterr().out


def test_identify_ls_on_heights_and_distances(tmp_path):
    # heights and distances written by hand (docs/formats.md section 6) from the nominal machine
    m = load_machine(DELTA)
    q = m.sample_q(60, np.random.default_rng(0))
    x = m.forward(q).position
    f = lambda v: ",".join(repr(float(a)) for a in np.atleast_1d(v))  # noqa: E731
    lines = ["measure,a_q1,a_q2,a_q3,b_q1,b_q2,b_q3,value"]
    for i in range(20):
        lines.append(f"distance,{f(q[i])},{f(q[i + 20])},{f(np.linalg.norm(x[i] - x[i + 20]))}")
    for i in range(40, 60):
        lines.append(f"height,{f(q[i])},,,,{f(x[i, 2] + 0.05)}")
    rec = tmp_path / "c.csv"
    rec.write_text("\n".join(lines) + "\n")
    out = tmp_path / "a.json"
    assert main(["identify", str(rec), "--machine", str(DELTA), "--json", str(out), "--quiet"]) == 0
    ans = json.loads(out.read_text())
    assert ans["rms_after"]["position"] < 1e-6 < ans["rms_before"]["position"]
    assert "tool.point.x" in ans["fixed"] and "tool.point.y" in ans["fixed"]


def test_bad_constraint_recording_exit_2(tmp_path, capsys):
    bad = tmp_path / "bad.csv"
    bad.write_text("measure,a_q1,a_q2,a_q3,value\nlength,1,2,3,4\n")
    assert main(["identify", str(bad), "--machine", str(DELTA)]) == 2
    err = capsys.readouterr().err
    assert "bad.csv" in err and "line 2" in err and "measure" in err


def test_kalman_takes_constraint_recordings(ballbar, tmp_path):
    out = tmp_path / "k.json"
    assert main(["identify", str(ballbar), "--machine", str(DELTA), "--method", "kalman", "--json", str(out), "--quiet"]) == 0
    ans = json.loads(out.read_text())
    assert ans["rms_after"]["position"] < ans["rms_before"]["position"]


def test_write_klipper_needs_a_linear_delta(tmp_path, capsys):
    prs3 = DELTA.parents[1] / "prs3"
    code = main(["identify", str(prs3 / "recording.csv"), "--machine", str(prs3 / "machine.toml"), "--write-klipper", str(tmp_path / "k.cfg")])
    assert code == 2 and "linear-delta" in capsys.readouterr().err
    assert not (tmp_path / "k.cfg").exists()


def test_simulate_ballbar_circle_outside_q_limits_exit_2_and_a_fitting_one_round_trips(tmp_path, capsys):
    prs3 = DELTA.parents[1] / "prs3" / "machine.toml"
    out = tmp_path / "bb.csv"
    args = ["simulate", "--machine", str(prs3), "--planes", "xz", "--poses", "24", "--seed", "1", "--out", str(out), "--quiet"]
    assert main([*args, "--ballbar", "30"]) == 2
    err = capsys.readouterr().err
    assert "radius 30 mm" in err and "plane xz" in err and "q_limits" in err and "smaller radius" in err
    assert not out.exists() and not out.with_suffix(".truth.json").exists()  # nothing written on refusal
    assert main([*args, "--ballbar", "25"]) == 0
    ans = tmp_path / "ident.json"
    # every reading within q_limits: identify reads the recording (exit 0, or 1 for a fit it calls not plausible)
    assert main(["identify", str(out), "--machine", str(prs3), "--method", "map", "--free", "all", "--json", str(ans), "--quiet"]) in (0, 1)
    assert json.loads(ans.read_text())["parameters"]
