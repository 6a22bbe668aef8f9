"""``bayescal plan --separate``: the command line's answer is the library's, and it refuses what it cannot plan."""

import json

import pytest

import bayescal
from bayescal.cli import main
from tests.conftest import PRS3_FILE, ROOT


@pytest.mark.slow
def test_plan_separate_writes_the_library_plan(tmp_path, capsys):
    rec = tmp_path / "rec.csv"
    assert main(["simulate", "--machine", str(PRS3_FILE), "--poses", "100", "--seed", "4",
                 "--effect", "joint_compliance:0.5", "--aux", "payload_kg", "--out", str(rec), "--quiet"]) == 0
    out, js = tmp_path / "next.csv", tmp_path / "next.json"
    assert main(["plan", "--machine", str(PRS3_FILE), "--separate", str(rec), "--n", "12", "--effects", "joint_compliance",
                 "--out", str(out), "--json", str(js)]) == 0
    printed = capsys.readouterr().out
    answer = json.loads(js.read_text())
    lib = bayescal.plan_next_session(PRS3_FILE, rec, 12, effects=["joint_compliance"])
    assert answer == json.loads(json.dumps(lib.to_dict()))
    assert out.read_text() == lib.to_csv()
    assert answer["planned_poses"] == 12 and answer["tool_std_planned_um"] < answer["tool_std_before_um"]
    assert f"wrote {out}" in printed and "most informative first" in printed
    # another condition by name; one the forecast does not offer is refused by name
    assert main(["plan", "--machine", str(PRS3_FILE), "--separate", str(rec), "--n", "12", "--effects", "joint_compliance",
                 "--condition", "temperature", "--out", str(out)]) == 2
    assert "--condition temperature: expected one of" in capsys.readouterr().err


def test_plan_separate_refuses_what_it_cannot_plan(tmp_path, capsys):
    out = tmp_path / "next.csv"
    clean = ROOT / "examples" / "prs3" / "recording.csv"
    # a recording with no effect to separate: said, and nothing written
    assert main(["plan", "--machine", str(PRS3_FILE), "--separate", str(clean), "--n", "5", "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "recording.csv" in err and ("nothing to separate" in err or "not confounded" in err) and not out.exists()
    assert main(["plan", "--machine", str(PRS3_FILE), "--n", "5", "--condition", "payload", "--out", str(out)]) == 2
    assert "--condition goes with --separate" in capsys.readouterr().err
    assert main(["plan", "--machine", str(PRS3_FILE), "--separate", str(clean), "--measure", "height", "--n", "5",
                 "--out", str(out)]) == 2
    assert "does not go with --measure height" in capsys.readouterr().err


def test_plan_separate_never_writes_over_its_recording(tmp_path, capsys):
    rec = tmp_path / "rec.csv"
    rec.write_bytes((ROOT / "examples" / "prs3" / "recording.csv").read_bytes())
    before = rec.read_bytes()
    assert main(["plan", "--machine", str(PRS3_FILE), "--separate", str(rec), "--n", "5", "--out", str(rec)]) == 2
    assert "--out" in capsys.readouterr().err and rec.read_bytes() == before


@pytest.mark.parametrize("extra", [["--criterion", "E"], ["--candidates", "0"], ["--dof", "3"], ["--given", "x.csv"],
                                   ["--radius", "5"], ["--no-box"], ["--certify", "5"]])
def test_plan_separate_refuses_the_options_it_does_not_use(tmp_path, capsys, extra):
    """A probe found them accepted and ignored: the plan was not what the command line asked for."""
    rec = ROOT / "examples" / "prs3" / "recording.csv"
    out = tmp_path / "next.csv"
    assert main(["plan", "--machine", str(PRS3_FILE), "--separate", str(rec), "--n", "5", *extra, "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and f"{extra[0]} does nothing with --separate" in err[0], err
    assert not out.exists()
