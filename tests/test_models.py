"""read_any_recording: the recording kind from the header, the same for a file and for its content, and the
reader of that kind's errors (file, line, column) passed on unchanged."""

from __future__ import annotations

import pytest

from bayescal.errors import RecordingError
from bayescal.io import Recording
from bayescal.io.constraints import ConstraintRecording
from bayescal.models import read_any_recording

CASES = {
    "pose.csv": ("q1,q2,q3,x,y,z\n1,2,3,4,5,6\n", Recording),
    "cons.csv": ("measure,a_q1,a_q2,a_q3,value\nheight,1,2,3,4\n", ConstraintRecording),
    "bom.csv": ("\ufeffmeasure,a_q1,a_q2,a_q3,value\nheight,1,2,3,4\n", ConstraintRecording),
    "crlf.csv": ("a_q1,a_q2,a_q3,value, measure \r\n1,2,3,4,height\r\n", ConstraintRecording),
    # a quoted header cell: the content used to be sniffed by splitting at commas and was taken for poses
    "quoted.csv": ('"measure",a_q1,a_q2,a_q3,value\nheight,1,2,3,4\n', ConstraintRecording),
}


@pytest.mark.parametrize("name", sorted(CASES))
def test_file_and_content_give_the_same_kind(tmp_path, name):
    text, kind = CASES[name]
    p = tmp_path / name
    p.write_text(text, encoding="utf-8", newline="")
    from_file = read_any_recording(p)
    from_text = read_any_recording(p, text=text)
    assert type(from_file) is kind and type(from_text) is kind
    assert from_file.n_poses == from_text.n_poses == 1


@pytest.mark.parametrize("text, where", [
    # the constraint reader's message: file, line 2, column measure, what was expected
    ("measure,a_q1,value\nlength,1,4\n", "line 2, column 'measure': expected one of distance, height, ballbar, got 'length'"),
    # the pose reader's: file, line 1, column x
    ("q1,q2\n1,2\n", "line 1, column 'x': missing measured position column; expected x, y, z"),
    ("", "line 1: empty file; expected a header row"),
])
def test_errors_name_file_line_and_column(tmp_path, text, where):
    p = tmp_path / "bad.csv"
    p.write_text(text, encoding="utf-8", newline="")
    for kw in ({}, {"text": text}):
        with pytest.raises(RecordingError) as err:
            read_any_recording(p, **kw)
        assert str(err.value) == f"{p}: {where}"


def test_missing_file_is_named(tmp_path):
    with pytest.raises(RecordingError, match="missing.csv: file not found; expected a recording"):
        read_any_recording(tmp_path / "missing.csv")
