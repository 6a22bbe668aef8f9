"""The outputs docs/getting-started.md and docs/cli.md show are what the commands print today.

Each page's marked blocks (``<!-- shown-output -->``, ``<!-- file: -->``, ``<!-- excerpt: -->``; see
tests/docs/shown_outputs.py) are run again in a temporary folder and compared line by line with what
the page shows.  When a change of bayescal changes an output on purpose, regenerate the page and
review the diff::

    PYTHONPATH=. python tests/docs/shown_outputs.py docs/getting-started.md docs/cli.md --write
"""

from __future__ import annotations

import pytest

from tests.docs.shown_outputs import ROOT, blocks, check_page, compare, refreshed, steps

PAGES = ["getting-started.md", "cli.md", "real-setup.md", "discrepancy.md", "tutorial.md"]


@pytest.mark.parametrize("page", PAGES)
def test_shown_outputs_are_current(page):
    path = ROOT / "docs" / page
    assert any(b.kind == "shown-output" for b in blocks(path.read_text(encoding="utf-8")))
    problems = check_page(path)
    assert not problems, "\n\n".join(problems) + "\n\nregenerate: PYTHONPATH=. python tests/docs/shown_outputs.py docs/" + page + " --write"


def test_comparison_rules():
    """Exact lines, '...' for any lines, 'text ...' for a line starting with text, the whole output otherwise."""
    out = ["a 1", "b 2", "c 3", "d 4"]
    assert compare(["a 1", "b 2", "c 3", "d 4"], out) is None
    assert compare(["a 1", "...", "d 4"], out) is None
    assert compare(["a 1", "b ...", "..."], out) is None
    assert compare(["...", "c 3", "..."], out) is None
    assert "goes on" in compare(["a 1", "b 2"], out)  # a block without '...' shows everything
    assert "not found" in compare(["a 1", "c 3", "..."], out)  # consecutive lines must follow each other
    assert "not found" in compare(["a 1", "b 3", "..."], out)  # a number that changed
    assert "not found" in compare(["...", "e 5"], out)


def test_refresh_keeps_elisions_and_replaces_stale_lines():
    shown = ["  method  ridge: 3 iterations", "...", "  RMS 0.0073 mm after ..."]
    actual = ["  method  ridge: 4 iterations", "x", "  RMS 0.0072 mm after, much more text"]
    assert refreshed(shown, actual) == ["  method  ridge: 4 iterations", "...", "  RMS 0.0072 mm after ..."]
    assert compare(refreshed(shown, actual), actual) is None


def test_sessions_are_split_into_commands_outputs_and_exit_codes():
    s = steps(["$ bayescal a \\", "    --b c", "out 1", "err  (exit 2)", "$ echo $?", "2", ""])
    assert [x.command for x in s] == ["bayescal a --b c", "echo $?"]
    assert s[0].shown == ["out 1", "err"] and s[0].exit_code == 2 and s[1].shown == ["2"]
