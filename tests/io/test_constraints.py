"""Constraint recordings (docs/formats.md section 6): strict reading, errors naming line and column, round trip."""

import numpy as np
import pytest

from bayescal.errors import RecordingError
from bayescal.io.constraints import (
    ConstraintRecording, constraints_to_csv, is_constraint_recording, read_constraints, write_constraints,
)

GOOD = """measure,a_q1,a_q2,a_q3,b_q1,b_q2,b_q3,value,pivot,sigma_position,temp_C
distance,1,2,3,4,5,6,65.0,,0.05,20.5
height,1,2,3,,,,24.3,,0.02,20.6
ballbar,1,2,3,,,,100.0,p1,0.001,20.7
ballbar,1,2,4,,,,100.0,p2,0.001,20.7
"""


def test_reads_every_measure_and_column():
    rec = read_constraints("c.csv", text=GOOD)
    assert rec.measure == ("distance", "height", "ballbar", "ballbar")
    np.testing.assert_array_equal(rec.qa[0], [1, 2, 3])
    np.testing.assert_array_equal(rec.qb[0], [4, 5, 6])
    assert np.isnan(rec.qb[1:]).all()
    np.testing.assert_array_equal(rec.value, [65.0, 24.3, 100.0, 100.0])
    assert rec.pivot == ("", "", "p1", "p2") and rec.pivot_ids == ("p1", "p2")
    np.testing.assert_array_equal(rec.sigma, [0.05, 0.02, 0.001, 0.001])
    assert list(rec.aux) == ["temp_C"]


def test_minimal_file_and_default_pivot(tmp_path):
    text = "measure,a_q1,a_q2,a_q3,value\nheight,1,2,3,0.5\nballbar,1,2,3,50\n"
    rec = read_constraints("c.csv", text=text)
    assert rec.pivot == ("", "1") and rec.sigma is None
    p = tmp_path / "c.csv"
    p.write_text(text)
    assert is_constraint_recording(p)
    p2 = tmp_path / "r.csv"
    p2.write_text("q1,q2,q3,x,y,z\n1,2,3,4,5,6\n")
    assert not is_constraint_recording(p2)



@pytest.mark.parametrize("text, constraint", [
    ("measure,a_q1,value\nheight,1,2\n", True),
    ("\ufeffmeasure,a_q1,value\nheight,1,2\n", True),  # a byte-order mark
    ("a_q1,value, measure \r\n1,2,height\r\n", True),  # spaces around the name, CRLF
    ("measure,a_q1,value\rheight,1,2\r", True),  # lone CR line ends
    ('"measure",a_q1,value\nheight,1,2\n', True),  # a quoted header cell, as CSV writers may quote
    ("q1,q2,q3,x,y,z\n1,2,3,4,5,6\n", False),
    ("q1,x\nmeasure,1\n", False),  # only the header counts
    ("measured,a_q1\n", False),
    ("", False),
])
def test_sniffing_a_file_and_its_content_agree(tmp_path, text, constraint):
    p = tmp_path / "r.csv"
    p.write_text(text, encoding="utf-8", newline="")
    assert is_constraint_recording(p) is constraint
    assert is_constraint_recording("ignored.csv", text=text) is constraint
    assert not is_constraint_recording(tmp_path / "missing.csv")  # the reader then says the file is missing

def test_round_trip(tmp_path):
    rec = read_constraints("c.csv", text=GOOD)
    path = write_constraints(tmp_path / "out.csv", rec)
    back = read_constraints(path)
    assert back.measure == rec.measure and back.pivot == rec.pivot
    for a, b in ((back.qa, rec.qa), (back.qb, rec.qb), (back.value, rec.value), (back.sigma, rec.sigma), (back.aux["temp_C"], rec.aux["temp_C"])):
        np.testing.assert_array_equal(a, b)
    assert constraints_to_csv(back) == constraints_to_csv(rec)


@pytest.mark.parametrize(
    "text, line, column, words",
    [
        ("a_q1,a_q2,value\n1,2,3\n", 1, "measure", "missing column"),
        ("measure,a_q1,a_q3,value\nheight,1,2,3\n", 1, None, "missing a_q2"),
        ("measure,a_q1,value\nlength,1,3\n", 2, "measure", "distance, height, ballbar"),
        ("measure,a_q1,value\nheight,x,3\n", 2, "a_q1", "expected a number"),
        ("measure,a_q1,value\ndistance,1,3\n", 1, "b_q1", "no b_q1"),
        ("measure,a_q1,b_q1,value\nheight,1,2,3\n", 2, "b_q1", "expected an empty cell"),
        ("measure,a_q1,b_q1,value\ndistance,1,,3\n", 2, "b_q1", "empty cell"),
        ("measure,a_q1,b_q1,value\ndistance,1,2,-3\n", 2, "value", "must be positive"),
        ("measure,a_q1,value,pivot\nballbar,1,3,a b\n", 2, "pivot", "pivot id"),
        ("measure,a_q1,value,pivot\nheight,1,3,p\n", 2, "pivot", "expected an empty cell"),
        ("measure,a_q1,value,sigma_position\nheight,1,3,0\n", 2, "sigma_position", "positive"),
        ("measure,a_q1,a_q2,b_q1,value\nheight,1,2,,3\n", 1, None, "as many b as a"),
        ("measure,a_q1,value\n", 2, None, "no data rows"),
        ("measure,a_q1,value\nheight,1\n", 2, None, "cells"),
        # issue 30 probe: 1e300 ran into an infinite noise estimate; a distance of a pose to itself; labels read as numbers
        ("measure,a_q1,value\nheight,1,1e300\n", 2, "value", "expected a length within +-1e+09 mm"),
        ("measure,a_q1,b_q1,value\ndistance,1,1,64.9\n", 2, "b_q1", "pose a and the same pose b"),
        ("measure,a_q1,value,role\nheight,1,3,check\n", 1, "role", "read in pose recordings only"),
        ("measure,a_q1,value,station\nheight,1,3,north\n", 1, "station", "read in pose recordings only"),
    ],
)
def test_errors_name_line_and_column(text, line, column, words):
    with pytest.raises(RecordingError) as exc:
        read_constraints("c.csv", text=text)
    e = exc.value
    assert e.row == line and e.column == column and words in str(e) and "c.csv" in str(e)


def test_machine_checks_name_the_column():
    rec = read_constraints("c.csv", text=GOOD)
    with pytest.raises(RecordingError, match="a_q1..a_q4"):
        rec.check_machine(4, None, "m.toml")
    lim = np.array([[0.0, 10.0]] * 3)
    with pytest.raises(RecordingError) as exc:
        ConstraintRecording(
            measure=("height", "distance"), qa=np.ones((2, 3)), qb=np.array([[np.nan] * 3, [1, 11, 1]]), value=np.ones(2), path="c.csv",
        ).check_machine(3, lim, "m.toml")
    assert exc.value.row == 3 and exc.value.column == "b_q2"
