"""Recordings of measured poses (CSV, docs/formats.md section 2), read strictly."""

from __future__ import annotations

import csv
import io
import math
import os
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np
from numpy.typing import NDArray

from ..errors import RecordingError
from .answers import write_text_atomic

__all__ = ["Recording", "read_recording", "write_recording", "recording_to_csv"]

_Q = re.compile(r"^q([1-9][0-9]*)$")
# docs/formats.md (the contract's preamble): "millimetres for lengths, radians for angles, unless a column name says
# otherwise (_deg, _um)".  A measured quantity's column may carry its unit as a suffix;
# it is converted on reading.  Other names stay auxiliary channels, read as they are.
# docs/formats.md section 4 adds _m and _mrad, and the per-pose noise columns sigma_position (mm)
# and sigma_angle (rad), which take the same suffixes.
_UNIT_COLUMN = re.compile(r"^(q[1-9][0-9]*|x|y|z|rx|ry|rz|nx|ny|nz|sigma_position|sigma_angle)_(um|mm|m|deg|rad|mrad)$")
_LENGTH_UNITS = {"mm": 1.0, "um": 1e-3, "m": 1e3}
_ANGLE_UNITS = {"rad": 1.0, "deg": math.pi / 180.0, "mrad": 1e-3}
_SIGMA = ("sigma_position", "sigma_angle")
_POS = ("x", "y", "z")
_ROT = ("rx", "ry", "rz")
_AXIS = ("nx", "ny", "nz")
AXIS_NORM_TOL = 1e-3


@dataclass(frozen=True)
class Recording:
    """Measured poses in measurement order.

    Attributes
    ----------
    q : ndarray, shape (n_poses, n_actuators)
        Commanded actuator positions, mm (prismatic) or rad (revolute).
    position : ndarray, shape (n_poses, 3)
        Measured tool point, base frame, mm.
    rotvec : ndarray, shape (n_poses, 3) or None
        Measured platform orientation (rotation vector, rad), 6-DOF only.
    axis : ndarray, shape (n_poses, 3) or None
        Measured unit tool axis, 5-DOF only.
    aux : dict of str to ndarray, shape (n_poses,)
        Auxiliary channels in file order.
    path : str
        Where it was read from (for messages), or ``"<memory>"``.
    q_columns : tuple of str
        The actuator columns' names as in the file (``q1``, ``q2_um``, ...),
        for messages; empty for recordings made in memory.
    q_units : tuple of str
        Per actuator, the unit a suffixed column declared (``"mm"`` for
        ``_mm``/``_um``, ``"rad"`` for ``_rad``/``_deg``; ``q`` holds the
        converted values) or ``""`` for a plain ``q<i>``; empty for
        recordings made in memory.
    sigma_position, sigma_angle : ndarray, shape (n_poses,) or None
        Per-pose one-sigma noise (mm, rad) from the optional columns of the
        same names (docs/formats.md section 4); None when absent.
    declared_units : dict of str to str
        The unit suffix each measured column carried (``{"x": "m"}``); a
        quantity without suffix is absent.  Used to judge unsuffixed columns
        whose numbers look like another unit.
    station : tuple of str or None
        The optional ``station`` column (docs/formats.md section 8): which set-up
        of the instrument took each row (any label); None when absent.
    role : tuple of str or None
        The optional ``role`` column: ``"fit"`` (used to identify) or
        ``"check"`` (held out: only predicted and scored); None when absent
        (every row ``fit``).
    line_numbers : ndarray of int, shape (n_poses,), optional
        CSV line of every row (header = line 1) when the recording is a
        subset of a file's rows; None: lines 2, 3, ... in order.
    """

    q: NDArray
    position: NDArray
    rotvec: NDArray | None = None
    axis: NDArray | None = None
    aux: dict[str, NDArray] = field(default_factory=dict)
    path: str = "<memory>"
    q_columns: tuple[str, ...] = ()
    q_units: tuple[str, ...] = ()
    # docs/formats.md section 4: per-pose noise and the units the columns declared
    sigma_position: NDArray | None = None
    sigma_angle: NDArray | None = None
    declared_units: dict = field(default_factory=dict)
    station: tuple[str, ...] | None = None
    role: tuple[str, ...] | None = None
    line_numbers: NDArray | None = None

    @property
    def n_poses(self) -> int:
        return self.q.shape[0]

    @property
    def n_actuators(self) -> int:
        return self.q.shape[1]

    @property
    def dof(self) -> int:
        """6 (position + orientation), 5 (position + tool axis) or 3 (position only)."""
        if self.rotvec is not None:
            return 6
        if self.axis is not None:
            return 5
        return 3

    def subset(self, idx) -> "Recording":
        """The poses ``idx`` (an index array or boolean mask), order kept."""
        idx = np.asarray(idx)
        return Recording(
            q=self.q[idx],
            position=self.position[idx],
            rotvec=None if self.rotvec is None else self.rotvec[idx],
            axis=None if self.axis is None else self.axis[idx],
            aux={k: v[idx] for k, v in self.aux.items()},
            path=self.path,
            q_columns=self.q_columns,
            q_units=self.q_units,
            sigma_position=None if self.sigma_position is None else self.sigma_position[idx],
            sigma_angle=None if self.sigma_angle is None else self.sigma_angle[idx],
            declared_units=self.declared_units,
            station=None if self.station is None else tuple(np.asarray(self.station, dtype=object)[idx].tolist()),
            role=None if self.role is None else tuple(np.asarray(self.role, dtype=object)[idx].tolist()),
            line_numbers=self.lines[idx],
        )

    @property
    def lines(self) -> NDArray:
        """CSV line of every row (header = line 1), shape (n_poses,)."""
        if self.line_numbers is None:
            return np.arange(2, self.n_poses + 2)
        return np.asarray(self.line_numbers, dtype=int)

    @property
    def is_check(self) -> NDArray:
        """Which rows are held out (``role = check``), shape (n_poses,) bool."""
        if self.role is None:
            return np.zeros(self.n_poses, dtype=bool)
        return np.array([r == "check" for r in self.role], dtype=bool)

    @property
    def stations(self) -> tuple[str, ...]:
        """The station labels in order of first appearance (one unnamed station when there is no column)."""
        if self.station is None:
            return ("",)
        return tuple(dict.fromkeys(self.station))

    @property
    def station_index(self) -> NDArray:
        """Index into :attr:`stations` of every row, shape (n_poses,) int."""
        if self.station is None:
            return np.zeros(self.n_poses, dtype=int)
        pos = {s: i for i, s in enumerate(self.stations)}
        return np.array([pos[s] for s in self.station], dtype=int)

    @property
    def frame_fit_poses(self) -> int:
        """Fewest ``fit`` rows that align an instrument frame: 3 points, or 2 poses with orientations."""
        return 3 if self.dof == 3 else 2

    def check_machine(
        self,
        n_actuators: int,
        q_limits: NDArray | None,
        machine_path: str = "",
        actuator_units: tuple[str, ...] | None = None,
    ) -> None:
        """Raise RecordingError if the actuator count, units or ``q_limits`` do not fit.

        ``actuator_units`` (``"mm"`` prismatic, ``"rad"`` revolute, per
        actuator) is checked against the units suffixed columns declared.
        """
        if self.n_actuators != n_actuators:
            raise RecordingError(
                self.path, 1, None,
                f"{self.n_actuators} actuator columns (q1..q{self.n_actuators}) but the machine "
                f"{machine_path} has {n_actuators} actuators; expected q1..q{n_actuators}",
            )
        if actuator_units is not None:
            for i, (have, want) in enumerate(zip(self.q_units, actuator_units)):
                if have and have != want:
                    kind = {"mm": "a length (mm, um)", "rad": "an angle (rad, deg)"}
                    raise RecordingError(
                        self.path, 1, self.q_columns[i],
                        f"{kind[have]}, but actuator q{i + 1} of the machine {machine_path} is "
                        f"{'prismatic' if want == 'mm' else 'revolute'}; expected {kind[want]}",
                    )
        if q_limits is None:
            return
        check_q_limits(self.path, self.q, q_limits, machine_path=machine_path, names=self.q_columns or None)


def check_q_limits(
    path: str, q: NDArray, q_limits: NDArray, *, suffix: str = "", machine_path: str = "",
    names: tuple[str, ...] | None = None,
) -> None:
    """Raise RecordingError naming line and column ``q<i><suffix>`` for the first value outside ``q_limits``.

    A relative tolerance of 1e-9 of the stroke lets values written at the
    limits with rounding pass.  ``names`` are the columns as the file names
    them (default ``q<i><suffix>``); values are in the machine's units.
    """
    lo, hi = q_limits[:, 0], q_limits[:, 1]
    span = np.maximum(hi - lo, 1.0)
    bad = (q < lo - 1e-9 * span) | (q > hi + 1e-9 * span)
    if bad.any():
        r, c = map(int, np.argwhere(bad)[0])
        raise RecordingError(
            path, r + 2, names[c] if names else f"q{c + 1}{suffix}",
            f"value {float(q[r, c])!r} outside q_limits [{float(lo[c])!r}, {float(hi[c])!r}] "
            f"of the machine file{' ' + machine_path if machine_path else ''}",
        )


# A decimal number as CSV files write it (ASCII digits, optional sign, point and exponent).
# Python's float() also takes "1_000" and non-ASCII digits; a typo "1_5" must not read as 15.
_NUMBER = re.compile(r"[+-]?(?:[0-9]+(?:\.[0-9]*)?|\.[0-9]+)(?:[eE][+-]?[0-9]+)?")


def parse_number(text: str, path: str, line: int, col: str) -> float:
    """One CSV cell as a finite float; RecordingError naming line and column otherwise."""
    s = text.strip()
    if s == "":
        raise RecordingError(path, line, col, "empty cell; expected a number")
    try:
        v = float(s)
    except ValueError:
        raise RecordingError(path, line, col, f"expected a number, got {s!r}") from None
    if not math.isfinite(v):
        raise RecordingError(path, line, col, f"expected a finite number, got {s!r}")
    if not _NUMBER.fullmatch(s):
        raise RecordingError(path, line, col, f"expected a decimal number such as 12.5 or -1.25e-3, got {s!r}")
    return v


#: Rows between two progress lines while a large CSV is parsed (bayescal.progress).
PROGRESS_ROWS = 100_000


def parse_table(path: str, header: list[str], rows: list[list[str]]) -> np.ndarray:
    """The data rows (file lines 2, 3, ...) as floats, shape (len(rows), len(header)).

    Every row must have one cell per header column and every cell must be a
    number (:func:`parse_number`); RecordingError naming line and column otherwise.
    """
    from ..progress import report

    data = np.empty((len(rows), len(header)))
    for i, row in enumerate(rows):
        line = i + 2
        if i and i % PROGRESS_ROWS == 0:  # about 2 s per 100,000 rows of a recording
            report(lambda: f"reading {path}: row {i:,} of {len(rows):,}")
        if len(row) != len(header):
            raise RecordingError(path, line, None, f"{len(row)} cells, expected {len(header)} (one per header column)")
        for j, cell in enumerate(row):
            data[i, j] = parse_number(cell, path, line, header[j])
    return data


def read_csv_rows(path: str, text: str | None, what: str) -> tuple[list[str], dict[str, int], list[list[str]]]:
    """Read a CSV strictly up to the header: every reader of bayescal's CSV files shares this.

    Returns the stripped header, the column index by name, and the data rows
    (trailing blank lines dropped).  Raises RecordingError for a missing or
    unreadable file, an empty file, empty or duplicate column names.
    """
    if text is None:
        # a regular file within the size limit, or standard input read once (bayescal.io.safe_paths)
        from .safe_paths import MAX_CSV_BYTES, read_input_text

        text = read_input_text(path, what, limit=MAX_CSV_BYTES, error=lambda msg: RecordingError(path, None, None, msg))
    if text.startswith("\ufeff"):  # a byte-order mark, as some spreadsheet programs write
        text = text[1:]
    if (nul := text.find("\x00")) >= 0:
        # invisible in a message (a header cell 'rz\0' would be named 'rz'): a binary or UTF-16 file, or a damaged one
        # the line ends csv reads (\n, \r\n, a lone \r) before it: str.splitlines also splits at \f, \v, \x1c ...
        before = text[:nul]
        line = before.count("\n") + before.count("\r") - before.count("\r\n") + 1
        raise RecordingError(path, max(line, 1), None, f"a NUL byte (character {nul + 1}); expected {what} as text")
    # newline="": line ends \n, \r\n and a lone \r all end a row
    reader = csv.reader(io.StringIO(text, newline=""))
    rows: list[list[str]] = []
    try:
        for row in reader:
            rows.append(row)
            if reader.line_num != len(rows):
                # a quoted cell holding a line break: line numbers in messages would go wrong
                raise RecordingError(path, len(rows), None, "a quoted cell spans more than one line; expected one row per line")
    except csv.Error as exc:
        raise RecordingError(path, reader.line_num, None, f"not readable as CSV ({exc})") from None
    blank = lambda r: all(c.strip() == "" for c in r)  # noqa: E731
    while rows and blank(rows[-1]):
        rows.pop()
    if not rows:
        raise RecordingError(path, 1, None, "empty file; expected a header row")
    for i, row in enumerate(rows):
        # docs/formats.md section 2: one header row, then one row per pose; nothing else between them
        first = row[0].strip() if row else ""
        what = "the header row" if i == 0 else "one row per measured pose"
        if first.startswith("#"):
            raise RecordingError(path, i + 1, None, f"a comment line; comments are not part of the CSV format (docs/formats.md section 2), expected {what}")
        if blank(row):
            raise RecordingError(path, i + 1, None, f"a blank line; expected {what} (blank lines only at the end)")
    header = [h.strip() for h in rows[0]]
    if len(header) == 1 and (sep := next((c for c in ";\t|" if c in header[0]), None)):
        raise RecordingError(
            path, 1, None, f"one column named {header[0]!r}: separated by {sep!r}; expected comma-separated columns"
        )
    seen: dict[str, int] = {}
    for j, h in enumerate(header):
        if h == "":
            raise RecordingError(path, 1, None, f"column {j + 1} has an empty name")
        if h in seen:
            raise RecordingError(path, 1, h, f"duplicate column (columns {seen[h] + 1} and {j + 1})")
        seen[h] = j
    return header, seen, rows[1:]


def read_recording(path: str | os.PathLike, *, text: str | None = None,
                   check_size: Callable[[int, int], None] | None = None) -> Recording:
    """Read a recording CSV strictly.

    Parameters
    ----------
    path : path-like
        The CSV file (used for messages only if ``text`` is given).
    text : str, optional
        The file's content, to parse from memory.
    check_size : callable, optional
        Called with the number of data rows and the measured components per
        row (6, 5 or 3) once the header is checked, before any cell is
        parsed: a caller's size limit (the memory a fit of that many rows
        takes, :func:`bayescal.instrument.prepare.fit_size_check`) ends a
        large file at once instead of after parsing it.

    Returns
    -------
    Recording

    Raises
    ------
    RecordingError
        For empty cells, non-numbers, non-unit tool axes, duplicate or
        incomplete columns, and ragged rows, naming line and column.
    """
    path = str(path)
    if check_size is not None:
        text = _early_size_check(path, text, check_size)
    header, seen, data_rows = read_csv_rows(path, text, "a recording (CSV)")
    header, seen, data_rows, labels = split_label_columns(path, header, seen, data_rows)
    seen, scale, q_unit = _unit_columns(path, header, seen)
    qnums = _pose_columns(path, seen)
    if not data_rows:
        raise RecordingError(path, 2, None, "no data rows; expected one row per measured pose")
    if check_size is not None:
        check_size(len(data_rows), 6 if _ROT[0] in seen else 5 if _AXIS[0] in seen else 3)
    data = parse_table(path, header, data_rows)
    data *= scale[None, :]
    col = lambda names: data[:, [seen[c] for c in names]]  # noqa: E731
    q = col([f"q{k}" for k in qnums])
    rotvec = col(_ROT) if _ROT[0] in seen else None
    axis = None
    if _AXIS[0] in seen:
        axis = col(_AXIS)
        norms = np.linalg.norm(axis, axis=1)
        bad = np.flatnonzero(np.abs(norms - 1.0) > AXIS_NORM_TOL)
        if bad.size:
            raise RecordingError(
                path, int(bad[0]) + 2, "nx",
                f"tool axis (nx, ny, nz) has norm {norms[bad[0]]:.6g}; expected a unit vector (within {AXIS_NORM_TOL})",
            )
        axis = axis / norms[:, None]
    known = set(_POS + _ROT + _AXIS + _SIGMA) | {f"q{k}" for k in qnums}
    aux = {h: data[:, seen[h]].copy() for h in seen if h not in known}
    check_channels(path, aux, labels.get("station"))
    sig = {name: _sigma_column(path, header, seen, data, name) for name in _SIGMA}
    declared = {m.group(1): m.group(2) for h in header if (m := _UNIT_COLUMN.match(h))}
    return Recording(
        q=q, position=col(_POS), rotvec=rotvec, axis=axis, aux=aux, path=path,
        q_columns=tuple(header[seen[f"q{k}"]] for k in qnums), q_units=tuple(q_unit.get(f"q{k}", "") for k in qnums),
        sigma_position=sig["sigma_position"], sigma_angle=sig["sigma_angle"], declared_units=declared,
        station=labels.get("station"), role=labels.get("role"),
    )


def near_reserved_columns(rec: Recording) -> list[str]:
    """Messages for auxiliary channels whose name is a near miss of a reserved column (``sigma_postion``).

    Any other name is an auxiliary channel (docs/formats.md section 2), so a misspelt ``sigma_position`` or
    ``station`` would be read silently as a channel and its meaning lost: :func:`bayescal.load` and the commands
    say so (a warning, not a refusal: a channel may be named so on purpose).
    """
    import difflib

    reserved = _POS + _ROT + _AXIS + _SIGMA + ("station", "role") + tuple(_MEANING)
    out = []
    for name in (n for n in rec.aux if n not in reserved):  # a channel of known meaning is read as such
        close = difflib.get_close_matches(name, [r for r in reserved if len(r) >= 4], n=1, cutoff=0.85)
        if close and len(name) >= 4:
            out.append(f"{rec.path}: column {name!r} is read as an auxiliary channel; did you mean the reserved "
                       f"column {close[0]!r}? (docs/formats.md section 2)")
    return out


#: What the channels with a lower bound hold, for messages.
_MEANING = {"payload_kg": "a payload mass in kg", "temp_C": "a temperature in degC", "time_s": "an elapsed time in s"}


def check_channels(path: str, aux: dict, station=None, lines=None) -> None:
    """Refuse auxiliary channels of known meaning whose values cannot be (docs/formats.md sections 2 and E5).

    A channel of :data:`bayescal.limits.AUX_LOWER_BOUNDS` below its bound
    (a negative ``payload_kg`` or ``time_s``, a ``temp_C`` below absolute
    zero) or above its :data:`~bayescal.limits.AUX_UPPER_BOUNDS` bound (a
    ``payload_kg`` of 1e300), and a ``time_s`` that goes backwards down the rows of a station:
    rows are in the order they were measured (section 2), so the elapsed
    time cannot fall.  RecordingError naming the line and column.

    Parameters
    ----------
    path : str
    aux : dict of str to ndarray, shape (n,)
    station : sequence of str, optional
        Each row's station: time is checked within each (another session may start its own clock).
    lines : array_like of int, optional
        The CSV line of each row (default: 2, 3, ...).
    """
    from ..limits import AUX_LOWER_BOUNDS, AUX_UPPER_BOUNDS

    n = len(next(iter(aux.values()))) if aux else 0
    lines = np.arange(2, n + 2) if lines is None else np.asarray(lines, dtype=int)
    for name, low in AUX_LOWER_BOUNDS.items():
        v = aux.get(name)
        if v is not None and (bad := np.flatnonzero(np.asarray(v) < low)).size:
            i = int(bad[0])
            raise RecordingError(path, int(lines[i]), name, f"{v[i]:g} is below {low:g}; expected {_MEANING[name]} "
                                 f">= {low:g}")
    for name, high in AUX_UPPER_BOUNDS.items():
        v = aux.get(name)
        if v is not None and (bad := np.flatnonzero(np.asarray(v) > high)).size:
            i = int(bad[0])
            raise RecordingError(path, int(lines[i]), name, f"{v[i]:g} is above {high:g}; expected {_MEANING[name]} "
                                 f"from {AUX_LOWER_BOUNDS[name]:g} to {high:g}")
    t = aux.get("time_s")
    if t is None:
        return
    groups = [np.arange(n)] if station is None else [np.flatnonzero(np.asarray(station) == s) for s in dict.fromkeys(station)]
    for idx in groups:
        drop = np.flatnonzero(np.diff(np.asarray(t)[idx]) < 0)
        if drop.size:
            i, prev = int(idx[drop[0] + 1]), int(idx[drop[0]])
            where = "" if station is None else f" of station {station[i]!r}"
            raise RecordingError(path, int(lines[i]), "time_s", f"time goes backwards: {t[i]:g} s after {t[prev]:g} s "
                                 f"on line {int(lines[prev])}; expected the rows{where} in the order they were measured "
                                 "(docs/formats.md section 2), time_s never decreasing")


def _pose_columns(path: str, seen: dict[str, int]) -> list[int]:
    """The actuator numbers ``1..N`` of the header; RecordingError for gaps and missing or incomplete pose columns."""
    qnums = sorted(int(m.group(1)) for h in seen if (m := _Q.match(h)))
    if not qnums:
        if "measure" in seen and "a_q1" in seen:
            # predict (and anything else that reads poses only) was told "no actuator columns" about a Klipper recording
            raise RecordingError(path, 1, None, "a constraint recording (measure, a_q1, ...: distances, heights, "
                                 "ballbar readings; docs/formats.md section 6); expected a recording of measured poses "
                                 "(q1, q2, ..., x, y, z), the only kind this command reads")
        raise RecordingError(path, 1, None, "no actuator columns; expected q1, q2, ..." + _case_hint(seen, "q1"))
    if qnums != list(range(1, len(qnums) + 1)):
        missing = sorted(set(range(1, max(qnums) + 1)) - set(qnums))
        raise RecordingError(path, 1, None, f"actuator columns must be q1..qN without gaps; missing q{missing[0]}")
    for group, label in ((_POS, "position"), (_ROT, "rotation vector"), (_AXIS, "tool axis")):
        present = [c for c in group if c in seen]
        if group is _POS and len(present) != 3:
            missing = [c for c in group if c not in seen]
            raise RecordingError(
                path, 1, missing[0], "missing measured position column; expected x, y, z" + _case_hint(seen, missing[0])
            )
        if 0 < len(present) < 3:
            missing = [c for c in group if c not in seen]
            raise RecordingError(path, 1, missing[0], f"incomplete {label}: expected all of {', '.join(group)}")
    if _ROT[0] in seen and _AXIS[0] in seen:
        raise RecordingError(
            path, 1, "nx", "both a rotation vector (rx, ry, rz) and a tool axis (nx, ny, nz); expected one of them"
        )
    return qnums


def _early_size_check(path: str, text: str | None, check_size: Callable[[int, int], None]) -> str:
    """``check_size`` from the line count and the header line, before the text is split into cells; the text.

    Splitting a million rows into cells takes seconds and about ten times the
    file's size in memory; the count of lines (trailing blank lines left out)
    and the measured components the header names are known at once.  The
    reader checks again with the exact count once the header is checked.
    """
    if text is None:
        from .safe_paths import MAX_CSV_BYTES, read_input_text

        text = read_input_text(path, "a recording (CSV)", limit=MAX_CSV_BYTES,
                               error=lambda msg: RecordingError(path, None, None, msg))
    end = len(text)
    while end and text[end - 1].isspace():
        end -= 1
    n_rows = text.count("\n", 0, end) + text.count("\r", 0, end) - text.count("\r\n", 0, end)
    first = text[: min(i for i in (text.find("\n"), text.find("\r"), len(text)) if i >= 0)]
    names = {(m.group(1) if (m := _UNIT_COLUMN.match(c.strip())) else c.strip()) for c in first.split(",")}
    dof = 6 if set(_ROT) <= names else 5 if set(_AXIS) <= names else 3
    if n_rows > 0:
        check_size(n_rows, dof)
    return text


#: Columns of labels, not numbers (docs/formats.md section 8): which instrument set-up took a row, and its role.
LABEL_COLUMNS = ("station", "role")
#: The values of ``role``.
ROLES = ("fit", "check")


def split_label_columns(path: str, header: list[str], seen: dict[str, int], rows: list[list[str]]):
    """Take the ``station`` and ``role`` label columns out of a CSV table before its numbers are parsed.

    Returns the remaining header, column index, data rows and ``{name: tuple of labels}``.
    RecordingError (line and column named) for an empty label, a ``role`` other
    than ``fit`` or ``check``, or a recording whose rows are all ``check``.
    """
    present = [c for c in LABEL_COLUMNS if c in seen]
    if not present:
        return header, seen, rows, {}
    labels: dict[str, tuple[str, ...]] = {}
    for name in present:
        j = seen[name]
        vals = []
        for i, row in enumerate(rows):
            if len(row) != len(header):
                raise RecordingError(path, i + 2, None, f"{len(row)} cells, expected {len(header)} (one per header column)")
            v = row[j].strip()
            if v == "":
                raise RecordingError(path, i + 2, name, f"empty cell; expected a {name} label"
                                     + (" (fit or check)" if name == "role" else ""))
            if name == "role" and v not in ROLES:
                raise RecordingError(path, i + 2, name, f"expected 'fit' or 'check', got {v!r}")
            vals.append(v)
        labels[name] = tuple(vals)
    if "role" in labels and all(v == "check" for v in labels["role"]):
        raise RecordingError(path, None, "role", "every row is 'check'; expected at least one 'fit' row to fit with")
    drop = {seen[c] for c in present}
    keep = [j for j in range(len(header)) if j not in drop]
    header2 = [header[j] for j in keep]
    rows2 = [[row[j] for j in keep] for row in rows]
    return header2, {h: i for i, h in enumerate(header2)}, rows2, labels


def _sigma_column(path: str, header: list[str], seen: dict[str, int], data: NDArray, name: str) -> NDArray | None:
    """A per-pose noise column (mm or rad after unit conversion), strictly positive; None if absent."""
    if name not in seen:
        return None
    v = data[:, seen[name]].copy()
    bad = np.flatnonzero(~(v > 0))
    if bad.size:
        raise RecordingError(
            path, int(bad[0]) + 2, header[seen[name]],
            f"expected a positive one-sigma noise ({'mm' if name == 'sigma_position' else 'rad'}), got {float(v[bad[0]])!r}",
        )
    from ..limits import sigma_problem  # the stated range of a noise (converted to mm or rad)

    for i, x in enumerate(v):
        if (problem := sigma_problem(float(x), name.removeprefix("sigma_"))) is not None:
            raise RecordingError(path, i + 2, header[seen[name]], problem)
    return v


def _case_hint(seen: dict[str, int], name: str) -> str:
    """`` (column names are case-sensitive: found 'X')`` when a column differs from ``name`` only in case."""
    found = [h for h in seen if h.lower() == name and h != name]
    return f" (column names are case-sensitive: found {found[0]!r})" if found else ""


def _unit_columns(path: str, header: list[str], seen: dict[str, int]) -> tuple[dict[str, int], NDArray, dict[str, str]]:
    """Resolve unit-suffixed columns (``x_um``, ``rx_deg``, ``q1_um``) to their quantity.

    Returns the column index by quantity name (``x_um`` -> ``x``; other names
    unchanged), the factor converting each file column to mm or rad, and the
    unit declared per actuator column.
    """
    out: dict[str, int] = {}
    scale = np.ones(len(header))
    q_unit: dict[str, str] = {}
    for h, j in seen.items():
        name = h
        if m := _UNIT_COLUMN.match(h):
            name, unit = m.group(1), m.group(2)
            if name in _AXIS:
                raise RecordingError(path, 1, h, f"the tool axis is a unit vector without unit; expected {name}")
            if name in _POS + ("sigma_position",) and unit not in _LENGTH_UNITS:
                raise RecordingError(path, 1, h, f"{name} is a length; expected {name} (mm), {name}_mm, {name}_um or {name}_m")
            if name in _ROT + ("sigma_angle",) and unit not in _ANGLE_UNITS:
                raise RecordingError(path, 1, h, f"{name} is an angle; expected {name} (rad), {name}_rad, {name}_mrad or {name}_deg")
            scale[j] = _LENGTH_UNITS.get(unit) or _ANGLE_UNITS[unit]
            if name.startswith("q"):
                q_unit[name] = "mm" if unit in _LENGTH_UNITS else "rad"
        if name in out:
            raise RecordingError(
                path, 1, h, f"the same quantity as column {header[out[name]]!r} (columns {out[name] + 1} and {j + 1}); expected one of them"
            )
        out[name] = j
    return out, scale, q_unit


def recording_to_csv(rec: Recording, *, precision: int | None = None) -> str:
    """The CSV text of a recording (docs/formats.md section 2 column names, measurement order).

    ``precision=None`` (default) writes each number as the shortest text that
    reads back to the same float, so a written recording is read back
    exactly; an integer writes that many significant digits.
    """
    cols: list[tuple[str, NDArray]] = [(f"q{k + 1}", rec.q[:, k]) for k in range(rec.n_actuators)]
    cols += [(c, rec.position[:, k]) for k, c in enumerate(_POS)]
    if rec.rotvec is not None:
        cols += [(c, rec.rotvec[:, k]) for k, c in enumerate(_ROT)]
    if rec.axis is not None:
        cols += [(c, rec.axis[:, k]) for k, c in enumerate(_AXIS)]
    cols += [(c, v) for c, v in (("sigma_position", rec.sigma_position), ("sigma_angle", rec.sigma_angle)) if v is not None]
    cols += list(rec.aux.items())
    labels = [(c, v) for c, v in (("station", rec.station), ("role", rec.role)) if v is not None]
    out = io.StringIO()
    w = csv.writer(out, lineterminator="\n")
    w.writerow([c for c, _ in cols] + [c for c, _ in labels])
    fmt = repr if precision is None else f"{{:.{precision}g}}".format
    for i in range(rec.n_poses):
        w.writerow([fmt(float(v[i])) for _, v in cols] + [v[i] for _, v in labels])
    return out.getvalue()


def write_recording(path: str | os.PathLike, rec: Recording, *, precision: int | None = None) -> Path:
    """Write a recording CSV atomically."""
    return write_text_atomic(path, recording_to_csv(rec, precision=precision))
