import numpy as np
import pytest

from bayescal.errors import RecordingError
from bayescal.io import read_recording, write_recording
from bayescal.io.recording import recording_to_csv

GOOD = "q1,q2,q3,x,y,z,rx,ry,rz,temp_C\n500,500,500,0,0,29.19,0,0,0,20.5\n480,510,500,1,2,3,0.001,0,0,20.7\n"


def test_reads_six_dof_with_aux():
    rec = read_recording("r.csv", text=GOOD)
    assert rec.dof == 6 and rec.n_poses == 2 and rec.n_actuators == 3
    assert list(rec.aux) == ["temp_C"] and rec.aux["temp_C"][1] == 20.7


def test_round_trip(tmp_path, sim6):
    p = write_recording(tmp_path / "r.csv", sim6.recording)
    back = read_recording(p)
    assert np.allclose(back.q, sim6.recording.q) and np.allclose(back.rotvec, sim6.recording.rotvec)


def test_five_dof_and_position_only():
    rec5 = read_recording("r.csv", text="q1,q2,q3,x,y,z,nx,ny,nz\n1,2,3,0,0,0,0,0,1\n")
    assert rec5.dof == 5
    rec3 = read_recording("r.csv", text="q1,q2,q3,x,y,z\n1,2,3,0,0,0\n")
    assert rec3.dof == 3


@pytest.mark.parametrize(
    "text,line,column,match",
    [
        ("q1,q2,q3,x,y,z\n1,,3,0,0,0\n", 2, "q2", "empty cell"),
        ("q1,q2,q3,x,y,z\n1,2,abc,0,0,0\n", 2, "q3", "expected a number"),
        ("q1,q2,q3,x,y,z\n1,2,3,0,0,nan\n", 2, "z", "finite"),
        ("q1,q2,q3,x,y,z,nx,ny,nz\n1,2,3,0,0,0,0,0,1\n1,2,3,0,0,0,0,0.5,1\n", 3, "nx", "unit vector"),
        ("q1,q2,q3,x,y,x\n1,2,3,0,0,0\n", 1, "x", "duplicate"),
        ("q1,q2,q3,x,y,z,rx,ry\n1,2,3,0,0,0,0,0\n", 1, "rz", "incomplete"),
        ("q1,q3,x,y,z\n1,2,0,0,0\n", 1, None, "missing q2"),
        ("q1,q2,q3,x,y,z\n1,2,3,0,0\n", 2, None, "cells"),
        ("q1,q2,q3,x,y,z\n", 2, None, "no data rows"),
        ("q1,q2,q3,x,y\n1,2,3,0,0\n", 1, "z", "position"),
        ("q1,q2,q3,x,y,z,rx,ry,rz,nx,ny,nz\n1,2,3,0,0,0,0,0,0,0,0,1\n", 1, "nx", "one of them"),
    ],
)
def test_malformed_recordings_name_line_and_column(text, line, column, match):
    with pytest.raises(RecordingError, match=match) as err:
        read_recording("bad.csv", text=text)
    assert err.value.row == line and err.value.column == column
    assert "bad.csv" in str(err.value)
    assert isinstance(err.value, ValueError)


def test_actuator_count_and_limits_checked_against_machine(prs3):
    rec = read_recording("r.csv", text="q1,q2,x,y,z\n500,500,0,0,0\n")
    with pytest.raises(RecordingError, match="expected q1..q3"):
        rec.check_machine(prs3.n_actuators, prs3.q_limits)
    rec = read_recording("r.csv", text="q1,q2,q3,x,y,z\n500,500,500,0,0,0\n500,600,500,0,0,0\n")
    with pytest.raises(RecordingError, match="outside q_limits") as err:
        rec.check_machine(prs3.n_actuators, prs3.q_limits)
    assert err.value.row == 3 and err.value.column == "q2"
    assert "value 600.0 outside q_limits [450.0, 550.0]" in str(err.value)


def test_missing_file():
    with pytest.raises(RecordingError, match="file not found"):
        read_recording("/nonexistent/rec.csv")


def test_csv_text_is_formats_md_columns(sim6):
    header = recording_to_csv(sim6.recording).splitlines()[0]
    assert header == "q1,q2,q3,x,y,z,rx,ry,rz"


def test_written_files_are_readable_like_plain_files(tmp_path, sim6):
    import os
    import stat

    from bayescal.io import write_json_atomic

    plain = tmp_path / "plain.txt"
    plain.write_text("x")
    mode = stat.S_IMODE(os.stat(plain).st_mode)
    for p in (write_recording(tmp_path / "r.csv", sim6.recording), write_json_atomic(tmp_path / "a.json", {"a": 1})):
        assert stat.S_IMODE(os.stat(p).st_mode) == mode
    assert not [f for f in os.listdir(tmp_path) if f.endswith(".tmp")]


def test_written_recording_reads_back_exactly(tmp_path, sim6):
    back = read_recording(write_recording(tmp_path / "r.csv", sim6.recording))
    assert np.array_equal(back.q, sim6.recording.q) and np.array_equal(back.position, sim6.recording.position)
    assert np.array_equal(back.rotvec, sim6.recording.rotvec)


@pytest.mark.parametrize(
    "text",
    [
        "q1,q2,q3,x,y,z\r\n500,501,502,1,2,3\r\n",  # Windows line ends
        "q1,q2,q3,x,y,z\r500,501,502,1,2,3\r",  # old Mac line ends
        "\ufeffq1,q2,q3,x,y,z\n500,501,502,1,2,3\n",  # byte-order mark
        "q1,q2,q3,x,y,z\n500,501,502,1,2,3",  # no final line end
        "z,q3,x,q1,y,q2\n3,502,1,500,2,501\n",  # any column order
        "q1,q2,q3,x,y,z\n5.0E2,+501,5.02e+2,1.,2.0e0,.3e1\n",  # number spellings
    ],
)
def test_spellings_formats_md_allows_read_the_same(text):
    rec = read_recording("r.csv", text=text)
    assert rec.q.tolist() == [[500.0, 501.0, 502.0]] and rec.position.tolist() == [[1.0, 2.0, 3.0]]


@pytest.mark.parametrize(
    "text,line,column,match",
    [
        ("q1,q2,q3,x,y,z\n1_5,2,3,0,0,0\n", 2, "q1", "decimal number"),  # float() would read 15
        ("q1,q2,q3,x,y,z\n\u0661,2,3,0,0,0\n", 2, "q1", "decimal number"),  # an Arabic-Indic one
        ("# recorded 2026-11-22\nq1,q2,q3,x,y,z\n1,2,3,0,0,0\n", 1, None, "comment"),
        ("q1,q2,q3,x,y,z\n1,2,3,0,0,0\n# pause\n1,2,3,0,0,0\n", 3, None, "comment"),
        ("q1,q2,q3,x,y,z\n1,2,3,0,0,0\n\n1,2,3,0,0,0\n", 3, None, "blank line"),
        ('q1,q2,q3,x,y,z\n1,2,"3\n",0,0,0\n1,2,3,0,0,x\n', 2, None, "spans more than one line"),
        ("q1;q2;q3;x;y;z\n1;2;3;0;0;0\n", 1, None, "comma-separated"),
        ("q1,q2,q3,x,y,z\n1,2,3,0,0," + "0" * 200_000 + "\n", 2, None, "not readable as CSV"),  # csv.Error
        ("q1,q2,q3,x,y,z\x00\n1,2,3,0,0,0\n", 1, None, "a NUL byte"),  # the column was named 'z' in the message
        ("q1,q2,q3,x,y,z\r\n1,2,3,0,0,0\r\n1,2,\x003,0,0,0\r\n", 3, None, "a NUL byte"),
        # review: a form feed in a cell counted as a line end (str.splitlines), so the NUL was put on line 4
        ("q1,q2,q3,x,y,z\n1,2,3,0,0,\x0c0\n1,2,\x003,0,0,0\n", 3, None, "a NUL byte"),
        ("q1,q2,q3,x,y,z\r1,2,3,0,0,0\r\x00", 3, None, "a NUL byte"),  # lone \r line ends
    ],
)
def test_what_formats_md_does_not_allow_is_named(text, line, column, match):
    with pytest.raises(RecordingError, match=match) as err:
        read_recording("bad.csv", text=text)
    assert (err.value.row, err.value.column) == (line, column)


def test_lone_cr_file_reads_from_disk(tmp_path):
    p = tmp_path / "r.csv"
    p.write_bytes(b"q1,q2,q3,x,y,z\r500,501,502,1,2,3\r")
    assert read_recording(p).q.tolist() == [[500.0, 501.0, 502.0]]


def test_unit_suffixes_are_converted_to_mm_and_rad():
    """docs/formats.md: mm and rad 'unless a column name says otherwise (_deg, _um)'."""
    text = "q1_um,q2,q3_mm,x_um,y,z,rx_deg,ry_rad,rz,temp_C\n500000,501,502,1500,2,3,90,0.5,0.25,21\n"
    rec = read_recording("r.csv", text=text)
    assert rec.dof == 6 and list(rec.aux) == ["temp_C"]  # not silently three more aux channels
    assert rec.q.tolist() == [[500.0, 501.0, 502.0]] and rec.position.tolist() == [[1.5, 2.0, 3.0]]
    assert np.allclose(rec.rotvec, [[np.pi / 2, 0.5, 0.25]])
    assert rec.q_columns == ("q1_um", "q2", "q3_mm") and rec.q_units == ("mm", "", "mm")
    again = read_recording("r.csv", text=recording_to_csv(rec))  # written in mm and rad, plain names
    assert np.array_equal(again.q, rec.q) and np.array_equal(again.rotvec, rec.rotvec)


@pytest.mark.parametrize(
    "header,column,match",
    [
        ("q1,q2,q3,x,y,z,x_um", "x_um", "same quantity as column 'x'"),
        ("q1,q2,q3,x_deg,y,z,w", "x_deg", "is a length"),
        ("q1,q2,q3,x,y,z,rx_um,ry,rz", "rx_um", "is an angle"),
        ("q1,q2,q3,x,y,z,nx_rad,ny,nz", "nx_rad", "unit vector"),
    ],
)
def test_unit_suffixes_that_make_no_sense_are_named(header, column, match):
    text = header + "\n" + ",".join(["0"] * len(header.split(","))) + "\n"
    with pytest.raises(RecordingError, match=match) as err:
        read_recording("bad.csv", text=text)
    assert (err.value.row, err.value.column) == (1, column)


def test_angle_column_for_a_prismatic_actuator_and_limits_name_the_file_column(prs3):
    rec = read_recording("r.csv", text="q1_deg,q2,q3,x,y,z\n500,500,500,0,0,0\n")
    with pytest.raises(RecordingError, match="prismatic") as err:
        rec.check_machine(3, prs3.q_limits, actuator_units=prs3.actuator_units)
    assert err.value.column == "q1_deg"
    rec = read_recording("r.csv", text="q1,q2_um,q3,x,y,z\n500,600000,500,0,0,0\n")
    with pytest.raises(RecordingError, match="600.0 outside") as err:
        rec.check_machine(3, prs3.q_limits, actuator_units=prs3.actuator_units)
    assert err.value.column == "q2_um"
    from bayescal.measurement import MeasurementModel

    rec = read_recording("r.csv", text="q1_rad,q2,q3,x,y,z\n500,500,500,0,0,0\n")
    with pytest.raises(RecordingError, match="revolute|prismatic"):
        MeasurementModel.from_recording(prs3, rec)


@pytest.mark.parametrize(
    "text,column,found",
    [("Q1,Q2,Q3,x,y,z\n1,2,3,0,0,0\n", None, "'Q1'"), ("q1,q2,q3,X,Y,Z\n1,2,3,0,0,0\n", "x", "'X'")],
)
def test_upper_case_names_get_a_hint(text, column, found):
    with pytest.raises(RecordingError, match="case-sensitive: found " + found) as err:
        read_recording("bad.csv", text=text)
    assert err.value.column == column


H = "q1,q2,q3,x,y,z"


@pytest.mark.parametrize("extra, cells, line, column, match", [
    ("payload_kg", ["5", "0", "-2", "4"], 4, "payload_kg", r"-2 is below 0; expected a payload mass in kg >= 0"),
    ("time_s", ["-1", "30", "60", "90"], 2, "time_s", r"-1 is below 0; expected an elapsed time in s >= 0"),
    ("temp_C", ["20", "-300", "21", "22"], 3, "temp_C", r"below -273.15"),
    # a payload of 1e300 kg passed, and diagnose and plan --separate died in an eigenvalue solver (issue 30 probe)
    ("payload_kg", ["5", "1e300", "1e5", "0"], 3, "payload_kg", r"1e\+300 is above 100000; expected a payload mass in kg "
                                                              r"from 0 to 100000"),
    ("temp_C", ["20", "21", "5000", "22"], 4, "temp_C", r"5000 is above 1000"),
    ("time_s", ["0", "30", "60", "45"], 5, "time_s", r"time goes backwards: 45 s after 60 s on line 4; expected the rows "
                                                      r"in the order they were measured"),
])
def test_channels_the_contract_gives_a_meaning_refuse_what_they_cannot_hold(extra, cells, line, column, match):
    """A negative payload or elapsed time, and time that falls down the rows (rows are in measured order, section 2)."""
    text = f"{H},{extra}\n" + "".join(f"1,2,3,4,5,6,{c}\n" for c in cells)
    with pytest.raises(RecordingError, match=match) as err:
        read_recording("r.csv", text=text)
    assert (err.value.row, err.value.column) == (line, column)


def test_time_runs_per_station_and_may_stand_still():
    text = (f"{H},time_s,station\n1,2,3,4,5,6,0,a\n1,2,3,4,5,6,100,a\n1,2,3,4,5,6,0,b\n1,2,3,4,5,6,100,a\n"
            "1,2,3,4,5,6,50,b\n")
    rec = read_recording("r.csv", text=text)  # each station its own clock (another day's session)
    assert rec.aux["time_s"].tolist() == [0, 100, 0, 100, 50]
    with pytest.raises(RecordingError, match="50 s after 100 s on line 5; expected the rows of station 'a'") as err:
        read_recording("r.csv", text=text.replace("1,2,3,4,5,6,50,b", "1,2,3,4,5,6,50,a"))
    assert (err.value.row, err.value.column) == (6, "time_s")
    # other channels take any finite value: the contract gives them no meaning
    assert read_recording("r.csv", text=f"{H},pose_id,strain\n1,2,3,4,5,6,-3,-1e3\n").aux["pose_id"][0] == -3


def test_the_channel_bounds_hold_at_their_ends_and_for_grid_aux():
    from bayescal.effects.stored import parse_aux_values
    from bayescal.errors import InputError

    rec = read_recording("r.csv", text=f"{H},payload_kg,temp_C\n1,2,3,4,5,6,1e5,1000\n1,2,3,4,5,6,0,-273.15\n")
    assert rec.aux["payload_kg"].tolist() == [1e5, 0.0]
    assert parse_aux_values(["payload_kg=1e5"]) == {"payload_kg": 1e5}
    with pytest.raises(InputError, match="expected payload_kg from 0 to 100000"):
        parse_aux_values(["payload_kg=1e300"])
