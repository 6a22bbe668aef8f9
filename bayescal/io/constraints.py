"""Constraint recordings: distances, heights and ballbar readings (CSV, docs/formats.md section 6).

One row per measurement:

* ``measure``: ``distance`` (between the tool points of poses a and b),
  ``height`` (z of the tool point of pose a, base frame) or ``ballbar``
  (distance from the tool point of pose a to a fixed pivot that is fitted;
  one pivot per recording, or one per value of the optional ``pivot`` column);
* ``a_q1`` ... ``a_qN``: actuator positions of pose a;
* ``b_q1`` ... ``b_qN``: of pose b (``distance`` only, empty otherwise);
* ``value``: the measured distance or height, mm;
* optional ``pivot`` (an id of letters, digits, ``_`` or ``-``) and
  ``sigma_position`` (mm, the one-sigma noise of ``value``);
* anything else: numeric auxiliary channels.
"""

from __future__ import annotations

import csv
import io
import os
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from ..errors import RecordingError
from ..limits import MAX_FILE_NUMBER, sigma_problem
from .answers import write_text_atomic
from .recording import check_q_limits, parse_number, read_csv_rows

__all__ = [
    "ConstraintRecording", "read_constraints", "write_constraints", "constraints_to_csv",
    "is_constraint_recording", "MEASURES",
]

#: The measurement types of docs/formats.md section 6.
MEASURES = ("distance", "height", "ballbar")
_AQ = re.compile(r"^a_q([1-9][0-9]*)$")
_BQ = re.compile(r"^b_q([1-9][0-9]*)$")
_PIVOT_ID = re.compile(r"^[A-Za-z0-9_-]+$")
# docs/formats.md (the contract's preamble): millimetres "unless a column name says otherwise (_deg, _um)", and section 4's
# suffixes (x_m, x_um): the measured length and its noise may carry a length unit.
_LENGTH_COLUMN = re.compile(r"^(value|sigma_position)_(um|mm|m|deg|rad|mrad)$")
_LENGTH_UNITS = {"mm": 1.0, "um": 1e-3, "m": 1e3}
#: The pivot id ballbar rows get when the recording has no ``pivot`` column.
DEFAULT_PIVOT = "1"


@dataclass(frozen=True)
class ConstraintRecording:
    """Measured relations between poses, in measurement order.

    Attributes
    ----------
    measure : tuple of str, length n
        ``distance``, ``height`` or ``ballbar`` per row.
    qa : ndarray, shape (n, N)
        Actuator positions of pose a (mm or rad).
    qb : ndarray, shape (n, N)
        Of pose b; NaN on rows that are not distances.
    value : ndarray, shape (n,)
        Measured distance or height, mm.
    pivot : tuple of str, length n
        Pivot id of ballbar rows, ``""`` on other rows.
    sigma : ndarray, shape (n,) or None
        Per-row one-sigma noise of ``value`` (mm), from ``sigma_position``.
    aux : dict of str to ndarray
        Auxiliary channels.
    path : str
    """

    measure: tuple[str, ...]
    qa: NDArray
    qb: NDArray
    value: NDArray
    pivot: tuple[str, ...] = ()
    sigma: NDArray | None = None
    aux: dict[str, NDArray] = field(default_factory=dict)
    path: str = "<memory>"

    def __post_init__(self) -> None:
        if not self.pivot:
            object.__setattr__(self, "pivot", tuple(DEFAULT_PIVOT if m == "ballbar" else "" for m in self.measure))

    @property
    def n_rows(self) -> int:
        return len(self.measure)

    n_poses = n_rows

    @property
    def n_actuators(self) -> int:
        return self.qa.shape[1]

    @property
    def pivot_ids(self) -> tuple[str, ...]:
        """Distinct pivot ids in order of first appearance."""
        return tuple(dict.fromkeys(p for p in self.pivot if p))

    def subset(self, idx) -> "ConstraintRecording":
        idx = np.asarray(idx)
        rows = np.arange(self.n_rows)[idx]
        return ConstraintRecording(
            measure=tuple(self.measure[i] for i in rows), qa=self.qa[idx], qb=self.qb[idx], value=self.value[idx],
            pivot=tuple(self.pivot[i] for i in rows), sigma=None if self.sigma is None else self.sigma[idx],
            aux={k: v[idx] for k, v in self.aux.items()}, path=self.path,
        )

    def check_machine(self, n_actuators: int, q_limits: NDArray | None, machine_path: str = "") -> None:
        """Raise RecordingError if the actuator count or ``q_limits`` do not fit the machine."""
        if self.n_actuators != n_actuators:
            raise RecordingError(
                self.path, 1, None,
                f"{self.n_actuators} actuator columns per pose (a_q1..a_q{self.n_actuators}) but the machine "
                f"{machine_path} has {n_actuators} actuators; expected a_q1..a_q{n_actuators}",
            )
        if q_limits is None:
            return
        check_q_limits(self.path, self.qa, q_limits, machine_path=machine_path, names=tuple(f"a_q{k + 1}" for k in range(n_actuators)))
        dist = np.array([m == "distance" for m in self.measure])
        if dist.any():
            qb = np.where(dist[:, None], self.qb, q_limits[:, 0][None, :])
            check_q_limits(self.path, qb, q_limits, machine_path=machine_path, names=tuple(f"b_q{k + 1}" for k in range(n_actuators)))


def is_constraint_recording(path: str | os.PathLike, *, text: str | None = None) -> bool:
    """True when the CSV's header has a ``measure`` column (a constraint recording, not a pose recording).

    The one place that tells the two kinds of recording apart, for a file on
    disk and for a file's content alike (the header is parsed as CSV, as the
    readers parse it, so a quoted ``"measure"`` counts).

    Parameters
    ----------
    path : path-like
        The CSV file (not read when ``text`` is given).
    text : str, optional
        The file's content.

    Returns
    -------
    bool
        False also for a file that cannot be read as CSV: the pose-recording
        reader then reports what is wrong with it (file, line, column).
    """
    from ..errors import BayescalError
    from .safe_paths import MAX_CSV_BYTES, read_input_text

    try:
        if text is None:
            # the reader's own checks (a regular file within the size limit; standard input read once)
            text = read_input_text(path, "a recording (CSV)", limit=MAX_CSV_BYTES)
        # as read_csv_rows: one byte-order mark dropped, any line end
        body = text[1:] if text.startswith("\ufeff") else text
        header = next(csv.reader(io.StringIO(body, newline="")), [])
    except (BayescalError, csv.Error):
        return False
    return "measure" in [h.strip() for h in header]


def _actuator_columns(path: str, seen: dict[str, int], pattern: re.Pattern, prefix: str) -> list[int]:
    nums = sorted(int(m.group(1)) for h in seen if (m := pattern.match(h)))
    if nums and nums != list(range(1, len(nums) + 1)):
        missing = sorted(set(range(1, max(nums) + 1)) - set(nums))
        raise RecordingError(path, 1, None, f"actuator columns must be {prefix}1..{prefix}N without gaps; missing {prefix}{missing[0]}")
    return nums


def _length_columns(
    path: str, header: list[str], seen: dict[str, int]
) -> tuple[list[str], dict[str, int], dict[str, float], dict[str, str]]:
    """Resolve ``value_um``, ``sigma_position_m``, ... to ``value`` / ``sigma_position``.

    Returns the header and column index with the quantity names, the factor to mm
    per quantity, and the file's column name per quantity (for messages).
    """
    orig, header, seen = header, list(header), dict(seen)
    scale = {"value": 1.0, "sigma_position": 1.0}
    file_col = {"value": "value", "sigma_position": "sigma_position"}
    for h, j in list(seen.items()):
        if not (m := _LENGTH_COLUMN.match(h)):
            continue
        name, unit = m.groups()
        if unit not in _LENGTH_UNITS:
            raise RecordingError(path, 1, h, f"{name} is a length; expected {name} (mm), {name}_mm, {name}_um or {name}_m")
        if name in seen:
            other = seen[name]
            raise RecordingError(
                path, 1, h, f"the same quantity as column {orig[other]!r} (columns {other + 1} and {j + 1}); expected one of them"
            )
        del seen[h]
        seen[name], header[j] = j, name
        scale[name], file_col[name] = _LENGTH_UNITS[unit], h
    return header, seen, scale, file_col


def read_constraints(path: str | os.PathLike, *, text: str | None = None) -> ConstraintRecording:
    """Read a constraint recording CSV strictly (docs/formats.md section 6).

    Parameters
    ----------
    path : path-like
        The CSV file (for messages only if ``text`` is given).
    text : str, optional
        The file's content.

    Returns
    -------
    ConstraintRecording

    Raises
    ------
    RecordingError
        Naming the file, line and column: unknown ``measure``, missing or
        non-numeric cells, ``b_q`` cells on rows that are not distances,
        non-positive distances, sigmas or ballbar readings, bad pivot ids.
    """
    path = str(path)
    header, seen, rows = read_csv_rows(path, text, "a constraint recording (CSV)")
    header, seen, unit_scale, file_col = _length_columns(path, header, seen)
    a_nums, b_nums, aux_cols = _constraint_columns(path, header, seen, rows)
    N = len(a_nums)
    n = len(rows)
    measure: list[str] = []
    qa = np.empty((n, N))
    qb = np.full((n, N), np.nan)
    value = np.empty(n)
    pivot: list[str] = []
    sigma = np.empty(n) if "sigma_position" in seen else None
    aux = {h: np.empty(n) for h in aux_cols}
    for i, row in enumerate(rows):
        line = i + 2
        if len(row) != len(header):
            raise RecordingError(path, line, None, f"{len(row)} cells, expected {len(header)} (one per header column)")
        cell = lambda c: row[seen[c]].strip()  # noqa: E731
        m = cell("measure")
        if m not in MEASURES:
            raise RecordingError(path, line, "measure", f"expected one of {', '.join(MEASURES)}, got {m!r}")
        measure.append(m)
        _read_poses(cell, path, line, m, N, b_nums, qa[i], qb[i])
        value[i] = _read_value(cell, path, line, m, file_col["value"], unit_scale["value"])
        if m == "distance" and np.array_equal(qa[i], qb[i]):
            # a pose's distance to itself is 0 whatever the geometry: the row carries no information, only an outlier
            raise RecordingError(path, line, "b_q1", f"a distance between pose a and the same pose b (q = {qa[i].tolist()}); "
                                 "expected two different poses")
        pivot.append(_read_pivot(cell, "pivot" in seen, path, line, m))
        if sigma is not None:
            sigma[i] = _read_sigma(cell, path, line, file_col["sigma_position"], unit_scale["sigma_position"])
        for h in aux_cols:
            aux[h][i] = parse_number(cell(h), path, line, h)
    return ConstraintRecording(
        measure=tuple(measure), qa=qa, qb=qb, value=value, pivot=tuple(pivot), sigma=sigma, aux=aux, path=path
    )


def _constraint_columns(path: str, header, seen: dict, rows) -> tuple[list[int], list[int], list[str]]:
    """The ``a_q`` and ``b_q`` numbers and the auxiliary columns of a constraint recording, its header checked."""
    for col in ("measure", "value"):
        if col not in seen:
            raise RecordingError(path, 1, col, "missing column; a constraint recording has measure, a_q1..a_qN, [b_q1..b_qN], value")
    a_nums = _actuator_columns(path, seen, _AQ, "a_q")
    if not a_nums:
        raise RecordingError(path, 1, None, "no actuator columns; expected a_q1, a_q2, ...")
    b_nums = _actuator_columns(path, seen, _BQ, "b_q")
    if b_nums and b_nums != a_nums:
        raise RecordingError(path, 1, None, f"b_q1..b_q{len(b_nums)} but a_q1..a_q{len(a_nums)}; expected as many b as a columns")
    if not rows:
        raise RecordingError(path, 2, None, "no data rows; expected one row per measurement")
    known = {"measure", "value", "pivot", "sigma_position"} | {f"a_q{k}" for k in a_nums} | {f"b_q{k}" for k in b_nums}
    aux_cols = [h for h in header if h not in known]
    for label in ("station", "role"):
        if label in aux_cols:
            # read as a numeric channel, the first label was "expected a number, got 'check'"
            raise RecordingError(path, 1, label, f"a {label} column is read in pose recordings only (docs/formats.md "
                                 "section 8); a constraint recording's other columns are numeric auxiliary channels")
    return a_nums, b_nums, aux_cols


def _read_poses(cell, path: str, line: int, m: str, N: int, b_nums, qa_i: NDArray, qb_i: NDArray) -> None:
    """A row's pose a into ``qa_i`` and, for a distance, pose b into ``qb_i`` (other rows: empty ``b_q`` cells)."""
    for k in range(N):
        qa_i[k] = parse_number(cell(f"a_q{k + 1}"), path, line, f"a_q{k + 1}")
    if m == "distance":
        if not b_nums:
            raise RecordingError(path, 1, "b_q1", f"line {line} is a distance, but the file has no b_q1..b_q{N} columns")
        for k in range(N):
            qb_i[k] = parse_number(cell(f"b_q{k + 1}"), path, line, f"b_q{k + 1}")
    else:
        for k in b_nums:
            if cell(f"b_q{k}") != "":
                raise RecordingError(path, line, f"b_q{k}", f"a {m} row has no pose b; expected an empty cell")


def _read_value(cell, path: str, line: int, m: str, col: str, scale: float) -> float:
    """A row's measured value in mm (positive but for a height, within the file limit)."""
    v = parse_number(cell("value"), path, line, col)
    if m != "height" and v <= 0:
        raise RecordingError(path, line, col, f"a {m} must be positive, got {v!r}")
    v = v * scale
    if abs(v) > MAX_FILE_NUMBER:  # 1e300 ran into a noise estimate of inf
        raise RecordingError(path, line, col, f"{v:g} mm; expected a length within +-{MAX_FILE_NUMBER:g} mm")
    return v


def _read_pivot(cell, has_column: bool, path: str, line: int, m: str) -> str:
    """A ballbar row's pivot id (the default pivot without the column); "" for the other rows."""
    pid = cell("pivot") if has_column else (DEFAULT_PIVOT if m == "ballbar" else "")
    if m == "ballbar":
        if not _PIVOT_ID.match(pid):
            raise RecordingError(path, line, "pivot", f"expected a pivot id of letters, digits, _ or -, got {pid!r}")
    elif pid != "":
        raise RecordingError(path, line, "pivot", f"a {m} row has no pivot; expected an empty cell")
    return pid if m == "ballbar" else ""


def _read_sigma(cell, path: str, line: int, col: str, scale: float) -> float:
    """A row's stated one-sigma noise in mm (positive, within :func:`bayescal.limits.sigma_problem`'s range)."""
    s = parse_number(cell("sigma_position"), path, line, col)
    if s <= 0:
        raise RecordingError(path, line, col, f"expected a positive one-sigma noise, got {s!r}")
    s = s * scale
    if (problem := sigma_problem(float(s), "position")) is not None:  # bayescal.limits
        raise RecordingError(path, line, col, problem)
    return s


def constraints_to_csv(rec: ConstraintRecording) -> str:
    """The CSV text of a constraint recording (shortest round-tripping numbers)."""
    N = rec.n_actuators
    has_b = any(m == "distance" for m in rec.measure)
    has_pivot = len(rec.pivot_ids) > 1 or any(p not in ("", DEFAULT_PIVOT) for p in rec.pivot)
    head = ["measure"] + [f"a_q{k + 1}" for k in range(N)] + ([f"b_q{k + 1}" for k in range(N)] if has_b else []) + ["value"]
    head += (["pivot"] if has_pivot else []) + (["sigma_position"] if rec.sigma is not None else []) + list(rec.aux)
    out = io.StringIO()
    w = csv.writer(out, lineterminator="\n")
    w.writerow(head)
    for i, m in enumerate(rec.measure):
        row = [m] + [repr(float(x)) for x in rec.qa[i]]
        if has_b:
            row += [repr(float(x)) for x in rec.qb[i]] if m == "distance" else [""] * N
        row.append(repr(float(rec.value[i])))
        if has_pivot:
            row.append(rec.pivot[i])
        if rec.sigma is not None:
            row.append(repr(float(rec.sigma[i])))
        row += [repr(float(v[i])) for v in rec.aux.values()]
        w.writerow(row)
    return out.getvalue()


def write_constraints(path: str | os.PathLike, rec: ConstraintRecording) -> Path:
    """Write a constraint recording CSV atomically."""
    return write_text_atomic(path, constraints_to_csv(rec))
