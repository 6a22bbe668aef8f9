"""Klipper configs read as Klipper reads them: every section SAVE_CONFIG writes (multi-line bed meshes and
calibration tables), includes, comments, the block's precedence rules; and a fuzz of the reader."""

from __future__ import annotations

from datetime import timedelta
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from bayescal.errors import BayescalError
from bayescal.klipper.cfg import AUTOSAVE_HEADER, KlipperConfigError, parse_klipper_text, read_klipper_config
from bayescal.klipper import klipper_recording, read_klipper_delta
from tests.klipper_configs import MAIN, saved_block, write_config


@pytest.fixture
def synthetic(tmp_path):
    return read_klipper_config(write_config(tmp_path / "printer"))


def test_every_saved_section_and_the_includes_are_read(synthetic):
    cfg = synthetic
    # the multi-line bed mesh of the SAVE_CONFIG block (Klipper writes continuation lines indented by a tab)
    rows = [[float(v) for v in line.split(",")] for line in cfg.sections["bed_mesh default"]["points"].strip().split("\n")]
    np.testing.assert_array_equal(rows, [[0.0125, -0.025, 0.0], [0.05, 0.0375, -0.0125], [-0.005, 0.0, 0.0225]])
    assert cfg.sections["bed_mesh hot"]["points"].split("\n")[1:] == ["0.1, 0.2", "0.3, 0.4"]
    assert cfg.sections["probe_eddy_current eddy"]["calibrate"].count("\n") == 2
    assert cfg.sections["angle my_angle"]["calibrate"].endswith("9.0,10.0")
    assert cfg.sections["temperature_probe my_probe"]["drift_calibration"].split("\n")[1:] == ["1.0, 2.0, 3.0", "4.0, 5.0, 6.0"]
    for sec, key, value in [("input_shaper", "shaper_freq_y", "48.0"), ("endstop_phase stepper_a", "trigger_phase", "23/64"),
                            ("skew_correction my_skew", "xy_skew", "0.0012"), ("extruder", "pid_kd", "114.000"),
                            ("axis_twist_compensation", "compensation_end_x", "60.0"), ("bed_tilt", "z_adjust", "0.010000"),
                            ("probe", "z_offset", "1.234"), ("probe", "pin", "PA11")]:
        assert cfg.sections[sec][key] == value, (sec, key)
    # comments: '#' anywhere, ';' at the start or after a space; a macro's indented lines are one value
    assert cfg.sections["printer"]["kinematics"] == "delta" and cfg.sections["printer"]["max_velocity"] == "300"
    assert cfg.sections["gcode_macro START_PRINT"]["gcode"].split("\n")[1:3] == ["G28", "G1 Z10 F3000"]
    # includes: a glob (sorted), a file that includes another, relative to the including file
    assert [p.split("printer/")[1] for p in cfg.files] == [
        "printer.cfg", "macros/a.cfg", "macros/b.cfg", "steppers.cfg", "more/tmc.cfg"]
    assert cfg.sections["tmc2209 stepper_a"]["run_current"] == "0.8" and cfg.sections["stepper_b"]["gear_ratio"] == "80:20"
    assert "gcode_macro A" in cfg.sections and cfg.missing_includes == () and cfg.notes() == []
    # where keys were set: file and line, in the block or not
    o = cfg.where("printer", "delta_radius")
    assert o.in_block and o.path.endswith("printer.cfg") and cfg.where("stepper_c", "microsteps").path.endswith("steppers.cfg")
    assert Path(cfg.path).read_text().split("\n")[o.line - 1] == "#*# delta_radius = 100.123456"
    kd = read_klipper_delta(cfg)
    np.testing.assert_allclose(kd.step_dist, 0.0125)  # rotation_distance 40/(200*16), 160/(200*16*4), 40/(400*8)
    assert kd.delta_radius == 100.123456 and kd.minimum_z == -5.0 and kd.print_radius == 90.0


def test_a_key_above_the_block_wins_over_the_block(tmp_path):
    # Klipper drops the block's copy of a key the sections above set, with its continuation lines
    main = MAIN.replace("#z_offset: 1.0", "z_offset: 1.0") + "\n[bed_mesh default]\npoints: 1, 2\n"
    cfg = read_klipper_config(write_config(tmp_path, main=main))
    assert cfg.sections["probe"]["z_offset"] == "1.0" and cfg.saved["probe"]["z_offset"] == "1.234"
    assert cfg.sections["bed_mesh default"]["points"] == "1, 2"
    assert cfg.sections["bed_mesh default"]["x_count"] == "3"  # the block's other keys are kept
    assert not cfg.where("probe", "z_offset").in_block


def test_crlf_line_ends_and_a_byte_order_mark(tmp_path):
    path = write_config(tmp_path)
    text = path.read_text()
    path.write_bytes(b"\xef\xbb\xbf" + text.replace("\n", "\r\n").encode())
    cfg = read_klipper_config(path)
    assert cfg.sections["bed_mesh default"]["points"].count("\n") == 3 and cfg.sections["printer"]["delta_radius"] == "100.123456"


@pytest.mark.parametrize("edit, why", [
    (lambda t: t.replace("#*# [probe]", "[probe]"), "does not start with '#*# '"),
    (lambda t: t.replace("#*# DO NOT EDIT THIS BLOCK OR BELOW.", "#*# do not edit"), "no SAVE_CONFIG header"),
    (lambda t: t.replace("[include steppers.cfg]", "#*# x\n[include steppers.cfg]"), "above the SAVE_CONFIG header"),
])
def test_an_edited_block_is_ignored_as_klipper_does_and_the_error_says_so(tmp_path, edit, why):
    path = write_config(tmp_path)
    path.write_text(edit(path.read_text()))
    cfg = read_klipper_config(path)
    assert cfg.saved == {} and "delta_radius" not in cfg.sections["printer"]
    with pytest.raises(KlipperConfigError) as exc:
        read_klipper_delta(cfg)
    assert "[printer] delta_radius: missing" in str(exc.value) and why in str(exc.value)
    assert any(why in n for n in cfg.notes())


def test_a_missing_key_names_the_include_it_may_come_from(tmp_path):
    (tmp_path / "printer.cfg").write_text("[include ui.cfg]\n[printer]\nkinematics: delta\n")
    cfg = read_klipper_config(tmp_path / "printer.cfg", missing_includes="skip")
    with pytest.raises(KlipperConfigError) as exc:
        read_klipper_delta(cfg)
    msg = str(exc.value)
    assert (exc.value.section, exc.value.key) == ("printer", "delta_radius")
    assert "ui.cfg" in msg and "line 1" in msg and "\n" not in msg
    assert cfg.notes() and "ui.cfg not found" in cfg.notes()[0]


def test_parse_errors_name_the_file_and_line_of_an_include(tmp_path):
    (tmp_path / "printer.cfg").write_text("[printer]\nkinematics: delta\n[include part.cfg]\n")
    (tmp_path / "part.cfg").write_text("[x]\na: 1\nthis line has no delimiter\n")
    with pytest.raises(KlipperConfigError) as exc:
        read_klipper_config(tmp_path / "printer.cfg")
    assert str(exc.value).startswith(f"{tmp_path / 'part.cfg'} line 3: not a Klipper config line")
    # keys after an include need their section again (Klipper parses the text between includes as a unit)
    (tmp_path / "printer.cfg").write_text("# top\n[printer]\n[include part2.cfg]\nkinematics: delta\n")
    (tmp_path / "part2.cfg").write_text("[y]\n")
    with pytest.raises(KlipperConfigError, match=r"printer.cfg line 4: a key before any \[section\]"):
        read_klipper_config(tmp_path / "printer.cfg")


def test_block_errors_are_placed_in_the_block():
    text = "[printer]\nkinematics: delta\n" + saved_block(["[printer]", "delta_radius = 1", "no delimiter here"])
    with pytest.raises(KlipperConfigError) as exc:
        parse_klipper_text(text, "p.cfg")
    assert str(exc.value).startswith("p.cfg line 9 (SAVE_CONFIG block): not a Klipper config line")


def test_the_header_is_klippers_three_lines():
    assert AUTOSAVE_HEADER.splitlines() == [
        "#*# <---------------------- SAVE_CONFIG ---------------------->",
        "#*# DO NOT EDIT THIS BLOCK OR BELOW. The contents are auto-generated.", "#*#"]


# ---------------------------------------------------------------- fuzz
_TOKENS = ["[printer]", "[stepper_a]", "[delta_calibrate]", "[include x.cfg]", "[include *.cfg]", "[include ]", "[DEFAULT]",
           "kinematics: delta", "delta_radius = 100", "arm_length: 215", "height0 = 1", "height0_pos = 1,2,3",
           "height2 = nan", "distance0 = 1e300", "  continued", "\tvalue", "#*# ", "#*#", AUTOSAVE_HEADER, "; c", "# c",
           "=", ":", "[", "]", "key", "a = b ; c", "é", "\x00", "\r", "\ufeff", "[include ../x.cfg]",
           "height00 = 1", "[include nope.cfg]", "[include nope/*.cfg]", "height" + "7" * 4400 + "_pos = 1,2,3", "gear_ratio: 1:0", "microsteps: 1e400"]


@settings(max_examples=60, deadline=timedelta(seconds=5), derandomize=True, suppress_health_check=[HealthCheck.too_slow])
@given(st.lists(st.one_of(st.sampled_from(_TOKENS), st.text(max_size=12)), max_size=25))
def test_fuzz_lines_end_in_a_config_or_a_bayescal_error(tmp_path_factory, parts):
    folder = tmp_path_factory.getbasetemp() / "fuzz_lines"
    folder.mkdir(exist_ok=True)
    (folder / "x.cfg").write_text("[stepper_b]\nangle: 1\n[include x.cfg]\n")  # a cycle if followed
    try:
        cfg = parse_klipper_text("\n".join(parts), str(folder / "p.cfg"), base_dir=folder)
        klipper_recording(cfg, read_klipper_delta(cfg))
    except BayescalError:
        pass


@settings(max_examples=40, deadline=timedelta(seconds=5), derandomize=True)
@given(st.binary(max_size=300))
def test_fuzz_bytes_end_in_a_config_or_a_bayescal_error(tmp_path_factory, data):
    path = tmp_path_factory.getbasetemp() / "fuzz_bytes.cfg"
    path.write_bytes(data)
    try:
        read_klipper_config(path)
    except BayescalError:
        pass
