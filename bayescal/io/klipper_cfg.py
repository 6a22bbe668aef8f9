"""Klipper printer configuration files (``printer.cfg``), read as Klipper reads them.

Klipper parses its config with Python's ``configparser`` (sections may
repeat and merge, ``#`` and ``;`` start comments, also inline), follows
``[include FILE]`` sections relative to the file, and reads the block that
``SAVE_CONFIG`` appends at the end (lines ``#*# ...`` after the line
``#*# <---------------------- SAVE_CONFIG ---------------------->``); the
values of that block override those of the sections above.  This module
does the same with the standard library's parser and returns the merged
sections; it does not check values (:mod:`bayescal.klipper` does, naming
section and key).
"""

from __future__ import annotations

import configparser
import glob
import os
from dataclasses import dataclass
from pathlib import Path

from ..errors import InputError

__all__ = ["KlipperConfig", "read_klipper_config", "parse_klipper_text", "KlipperConfigError", "AUTOSAVE_HEADER"]

AUTOSAVE_HEADER = "#*# <---------------------- SAVE_CONFIG ---------------------->"
_AUTOSAVE_PREFIX = "#*#"


class KlipperConfigError(InputError):
    """A Klipper config that cannot be used: names the file, the section and the key."""

    def __init__(self, path: str, section: str, key: str, expected: str):
        self.path, self.section, self.key = path, section, key
        where = (f"[{section}]" + (f" {key}" if key else "") + ": ") if section else ""
        super().__init__(f"{path}: {where}{expected}")


@dataclass(frozen=True)
class KlipperConfig:
    """Merged sections of a Klipper config (SAVE_CONFIG block applied).

    Attributes
    ----------
    sections : dict of str to dict of str to str
        Section name (as written, e.g. ``stepper_a``) to option values (text).
    saved : dict of str to dict of str to str
        The SAVE_CONFIG block alone (empty if the file has none).
    path : str
    """

    sections: dict
    saved: dict
    path: str

    def has(self, section: str, key: str | None = None) -> bool:
        if section not in self.sections:
            return False
        return key is None or key in self.sections[section]

    def error(self, section: str, key: str, expected: str) -> KlipperConfigError:
        return KlipperConfigError(self.path, section, key, expected)

    def get(self, section: str, key: str, default: str | None = None) -> str:
        if section not in self.sections:
            if default is not None:
                return default
            raise self.error(section, "", f"missing section; expected a [{section}] section with '{key}'")
        sec = self.sections[section]
        if key not in sec or sec[key] is None:
            if default is not None:
                return default
            raise self.error(section, key, "missing; expected a value")
        return sec[key]

    def getfloat(self, section: str, key: str, default: float | None = None, *, positive: bool = False) -> float:
        text = self.get(section, key, None if default is None else repr(float(default)))
        try:
            v = float(text)
        except ValueError:
            raise self.error(section, key, f"expected a number, got {text!r}") from None
        if v != v or v in (float("inf"), float("-inf")):
            raise self.error(section, key, f"expected a finite number, got {text!r}")
        if positive and v <= 0:
            raise self.error(section, key, f"expected a positive number, got {text!r}")
        return v

    def getfloats(self, section: str, key: str, count: int) -> list[float]:
        text = self.get(section, key)
        parts = [p.strip() for p in text.split(",")]
        try:
            vals = [float(p) for p in parts]
        except ValueError:
            raise self.error(section, key, f"expected {count} comma-separated numbers, got {text!r}") from None
        if len(vals) != count:
            raise self.error(section, key, f"expected {count} comma-separated numbers, got {len(vals)} in {text!r}")
        return vals

    def merged(self, other: "KlipperConfig") -> "KlipperConfig":
        """This config with ``other``'s values on top (as a pasted snippet would be)."""
        out = {k: dict(v) for k, v in self.sections.items()}
        for sec, opts in other.sections.items():
            out.setdefault(sec, {}).update(opts)
        return KlipperConfig(sections=out, saved=self.saved, path=self.path)


def _parser() -> configparser.RawConfigParser:
    # Klipper's own settings: repeated sections merge, inline comments after '#' or ';'
    p = configparser.RawConfigParser(strict=False, inline_comment_prefixes=(";", "#"))
    return p


def _split_autosave(text: str, path: str) -> tuple[str, str]:
    lines = text.splitlines()
    for i, line in enumerate(lines):
        if line.rstrip() == AUTOSAVE_HEADER:
            block = []
            for j, raw in enumerate(lines[i + 1 :], start=i + 2):
                s = raw.strip()
                if not s:
                    continue
                if not s.startswith(_AUTOSAVE_PREFIX):
                    raise KlipperConfigError(path, "SAVE_CONFIG", "", f"line {j}: expected '#*# ...' lines after the SAVE_CONFIG header, got {s[:40]!r}")
                content = s[len(_AUTOSAVE_PREFIX):].strip()
                if block or content.startswith("["):  # Klipper's header ends with a "DO NOT EDIT ..." line
                    block.append(content)
            return "\n".join(lines[:i]) + "\n", "\n".join(block) + "\n"
    return text, ""


def _sections(text: str, path: str, base_dir: Path | None, depth: int = 0) -> dict:
    p = _parser()
    try:
        p.read_string(text, source=path)
    except configparser.Error as exc:
        raise KlipperConfigError(path, "", "", f"not readable as a Klipper config ({exc.__class__.__name__}: {exc})") from None
    out: dict[str, dict[str, str]] = {}
    for sec in p.sections():
        if sec.startswith("include ") and base_dir is not None:
            if depth > 10:
                raise KlipperConfigError(path, sec, "", "includes nested more than 10 deep")
            pattern = str(base_dir / sec[len("include "):].strip())
            # Klipper refuses a missing include; only its printer geometry matters here, and a
            # published printer.cfg often names a UI include (fluidd.cfg) that is not shipped with it
            for f in sorted(glob.glob(pattern)):
                sub_text = Path(f).read_text(encoding="utf-8")
                for k, v in _sections(_split_autosave(sub_text, f)[0], f, Path(f).parent, depth + 1).items():
                    out.setdefault(k, {}).update(v)
            continue
        out.setdefault(sec, {}).update(dict(p.items(sec)))
    return out


def parse_klipper_text(text: str, path: str = "<memory>", *, base_dir: str | os.PathLike | None = None) -> KlipperConfig:
    """Parse Klipper config text; ``base_dir`` resolves ``[include ...]`` (None: includes ignored)."""
    main, block = _split_autosave(text.removeprefix("\ufeff"), path)
    sections = _sections(main, path, Path(base_dir) if base_dir is not None else None)
    saved = _sections(block, f"{path} (SAVE_CONFIG block)", None) if block else {}
    for sec, opts in saved.items():
        sections.setdefault(sec, {}).update(opts)
    return KlipperConfig(sections=sections, saved=saved, path=path)


def read_klipper_config(path: str | os.PathLike) -> KlipperConfig:
    """Read a Klipper ``printer.cfg`` (with its includes and SAVE_CONFIG block).

    Raises
    ------
    KlipperConfigError
        For an unreadable file or a config ``configparser`` rejects.
    """
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise KlipperConfigError(str(path), "", "", "file not found; expected a Klipper printer.cfg") from None
    except IsADirectoryError:
        raise KlipperConfigError(str(path), "", "", "is a folder; expected a Klipper printer.cfg") from None
    except UnicodeDecodeError as exc:
        raise KlipperConfigError(str(path), "", "", f"not a UTF-8 text file ({exc})") from None
    return parse_klipper_text(text, str(path), base_dir=path.parent)
