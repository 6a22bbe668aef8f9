"""Outputs never replace inputs, go only to regular files, and are checked before any computation (issue 30, items 3-4)."""

from __future__ import annotations

import os
import shutil

import numpy as np
import pytest

from bayescal.cli import main
from bayescal.errors import InputError
from bayescal.machines import write_machine_files
from bayescal.machines.files import load_machine
from tests.conftest import PRS3_FILE, ROOT

REC = ROOT / "examples" / "prs3" / "recording.csv"
HYB = ROOT / "examples" / "hybrid_table"


def run(capsys, *argv) -> tuple[int, list[str]]:
    code = main([str(a) for a in argv])
    err = capsys.readouterr().err.strip().splitlines()
    return code, err


@pytest.fixture
def files(tmp_path):
    shutil.copy(REC, tmp_path / "r.csv")
    shutil.copy(PRS3_FILE, tmp_path / "m.toml")
    return tmp_path


def _unchanged(path, original):
    assert path.read_bytes() == original.read_bytes()


@pytest.mark.parametrize("argv, options", [
    (["identify", "{d}/r.csv", "--machine", "{d}/m.toml", "--json", "{d}/r.csv"], ("--json", "recording")),
    (["identify", "{d}/r.csv", "--machine", "{d}/m.toml", "--write-machine", "{d}/m.toml"], ("--write-machine", "--machine")),
    (["identify", "{d}/r.csv", "--machine", "{d}/m.toml", "--report", "{d}/m.toml"], ("--report", "--machine")),
    (["simulate", "--machine", "{d}/m.toml", "--poses", "3", "--seed", "1", "--out", "{d}/m.toml"], ("--out", "--machine")),
    (["simulate", "--machine", "{d}/m.toml", "--poses", "3", "--seed", "1", "--truth", "{d}/m.json", "--out", "{d}/x.csv"],
     ("the true machine file beside --truth", "--machine")),
    (["simulate", "--machine", "{d}/m.toml", "--poses", "3", "--seed", "1", "--truth", "{d}/X", "--out", "{d}/X"],
     ("--truth", "--out")),
    (["identify", "{d}/r.csv", "--machine", "{d}/m.toml", "--json", "{d}/a.json", "--report", "{d}/a.json"],
     ("--json", "--report")),
    (["simulate", "--machine", "{d}/m.toml", "--poses", "3", "--seed", "1", "--poses-file", "{d}/r.csv", "--out", "{d}/r.csv"],
     ("--out", "--poses-file")),
])
def test_an_output_that_is_an_input_or_another_output_is_refused_up_front(files, capsys, argv, options):
    code, err = run(capsys, *[a.format(d=files) for a in argv])
    assert code == 2 and len(err) == 1
    assert all(o in err[0] for o in options), err
    _unchanged(files / "r.csv", REC)
    _unchanged(files / "m.toml", PRS3_FILE)
    assert not (files / "X").exists() and not (files / "x.csv").exists()


def test_an_output_reached_through_a_link_or_a_hard_link_is_the_input(files, capsys):
    os.link(files / "r.csv", files / "hard.csv")
    (files / "link.csv").symlink_to(files / "r.csv")
    code, err = run(capsys, "identify", files / "link.csv", "--machine", files / "m.toml", "--json", files / "hard.csv")
    assert code == 2 and "is the same file as recording" in err[0]
    _unchanged(files / "r.csv", REC)


@pytest.mark.parametrize("target, match", [
    ("/dev/null", "is a character device"), ("{d}/pipe", "is a named pipe"), ("{d}/planted.json", "is a symbolic link"),
    ("{d}", "is a folder"), ("{d}/nope/a.json", "does not exist"),
])
def test_outputs_go_only_to_regular_files(files, capsys, target, match):
    os.mkfifo(files / "pipe")
    (files / "victim.txt").write_text("keep")
    (files / "planted.json").symlink_to(files / "victim.txt")
    if target == "/dev/null" and not os.path.exists("/dev/null"):
        pytest.skip("no /dev/null")
    code, err = run(capsys, "identify", files / "r.csv", "--machine", files / "m.toml", "--json", target.format(d=files))
    assert code == 2 and len(err) == 1 and match in err[0] and "--json" in err[0]
    assert (files / "victim.txt").read_text() == "keep"


@pytest.mark.parametrize("figure", ["heatmap", "heat.txt", "folder.png"])
def test_figure_names_are_checked_before_the_grid_is_computed(files, capsys, figure):
    (files / "folder.png").mkdir()
    code, err = run(capsys, "grid", files / "r.csv", "--machine", files / "m.toml", "--figure", files / figure,
                    "--out", files / "g.csv")
    assert code == 2 and len(err) == 1 and "--figure" in err[0]
    assert not (files / "g.csv").exists()  # refused before any output (and before the identification)


def test_a_write_error_names_the_users_path(files, capsys):
    (files / "file").write_text("")
    code, err = run(capsys, "simulate", "--machine", files / "m.toml", "--poses", "3", "--seed", "1",
                    "--out", files / "file" / "x.csv", "--mkdir")
    assert code == 2 and "x.csv" in err[0] and ".tmp" not in err[0]


def test_simulate_writes_its_three_files_as_a_unit(files, capsys):
    code, _ = run(capsys, "simulate", "--machine", files / "m.toml", "--poses", "4", "--seed", "2", "--out", files / "s.csv",
                  "--quiet")
    assert code == 0
    assert {p.name for p in files.iterdir()} >= {"s.csv", "s.truth.json", "s.truth.toml"}
    assert not [p for p in files.iterdir() if p.name.startswith(".")]


def test_a_hybrid_is_written_as_a_unit_or_not_at_all(tmp_path):
    machine = load_machine(HYB / "machine.toml")
    os.mkfifo(tmp_path / "cal.m2.toml")  # one module's target cannot be written
    with pytest.raises(InputError, match="cal.m2.toml: is a named pipe"):
        write_machine_files(tmp_path / "cal.toml", machine, np.zeros(machine.n_params))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["cal.m2.toml"]  # no main file, no other module, no temporary
    os.unlink(tmp_path / "cal.m2.toml")
    paths = write_machine_files(tmp_path / "cal.toml", machine, np.zeros(machine.n_params))
    assert [p.name for p in paths] == ["cal.toml", "cal.m1.toml", "cal.m2.toml"]
    assert load_machine(tmp_path / "cal.toml").n_params == machine.n_params


def test_a_hybrid_write_never_replaces_a_module_the_run_read(tmp_path, capsys):
    # the output's module names are derived (<stem>.m1.toml): the file an input machine reads as a module is protected
    for f in ("head.toml", "table.toml", "recording.csv"):
        shutil.copy(HYB / f, tmp_path / f)
    text = (HYB / "machine.toml").read_text().replace('"head.toml"', '"cal.m1.toml"')
    (tmp_path / "machine.toml").write_text(text)
    shutil.copy(HYB / "head.toml", tmp_path / "cal.m1.toml")
    before = (tmp_path / "cal.m1.toml").read_bytes()
    code, err = run(capsys, "identify", tmp_path / "recording.csv", "--machine", tmp_path / "machine.toml", "--method", "map",
                    "--write-machine", tmp_path / "cal.toml", "--quiet")
    assert code == 2 and "an input of this run" in err[-1] and "cal.m1.toml" in err[-1]
    assert (tmp_path / "cal.m1.toml").read_bytes() == before and not (tmp_path / "cal.toml").exists()
