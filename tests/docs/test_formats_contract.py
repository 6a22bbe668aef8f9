"""docs/formats.md is the one file-format contract in the repository.

Nothing in the repository may cite a copy of the contract kept outside it (the
name is spelled in two parts below so that this file does not cite it
either); and when the shared contract sits beside the checkout (in
``../shared/``, absent on a fresh clone), every section of it
appears in docs/formats.md word for word, in order (whitespace normalised).
"""

from __future__ import annotations

import os
import re
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
PAGE = ROOT / "docs" / "formats.md"
OUTSIDE_NAME = "FORMATS" + ".md"
#: Folders that are not the repository's own files (builds, caches, environments).
SKIP_DIRS = {".git", ".venv", "venv", "site", "build", "dist", "__pycache__", ".pytest_cache", ".mypy_cache",
             ".ruff_cache", ".hypothesis", "node_modules", ".tox", ".nox"}


def _shared_contract() -> Path | None:
    env = os.environ.get("BAYESCAL_SHARED")
    places = ([Path(env)] if env else []) + [ROOT.parent / "shared", ROOT.parent.parent / "shared"]
    return next((p / OUTSIDE_NAME for p in places if (p / OUTSIDE_NAME).is_file()), None)


def _repository_files() -> list[Path]:
    """The tracked files (git), else every file of the tree outside builds and caches."""
    try:
        out = subprocess.run(["git", "ls-files", "-z"], cwd=ROOT, capture_output=True, check=True, timeout=60).stdout
        files = [ROOT / f for f in out.decode("utf-8", "surrogateescape").split("\0") if f]
        if files:
            return [f for f in files if f.is_file()]
    except (OSError, subprocess.SubprocessError):
        pass
    return [p for p in ROOT.rglob("*") if p.is_file() and not (set(p.relative_to(ROOT).parts[:-1]) & SKIP_DIRS)
            and not any(part.endswith(".egg-info") for part in p.relative_to(ROOT).parts)]


def _sections(text: str) -> list[str]:
    """The text split before every level-2 heading outside code fences (the first part: title and preamble)."""
    parts, current, fenced = [], [], False
    for line in text.splitlines():
        if line.startswith("```"):
            fenced = not fenced
        if line.startswith("## ") and not fenced and current:
            parts.append("\n".join(current))
            current = []
        current.append(line)
    parts.append("\n".join(current))
    return parts


def _normalised(text: str) -> str:
    return re.sub(r"\s+", " ", text).strip()


def test_nothing_cites_a_contract_outside_the_repository():
    offenders = []
    for f in _repository_files():
        if f == PAGE:
            continue
        try:
            data = f.read_bytes()
        except OSError:
            continue
        if OUTSIDE_NAME.encode() in data:
            lines = [i + 1 for i, ln in enumerate(data.split(b"\n")) if OUTSIDE_NAME.encode() in ln]
            offenders.append(f"{f.relative_to(ROOT)}: line(s) {', '.join(map(str, lines))}")
    assert not offenders, "cite docs/formats.md (section N) instead:\n" + "\n".join(offenders)


def test_the_page_carries_the_contracts_sections_in_order():
    """On any checkout: sections 1-8 of the contract, numbered as the contract numbers them, then bayescal's part."""
    headings = [ln for ln in PAGE.read_text(encoding="utf-8").splitlines() if re.match(r"#{1,2} ", ln)]
    numbered = [h for h in headings if re.match(r"## \d+\. ", h)]
    assert [int(re.match(r"## (\d+)\.", h).group(1)) for h in numbered] == list(range(1, 9))
    assert headings[0] == "# bayescal interchange formats (the contract)"
    own = headings.index("# bayescal's own files and extensions")
    assert own > headings.index(numbered[-1])
    assert all(re.match(r"## E\d+\. ", h) for h in headings[own + 1:] if h.startswith("## "))


def test_every_section_of_the_shared_contract_is_on_the_page_verbatim():
    contract = _shared_contract()
    if contract is None:
        pytest.skip("../shared/" + OUTSIDE_NAME + " absent (a fresh clone): nothing to compare with")
    page = _normalised(PAGE.read_text(encoding="utf-8"))
    pos = 0
    for section in _sections(contract.read_text(encoding="utf-8")):
        s = _normalised(section)
        at = page.find(s, pos)
        assert at >= 0, f"not on docs/formats.md word for word (or out of order): {section.splitlines()[0]!r}"
        pos = at + len(s)
