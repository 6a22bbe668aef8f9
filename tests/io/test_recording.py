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
