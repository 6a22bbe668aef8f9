"""Klipper delta printers: the real FLSUN Q5 config (GPL-3.0, read from ../shared, never copied; those tests
skip without it), step-to-millimetre conversion, nominal geometry, the README's independent checks; and a
synthetic config: the saved measurements against closed-form stable positions, refusals of incomplete or
absurd saved data."""

import json
import os
from pathlib import Path

import numpy as np
import pytest

from bayescal.cli import main
from bayescal.constraints.model import ConstraintModel
from bayescal.io.constraints import read_constraints
from bayescal.klipper.cfg import AUTOSAVE_HEADER, KlipperConfigError, parse_klipper_text, read_klipper_config
from bayescal.klipper import klipper_machine, klipper_recording, read_klipper_delta
from bayescal.machines.check import check_machine
from bayescal.machines.files import load_machine
from tests import klipper_configs as synth

# the checkout sits beside shared/ (<clone>/../shared); BAYESCAL_SHARED points elsewhere (a git worktree)
SHARED = Path(os.environ.get("BAYESCAL_SHARED", Path(__file__).resolve().parents[2] / ".." / "shared"))
DATA = SHARED / "data" / "real" / "delta_flsun_q5"
POST = DATA / "printer-post-calibration.cfg"
PRE = DATA / "printer-pre-calibration.cfg"
q5 = pytest.mark.skipif(not POST.exists(), reason="../shared/data/real/delta_flsun_q5 not present")


def _saved_calibration_block() -> str:
    """The FLSUN Q5's saved measurements alone, under Klipper's SAVE_CONFIG header."""
    text = POST.read_text()
    return "\n" + AUTOSAVE_HEADER + text[text.index("#*# [delta_calibrate]"):]


@pytest.fixture(scope="module")
def post():
    cfg = read_klipper_config(POST, missing_includes="skip")  # its fluidd.cfg did not travel with it
    return cfg, read_klipper_delta(cfg)


@q5
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


@q5
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


@q5
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


@q5
def test_cli_writes_machine_and_recording(tmp_path, capsys):
    assert main(["klipper", str(POST), "--out", str(tmp_path / "k"), "--json", str(tmp_path / "k.json"),
                 "--skip-missing-includes"]) == 0
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


@q5
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


@q5
def test_cli_error_exit_2(capsys):
    assert main(["klipper", str(PRE), "--out", "/nonexistent/never", "--skip-missing-includes"]) == 2
    assert "[printer] delta_radius" in capsys.readouterr().err


# ---------------------------------------------------------------- a synthetic config (no ../shared data needed)
def test_saved_measurements_of_a_synthetic_config_match_closed_form_positions(tmp_path):
    cfg = read_klipper_config(synth.write_config(tmp_path))
    kd = read_klipper_delta(cfg)
    rec = klipper_recording(cfg, kd)
    assert rec.measure == ("height",) * 8 + ("distance",) * 6
    np.testing.assert_array_equal(rec.aux["klipper_manual"], [1] + [0] * 13)
    np.testing.assert_array_equal(rec.aux["klipper_index"], [0, 0, 1, 2, 3, 4, 5, 6, 0, 1, 2, 3, 4, 5])
    # Klipper's stable positions (written with 3 decimals: 6e-6 mm of carriage) map back to the nozzle points
    m = klipper_machine(kd, q_span=np.vstack([rec.qa, rec.qb[8:]]))
    pts = np.vstack([synth.MANUAL, synth.probe_points()])
    np.testing.assert_allclose(m.forward(rec.qa[:8]).position, pts, atol=1e-4)
    np.testing.assert_allclose(rec.value[:8], pts[:, 2])
    a, b = synth.distance_pairs()
    np.testing.assert_allclose(m.forward(rec.qa[8:]).position, a, atol=1e-4)
    np.testing.assert_allclose(m.forward(rec.qb[8:]).position, b, atol=1e-4)
    np.testing.assert_allclose(rec.value[8:], np.linalg.norm(b - a, axis=1), atol=5e-4)


def _edited(tmp_path, edit):
    lines = synth.calibration_block()
    return read_klipper_config(synth.write_config(tmp_path, block=edit(lines)))


def _drop(key):
    return lambda lines: [ln for ln in lines if not ln.startswith(f"{key} =")]


def _set(key, value):
    return lambda lines: [f"{key} = {value}" if ln.startswith(f"{key} =") else ln for ln in lines]


@pytest.mark.parametrize("edit, key, words", [
    (_drop("height3"), "height3", "missing, but height6 is present"),
    (lambda lines: [ln for ln in lines if not ln.startswith(tuple(f"height{i}" for i in range(2, 7)))], "height2",
     "at least 3 points"),
    (_drop("distance1"), "distance1", "without gaps"),
    (_drop("height2_pos"), "height2_pos", "missing; expected 3 stable positions with height2"),
    (_drop("distance4_pos2"), "distance4_pos2", "missing"),
    (lambda lines: lines + ["height7_pos = 1,2,3"], "height7_pos", "present without height7"),
    (lambda lines: lines + ["height01 = 1"], "height01", "not a key SAVE_CONFIG writes"),
    (lambda lines: lines + ["height999 = 1"], "height999", "below 999"),
    pytest.param(lambda lines: lines + ["height" + "9" * 5000 + " = 1"], "height" + "9" * 5000, "not a key",
                 id="no-int-of-5000-digits"),
    (lambda lines: lines + ["height2_pos1 = 1,2,3"], "height2_pos1", "not a key SAVE_CONFIG writes"),
    (_set("height1_pos", "nan,20000,20000"), "height1_pos", "finite"),
    (_set("height1_pos", "1e300,20000,20000"), "height1_pos", "within the carriages' travel"),
    (_set("height1_pos", "-1e6,20000,20000"), "height1_pos", "within the carriages' travel"),
    (_set("height1_pos", "20000,20000"), "height1_pos", "3 comma-separated numbers"),
    (_set("height1_pos", "inf,1,1"), "height1_pos", "finite"),
    (_set("height1", "1e300"), "height1", "expected a number from"),
    (_set("height1", "nan"), "height1", "finite"),
    (_set("distance0", "0"), "distance0", "above 0"),
    (_set("distance0", "1e6"), "distance0", "at most"),
    (_set("delta_radius", "nan"), "delta_radius", "finite"),
    (_set("arm_length", "1e300"), "arm_length", "at most 10000"),
    (_set("arm_length", "90"), "arm_length", "above 100.123"),
    (_set("angle", "1e9"), "angle", "from -720 to 720"),
    (_set("position_endstop", "-inf"), "position_endstop", "finite"),
])
def test_incomplete_or_absurd_saved_data_is_refused_with_the_key(tmp_path, edit, key, words):
    cfg = _edited(tmp_path, edit)
    with pytest.raises(KlipperConfigError) as exc:
        klipper_recording(cfg, read_klipper_delta(cfg))
    msg = str(exc.value)
    assert exc.value.key == key and words in msg and "\n" not in msg
    # placed at the line that set the key (or, for a missing key, the line of its neighbour), in the block
    assert "(SAVE_CONFIG block)" in msg and exc.value.line is not None
    line = (tmp_path / "printer.cfg").read_text().split("\n")[exc.value.line - 1]
    assert line.startswith("#*# ")


@pytest.mark.parametrize("section, key, value, words", [
    ("stepper_a", "microsteps", "16.5", "whole number"),
    ("stepper_b", "rotation_distance", "0", "above 0"),
    ("stepper_b", "gear_ratio", "0:20", "positive finite ratios"),
    ("printer", "print_radius", "1e12", "at most"),
    ("printer", "minimum_z_position", "300", "at most the lowest position_endstop"),
])
def test_absurd_regular_values_are_refused_at_their_file_and_line(tmp_path, section, key, value, words):
    path = synth.write_config(tmp_path)
    steppers = tmp_path / "steppers.cfg"
    target = steppers if section.startswith("stepper") else path
    # a repeated section at the end of the regular text: its value is the one Klipper uses
    text, at = target.read_text(), "\n" + AUTOSAVE_HEADER
    extra = f"\n[{section}]\n{key}: {value}\n"
    target.write_text(text.replace(at, extra + at) if at in text else text + extra)
    cfg = read_klipper_config(path)
    with pytest.raises(KlipperConfigError) as exc:
        read_klipper_delta(cfg)
    assert (exc.value.section, exc.value.key) == (section, key) and words in str(exc.value)
    assert exc.value.path == str(target) and target.read_text().split("\n")[exc.value.line - 1] == f"{key}: {value}"


def test_cli_refuses_a_block_with_a_gap_in_one_line(tmp_path, capsys):
    path = synth.write_config(tmp_path, block=_drop("height3")(synth.calibration_block()))
    assert main(["klipper", str(path), "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "[delta_calibrate] height3: missing, but height6 is present" in err
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("kw", [{"sigma_height": 1e300}, {"sigma_distance": 1e-300}])
def test_row_sigmas_outside_the_noise_range_are_refused(tmp_path, kw):
    # --sigma-distance 1e300 was written into the recording, which identify then refused
    from bayescal.errors import InputError

    cfg = read_klipper_config(synth.write_config(tmp_path))
    with pytest.raises(InputError, match=r"sigma_(height|distance) \(--sigma-(height|distance)\): expected a one-sigma "
                       r"position noise from 1e-06 to 1000 mm"):
        klipper_recording(cfg, read_klipper_delta(cfg), **kw)
