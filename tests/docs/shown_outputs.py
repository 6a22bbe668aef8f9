"""Outputs shown in the docs, re-run: the commands of a page run again and their output compared with what it shows.

A page marks what is checked with HTML comments (invisible on the site) right before a fenced block:

``<!-- shown-output -->``
    The block is a terminal session: ``$ command`` lines (a trailing ``\\`` continues a command on the
    next line), each followed by the output it shows.  ``bayescal ...`` runs in this process (the
    import is paid once), ``python FILE`` runs a file written earlier on the page and ``python -c
    CODE`` its code (in this process too), ``echo $?`` prints
    the last exit code, anything else runs in ``bash``; stdout and stderr are read together, in the
    order they were written, as a terminal shows them.
``<!-- file: NAME -->``
    The block's text is written to ``NAME`` (a script the page runs later).
``<!-- excerpt: NAME -->``
    The block's lines appear, in order, in the file ``NAME`` that an earlier command wrote.

Every block of a page runs in order in one temporary folder, which holds a link ``examples`` to the
repository's examples.  The comparison (:func:`compare`) is exact line by line (trailing spaces
aside), with two ways to leave output out: a line ``...`` stands for any number of lines, and a line
ending in ``...`` for any line that starts with the text before it.  A block that does not end in a
``...`` line shows the whole output.  A line may end with an annotation ``(exit N)`` after two or more
spaces: the command's exit code.

Run as a script to rewrite a page's shown outputs from fresh runs (each shown line replaced by the
most similar line of the new output, elisions kept), then review the diff::

    PYTHONPATH=. python tests/docs/shown_outputs.py docs/getting-started.md [--write]
"""

from __future__ import annotations

import contextlib
import difflib
import io
import os
import re
import runpy
import shlex
import subprocess
import sys
import tempfile
from dataclasses import dataclass, field
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
GAP = "..."
_MARKER = re.compile(r"<!--\s*(shown-output|file|excerpt)\s*:?\s*(\S*)\s*-->")
_EXIT = re.compile(r"\s{2,}\(exit (\d+)\)\s*$")


@dataclass
class Step:
    """One command of a session and the output lines the page shows for it."""

    command: str
    shown: list[str] = field(default_factory=list)
    exit_code: int | None = None  # from an "(exit N)" annotation


@dataclass
class Block:
    """A marked fenced block: its kind, its argument, its lines and where they are in the page."""

    kind: str  # "shown-output", "file", "excerpt"
    arg: str
    lines: list[str]
    start: int  # index in the page's lines of the first line inside the fence
    end: int  # index of the closing fence


def blocks(text: str) -> list[Block]:
    """The marked blocks of a page, in order."""
    lines = text.split("\n")
    out, i = [], 0
    while i < len(lines):
        m = _MARKER.fullmatch(lines[i].strip())
        if m and i + 1 < len(lines) and lines[i + 1].startswith("```"):
            end = next(j for j in range(i + 2, len(lines)) if lines[j].startswith("```"))
            out.append(Block(m.group(1), m.group(2), lines[i + 2:end], i + 2, end))
            i = end
        i += 1
    return out


def steps(lines: list[str]) -> list[Step]:
    """The commands of a session block and the output shown after each."""
    out: list[Step] = []
    i = 0
    while i < len(lines):
        line = lines[i]
        if line.startswith("$ "):
            cmd = line[2:]
            while cmd.endswith("\\") and i + 1 < len(lines):
                i += 1
                cmd = cmd[:-1].rstrip() + " " + lines[i].strip()
            out.append(Step(cmd))
        elif out:
            m = _EXIT.search(line)
            if m:
                out[-1].exit_code = int(m.group(1))
                line = line[: m.start()]
            out[-1].shown.append(line)
        i += 1
    for s in out:
        while s.shown and not s.shown[-1].strip():
            s.shown.pop()
    return out


class Session:
    """Runs a page's commands in one temporary folder."""

    def __init__(self, folder: Path):
        self.folder = folder
        self.last = 0
        (folder / "examples").symlink_to(ROOT / "examples", target_is_directory=True)

    def run(self, command: str) -> tuple[int, list[str]]:
        buf = io.StringIO()
        words = shlex.split(command)
        if command.strip() == "echo $?":
            return 0, [str(self.last)]
        old = Path.cwd()
        os.chdir(self.folder)
        try:
            if words[0] == "bayescal":
                code = self._bayescal(words[1:], buf)
            elif words[0] == "python" and len(words) == 2:
                with contextlib.redirect_stdout(buf), contextlib.redirect_stderr(buf):
                    runpy.run_path(words[1], run_name="__main__")
                code = 0
            elif words[0] == "python" and len(words) == 3 and words[1] == "-c":
                with contextlib.redirect_stdout(buf), contextlib.redirect_stderr(buf):
                    exec(compile(words[2], "<python -c>", "exec"), {"__name__": "__main__"})
                code = 0
            else:
                done = subprocess.run(["bash", "-c", command], capture_output=True, text=True, timeout=60)
                buf.write(done.stdout + done.stderr)
                code = done.returncode
        finally:
            os.chdir(old)
        self.last = code
        return code, buf.getvalue().rstrip("\n").split("\n") if buf.getvalue().strip() else []

    @staticmethod
    def _bayescal(argv: list[str], buf: io.StringIO) -> int:
        from bayescal.cli import main

        with contextlib.redirect_stdout(buf), contextlib.redirect_stderr(buf):
            try:
                return int(main(argv) or 0)
            except SystemExit as exc:  # argparse's own exits
                return int(exc.code or 0)


def _is_gap(line: str) -> bool:
    return line.strip() == GAP


def _line_matches(shown: str, actual: str) -> bool:
    s, a = shown.rstrip(), actual.rstrip()
    if s.endswith(GAP) and s.strip() != GAP:
        return a.startswith(s[: -len(GAP)].rstrip())
    return s == a


def compare(shown: list[str], actual: list[str]) -> str | None:
    """None when ``actual`` fits ``shown`` (module docstring), else what does not, in words."""
    segments, current = [], []
    for line in shown:
        if _is_gap(line):
            segments.append(current)
            current = []
            segments.append(None)  # a gap
        else:
            current.append(line)
    segments.append(current)
    pos, gap = 0, False
    for seg in segments:
        if seg is None:
            gap = True
            continue
        if not seg:
            continue
        starts = range(pos, len(actual) - len(seg) + 1) if gap else [pos]
        at = next((k for k in starts if all(_line_matches(s, actual[k + j]) for j, s in enumerate(seg))), None)
        if at is None:
            near = actual[pos: pos + len(seg) + 3]
            return "shown:\n  " + "\n  ".join(seg) + "\nnot found" + (" after a gap" if gap else " at output line "
                                                                      f"{pos + 1}") + "; the output there:\n  " + "\n  ".join(near)
        pos, gap = at + len(seg), False
    if not gap and any(line.strip() for line in actual[pos:]):
        return "the output goes on after the lines shown (end the block with '...'):\n  " + "\n  ".join(actual[pos: pos + 4])
    return None


def refreshed(shown: list[str], actual: list[str]) -> list[str]:
    """``shown`` with each line replaced by the most similar line of ``actual`` (in order), elisions kept."""
    out, pos = [], 0
    for line in shown:
        if _is_gap(line) or not line.strip():
            out.append(line)
            continue
        best, score = None, 0.0
        for k in range(pos, len(actual)):
            r = difflib.SequenceMatcher(None, line, actual[k]).ratio()
            if r > score:
                best, score = k, r
        if best is None or score < 0.5:
            out.append(line)
            continue
        new = actual[best]
        if line.rstrip().endswith(GAP) and line.strip() != GAP:
            keep = len(line.rstrip()[: -len(GAP)].rstrip())
            new = new[:keep].rstrip() + " " + GAP if len(new) > keep else new
        out.append(new)
        pos = best + 1
    return out


def check_page(path: Path, *, write: bool = False) -> list[str]:
    """Run the marked blocks of a page; the problems found (with ``write``: the page rewritten first)."""
    text = path.read_text(encoding="utf-8")
    lines = text.split("\n")
    problems: list[str] = []
    with tempfile.TemporaryDirectory(prefix="bayescal_docs_") as tmp:
        session = Session(Path(tmp))
        for b in blocks(text):
            if b.kind == "file":
                (Path(tmp) / b.arg).write_text("\n".join(b.lines) + "\n", encoding="utf-8")
            elif b.kind == "excerpt":
                actual = (Path(tmp) / b.arg).read_text(encoding="utf-8").split("\n")
                if write:
                    lines[b.start:b.end] = refreshed(b.lines, actual)
                elif compare([GAP, *b.lines, GAP], actual):
                    problems.append(f"{path.name} line {b.start + 1}: not an excerpt of {b.arg}")
            else:
                new_lines = _run_session(session, b, path, problems, write)
                lines[b.start:b.end] = new_lines
    if write:
        path.write_text("\n".join(lines), encoding="utf-8")
    return problems


def _run_session(session: Session, b: Block, path: Path, problems: list[str], write: bool) -> list[str]:
    """Run one session block; the block's lines, refreshed when ``write``."""
    out = []
    raw = b.lines
    i = 0
    for s in steps(raw):
        code, actual = session.run(s.command)
        # the block's own lines for this step: the command (with continuations) and what follows it
        while not raw[i].startswith("$ "):
            out.append(raw[i])
            i += 1
        out.append(raw[i])
        i += 1
        while raw[i - 1].rstrip().endswith("\\"):
            out.append(raw[i])
            i += 1
        j = i
        while j < len(raw) and not raw[j].startswith("$ "):
            j += 1
        shown_raw = raw[i:j]
        i = j
        if s.exit_code is not None and code != s.exit_code:
            problems.append(f"{path.name}: '{s.command}' exited {code}, the page says {s.exit_code}")
        problem = compare(s.shown, actual)
        if problem:
            problems.append(f"{path.name}: '{s.command}':\n{problem}")
        if write:
            annotated = [ln for ln in shown_raw]
            body = refreshed([_EXIT.sub("", ln) for ln in annotated], actual)
            out += [b2 + (m.group(0) if (m := _EXIT.search(a)) else "") for a, b2 in zip(annotated, body)]
        else:
            out += shown_raw
    out += raw[i:]
    return out


def main(argv: list[str] | None = None) -> int:
    import argparse

    p = argparse.ArgumentParser(description="re-run the outputs a docs page shows")
    p.add_argument("pages", nargs="+", type=Path)
    p.add_argument("--write", action="store_true", help="rewrite the shown outputs from fresh runs")
    args = p.parse_args(argv)
    bad = 0
    for page in args.pages:
        for problem in check_page(page, write=args.write):
            print(problem, end="\n\n")
            bad += 1
    return 1 if bad else 0


if __name__ == "__main__":
    sys.path.insert(0, str(ROOT))
    raise SystemExit(main())
