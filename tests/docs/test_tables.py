"""Every table of the docs renders as a table: a block of '|' lines starts with a header and a '|---|' row.

A blank line inside a table ends it; the rows after it then rendered as raw '|' text on the site (six
tables did, in cli.md, formats.md and regularisation.md).
"""

from __future__ import annotations

import re

from tests.docs.shown_outputs import ROOT

SEPARATOR = re.compile(r"^\|(\s*:?-{3,}:?\s*\|)+\s*$")


def _table_starts(text: str):
    """(line number, line, next line) of the first line of every block of table rows outside code fences."""
    fenced, previous = False, ""
    lines = text.split("\n")
    for i, line in enumerate(lines):
        if line.startswith("```"):
            fenced = not fenced
        elif not fenced and line.startswith("|") and not previous.startswith("|"):
            yield i + 1, line, lines[i + 1] if i + 1 < len(lines) else ""
        previous = "" if fenced else line


def test_every_table_has_a_header_row():
    bad = [f"{page.name}:{n}: {line[:60]}" for page in sorted((ROOT / "docs").glob("*.md"))
           for n, line, nxt in _table_starts(page.read_text(encoding="utf-8")) if not SEPARATOR.match(nxt)]
    assert not bad, "rows outside a table (a blank line inside it?):\n" + "\n".join(bad)


def test_the_check_finds_a_split_table():
    text = "| a | b |\n|---|---|\n| 1 | 2 |\n\n| 3 | 4 |\n"
    starts = list(_table_starts(text))
    assert [n for n, *_ in starts] == [1, 5] and not SEPARATOR.match(starts[1][2])
