"""Which files a run may read and write (bayescal.io.safe_paths): regular files, read once, no input overwritten."""

from __future__ import annotations

import io
import os
import sys

import pytest

from bayescal.errors import InputError, RecordingError
from bayescal.io.safe_paths import (
    check_outputs, check_replaceable, figure_format, read_input_bytes, read_input_text, run_scope,
)


def test_a_regular_file_is_read_and_its_size_limited(tmp_path):
    p = tmp_path / "a.csv"
    p.write_bytes(b"q1,x\n1,2\n")
    assert read_input_bytes(p, "a recording", limit=100) == b"q1,x\n1,2\n"
    with pytest.raises(InputError, match=r"a\.csv: 9 bytes, more than the limit of 8 bytes for a recording"):
        read_input_bytes(p, "a recording", limit=8)


@pytest.mark.parametrize("make, kind", [
    (lambda p: os.mkfifo(p), "a named pipe"),
    (lambda p: p.mkdir(), "a folder"),
])
def test_a_pipe_or_a_folder_is_refused_before_it_is_opened(tmp_path, make, kind):
    p = tmp_path / "in.csv"
    make(p)
    # a FIFO without a writer would block open() forever: the refusal comes from stat, before any open
    with pytest.raises(RecordingError, match=f"in.csv: is {kind}"):
        read_input_bytes(p, "a recording", limit=100, error=lambda m: RecordingError(str(p), None, None, m))


@pytest.mark.parametrize("device", ["/dev/zero", "/dev/urandom", "/dev/null"])
def test_devices_are_refused(device):
    if not os.path.exists(device):
        pytest.skip(f"no {device}")
    with pytest.raises(InputError, match=f"{device}: is a character device, not a regular file; expected a machine file"):
        read_input_bytes(device, "a machine file", limit=1 << 20)


def test_a_missing_file_and_bad_utf8_name_the_file(tmp_path):
    with pytest.raises(InputError, match="nope.toml: file not found; expected x"):
        read_input_text(tmp_path / "nope.toml", "x", limit=10)
    bad = tmp_path / "latin.csv"
    bad.write_bytes(b"caf\xe9\n")
    with pytest.raises(InputError, match="latin.csv: not a UTF-8 text file"):
        read_input_text(bad, "x", limit=10)


def test_standard_input_is_read_once_per_run(monkeypatch):
    text = "q1,x\n1,2\n"
    monkeypatch.setattr(sys, "stdin", io.TextIOWrapper(io.BytesIO(text.encode())))
    with run_scope():
        # a reader that looks at the header first and then parses the file gets the same text both times
        assert read_input_text("/dev/stdin", "a recording", limit=100) == text
        assert read_input_text("/dev/stdin", "a recording", limit=100) == text
    monkeypatch.setattr(sys, "stdin", io.TextIOWrapper(io.BytesIO(b"x" * 50)))
    with run_scope(), pytest.raises(InputError, match="more than the limit of 10 bytes"):
        read_input_bytes("/dev/stdin", "a recording", limit=10)


def test_an_output_that_is_an_input_is_refused_by_identity(tmp_path):
    rec = tmp_path / "r.csv"
    rec.write_text("q1\n")
    link = tmp_path / "link.csv"
    link.symlink_to(rec)
    hard = tmp_path / "hard.csv"
    os.link(rec, hard)
    for out in (rec, hard):
        with pytest.raises(InputError, match=r"--json .* is the same file as recording .*link.csv"):
            check_outputs({"--json": out}, {"recording": link})
    # a name that merely looks alike is not the same file
    check_outputs({"--json": tmp_path / "r.csv.json"}, {"recording": rec})


def test_two_outputs_of_one_file_are_refused_even_when_new(tmp_path):
    (tmp_path / "sub").mkdir()
    with pytest.raises(InputError, match=r"--json .*a.json and --report .*a.json are the same file"):
        check_outputs({"--json": tmp_path / "a.json", "--report": tmp_path / "sub" / ".." / "a.json"})


def test_link_device_pipe_and_folder_targets_are_refused(tmp_path):
    victim = tmp_path / "victim.txt"
    victim.write_text("keep")
    planted = tmp_path / "out.json"
    planted.symlink_to(victim)
    with pytest.raises(InputError, match="--json .*out.json: is a symbolic link"):
        check_outputs({"--json": planted})
    os.mkfifo(tmp_path / "pipe")
    with pytest.raises(InputError, match="is a named pipe"):
        check_outputs({"--out": tmp_path / "pipe"})
    with pytest.raises(InputError, match="is a folder; expected a file name"):
        check_outputs({"--out": tmp_path})
    if os.path.exists("/dev/null"):
        with pytest.raises(InputError, match="/dev/null: is a character device"):
            check_outputs({"--json": "/dev/null"})
    assert victim.read_text() == "keep"


def test_missing_folders_need_mkdir_and_a_file_in_the_way_is_named(tmp_path):
    with pytest.raises(InputError, match="the folder .*new does not exist .*--mkdir"):
        check_outputs({"--json": tmp_path / "new" / "a.json"})
    check_outputs({"--json": tmp_path / "new" / "deeper" / "a.json"}, mkdir=True)
    (tmp_path / "file").write_text("")
    with pytest.raises(InputError, match="is not a folder"):
        check_outputs({"--json": tmp_path / "file" / "a.json"}, mkdir=True)
    with pytest.raises(InputError, match="exists and is not a folder"):
        check_outputs({}, folders={"--figures": tmp_path / "file"})
    # files inside an output folder the command creates need no --mkdir
    check_outputs({"--out's table.txt": tmp_path / "cmp" / "table.txt"}, folders={"--out": tmp_path / "cmp"})


def test_inputs_read_within_a_run_are_never_replaced(tmp_path):
    m = tmp_path / "m.toml"
    m.write_text("kind = 'x'\n")
    check_replaceable(m)  # outside a run: a plain file
    with run_scope():
        read_input_bytes(m, "a machine file", limit=100)
        with pytest.raises(InputError, match="an input of this run"):
            check_replaceable(m)
        state = tmp_path / "state.json"
        state.write_text("{}")
        read_input_bytes(state, "state", limit=100, protect=False)  # state a run rewrites
        check_replaceable(state)


@pytest.mark.parametrize("name, ok", [("a.png", True), ("a.PDF", True), ("a.svg", True), ("heatmap", False),
                                      ("heat.txt", False), ("a.png.bak", False)])
def test_figure_names_need_a_format_matplotlib_writes(name, ok):
    if ok:
        assert figure_format(name) == name.rsplit(".", 1)[1].lower()
    else:
        with pytest.raises(InputError, match=f"figure {name}: .*expected a figure file name ending in .png"):
            figure_format(name)


def test_the_figure_formats_are_ones_matplotlib_writes():
    from matplotlib.backend_bases import FigureCanvasBase

    from bayescal.io.safe_paths import FIGURE_FORMATS

    assert set(FIGURE_FORMATS) <= set(FigureCanvasBase.get_supported_filetypes())


def test_named_inputs_that_are_not_regular_files_are_refused_up_front(tmp_path):
    from bayescal.io.safe_paths import check_inputs

    os.mkfifo(tmp_path / "fifo")
    (tmp_path / "ok.csv").write_text("x")
    check_inputs({"recording": tmp_path / "ok.csv", "--machine": tmp_path / "missing.toml", "--poses-file": "/dev/stdin"})
    with pytest.raises(InputError, match="config .*fifo: is a named pipe"):
        check_inputs({"config": tmp_path / "fifo"})
    with pytest.raises(InputError, match="--machine .*: is a folder"):
        check_inputs({"--machine": tmp_path})


# ------------------------------------------------------------------ output folders through links (issue 30)
def test_an_output_folder_that_is_a_link_is_refused(tmp_path):
    from bayescal.errors import InputError
    from bayescal.io.safe_paths import check_outputs, output_folder

    victim = tmp_path / "elsewhere"
    victim.mkdir()
    (tmp_path / "figs").symlink_to(victim, target_is_directory=True)
    with pytest.raises(InputError, match=r"--figures .*figs: is a symbolic link"):
        check_outputs({}, folders={"--figures": tmp_path / "figs"})
    with pytest.raises(InputError, match="is a symbolic link"):
        output_folder(tmp_path / "figs")
    (tmp_path / "file").write_text("x")
    with pytest.raises(InputError, match="not a folder"):
        output_folder(tmp_path / "file")
    assert output_folder(tmp_path / "new" / "sub").is_dir()  # a missing folder is made
    assert list(victim.iterdir()) == []


@pytest.mark.parametrize("argv", [
    ["diagnose", "{rec}", "--machine", "{m}", "--figures", "{link}"],
    ["identify", "{rec}", "--machine", "{m}", "--method", "ridge", "--lam", "auto", "--figures", "{link}"],
    ["compare", "--machine", "{m}", "--methods", "ls", "--trials", "1", "--out", "{link}", "--no-progress"],
    ["klipper", "{cfg}", "--out", "{link}"],
])
def test_commands_refuse_a_linked_output_folder_before_computing(tmp_path, capsys, argv):
    import shutil

    from bayescal.cli import main
    from tests.conftest import PRS3_FILE, ROOT

    victim = tmp_path / "elsewhere"
    victim.mkdir()
    (tmp_path / "link").symlink_to(victim, target_is_directory=True)
    shutil.copy(ROOT / "examples" / "prs3" / "recording.csv", tmp_path / "r.csv")
    shutil.copy(PRS3_FILE, tmp_path / "m.toml")
    (tmp_path / "p.cfg").write_text("[printer]\nkinematics: delta\n")
    words = [a.format(rec=tmp_path / "r.csv", m=tmp_path / "m.toml", link=tmp_path / "link", cfg=tmp_path / "p.cfg")
             for a in argv]
    assert main(words) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "is a symbolic link" in err and str(tmp_path / "link") in err
    assert list(victim.iterdir()) == []
