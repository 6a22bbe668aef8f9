"""A grid applies identify's plausibility rule (issue 30): one pose or copied rows are refused, ``force`` writes.

The library (:func:`bayescal.bayes.recording_grid.recording_grid`) judges the
fit with the function identify uses (``judge_fit``), so the two agree on the
same inputs; the command reports, writes nothing and exits 1 like identify,
and ``--force`` writes the grid anyway.
"""

from __future__ import annotations

import contextlib
import io
import json
import shutil

import pytest

import bayescal
from bayescal.bayes.recording_grid import recording_grid
from bayescal.cli import main
from bayescal.errors import InputError
from tests.conftest import PRS3_FILE, ROOT

REC = ROOT / "examples" / "prs3" / "recording.csv"


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    d = tmp_path_factory.mktemp("gridplaus")
    lines = REC.read_text().splitlines()
    (d / "one.csv").write_text("\n".join(lines[:2]) + "\n")
    (d / "copies.csv").write_text("\n".join([lines[0]] + [lines[1]] * 36) + "\n")
    shutil.copy(PRS3_FILE, d / "m.toml")
    return d


def run(argv):
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = main([str(a) for a in argv])
    return code, out.getvalue(), err.getvalue()


@pytest.mark.parametrize("name", ["one", "copies"])
def test_library_grid_judges_like_identify(files, name):
    session = bayescal.load(files / "m.toml", files / f"{name}.csv")
    answer = recording_grid(session, method="map", nodes=2)
    cal = bayescal.calibrate(session, method="map")
    assert cal.plausibility.plausible is False
    assert answer.plausible is False
    assert answer.plausibility.reasons == cal.plausibility.reasons
    assert answer.to_dict()["plausible"] is False
    with pytest.raises(InputError, match="write_csv: the calibration is not plausible"):
        answer.write_csv(files / f"lib_{name}.csv")
    assert not (files / f"lib_{name}.csv").exists()
    answer.write_csv(files / f"lib_{name}.csv", force=True)
    assert (files / f"lib_{name}.csv").read_text().startswith("q1,q2,q3,dx")


def test_the_whole_recording_is_plausible(files):
    answer = bayescal.grid(bayescal.load(files / "m.toml", REC), nodes=2)
    assert answer.plausible and answer.to_dict()["plausible"] is True


@pytest.mark.parametrize("name,method", [("one", "kalman"), ("copies", "map")])
def test_command_refuses_like_identify_and_force_writes(files, name, method):
    rec, m = files / f"{name}.csv", files / "m.toml"
    code_id, out_id, _ = run(["identify", rec, "--machine", m, "--method", method])
    assert code_id == 1 and "NOT PLAUSIBLE" in out_id
    out = files / f"g_{name}.csv"
    code, text, err = run(["grid", rec, "--machine", m, "--method", method, "--nodes", "2", "--out", out,
                           "--json", files / f"g_{name}.json"])
    assert code == 1 and "NOT PLAUSIBLE" in text and "no grid written" in text and err == ""
    assert not out.exists() and not (files / f"g_{name}.json").exists()
    code, text, err = run(["grid", rec, "--machine", m, "--method", method, "--nodes", "2", "--out", out, "--force",
                           "--json", files / f"g_{name}.json"])
    assert code == 1 and out.exists() and f"wrote {out}" in err
    assert json.loads((files / f"g_{name}.json").read_text())["plausible"] is False
