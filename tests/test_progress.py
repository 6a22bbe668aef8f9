"""Progress lines of long computations (bayescal.progress): silent unless asked, on stderr from the command line."""

from __future__ import annotations

import io
import time

import pytest

import bayescal
from bayescal.identify import identify
from bayescal import progress
from bayescal.progress import StderrProgress, report, reporting

from .conftest import PRS3_FILE, ROOT

REC = ROOT / "examples" / "prs3" / "recording.csv"


def test_report_is_silent_without_a_sink_and_formats_lazily(capsys):
    called = []
    report(lambda: called.append(1) or "never")
    assert not called and capsys.readouterr() == ("", "")
    lines = []
    with reporting(lines.append):
        report("a")
        report(lambda: "b")
    report("after")  # the sink is gone with the block
    assert lines == ["a", "b"]


def test_the_fit_reports_each_gauss_newton_iteration_only_when_asked(capsys):
    model = bayescal.load(PRS3_FILE, REC).fit_model
    lines = []
    with reporting(lines.append):
        res = identify(model, method="map")
    its = [ln for ln in lines if ln.startswith("Gauss-Newton iteration")]
    assert res.success and len(its) == res.iterations
    assert its[0].startswith("Gauss-Newton iteration 1 of at most 50: cost ")
    identify(model, method="map")
    assert capsys.readouterr() == ("", "")  # the library itself prints nothing


def test_stderr_lines_wait_for_the_delay_and_keep_the_last_line_of_it():
    out = io.StringIO()
    sink = StderrProgress("identify", delay=0.2, interval=0.0, stream=out)
    sink("solving")
    assert out.getvalue() == ""  # a quick run prints nothing
    deadline = time.monotonic() + 10
    while not out.getvalue() and time.monotonic() < deadline:
        time.sleep(0.05)
    assert out.getvalue() == "bayescal identify: solving\n"  # the stage a long run began with, once the delay ended
    sink("iteration 1")
    sink.close()
    assert out.getvalue().splitlines() == ["bayescal identify: solving", "bayescal identify: iteration 1"]


def test_a_run_within_the_delay_prints_nothing():
    out = io.StringIO()
    with reporting(StderrProgress("x", delay=60.0, stream=out)):
        report("quick")
    time.sleep(0.05)
    assert out.getvalue() == ""


def test_the_command_line_writes_lines_unless_quiet(monkeypatch, capsys):
    from bayescal.cli import main
    from bayescal import progress

    monkeypatch.delenv(progress.PROGRESS_ENV, raising=False)  # tests/conftest.py turns the lines off
    # no delay, no throttle: every line the run reports (a real run waits PROGRESS_DELAY seconds)
    monkeypatch.setattr(progress.StderrProgress.__init__, "__kwdefaults__", {"delay": 0.0, "interval": 0.0, "stream": None})
    args = ["identify", str(REC), "--machine", str(PRS3_FILE), "--method", "map"]
    assert main(args) == 0
    err = capsys.readouterr().err
    assert "bayescal identify: Gauss-Newton iteration 1 of at most 50" in err
    assert main(args + ["--quiet"]) == 0
    assert capsys.readouterr().err == ""
    assert main(args + ["--no-progress"]) == 0
    assert "Gauss-Newton" not in capsys.readouterr().err
    monkeypatch.setenv(progress.PROGRESS_ENV, "off")
    assert main(args) == 0
    assert "Gauss-Newton" not in capsys.readouterr().err


@pytest.mark.parametrize("value,wanted", [("off", False), (" FALSE ", False), ("0", False), ("", True), ("on", True),
                                          ("Yes", True)])
def test_progress_env_values(monkeypatch, value, wanted):
    monkeypatch.setenv(progress.PROGRESS_ENV, value)
    assert progress.progress_wanted() is wanted


@pytest.mark.parametrize("value", ["abc", "of", "-1", "1e400", "a\nb"])
def test_an_unknown_progress_value_is_refused_in_one_line(monkeypatch, capsys, value):
    from bayescal.cli import main
    from bayescal.errors import InputError
    from tests.conftest import PRS3_FILE

    monkeypatch.setenv(progress.PROGRESS_ENV, value)
    with pytest.raises(InputError, match="BAYESCAL_PROGRESS"):
        progress.progress_wanted()
    assert main(["simulate", "--machine", str(PRS3_FILE), "--poses", "3", "--seed", "1", "--out", "/nonexistent/x.csv",
                 "--quiet"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "environment variable BAYESCAL_PROGRESS" in err
