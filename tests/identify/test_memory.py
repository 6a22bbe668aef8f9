"""identify refuses a recording whose arrays would not fit in memory, before computing (issue 30, item 10)."""

from __future__ import annotations

import pytest

import bayescal
from bayescal import limits
from bayescal.errors import InputError
from bayescal.identify import identify

from ..conftest import PRS3_FILE, ROOT


def test_identify_refuses_what_would_not_fit(monkeypatch):
    model = bayescal.load(PRS3_FILE, ROOT / "examples" / "prs3" / "recording.csv").fit_model
    need = 10.0 * 8 * model.n_poses * model.dof * model.n_params
    monkeypatch.setattr(limits, "memory_budget", lambda: need / 2)
    with pytest.raises(InputError, match=r"216 measured components x 36 parameters needs about .*every k-th row"):
        identify(model, method="map")
    monkeypatch.setattr(limits, "memory_budget", lambda: need * 2)
    assert identify(model, method="map").success


def test_the_command_refuses_before_solving_any_pose(monkeypatch, capsys):
    """The budget is checked as soon as the recording is read (the estimate: bayescal.limits.fit_memory)."""
    from bayescal.cli import main
    from bayescal.instrument import prepare

    solved = []
    monkeypatch.setattr(prepare, "check_recording_solves", lambda *a: solved.append(1))
    need = limits.fit_memory(216, 36)
    assert need == 10 * 8 * 216 * 36  # ten float64 arrays of components x parameters
    monkeypatch.setenv(limits.BUDGET_ENV, f"{need / 2 / 1024:.0f}K")
    rec = ROOT / "examples" / "prs3" / "recording.csv"
    code = main(["identify", str(rec), "--machine", str(PRS3_FILE), "--method", "map"])
    err = capsys.readouterr().err
    assert code == 2 and not solved
    assert err.count("\n") == 1 and "recording.csv: identifying from 216 measured components x 36 parameters needs" in err
    assert f"set by {limits.BUDGET_ENV}" in err and "every k-th row" in err


@pytest.mark.parametrize("text", ["abc", "-1G", "0", "nanM"])
def test_a_budget_that_is_not_a_size_is_refused_naming_the_variable(monkeypatch, text):
    monkeypatch.setenv(limits.BUDGET_ENV, text)
    with pytest.raises(InputError, match=limits.BUDGET_ENV):
        limits.memory_budget()


def test_the_stated_budget_is_read_in_bytes(monkeypatch):
    for text, value in [("2G", 2 * 2**30), ("500m", 500 * 2**20), ("1e9", 1e9), ("64K", 65536)]:
        monkeypatch.setenv(limits.BUDGET_ENV, text)
        assert limits.memory_budget() == value


@pytest.mark.parametrize("header, dof", [("q1,q2,q3,x,y,z,rx,ry,rz", 6), ("q1,q2,q3,x_mm,y_mm,z_mm,nx,ny,nz", 5),
                                         ("q1,q2,q3,x,y,z", 3)])
def test_the_reader_states_rows_and_components_before_parsing_a_cell(header, dof):
    """Lines counted (trailing blank lines left out, any line end), the header's components: before any cell."""
    from bayescal.io import read_recording

    seen = []
    text = header + "\r\n" + "1,2,not a number\r\n" * 4 + "1,2\n\n \n"
    with pytest.raises(InputError):  # the cells are bad: the check came first
        read_recording("r.csv", text=text, check_size=lambda n, d: seen.append((n, d)))
    assert seen == [(5, dof)] * 2  # from the line count, then from the rows once the header is checked


def test_a_recording_too_large_to_fit_ends_when_its_header_is_read(monkeypatch):
    from bayescal.io import recording

    parsed = []
    monkeypatch.setattr(recording, "parse_table", lambda *a: parsed.append(1))
    monkeypatch.setenv(limits.BUDGET_ENV, "1K")
    rec = ROOT / "examples" / "prs3" / "recording.csv"
    with pytest.raises(InputError, match=r"recording.csv: identifying from 216 measured components x 36 parameters"):
        bayescal.load(PRS3_FILE, rec)
    assert not parsed
