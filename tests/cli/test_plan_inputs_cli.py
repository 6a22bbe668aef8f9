"""``plan`` refuses an output that is a file its machine reads, before computing anything (issue 30).

A hybrid's module files and the URDF a machine file names are found only by
reading the machine file: the run declares its outputs
(:func:`bayescal.io.safe_paths.run_scope`) and the read refuses one, so the
plan (here replaced by a function that fails the test) never starts.
"""

from __future__ import annotations

import hashlib
import shutil

import pytest

import bayescal.design.plan as design_plan
from bayescal.cli import main
from tests.conftest import ROOT


def _digest(folder):
    return {p.name: hashlib.sha256(p.read_bytes()).hexdigest() for p in sorted(folder.iterdir()) if p.is_file()}


@pytest.fixture
def no_plan(monkeypatch):
    def never(*a, **k):
        raise AssertionError("the plan was computed before the output was refused")

    # the library's planner (bayescal.design.verb imports it when called)
    monkeypatch.setattr(design_plan, "plan_poses", never)


@pytest.mark.parametrize("option,target", [("--out", "head.toml"), ("--json", "table.toml"), ("--report", "x.html")])
def test_plan_over_a_hybrid_module_is_refused_before_planning(tmp_path, capsys, no_plan, option, target):
    for f in (ROOT / "examples" / "hybrid_table").glob("*.toml"):
        shutil.copy(f, tmp_path / f.name)
    if target == "x.html":  # a report that is a link to a module resolves to the module file
        (tmp_path / "x.html").symlink_to(tmp_path / "head.toml")
    before = _digest(tmp_path)
    argv = ["plan", "--machine", str(tmp_path / "machine.toml"), "--n", "5", "--out", str(tmp_path / "p.csv")]
    if option == "--out":
        argv[-1] = str(tmp_path / target)
    else:
        argv += [option, str(tmp_path / target)]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and option in err and ("input of this run" in err or "symbolic link" in err), err
    assert _digest(tmp_path) == before


def test_plan_over_the_urdf_the_machine_reads_is_refused_before_planning(tmp_path, capsys, no_plan):
    from tests.machines.test_urdf import FROM_URDF, URDF

    (tmp_path / "arm.urdf").write_text(URDF)
    (tmp_path / "m.toml").write_text(FROM_URDF)
    assert main(["plan", "--machine", str(tmp_path / "m.toml"), "--n", "5", "--out", str(tmp_path / "arm.urdf")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "arm.urdf" in err and "input of this run" in err and "URDF" in err, err
    assert (tmp_path / "arm.urdf").read_text() == URDF


def test_plan_separate_over_a_module_is_refused_before_planning(tmp_path, capsys, monkeypatch):

    for f in list((ROOT / "examples" / "hybrid_table").glob("*.toml")) + [ROOT / "examples" / "hybrid_table" /
                                                                          "recording.csv"]:
        shutil.copy(f, tmp_path / f.name)
    before = _digest(tmp_path)
    assert main(["plan", "--machine", str(tmp_path / "machine.toml"), "--separate", str(tmp_path / "recording.csv"),
                 "--n", "5", "--out", str(tmp_path / "table.toml")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "--out" in err and "table.toml" in err and "input of this run" in err, err
    assert _digest(tmp_path) == before


def test_run_scope_refuses_an_output_when_it_is_read(tmp_path):
    from bayescal.errors import InputError
    from bayescal.io.safe_paths import read_input_text, run_scope

    (tmp_path / "a.toml").write_text("x = 1\n")
    with run_scope({"--out": tmp_path / "a.toml", "--json": tmp_path / "new.json"}):
        with pytest.raises(InputError, match=r"--out .*a.toml: is .*a.toml, an input of this run \(a thing\)"):
            read_input_text(tmp_path / "a.toml", "a thing", limit=100)
    with run_scope({"--out": tmp_path / "a.toml"}):  # state a run reads and rewrites is not protected
        assert read_input_text(tmp_path / "a.toml", "a thing", limit=100, protect=False) == "x = 1\n"
