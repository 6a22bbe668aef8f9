"""Reading a Klipper config's files: include cycles, include trees beyond the limits, text that is not UTF-8,
files that are not regular, includes that point at files that are not configs (never quoted in errors)."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from bayescal.cli import main
from bayescal.klipper.cfg import KlipperConfigError, read_klipper_config
from bayescal.klipper.source import MAX_INCLUDE_DEPTH, MAX_INCLUDED_FILES


def _refused(path: Path, capsys, *options: str) -> str:
    """The one-line error of `bayescal klipper` on ``path`` (exit 2), also raised by the reader."""
    with pytest.raises(KlipperConfigError):
        read_klipper_config(path, missing_includes="error" if "error" in options else "skip")
    assert main(["klipper", str(path), "--out", str(path.parent / "out"), *options]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "Traceback" not in err
    return err


def test_an_include_cycle_is_named(tmp_path, capsys):
    (tmp_path / "printer.cfg").write_text("[printer]\nkinematics: delta\n[include a.cfg]\n")
    (tmp_path / "a.cfg").write_text("# a\n[include sub/b.cfg]\n")
    (tmp_path / "sub").mkdir()
    (tmp_path / "sub" / "b.cfg").write_text("[include ../a.cfg]\n")
    err = _refused(tmp_path / "printer.cfg", capsys)
    assert "include cycle:" in err and "a.cfg line 2 includes" in err and "b.cfg line 1 includes" in err
    # a file including itself, and the main file included again
    (tmp_path / "printer.cfg").write_text("[include printer.cfg]\n")
    assert "include cycle" in _refused(tmp_path / "printer.cfg", capsys)
    # the same file included twice side by side is no cycle (Klipper reads it twice)
    (tmp_path / "printer.cfg").write_text("[include c.cfg]\n[include c.cfg]\n")
    (tmp_path / "c.cfg").write_text("[printer]\nkinematics: delta\n")
    assert read_klipper_config(tmp_path / "printer.cfg").files[1:] == (str(tmp_path / "c.cfg"),) * 2


def test_an_include_tree_beyond_the_limits_is_refused_at_once(tmp_path, capsys):
    # 4 files per level, 10 levels: 4 + 16 + ... + 4**10 (about 1.4 million) includes if expanded
    (tmp_path / "printer.cfg").write_text("[include L1/*.cfg]\n")
    for level in range(1, 11):
        (tmp_path / f"L{level}").mkdir()
        for k in range(4):
            nxt = f"[include ../L{level + 1}/*.cfg]\n" if level < 10 else ""
            (tmp_path / f"L{level}" / f"f{k}.cfg").write_text(f"[m{level}_{k}]\na: 1\n" + nxt)
    err = _refused(tmp_path / "printer.cfg", capsys)
    assert f"more than {MAX_INCLUDED_FILES} included files" in err
    # a chain deeper than the limit
    for n in range(MAX_INCLUDE_DEPTH + 2):
        (tmp_path / f"d{n}.cfg").write_text(f"[include d{n + 1}.cfg]\n")
    (tmp_path / "printer.cfg").write_text("[include d0.cfg]\n")
    assert f"nested more than {MAX_INCLUDE_DEPTH} deep" in _refused(tmp_path / "printer.cfg", capsys)


def test_latin1_in_an_include_is_a_clear_error(tmp_path, capsys):
    (tmp_path / "printer.cfg").write_text("[printer]\nkinematics: delta\n[include extra.cfg]\n")
    (tmp_path / "extra.cfg").write_bytes(b"[probe]\n# caf\xe9 calibration\nz_offset: 1\n")
    err = _refused(tmp_path / "printer.cfg", capsys)
    assert f"{tmp_path / 'extra.cfg'} line 2: not UTF-8 text (byte 0xE9)" in err


@pytest.mark.parametrize("content", [
    b"root:x:0:0:SECRET-root:/root:/bin/bash\ndaemon:x:1:1:SECRET-daemon:/usr/sbin\n",  # like /etc/passwd
    b"password = SECRET-hunter2\n",  # a key before any section
    b"[section]\nSECRET-line-without-delimiter\n",  # a line configparser rejects
    b"[x]\nkey = SECRET\x00binary\n",
    b"\x89PNG\r\n\x1a\nSECRET\xff\xfe",
])
def test_an_include_that_is_not_a_config_is_not_quoted(tmp_path, capsys, content):
    (tmp_path / "secret").write_bytes(content)
    (tmp_path / "conf").mkdir()
    (tmp_path / "conf" / "printer.cfg").write_text("[printer]\nkinematics: delta\n[include ../secret]\n")
    err = _refused(tmp_path / "conf" / "printer.cfg", capsys)
    assert "SECRET" not in err and "conf/../secret line " in err


def test_the_real_etc_passwd_is_not_quoted(tmp_path, capsys):
    if not Path("/etc/passwd").is_file():
        pytest.skip("no /etc/passwd")
    depth = len(tmp_path.parts) - 1
    (tmp_path / "printer.cfg").write_text(f"[include {'../' * depth}etc/passwd]\n")
    err = _refused(tmp_path / "printer.cfg", capsys)
    assert "root" not in err.replace(str(tmp_path), "") and "etc/passwd line 1" in err


def test_files_that_are_not_regular_are_refused_without_reading(tmp_path, capsys):
    fifo = tmp_path / "pipe.cfg"
    os.mkfifo(fifo)  # reading it would block until a writer comes
    # named on the command line, the CLI's own input check refuses it first (bayescal/io/safe_paths.py)
    err = _refused(fifo, capsys)
    assert "FIFO" in err and "regular file" in err
    (tmp_path / "printer.cfg").write_text("[include pipe.cfg]\n")
    assert "pipe.cfg: is a FIFO" in _refused(tmp_path / "printer.cfg", capsys)
    if Path("/dev/zero").exists():
        assert "device" in _refused(Path("/dev/zero"), capsys)
        (tmp_path / "printer.cfg").write_text("[include /dev/zero]\n")
        assert "/dev/zero: is a character device" in _refused(tmp_path / "printer.cfg", capsys)
    (tmp_path / "printer.cfg").write_text("[include sub]\n")
    (tmp_path / "sub").mkdir()
    assert "sub: is a folder" in _refused(tmp_path / "printer.cfg", capsys)
    assert "file not found" in _refused(tmp_path / "nothing.cfg", capsys)


def test_a_wildcard_may_match_nothing_a_plain_name_must_exist(tmp_path, capsys):
    # Klipper (klippy/configfile.py _resolve_include): "Include file '...' does not exist" unless glob.has_magic
    (tmp_path / "printer.cfg").write_text("[include none/*.cfg]\n[printer]\nkinematics: delta\n")
    assert read_klipper_config(tmp_path / "printer.cfg").sections == {"printer": {"kinematics": "delta"}}
    (tmp_path / "printer.cfg").write_text("[include none/*.cfg]\n[include fluidd.cfg]\n[printer]\nkinematics: delta\n")
    with pytest.raises(KlipperConfigError, match="line 2: .include fluidd.cfg.: .*fluidd.cfg does not exist"):
        read_klipper_config(tmp_path / "printer.cfg", missing_includes="error")
    err = _refused(tmp_path / "printer.cfg", capsys, "--missing-includes", "error")
    assert f"{tmp_path / 'printer.cfg'} line 2" in err and str(tmp_path / "fluidd.cfg") in err
    cfg = read_klipper_config(tmp_path / "printer.cfg")  # skipped by default, remembered
    assert [(m.line, Path(m.target).name) for m in cfg.missing_includes] == [(2, "fluidd.cfg")]
    assert cfg.sections == {"printer": {"kinematics": "delta"}}


def test_a_missing_include_further_down_names_the_including_file(tmp_path, capsys):
    (tmp_path / "printer.cfg").write_text("[printer]\nkinematics: delta\n[include sub/a.cfg]\n")
    (tmp_path / "sub").mkdir()
    (tmp_path / "sub" / "a.cfg").write_text("# steppers\n\n[include b.cfg]\n")
    err = _refused(tmp_path / "printer.cfg", capsys, "--missing-includes", "error")
    assert f"{tmp_path / 'sub' / 'a.cfg'} line 3: [include b.cfg]: {tmp_path / 'sub' / 'b.cfg'} does not exist" in err


def test_a_folder_with_wildcard_characters_keeps_its_includes(tmp_path):
    # the FLSUN Q5's repository names its files 'printer [Post-Calibration].cfg': a folder may be named so too
    folder = tmp_path / "printer [v2]"
    folder.mkdir()
    (folder / "printer.cfg").write_text("[include parts/*.cfg]\n[include steppers.cfg]\n")
    (folder / "parts").mkdir()
    (folder / "parts" / "a.cfg").write_text("[printer]\nkinematics: delta\n")
    (folder / "steppers.cfg").write_text("[stepper_a]\nmicrosteps: 16\n")
    cfg = read_klipper_config(folder / "printer.cfg")
    assert cfg.sections == {"printer": {"kinematics": "delta"}, "stepper_a": {"microsteps": "16"}} and not cfg.missing_includes
