"""``bayescal identify --discrepancy`` with stations and check rows, then ``bayescal predict`` (docs/formats.md section 8)."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest

from bayescal.cli import main
from bayescal.geometry import so3_exp, so3_log
from bayescal.io import read_recording
from bayescal.io.recording import write_recording
from bayescal.machines.files import load_machine
from bayescal.machines.framed import Frame
from bayescal.prediction.recording import predict_recording
from bayescal.simulate import simulate_recording

from ..conftest import PRS3_FILE

FRAMES = {"east": Frame.from_rotation_vector([2000.0, -500.0, 300.0], [0.1, -0.2, 1.2]),
          "west": Frame.from_rotation_vector([-1500.0, 2500.0, -100.0], [0.0, 0.3, -2.0])}


def _session(prs3, n, seed, truth, *, shift=None):
    """A recording of the same true machine with a smooth mismatch, two stations, every third row held out."""
    sim = simulate_recording(prs3, n, seed=seed, dof=6, theta_true=truth)
    rec = sim.recording
    z = (rec.q - 500.0) / 50.0
    p = rec.position + 0.03 * np.column_stack([np.sin(1.3 * z[:, 0]) * z[:, 1], np.cos(z[:, 2]) * z[:, 0], z[:, 1] ** 2 - 1])
    st = np.where(rec.q[:, 0] < 500, "east", "west")
    pos, rv = p.copy(), rec.rotvec.copy()
    for k, f in FRAMES.items():
        f = f if shift is None else Frame(f.origin + shift, f.rotation)
        s = st == k
        pos[s] = f.to_instrument(p[s])
        rv[s] = so3_log(f.rotation.T @ so3_exp(rec.rotvec[s]))
    role = np.where(np.arange(n) % 3 == 0, "check", "fit")
    return replace(rec, position=pos, rotvec=rv, station=tuple(st), role=tuple(role))


@pytest.fixture(scope="module")
def calibrated(prs3, tmp_path_factory):
    d = tmp_path_factory.mktemp("predict")
    truth = simulate_recording(prs3, 3, seed=7, dof=6).theta_true
    write_recording(d / "cal.csv", _session(prs3, 150, 7, truth))
    write_recording(d / "new.csv", _session(prs3, 90, 8, truth, shift=np.array([30.0, -20.0, 5.0])))
    code = main(["identify", str(d / "cal.csv"), "--machine", str(PRS3_FILE), "--method", "map", "--frame", "fit",
                 "--discrepancy", "auto", "--write-machine", str(d / "m.toml"), "--json", str(d / "id.json"), "--quiet"])
    assert code == 0
    return d


def test_identify_holds_out_check_rows_and_writes_the_discrepancy(calibrated):
    ans = json.loads((calibrated / "id.json").read_text())
    assert ans["n_poses"] == 100  # the 50 check rows were not fitted
    check = ans["check"]
    assert check["summary"]["n"] == 50 and len(check["rows"]) == 50
    assert all(r["role"] == "check" for r in check["rows"])
    assert set(ans["frames"]) == {"east", "west"}
    assert ans["discrepancy"]["kept"] and ans["discrepancy"]["log_evidence_gain"] > 6
    text = (calibrated / "m.toml").read_text()
    assert "[discrepancy]" in text and "[calibration]" in text and "[instrument]" not in text  # stations are the session's
    m = load_machine(calibrated / "m.toml")
    assert m.discrepancy is not None and m.calibration is not None


def test_predict_json_is_the_contract_and_the_library_answer(calibrated):
    out = calibrated / "p.json"
    code = main(["predict", str(calibrated / "new.csv"), "--machine", str(calibrated / "m.toml"), "--frame", "fit",
                 "--json", str(out), "--quiet"])
    assert code == 0
    ans = json.loads(out.read_text())
    assert set(ans["summary"]) == {"check", "fit"}
    s = ans["summary"]["check"]
    for key in ("n", "mean_error_position_mm", "median_error_position_mm", "p95_error_position_mm", "coverage_90"):
        assert key in s
    assert s["n"] == 30 and ans["summary"]["fit"]["n"] == 60
    row = ans["rows"][0]
    for key in ("line", "station", "role", "measured", "predicted", "std", "error_position_mm", "inside_90"):
        assert key in row
    assert row["line"] == 2 and len(row["std"]) == 6
    # the command line is the library's answer
    lib = predict_recording(load_machine(calibrated / "m.toml"), read_recording(calibrated / "new.csv"), frame="fit")
    assert json.loads(json.dumps(lib.to_dict(), default=float)) == ans
    # on a new session of the same machine, with stations moved: an honest region and a small error
    assert 0.75 <= s["coverage_90"] <= 1.0
    assert s["mean_error_position_mm"] < 0.02


def test_rows_that_cannot_be_predicted_say_why(calibrated, tmp_path):
    rec = read_recording(calibrated / "new.csv")
    st = np.array(rec.station, dtype=object)
    role = np.array(rec.role, dtype=object)
    lonely = np.flatnonzero(st == "east")[:4]
    st[lonely] = "ghost"
    role[lonely] = "check"  # a station with no fit rows: its frame cannot be fitted
    write_recording(tmp_path / "r.csv", replace(rec, station=tuple(st), role=tuple(role)))
    out = tmp_path / "p.json"
    assert main(["predict", str(tmp_path / "r.csv"), "--machine", str(calibrated / "m.toml"), "--frame", "fit",
                 "--json", str(out), "--quiet"]) == 0
    ans = json.loads(out.read_text())
    ghost = [r for r in ans["rows"] if r["station"] == "ghost"]
    assert len(ghost) == 4 and all("too few fit rows" in r["error"] for r in ghost)
    assert ans["summary"]["check"]["n_failed"] == 4


def test_predict_refuses_a_calibrated_machine_of_another_kind(calibrated, capsys):
    code = main(["predict", str(calibrated / "new.csv"), "--machine", "examples/arm6/machine.toml", "--quiet"])
    assert code == 2
    assert "error" in capsys.readouterr().err


def test_noise_free_recording_identifies_and_predicts(tmp_path, capsys):
    # a simulated recording without noise: the stated noise is far overstated; the scale found is held at its
    # floor (bayescal.identify.calibrate.MIN_NOISE_SCALE), so the written record stays one predict reads
    prs3 = load_machine(PRS3_FILE)
    truth = np.random.default_rng(4).normal(size=prs3.n_params) * prs3.tolerance * 0.3
    r = simulate_recording(prs3, 40, seed=5, dof=6, theta_true=truth).recording
    exact = prs3.forward(r.q, truth)
    rec = tmp_path / "r.csv"
    write_recording(rec, replace(r, position=exact.position, rotvec=so3_log(exact.rotation)))
    cal, out = tmp_path / "cal.toml", tmp_path / "a.json"
    assert main(["identify", str(rec), "--machine", str(PRS3_FILE), "--write-machine", str(cal),
                 "--json", str(out), "--quiet"]) == 0
    ans = json.loads(out.read_text())
    assert ans["noise"]["verdict"] == "overstated" and ans["noise"]["scale_used"] == pytest.approx(1e-3)
    pout = tmp_path / "p.json"
    assert main(["predict", str(rec), "--machine", str(cal), "--json", str(pout), "--quiet"]) == 0, capsys.readouterr().err
    fit = json.loads(pout.read_text())["summary"]["fit"]
    assert fit["n"] == 40 and fit["mean_error_position_mm"] < 1e-3


@pytest.mark.parametrize("edit, match", [
    (("accel.base.y,", ""), "column(s) accel.base.y missing"),
    (("accel.base.", "accel.nobody."), "no body 'nobody' on this machine"),
    (("accel.base.z", "accel.base.w"), "column(s) accel.base.z missing"),
])
def test_predict_checks_body_sensor_columns_as_identify_does(tmp_path, capsys, edit, match):
    """A probe found predict accepting a sensor without its y column, on a body the machine lacks, or mistyped."""
    from ..conftest import ROOT

    tele = ROOT / "examples" / "telescope"
    lines = (tele / "session_b.csv").read_text().splitlines()
    header = lines[0].split(",")
    if edit[0] == "accel.base.y,":  # drop the column with its cells
        k = header.index("accel.base.y")
        lines = [",".join(c for i, c in enumerate(line.split(",")) if i != k) for line in lines]
    else:
        lines[0] = lines[0].replace(*edit)
    rec = tmp_path / "b.csv"
    rec.write_text("\n".join(lines) + "\n")
    out = tmp_path / "p.json"
    assert main(["predict", str(rec), "--machine", str(tele / "machine.toml"), "--frame", "fit", "--json", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and str(rec) in err[0] and match in err[0], err
    assert not out.exists()
