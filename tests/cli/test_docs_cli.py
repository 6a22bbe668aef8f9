"""docs/cli.md documents every command and every option the parser has."""

from __future__ import annotations

import argparse

from bayescal.cli import COMMANDS, build_parser
from tests.conftest import ROOT


def test_every_command_and_option_is_in_docs_cli():
    text = (ROOT / "docs" / "cli.md").read_text(encoding="utf-8")
    parser = build_parser()
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    missing = []
    for name in COMMANDS:
        section = text.split(f"## `bayescal {name}`", 1)
        if len(section) == 1:
            missing.append(f"section for {name}")
            continue
        body = section[1].split("\n## `bayescal ", 1)[0]
        for action in sub.choices[name]._actions:
            for opt in action.option_strings:
                if opt not in ("-h", "--help") and f"`{opt}`" not in body:
                    missing.append(f"{name} {opt}")
    assert not missing, missing


def test_docs_index_links_every_page():
    index = (ROOT / "docs" / "index.md").read_text(encoding="utf-8")
    pages = sorted(p.name for p in (ROOT / "docs").glob("*.md") if p.name != "index.md")
    assert [p for p in pages if f"({p}" not in index] == []


def test_every_help_text_renders():
    """argparse formats help strings with %: a bare '%' in one (a '90 % region') printed a dict into --help."""
    parser = build_parser()
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    texts = [parser.format_help()] + [p.format_help() for p in sub.choices.values()]
    assert not [t for t in texts if "option_strings" in t or "'dest'" in t]
    # a help text with a % sign once broke --help; argparse wraps lines, so compare words
    assert "with its uncertainty" in " ".join(parser.format_help().split())
