"""Atomic writes (bayescal.io.answers): unique temporary files, no link followed, sets written as a unit."""

from __future__ import annotations

import os

import pytest

from bayescal.errors import InputError
from bayescal.io import answers
from bayescal.io.answers import write_files_atomic, write_text_atomic, write_with_atomic


def _leftovers(folder):
    return sorted(p.name for p in folder.iterdir() if p.name.startswith("."))


def test_a_write_replaces_a_regular_file_and_leaves_no_temporary(tmp_path):
    p = tmp_path / "a.json"
    p.write_text("old")
    write_text_atomic(p, "new\r\n")
    assert p.read_bytes() == b"new\r\n" and _leftovers(tmp_path) == []


def test_a_planted_link_is_refused_and_its_target_untouched(tmp_path):
    victim = tmp_path / "victim.txt"
    victim.write_text("keep")
    link = tmp_path / "out.json"
    link.symlink_to(victim)
    with pytest.raises(InputError, match="out.json: is a symbolic link"):
        write_text_atomic(link, "x")
    assert victim.read_text() == "keep" and link.is_symlink()


def test_a_planted_link_at_the_old_fixed_temporary_name_is_harmless(tmp_path):
    # figures used the fixed name .NAME.tmp.png; a link planted there redirected the write
    victim = tmp_path / "victim.png"
    victim.write_bytes(b"keep")
    (tmp_path / ".fig.png.tmp.png").symlink_to(victim)
    write_with_atomic(tmp_path / "fig.png", stream=lambda fh: fh.write(b"\x89PNG"))
    assert victim.read_bytes() == b"keep" and (tmp_path / "fig.png").read_bytes() == b"\x89PNG"


def test_a_failing_writer_removes_its_temporary_and_keeps_the_old_file(tmp_path):
    p = tmp_path / "fig.png"
    p.write_bytes(b"old")

    def boom(fh):
        fh.write(b"half")
        raise RuntimeError("writer failed")

    with pytest.raises(RuntimeError, match="writer failed"):
        write_with_atomic(p, stream=boom)
    assert p.read_bytes() == b"old" and _leftovers(tmp_path) == []


def test_errors_name_the_users_path_not_the_temporary(tmp_path):
    (tmp_path / "file").write_text("")
    with pytest.raises(InputError) as e:
        write_text_atomic(tmp_path / "file" / "a.json", "x")
    assert "a.json" in str(e.value) and ".tmp" not in str(e.value)


def test_a_set_is_all_or_nothing_when_a_rename_fails(tmp_path, monkeypatch):
    main, mod = tmp_path / "m.toml", tmp_path / "m.m1.toml"
    main.write_text("old main")
    real = os.replace
    calls = []

    def failing_second(src, dst):
        calls.append(dst)
        if len(calls) == 2 and str(dst) == str(main):  # the second rename of the set (the restores go through)
            raise OSError(28, "No space left on device")
        return real(src, dst)

    monkeypatch.setattr(answers.os, "replace", failing_second)
    with pytest.raises(InputError, match=r"m\.toml: cannot write it \(No space left on device\)"):
        write_files_atomic([(mod, "new module"), (main, "new main")])
    monkeypatch.setattr(answers.os, "replace", real)
    # the module renamed first was taken back (it did not exist), the main file is the old one, nothing left over
    assert not mod.exists() and main.read_text() == "old main" and _leftovers(tmp_path) == []


def test_a_set_restores_replaced_files_from_their_backups(tmp_path, monkeypatch):
    a, b = tmp_path / "a.csv", tmp_path / "b.json"
    a.write_text("old a")
    b.write_text("old b")
    real = os.replace
    n = []

    def fail_on_b(src, dst):
        n.append(dst)
        if str(dst) == str(b) and str(src).endswith(".tmp"):
            raise OSError(5, "Input/output error")
        return real(src, dst)

    monkeypatch.setattr(answers.os, "replace", fail_on_b)
    with pytest.raises(InputError, match="b.json: cannot write it"):
        write_files_atomic([(a, "new a"), (b, "new b")])
    monkeypatch.setattr(answers.os, "replace", real)
    assert a.read_text() == "old a" and b.read_text() == "old b" and _leftovers(tmp_path) == []


def test_a_set_checks_every_target_before_writing_any(tmp_path):
    os.mkfifo(tmp_path / "t.json")
    with pytest.raises(InputError, match="t.json: is a named pipe"):
        write_files_atomic([(tmp_path / "r.csv", "x"), (tmp_path / "t.json", "y")])
    assert not (tmp_path / "r.csv").exists() and _leftovers(tmp_path) == []


def test_written_files_get_the_mode_a_plain_open_gives(tmp_path):
    p = write_text_atomic(tmp_path / "a.txt", "x")
    mask = os.umask(0)
    os.umask(mask)
    assert p.stat().st_mode & 0o777 == 0o666 & ~mask
