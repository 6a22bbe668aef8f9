"""The text of a Klipper config and of the files it includes, read as Klipper reads them, within limits.

Klipper's rules (``klippy/configfile.py``, in our own words):

* a config is text (bayescal requires UTF-8, what Klipper's hosts use); line
  ends ``\\r\\n`` and ``\\r`` count as ``\\n``;
* on every line, a ``#`` and everything after it is a comment, removed before
  anything else looks at the line (``;`` comments are left to the parser);
* a line ``[include PATTERN]`` is replaced by the files matching ``PATTERN``, a
  glob relative to the folder of the file that names it (an absolute pattern
  is taken as it is), in sorted order; a pattern without wildcards must name
  a file, one with wildcards may match nothing (bayescal takes the folder's
  own name literally, wildcard characters and all);
* included files may include others; a file that includes itself, directly or
  further down, is an error;
* the text between two includes is parsed as one piece, into the same parser,
  in order: a value set later overrides one set earlier.

An include without wildcards that names no file is skipped and remembered
(a published ``printer.cfg`` often names a UI include, ``fluidd.cfg`` or
``mainsail.cfg``, that does not travel with it and holds no calibration):
the reader's notes name it, and a key that is then missing is reported with
the include it may have come from.  Asked to (``missing_includes="error"``,
``bayescal klipper --missing-includes error``) it is an error, as in Klipper
(``Include file ... does not exist``), naming the including file, its line
and the missing path.

What bayescal does differently, and why:

* limits no real config reaches, so that a hostile or broken include tree
  fails at once: at most :data:`MAX_INCLUDED_FILES` included files in all,
  nested at most :data:`MAX_INCLUDE_DEPTH` deep, :data:`MAX_FILE_BYTES` per
  file and :data:`MAX_TOTAL_BYTES` in all; only regular files are read (a
  FIFO or a device such as ``/dev/zero`` is refused before it is read);
* errors name the file and line and never quote a file's lines: an include
  may point anywhere (``[include ../../etc/passwd]``).
"""

from __future__ import annotations

import configparser
import glob
import os
import stat
from dataclasses import dataclass, field

from ..errors import InputError

__all__ = [
    "KlipperConfigError", "Chunk", "MissingInclude", "ConfigSource", "read_main_text", "normalize_text", "config_source",
    "MAX_INCLUDED_FILES", "MAX_INCLUDE_DEPTH", "MAX_FILE_BYTES", "MAX_TOTAL_BYTES",
]

#: Included files read in all (a glob's every match counts, and a file included twice counts twice).
MAX_INCLUDED_FILES = 200
#: Include nesting: the main file includes level 1, which includes level 2, ...
MAX_INCLUDE_DEPTH = 12
#: Bytes per file, and for all included files together (a config with a large bed mesh is a few hundred kB).
MAX_FILE_BYTES = 4 * 1024 * 1024
MAX_TOTAL_BYTES = 16 * 1024 * 1024

_SECTION = configparser.RawConfigParser.SECTCRE
_INCLUDE = "include "


class KlipperConfigError(InputError):
    """A Klipper config that cannot be used: names the file, the line, the section and the key."""

    def __init__(self, path: str, section: str, key: str, expected: str, *, line: int | None = None,
                 in_block: bool = False):
        self.path, self.section, self.key, self.line, self.expected = str(path), section, key, line, expected
        place = self.path + (f" line {line}" if line is not None else "") + (" (SAVE_CONFIG block)" if in_block else "")
        where = (f"[{section}]" + (f" {key}" if key else "") + ": ") if section else ""
        super().__init__(f"{place}: {where}{expected}")


def _error(path: str, line: int | None, expected: str) -> KlipperConfigError:
    return KlipperConfigError(path, "", "", expected, line=line)


@dataclass(frozen=True)
class Chunk:
    """Lines parsed as one piece (between two includes), comments after ``#`` removed.

    ``first_line`` is the 1-based line of ``lines[0]`` in ``path``.
    """

    path: str
    first_line: int
    lines: tuple[str, ...]


@dataclass(frozen=True)
class MissingInclude:
    """An ``[include ...]`` without wildcards that names no file (``path`` line ``line`` names ``target``)."""

    path: str
    line: int
    target: str


@dataclass(frozen=True)
class ConfigSource:
    """The regular part of a config, as chunks in parse order, and what its includes did.

    Attributes
    ----------
    chunks : tuple of Chunk
    files : tuple of str
        Every file read, main file first, in reading order.
    missing : tuple of MissingInclude
    """

    chunks: tuple[Chunk, ...]
    files: tuple[str, ...]
    missing: tuple[MissingInclude, ...]


@dataclass
class _Walk:
    """State of one read: the budget spent, the include chain (for cycles), the results."""

    n_included: int = 0
    n_bytes: int = 0
    chain: list = field(default_factory=list)  # [real path, path, line of the include being followed]
    chunks: list = field(default_factory=list)
    files: list = field(default_factory=list)
    missing: list = field(default_factory=list)
    skip_missing: bool = False  # a missing plain include is remembered instead of refused


def _file_kind(mode: int) -> str:
    for test, name in ((stat.S_ISFIFO, "a FIFO"), (stat.S_ISCHR, "a character device"), (stat.S_ISBLK, "a block device"),
                       (stat.S_ISSOCK, "a socket")):
        if test(mode):
            return name
    return "not a regular file"


def _read_bytes(path: str, walk: _Walk) -> bytes:
    """The bytes of a regular file, within the budget; a FIFO is opened without blocking and refused."""
    flags = os.O_RDONLY | getattr(os, "O_NONBLOCK", 0) | getattr(os, "O_NOCTTY", 0)
    try:
        fd = os.open(path, flags)
    except FileNotFoundError:
        raise _error(path, None, "file not found; expected a Klipper config file") from None
    except IsADirectoryError:
        raise _error(path, None, "is a folder; expected a Klipper config file") from None
    except OSError as exc:
        raise _error(path, None, f"cannot be read ({exc.strerror or type(exc).__name__})") from None
    try:
        mode = os.fstat(fd).st_mode
        if stat.S_ISDIR(mode):
            raise _error(path, None, "is a folder; expected a Klipper config file")
        if not stat.S_ISREG(mode):
            raise _error(path, None, f"is {_file_kind(mode)}, not a regular file; expected a Klipper config file")
        limit = min(MAX_FILE_BYTES, MAX_TOTAL_BYTES - walk.n_bytes)
        parts, size = [], 0
        while block := os.read(fd, 1 << 16):
            size += len(block)
            if size > limit:
                raise _error(path, None, f"larger than {limit // 1024} kB (the limit per file is {MAX_FILE_BYTES // 2**20} MB, "
                                         f"{MAX_TOTAL_BYTES // 2**20} MB for the files a config includes); not a Klipper config")
            parts.append(block)
    except OSError as exc:
        raise _error(path, None, f"cannot be read ({exc.strerror or type(exc).__name__})") from None
    finally:
        os.close(fd)
    walk.n_bytes += size
    return b"".join(parts)


def decode_config(data: bytes, path: str) -> str:
    """UTF-8 text with ``\\n`` line ends (a leading byte-order mark dropped); errors name the line, not its text."""
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError as exc:
        line = data.count(b"\n", 0, exc.start) + 1
        raise _error(path, line, f"not UTF-8 text (byte 0x{data[exc.start]:02X}); Klipper reads its config as UTF-8 text: "
                                 "save the file as UTF-8") from None
    return normalize_text(text, path)


def _include_header(line: str) -> str | None:
    mo = _SECTION.match(line)
    header = mo.group("header") if mo else ""
    return header[len(_INCLUDE):].strip() if header.startswith(_INCLUDE) else None


def _expand(text: str, path: str, folder: str | None, walk: _Walk) -> None:
    """Split ``text`` at its include lines into chunks, reading the included files in between."""
    walk.files.append(path)
    start, buf = 1, []
    for no, raw in enumerate(text.split("\n"), start=1):
        line = raw.split("#", 1)[0]
        spec = _include_header(line)
        if spec is None:
            buf.append(line)
            continue
        walk.chunks.append(Chunk(path, start, tuple(buf)))
        start, buf = no + 1, []
        walk.chain[-1][2] = no
        _include(spec, path, no, folder, walk)
    walk.chunks.append(Chunk(path, start, tuple(buf)))


def _matches(spec: str, path: str, line: int, folder: str, walk: _Walk) -> list[str]:
    # the folder is taken literally (Klipper globs it too, so a folder named 'printer [v2]' loses its includes there)
    pattern = os.path.join(glob.escape(folder), spec)
    names = []
    for name in glob.iglob(pattern):  # lazily: a pattern matching thousands of files stops at the limit
        names.append(name)
        if walk.n_included + len(names) > MAX_INCLUDED_FILES:
            raise _error(path, line, f"[include {spec}]: more than {MAX_INCLUDED_FILES} included files in all "
                                     f"(bayescal's limit; no printer config needs more)")
    if not names and not glob.has_magic(spec):
        target = os.path.join(folder, spec)
        if not walk.skip_missing:  # Klipper: "Include file '...' does not exist"; a glob may match nothing
            raise _error(path, line, f"[include {spec}]: {target} does not exist (Klipper refuses to start without "
                                     "it); expected an existing file or a glob pattern (--missing-includes skip, "
                                     "missing_includes='skip', reads the config without it)")
        walk.missing.append(MissingInclude(path, line, target))
    return sorted(names)


def _include(spec: str, path: str, line: int, folder: str | None, walk: _Walk) -> None:
    if not spec:
        raise _error(path, line, "[include] names no file; expected [include FILE] (a path or a glob pattern)")
    if folder is None:  # text without a folder (memory): its includes cannot be resolved
        walk.missing.append(MissingInclude(path, line, spec))
        return
    if len(walk.chain) > MAX_INCLUDE_DEPTH:
        raise _error(path, line, f"[include {spec}]: includes nested more than {MAX_INCLUDE_DEPTH} deep (bayescal's limit)")
    for name in _matches(spec, path, line, folder, walk):
        walk.n_included += 1
        real = os.path.realpath(name)
        if any(real == frame[0] for frame in walk.chain):
            first = next(i for i, frame in enumerate(walk.chain) if frame[0] == real)
            steps = [f"{p} line {n} includes" for _, p, n in walk.chain[first:]]
            raise _error(path, line, f"include cycle: {' '.join(steps)} {name} again")
        try:
            text = decode_config(_read_bytes(name, walk), name)
        except KlipperConfigError as exc:
            raise KlipperConfigError(exc.path, "", "", f"{exc.expected} (named by [include] at {path} line {line})",
                                     line=exc.line) from None
        walk.chain.append([real, name, 0])
        _expand(text, name, os.path.dirname(name), walk)
        walk.chain.pop()


def read_main_text(path: str | os.PathLike) -> str:
    """The main config file's text (a regular file, within :data:`MAX_FILE_BYTES`, UTF-8), ``\\n`` line ends."""
    path = os.fspath(path)
    return decode_config(_read_bytes(path, _Walk()), path)


def normalize_text(text: str, path: str = "<memory>") -> str:
    """Text in memory checked as a file is (size, no NUL) with ``\\n`` line ends and no byte-order mark."""
    if len(text) > MAX_FILE_BYTES:
        raise _error(path, None, f"larger than {MAX_FILE_BYTES // 2**20} MB; not a Klipper config")
    if (nul := text.find("\0")) >= 0:
        raise _error(path, text.count("\n", 0, nul) + 1, "a NUL character: not a text file, not a Klipper config")
    return text.removeprefix("\ufeff").replace("\r\n", "\n").replace("\r", "\n")


def config_source(text: str, path: str, folder: str | os.PathLike | None, *,
                  missing_includes: str = "skip") -> ConfigSource:
    """The regular part ``text`` of the config ``path`` with its includes, as chunks in parse order.

    ``folder`` resolves relative includes (Klipper: the config file's folder);
    None leaves every include unread (listed in ``missing``).
    ``missing_includes``: ``"error"`` (Klipper's rule: an include without
    wildcards that names no file is refused) or ``"skip"`` (it is listed in
    ``missing``).

    Raises
    ------
    KlipperConfigError
        An include that names no file (``missing_includes="error"``), cannot
        be read, is not UTF-8 text, is not a regular file, forms a cycle, or
        exceeds a limit; naming the file and line.
    """
    if missing_includes not in ("error", "skip"):
        raise InputError(f"missing_includes: expected 'error' or 'skip', got {missing_includes!r}")
    folder = None if folder is None else os.fspath(folder)
    walk = _Walk(chain=[[os.path.realpath(path) if folder is not None else path, path, 0]],
                 skip_missing=missing_includes == "skip")
    _expand(text, path, folder, walk)
    return ConfigSource(chunks=tuple(walk.chunks), files=tuple(walk.files), missing=tuple(walk.missing))
