"""The ``SAVE_CONFIG`` block at the end of a Klipper ``printer.cfg``, found and merged as Klipper does.

Klipper's rules (``klippy/configfile.py``, in our own words):

* the block starts at the three header lines :data:`AUTOSAVE_HEADER` (after a
  line end); every line below them starts with ``#*#``, followed by a space
  unless the line is just ``#*#``; the prefix (4 characters) removed, the
  lines are a config of their own (values may continue over indented lines,
  as a saved bed mesh's ``points`` do);
* Klipper ignores the whole block (and reads the file as if it had none)
  when a line below the header does not start so, when a ``#*# `` line
  stands above the header, or when the header appears twice; bayescal reads
  the file the same way and remembers why, for its error messages;
* a key set above the block (in ``printer.cfg`` or its includes) wins over
  the same key in the block: Klipper drops the block's line and its
  continuation lines.  (The next ``SAVE_CONFIG`` then comments out the
  regular line instead, if it saves that key again.)
"""

from __future__ import annotations

import re
from collections.abc import Callable
from dataclasses import dataclass

from .source import Chunk

__all__ = ["AUTOSAVE_HEADER", "SplitConfig", "split_autosave", "without_overridden"]

#: The three lines Klipper writes above its SAVE_CONFIG block (each line ending in ``\n``).
AUTOSAVE_HEADER = (
    "#*# <---------------------- SAVE_CONFIG ---------------------->\n"
    "#*# DO NOT EDIT THIS BLOCK OR BELOW. The contents are auto-generated.\n"
    "#*#\n"
)
_MARKER = "\n" + AUTOSAVE_HEADER
_PREFIX = "#*#"
_COMMENT = re.compile(r"[#;].*$")
_NAME_END = re.compile(r"[^A-Za-z0-9_].*$")


@dataclass(frozen=True)
class SplitConfig:
    """A config's text split as Klipper splits it.

    Attributes
    ----------
    regular : str
        The text above the block (the whole text when there is no block or Klipper ignores it).
    block : Chunk or None
        The block's lines, prefix and ``#`` comments removed, numbered as in the file.
    ignored : str or None
        Why Klipper ignores the ``#*#`` lines of this file, naming the line; None when it reads them (or there are none).
    """

    regular: str
    block: Chunk | None
    ignored: str | None


def _line_of(text: str, index: int) -> int:
    return text.count("\n", 0, index) + 1


def split_autosave(text: str, path: str) -> SplitConfig:
    """Split ``text`` (``\\n`` line ends) into the regular part and the SAVE_CONFIG block."""
    pos = text.find(_MARKER)
    if pos < 0:
        stray = text.find("\n" + _PREFIX + " ")
        why = None if stray < 0 else (
            f"line {_line_of(text, stray + 1)} starts with '#*# ' but the file has no SAVE_CONFIG header as Klipper "
            "writes it (three lines), so Klipper ignores every '#*#' line")
        return SplitConfig(text, None, why)
    after = pos + len(_MARKER)
    rest = text[after:]
    first = _line_of(text, after + len(rest) - len(rest.lstrip()))
    data = rest.strip()
    if (stray := text.find("\n" + _PREFIX + " ", 0, pos)) >= 0:
        return SplitConfig(text, None, f"line {_line_of(text, stray + 1)} starts with '#*# ' above the SAVE_CONFIG header, "
                                       "so Klipper ignores the whole block")
    if (again := data.find(_MARKER)) >= 0:
        return SplitConfig(text, None, f"a second SAVE_CONFIG header at line {first + data.count(chr(10), 0, again) + 1}, "
                                       "so Klipper ignores the whole block")
    lines = data.split("\n") if data else []
    for k, line in enumerate(lines):
        if not line.startswith(_PREFIX) or (len(line) >= 4 and not line.startswith(_PREFIX + " ")):
            return SplitConfig(text, None, f"line {first + k} below the SAVE_CONFIG header does not start with '#*# ' "
                                           "(the block was edited), so Klipper ignores the whole block")
    if not lines:
        return SplitConfig(text[:pos], None, None)
    return SplitConfig(text[:pos], Chunk(path, first, tuple(line[4:].split("#", 1)[0] for line in lines)), None)


def without_overridden(block: Chunk, has_option: Callable[[str | None, str], bool]) -> tuple[Chunk, set]:
    """The block without the keys the regular config sets (blank lines keep the numbering), and those keys.

    ``has_option(section, key)`` tells whether the regular config sets the
    key (``configparser``'s own test, which also looks at ``[DEFAULT]``).
    """
    out, dropped = [], set()
    section, dup = None, False
    for line in block.lines:
        pruned = _COMMENT.sub("", line).rstrip()
        if not pruned:
            out.append(line)
        elif pruned[0].isspace():  # a continuation line goes with its key
            out.append("" if dup else line)
        elif pruned[0] == "[":
            section, dup = pruned[1:-1].strip(), False
            out.append(line)
        else:
            key = _NAME_END.sub("", pruned)
            dup = bool(key) and has_option(section, key)
            if dup:
                dropped.add((section, key.lower()))
            out.append("" if dup else line)
    return Chunk(block.path, block.first_line, tuple(out)), dropped
