"""Klipper delta printers: the real FLSUN Q5 config (GPL-3.0, read from ../shared, never copied),
step-to-millimetre conversion, nominal geometry, the README's independent checks, --write-klipper."""

import json
import os
from pathlib import Path

import numpy as np
import pytest

from bayescal.cli import main
from bayescal.constraint_model import ConstraintModel
from bayescal.io.constraints import read_constraints
from bayescal.io.klipper_cfg import KlipperConfigError, parse_klipper_text, read_klipper_config
from bayescal.klipper import klipper_machine, klipper_recording, klipper_text, klipper_values, read_klipper_delta
from bayescal.machines import check_machine, load_machine

# the checkout sits beside shared/ (<clone>/../shared); BAYESCAL_SHARED points elsewhere (a git worktree)
SHARED = Path(os.environ.get("BAYESCAL_SHARED", Path(__file__).resolve().parents[1] / ".." / "shared"))
DATA = SHARED / "data" / "real" / "delta_flsun_q5"
POST = DATA / "printer-post-calibration.cfg"
PRE = DATA / "printer-pre-calibration.cfg"
pytestmark = pytest.mark.skipif(not POST.exists(), reason="../shared/data/real/delta_flsun_q5 not present")


def _saved_calibration_block() -> str:
    text = POST.read_text()
    block = text[text.index("#*# [delta_calibrate]"):]
    return "#*# <---------------------- SAVE_CONFIG ---------------------->\n#*#\n" + block


@pytest.fixture(scope="module")
def post():
    cfg = read_klipper_config(POST)
    return cfg, read_klipper_delta(cfg)


def test_step_distance_and_nominal_geometry(post):
    cfg, kd = post
    np.testing.assert_allclose(kd.step_dist, 40.0 / (200 * 16))  # 0.0125 mm, 80 microsteps per mm
    assert kd.delta_radius == 101.288849
    np.testing.assert_array_equal(kd.angle_deg, [210.481232, 330.925002, 90.0])
    np.testing.assert_array_equal(kd.arm_length, [217.6266, 216.0959, 215.7964])
    np.testing.assert_array_equal(kd.position_endstop, [218.724820, 219.438345, 218.763895])
    rec = klipper_recording(cfg, kd)
    assert rec.measure == ("height",) * 7 + ("distance",) * 12
    np.testing.assert_allclose(rec.qa[0], [-194.55] * 3)  # 15564 microsteps below the endstops
    np.testing.assert_allclose(rec.qa[1], [-20478 * 0.0125, -20478 * 0.0125, -13533.8 * 0.0125])
    np.testing.assert_allclose(rec.qb[7], np.array([15679.602, 20316.269, 20220.941]) * -0.0125)
    np.testing.assert_allclose(rec.value[[0, 7, 18]], [24.374, 64.94, 64.87])
    m = klipper_machine(kd, q_span=rec.qa)
    E = kd.position_endstop + np.sqrt(kd.arm_length**2 - kd.delta_radius**2)
    np.testing.assert_allclose(m.zero, E)
    np.testing.assert_allclose(np.rad2deg(m.angle), kd.angle_deg)
    assert check_machine(m) == []


def test_nominal_printer_maps_stable_positions_back_to_the_probe_points():
    # README check 2: with the nominal parameters (R = 105, L = 216, endstops 219) in force while
    # probing, every height_pos maps back to its probe point within 0.005 mm; nozzle 24.450 at the centre
    text = PRE.read_text().replace("#delta_radius: 105", "delta_radius: 105") + "\n" + _saved_calibration_block()
    cfg = parse_klipper_text(text, "pre+block.cfg")
    kd = read_klipper_delta(cfg)
    rec = klipper_recording(cfg, kd)
    m = klipper_machine(kd, q_span=rec.qa)
    x = m.forward(rec.qa[:7]).position
    r = 100.0 * np.array([0.0, 0.95, 0.90, 0.85, 0.70, 0.75, 0.80])
    ang = np.radians(90.0 + 60.0 * np.r_[0, 0:6])
    probe = np.column_stack([r * np.cos(ang), r * np.sin(ang)])
    assert np.abs(x[:, :2] - probe).max() < 0.005
    assert abs(x[0, 2] - 24.450) < 5e-4
    assert np.all((x[1:, 2] > 22.80) & (x[1:, 2] < 23.13))


def test_residuals_and_klipper_objective_of_the_final_config(post):
    # README check 4: the final cfg gives height RMS 0.068, distance RMS 0.212, objective 0.647657
    cfg, kd = post
    rec = klipper_recording(cfg, kd)
    model = ConstraintModel.from_recording(klipper_machine(kd, q_span=rec.qa), rec)
    res = model.residual(model.predict(None))[:, 0]
    h, d = res[:7], res[7:]
    assert abs(np.sqrt(np.mean(h**2)) - 0.068) < 1e-3  # the README rounds to 3 decimals
    assert abs(np.sqrt(np.mean(d**2)) - 0.212) < 1e-3
    w = 12 / (0.5 * 7)  # Klipper's weight of the heights when distances exist
    assert abs(w * np.sum(h**2) + np.sum(d**2) - 0.647657) < 1e-5


def test_cli_writes_machine_and_recording(tmp_path, capsys):
    assert main(["klipper", str(POST), "--out", str(tmp_path / "k"), "--json", str(tmp_path / "k.json")]) == 0
    summary = json.loads((tmp_path / "k.json").read_text())
    assert summary["step_dist"] == [0.0125] * 3 and summary["n_distances"] == 12
    m = load_machine(tmp_path / "k" / "machine.toml")
    rec = read_constraints(tmp_path / "k" / "recording.csv")
    assert m.kind == "linear-delta" and rec.n_rows == 19
    assert "7 heights, 12 distances" in capsys.readouterr().out
    # the sigmas are guesses that weight heights against distances: no [measurement] table, the noise is not stated
    lines = (tmp_path / "k" / "machine.toml").read_text().splitlines()
    assert not m.noise.given and "[measurement]" not in lines
    ans = tmp_path / "a.json"
    # docs/delta-printers.md's command: 21 parameters from 19 rows under the prior is plausible (effective
    # parameters < rows), the prior scale is estimated (noise not stated), Klipper's keys are written
    assert main(["identify", str(tmp_path / "k" / "recording.csv"), "--machine", str(tmp_path / "k" / "machine.toml"),
                 "--method", "map", "--free", "all", "--json", str(ans), "--write-klipper", str(tmp_path / "k.cfg"),
                 "--quiet"]) == 0
    a = json.loads(ans.read_text())
    assert a["plausible"] and 0.05 <= a["prior_scale"] <= 20
    # the saved geometry is Klipper's fit to these very rows: little left to change, nothing made worse
    assert a["rms_after"]["position"] <= a["rms_before"]["position"] + 1e-9
    assert "[stepper_c]" in (tmp_path / "k.cfg").read_text()
    # least squares over all 21 from 19 rows reproduces any recording: refused as bad input
    assert main(["identify", str(tmp_path / "k" / "recording.csv"), "--machine", str(tmp_path / "k" / "machine.toml"),
                 "--method", "ls", "--free", "all", "--quiet"]) == 2


def test_write_klipper_round_trip(post):
    cfg, kd = post
    rec = klipper_recording(cfg, kd)
    m = klipper_machine(kd, q_span=rec.qa)
    theta = np.zeros(m.n_params)
    names = m.layout.names
    for k, v in {"tower1.angle": 0.004, "tower2.angle": -0.003, "tower1.radius": 0.7, "tower2.radius": 0.7,
                 "tower3.radius": 0.7, "tower1.zero": -0.4, "tower3.zero": 0.9, "tower2.arm_length": 1.1,
                 "tower3.arm_length": -0.6, "tool.point.z": -0.25}.items():
        theta[names.index(k)] = v
    values, notes = klipper_values(m, theta)
    assert notes == []
    back = cfg.merged(parse_klipper_text(klipper_text(m, theta), "snippet.cfg"))
    m2 = klipper_machine(read_klipper_delta(back), q_span=rec.qa)
    q = np.vstack([rec.qa, rec.qb[7:]])
    np.testing.assert_allclose(m2.forward(q).position, m.forward(q, theta).position, atol=1e-9)
    # what Klipper cannot hold is reported, not silently dropped
    theta[names.index("tower1.direction.tilt_x")] = 1e-3
    theta[names.index("tower2.radius")] = 0.2
    theta[names.index("tool.point.x")] = 0.3
    notes = klipper_values(m, theta)[1]
    assert any("tilt" in n for n in notes) and any("radii" in n for n in notes) and any("horizontal" in n for n in notes)


@pytest.mark.parametrize(
    "edit, section, key",
    [
        (lambda t: t, "printer", "delta_radius"),  # the published pre-calibration file has it commented out
        (lambda t: t.replace("#delta_radius: 105", "delta_radius: 105"), "delta_calibrate", "height0"),
        (lambda t: t.replace("#delta_radius: 105", "delta_radius: 105").replace("kinematics: delta", "kinematics: corexy"), "printer", "kinematics"),
        (lambda t: t.replace("#delta_radius: 105", "delta_radius: 105").replace("rotation_distance: 40\nendstop_pin: PA12", "endstop_pin: PA12"), "stepper_b", "rotation_distance"),
        (lambda t: t.replace("#delta_radius: 105", "delta_radius: 105").replace("arm_length: 216.0", "arm_length: 90"), "stepper_a", "arm_length"),
    ],
)
def test_errors_name_section_and_key(edit, section, key):
    cfg = parse_klipper_text(edit(PRE.read_text()), "printer.cfg")
    with pytest.raises(KlipperConfigError) as exc:
        klipper_recording(cfg, read_klipper_delta(cfg))
    assert (exc.value.section, exc.value.key) == (section, key)
    assert f"[{section}] {key}" in str(exc.value) and "printer.cfg" in str(exc.value)


def test_cli_error_exit_2(capsys):
    assert main(["klipper", str(PRE), "--out", "/nonexistent/never"]) == 2
    assert "[printer] delta_radius" in capsys.readouterr().err
