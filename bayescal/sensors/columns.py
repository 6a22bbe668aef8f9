"""The body-sensor columns of a recording: ``accel.<body>.x``, ``.y``, ``.z`` (docs/formats.md section 8).

Only the direction of a reading is used, in any consistent unit.  Errors
name the recording, the line and the column (exit code 2 from the command
line).
"""

from __future__ import annotations

import re

import numpy as np
from numpy.typing import NDArray

from ..errors import RecordingError

__all__ = ["SENSOR_COLUMN", "sensor_readings", "is_body_measurement"]

#: ``accel.<body>.<axis>``: a body name may itself contain dots (a URDF link name)
SENSOR_COLUMN = re.compile(r"accel\.(?P<body>.+)\.(?P<axis>[xyz])")
#: The same in any case (``Accel.base.X``): a sensor spelled otherwise, refused rather than read as a channel.
_ANY_CASE = re.compile(SENSOR_COLUMN.pattern, re.IGNORECASE)


def is_body_measurement(column: str) -> bool:
    """Whether ``column`` is a reading of a sensor on a body other than the base: a measurement (section 8), not a
    condition the machine runs under (a base sensor's gravity is one), so never an input that explains residuals."""
    m = SENSOR_COLUMN.fullmatch(column)
    return m is not None and m["body"] != "base"


def _near_miss(col: str, bodies: tuple[str, ...]) -> str | None:
    """The spelling a column that is a sensor's in another case should have (None: not such a column).

    ``accel`` and the axis are lower case; the body keeps its case when the
    machine has it, else takes the machine's body of that name in any case.
    """
    m = _ANY_CASE.fullmatch(col)
    if m is None or SENSOR_COLUMN.fullmatch(col):
        return None
    body = m["body"]
    if body not in bodies:
        body = next((b for b in bodies if b.lower() == body.lower()), body)
    return f"accel.{body}.{m['axis'].lower()}"


def sensor_readings(aux: dict, path: str, lines, bodies: tuple[str, ...]) -> dict[str, NDArray]:
    """Unit readings per body from a recording's auxiliary channels, file order kept.

    Parameters
    ----------
    aux : dict of str to ndarray, shape (n,)
        The recording's channels.
    path : str
        The recording, for messages.
    lines : array_like of int, shape (n,)
        The CSV line of every row (header = line 1).
    bodies : tuple of str
        The bodies the machine exposes (:attr:`Machine.sensor_bodies`).

    Returns
    -------
    dict of str to ndarray, shape (n, 3)
        Unit vectors (the readings normalised), per body.

    Raises
    ------
    RecordingError
        A column spelled like a sensor's in another case (``accel.base.X``:
        naming it and the spelling expected), a body the machine does not
        have (naming the column and the bodies it has), a body without all three of ``x``, ``y``, ``z``, or a
        reading of zero length (naming the line).
    """
    found: dict[str, dict[str, str]] = {}
    for col in aux:
        m = SENSOR_COLUMN.fullmatch(col)
        if m:
            found.setdefault(m["body"], {})[m["axis"]] = col
        elif (spelled := _near_miss(col, bodies)) is not None:
            # read as a channel, a sensor typed 'accel.base.X' would silently be no sensor at all
            raise RecordingError(path, 1, col, f"a body sensor's column in the wrong case; expected {spelled!r} "
                                 "(lower-case 'accel' and axis x, y, z; docs/formats.md section 8), or another name "
                                 "for an auxiliary channel")
    out = {}
    for body, axes in found.items():
        first = next(iter(axes.values()))
        if body not in bodies:
            kind = "" if len(bodies) > 1 else " (this machine kind exposes no body but the base)"
            raise RecordingError(path, None, first, f"no body {body!r} on this machine{kind}; expected accel.<body>.x/y/z "
                                 f"with <body> one of {', '.join(bodies)}")
        missing = [f"accel.{body}.{a}" for a in "xyz" if a not in axes]
        if missing:
            raise RecordingError(path, None, first, f"column(s) {', '.join(missing)} missing; a body sensor needs all three "
                                 "of x, y, z")
        v = np.column_stack([np.asarray(aux[f"accel.{body}.{a}"], dtype=float) for a in "xyz"])
        norm = np.linalg.norm(v, axis=1)
        bad = np.flatnonzero(~(np.isfinite(norm) & (norm > 0)))
        if bad.size:
            i = int(bad[0])
            raise RecordingError(path, int(np.asarray(lines)[i]), f"accel.{body}.x",
                                 f"the sensor on {body!r} reads {v[i].tolist()}; expected a finite vector of non-zero length")
        out[body] = v / norm[:, None]
    return out
