"""Relative recordings (CSV): measured differences between pairs of poses, read strictly.

Layout (docs/redundant.md, "Relative recording"): one header row, then one
row per relative measurement, in measurement order.

| column | meaning |
|---|---|
| ``q1_from`` ... ``qN_from`` | commanded actuator positions of the first pose, mm |
| ``q1_to`` ... ``qN_to`` | commanded actuator positions of the second pose, mm |
| ``dx``, ``dy``, ``dz`` | measured tool displacement from the first to the second pose, base frame, mm |
| ``drx``, ``dry``, ``drz`` | measured change of orientation (small rotation about the base axes), rad |
| anything else | an auxiliary channel (for example ``line``, ``xd_to``), numbers only |

At least one of the six measured columns must be present; the columns that
are present are the components the instrument read.  Empty cells,
non-numbers, duplicate or unpaired actuator columns are errors naming the
file, line and column.
"""

from __future__ import annotations

import csv
import io
import os
import re
from dataclasses import dataclass, field
from pathlib import Path

from numpy.typing import NDArray

from ..errors import RecordingError
from ..io.recording import check_q_limits, parse_table, read_csv_rows
from ..io.answers import write_text_atomic

__all__ = ["RelativeRecording", "COMPONENTS", "read_relative_recording", "write_relative_recording", "relative_to_csv"]

#: Measured components a relative recording may hold, in this order.
COMPONENTS = ("dx", "dy", "dz", "drx", "dry", "drz")
_Q = re.compile(r"^q([1-9][0-9]*)_(from|to)$")


@dataclass(frozen=True)
class RelativeRecording:
    """Relative measurements between pose pairs.

    Attributes
    ----------
    q_from, q_to : ndarray, shape (n_pairs, m)
        Commanded actuator positions, mm.
    components : tuple of str
        Measured components (a subset of :data:`COMPONENTS`, in that order).
    values : ndarray, shape (n_pairs, n_components)
        mm or rad.
    aux : dict of str to ndarray
    path : str
    """

    q_from: NDArray
    q_to: NDArray
    components: tuple[str, ...]
    values: NDArray
    aux: dict[str, NDArray] = field(default_factory=dict)
    path: str = "<memory>"

    @property
    def n_pairs(self) -> int:
        return self.q_from.shape[0]

    @property
    def n_actuators(self) -> int:
        return self.q_from.shape[1]

    def check_machine(self, n_actuators: int, q_limits: NDArray | None) -> None:
        """Raise RecordingError if the actuator count or ``q_limits`` do not fit the machine."""
        if self.n_actuators != n_actuators:
            raise RecordingError(self.path, 1, None, f"{self.n_actuators} actuators per pose but the machine has {n_actuators}")
        if q_limits is None:
            return
        for tag, q in (("from", self.q_from), ("to", self.q_to)):
            check_q_limits(self.path, q, q_limits, suffix=f"_{tag}")


def read_relative_recording(path: str | os.PathLike, *, text: str | None = None) -> RelativeRecording:
    """Read a relative recording CSV strictly (see the module docstring).

    Raises
    ------
    RecordingError
        Naming the file, the line (header = line 1) and the column.
    """
    path = str(path)
    header, seen, data_rows = read_csv_rows(path, text, "a relative recording (CSV)")
    nums = {"from": set(), "to": set()}
    for h in header:
        if mt := _Q.match(h):
            nums[mt.group(2)].add(int(mt.group(1)))
    if not nums["from"] and not nums["to"]:
        raise RecordingError(path, 1, None, "no actuator columns; expected q1_from, ..., qN_from and q1_to, ..., qN_to")
    m = max(nums["from"] | nums["to"])
    for tag in ("from", "to"):
        missing = sorted(set(range(1, m + 1)) - nums[tag])
        if missing:
            raise RecordingError(path, 1, f"q{missing[0]}_{tag}", f"missing actuator column; expected q1_{tag} .. q{m}_{tag}")
    comps = tuple(c for c in COMPONENTS if c in seen)
    if not comps:
        raise RecordingError(path, 1, None, f"no measured column; expected at least one of {', '.join(COMPONENTS)}")
    if not data_rows:
        raise RecordingError(path, 2, None, "no data rows; expected one row per relative measurement")
    data = parse_table(path, header, data_rows)
    col = lambda names: data[:, [seen[c] for c in names]]  # noqa: E731
    qf = col([f"q{k}_from" for k in range(1, m + 1)])
    qt = col([f"q{k}_to" for k in range(1, m + 1)])
    known = set(comps) | {f"q{k}_{t}" for k in range(1, m + 1) for t in ("from", "to")}
    aux = {h: data[:, seen[h]].copy() for h in header if h not in known}
    return RelativeRecording(q_from=qf, q_to=qt, components=comps, values=col(comps), aux=aux, path=path)


def relative_to_csv(rec: RelativeRecording, *, precision: int = 12) -> str:
    """CSV text of a relative recording."""
    m = rec.n_actuators
    cols = [(f"q{k + 1}_from", rec.q_from[:, k]) for k in range(m)] + [(f"q{k + 1}_to", rec.q_to[:, k]) for k in range(m)]
    cols += [(c, rec.values[:, j]) for j, c in enumerate(rec.components)] + list(rec.aux.items())
    out = io.StringIO()
    w = csv.writer(out, lineterminator="\n")
    w.writerow([c for c, _ in cols])
    fmt = f"{{:.{precision}g}}"
    for i in range(rec.n_pairs):
        w.writerow([fmt.format(float(v[i])) for _, v in cols])
    return out.getvalue()


def write_relative_recording(path: str | os.PathLike, rec: RelativeRecording, *, precision: int = 12) -> Path:
    """Write a relative recording CSV atomically."""
    return write_text_atomic(path, relative_to_csv(rec, precision=precision))
