"""Recordings from real instruments through the command line: --frame, plausibility, --force, units."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from bayescal.cli import main
from bayescal.io import read_recording, write_recording
from bayescal.machines.files import load_machine
from tests.conftest import PRS3_FILE
from tests.instrument.frames import random_frame, to_instrument

ROOT = Path(__file__).resolve().parents[2]
EXAMPLE = ROOT / "examples" / "prs3" / "recording.csv"


@pytest.fixture(scope="module")
def tracker(tmp_path_factory):
    """A simulated recording in a tracker frame rotated 150 deg and metres away, and the truth."""
    d = tmp_path_factory.mktemp("tracker")
    rec = d / "rec.csv"
    assert main(["simulate", "--machine", str(PRS3_FILE), "--poses", "40", "--seed", "12", "--out", str(rec), "--quiet"]) == 0
    o, R = random_frame(np.random.default_rng(12), max_angle=np.radians(150))
    out = d / "tracker.csv"
    write_recording(out, to_instrument(read_recording(rec), o, R))
    return out, o, R, d


def _frame_ok(ans, o, R):
    f = ans["frame"]
    Rf = Rotation.from_rotvec(f["rotation_vector"]).as_matrix()
    # the frame is identified up to the gauge it shares with the base parameters (sub-mm, sub-mrad here)
    assert np.linalg.norm(np.array(f["origin"]) - o) < 20.0
    assert np.linalg.norm(Rotation.from_matrix(Rf.T @ R).as_rotvec()) < 1e-2
    assert all(s is not None and s > 0 for s in f["std"]["origin"] + f["std"]["rotation_vector"])
    assert ans["plausible"] is True


@pytest.mark.parametrize("method", [
    ["--method", "map"],
    ["--method", "kalman"],
    ["--method", "mcmc", "--surrogate", "linear", "--steps", "200", "--walkers", "90"],
])
def test_identify_frame_fit(tracker, capsys, method):
    rec, o, R, d = tracker
    js, cal = d / f"{method[1]}.json", d / f"{method[1]}.toml"
    code = main(["identify", str(rec), "--machine", str(PRS3_FILE), *method, "--frame", "fit", "--json", str(js),
                 "--write-machine", str(cal), "--quiet"])
    assert code == 0
    ans = json.loads(js.read_text())
    _frame_ok(ans, o, R)
    assert ans["rms_after"]["position"] < 0.02
    # the calibrated machine carries the frame: as a base-frame run it explains the tracker recording
    m = load_machine(cal)
    assert np.allclose(m.frame0.origin, ans["frame"]["origin"])
    assert main(["identify", str(rec), "--machine", str(cal), "--method", "map", "--json", str(js), "--quiet"]) == 0
    assert json.loads(js.read_text())["rms_before"]["position"] < 0.02


def test_base_frame_run_refuses_a_tracker_frame(tracker, capsys):
    rec, *_ = tracker
    code = main(["identify", str(rec), "--machine", str(PRS3_FILE), "--method", "map"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and "--frame fit" in err[0]


def test_base_frame_run_warns_on_a_small_offset(tmp_path, capsys):
    from dataclasses import replace

    rec = read_recording(EXAMPLE)
    p = tmp_path / "off.csv"
    write_recording(p, replace(rec, position=rec.position + [2.0, 0.0, 0.0]))
    main(["identify", str(p), "--machine", str(PRS3_FILE), "--method", "map"])
    err = capsys.readouterr().err
    assert "warning" in err and "--frame fit" in err


def test_diagnose_and_grid_frame_fit(tracker, capsys):
    rec, o, R, d = tracker
    js = d / "diag.json"
    assert main(["diagnose", str(rec), "--machine", str(PRS3_FILE), "--frame", "fit", "--json", str(js), "--quiet",
                 "--effects", "backlash"]) == 0
    ans = json.loads(js.read_text())
    assert ans["verdict"] == "none"
    _frame_ok({**ans, "plausible": True}, o, R)
    # the library's diagnosis carries the frame's keys: the command's answer byte for byte (before, the command
    # added them from a fit of its own, and bayescal.diagnose had no frame option)
    import bayescal
    from bayescal.io.answers import json_text

    lib = bayescal.diagnose(PRS3_FILE, rec, frame="fit", effects=["backlash"])
    assert json_text(lib.to_dict()) == js.read_text() and lib.frame == {"frame": ans["frame"]}
    g = d / "grid.csv"
    assert main(["grid", str(rec), "--machine", str(PRS3_FILE), "--frame", "fit", "--out", str(g), "--nodes", "3", "--quiet"]) == 0
    assert g.read_text().startswith("q1,q2,q3,dx")


def test_plan_accepts_and_compare_refuses_frame_fit(tmp_path, capsys):
    out = tmp_path / "p.csv"
    assert main(["plan", "--machine", str(PRS3_FILE), "--n", "12", "--candidates", "300", "--random-sets", "2",
                 "--frame", "fit", "--out", str(out), "--quiet"]) == 0
    assert main(["compare", "--machine", str(PRS3_FILE), "--frame", "fit", "--trials", "2", "--quiet"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--frame fit" in err[0]


def test_example_least_squares_refuses_and_force_writes(tmp_path, capsys):
    cal, js = tmp_path / "x.toml", tmp_path / "a.json"
    args = ["identify", str(EXAMPLE), "--machine", str(PRS3_FILE), "--method", "ls", "--write-machine", str(cal), "--json", str(js)]
    assert main(args) == 1
    out = capsys.readouterr().out
    assert "NOT PLAUSIBLE" in out and "chain3.rail_origin.x" in out and "unidentifiable combination" in out
    assert not cal.exists()
    ans = json.loads(js.read_text())
    assert ans["plausible"] is False and ans["plausibility"]["reasons"]
    assert main(args + ["--force", "--quiet"]) == 1 and cal.exists()


def test_example_main_command_still_succeeds(tmp_path):
    cal = tmp_path / "x.toml"
    assert main(["identify", str(EXAMPLE), "--machine", str(PRS3_FILE), "--method", "ridge", "--lam", "auto",
                 "--write-machine", str(cal), "--quiet"]) == 0
    assert cal.exists()


def test_three_poses_refuse(tmp_path, capsys):
    lines = EXAMPLE.read_text().splitlines()[:4]
    rec = tmp_path / "three.csv"
    rec.write_text("\n".join(lines) + "\n")
    cal = tmp_path / "x.toml"
    assert main(["identify", str(rec), "--machine", str(PRS3_FILE), "--method", "ls", "--write-machine", str(cal)]) == 1
    assert "no residual degrees of freedom" in capsys.readouterr().out and not cal.exists()


def test_metres_refused_with_exit_2(tmp_path, capsys):
    rec = read_recording(EXAMPLE)
    from dataclasses import replace

    p = tmp_path / "m.csv"
    write_recording(p, replace(rec, position=rec.position / 1000))
    assert main(["identify", str(p), "--machine", str(PRS3_FILE)]) == 2
    err = capsys.readouterr().err
    assert "metres" in err and "x_m" in err


def test_worked_example_script(tmp_path):
    """The docs' script rewrites a recording into a tracker frame; --frame fit reads it."""
    out = tmp_path / "t.csv"
    subprocess.run([sys.executable, str(ROOT / "examples" / "instrument" / "to_tracker_frame.py"), str(EXAMPLE), str(out),
                    "--angle-deg", "170", "--origin", "3000,-2000,1500"], check=True, capture_output=True)
    js = tmp_path / "a.json"
    assert main(["identify", str(out), "--machine", str(PRS3_FILE), "--method", "map", "--frame", "fit", "--json", str(js), "--quiet"]) == 0
    assert np.linalg.norm(np.array(json.loads(js.read_text())["frame"]["origin"]) - [3000, -2000, 1500]) < 20
