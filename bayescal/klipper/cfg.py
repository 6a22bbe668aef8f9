"""Klipper printer configuration files (``printer.cfg``), read as Klipper reads them.

Klipper parses its config with Python's ``configparser`` (sections may
repeat and merge, a later value overrides an earlier one, a value may
continue over indented lines, ``;`` starts a comment at the start of a line
or after a space), after its own passes: ``#`` comments and ``[include ...]``
files (:mod:`bayescal.klipper.source`) and the ``SAVE_CONFIG`` block at
the end of the file (:mod:`bayescal.klipper.autosave`).  This module does
the same with the same parser and settings and returns the merged sections,
remembering where every key was set (file and line) so that an error about
a value names them.  It checks no values beyond their form as numbers
(:mod:`bayescal.klipper` does, naming section and key).
"""

from __future__ import annotations

import configparser
import math
import os
from dataclasses import dataclass, field

from .autosave import AUTOSAVE_HEADER, split_autosave, without_overridden
from .source import Chunk, KlipperConfigError, config_source, normalize_text, read_main_text

__all__ = ["KlipperConfig", "Origin", "read_klipper_config", "parse_klipper_text", "KlipperConfigError", "AUTOSAVE_HEADER"]

_DEFAULT = "DEFAULT"  # configparser's section whose keys every section has


@dataclass(frozen=True)
class Origin:
    """Where a key was set: file, 1-based line, and whether in the SAVE_CONFIG block."""

    path: str
    line: int
    in_block: bool = False


def _shown(text: str) -> str:
    """A value for an error message: short, so that an error never dumps a file."""
    return repr(text if len(text) <= 40 else text[:40] + "...")


@dataclass(frozen=True)
class KlipperConfig:
    """Merged sections of a Klipper config, as Klipper sees them (SAVE_CONFIG block applied).

    Attributes
    ----------
    sections : dict of str to dict of str to str
        Section name (as written, e.g. ``stepper_a``, ``bed_mesh default``) to
        option (lower case) to value (text; a multi-line value joined by ``\\n``).
    saved : dict of str to dict of str to str
        The SAVE_CONFIG block alone (empty if the file has none or Klipper ignores it).
    path : str
        The main file.
    origin : dict of (str, str) to Origin
        Where each ``(section, key)`` of ``sections`` was set.
    files : tuple of str
        The files read, main file first.
    missing_includes : tuple of MissingInclude
        Includes without wildcards that name no file (skipped; Klipper would refuse them).
    autosave_note : str or None
        Why Klipper ignores this file's ``#*#`` lines, if it does.
    """

    sections: dict
    saved: dict
    path: str
    origin: dict = field(default_factory=dict)
    files: tuple = ()
    missing_includes: tuple = ()
    autosave_note: str | None = None

    def has(self, section: str, key: str | None = None) -> bool:
        if section not in self.sections:
            return False
        return key is None or key in self.sections[section]

    def where(self, section: str, key: str) -> Origin | None:
        """The file and line that set ``[section] key`` (None if unknown or unset)."""
        return self.origin.get((section, key)) or self.origin.get((_DEFAULT, key))

    def error(self, section: str, key: str, expected: str) -> KlipperConfigError:
        """An error about ``[section] key``, placed at the line that set it when known."""
        o = self.where(section, key) if key else None
        if o is None:
            return KlipperConfigError(self.path, section, key, expected)
        return KlipperConfigError(o.path, section, key, expected, line=o.line, in_block=o.in_block)

    def error_near(self, section: str, key: str, near: str, expected: str) -> KlipperConfigError:
        """An error about the unset ``[section] key``, placed at the line of the key ``near`` it."""
        o = self.where(section, near)
        if o is None:
            return KlipperConfigError(self.path, section, key, expected)
        return KlipperConfigError(o.path, section, key, expected, line=o.line, in_block=o.in_block)

    def sources_note(self) -> str:
        """What else may hold a missing key: includes that were not found, a SAVE_CONFIG block Klipper ignores."""
        files = "" if len(self.files) <= 1 else f" or the {len(self.files) - 1} files it includes"
        notes = [f"not set in {self.path}{files}"]
        for m in self.missing_includes[:2]:
            notes.append(f"it may be in {m.target}, named by [include] at {m.path} line {m.line} but not found")
        if len(self.missing_includes) > 2:
            notes.append(f"{len(self.missing_includes) - 2} more includes not found")
        if self.autosave_note:
            notes.append(self.autosave_note)
        return "; ".join(notes)

    def notes(self) -> list[str]:
        """What the reader did that Klipper would not: includes skipped, a SAVE_CONFIG block Klipper ignores."""
        out = [f"[include] at {m.path} line {m.line}: {m.target} not found; skipped (Klipper would refuse to start "
               "without it)" for m in self.missing_includes]
        if self.autosave_note:
            out.append(f"SAVE_CONFIG block not read: {self.autosave_note}")
        return out

    def get(self, section: str, key: str, default: str | None = None) -> str:
        if section not in self.sections:
            if default is not None:
                return default
            raise self.error(section, "", f"missing section; expected a [{section}] section with '{key}' ({self.sources_note()})")
        sec = self.sections[section]
        if key not in sec or sec[key] is None:
            if default is not None:
                return default
            raise self.error(section, key, f"missing; expected a value ({self.sources_note()})")
        return sec[key]

    def _number(self, section: str, key: str, text: str, what: str = "a number") -> float:
        try:
            v = float(text)
        except ValueError:
            raise self.error(section, key, f"expected {what}, got {_shown(text)}") from None
        if not math.isfinite(v):
            raise self.error(section, key, f"expected a finite number, got {_shown(text)}")
        return v

    def _bounded(self, section: str, key: str, v: float, text: str, lo, hi, above, why: str = "") -> float:
        why = f" ({why})" if why else ""
        if above is not None and v <= above:
            raise self.error(section, key, f"expected a number above {above:g}{why}, got {_shown(text)}")
        if (lo is not None and v < lo) or (hi is not None and v > hi):
            span = f"from {lo:g} to {hi:g}" if lo is not None and hi is not None else (
                f"at least {lo:g}" if lo is not None else f"at most {hi:g}")
            raise self.error(section, key, f"expected a number {span}{why}, got {_shown(text)}")
        return v

    def getfloat(self, section: str, key: str, default: float | None = None, *, lo: float | None = None,
                 hi: float | None = None, above: float | None = None, why: str = "") -> float:
        """A finite number, checked against ``lo <= v <= hi`` and ``v > above`` (``why``: the bound's reason, for the
        message); ``default`` when the key is unset."""
        if default is not None and not self.has(section, key):
            return float(default)
        text = self.get(section, key)
        return self._bounded(section, key, self._number(section, key, text), text, lo, hi, above, why)

    def getfloats(self, section: str, key: str, count: int, *, lo: float | None = None, hi: float | None = None) -> list[float]:
        """``count`` comma-separated finite numbers within ``lo .. hi``."""
        text = self.get(section, key)
        parts = [p.strip() for p in text.split(",")]
        what = f"{count} comma-separated numbers"
        if len(parts) != count:
            raise self.error(section, key, f"expected {what}, got {len(parts)} in {_shown(text)}")
        vals = [self._number(section, key, p, what) for p in parts]
        for v in vals:
            self._bounded(section, key, v, text, lo, hi, None)
        return vals

    def merged(self, other: "KlipperConfig") -> "KlipperConfig":
        """This config with ``other``'s values on top (as a block pasted above the SAVE_CONFIG block would be)."""
        out = {k: dict(v) for k, v in self.sections.items()}
        for sec, opts in other.sections.items():
            out.setdefault(sec, {}).update(opts)
        return KlipperConfig(sections=out, saved=self.saved, path=self.path, origin={**self.origin, **other.origin},
                             files=self.files, missing_includes=self.missing_includes, autosave_note=self.autosave_note)


# ---------------------------------------------------------------- parsing
def _parser() -> configparser.RawConfigParser:
    # Klipper's own settings: repeated sections merge, later values override, inline comments after ';' or '#'
    return configparser.RawConfigParser(strict=False, inline_comment_prefixes=(";", "#"))


def _read_chunk(parser: configparser.RawConfigParser, chunk: Chunk, in_block: bool) -> None:
    """Parse one chunk into ``parser``; errors name the file and line, never the line's text."""
    def fail(lineno: int, expected: str):
        return KlipperConfigError(chunk.path, "", "", expected, line=chunk.first_line + lineno - 1, in_block=in_block)

    try:
        parser.read_string("\n".join(chunk.lines), source=chunk.path)
    except configparser.MissingSectionHeaderError as exc:
        raise fail(exc.lineno, "a key before any [section] header (after an [include] line, keys need their "
                               "[section] again); not a Klipper config") from None
    except configparser.ParsingError as exc:
        more = f" ({len(exc.errors) - 1} more such lines)" if len(exc.errors) > 1 else ""
        raise fail(exc.errors[0][0], "not a Klipper config line: expected '[section]', 'key: value' or 'key = value', "
                                     f"or an indented line continuing the value above{more}") from None
    except configparser.Error as exc:
        raise KlipperConfigError(chunk.path, "", "", f"not readable as a Klipper config ({type(exc).__name__})",
                                 in_block=in_block) from None


def _uncommented(line: str) -> str:
    """``line`` without a comment, by configparser's rule (``#``/``;`` at the start, or after whitespace)."""
    if line.strip().startswith(("#", ";")):
        return ""
    cut = len(line)
    for prefix in ("#", ";"):
        i = line.find(prefix)
        while i > 0 and not line[i - 1].isspace():
            i = line.find(prefix, i + 1)
        if i >= 0:
            cut = min(cut, i)
    return line[:cut]


def _origins(chunk: Chunk, in_block: bool) -> dict:
    """Where each key of a chunk is set: configparser's own line logic, for error messages."""
    out: dict = {}
    section, in_value, indent_level = None, False, 0
    for k, line in enumerate(chunk.lines):
        value = _uncommented(line).strip()
        if not value:
            continue
        mo = configparser.RawConfigParser.NONSPACECRE.search(line)
        indent = mo.start() if mo else 0
        if section is not None and in_value and indent > indent_level:
            continue  # a continuation line
        indent_level = indent
        if mo := configparser.RawConfigParser.SECTCRE.match(value):
            section, in_value = mo.group("header"), False
            continue
        mo = configparser.RawConfigParser.OPTCRE.match(value)
        if section is not None and mo and mo.group("option").strip():
            in_value = True
            out[(section, mo.group("option").rstrip().lower())] = Origin(chunk.path, chunk.first_line + k, in_block)
    return out


def _sections(parser: configparser.RawConfigParser) -> dict:
    return {sec: dict(parser.items(sec)) for sec in parser.sections()}


def _config(text: str, path: str, folder, missing_includes: str = "skip") -> KlipperConfig:
    split = split_autosave(text, path)
    source = config_source(split.regular, path, folder, missing_includes=missing_includes)
    parser, origin = _parser(), {}
    for chunk in source.chunks:
        _read_chunk(parser, chunk, False)
        origin.update(_origins(chunk, False))
    saved = {}
    if split.block is not None:
        alone = _parser()
        _read_chunk(alone, split.block, True)  # the block's own errors, with its lines
        saved = _sections(alone)
        kept, dropped = without_overridden(split.block, parser.has_option)
        _read_chunk(parser, kept, True)
        origin.update({k: o for k, o in _origins(kept, True).items() if k not in dropped})
    return KlipperConfig(sections=_sections(parser), saved=saved, path=path, origin=origin, files=source.files,
                         missing_includes=source.missing, autosave_note=split.ignored)


def parse_klipper_text(text: str, path: str = "<memory>", *, base_dir: str | os.PathLike | None = None,
                       missing_includes: str = "skip") -> KlipperConfig:
    """Parse Klipper config text; ``base_dir`` resolves ``[include ...]`` (None: includes not followed).

    ``missing_includes`` as for :func:`read_klipper_config` (with ``base_dir`` None every include is
    left unread and listed in ``missing_includes``).

    Raises
    ------
    KlipperConfigError
        For text ``configparser`` rejects, or an include that cannot be read, naming file and line.
    """
    return _config(normalize_text(text, path), path, base_dir, missing_includes)


def read_klipper_config(path: str | os.PathLike, *, missing_includes: str = "skip") -> KlipperConfig:
    """Read a Klipper ``printer.cfg`` with its includes and SAVE_CONFIG block, as Klipper does.

    Parameters
    ----------
    path : str or PathLike
    missing_includes : {"error", "skip"}
        An ``[include FILE]`` without wildcards that names no file: ``"skip"`` (the default) reads the
        config without it, lists it in ``missing_includes`` and in :meth:`KlipperConfig.notes`, and names it
        where a key the calibration needs is then missing (a published config's ``fluidd.cfg`` or
        ``mainsail.cfg`` seldom travels with it, and holds no calibration); ``"error"`` refuses it as
        Klipper does, naming the including file, its line and the path. A glob that matches nothing is
        accepted either way, as by Klipper.

    Raises
    ------
    KlipperConfigError
        For a file that is missing, not a regular file, not UTF-8 text, or
        not a config ``configparser`` accepts; for a missing include (with ``"error"``),
        an include cycle, or an include tree beyond bayescal's limits
        (:mod:`bayescal.klipper.source`); naming the file and line.
    """
    path = os.fspath(path)
    return _config(read_main_text(path), path, os.path.dirname(path), missing_includes)
