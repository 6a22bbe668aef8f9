import pytest

from bayescal.errors import MachineFileError
from bayescal.machines.files import load_machine, machine_from_text
from tests.conftest import PRS3_FILE

GOOD = PRS3_FILE.read_text()


@pytest.mark.parametrize(
    "edit,key,match",
    [
        (lambda s: s.replace('kind = "3-PRS"', 'kind = "hexapod"'), "kind", "unknown kind"),
        (lambda s: s.replace("link_length    = 400.0", "link_length    = -400.0", 1), "chain[1].link_length", "positive"),
        (lambda s: s.replace("rail_direction = [0.0, 0.0, 1.0]", "rail_direction = [0.0, 0.0, 2.0]", 1), "chain[1].rail_direction", "unit vector"),
        (lambda s: s.replace("sphere_center  = [150.0, 0.0, 0.0]", "sphere_center  = [150.0, 0.0]", 1), "chain[1].sphere_center", "3 finite numbers"),
        (lambda s: s.replace("point = [0.0, 0.0, -100.0]", "pointt = [0.0, 0.0, -100.0]"), "tool.pointt", "unknown key"),
        (lambda s: s.replace("[450.0, 550.0], [450.0, 550.0], [450.0, 550.0]", "[450.0, 550.0], [550.0, 450.0], [450.0, 550.0]"), "workspace.q_limits", "min < max"),
        (lambda s: s.replace("sigma_position = 0.005", 'sigma_position = "small"'), "measurement.sigma_position", "number"),
        (lambda s: s + "\n[tolerance]\nlink_lenght = 0.01\n", "tolerance.link_lenght", "unknown key"),
        (lambda s: s[: s.rindex("[[chain]]")] + s[s.index("[tool]") :], "chain", "expected 3"),
    ],
)
def test_malformed_machine_files_name_the_key(tmp_path, edit, key, match):
    p = tmp_path / "m.toml"
    p.write_text(edit(GOOD))
    with pytest.raises(MachineFileError, match=match) as err:
        load_machine(p)
    assert err.value.key == key
    assert str(p) in str(err.value)


def test_syntax_error_and_missing_file(tmp_path):
    p = tmp_path / "m.toml"
    p.write_text("kind = \n")
    with pytest.raises(MachineFileError, match="not valid TOML"):
        load_machine(p)
    with pytest.raises(MachineFileError, match="file not found"):
        load_machine(tmp_path / "none.toml")


def test_tolerance_table_overrides_defaults():
    m = machine_from_text(GOOD + "\n[tolerance]\nlink_length = 0.01\n")
    i = m.layout.index("chain2.link_length")
    assert m.tolerance[i] == 0.01
    assert m.tolerance[m.layout.index("chain2.rail_origin.x")] == 0.05


def test_missing_q_limits_is_named(tmp_path):
    p = tmp_path / "m.toml"
    p.write_text(GOOD.replace("q_limits = ", "limits = "))
    with pytest.raises(MachineFileError, match="unknown key"):
        load_machine(p)
    p.write_text(GOOD.split("[workspace]")[0] + "[workspace]\n")
    with pytest.raises(MachineFileError, match="missing; expected 3 lists of 2 numbers") as err:
        load_machine(p)
    assert err.value.key == "workspace.q_limits"


def test_machine_name_with_quotes_and_control_characters_round_trips(prs3):
    from dataclasses import replace

    m = replace(prs3, name='head "A"\\\n\tline\x01')
    assert machine_from_text(m.to_toml()).name == m.name


def test_byte_order_mark_is_read_and_other_encodings_are_named(tmp_path):
    p = tmp_path / "m.toml"
    p.write_bytes(b"\xef\xbb\xbf" + GOOD.encode())
    assert load_machine(p).name == "spindle head A"
    assert machine_from_text("\ufeff" + GOOD).name == "spindle head A"
    p.write_bytes(GOOD.replace("spindle head A", "Spindelkopf M\u00fcller").encode("latin-1"))
    with pytest.raises(MachineFileError, match="not a UTF-8 text file"):
        load_machine(p)


def test_hand_rounded_direction_cosines_are_accepted_and_normalised():
    """Rails leaning 20 degrees, written with 5 significant digits (norm 0.9999975)."""
    import numpy as np

    text = GOOD.replace("rail_direction = [0.0, 0.0, 1.0]", "rail_direction = [0.0, -0.34202, 0.93969]", 1)
    m = machine_from_text(text)
    assert np.linalg.norm(m.rail_direction[0]) == pytest.approx(1.0, abs=1e-15)
    assert np.allclose(m.rail_direction[0], [0.0, -np.sin(np.radians(20)), np.cos(np.radians(20))], atol=1e-5)
    with pytest.raises(MachineFileError, match="unit vector"):
        machine_from_text(GOOD.replace("rail_direction = [0.0, 0.0, 1.0]", "rail_direction = [0.0, 0.05, 1.0]", 1))


def test_top_level_key_written_after_a_table_gets_a_hint():
    with pytest.raises(MachineFileError, match="top-level key: write it before the first") as err:
        machine_from_text(GOOD.replace('name = "spindle head A"\n', "") + '\nname = "head A"\n')
    assert err.value.key.endswith(".name")


@pytest.mark.parametrize(
    "edit,key",
    [
        (lambda s: s.replace("point = [0.0, 0.0, -100.0]", "point = [0.0, 0.0, -1e300]"), "tool.point"),
        (lambda s: s.replace("link_length    = 400.0", "link_length    = 1e300", 1), "chain[1].link_length"),
        (lambda s: s.replace("[[450.0, 550.0], [450.0", "[[-1e300, 1e300], [450.0"), "workspace.q_limits"),
        (lambda s: s + "\n[tolerance]\nlink_length = 1e300\n", "tolerance.link_length"),
        (lambda s: s + "\n[instrument]\norigin = [1e300, 0.0, 0.0]\n", "instrument.origin"),
    ],
)
def test_numbers_beyond_the_file_limit_are_refused(tmp_path, edit, key):
    # 1e300 passed the finite-number check: simulate wrote a recording of x = -1e300 mm, plan divided by zero
    p = tmp_path / "m.toml"
    p.write_text(edit(GOOD))
    with pytest.raises(MachineFileError, match=r"magnitude at most 1e\+09 .*got -?1e\+300") as err:
        load_machine(p)
    assert err.value.key == key and str(p) in str(err.value)


def test_numbers_at_the_file_limit_are_read():
    m = machine_from_text(GOOD + "\n[tolerance]\ntool_point = 1e9\n")
    assert m.tolerance[m.layout.names.index("tool.point.x")] == 1e9
