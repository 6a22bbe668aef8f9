"""Strict reading of machine files (TOML, docs/formats.md section 1).

The kind-specific keys are read by each machine module through
:class:`TomlTable`, which names the file and the dotted key in every error.
"""

from __future__ import annotations

import math
import os
import tomllib
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import MachineFileError
from ..limits import file_number_problem

__all__ = ["read_toml", "parse_toml_text", "TomlTable", "format_toml_value", "toml_key", "UNIT_NORM_TOL"]

#: How far from 1 the norm of a unit vector in a machine file may be (it is then normalised).
UNIT_NORM_TOL = 1e-4


def read_toml(path: str | os.PathLike) -> "TomlTable":
    """Parse a TOML file; MachineFileError for a missing, unreadable or non-regular file, or a syntax error.

    The file must be a regular file of at most
    :data:`~bayescal.io.safe_paths.MAX_TOML_BYTES` (a folder, a named pipe or
    a device is refused before it is read; :func:`~bayescal.io.safe_paths.read_input_text`).
    """
    from .safe_paths import MAX_TOML_BYTES, read_input_text

    path = Path(path)
    # utf-8-sig: a byte-order mark (some Windows editors write one) is not part of the TOML
    text = read_input_text(path, "a machine file (TOML)", limit=MAX_TOML_BYTES,
                           error=lambda message: MachineFileError(str(path), "", message))
    return TomlTable(parse_toml_text(text, str(path)), str(path), "")


def parse_toml_text(text: str, path: str) -> dict:
    """``tomllib.loads`` with every failure a MachineFileError naming ``path``.

    Besides syntax errors: an integer of more than 4300 digits (Python's
    limit on converting text to int) and nesting deeper than the parser's
    recursion allows are refused, not raised as ValueError / RecursionError.
    """
    try:
        return tomllib.loads(text.removeprefix("\ufeff"))
    except tomllib.TOMLDecodeError as exc:
        raise MachineFileError(path, "", f"not valid TOML ({exc})") from None
    except ValueError as exc:  # "Exceeds the limit (4300 digits) for integer string conversion"
        what = "an integer of more than 4300 digits" if "digits" in str(exc) else f"a value that cannot be read ({exc})"
        raise MachineFileError(path, "", f"not a machine file: {what}") from None
    except RecursionError:
        raise MachineFileError(path, "", "not a machine file: arrays or tables nested too deeply") from None


#: Keys that belong at the top of a machine file, before any table.
_TOP_LEVEL = frozenset({"kind", "name", "assembly"})


class TomlTable:
    """A view of one TOML table that validates values and names them in errors."""

    def __init__(self, data: dict[str, Any], path: str, prefix: str):
        self.data, self.path, self.prefix = data, path, prefix

    def _key(self, key: str) -> str:
        return f"{self.prefix}.{key}" if self.prefix else key

    def error(self, key: str, expected: str) -> MachineFileError:
        return MachineFileError(self.path, self._key(key), expected)

    def has(self, key: str) -> bool:
        return key in self.data

    def keys(self):
        return self.data.keys()

    def reject_unknown(self, allowed: set[str]) -> None:
        """Raise for keys not in ``allowed`` (typos must not pass silently)."""
        for key in self.data:
            if key not in allowed:
                hint = ""
                if self.prefix and key in _TOP_LEVEL:
                    # TOML puts every key after a [table] header into that table
                    hint = f" ('{key}' is a top-level key: write it before the first [table] header)"
                raise self.error(key, f"unknown key; expected one of: {', '.join(sorted(allowed))}{hint}")

    def string(self, key: str, default: str | None = None) -> str:
        if key not in self.data:
            if default is None:
                raise self.error(key, "missing; expected a string")
            return default
        v = self.data[key]
        if not isinstance(v, str):
            raise self.error(key, f"expected a string, got {v!r}")
        return v

    def number(self, key: str, default: float | None = None, *, positive: bool = False) -> float:
        if key not in self.data:
            if default is None:
                raise self.error(key, "missing; expected a number")
            return float(default)
        v = self.data[key]
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
            raise self.error(key, f"expected a finite number, got {v!r}")
        if positive and v <= 0:
            raise self.error(key, f"expected a positive number, got {v!r}")
        self._bounded(key, [v])
        return float(v)

    def _bounded(self, key: str, values) -> None:
        """Refuse a number beyond :data:`~bayescal.limits.MAX_FILE_NUMBER` (a typo such as 1e300)."""
        for x in values:
            if (problem := file_number_problem(float(x))) is not None:
                raise self.error(key, problem)

    def vector(self, key: str, n: int = 3, *, unit: bool = False, default=None) -> np.ndarray:
        if key not in self.data:
            if default is None:
                raise self.error(key, f"missing; expected a list of {n} numbers")
            return np.asarray(default, dtype=float)
        v = self.data[key]
        if (
            not isinstance(v, list)
            or len(v) != n
            or any(isinstance(x, bool) or not isinstance(x, (int, float)) or not math.isfinite(x) for x in v)
        ):
            raise self.error(key, f"expected a list of {n} finite numbers, got {v!r}")
        self._bounded(key, v)
        arr = np.asarray(v, dtype=float)
        if unit:
            norm = float(np.linalg.norm(arr))
            # hand-written direction cosines carry 5 or 6 significant digits (0.34202, 0.93969:
            # norm 0.9999975); they are normalised.  A norm off by more is a typo, not rounding.
            if abs(norm - 1.0) > UNIT_NORM_TOL:
                raise self.error(key, f"expected a unit vector (norm 1 within {UNIT_NORM_TOL:g}), got norm {norm:.9g}")
            arr = arr / norm
        return arr

    def matrix(self, key: str, rows: int, cols: int) -> np.ndarray:
        if key not in self.data:
            raise self.error(key, f"missing; expected {rows} lists of {cols} numbers")
        v = self.data[key]
        ok = isinstance(v, list) and len(v) == rows and all(
            isinstance(r, list)
            and len(r) == cols
            and all(not isinstance(x, bool) and isinstance(x, (int, float)) and math.isfinite(x) for x in r)
            for r in v
        )
        if not ok:
            raise self.error(key, f"expected {rows} lists of {cols} finite numbers, got {v!r}")
        self._bounded(key, [x for r in v for x in r])
        return np.asarray(v, dtype=float)

    def table(self, key: str, *, required: bool = True) -> "TomlTable | None":
        if key not in self.data:
            if required:
                raise self.error(key, "missing table")
            return None
        v = self.data[key]
        if not isinstance(v, dict):
            raise self.error(key, f"expected a table [{key}], got {type(v).__name__}")
        return TomlTable(v, self.path, self._key(key))

    def array_of_tables(self, key: str, n: int | None = None) -> list["TomlTable"]:
        v = self.data.get(key)
        if not isinstance(v, list) or not v or not all(isinstance(t, dict) for t in v):
            raise self.error(key, f"missing or malformed; expected one or more [[{key}]] tables")
        if n is not None and len(v) != n:
            raise self.error(key, f"expected {n} [[{key}]] tables, got {len(v)}")
        return [TomlTable(t, self.path, f"{self._key(key)}[{i + 1}]") for i, t in enumerate(v)]


_TOML_ESCAPES = {'"': '\\"', "\\": "\\\\", "\b": "\\b", "\t": "\\t", "\n": "\\n", "\f": "\\f", "\r": "\\r"}


def toml_key(key: str) -> str:
    """A TOML key: bare where TOML allows (letters, digits, ``_``, ``-``), else a quoted basic string.

    A dotted name such as ``chain2.link_length`` is quoted: bare, TOML would read it as a nested table.
    """
    return key if key and all(c.isascii() and (c.isalnum() or c in "_-") for c in key) else _toml_string(key)


def _toml_string(s: str) -> str:
    """A TOML basic string: quotes, backslashes and control characters escaped (TOML 1.0)."""
    out = []
    for ch in s:
        if ch in _TOML_ESCAPES:
            out.append(_TOML_ESCAPES[ch])
        elif ord(ch) < 0x20 or ord(ch) == 0x7F:
            out.append(f"\\u{ord(ch):04X}")
        else:
            out.append(ch)
    return '"' + "".join(out) + '"'


def format_toml_value(v: Any) -> str:
    """Format a number, string, vector or matrix as TOML with full float precision."""
    if isinstance(v, str):
        return _toml_string(v)
    if isinstance(v, (bool, np.bool_)):
        return "true" if v else "false"
    if isinstance(v, (int, np.integer)):
        return str(int(v))
    if isinstance(v, (float, np.floating)):
        return repr(float(v))
    arr = np.asarray(v)
    if arr.ndim >= 1:
        return "[" + ", ".join(format_toml_value(x) for x in (arr.tolist() if arr.ndim == 1 else list(arr))) + "]"
    return format_toml_value(arr.item())
